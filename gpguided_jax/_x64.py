"""The one place where float64 is switched on.

The sparse GP keeps an inverse Gram matrix and a negative semi-definite C up to date by rank-one
updates; in float32 these lose several digits per few hundred updates, and the hyperparameter fit
takes a 2000x2000 Cholesky. So `import gpguided_jax` enables ``jax_enable_x64`` unless the
environment variable ``GPGUIDED_JAX_X64`` is set to ``0``. With x64 on, float32 is still available
by passing float32 arrays (the tests run the GP in float32 that way).
"""

import os

import jax

X64_ENV_VAR = "GPGUIDED_JAX_X64"


def enable_x64_from_env() -> bool:
    """Enables float64 in JAX unless ``GPGUIDED_JAX_X64=0``; returns whether it is on."""
    if os.environ.get(X64_ENV_VAR, "1") != "0":
        jax.config.update("jax_enable_x64", True)
    return bool(jax.config.jax_enable_x64)
