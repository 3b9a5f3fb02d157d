"""Shared test set-up.

* JAX's 64-bit mode is on (the package leaves it to the user; float32 tests pass float32 arrays or
  `dtype="float32"` explicitly, and test_cli.py's
  `test_a_repeated_run_loads_its_programs_from_the_compile_cache` runs the command line in
  float32 with the mode off).
* One LAPACK thread per test worker, as the command line runs (`runtime.single_threaded_lapack`):
  with `pytest -n 2` on 2 cores, OpenBLAS's default of one thread per core per call
  oversubscribed the cores in every hyperparameter fit.
* One persistent compilation cache for the test run, shared by the workers and by the
  command-line subprocesses (GPGUIDED_COMPILE_CACHE), in a fresh temporary directory: a program
  that several tests compile (the same tiny preset, resumed runs, repeated CLI runs) is compiled
  once. The cache gives the same results bit for bit (`test_a_repeated_run_loads_its_programs_
  from_the_compile_cache`), and the tests never write to the user's own cache in ~/.cache.
* The tests that run an experiment script, a notebook or the command line end to end at tiny
  sizes (plumbing: files, shapes, finiteness, and runs that must agree with each other, all
  compiled alike) run it in a subprocess whose XLA CPU backend compiles at optimisation level 0
  with XLA's older fusion emitters (`fast_compile_env`): they spend most of their time compiling,
  and both make the compilation, and so these tests, markedly faster. The library's in-process
  tests and the compile-cache test compile as a user's run does.
* `make test` runs `--dist loadgroup`, so that the tests of one `xdist_group` share their
  session-scoped fixtures on one worker; where xdist's grouping was lost, the grouped tests fail
  saying so (`pytest_collection_modifyitems` below). The long modules are collected first, so
  that the workers end together.
* Two tiers: `make test` runs the fast one, `-m "not slow"`, so that a change is checked in a
  couple of minutes on 2 cores; `make test-all` (and CI) runs every test. The tests that
  `make test` leaves out, the longest by `--durations=0`, are marked `slow`, or with the marker
  of their kind, which implies `slow` (`LONG_KINDS`, added in `pytest_collection_modifyitems`
  below): `cli` (the command line, an experiment script or the README's code end to end in a
  subprocess), `notebooks` (a notebook executed in a kernel), `distributed` (two processes or
  two host devices), `training` (training in the test's process: runs of the training loop or of
  its updates, sweeps, the baselines' PPO and SAC). A long test of none of these kinds (the
  sparse GP's long streams and 80-bit replays, property searches, Monte Carlo, finite-difference
  and `check_grads` comparisons, hyperparameter and model fits, jit and vmap against the plain
  function) is marked `slow` alone. pyproject.toml registers the markers, and `--strict-markers`
  makes a misspelt one an error (tests/test_tiers.py). The tests of an `xdist_group` whose shared
  fixture is long are all slow, so that the fast tier never computes such a fixture for a few of
  them.
"""

import functools
import importlib.util
import os
import subprocess
import sys
import tempfile

_CACHE = os.path.join(tempfile.gettempdir(), "gpguided-tests-xla-"
                      + os.environ.get("PYTEST_XDIST_TESTRUNUID", str(os.getpid())))
os.environ["GPGUIDED_COMPILE_CACHE"] = _CACHE  # before the CLI module reads it

import jax  # noqa: E402
import pytest  # noqa: E402

import gpguided_jax  # noqa: E402
from gpguided_jax import runtime  # noqa: E402

runtime.single_threaded_lapack()
gpguided_jax.enable_x64()
jax.config.update("jax_compilation_cache_dir", _CACHE)
# every program, the small ones included (as the command line caches them): the two workers
# compile many of the same small programs, and reading one back is faster than compiling it
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def experiment(name: str):
    """The script experiments/<name>.py as a fresh module (scripts, not a package; the scripts it
    imports by name, as `model_study`, are found beside it while it loads)."""
    folder = os.path.join(ROOT, "experiments")
    spec = importlib.util.spec_from_file_location(name, os.path.join(folder, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, folder)
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(folder)
    return module
LEVEL0_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
# ... and XLA's older (non-MLIR) fusion emitters, which compile faster still than level 0 alone.
# They round some fusions differently, so a script that compares two code paths of the library
# to a tight tolerance compiles at level 0 alone (`fast_compile="level0"`).
FAST_COMPILE_XLA_FLAGS = f"{LEVEL0_XLA_FLAGS} --xla_cpu_use_fusion_emitters=false"


@functools.cache
def _fast_compile_flags() -> str:
    """FAST_COMPILE_XLA_FLAGS if this jaxlib knows them (XLA aborts on an unknown flag, and a newer
    jaxlib may drop the older emitters' switch), else LEVEL0_XLA_FLAGS; checked once per worker."""
    env = dict(os.environ, XLA_FLAGS=FAST_COMPILE_XLA_FLAGS)
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env,
                           capture_output=True, timeout=120)
    return FAST_COMPILE_XLA_FLAGS if probe.returncode == 0 else LEVEL0_XLA_FLAGS


