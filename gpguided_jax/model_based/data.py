"""gp_model's data: the transitions it takes in from the real episodes, as the GP's inputs and
targets, in a fixed-size ring buffer (design: docs/design.md#model).

One GP per coordinate e of the normalised observation z models its change, Delta z_e = z'_e -
z_e (an angle's change taken modulo one turn), on the input (z, a) (`Task.features`); with
`hold_time` > 0 a transition is one decision of `prog.hold` control steps (`decisions`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gpguided_jax import hyperfit


class ModelData(NamedTuple):
    """The transitions the model is conditioned on, in a ring buffer of C slots.

    Attributes:
      inputs: (C, D) GP inputs (z, a).
      targets: (C, E) changes of the normalised observation (and, for a learnt reward, a last
        column: the decision's reward).
      valid: (C,) bool, the slots that hold a transition before its episode's end.
      count: () int32, transitions written so far (the next slot is count mod C).
      log_kernels: `hyperfit.LogParams` with a leading (E,) axis (one per column of `targets`): the
        current kernels, in logs.
      hallucination: (obs_dim,) controller parameters of the optimistic exploration's eta (zeros
        for the other choices).
      observations: (C, obs_dim) the observations the decisions were taken in (the plan's
        particles may start from them).
    """

    inputs: jax.Array
    targets: jax.Array
    valid: jax.Array
    count: jax.Array
    log_kernels: hyperfit.LogParams
    hallucination: object
    observations: jax.Array


def wrap(x):
    """An angle difference wrapped to [-pi, pi)."""
    return jnp.mod(x + jnp.pi, 2.0 * jnp.pi) - jnp.pi



def targets_of(task, obs, next_obs):
    """Delta z = (next_obs - obs) / scale, the angles' differences wrapped to [-pi, pi)."""
    d = next_obs - obs
    if task.angles:
        idx = jnp.asarray(task.angles)
        d = d.at[..., idx].set(wrap(d[..., idx]))
    return d / jnp.asarray(task.obs_scale, obs.dtype)



def next_of(task, obs, delta):
    """The observation after a change Delta z (the inverse of `targets_of`): angles wrapped the
    way the task wraps them ([0, 2 pi) for the paper's pendulum)."""
    nxt = obs + delta * jnp.asarray(task.obs_scale, obs.dtype)
    if task.angles:
        idx = jnp.asarray(task.angles)
        nxt = nxt.at[..., idx].set(jnp.mod(nxt[..., idx], 2.0 * jnp.pi))
    return nxt



def decision_rewards(hold: int, rewards):
    """(N, T) rewards summed over each decision of `hold` control steps: (N, T // hold) (a last,
    incomplete hold dropped, as `decisions` drops it)."""
    n, t = rewards.shape
    k = t // hold
    return jnp.sum(rewards[:, : k * hold].reshape(n, k, hold), axis=-1)



def decisions(hold: int, obs, next_obs, actions, alive=None, ends=None):
    """The transitions the model takes in from a batch of episodes (N, T, ...): one per decision
    of `hold` control steps, from the observation the action was chosen in to the one at the end
    of its hold (a last, incomplete hold is dropped). Returns (obs, next_obs, actions, valid),
    `valid` (N, T // hold) False for a decision not taken wholly before its episode's end, or
    (restarted episodes, `ends`) one across an end, whose next observation is another episode's."""
    n, t = actions.shape[:2]
    k = t // hold
    valid = jnp.ones((n, t), bool) if alive is None else alive
    if ends is not None:  # a restarted episode's last step leads to the next one's start
        valid = valid & ~ends
    if hold == 1:
        return obs, next_obs, actions, valid
    first = lambda v: v[:, : k * hold: hold]  # noqa: E731
    blocks = lambda v: v[:, : k * hold].reshape((n, k, hold) + v.shape[2:])  # noqa: E731
    return (first(obs), blocks(next_obs)[:, :, -1], first(actions),
            jnp.all(blocks(valid), axis=2))



def empty_data(capacity: int, input_dim: int, output_dim: int, dtype, hallucination,
               obs_dim: int = 0) -> ModelData:
    log_k = hyperfit.LogParams(jnp.zeros((output_dim, input_dim), dtype),
                               jnp.zeros((output_dim,), dtype), jnp.full((output_dim,), -4.0, dtype))
    return ModelData(jnp.zeros((capacity, input_dim), dtype), jnp.zeros((capacity, output_dim), dtype),
                     jnp.zeros((capacity,), bool), jnp.zeros((), jnp.int32), log_k, hallucination,
                     jnp.zeros((capacity, obs_dim), dtype))



def take_in(data: ModelData, inputs, targets, valid, observations=None) -> ModelData:
    """Writes (n, D) inputs, (n, E) targets, (n,) valid flags and (n, obs_dim) observations (if
    given) into the ring buffer (the oldest slots first once it is full)."""
    capacity = data.inputs.shape[0]
    slots = (data.count + jnp.arange(inputs.shape[0])) % capacity
    obs = data.observations
    if observations is not None and obs.shape[-1]:
        obs = obs.at[slots].set(observations)
    return data._replace(inputs=data.inputs.at[slots].set(inputs),
                         targets=data.targets.at[slots].set(targets),
                         valid=data.valid.at[slots].set(valid),
                         count=data.count + inputs.shape[0], observations=obs)



def subset(key, valid, n: int):
    """n indices of valid slots, without repetition while there are n of them (then with)."""
    p = valid.astype(jnp.float32)
    enough = jnp.sum(p) >= n
    scores = jnp.where(valid, jax.random.uniform(key, valid.shape), -1.0)
    without = jnp.argsort(-scores)[:n]
    with_ = jax.random.choice(key, valid.shape[0], (n,), replace=True, p=p / jnp.maximum(jnp.sum(p), 1.0))
    return jnp.where(enough, without, with_)
