"""Analysis of trained runs: state-space coverage and GP surfaces over the (phi, omega) plane.

* `visited_cells` / `state_coverage`: which cells of a regular grid over the pendulum's state space
  a batch of states falls in, and their share of the grid. This is the number behind the paper's
  claim that guided exploration changes where the agent goes (§V, Fig. 2 and 4).
* `gp_at_states` / `gp_surface`: the GP's state value V(s) = Q_GP(s, c(s)) (Fig. 4) and latent
  predictive variance sigma^2(s, c(s)) (Fig. 2, eq. 6) at the controller's action, at given states
  or over a (phi, omega) grid.

All functions are pure JAX (jit- and vmap-able); the grid sizes are static Python ints.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from gpguided_jax import kernels, sparse_gp

TWO_PI = 2.0 * math.pi

# Default coverage grid: 36 angle bins (10 degrees each) over [0, 2 pi) and 32 velocity bins
# (0.5 rad/s each) over [-8, 8] rad/s. 8 rad/s exceeds sqrt(4 g / l) = 6.3 rad/s, the speed at the
# bottom of a free fall from upright, so the grid spans every state a +-5 N m swing reaches.
NUM_ANGLE_BINS = 36
NUM_VELOCITY_BINS = 32
MAX_VELOCITY = 8.0


def cell_indices(
    states: jax.Array,
    *,
    num_angle_bins: int = NUM_ANGLE_BINS,
    num_velocity_bins: int = NUM_VELOCITY_BINS,
    max_velocity=MAX_VELOCITY,
) -> tuple[jax.Array, jax.Array]:
    """Grid cell (angle bin, velocity bin) of each state.

    The angle is wrapped to [0, 2 pi) and split into `num_angle_bins` equal bins; the velocity range
    [-max_velocity, max_velocity] into `num_velocity_bins` equal bins. States faster than
    `max_velocity` are counted in the outermost velocity bin (clipped, not dropped).

    Args:
      states: (..., 2) states [phi, omega].

    Returns:
      (i_angle, i_velocity): int32 arrays of shape states.shape[:-1].
    """
    phi = jnp.mod(states[..., 0], TWO_PI)
    omega = states[..., 1]
    # floor() of a value that rounds to exactly 2 pi (or +max_velocity) would be one past the end.
    i_angle = jnp.clip(jnp.floor(phi / TWO_PI * num_angle_bins), 0, num_angle_bins - 1)
    u = (omega + max_velocity) / (2.0 * max_velocity)
    i_velocity = jnp.clip(jnp.floor(u * num_velocity_bins), 0, num_velocity_bins - 1)
    return i_angle.astype(jnp.int32), i_velocity.astype(jnp.int32)


def visited_cells(
    states: jax.Array,
    mask: jax.Array | None = None,
    *,
    num_angle_bins: int = NUM_ANGLE_BINS,
    num_velocity_bins: int = NUM_VELOCITY_BINS,
    max_velocity=MAX_VELOCITY,
) -> jax.Array:
    """Boolean occupancy grid (num_angle_bins, num_velocity_bins): True where any state falls.

    Args:
      states: (..., 2) states [phi, omega]; every leading axis is flattened.
      mask: optional bool array of shape states.shape[:-1]; states where it is False are ignored.
    """
    i_a, i_v = cell_indices(
        states,
        num_angle_bins=num_angle_bins,
        num_velocity_bins=num_velocity_bins,
        max_velocity=max_velocity,
    )
    hit = jnp.ones(i_a.shape, bool) if mask is None else jnp.asarray(mask, bool)
    grid = jnp.zeros((num_angle_bins, num_velocity_bins), bool)
    # .max as a scatter: a masked-out state writes False, which never clears a True.
    return grid.at[i_a.reshape(-1), i_v.reshape(-1)].max(hit.reshape(-1))


def state_coverage(
    states: jax.Array,
    mask: jax.Array | None = None,
    *,
    num_angle_bins: int = NUM_ANGLE_BINS,
    num_velocity_bins: int = NUM_VELOCITY_BINS,
    max_velocity=MAX_VELOCITY,
) -> jax.Array:
    """Share in [0, 1] of the cells of the state grid (see `cell_indices`) visited by `states`.

    Args:
      states: (..., 2) states [phi, omega] (e.g. all states of a run's episodes).
      mask: optional bool array of shape states.shape[:-1] selecting the states to count.

    Returns:
      () visited cells / (num_angle_bins * num_velocity_bins).
    """
    grid = visited_cells(
        states,
        mask,
        num_angle_bins=num_angle_bins,
        num_velocity_bins=num_velocity_bins,
        max_velocity=max_velocity,
    )
    return jnp.mean(grid.astype(jnp.result_type(float)))


def gp_at_states(
    gp: sparse_gp.SparseGPState,
    kernel: kernels.KernelParams,
    controller,
    controller_params,
    states: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """GP state value V(s) = Q_GP(s, c(s)) = mu(x*) (eq. 5) and latent variance sigma^2(x*) (eq. 6,
    Csato-Opper sign) at x* = (sin phi, cos phi, omega, c(s)), for a batch of states.

    These are the quantities of Fig. 4 and Fig. 2 (the guided exploration variance of eq. 16 is
    lambda_v times the latter).

    Args:
      gp: one seed's `SparseGPState`.
      kernel: its `KernelParams`.
      controller: a `gpguided_jax.controllers.Controller`.
      controller_params: theta_c (e.g. `TrainState.theta.controller`).
      states: (N, 2) states [phi, omega].

    Returns:
      (value, latent_variance), each (N,).
    """

    def at(s):
        x = kernels.state_action_features(s, controller.apply(controller_params, s))
        return sparse_gp.predict(gp, x, kernel)

    return jax.vmap(at)(states)


def gp_surface(
    gp: sparse_gp.SparseGPState,
    kernel: kernels.KernelParams,
    controller,
    controller_params,
    phi: jax.Array,
    omega: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """`gp_at_states` over the grid phi x omega: (value, latent_variance), each (A, B), indexed
    [angle, velocity], for phi (A,) and omega (B,)."""
    dtype = jnp.result_type(float)
    p, w = jnp.meshgrid(jnp.asarray(phi, dtype), jnp.asarray(omega, dtype), indexing="ij")
    states = jnp.stack([p.ravel(), w.ravel()], axis=-1)
    value, var = gp_at_states(gp, kernel, controller, controller_params, states)
    return value.reshape(p.shape), var.reshape(p.shape)

