"""Random draws that do not depend on the computation dtype.

JAX's samplers produce different numbers for the same key in float32 and float64. Every draw of a
training run is made in float32 and then cast, so that one seed sees the same start states, reward
noise and exploration noise whichever `TrainConfig.dtype` it runs in: a float32 run and a float64
run of a seed then differ only through rounding, which is what the float32-vs-float64 comparison
measures. float32 noise has 24 bits of resolution, far below anything a policy gradient can feel.
"""

import jax
import jax.numpy as jnp


def normal(key: jax.Array, shape, dtype) -> jax.Array:
    """Standard normal draws of `shape`, drawn in float32 and cast to `dtype`."""
    return jax.random.normal(key, shape, jnp.float32).astype(dtype)


def categorical(key: jax.Array, logits: jax.Array) -> jax.Array:
    """argmax(logits + Gumbel noise), the noise drawn in float32 (dtype-independent); int32."""
    noise = jax.random.gumbel(key, logits.shape, jnp.float32).astype(logits.dtype)
    return jnp.argmax(logits + noise).astype(jnp.int32)
