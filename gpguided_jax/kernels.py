"""ARD squared-exponential kernel and the state-action feature map (design: docs/design.md#gp-model).

Written for one pair of points and vmapped twice for Gram matrices, as in tinygp.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp


class KernelParams(NamedTuple):
    """Hyperparameters of the ARD squared-exponential kernel with Gaussian noise.

    Attributes:
      lengthscales: (D,) positive length-scales l_d.
      signal_variance: () positive sigma_f^2.
      noise_variance: () positive observation-noise variance sigma_n^2.
    """

    lengthscales: jax.Array
    signal_variance: jax.Array
    noise_variance: jax.Array


def make_kernel_params(lengthscales, signal_variance=1.0, noise_variance=0.1, dtype=None):
    """Builds `KernelParams`, casting every leaf to one floating dtype."""
    dtype = dtype or jnp.result_type(float)
    return KernelParams(
        lengthscales=jnp.asarray(lengthscales, dtype),
        signal_variance=jnp.asarray(signal_variance, dtype),
        noise_variance=jnp.asarray(noise_variance, dtype),
    )


def se_ard(x1: jax.Array, x2: jax.Array, hyper: KernelParams) -> jax.Array:
    """k(x, x') = sigma_f^2 exp(-1/2 sum_d (x_d - x'_d)^2 / l_d^2) for one pair of (D,) inputs."""
    z = (x1 - x2) / hyper.lengthscales
    return hyper.signal_variance * jnp.exp(-0.5 * jnp.sum(z * z))


def kernel_diag(x: jax.Array, hyper: KernelParams) -> jax.Array:
    """k(x, x) = sigma_f^2 (a stationary kernel); kept as a function so that shapes/dtypes follow x."""
    del x
    return hyper.signal_variance


def cross_covariance(xs: jax.Array, x: jax.Array, hyper: KernelParams) -> jax.Array:
    """k(B, x): (N,) covariances between the rows of xs (N, D) and one point x (D,)."""
    return jax.vmap(se_ard, in_axes=(0, None, None))(xs, x, hyper)


def gram(xs1: jax.Array, xs2: jax.Array, hyper: KernelParams) -> jax.Array:
    """K(xs1, xs2): (N1, N2) Gram matrix."""
    return jax.vmap(cross_covariance, in_axes=(None, 0, None), out_axes=1)(xs1, xs2, hyper)


def state_action_features(state: jax.Array, action: jax.Array) -> jax.Array:
    """x = (sin phi, cos phi, omega, a), so that the angle enters periodically
    (design: docs/design.md#gp-model).

    Args:
      state: (2,) [phi, omega].
      action: () torque (the controller output or the taken action).

    Returns:
      (4,) feature vector.
    """
    phi, omega = state[0], state[1]
    return jnp.stack([jnp.sin(phi), jnp.cos(phi), omega, jnp.asarray(action, state.dtype)])
