"""Shared test set-up.

* JAX's 64-bit mode is on (the package leaves it to the user; float32 tests pass float32 arrays or
  `dtype="float32"` explicitly, and tests/test_dtype.py runs the command line with the mode off).
* One LAPACK thread per test worker, as the command line runs (`cli.single_threaded_lapack`): with
  `pytest -n 2` on 2 cores, OpenBLAS's default of one thread per core per call oversubscribed the
  cores in every hyperparameter fit.
* One persistent compilation cache for the session, shared by the workers and by the command-line
  subprocesses (GPGUIDED_COMPILE_CACHE), in a fresh temporary directory: a program that several
  tests compile (the same tiny preset, resumed runs, repeated CLI runs) is compiled once. The
  cache gives the same results bit for bit (`test_a_repeated_run_loads_its_programs_from_the_
  compile_cache`), and the tests never write to the user's own cache in ~/.cache.
"""

import os
import tempfile

_CACHE = os.path.join(tempfile.gettempdir(), "gpguided-tests-xla-"
                      + os.environ.get("PYTEST_XDIST_TESTRUNUID", str(os.getpid())))
os.environ["GPGUIDED_COMPILE_CACHE"] = _CACHE  # before the CLI module reads it

import jax  # noqa: E402

import gpguided_jax  # noqa: E402
from gpguided_jax import cli  # noqa: E402

cli.single_threaded_lapack()
gpguided_jax.enable_x64()
jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def pytest_sessionfinish(session, exitstatus):
    """The controller (not an xdist worker) removes the session's compilation cache at the end."""
    if not hasattr(session.config, "workerinput"):
        import shutil

        shutil.rmtree(_CACHE, ignore_errors=True)
