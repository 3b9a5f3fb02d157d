"""gpguided_jax: guided policy search with sparse online Gaussian processes in JAX.

A JAX implementation of Jakab & Csato, "Reinforcement learning with guided policy search using
Gaussian processes" (IJCNN 2012). Importing the package enables float64 in JAX (see `_x64.py`;
set GPGUIDED_JAX_X64=0 before import to keep JAX's float32 default).
"""

from gpguided_jax._x64 import enable_x64_from_env as _enable_x64_from_env

_enable_x64_from_env()

from gpguided_jax import kernels, pendulum, sparse_gp  # noqa: E402

__version__ = "0.1.0"

__all__ = ["kernels", "pendulum", "sparse_gp", "__version__"]
