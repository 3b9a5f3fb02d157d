"""The torque-limited pendulum of the paper (§VI, eq. 23-24) as pure JAX functions
(design: docs/design.md#pendulum).

State s = [phi, omega] (shape (2,)): phi is measured from the hanging rest position and wrapped to
[0, 2*pi); the target is upright, phi = pi. Dynamics with torque u and viscous friction b:

    phi' = omega,    omega' = (u - b*omega - m*g*l*sin(phi)) / (m*l^2),

integrated by classical Runge-Kutta 4 with `substeps` sub-steps per control interval dt = 0.005 s
(200 Hz). Torque is clipped to [-max_torque, max_torque]; with the defaults m*g*l = 9.81 > 5, so the
pendulum cannot be lifted directly and a swing-up needs several swings.

Reward (eq. 24, sign restored): R = -(phi - pi)^2 - (omega/4)^2 + eps, eps ~ N(0, reward_noise_std^2),
evaluated on the state *after* the step (the state the action led to), so every action, the last
of an episode included, is credited with its immediate consequence.

Start states: phi ~ N(start_mean[0], start_std[0]^2) wrapped, omega ~ N(start_mean[1], start_std[1]^2).
The paper does not give this distribution; the default is a band around upright (phi = pi +- 0.6
rad, omega +- 0.5 rad/s), where a 50-step (0.25 s) episode can make a difference. The swing-up
preset of the training config starts at the bottom instead.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import _random

TWO_PI = 2.0 * math.pi


@dataclasses.dataclass(frozen=True)
class PendulumParams:
    """Physical and task parameters. Every field but `substeps` is a traced leaf (vmappable).

    Attributes:
      mass: () kg.
      length: () m.
      gravity: () m/s^2.
      friction: () viscous friction coefficient b (N m s); not in the paper, default 0.
      dt: () control interval in seconds (200 Hz -> 0.005).
      max_torque: () torque limit (N m).
      reward_noise_std: () standard deviation sigma_r of the reward noise.
      start_mean: (2,) mean of the start state [phi, omega].
      start_std: (2,) standard deviation of the start state [phi, omega].
      substeps: static int, RK4 sub-steps per control interval.
    """

    mass: jax.Array
    length: jax.Array
    gravity: jax.Array
    friction: jax.Array
    dt: jax.Array
    max_torque: jax.Array
    reward_noise_std: jax.Array
    start_mean: jax.Array
    start_std: jax.Array
    substeps: int = 1


_DATA_FIELDS = [f.name for f in dataclasses.fields(PendulumParams) if f.name != "substeps"]
jax.tree_util.register_dataclass(PendulumParams, data_fields=_DATA_FIELDS, meta_fields=["substeps"])

DEFAULTS = dict(
    mass=1.0,
    length=1.0,
    gravity=9.81,
    friction=0.0,
    dt=0.005,
    max_torque=5.0,
    reward_noise_std=0.1,
    start_mean=(math.pi, 0.0),
    start_std=(0.6, 0.5),
    substeps=1,
)

# field -> (lower bound, whether the bound is strict)
_BOUNDS = {
    "mass": (0.0, True),
    "length": (0.0, True),
    "gravity": (0.0, False),
    "friction": (0.0, False),
    "dt": (0.0, True),
    "max_torque": (0.0, True),
    "reward_noise_std": (0.0, False),
    "start_std": (0.0, False),
}


def _validate(name: str, value) -> None:
    if isinstance(value, jax.core.Tracer):
        return  # cannot check traced values; make_params is meant to be called eagerly
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"PendulumParams.{name} must be finite, got {value!r}")
    if name in _BOUNDS:
        lo, strict = _BOUNDS[name]
        bad = arr <= lo if strict else arr < lo
        if np.any(bad):
            rel = ">" if strict else ">="
            raise ValueError(f"PendulumParams.{name} must be {rel} {lo}, got {value!r}")


def make_params(dtype=None, **overrides) -> PendulumParams:
    """Builds validated `PendulumParams` from the defaults and keyword overrides.

    Raises:
      TypeError: for an unknown field name.
      ValueError: naming the field, for a non-finite value, a non-positive mass, length, dt or
        torque limit, a negative gravity, friction, noise std or start std, or substeps < 1.
    """
    unknown = set(overrides) - set(DEFAULTS)
    if unknown:
        raise TypeError(f"unknown PendulumParams field(s): {sorted(unknown)}")
    values = {**DEFAULTS, **overrides}
    substeps = values.pop("substeps")
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"PendulumParams.substeps must be an integer >= 1, got {substeps!r}")
    dtype = dtype or jnp.result_type(float)
    leaves = {}
    for name, value in values.items():
        _validate(name, value)
        leaves[name] = jnp.asarray(value, dtype)
    for name in ("start_mean", "start_std"):
        if leaves[name].shape != (2,):
            raise ValueError(f"PendulumParams.{name} must have shape (2,), got {leaves[name].shape}")
    return PendulumParams(**leaves, substeps=int(substeps))


def wrap_angle(phi: jax.Array) -> jax.Array:
    """Wraps an angle to [0, 2*pi); guards the float case where mod returns exactly 2*pi."""
    wrapped = jnp.mod(phi, TWO_PI)
    return jnp.where(wrapped >= TWO_PI, wrapped - TWO_PI, wrapped)


def dynamics(y: jax.Array, torque: jax.Array, params: PendulumParams) -> jax.Array:
    """Time derivative [phi', omega'] of the state y = [phi, omega] under a (clipped) torque."""
    phi, omega = y[0], y[1]
    inertia = params.mass * params.length**2
    domega = (
        torque - params.friction * omega - params.mass * params.gravity * params.length * jnp.sin(phi)
    ) / inertia
    return jnp.stack([omega, domega])


def _rk4(y, torque, params, h):
    k1 = dynamics(y, torque, params)
    k2 = dynamics(y + 0.5 * h * k1, torque, params)
    k3 = dynamics(y + 0.5 * h * k2, torque, params)
    k4 = dynamics(y + h * k3, torque, params)
    return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def integrate(y: jax.Array, torque: jax.Array, params: PendulumParams) -> jax.Array:
    """Advances y by one control interval dt with `params.substeps` RK4 sub-steps (no wrapping)."""
    h = params.dt / params.substeps
    return jax.lax.fori_loop(0, params.substeps, lambda _, z: _rk4(z, torque, params, h), y)


def energy(state: jax.Array, params: PendulumParams) -> jax.Array:
    """Hamiltonian H = p^2/(2 m l^2) - m g l cos(phi), p = m l^2 omega (eq. 23)."""
    phi, omega = state[..., 0], state[..., 1]
    ml2 = params.mass * params.length**2
    return 0.5 * ml2 * omega**2 - params.mass * params.gravity * params.length * jnp.cos(phi)


def clip_torque(action: jax.Array, params: PendulumParams) -> jax.Array:
    return jnp.clip(action, -params.max_torque, params.max_torque)


def reward_mean(state: jax.Array) -> jax.Array:
    """Noise-free reward -(phi - pi)^2 - (omega/4)^2 of a wrapped state (eq. 24, sign restored)."""
    return -((state[0] - math.pi) ** 2) - (state[1] / 4.0) ** 2


def reset(key: jax.Array, params: PendulumParams) -> jax.Array:
    """Draws a start state [phi, omega] (phi wrapped to [0, 2*pi))."""
    z = _random.normal(key, (2,), params.start_mean.dtype)
    s = params.start_mean + params.start_std * z
    return jnp.stack([wrap_angle(s[0]), s[1]])


def step(key: jax.Array, state: jax.Array, action: jax.Array, params: PendulumParams):
    """One control interval.

    Args:
      key: PRNG key for the reward noise.
      state: (2,) [phi, omega].
      action: () torque before clipping.
      params: `PendulumParams`.

    Returns:
      (next_state, reward): next_state (2,) with phi wrapped; reward () evaluated on next_state.
    """
    torque = clip_torque(jnp.asarray(action, state.dtype), params)
    y = integrate(state, torque, params)
    next_state = jnp.stack([wrap_angle(y[0]), y[1]])
    noise = params.reward_noise_std * _random.normal(key, (), state.dtype)
    return next_state, reward_mean(next_state) + noise


class Trajectory(NamedTuple):
    """One episode. T = number of steps.

    Attributes:
      states: (T, 2) states s_t in which the actions were taken.
      actions: (T,) actions a_t before clipping.
      rewards: (T,) rewards r_t = R(s_{t+1}) + noise.
      final_state: (2,) s_T.
    """

    states: jax.Array
    actions: jax.Array
    rewards: jax.Array
    final_state: jax.Array


PolicyFn = Callable[[jax.Array, jax.Array], jax.Array]


def rollout(
    key: jax.Array,
    params: PendulumParams,
    policy_fn: PolicyFn,
    num_steps: int,
    start_state: jax.Array | None = None,
) -> Trajectory:
    """One episode of `num_steps` steps (a `lax.scan`); vmap over keys for a batch.

    Args:
      key: PRNG key (split into the start state, the actions and the reward noise).
      params: `PendulumParams`.
      policy_fn: (key, state) -> action.
      num_steps: static episode length.
      start_state: optional (2,) start state; drawn with `reset` when None.
    """
    key_reset, key_steps = jax.random.split(key)
    s0 = reset(key_reset, params) if start_state is None else jnp.asarray(start_state)

    def body(state, step_key):
        key_action, key_reward = jax.random.split(step_key)
        action = policy_fn(key_action, state)
        next_state, reward = step(key_reward, state, action, params)
        return next_state, (state, action, reward)

    final, (states, actions, rewards) = jax.lax.scan(
        body, s0, jax.random.split(key_steps, num_steps)
    )
    return Trajectory(states, actions, rewards, final)


def batch_rollout(keys, params, policy_fn, num_steps) -> Trajectory:
    """`rollout` vmapped over a (B,) batch of keys: every field gains a leading axis B."""
    return jax.vmap(rollout, in_axes=(0, None, None, None))(keys, params, policy_fn, num_steps)
