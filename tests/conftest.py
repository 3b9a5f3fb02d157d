"""Shared test set-up: importing the package enables float64 (gpguided_jax/_x64.py)."""

import gpguided_jax  # noqa: F401
