"""The command line and the package's global configuration: argument checks, dtype both ways,
corrupt files in --out, atomic writes, and that importing the package leaves JAX's x64 flag alone."""

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPRODUCE_KW, fast_compile_env

from gpguided_jax import cli, config, runtime
from gpguided_jax import reproduce as R
from gpguided_jax import train as T

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _python(code: str, **env):
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, **env}, cwd=ROOT)
    return proc


def test_lapack_runs_one_thread_unless_the_user_says_otherwise():
    """One OpenBLAS thread; a user's own setting, or an already-loaded LAPACK, is left alone."""
    assert runtime.lapack_threads({}, lapack_loaded=False) == "1"
    assert runtime.lapack_threads({"PATH": "/bin"}, lapack_loaded=False) == "1"
    assert runtime.lapack_threads({}, lapack_loaded=True) is None
    for name in runtime.LAPACK_THREAD_VARIABLES:
        assert runtime.lapack_threads({name: "2"}, lapack_loaded=False) is None


def test_openblas_runs_one_thread_under_the_cli():
    """End to end: after `runtime.set_cpu_devices(2)` the OpenBLAS that JAX's LAPACK calls use (SciPy's)
    runs one thread (with one per core it oversubscribes the cores). It fails if a module that the
    command line imports first imports scipy.stats, which loads OpenBLAS before the variable is set."""
    code = (  # what `cli.main` imports before a command sets the devices, then the devices
        "from gpguided_jax import cli; cli.build_parser()\n"
        "from gpguided_jax import bench, reproduce, runtime, sweep; runtime.set_cpu_devices(2)\n"
        "import jax, jax.numpy as jnp; jax.jit(jnp.linalg.cholesky)(jnp.eye(3)).block_until_ready()\n"
        "import ctypes, glob, os, scipy\n"
        "libs = glob.glob(os.path.join(os.path.dirname(scipy.__file__) + '.libs', '*openblas*'))\n"
        "print(ctypes.CDLL(libs[0]).scipy_openblas_get_num_threads() if libs else 'none')\n"
        "print(len(jax.devices()), runtime.available_cores())")
    env = {k: v for k, v in os.environ.items()
           if k not in runtime.LAPACK_THREAD_VARIABLES and k != "XLA_FLAGS"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    threads, devices_cores = proc.stdout.split("\n")[:2]
    if threads == "none":
        pytest.skip("SciPy does not bundle OpenBLAS here")
    assert int(devices_cores.split()[0]) == 2
    assert int(threads) == 1


@pytest.mark.parametrize(
    "args,message",
    [
        (["--chunk-size", "0"], "--chunk-size: must be >= 1, got 0"),
        (["--devices", "0"], "--devices: must be >= 1, got 0"),
        (["--seeds", "0"], "--seeds: must be >= 1, got 0"),
        (["--seed-start", "-3"], "--seed-start: must be >= 0, got -3"),
        (["--chunk-size", "two"], "--chunk-size: expected a positive integer, got 'two'"),
        (["--dtype", "float16"], "--dtype: invalid choice"),
    ],
)
def test_bad_arguments_are_refused_in_one_line(args, message, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["reproduce", "--preset", "tiny", *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize("args,message", [
    (["--exploration", "ou", "--methods", "guided_direction"], "takes 'white' only"),
    (["--exploration", "coloured", "--noise-exponent", "4"], "noise_exponent: must be in [0, 3]"),
    (["--hold-time", "-0.1"], "hold_time: must be >= 0 seconds"),
    (["--exploration", "ou", "--correlation-time", "0"], "noise_correlation_time: must be > 0"),
    (["--exploration", "parameter", "--methods", "guided_variance"], "reinforce and gp_pg only"),
    (["--exploration", "parameter", "--resample-time", "-1"],
     "noise_resample_time: must be >= 0 seconds"),
    (["--optimism", "-1", "--methods", "guided_direction"], "optimism: must be >= 0"),
])
def test_bad_exploration_is_refused_in_one_line(args, message):
    with pytest.raises(SystemExit) as exc:
        cli.main(["reproduce", "--preset", "tiny", "--compile-cache", "none", *args])
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_exploration_flags_reach_the_config(monkeypatch):
    from gpguided_jax import reproduce

    seen = {}
    monkeypatch.setattr(reproduce, "reproduce", lambda **kw: seen.update(kw) or {"complete": False})
    cli.main(["reproduce", "--preset", "tiny", "--methods", "reinforce", "--compile-cache", "none",
              "--exploration", "ou", "--correlation-time", "0.2", "--hold-time", "0.01"])
    assert seen["overrides"] == {"exploration": "ou", "noise_correlation_time": 0.2,
                                 "hold_time": 0.01}
    cli.main(["reproduce", "--preset", "tiny", "--methods", "gp_pg", "--compile-cache", "none",
              "--exploration", "parameter", "--resample-time", "0.25"])
    assert seen["overrides"] == {"exploration": "parameter", "noise_resample_time": 0.25}
    cli.main(["reproduce", "--preset", "tiny", "--methods", "guided_direction", "--compile-cache",
              "none", "--optimism", "2", "--hold-time", "0.01"])
    assert seen["overrides"] == {"optimism": 2.0, "hold_time": 0.01}
    cli.main(["reproduce", "--preset", "tiny", "--methods", "reinforce", "--compile-cache", "none",
              "--env", "gymnax:MountainCarContinuous-v0", "--episode-end", "restart"])
    assert seen["overrides"] == {"env": "gymnax:MountainCarContinuous-v0",
                                 "episode_end": "restart"}
    cli.main(["reproduce", "--preset", "tiny", "--methods", "gp_pg", "--compile-cache", "none",
              "--hold-time", "0.01", "--set", "num_updates=3", "learning_rate=0.5",
              "use_baseline=true", "discount_horizon=0.2"])
    assert seen["overrides"] == {"hold_time": 0.01, "num_updates": 3, "learning_rate": 0.5,
                                 "use_baseline": True, "discount_horizon": 0.2}


@pytest.mark.parametrize("args,message", [
    (["--set", "no_such_field=1"], "unknown TrainConfig field(s): ['no_such_field']"),
    (["--set", "num_updates"], "--set expects FIELD=VALUE, got 'num_updates'"),
    (["--set", "num_updates=0"], "TrainConfig.num_updates: must be a positive integer, got 0"),
    (["--hold-time", "0.1", "--set", "hold_time=0.2"], "--set hold_time: given by its own option"),
])
def test_bad_set_is_refused_in_one_line(args, message):
    with pytest.raises(SystemExit) as exc:
        cli.main(["reproduce", "--preset", "tiny", "--compile-cache", "none", *args])
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_import_does_not_touch_the_x64_flag():
    proc = _python("import jax, gpguided_jax, gpguided_jax.train, gpguided_jax.reproduce; "
                   "print(jax.config.jax_enable_x64)", JAX_ENABLE_X64="0")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


def test_float64_without_x64_is_refused_with_advice():
    proc = _python("from gpguided_jax import config; config.preset('tiny')", JAX_ENABLE_X64="0")
    assert proc.returncode != 0 and "enable_x64" in proc.stderr
    proc = _python("from gpguided_jax import config; "
                   "print(config.preset('tiny', dtype='float32').learning_rate.dtype)",
                   JAX_ENABLE_X64="0")
    assert proc.returncode == 0 and proc.stdout.strip() == "float32", proc.stderr


def _check_cli_run(proc, out, dtype, method, kept=False):
    """A finished `gpguided reproduce`: its tables printed, `method`'s checkpoint in `dtype` if it
    was `kept`, else no checkpoint left, every record finite, no temporary file left, and no
    traceback or loader false alarm in the log."""
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "failing seeds" in proc.stdout and "P(X > Y)" in proc.stdout
    if kept:
        with np.load(out / f"checkpoint_{method}.npz") as f:
            floats = [f[k] for k in f.files if k.startswith("leaf_") and f[k].dtype.kind == "f"]
        assert floats and all(x.dtype == np.dtype(dtype) for x in floats)
    else:
        assert not [p for p in os.listdir(out) if p.startswith("checkpoint_")], os.listdir(out)
    for noise in ("Traceback", "prefer-no-gather", "Assume version compatibility"):
        assert noise not in proc.stderr, proc.stderr[-3000:]
    with np.load(out / "results.npz") as f:
        for k in T.RECORD_FIELDS:
            assert np.all(np.isfinite(f[k])), k
    leftovers = [p for p in os.listdir(out) if ".tmp" in p]
    assert not leftovers, leftovers


@pytest.mark.training
def test_corrupt_checkpoint_and_kernels_are_set_aside(tmp_path):
    kw = dict(REPRODUCE_KW, methods=["gp_pg"], keep_checkpoints=True)
    first = R.reproduce(out_dir=str(tmp_path), progress=lambda m: None, **kw)
    ckpt, kern = tmp_path / "checkpoint_gp_pg.npz", tmp_path / "kernels_gp_pg.npz"
    ckpt.write_bytes(b"not a zip file")
    kern.write_bytes(ckpt.read_bytes()[:5])
    msgs = []
    again = R.reproduce(out_dir=str(tmp_path), progress=msgs.append, **kw)
    assert any("checkpoint_gp_pg.npz could not be read" in m for m in msgs), msgs
    assert any("kernels_gp_pg.npz could not be read" in m for m in msgs), msgs
    assert (tmp_path / "checkpoint_gp_pg.npz.corrupt").exists()
    assert (tmp_path / "kernels_gp_pg.npz.corrupt").exists()
    # started afresh, so the results are those of the first run
    assert again["summary"][0]["final_mean"] == first["summary"][0]["final_mean"]
    # a checkpoint with the right digest but missing arrays is set aside too
    with np.load(ckpt) as f:
        arrays = {k: f[k] for k in f.files if k != "leaf_0"}
    np.savez(ckpt, **arrays)
    msgs = []
    R.reproduce(out_dir=str(tmp_path), progress=msgs.append, **kw)
    assert any("missing or mis-shaped" in m for m in msgs), msgs


@pytest.mark.cli
def test_a_repeated_run_loads_its_programs_from_the_compile_cache(tmp_path):
    """The whole pipeline from the command line, in float32 with JAX's x64 mode off (float64: the
    multi-device runs of tests/test_train.py and tests/test_distributed.py), twice with one
    persistent compilation cache: the second process loads what the first compiled (loading a
    much larger program crashes; design: docs/design.md#decisions), and its results are the same
    bit for bit. The first keeps its checkpoints (every float of its state in float32), the
    second deletes them."""
    cache = tmp_path / "cache"

    def run(name, *extra):
        proc = subprocess.run(
            [sys.executable, "-m", "gpguided_jax.cli", "reproduce", "--preset", "tiny", "--seeds",
             "2", "--methods", "reinforce", "guided_variance", "--dtype", "float32", "--chunk-size",
             "3", "--out", str(tmp_path / name), "--compile-cache", str(cache), *extra],
            capture_output=True, text=True, timeout=600, cwd=ROOT,
            # the command's own default caches every program (with JAX's, only those that take
            # over 1 s to compile: a program near that threshold can be written by one run and
            # not the other); compiled fast, as the other end-to-end tests (the cache keys on the
            # flags, and both runs use the same)
            env={k: v for k, v in fast_compile_env().items()
                 if k != "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"})
        _check_cli_run(proc, tmp_path / name, "float32", "guided_variance", kept=bool(extra))
        assert f"compilation cache: {keyed}" in proc.stderr
        counts = re.search(r"compilation cache: (\d+) of (\d+) program\(s\) loaded from .*?, "
                           r"(\d+) compiled, (\d+) of them written", proc.stderr)
        assert counts, proc.stderr[-3000:]
        loaded, requests, compiled, written = map(int, counts.groups())
        assert loaded + compiled == requests and compiled == written  # every program is cached
        return {p: os.stat(os.path.join(keyed, p)).st_mtime_ns for p in os.listdir(keyed)}, \
            requests, loaded

    keyed = runtime.compile_cache_dir(str(cache))  # this CPU type's programs
    assert os.path.dirname(keyed) == str(cache)
    entries, cold_requests, _ = run("cold", "--keep-checkpoints")
    assert entries, "nothing was written to the compilation cache"
    warm_entries, warm_requests, warm_loaded = run("warm")
    assert warm_entries == entries  # a program compiled again would be written again
    assert warm_loaded == warm_requests == cold_requests  # JAX's own count: every one loaded
    with np.load(tmp_path / "cold" / "results.npz") as a, np.load(tmp_path / "warm" / "results.npz") as b:
        for k in T.RECORD_FIELDS:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_compile_cache_counter_counts_jax_monitoring_events():
    """The counts behind the command's last line on the cache, from JAX's event names."""
    counter = runtime.CompileCacheCounter()
    for event in ["/jax/compilation_cache/compile_requests_use_cache"] * 5 + [
            "/jax/compilation_cache/cache_hits"] * 2 + ["/jax/compilation_cache/cache_misses",
                                                        "/jax/some_other_event"]:
        counter(event)
    assert (counter.requests, counter.loaded, counter.written) == (5, 2, 1)
    line = counter.summary("/c", 1.0)
    assert line.startswith("compilation cache: 2 of 5 program(s) loaded from /c, 3 compiled, 1 of")


def test_the_compile_cache_is_kept_per_cpu_type():
    """One directory per CPU type and jaxlib build, the same in every process of this machine."""
    key = runtime.cpu_key()
    assert re.fullmatch(r"[\w.-]+-[0-9a-f]{12}", key) and os.sep not in key
    assert runtime.compile_cache_dir("/c") == os.path.join("/c", key)
    proc = _python("from gpguided_jax import runtime; print(runtime.cpu_key())")
    assert proc.returncode == 0 and proc.stdout.strip() == key


def test_drop_stderr_lines_drops_the_matching_lines_of_native_code_too():
    """Lines written to file descriptor 2 (as XLA's C++ logging does) and through sys.stderr, in
    order; only the matching ones are dropped."""
    code = ("import os, re, sys\n"
            "from gpguided_jax import runtime\n"
            "runtime.drop_stderr_lines(re.compile(rb'false alarm'))\n"
            "os.write(2, b'native one\\nE cpu_aot_loader.cc:1] a false alarm\\n')\n"
            "print('python two', file=sys.stderr, flush=True)\n"
            "os.write(2, b'native three\\n')\n")
    proc = _python(code)
    assert proc.returncode == 0
    assert proc.stderr.splitlines() == ["native one", "python two", "native three"]
    alarms = (b"E1203 18:11:58.192149   16209 cpu_aot_loader.cc:220] Loading XLA:CPU AOT result. "
              b"Target machine feature +prefer-no-gather is not  supported on the host machine.",
              b"W1203 18:13:29.433365   16785 pjrt_executable.cc:642] Assume version compatibility. "
              b"PjRt-IFRT does not track XLA executable versions.")
    for line in alarms:  # XLA's own lines, as jaxlib prints them
        assert runtime._LOADER_FALSE_ALARMS.search(line)
    assert not runtime._LOADER_FALSE_ALARMS.search(b"E cpu_aot_loader.cc:220] something else")


def test_an_unusable_or_busy_out_is_refused_in_one_line(tmp_path, capsys):
    """--out a file, a path under a file, or a directory another run holds: one line, exit 1."""
    from gpguided_jax import checkpoints

    (tmp_path / "file").write_text("")
    for out, message in ((tmp_path / "file", "exists and is not a directory"),
                         (tmp_path / "file" / "sub", "cannot write to")):
        with pytest.raises(SystemExit) as exc:
            cli.main(["reproduce", "--preset", "tiny", "--out", str(out), "--compile-cache", "none"])
        assert message in str(exc.value) and str(exc.value).startswith("gpguided reproduce: error:")
        assert "\n" not in str(exc.value)
    with checkpoints.open_out_dir(str(tmp_path / "busy")):  # another run holds it
        with pytest.raises(checkpoints.OutDirError, match="another run is writing to"):
            with checkpoints.open_out_dir(str(tmp_path / "busy")):
                pass
    with checkpoints.open_out_dir(str(tmp_path / "busy")):  # released at the end of the run
        pass


def test_ctrl_c_says_how_to_resume(monkeypatch, capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_reproduce", interrupted)
    assert cli.main(["reproduce", "--preset", "tiny", "--out", "somewhere"]) == 130
    err = capsys.readouterr().err.strip()
    assert err == ("gpguided reproduce: interrupted; run the same command again to resume from the "
                   "checkpoints in somewhere")


def test_help_shows_the_defaults(capsys):
    with pytest.raises(SystemExit):
        cli.main(["reproduce", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for default in ("(default: paper)", "(default: 10)", "(default: 1000)", "(default: float64)",
                    "(default: 50)", "(default: auto)", "(default: shared)"):
        assert default in out, default


def test_the_eta_leaves_out_the_first_chunk():
    """The first chunk of a call compiles its program: no ETA from it; the rate after it."""
    cfg = config.preset("tiny", method="reinforce")
    rec = T.UpdateRecord(*[np.zeros((2, 3)) for _ in T.RECORD_FIELDS])
    first = R._chunk_progress(cfg, rec, 2, 3, None, 4.2)
    assert "first chunk in 4.2s" in first and "ETA after the next chunk" in first
    later = R._chunk_progress(cfg, rec, 2, 3, 1.5, 4.2)
    assert f"ETA {(cfg.num_updates - 3) / 1.5:.0f}s" in later and "1.5 updates/s" in later
    assert "44565" not in runtime.CompileCacheCounter().summary("/c", 1.0)
