"""The swing-up task: its success criterion, a reference controller that solves it, and a fit of
the policy class to that controller.

A swing-up must bring the pendulum from hanging down to upright and hold it there. With a torque
limit of 5 N m against m g l = 9.81 N m it needs several swings: the energy-pumping controller
(`energy_pumping_policy`) pushes along the angular velocity until the pendulum has the upright
state's energy, then a PD law balances it. It needs about 2.4 s from rest.

`success`: an episode succeeds if |phi - pi| < tolerance at every step of its last `hold_time`
seconds. The swing-up preset (`config.PRESETS["swingup"]`) was chosen so that the energy-pumping
controller succeeds from (nearly) every start state of the preset's distribution
(`success_rate`, tests/test_swingup.py), and `fit_controller` shows that the RBF policy
class can represent a swing-up: fitted to the energy-pumping controller by least squares, run
without noise, it succeeds as often.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax

from gpguided_jax import controllers as controllers_lib
from gpguided_jax import pendulum


def success(states: jax.Array, dt, *, tolerance: float = 0.3, hold_time: float = 1.0) -> jax.Array:
    """Whether one episode ends in a held swing-up: |phi_t - pi| < tolerance for every state of
    the last round(hold_time / dt) steps (phi wrapped to [0, 2 pi)).

    Args:
      states: (T, 2) states [phi, omega] of one episode (the state after each step).
      dt: control interval (s), a Python float.
      tolerance: rad.
      hold_time: s.

    Returns:
      () bool.
    """
    if states.ndim != 2 or states.shape[-1] != 2:
        raise ValueError(f"states must have shape (T, 2), got {states.shape}")
    n = hold_steps(dt, hold_time)
    if not 1 <= n <= states.shape[0]:
        raise ValueError(
            f"an episode of {states.shape[0]} steps is shorter than the hold time ({n} steps of {dt} s)"
        )
    phi = pendulum.wrap_angle(states[-n:, 0])
    return jnp.all(jnp.abs(phi - jnp.pi) < tolerance)


def hold_steps(dt, hold_time: float) -> int:
    """The number of control steps in `hold_time` seconds."""
    return int(round(float(hold_time) / float(dt)))


def energy_pumping_policy(params: pendulum.PendulumParams, *, near_top: float = 0.9,
                          kp: float = 20.0, kd: float = 4.0) -> Callable:
    """The reference swing-up controller, (key, state) -> torque (deterministic).

    Where cos(phi - pi) > near_top (within ~0.45 rad of upright) a PD law
    -kp (phi - pi) - kd omega balances the pendulum; elsewhere it pumps energy with the full torque
    along omega while the energy is below the upright state's (m g l), and brakes gently above it.
    """
    e_top = params.mass * params.gravity * params.length

    def policy(key, state):
        del key
        energy = pendulum.energy(state, params)
        balance = -kp * (state[0] - jnp.pi) - kd * state[1]
        pump = params.max_torque * jnp.sign(state[1] + 1e-3) * jnp.where(energy < e_top, 1.0, -0.2)
        return jnp.where(jnp.cos(state[0] - jnp.pi) > near_top, balance, pump)

    return policy


def success_flags(key, params: pendulum.PendulumParams, policy_fn: Callable, episode_length: int,
                  num_episodes: int, *, tolerance: float = 0.3, hold_time: float = 1.0) -> jax.Array:
    """(num_episodes,) bool: `success` of fresh episodes of `policy_fn` (key, state) -> torque,
    start states drawn from `params`."""
    traj = pendulum.batch_rollout(jax.random.split(key, num_episodes), params, policy_fn,
                                  episode_length)
    dt = float(np.asarray(params.dt))
    return jax.vmap(lambda s: success(s, dt, tolerance=tolerance, hold_time=hold_time))(traj.states)


def success_rate(key, params, policy_fn, episode_length: int, num_episodes: int, **success_kwargs
                 ) -> float:
    """Share of `success_flags` (compiled; `params` and `policy_fn` are closed over)."""
    run = jax.jit(lambda k: success_flags(k, params, policy_fn, episode_length, num_episodes,
                                          **success_kwargs))
    return float(jnp.mean(run(key)))


def fit_controller(controller: controllers_lib.Controller, params: pendulum.PendulumParams,
                   target: Callable, key, *, episode_length: int, num_episodes: int = 200,
                   action_noise: float = 1.0, steps: int = 1500, learning_rate: float = 0.05):
    """theta_c of `controller` fitted to the controller `target` by least squares.

    The states are those of `num_episodes` episodes of `target` with Gaussian action noise of
    std `action_noise` (so that the fit also sees states off the target's own path); the loss is
    the mean squared torque difference, u_max tanh(theta^T psi(s)) vs target(s) clipped to the
    limit, minimised by Adam from the linear least-squares fit of atanh(target / u_max).

    Returns:
      (theta_c, mean squared torque error).
    """
    def noisy(k, s):
        return target(k, s) + action_noise * jax.random.normal(k, (), s.dtype)

    traj = pendulum.batch_rollout(jax.random.split(key, num_episodes), params, noisy,
                                  episode_length)
    states = traj.states.reshape(-1, 2)
    u_max = controller.u_max
    u = jnp.clip(jax.vmap(lambda s: target(None, s))(states), -u_max, u_max)
    theta0 = controller.init(states.dtype)
    flat0, unravel = jax.flatten_util.ravel_pytree(theta0)
    psi = jax.vmap(lambda s: jax.flatten_util.ravel_pytree(controller.features(s))[0])(states)
    w0 = jnp.linalg.lstsq(psi, jnp.arctanh(jnp.clip(u / u_max, -0.95, 0.95)))[0]

    def loss(w):
        return jnp.mean((u_max * jnp.tanh(psi @ w) - u) ** 2)

    opt = optax.adam(learning_rate)

    def step(carry, _):
        w, st = carry
        value, grad = jax.value_and_grad(loss)(w)
        updates, st = opt.update(grad, st)
        return (optax.apply_updates(w, updates), st), value

    (w, _), _ = jax.jit(lambda w0: jax.lax.scan(step, (w0, opt.init(w0)), None, length=steps))(w0)
    del flat0
    return unravel(w), float(loss(w))
