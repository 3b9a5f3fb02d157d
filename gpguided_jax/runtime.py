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
        line = (f"compilation cache: {self.loaded} of {self.requests} program(s) loaded from {path}, "
                f"{self.requests - self.loaded} compiled, {self.written} of them written to it "
                f"(those that took over {min_compile_s:g} s to compile)")
        if self.loaded:
            line += (". XLA:CPU may log 'Target machine feature +prefer-no-gather is not supported "
                     "on the host machine ... SIGILL' for each program it loads: on CPUs whose "
                     "LLVM tuning sets these preferences that is a false alarm, "
                     "openxla/xla#44565; the programs loaded are the ones compiled here")
        return line


_COMPILE_CACHE: tuple[str, CompileCacheCounter] | None = None  # (directory, counter) once set


def set_compile_cache(path: str | None) -> None:
    """JAX's persistent compilation cache: a repeated run loads its compiled programs instead of
    compiling them again. 'none' turns it off.

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

        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
            # every program, not only those over JAX's default of 1 s: the many small programs of a
            # run that compile in under 1 s would otherwise be compiled again by every warm run
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        if not faulthandler.is_enabled():
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
