"""Shared test set-up: the suite runs with JAX's 64-bit mode on (the package leaves it to the user;
float32 tests pass float32 arrays or `dtype="float32"` explicitly, and tests/test_dtype.py runs the
command line with the mode off), and with one LAPACK thread per test worker, as the command line
runs (`cli.single_threaded_lapack`): with `pytest -n 2` on 2 cores, OpenBLAS's default of one
thread per core per call oversubscribed the cores in every hyperparameter fit."""

import gpguided_jax
from gpguided_jax import cli

cli.single_threaded_lapack()
gpguided_jax.enable_x64()
