"""Shared test set-up: the suite runs with JAX's 64-bit mode on (the package leaves it to the user;
float32 tests pass float32 arrays or `dtype="float32"` explicitly, and tests/test_dtype.py runs the
command line with the mode off)."""

import gpguided_jax

gpguided_jax.enable_x64()
