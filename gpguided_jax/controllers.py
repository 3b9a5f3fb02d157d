"""Deterministic controllers c(s; theta_c) = u_max * tanh(theta_c^T psi(s)) (paper §II; design:
docs/design.md#policies).

The controllers here are linear in their parameters before the squashing, so the parameter pytree
and the feature map psi(s) have the same structure, and

  dc/dtheta_c = u_max * (1 - tanh(z)^2) * psi(s),   z = <theta_c, psi(s)>.

Two feature maps are provided:

* `linear_controller`: psi(s) = (sin phi, cos phi, omega, 1), one weight vector of length 4.
* `rbf_controller`: a radial-basis-function network whose centres lie on a fixed grid over
  (phi, omega), embedded periodically as (sin phi, cos phi, omega), with fixed widths, plus a bias.

`trainable_rbf_controller` is not linear in its parameters: an RBF network whose centres, widths
and output weights are all trained (PILCO's controller, Deisenroth & Rasmussen 2011), optionally
plus a linear part. It declares no hand-derived gradient (gp_model differentiates it by autodiff);
the paper's methods refuse it.

Following optax, a constructor closes over the static configuration (torque limit, centres and
widths, which are NumPy constants) and returns a `Controller` of pure functions of
(params, state). The state is one (2,) vector [phi, omega]; batch with `jax.vmap`.
"""

from collections.abc import Callable
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

Params = Any  # a pytree of arrays with the structure of the controller's features


class LinearParams(NamedTuple):
    """Parameters of the linear controller.

    Attributes:
      weights: (4,) weights of the features (sin phi, cos phi, omega, 1).
    """

    weights: jax.Array


class RBFParams(NamedTuple):
    """Parameters of the RBF-network controller.

    Attributes:
      weights: (M,) weights of the M radial basis functions.
      bias: () bias added before the squashing.
    """

    weights: jax.Array
    bias: jax.Array


class Controller(NamedTuple):
    """A controller as a bundle of pure functions: what every method needs is `init` and `apply`
    (gp_model's gradients come by autodiff through them); the paper's estimators also need the
    hand-derived `value_and_grad`, which the squashed, linear-in-parameters controllers here give.

    Attributes:
      init: `init(dtype=None) -> params`, the deterministic initialiser (all zeros, so c(s) = 0
        everywhere and tanh is at its steepest).
      apply: `apply(params, state) -> c`, the torque c(s; theta_c) in (-u_max, u_max).
      u_max: the torque limit (a Python float, static).
      features: `features(state) -> psi`, a pytree like params (a linear-in-parameters
        controller's; None for another).
      value_and_grad: `value_and_grad(params, state) -> (c, dc_dparams)`, with the hand-derived
        gradient dc/dtheta_c as a pytree like params (None: a controller for methods that
        differentiate `apply` by autodiff only).
    """

    init: Callable[..., Params]
    apply: Callable[[Params, jax.Array], jax.Array]
    u_max: float
    features: Callable[[jax.Array], Params] | None = None
    value_and_grad: Callable[[Params, jax.Array], tuple[jax.Array, Params]] | None = None


def mean_and_grad(controller: Controller, params: Params, state: jax.Array):
    """(c(s), dc/dtheta_c): the controller's hand-derived `value_and_grad`, or autodiff of its
    `apply` for a controller that declares none (the roll-outs' score function needs the
    gradient whatever the controller)."""
    if controller.value_and_grad is not None:
        return controller.value_and_grad(params, state)
    return jax.value_and_grad(controller.apply)(params, state)


def _preactivation(params: Params, psi: Params) -> jax.Array:
    """z = <theta_c, psi(s)>, summed over every leaf."""
    products = jax.tree_util.tree_map(lambda w, f: jnp.sum(w * f), params, psi)
    return sum(jax.tree_util.tree_leaves(products))


def make_squashed(features_fn, zeros_fn, u_max: float, state_dim: int = 2) -> Controller:
    """Builds the squashed controller c = u_max tanh(<theta_c, psi(s)>) for a feature map psi =
    `features_fn(state)` of a (state_dim,) state, with the zero parameters `zeros_fn(dtype)`."""

    def features(state):
        chex.assert_shape(state, (state_dim,))
        return features_fn(state)

    def apply(params, state):
        z = _preactivation(params, features(state))
        return u_max * jnp.tanh(z)

    def value_and_grad(params, state):
        psi = features(state)
        squashed = jnp.tanh(_preactivation(params, psi))
        # d/dz u_max tanh(z) = u_max (1 - tanh(z)^2); exactly the expression jax's tanh rule uses,
        # so the saturated regime (|z| large, c at the torque limit) agrees bit for bit.
        slope = u_max * (1.0 - squashed * squashed)
        grad = jax.tree_util.tree_map(lambda f: slope * f, psi)
        return u_max * squashed, grad

    def init(dtype=None):
        return zeros_fn(dtype or jnp.result_type(float))

    return Controller(
        init=init, apply=apply, u_max=u_max, features=features, value_and_grad=value_and_grad
    )


