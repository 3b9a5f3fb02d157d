"""Sparse online Gaussian process (Csato & Opper) with fixed-size basis-vector buffers (SPEC §2).

Convention: the latent predictive variance is sigma^2(x) = k(x, x) + k(x)^T C k(x) with C negative
semi-definite (Csato-Opper sign; the paper writes C with the opposite sign).

Buffers have M + 1 slots (capacity M, plus one slot so that a new point can be inserted before the
KL-optimal deletion). An inactive slot has mask False, alpha 0 and zero rows/columns in C and Q.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gpguided_jax import kernels


class SparseGPState(NamedTuple):
    """State of the online sparse GP. S = capacity + 1 slots, D = input dimension.

    Attributes:
      basis_vectors: (S, D) inputs of the basis vectors (rows of inactive slots are ignored).
      alpha: (S,) posterior mean coefficients; mu(x) = k(B, x)^T alpha.
      C: (S, S) negative semi-definite posterior covariance correction.
      Q: (S, S) inverse Gram matrix K_B^{-1} of the active basis vectors.
      timestamps: (S,) int32 index of the policy update during which each BV was added.
      mask: (S,) bool, True for active slots.
    """

    basis_vectors: jax.Array
    alpha: jax.Array
    C: jax.Array
    Q: jax.Array
    timestamps: jax.Array
    mask: jax.Array


def init(capacity: int, input_dim: int, dtype=None) -> SparseGPState:
    """An empty GP with room for `capacity` basis vectors (static)."""
    dtype = dtype or jnp.result_type(float)
    slots = capacity + 1
    return SparseGPState(
        basis_vectors=jnp.zeros((slots, input_dim), dtype),
        alpha=jnp.zeros((slots,), dtype),
        C=jnp.zeros((slots, slots), dtype),
        Q=jnp.zeros((slots, slots), dtype),
        timestamps=jnp.zeros((slots,), jnp.int32),
        mask=jnp.zeros((slots,), bool),
    )


def masked_kernel_vector(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams):
    """k(B, x) with inactive slots set to 0: (S,)."""
    k = kernels.cross_covariance(state.basis_vectors, x, hyper)
    return jnp.where(state.mask, k, jnp.zeros_like(k))


def predict(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams):
    """Predictive mean (eq. 5) and latent variance (eq. 6, Csato-Opper sign) at one input x (D,).

    Returns:
      (mean, latent_variance), both scalars; the variance is clipped to [0, k(x, x)].
    """
    k = masked_kernel_vector(state, x, hyper)
    kxx = kernels.kernel_diag(x, hyper)
    mean = k @ state.alpha
    var = kxx + k @ (state.C @ k)
    return mean, jnp.clip(var, 0.0, kxx)
