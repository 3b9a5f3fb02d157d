"""The uses of gp_model's uncertainty in its simulated roll-outs, each a value (design:
docs/design.md#model):

  MEAN        every particle follows the posterior mean (the greedy, certainty-equivalent model);
  SAMPLE      each particle follows its own function drawn from the posterior, plus the learnt
              transition noise (uncertainty propagated through the roll-outs by sampling, as
              PILCO's moment matching propagates it analytically);
  THOMPSON    one function drawn per update, followed by every particle (posterior sampling);
  OPTIMISTIC  H-UCRL's hallucinated control (Curi et al. 2020): the next state is mu(x) +
              beta sigma(x) eta(z), eta in [-1, 1]^E a second controller optimised jointly with
              the policy to maximise the same return (optimism within the model's confidence).

`ModelSettings.exploration` names one (`USES`); the plan (`make_plan`) and the roll-out read what
the value declares, so a new use is a new `Uncertainty`.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from gpguided_jax.model_based.gp import SparseModel, sample_weights, variance_factors


class Uncertainty(NamedTuple):
    """One use of the model's uncertainty.

    Attributes:
      name: its name (`ModelSettings.exploration`).
      functions: `functions(model, key, num_particles) -> (P, E, M)`, the weights of each
        particle's function (f(x) = k(x, Z) . w).
      transition_noise: whether the particles draw the learnt transition noise at every step.
      hallucinates: whether a second controller eta moves the next state within beta sigma(x)
        (the roll-out then reads the model's variance, `variance_factors`).
    """

    name: str
    functions: Callable
    transition_noise: bool = False
    hallucinates: bool = False


def _mean(model: SparseModel, key, num_particles: int):
    del key
    return jnp.broadcast_to(model.weights, (num_particles,) + model.weights.shape)


def _each_its_own(model: SparseModel, key, num_particles: int):
    return sample_weights(model, key, (num_particles,))


def _one_for_all(model: SparseModel, key, num_particles: int):
    return jnp.broadcast_to(sample_weights(model, key), (num_particles,) + model.weights.shape)


MEAN = Uncertainty("mean", _mean)
SAMPLE = Uncertainty("sample", _each_its_own, transition_noise=True)
THOMPSON = Uncertainty("thompson", _one_for_all)
OPTIMISTIC = Uncertainty("optimistic", _mean, hallucinates=True)
USES: dict[str, Uncertainty] = {u.name: u for u in (MEAN, SAMPLE, THOMPSON, OPTIMISTIC)}


def get(use: str | Uncertainty) -> Uncertainty:
    """The `Uncertainty` named `use` (a value passes through); `ValueError` naming the choices."""
    if isinstance(use, Uncertainty):
        return use
    if use not in USES:
        raise ValueError(f"unknown use of the model's uncertainty {use!r}; choose from {tuple(USES)}")
    return USES[use]


class Plan(NamedTuple):
    """What one update's simulated roll-outs hold fixed (common random numbers).

    Attributes:
      start: (P, obs_dim) the particles' start observations.
      weights: (P, E, M) each particle's function (`Uncertainty.functions`).
      noise: (P, T, E) standard normals of the transition noise (zeros without it).
      variance: `variance_factors` of the model (a hallucinating use; None otherwise).
    """

    start: jax.Array
    weights: jax.Array
    noise: jax.Array
    variance: tuple | None = None


def make_plan(prog, cfg, model: SparseModel, key, use: str | Uncertainty, num_particles: int,
              num_steps: int, visited=None, num_visited: int = 0) -> Plan:
    """The particles' start states, functions and noise for one update's roll-outs under the use
    of the uncertainty `use`. The start states are draws from the task's start distribution
    (`Task.reset`), but for the last `num_visited` particles, which start from observations the
    real episodes visited: `visited` = (obs (C, obs_dim), valid (C,)), drawn uniformly among the
    valid rows."""
    use = get(use)
    task = prog.task
    k_start, k_w, k_n = jax.random.split(key, 3)
    start = jax.vmap(lambda k: task.reset(k, cfg)[1])(jax.random.split(k_start, num_particles))
    if num_visited:
        obs, valid = visited
        p = valid.astype(obs.dtype)
        rows = jax.random.choice(jax.random.fold_in(k_start, 1), obs.shape[0], (num_visited,),
                                 p=p / jnp.maximum(jnp.sum(p), 1.0))
        # before any data (no valid row), every particle starts from the start distribution
        seen = jnp.where(jnp.any(valid), obs[rows], start[num_particles - num_visited:])
        start = start.at[num_particles - num_visited:].set(seen)
    e = model.weights.shape[0]
    weights = use.functions(model, k_w, num_particles)
    shape = (num_particles, num_steps, e)
    noise = (jax.random.normal(k_n, shape, model.weights.dtype) if use.transition_noise
             else jnp.zeros(shape, model.weights.dtype))
    return Plan(start, weights, noise, variance_factors(model) if use.hallucinates else None)