def linear_controller(u_max: float = 5.0) -> Controller:
    """c(s) = u_max tanh(w^T (sin phi, cos phi, omega, 1)) (design: docs/design.md#policies).

    Args:
      u_max: torque limit (the pendulum clips to [-5, 5] N m).
    """

    def features_fn(state):
        phi, omega = state[0], state[1]
        return LinearParams(
            weights=jnp.stack([jnp.sin(phi), jnp.cos(phi), omega, jnp.ones_like(phi)])
        )

    def zeros_fn(dtype):
        return LinearParams(weights=jnp.zeros((4,), dtype))

    return make_squashed(features_fn, zeros_fn, float(u_max))


def rbf_grid(num_angles: int = 8, num_velocities: int = 5, max_velocity: float = 6.0):
    """Centres of the RBF network on a regular grid over (phi, omega).

    Angles are spread uniformly over [0, 2 pi) (the first one at phi = 0, hanging down, so the
    grid contains the upright pi whenever num_angles is even); velocities uniformly over
    [-max_velocity, max_velocity].

    Returns:
      (num_angles * num_velocities, 2) NumPy array of [phi, omega] centres.
    """
    angles = 2.0 * np.pi * np.arange(num_angles) / num_angles
    velocities = np.linspace(-max_velocity, max_velocity, num_velocities)
    grid = np.stack(np.meshgrid(angles, velocities, indexing="ij"), axis=-1)
    return grid.reshape(-1, 2)


def rbf_controller(
    u_max: float = 5.0,
    *,
    num_angles: int = 8,
    num_velocities: int = 5,
    max_velocity: float = 6.0,
    angle_width: float | None = None,
    velocity_width: float | None = None,
) -> Controller:
    """RBF network c(s) = u_max tanh(sum_i w_i exp(-d_i(s)^2 / 2) + b) (design: docs/design.md#policies).

    The state is embedded periodically as y(s) = (sin phi, cos phi, omega), the centres mu_i are
    the embeddings of an `rbf_grid`, and

      d_i(s)^2 = |(sin phi, cos phi) - (sin phi_i, cos phi_i)|^2 / w_phi^2
                 + (omega - omega_i)^2 / w_omega^2.

    Args:
      u_max: torque limit.
      num_angles, num_velocities, max_velocity: the grid of centres (static; fixes M).
      angle_width: w_phi, a chord length on the unit circle; default the chord between
        neighbouring grid angles, 2 sin(pi / num_angles).
      velocity_width: w_omega; default the grid spacing in omega.
    """
    centres = rbf_grid(num_angles, num_velocities, max_velocity)
    if angle_width is None:
        angle_width = 2.0 * np.sin(np.pi / num_angles)
    if velocity_width is None:
        velocity_width = 2.0 * max_velocity / max(num_velocities - 1, 1)
    embedded_centres = np.stack(
        [np.sin(centres[:, 0]), np.cos(centres[:, 0]), centres[:, 1]], axis=-1
    )
    inverse_widths = np.array([1.0 / angle_width, 1.0 / angle_width, 1.0 / velocity_width])
    num_centres = centres.shape[0]

    def features_fn(state):
        phi, omega = state[0], state[1]
        embedded = jnp.stack([jnp.sin(phi), jnp.cos(phi), omega])
        z = (embedded[None, :] - jnp.asarray(embedded_centres, state.dtype)) * jnp.asarray(
            inverse_widths, state.dtype
        )
        return RBFParams(weights=jnp.exp(-0.5 * jnp.sum(z * z, axis=-1)), bias=jnp.ones_like(phi))

    def zeros_fn(dtype):
        return RBFParams(weights=jnp.zeros((num_centres,), dtype), bias=jnp.zeros((), dtype))

    return make_squashed(features_fn, zeros_fn, float(u_max))


class TrainableRBFParams(NamedTuple):
    """Parameters of the trainable RBF network (`trainable_rbf_controller`).

    Attributes:
      centres: (M, K) centres in the embedding y(s).
      log_widths: (K,) logs of the widths, one per coordinate of the embedding, shared by the
        units (PILCO's shared lengthscales).
      weights: (M,) output weights.
      bias: () bias added before the squashing.
      linear: (K,) weights of a linear part w^T y(s) (None for the network alone: no leaf, so
        that every leaf has a size).
    """

    centres: jax.Array
    log_widths: jax.Array
    weights: jax.Array
    bias: jax.Array
    linear: jax.Array | None


