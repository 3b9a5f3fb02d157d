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
  OPTIMISTIC_REWARD  optimism about a learnt reward: a decision earns the reward output's upper
              confidence bound r(x) + beta sigma_r(x), sigma_r its epistemic (latent) standard
              deviation (GP-UCB's index, Srinivas et al. 2010, eq. 6, with beta for beta_t^1/2),
              the particles following the mean. Only where the reward is learnt
              (`ModelSettings.check` refuses it otherwise).
  OPTIMISTIC_JOINT  both: H-UCRL's hallucinated control over the dynamics and the learnt reward's
              upper confidence bound, with the one beta.
  INFORMATION an information bonus: each decision earns, beside the objective's reward,
              lambda sum_e sigma_e^2(x), the model's epistemic variance of the dynamics' outputs
              (the changes of the normalised observation, so in its units squared) at the
              decision's input, the particles following the mean: the paper's guided variance
              (the exploration noise's variance scaled by the GP's, eq. 16-19) made a planning
              objective, so that the controller is drawn to where the model knows least. Its
              weight lambda (`ModelSettings.information_weight`) is a schedule fixed before the
              runs: one constant per run, the decay over the updates being the variance's own
              as the data fill the state space. GP-UCB's beta_t (Srinivas et al. 2010, Theorems
              1-2) is not used: it needs a finite domain's size or the RKHS norm's bound and
              the domain's Lipschitz constants, none of which a task gives, and is known to be
              far too large in practice (their own experiments scale it down by 5).

`ModelSettings.exploration` names one (`USES`); the plan (`make_plan`) and the roll-out read what
the value declares (the plan's fields `variance`, `reward_bonus` and `information`, and the
hallucination's parameters), so a new use is a new `Uncertainty`.
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
      reward_optimism: whether a decision's learnt reward is its upper confidence bound
        r + beta sigma_r (`optimistic_outputs`); it needs a learnt reward.
      information: whether a decision earns the information bonus lambda sum_e sigma_e^2
        (`information_bonus`).
    """

    name: str
    functions: Callable
    transition_noise: bool = False
    hallucinates: bool = False
    reward_optimism: bool = False
    information: bool = False

    @property
    def reads_variance(self) -> bool:
        """Whether the roll-out reads the model's variance (`Plan.variance`)."""
        return self.hallucinates or self.reward_optimism or self.information


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
OPTIMISTIC_REWARD = Uncertainty("optimistic_reward", _mean, reward_optimism=True)
OPTIMISTIC_JOINT = Uncertainty("optimistic_joint", _mean, hallucinates=True, reward_optimism=True)
INFORMATION = Uncertainty("information", _mean, information=True)
USES: dict[str, Uncertainty] = {u.name: u for u in (MEAN, SAMPLE, THOMPSON, OPTIMISTIC,
                                                    OPTIMISTIC_REWARD, OPTIMISTIC_JOINT,
                                                    INFORMATION)}


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
      variance: `variance_factors` of the model (a use that reads the variance,
        `Uncertainty.reads_variance`; None otherwise).
      reward_bonus: () beta, the multiple of the learnt reward's epistemic standard deviation
        added to it (`Uncertainty.reward_optimism`; None otherwise).
      information: () lambda, the weight of the information bonus (`Uncertainty.information`;
        None otherwise).
    """

    start: jax.Array
    weights: jax.Array
    noise: jax.Array
    variance: tuple | None = None
    reward_bonus: jax.Array | None = None
    information: jax.Array | None = None


def epistemic_std(var):
    """sqrt(var) of a latent variance, its gradient 0 (not inf times 0) where var rounds to 0."""
    return jnp.sqrt(jnp.maximum(var, jnp.finfo(var.dtype).tiny))


def optimistic_outputs(outputs, var, num_dynamics: int, beta):
    """The model's outputs at an input with the learnt reward (the outputs after the
    `num_dynamics` dynamics' ones) raised to its upper confidence bound r + beta sigma_r; `var`
    (E,) the outputs' latent variances (`gp.fast_variance`)."""
    return outputs.at[num_dynamics:].add(beta * epistemic_std(var[num_dynamics:]))


def information_bonus(var, num_dynamics: int, weight):
    """lambda sum_e sigma_e^2 over the first `num_dynamics` outputs (the dynamics'; a learnt
    reward's variance does not count): `var` (E,) the latent variances (`gp.fast_variance`)."""
    return weight * jnp.sum(var[:num_dynamics])


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
    e, dtype = model.weights.shape[0], model.weights.dtype
    weights = use.functions(model, k_w, num_particles)
    shape = (num_particles, num_steps, e)
    noise = (jax.random.normal(k_n, shape, dtype) if use.transition_noise
             else jnp.zeros(shape, dtype))
    own = cfg.settings
    return Plan(start, weights, noise, variance_factors(model) if use.reads_variance else None,
                jnp.asarray(own.beta, dtype) if use.reward_optimism else None,
                jnp.asarray(own.information_weight, dtype) if use.information else None)