def fast_compile_env(level0_only=False, **extra):
    """os.environ (and `extra`) with XLA_FLAGS for fast compilation: for the end-to-end tests of
    experiment scripts, notebooks and the command line only. The compilation cache keys on the
    flags, so programs compiled so are never loaded by a test that compiles with the defaults."""
    env = dict(os.environ, **extra)
    flags = LEVEL0_XLA_FLAGS if level0_only else _fast_compile_flags()
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {flags}".strip()
    return env


def run_script(args, *, fast_compile=True, timeout=600, **env):
    """`python args...` in the project root (an experiment script, or ``-m gpguided_jax.cli``),
    with `env` added to the environment; fails the test, with the end of its stderr, unless it
    exits 0. `fast_compile`: True (`FAST_COMPILE_XLA_FLAGS` where jaxlib knows them), "level0"
    (`LEVEL0_XLA_FLAGS`) or False (XLA's defaults, as a user's run compiles). Returns the
    CompletedProcess."""
    if fast_compile:
        env = fast_compile_env(level0_only=fast_compile == "level0", **env)
    else:
        env = dict(os.environ, **env)
    proc = subprocess.run([sys.executable, *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


# The in-process runs of `reproduce` (test_train.py, test_cli.py) share their seeds and chunk
# length: the GP methods' one program and the fit are compiled once for all of them (in one
# worker; the other loads them from the test run's compilation cache).
REPRODUCE_KW = dict(preset="tiny", seeds=[0, 1], chunk_size=2)

# The reference run of the multi-device tests (tests/test_distributed.py, test_train.py's
# test_two_host_devices_vmapped_agree_with_each_seed_alone): the tiny preset's gp_pg, 4 seeds in
# chunks of 2.
TWO_DEVICE_ARGS = ["reproduce", "--preset", "tiny", "--seeds", "4", "--methods", "gp_pg",
                   "--chunk-size", "2"]


@pytest.fixture(scope="session")
def two_device_run(tmp_path_factory):
    """`gpguided reproduce` (TWO_DEVICE_ARGS) in one process with two host CPU devices, run once
    for the tests of the xdist group "two_devices"; returns its --out directory."""
    out = tmp_path_factory.mktemp("two_device_run")
    # level 0 alone: the group's tests compare runs over 1 and 2 devices and 2 processes bit for
    # bit, which XLA's older fusion emitters break (by ~1e-10 relative)
    run_script(["-m", "gpguided_jax.cli", *TWO_DEVICE_ARGS, "--out", out], fast_compile="level0",
               XLA_FLAGS="--xla_force_host_platform_device_count=2")
    return out


# Modules whose tests are long (end-to-end runs in subprocesses, whole training programs): run
# first, so that the two workers end together on short tests rather than one of them idling while
# the other finishes a long one (xdist hands out tests in collection order after the groups).
_LONG_MODULES = ("test_distributed.py", "test_tasks.py", "test_notebooks.py", "test_bench.py",
                 "test_analysis.py", "test_train.py", "test_cli.py", "test_baselines.py",
                 "test_sweep.py", "test_critic.py", "test_methods.py", "test_sparse_gp.py")


# The kinds of long test (markers registered in pyproject.toml), each of which implies `slow`.
LONG_KINDS = ("cli", "notebooks", "distributed", "training")

_UNGROUPED = []  # xdist_group tests that this worker's xdist failed to group


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config, items):
    """Marks every test of a kind in `LONG_KINDS` `slow` too, before pytest's `-m` deselects by
    marker (hence a wrapper: this part runs before the hook's other implementations).
    Then, after the others (xdist's included), puts the long modules first (`_LONG_MODULES`). In
    an xdist worker under `--dist loadgroup`, every test with an `xdist_group` mark must have the
    group appended to its node id (``...@group``): that suffix is all xdist's scheduler groups
    by. pytest 9.2 ignores xdist 3.8's way of appending it (pytest-dev/pytest-xdist#1386, hence
    `pytest<9.2` in pyproject.toml), and the groups were split over the workers without a word,
    each worker computing the shared fixtures again (the suite took a minute longer). Such tests
    now fail, saying why (an error raised here, in a worker, is not shown)."""
    for item in items:
        if any(item.get_closest_marker(kind) for kind in LONG_KINDS):
            item.add_marker(pytest.mark.slow)
    yield
    rank = {name: i for i, name in enumerate(_LONG_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable within a module
    if getattr(config.option, "loadgroup", False):  # set by xdist, in its workers only
        _UNGROUPED.extend(item.nodeid for item in items
                          if item.get_closest_marker("xdist_group") and "@" not in item.nodeid)


def pytest_runtest_setup(item):
    if item.nodeid in _UNGROUPED:
        pytest.fail("--dist loadgroup: pytest-xdist did not group this test's xdist_group; this "
                    "pytest/xdist pair loses the groups (pytest-dev/pytest-xdist#1386): install "
                    "the pytest that requirements.lock pins", pytrace=False)


def pytest_sessionfinish(session, exitstatus):
    """The controller (not an xdist worker) removes the test run's compilation cache at the end."""
    if not hasattr(session.config, "workerinput"):
        import shutil

        shutil.rmtree(_CACHE, ignore_errors=True)