def trainable_rbf_controller(embed: Callable[[jax.Array], jax.Array], centres, widths, u_max: float,
                             *, linear: bool = False) -> Controller:
    """c(s) = u_max tanh(sum_i w_i exp(-|(y(s) - mu_i) / ell|^2 / 2) + b [+ v^T y(s)]), with the
    centres mu_i, the widths ell (one per coordinate of the embedding y = `embed(s)`), the weights
    w, the bias b and the linear part's v all trained (design: docs/design.md#model).

    Args:
      embed: the embedding y(s), a (K,) vector (the normalised observation, or the pendulum's
        (sin phi, cos phi, omega)).
      centres: (M, K) the centres' initial values (NumPy).
      widths: (K,) or () the widths' initial values (NumPy).
      u_max: torque limit.
      linear: whether to add the linear part v^T y(s) (zero at the start).
    """
    centres = np.asarray(centres, np.float64)
    m, k = centres.shape
    log_widths = np.log(np.broadcast_to(np.asarray(widths, np.float64), (k,)))

    def apply(params, state):
        y = embed(state)
        d = (y[None, :] - params.centres) * jnp.exp(-params.log_widths)
        z = jnp.exp(-0.5 * jnp.sum(d * d, axis=-1)) @ params.weights + params.bias
        if linear:
            z = z + params.linear @ y
        return u_max * jnp.tanh(z)

    def init(dtype=None):
        dtype = dtype or jnp.result_type(float)
        return TrainableRBFParams(jnp.asarray(centres, dtype), jnp.asarray(log_widths, dtype),
                                  jnp.zeros((m,), dtype), jnp.zeros((), dtype),
                                  jnp.zeros((k,), dtype) if linear else None)

    return Controller(init=init, apply=apply, u_max=float(u_max))


def farthest_point_centres(points: np.ndarray, n: int) -> np.ndarray:
    """`n` of `points` chosen greedily, each the farthest from those chosen before (the first is
    the point nearest the mean): an even cover of the visited region."""
    chosen = [int(np.argmin(np.sum((points - points.mean(0)) ** 2, axis=1)))]
    dist = np.sum((points - points[chosen[0]]) ** 2, axis=1)
    for _ in range(min(n, len(points)) - 1):
        j = int(np.argmax(dist))
        chosen.append(j)
        dist = np.minimum(dist, np.sum((points - points[j]) ** 2, axis=1))
    return points[chosen]


def mean_gap(centres: np.ndarray) -> float:
    """The mean distance from a centre to its nearest neighbour (1 for a single centre)."""
    if len(centres) < 2:
        return 1.0
    gaps = np.sqrt(np.sum((centres[:, None] - centres[None]) ** 2, axis=-1))
    np.fill_diagonal(gaps, np.inf)
    return float(np.mean(np.min(gaps, axis=1)))


def pendulum_trainable_rbf(u_max: float = 5.0, units: int = 0, *, linear: bool = False,
                           max_velocity: float = 6.0) -> Controller:
    """`trainable_rbf_controller` on the paper's pendulum: the embedding (sin phi, cos phi,
    omega), the centres started on `rbf_controller`'s grid (units 0: its 40), or `units` of them
    spread by farthest points over a fine grid of the state space, each coordinate in units of
    the default network's widths (which are the initial widths)."""
    inv = np.array([1.0 / (2.0 * np.sin(np.pi / 8)), 1.0 / (2.0 * np.sin(np.pi / 8)),
                    4.0 / (2.0 * max_velocity)])
    grid = rbf_grid(8, 5, max_velocity) if units <= 0 else rbf_grid(64, 33, max_velocity)
    embedded = np.stack([np.sin(grid[:, 0]), np.cos(grid[:, 0]), grid[:, 1]], axis=-1)
    if units > 0:
        embedded = farthest_point_centres(embedded * inv, units) / inv

    def embed(state):
        chex.assert_shape(state, (2,))
        return jnp.stack([jnp.sin(state[0]), jnp.cos(state[0]), state[1]])

    return trainable_rbf_controller(embed, embedded, 1.0 / inv, u_max, linear=linear)


CONTROLLERS = {"linear": linear_controller, "rbf": rbf_controller,
               "rbf_trainable": pendulum_trainable_rbf,
               "linear_rbf": lambda u_max=5.0, units=0: pendulum_trainable_rbf(u_max, units,
                                                                               linear=True)}


def make_controller(name: str, **kwargs) -> Controller:
    """Looks a controller constructor up by name (`CONTROLLERS`: 'linear', 'rbf', 'rbf_trainable'
    or 'linear_rbf')."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; choose from {sorted(CONTROLLERS)}")
    return CONTROLLERS[name](**kwargs)
