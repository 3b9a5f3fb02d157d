"""gp_mpc: a planner that acts through gp_model's GP model (design: docs/design.md#model).

gp_model acts with a controller optimised once per update; gp_mpc plans again at every decision
of the real episodes, from the real observation, through the model the last update built: model
predictive control with a learnt GP model (GP-MPC, Kamthe & Deisenroth, AISTATS 2018), its
open-loop problem solved by sampling action sequences of `mpc_horizon` seconds
(`planner_steps` decisions) with one of `SEQUENCE_OPTIMISERS` (`mpc_planner`):

  CEM   the cross-entropy method (Rubinstein 1999; as PETS, Chua et al. 2018, plans):
        `mpc_samples` sequences drawn from a diagonal Gaussian, clipped to the action bound; the
        `mpc_elites` with the highest returns refit its mean and standard deviation; after
        `mpc_iterations` iterations the plan is its mean;
  MPPI  model predictive path integral control (Williams et al., ICRA 2017, Algorithm 2's
        update): the sequences weighed by exp(R / lambda), lambda = `mpc_temperature` (in units
        of the return), their weighted mean the next iteration's centre; the sampling standard
        deviation stays `mpc_init_std` u_max.

The return of a sequence is the planning objective's (`objectives`: the task's stated reward or a
learnt one) summed along the model's posterior mean (certainty-equivalent: the planner does not
use the model's uncertainty), each decision's reward weighed by the probability of being alive,
the task's end smoothed as in gp_model's roll-outs (`model_end_softness`). Every iteration also
evaluates two warm-start sequences: the learnt controller's actions along its own roll-out
through the model (gp_model's controller, still optimised by every update), and the previous
decision's plan shifted by one decision (its last action repeated), carried from decision to
decision in the policy's memory (`policies.Policy.memory`). The sampling starts from the shifted
plan, or from the controller's actions at an episode's first decision. The action taken is the
plan's first, plus the fixed-noise policy's Gaussian noise, exp(log_std): `min_std` after the
first update (`actor.LEARNT_CONTROLLER`'s `act_with`).

When the model takes data in: once per update, as gp_model's does (`method.update`: take in,
refit, condition, optimise the controller). The planner plans through the model conditioned on
the data of the updates before; the transitions of the episode it acts in enter the model only
at the end of the update. The model is rebuilt from the method's state (`ModelData`) once per
update, before its episodes (`context`, the method's `Method.context`), the same model the last
update built. Before the model has any data (the first update's episodes) the policy acts with
the controller and the initial exploration noise, as gp_model does.

Cost per decision: (`mpc_samples` + 2) x `mpc_iterations` + 1 sequences of `planner_steps`
model steps, each step one kernel row k(x, Z) per output (E x M kernel evaluations), all in one
compiled program; docs/model_based.md gives the measured time.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import chex
import jax
import jax.numpy as jnp

from gpguided_jax import _random, config, exploration, methods, policies
from gpguided_jax import settings as settings_lib
from gpguided_jax.model_based import objectives
from gpguided_jax.model_based.actor import LEARNT_CONTROLLER, Actor
from gpguided_jax.model_based.data import next_of
from gpguided_jax.model_based.gp import SparseModel, build, k_star
from gpguided_jax.model_based.method import ModelSettings, make_method

POLICY = "gp_mpc_planner"  # the planner's roll-out policy name (`policies.register`)


# ------------------------------------------------------------------------------------------------
# The sequence optimisers: one decision's open-loop problem, max_u R(u) over (T,) sequences.
# ------------------------------------------------------------------------------------------------


class Planned(NamedTuple):
    """A sequence optimiser's result.

    Attributes:
      actions: (T,) the plan: the sampling distribution's mean after the last iteration.
      std: (T,) its standard deviation then (CEM: the last elites'; MPPI: the fixed one).
    """

    actions: jax.Array
    std: jax.Array


def _candidates(key, mean, std, warm, samples: int, low, high, colour):
    """(samples + W, T): Gaussian draws about `mean` (standard normals coloured along the
    sequence by the (T, T) Cholesky factor `colour` of their correlation, or white for None),
    clipped to [low, high], then `warm`."""
    eps = _random.normal(key, (samples,) + mean.shape, mean.dtype)
    if colour is not None:
        eps = eps @ jnp.asarray(colour, mean.dtype).T
    return jnp.concatenate([jnp.clip(mean + std * eps, low, high), warm], axis=0)


def _scores(returns, candidates):
    """The candidates' returns, a non-finite one as -inf (never chosen, never weighed)."""
    r = jax.vmap(returns)(candidates)
    return jnp.where(jnp.isfinite(r), r, -jnp.inf)


def cem(key, returns: Callable, mean, std, warm, *, samples: int, iterations: int, elites: int,
        low, high, colour=None) -> Planned:
    """The cross-entropy method on `returns(u) -> ()` over (T,) sequences u: each of `iterations`
    iterations draws `samples` sequences from N(mean, diag std^2) (coloured by `colour`, iCEM's
    correlated draws; clipped to [low, high]), adds the (W, T) `warm` sequences, and refits mean
    and std to the `elites` with the highest returns. Returns the last mean and std."""
    chex.assert_rank([mean, std, warm], [1, 1, 2])

    def iteration(carry, k):
        mean, std = carry
        cand = _candidates(k, mean, std, warm, samples, low, high, colour)
        _, best = jax.lax.top_k(_scores(returns, cand), elites)
        chosen = cand[best]
        return (jnp.mean(chosen, axis=0), jnp.std(chosen, axis=0)), None

    (mean, std), _ = jax.lax.scan(iteration, (mean, std), jax.random.split(key, iterations))
    return Planned(mean, std)


def mppi(key, returns: Callable, mean, std, warm, *, samples: int, iterations: int, temperature,
         low, high, colour=None) -> Planned:
    """MPPI's update (Williams et al. 2017) on `returns(u) -> ()` over (T,) sequences u: each of
    `iterations` iterations draws `samples` sequences from N(mean, diag std^2) (coloured by
    `colour`; clipped to [low, high]), adds the (W, T) `warm` sequences, and moves the mean to
    their average weighed by exp(R / temperature). The std is fixed. Returns the last mean and
    the std.

    Without clipping or warm sequences, on R(u) = -(u - u*)^T H (u - u*) the update's expectation
    over infinitely many samples is u* + (I + 2 std^2 H / temperature)^-1 (mean - u*) (the product
    of the Gaussian and the weight; tests/test_planner.py holds the planner against it)."""
    chex.assert_rank([mean, std, warm], [1, 1, 2])

    def iteration(mean, k):
        cand = _candidates(k, mean, std, warm, samples, low, high, colour)
        w = jax.nn.softmax(_scores(returns, cand) / temperature)
        return w @ cand, None

    mean, _ = jax.lax.scan(iteration, mean, jax.random.split(key, iterations))
    return Planned(mean, std)


class SequenceOptimiser(NamedTuple):
    """A planner's optimiser of one decision's action sequence (`PlannerSettings.planner`).

    Attributes:
      name: its name.
      run: `run(key, returns, mean, std, warm, *, samples, iterations, elites, temperature, low,
        high, colour) -> Planned` (`cem`'s and `mppi`'s arguments; each ignores the other's).
    """

    name: str
    run: Callable


CEM = SequenceOptimiser("cem", lambda *args, temperature, **kw: cem(*args, **kw))
MPPI = SequenceOptimiser("mppi", lambda *args, elites, **kw: mppi(*args, **kw))
SEQUENCE_OPTIMISERS: dict[str, SequenceOptimiser] = {p.name: p for p in (CEM, MPPI)}


# ------------------------------------------------------------------------------------------------
# The model's mean roll-out of one sequence.
# ------------------------------------------------------------------------------------------------


def mean_step(task, model: SparseModel, target_mean, obs, action):
    """One decision through the model's posterior mean: (next observation, the model's outputs
    (E,), the learnt reward last where there is one)."""
    out = jnp.sum(k_star(model, task.features(obs, action)) * model.weights, axis=-1) + target_mean
    return next_of(task, obs, out[:task.obs_dim]), out


def gp_mean_step(prog, ctx, obs, action):
    """The planner's model step (`make_policy`'s default): the GP the last update built, its mean
    (`mean_step` with the context's model)."""
    return mean_step(prog.task, ctx.model, ctx.target_mean, obs, action)


def _end_probability(task, nxt, end_softness):
    """gp_model's smoothed end (`rollout.simulate`): sigmoid(margin / softness), or the hard end."""
    if task.end_margin is not None:
        return jax.nn.sigmoid(task.end_margin(nxt) / end_softness)
    return task.end_fn(nxt).astype(nxt.dtype)


def sequence_return(prog, objective: objectives.Objective, step: Callable, obs, actions,
                    end_softness):
    """The return of the (T,) decisions `actions` from `obs` through the model `step(obs, action)
    -> (next_obs, outputs)`: the objective's rewards summed undiscounted, each weighed by the
    probability of being alive (a task with an end; `rollout.simulate`'s rule)."""
    task = prog.task

    def one(carry, a):
        obs, alive = carry
        nxt, out = step(obs, a)
        if task.end_fn is None:
            return (nxt, alive), objective.reward(task, prog.hold, obs, a, nxt, None, out)
        p_end = _end_probability(task, nxt, end_softness)
        r = objective.reward(task, prog.hold, obs, a, nxt, p_end, out)
        return (nxt, alive * (1.0 - p_end)), alive * r

    _, rewards = jax.lax.scan(one, (obs, jnp.ones((), obs.dtype)), actions)
    return jnp.sum(rewards)


def controller_actions(prog, step: Callable, obs, controller_params, num_steps: int):
    """(num_steps,) the controller's actions along its own roll-out through the model `step`."""
    def one(obs, _):
        a = prog.controller.apply(controller_params, obs)
        return step(obs, a)[0], a

    return jax.lax.scan(one, obs, None, length=num_steps)[1]


# ------------------------------------------------------------------------------------------------
# The settings, the policy's context and memory, the policy.
# ------------------------------------------------------------------------------------------------


@settings_lib.declare(
    static=ModelSettings.STATIC + ("samples", "iterations", "elites", "plan_horizon", "planner",
                                   "noise_exponent"),
    prefix="mpc_",
    aliases={**{flat: f for f, flat in ModelSettings.FLAT.items()}, "mpc_horizon": "plan_horizon"})
class PlannerSettings(ModelSettings):
    """gp_mpc's settings: gp_model's (`ModelSettings`, flat names `model_<field>`: the model, its
    refit, and the controller optimised by every update, which warm-starts the planner) and the
    planner's own (flat names `mpc_<field>`; the horizon's is `mpc_horizon`).

    Static:
      samples: sequences drawn per iteration (two warm-start sequences besides).
      iterations: the sequence optimiser's iterations per decision.
      elites: CEM's elites (at most `samples`).
      plan_horizon: the planning horizon, seconds (`planner_steps` decisions).
      planner: the sequence optimiser (`SEQUENCE_OPTIMISERS`: 'cem', 'mppi').
      noise_exponent: beta of the draws' power spectrum along the sequence, S(f) ~ f^-beta
        (`exploration.make_noise`'s 'coloured'; iCEM, Pinneri et al. 2020): 0 white, 2 red,
        smoother sequences.

    Traced:
      temperature: MPPI's lambda, in units of the return.
      init_std: the sampling standard deviation at a decision's start, as a fraction of the action
        bound (MPPI's throughout).
    """

    samples: int = 64
    iterations: int = 3
    elites: int = 8
    plan_horizon: float = 0.5
    planner: str = "cem"
    noise_exponent: float = 0.0
    temperature: Any = 1.0
    init_std: Any = 0.5

    def check(self, cfg) -> None:
        """gp_model's checks, then the planner's (`settings.SettingError` naming the setting)."""
        super().check(cfg)
        flat = type(self).FLAT
        settings_lib.choice(flat["planner"], self.planner, tuple(SEQUENCE_OPTIMISERS), "planner")
        for f in ("samples", "iterations", "elites"):
            settings_lib.integer(flat[f], getattr(self, f), 1)
        if self.elites > self.samples:
            settings_lib.fail(flat["elites"], f"must be at most {flat['samples']} "
                              f"({self.samples}), got {self.elites}")
        settings_lib.seconds(flat["plan_horizon"], self.plan_horizon)
        settings_lib.number(flat["noise_exponent"], self.noise_exponent, lambda v: 0 <= v <= 3,
                            "in [0, 3]")
        settings_lib.traced(flat["temperature"], self.temperature, positive=True)
        settings_lib.traced(flat["init_std"], self.init_std, positive=True)


def planner_steps(prog, cfg) -> int:
    """The planning horizon's decisions: `mpc_horizon` seconds in decisions of `prog.hold`
    control intervals (as `method.plan_steps` converts gp_model's)."""
    dt = config.control_interval(prog.config) * prog.hold
    return max(1, int(round(cfg.settings.plan_horizon / dt)))


class PlannerContext(NamedTuple):
    """What the planner reads in an update's episodes (`context`).

    Attributes:
      model: the `SparseModel` the last update built.
      target_mean: (E,) the outputs' data means.
      ready: () bool, whether the model has data (False on the first update: the controller acts).
      temperature, init_std, end_softness: () the traced settings.
    """

    model: SparseModel
    target_mean: jax.Array
    ready: jax.Array
    temperature: jax.Array
    init_std: jax.Array
    end_softness: jax.Array


class PlanMemory(NamedTuple):
    """The planner's memory across an episode's decisions.

    Attributes:
      plan: (T,) the previous decision's plan.
      started: () bool, False before the episode's first decision.
    """

    plan: jax.Array
    started: jax.Array


def context(prog, cfg, state) -> PlannerContext:
    """gp_mpc's `Method.context`: the model conditioned on the method's state (`ModelData`) as the
    last update left it, built once for the update's episodes."""
    own, data = cfg.settings, state.method_state
    model, target_mean = build(data, own.inducing)
    return PlannerContext(model, target_mean, jnp.any(data.valid), own.temperature, own.init_std,
                          own.end_softness)


def plan(prog, key, controller_params, obs, ctx: PlannerContext, memory: PlanMemory,
         model_step: Callable = gp_mean_step) -> Planned:
    """One decision's plan from `obs` (module notes): the sequence optimiser of the settings,
    warm-started by the controller's actions and the previous plan shifted by one decision,
    through `model_step(prog, ctx, obs, action) -> (next_obs, outputs)`."""
    own, task = prog.config.settings, prog.task
    objective = objectives.for_task(task, own.reward)
    num_steps = memory.plan.shape[0]
    step = lambda o, a: model_step(prog, ctx, o, a)  # noqa: E731
    ctrl = controller_actions(prog, step, obs, controller_params, num_steps)
    shifted = jnp.concatenate([memory.plan[1:], memory.plan[-1:]])
    mean = jnp.where(memory.started, shifted, ctrl)
    u_max = jnp.asarray(task.max_action, obs.dtype)
    std = jnp.full((num_steps,), ctx.init_std * u_max, obs.dtype)

    def returns(actions):
        return sequence_return(prog, objective, step, obs, actions, ctx.end_softness)

    colour = None if own.noise_exponent == 0 else exploration.make_noise(
        "coloured", num_steps, 1.0, exponent=own.noise_exponent).cholesky
    return SEQUENCE_OPTIMISERS[own.planner].run(
        key, returns, mean, std, jnp.stack([ctrl, shifted]), samples=own.samples,
        iterations=own.iterations, elites=own.elites, temperature=ctx.temperature, low=-u_max,
        high=u_max, colour=colour)


def make_policy(prog, model_step: Callable = gp_mean_step) -> policies.Policy:
    """The planner as a roll-out policy of `prog` (`policies.register`): its action is the plan's
    first plus N(0, exp(log_std)^2) noise (the controller's action before the model has data,
    `ctx.ready`); its score is 0 (gp_mpc's update reads none) and its density is not defined.
    `model_step(prog, ctx, obs, action) -> (next_obs, outputs)`: the model it plans through
    (gp_mpc's: the GP's mean, `gp_mean_step`; a test's: the true dynamics)."""
    controller = prog.controller
    num_steps = planner_steps(prog, prog.config)

    def memory(theta, ctx):
        del ctx
        dtype = theta.log_std.dtype
        return PlanMemory(jnp.zeros((num_steps,), dtype), jnp.zeros((), bool))

    def act(key, theta, state, ctx, mem):
        chex.assert_rank(state, 1)
        # the noise drawn from `key` as the fixed-noise policy draws it: before the model has data
        # the planner acts as gp_model's policy does, draw for draw
        planned = plan(prog, jax.random.fold_in(key, 1), theta.controller, state, ctx, mem,
                       model_step)
        mean_action = jnp.where(ctx.ready, planned.actions[0],
                                controller.apply(theta.controller, state))
        std = jnp.exp(theta.log_std)
        action = mean_action + std * _random.normal(key, (), state.dtype)
        empty = jnp.zeros((0,), state.dtype)
        aux = policies.PolicyAux(mean_action, std * std, empty, empty, empty,
                                 jnp.zeros((), jnp.int32))
        score = jax.tree_util.tree_map(jnp.zeros_like, theta)
        return action, aux, score, std, PlanMemory(planned.actions, jnp.ones((), bool))

    def sample(key, theta, state, ctx):
        return act(key, theta, state, ctx, memory(theta, ctx))[:2]

    def no_density(*args):
        raise NotImplementedError("the planner's action has no density in closed form (its "
                                  "score is 0: gp_mpc's update reads none)")

    def exploration_std(theta, state, ctx, aux):
        del state, ctx, aux
        return jnp.exp(theta.log_std)

    return policies.Policy(sample, no_density, no_density, exploration_std, act, POLICY,
                           reads_gp=False, memory=memory)


PLANNER = Actor(POLICY, LEARNT_CONTROLLER.act_with)
"""gp_mpc's actor: the planner acts; the update leaves it the optimised controller (its warm start)
and the noise floor `min_std`, as gp_model's actor does."""

policies.register(POLICY, make_policy)
METHOD = methods.register(make_method(
    "gp_mpc", actor=PLANNER, settings=PlannerSettings, context=context, explorations=("white",),
    explain_exploration="gp_mpc's planner acts with white noise about its plan's first action",
    compare_with=("gp_model",)))
