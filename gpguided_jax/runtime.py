"""The process's runtime set-up, before and around JAX: LAPACK threads, CPU devices, precision,
and the persistent compilation cache. Light: importing it imports no JAX (the command line sets
the LAPACK threads and the CPU devices before JAX starts).

* `single_threaded_lapack`: one OpenBLAS thread for JAX's CPU LAPACK calls (`lapack_threads`);
* `set_cpu_devices`: one JAX CPU device per core (`available_cores`), so that the seeds' shards
  run in parallel;
* `set_precision`: JAX's 64-bit mode for float64 runs;
* `set_compile_cache` / `report_compile_cache`: JAX's persistent compilation cache, and how many
  programs a run loaded from it and compiled (`CompileCacheCounter`).
"""

from __future__ import annotations

import os
import re
import sys

DEFAULT_COMPILE_CACHE = os.environ.get(
    "GPGUIDED_COMPILE_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "gpguided_jax", "xla"))
LAPACK_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def lapack_threads(environ, lapack_loaded: bool) -> str | None:
    """The OPENBLAS_NUM_THREADS this process's LAPACK should run with: "1", or None to leave it.

    JAX's CPU LAPACK calls (the hyperparameter fit's Cholesky and triangular solves) go to the
    OpenBLAS that SciPy bundles, which by default starts one thread per core for every call. With
    one JAX device per core, every device makes such calls at the same time and the threads
    oversubscribe the cores: the fit is much slower than with one thread (design:
    docs/design.md#decisions). One thread also makes the LAPACK results independent of the
    core count and of the device count (OpenBLAS's rounding depends on its thread count).
    None when the user has set any of `LAPACK_THREAD_VARIABLES`, or when SciPy's LAPACK is
    already loaded (OpenBLAS reads the variable when it loads)."""
    if lapack_loaded or any(v in environ for v in LAPACK_THREAD_VARIABLES):
        return None
    return "1"


def single_threaded_lapack() -> None:
    """Sets OPENBLAS_NUM_THREADS=1 for this process (see `lapack_threads`); call it before JAX's
    first LAPACK call, as `cli.main` does before anything else."""
    threads = lapack_threads(os.environ, "scipy.linalg" in sys.modules)
    if threads is not None:
        os.environ["OPENBLAS_NUM_THREADS"] = threads


def set_cpu_devices(count: int | None) -> None:
    """One JAX CPU device per core, or `count` (before JAX starts its backends), so that the
    seeds' shards run in parallel: XLA runs one CPU device's program largely on one core. LAPACK
    runs one thread (`single_threaded_lapack`). The device count is left alone when XLA_FLAGS
    already sets it. Accelerators are unaffected.

    Raises:
      SystemExit: `count` was given and JAX has already started in this process.
    """
    single_threaded_lapack()
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", int(count or available_cores()))
    except RuntimeError:  # JAX already runs in this process (e.g. `cli.main` from a notebook)
        if count is not None:
            raise SystemExit(
                f"gpguided: error: --cpu-devices {count}: JAX has already started in this process "
                f"with {len(jax.devices('cpu'))} CPU device(s); run the command in a new process"
            ) from None


def set_precision(dtype: str) -> None:
    """float64 runs need JAX's 64-bit mode; this process is ours, so switch it as asked."""
    import gpguided_jax

    gpguided_jax.enable_x64(dtype == "float64")


class CompileCacheCounter:
    """Counts, from JAX's monitoring events in this process, the programs looked up in the
    persistent compilation cache, those loaded from it, and those written to it.

    A program that is looked up and not loaded was compiled (it is written unless it compiled
    faster than jax_persistent_cache_min_compile_time_secs). The counts tell whether a repeated
    run really loaded its programs, which the cache's own log does not say."""

    _EVENTS = {"/jax/compilation_cache/compile_requests_use_cache": "requests",
               "/jax/compilation_cache/cache_hits": "loaded",
               "/jax/compilation_cache/cache_misses": "written"}  # recorded on writing an entry

    def __init__(self):
        self.requests = self.loaded = self.written = 0

    def __call__(self, event: str, **kwargs) -> None:
        name = self._EVENTS.get(event)
        if name is not None:
            setattr(self, name, getattr(self, name) + 1)

    def summary(self, path: str, min_compile_s: float) -> str:
        return (f"compilation cache: {self.loaded} of {self.requests} program(s) loaded from {path}, "
                f"{self.requests - self.loaded} compiled, {self.written} of them written to it "
                f"(those that took over {min_compile_s:g} s to compile)")


def cpu_key() -> str:
    """A name for this CPU type and jaxlib build: the architecture, a readable model tag and a
    digest of the CPU's model and feature flags (``/proc/cpuinfo`` on Linux) and of jaxlib's
    version. A compiled program is specific to the CPU features it was compiled for, so the
    compilation cache keeps one directory per key, and a program is never loaded on a CPU of
    another type (nor by another jaxlib), even where the cache directory is shared."""
    import hashlib
    import platform

    fields: dict[str, str] = {}  # the first processor's
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    if fields:
                        break
                    continue
                name, _, value = line.partition(":")
                fields.setdefault(name.strip(), value.strip())
    except OSError:  # not Linux
        pass
    model = fields.get("model name") or fields.get("CPU part") or platform.processor()
    flags = fields.get("flags") or fields.get("Features", "")
    try:
        from jaxlib import version as jaxlib_version

        jaxlib = jaxlib_version.__version__
    except ImportError:
        jaxlib = "unknown"
    digest = hashlib.sha256("\n".join((platform.machine(), model, flags, jaxlib)).encode())
    tag = re.sub(r"[^a-z0-9]+", "-", model.lower()).strip("-")[:32] or "cpu"
    return f"{platform.machine() or 'unknown'}-{tag}-{digest.hexdigest()[:12]}"


def compile_cache_dir(base: str) -> str:
    """The directory of `base`'s compilation cache that this CPU type uses (`cpu_key`)."""
    return os.path.join(base, cpu_key())


# What XLA logs on loading a cached program that is a false alarm here, where the cache is kept
# per CPU type and jaxlib build (`cpu_key`), so that a program is only ever loaded by the CPU
# type and the jaxlib that compiled it: the loader compares the features the program was compiled
# for with the host's and reports LLVM tuning preferences that are not CPU features, on the very
# machine that compiled it (openxla/xla#44565); and PjRt says it does not track the executable's
# XLA version. Every such line is dropped from the log (`drop_stderr_lines`).
_LOADER_FALSE_ALARMS = re.compile(
    rb"cpu_aot_loader\.cc:\d+\] Loading XLA:CPU AOT result\. Target machine feature "
    rb"\+prefer-no-(gather|scatter) is not +supported on the host machine"
    rb"|pjrt_executable\.cc:\d+\] Assume version compatibility\. PjRt-IFRT does not track XLA "
    rb"executable versions")
_STDERR_FILTER: tuple | None = None  # (terminal fd, its file, the thread) once installed


def drop_stderr_lines(pattern: re.Pattern = _LOADER_FALSE_ALARMS) -> None:
    """Drops the lines of this process's standard error (file descriptor 2, so native code's
    logging too) that match `pattern`; every other line passes unchanged and in order. Fatal-error
    reports (`faulthandler`) go straight to the original standard error. Installed once per
    process; undone at exit."""
    global _STDERR_FILTER
    if _STDERR_FILTER is not None:
        return
    import atexit
    import faulthandler
    import threading

    sys.stderr.flush()
    terminal = os.dup(2)
    read_end, write_end = os.pipe()
    os.dup2(write_end, 2)
    os.close(write_end)

    def pump():
        with os.fdopen(read_end, "rb") as lines:
            for line in lines:
                if not pattern.search(line):
                    view = memoryview(line)
                    while view:
                        view = view[os.write(terminal, view):]

    thread = threading.Thread(target=pump, name="stderr-filter", daemon=True)
    thread.start()
    terminal_file = os.fdopen(os.dup(terminal), "w")
    faulthandler.enable(file=terminal_file)
    _STDERR_FILTER = (terminal, terminal_file, thread)

    def undo():
        sys.stderr.flush()
        os.dup2(terminal, 2)  # closes the pipe's last writer: the thread reads to its end
        thread.join(timeout=5)

    atexit.register(undo)


_COMPILE_CACHE: tuple[str, CompileCacheCounter] | None = None  # (directory, counter) once set


def set_compile_cache(path: str | None) -> None:
    """JAX's persistent compilation cache: a repeated run loads its compiled programs instead of
    compiling them again. 'none' turns it off. The programs go to the subdirectory of `path` for
    this CPU type (`compile_cache_dir`), so a cached program is never loaded on a CPU it was not
    compiled for, and the loader's false alarms are dropped from the log (`drop_stderr_lines`).

    With jax 0.9.2 on CPU every program this project compiles loads correctly (and computes the
    same results bit for bit), but loading a much larger cached program crashes the process
    (design: docs/design.md#decisions). The cache directory is therefore named in the log, and
    `faulthandler` is on, so that such a crash says where it happened and how to avoid it. At the
    end the command says how many programs it loaded and compiled (`report_compile_cache`)."""
    global _COMPILE_CACHE
    if path and path.lower() != "none":
        import faulthandler

        import jax
        import jax.monitoring

        path = compile_cache_dir(path)
        os.makedirs(path, exist_ok=True)
        drop_stderr_lines()
        jax.config.update("jax_compilation_cache_dir", path)
        if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
            # every program, not only those over JAX's default of 1 s: the many small programs of a
            # run that compile in under 1 s would otherwise be compiled again by every warm run
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        if not faulthandler.is_enabled():  # `drop_stderr_lines` enabled it
            faulthandler.enable()
        if _COMPILE_CACHE is None:
            counter = CompileCacheCounter()
            jax.monitoring.register_event_listener(counter)
            _COMPILE_CACHE = (path, counter)
        print(f"compilation cache: {path} ('--compile-cache none' turns it off)", file=sys.stderr,
              flush=True)


def report_compile_cache() -> None:
    """The `CompileCacheCounter` line, to stderr, if `set_compile_cache` turned the cache on."""
    if _COMPILE_CACHE is not None:
        import jax

        path, counter = _COMPILE_CACHE
        print(counter.summary(path, jax.config.jax_persistent_cache_min_compile_time_secs),
              file=sys.stderr, flush=True)
