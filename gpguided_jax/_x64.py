"""Float64 in JAX is the user's choice: this package never switches it on at import.

JAX computes in float32 unless its 64-bit mode is on. The sparse GP and the hyperparameter fit are
run in float64 by default (`TrainConfig.dtype = "float64"`), which needs that mode; call
`gpguided_jax.enable_x64()` (or `jax.config.update("jax_enable_x64", True)`, or set the
environment variable JAX_ENABLE_X64=1) before creating any arrays. `TrainConfig(dtype="float32")`
runs everything in float32 and works either way. The `gpguided` command line sets the mode from
its `--dtype` option.
"""

import jax


def enable_x64(enabled: bool = True) -> bool:
    """Turns JAX's 64-bit mode on (or off) for this process; returns whether it is on.

    Call it before creating arrays: arrays made before the switch keep their dtype.
    """
    jax.config.update("jax_enable_x64", bool(enabled))
    return bool(jax.config.jax_enable_x64)


def x64_enabled() -> bool:
    """Whether JAX's 64-bit mode is on."""
    return bool(jax.config.jax_enable_x64)
