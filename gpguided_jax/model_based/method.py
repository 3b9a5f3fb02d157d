"""gp_model: the GP as a model of the task, the controller optimised through simulated roll-outs,
declared as a `methods.Method` with its own settings (design: docs/design.md#model).

Each update of Algorithm 1's loop (steps 1-2 roll out the episodes with the current controller
and the exploration noise, as for every method) then does three things:

1. **The model takes the transitions in** (`data`): one per decision, into a ring buffer of
   `capacity`, with a mask for the slots not yet written and for the steps after an episode's end.
2. **The hyperparameters are refitted** (`gp.refit`) on a random subset of `fit_subset` buffered
   transitions, `fit_steps` Adam steps warm-started from the previous update's kernels, and the
   model is conditioned on the buffer (`gp.build`).
3. **The controller is optimised through the model** (`optimise`): `steps` steps of the optimiser
   on the mean return of `particles` simulated roll-outs (`rollout.simulate`) of `horizon`
   seconds from the task's own start distribution (`Task.reset`), with the planning objective
   (`objectives`: the task's stated reward or a learnt one) and the task's end where it has one
   (`Task.end_fn`). The gradient is the reparameterised one through the roll-outs (autodiff),
   with common random numbers: the particles' start states and the model's samples are drawn
   once per update (`uncertainty.make_plan`, under the settings' use of the uncertainty).

The actor (`actor.LEARNT_CONTROLLER`) then acts with the optimised controller in the next
update's episodes. `make_method` declares the method with another actor (a planner that acts),
under another name, sharing these settings.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gpguided_jax import config, exploration, hyperfit, methods, rollouts, tasks
from gpguided_jax import settings as settings_lib
from gpguided_jax.model_based import objectives, uncertainty
from gpguided_jax.model_based.actor import LEARNT_CONTROLLER, Actor
from gpguided_jax.model_based.data import (
    ModelData,
    decision_rewards,
    decisions,
    empty_data,
    take_in,
    targets_of,
)
from gpguided_jax.model_based.gp import build, predict, refit
from gpguided_jax.model_based.optimise import OPTIMISERS, optimise
from gpguided_jax.model_based.rollout import simulate

RECORDS = ("model_return", "model_gain", "model_error", "model_reward_error", "model_std",
           "model_lengthscale_action", "model_data")


@settings_lib.declare(static=("capacity", "inducing", "fit_subset", "fit_steps", "particles",
                              "steps", "horizon", "exploration", "optimizer", "reward",
                              "visited_starts", "fresh_draws", "keep_best", "restarts",
                              "held_aside"),
                      prefix="model_")
class ModelSettings:
    """gp_model's own settings (flat names `model_<field>`).

    Static:
      capacity: transitions kept in the ring buffer (at most the run's decisions).
      inducing: inducing inputs of each output's sparse GP.
      fit_subset: the refit's random subset of the buffer.
      fit_steps: the refit's Adam steps per update.
      particles: simulated particles per update.
      steps: optimiser steps on the simulated return per update.
      horizon: the simulated roll-outs' horizon, seconds.
      exploration: the use of the model's uncertainty in them (`uncertainty.USES`: 'mean',
        'sample', 'thompson', 'optimistic', 'optimistic_reward', 'optimistic_joint',
        'information'; the two optimistic about the reward need it learnt).
      optimizer: the controller's optimiser (`optimise.OPTIMISERS`: 'adam', 'lbfgs').
      visited_starts: the share of the particles that start from observations the real episodes
        visited (drawn from the buffer), the others from the task's start distribution.
      fresh_draws: a new plan (start states, functions, noise) at every optimiser step, where
        False fixes one per update (common random numbers).
      keep_best: keep the iterate with the best simulated return seen (early stopping), not the
        last.
      restarts: controllers optimised per update: the current one and `restarts - 1` others
        (the initial controller perturbed by N(0, `RESTART_SCALE`^2) per parameter); the best by
        simulated return on the held-aside particles is kept.
      held_aside: particles of another plan on which the restarts are compared (0: the plan
        they were optimised on).
      reward: the planning objective (`objectives.OBJECTIVES`): 'stated' (the task's
        `reward_fn`), 'learned' (one more GP output, learnt with the dynamics), 'survival' (the
        log-probability of not meeting the task's end), 'saturating' (PILCO's saturating cost on
        the task's target), or 'auto' (stated where the task states it, learned otherwise).

    Traced:
      learning_rate: Adam's step size on the simulated return.
      final_rate: the step size's cosine decay over the steps, to this fraction of the first
        (1: constant; Adam only).
      beta: the confidence multiple of the hallucinated control ('optimistic',
        'optimistic_joint') and of the learnt reward's upper confidence bound
        ('optimistic_reward', 'optimistic_joint').
      information_weight: lambda, the weight of the information bonus lambda sum_e sigma_e^2
        ('information'; the dynamics' epistemic variance in the normalised observation's units
        squared), constant over a run (`uncertainty` module notes).
      end_softness: the smoothing of a task's end in the simulated roll-outs (the temperature of
        the end's probability, in units of the observation's normalisation scale).
    """

    capacity: int = 4000
    inducing: int = 200
    fit_subset: int = 300
    fit_steps: int = 50
    particles: int = 16
    steps: int = 100
    horizon: float = 4.0
    exploration: str = "mean"
    optimizer: str = "adam"
    reward: str = "auto"
    visited_starts: float = 0.0
    fresh_draws: bool = False
    keep_best: bool = False
    restarts: int = 1
    held_aside: int = 0
    learning_rate: Any = 0.01
    final_rate: Any = 1.0
    beta: Any = 1.0
    end_softness: Any = 0.1
    information_weight: Any = 1.0

    def check(self, cfg) -> None:
        """Raises `settings.SettingError` naming the first setting that makes no sense."""
        flat = type(self).FLAT
        for f, choices, what in (("exploration", tuple(uncertainty.USES), "model exploration"),
                                 ("optimizer", tuple(OPTIMISERS), "model optimiser"),
                                 ("reward", objectives.names(), "model reward")):
            settings_lib.choice(flat[f], getattr(self, f), choices, what)
        for f in ("capacity", "inducing", "fit_subset", "fit_steps", "particles", "steps",
                  "restarts"):
            settings_lib.integer(flat[f], getattr(self, f), 1)
        settings_lib.integer(flat["held_aside"], self.held_aside, 0)
        for f in ("fresh_draws", "keep_best"):
            if not isinstance(getattr(self, f), bool):
                settings_lib.fail(flat[f], f"must be true or false, got {getattr(self, f)!r}")
        if not (isinstance(self.visited_starts, (int, float)) and 0 <= self.visited_starts < 1):
            settings_lib.fail(flat["visited_starts"], f"must be a share in [0, 1), got "
                              f"{self.visited_starts!r}")
        settings_lib.traced(flat["final_rate"], self.final_rate, positive=True)
        settings_lib.seconds(flat["horizon"], self.horizon)
        settings_lib.traced(flat["learning_rate"], self.learning_rate, positive=True)
        settings_lib.traced(flat["end_softness"], self.end_softness, positive=True)
        settings_lib.traced(flat["beta"], self.beta, non_negative=True)
        settings_lib.traced(flat["information_weight"], self.information_weight,
                            non_negative=True)
        task = tasks.make_task(cfg.env)
        objective = objectives.for_task(task, self.reward)
        if uncertainty.get(self.exploration).reward_optimism and not objective.learned:
            settings_lib.fail(flat["exploration"], f"{self.exploration!r} is optimistic about a "
                              f"learnt reward, and {cfg.env} plans with {objective.name!r}: set "
                              "model_reward='learned'")
        lacks = objectives.missing(task, objective)
        if lacks is not None:
            hint = "; 'learned' or 'auto' learns the reward" if objective is objectives.STATED else ""
            settings_lib.fail(flat["reward"], f"{self.reward!r} plans with what {cfg.env} does "
                              f"not declare: {lacks}{hint}")


# The settings gp_model was tuned to, per preset (`Method.presets`): experiments/model_study.py,
# its budget in updates of one episode, its base settings and tuned ones (docs/model_based.md).
PRESETS = {
    # 10 episodes, decisions held 0.1 s
    "swingup": {"episodes_per_update": 1, "hold_time": 0.1, "init_log_std": math.log(2.0),
                "min_std": 0.05, "eval_episodes": 10, "model_horizon": 6.0, "num_updates": 11,
                "model_exploration": "thompson"},
    # 2,000 steps; the planning study's linear plus RBF controller, particles half from visited
    # starts, fresh draws at every step, and its cost stage's model and particles (the least
    # wall time to the threshold)
    "pendulum-v1": {"episodes_per_update": 1, "num_updates": 11, "init_log_std": 0.0,
                    "min_std": 0.05, "eval_episodes": 10, "model_exploration": "thompson",
                    "model_horizon": 2.0, "model_learning_rate": 0.03, "model_steps": 200,
                    "model_inducing": 100, "controller": "linear_rbf", "model_particles": 16,
                    "model_visited_starts": 0.5, "model_fresh_draws": True},
    # 10 episodes, decisions held 5 steps; the planning study's trainable RBF network, particles
    # half from visited starts and the longer search
    "mountaincar-continuous": {"episodes_per_update": 1, "hold_time": 5.0, "init_log_std": 0.0,
                               "min_std": 0.05, "eval_episodes": 5, "model_horizon": 200.0,
                               "model_end_softness": 1.0, "num_updates": 11,
                               "model_exploration": "thompson", "controller": "rbf_trainable",
                               "model_particles": 64, "model_visited_starts": 0.5,
                               "model_steps": 200, "model_final_rate": 0.1,
                               "model_keep_best": True},
    # restarted episodes, 6,000 steps
    "inverted-pendulum": {"episodes_per_update": 1, "num_updates": 7, "episode_end": "restart",
                          "init_log_std": math.log(0.5), "min_std": 0.05, "eval_episodes": 5,
                          "model_capacity": 3000, "model_horizon": 4.0,
                          "model_exploration": "sample"},
    # 6,000 steps
    "inverted-double-pendulum": {"episodes_per_update": 1, "num_updates": 7,
                                 "episode_end": "restart", "init_log_std": math.log(0.5),
                                 "min_std": 0.05, "eval_episodes": 5, "model_capacity": 3000,
                                 "model_horizon": 4.0, "model_exploration": "optimistic"},
}


# The presets of experiments/exploration_uses_study.py: the car and the swing-up with the reward
# learnt (the config presets set `model_reward`), the sparse swing-up at each action cost.
PRESETS.update({
    # the study's settings (the model study's tuned ones, before the planning parts) and the use
    # with the best score on its tuning seeds (`exploration_uses_study.preset_choice`)
    "mountaincar-continuous-learned": {"episodes_per_update": 1, "hold_time": 5.0,
                                       "init_log_std": 0.0, "min_std": 0.05, "eval_episodes": 5,
                                       "model_horizon": 200.0, "model_end_softness": 1.0,
                                       "num_updates": 11, "controller": "rbf",
                                       "model_particles": 16, "model_visited_starts": 0.0,
                                       "model_steps": 100, "model_final_rate": 1.0,
                                       "model_keep_best": False, "model_beta": 1.0,
                                       "model_exploration": "information",
                                       "model_information_weight": 20.0},
    # placeholders until the study's tuning chooses them: the model study's preset of the same
    # task (the sparse swing-up: Pendulum-v1's, its 20 learning episodes and roll-outs long enough
    # to swing up in), under the use each study is about, at beta 1
    "swingup-learned": {**PRESETS["swingup"], "model_exploration": "optimistic_reward",
                        "model_beta": 1.0},
    **{f"pendulum-sparse-{c:g}": {**PRESETS["pendulum-v1"], "num_updates": 21,
                                  "model_horizon": 4.0, "model_exploration": "optimistic",
                                  "model_beta": 1.0}
       for c in tasks.SPARSE_PENDULUM_COSTS},
})


def learns_reward(task, cfg) -> bool:
    """Whether gp_model learns the task's reward under `cfg`'s settings (`ModelSettings.reward`)."""
    return objectives.for_task(task, cfg.settings.reward).learned


def plan_steps(prog, cfg) -> int:
    """The simulated roll-outs' steps: the settings' `horizon` seconds in decisions of `prog.hold`
    control intervals."""
    dt = config.control_interval(prog.config) * prog.hold
    return max(1, int(round(cfg.settings.horizon / dt)))


def _relative_error(pred, target, valid):
    """sum (pred - target)^2 / sum target^2 over the valid rows (1 - R^2 about 0)."""
    w = valid.reshape(valid.shape + (1,) * (target.ndim - 1))
    err = jnp.sum((pred - target) ** 2 * w)
    return err / jnp.maximum(jnp.sum(target ** 2 * w), jnp.finfo(target.dtype).tiny)


def init(prog, key, cfg) -> ModelData:
    """The empty buffer: room for the run's decisions, at most the settings' `capacity`."""
    del key
    task, static, own = prog.task, prog.config, cfg.settings
    capacity = min(own.capacity, static.num_updates * static.episodes_per_update
                   * (static.episode_length // prog.hold))
    zeros = prog.controller.init(prog.dtype)
    hallucination = jax.tree_util.tree_map(lambda a: jnp.zeros((task.obs_dim,) + a.shape, a.dtype), zeros)
    outputs = task.obs_dim + learns_reward(task, cfg)
    return empty_data(capacity, task.feature_dim, outputs, prog.dtype, hallucination, task.obs_dim)


def make_update(actor: Actor = LEARNT_CONTROLLER):
    """gp_model's improvement step with `actor` acting in the real episodes after it."""

    def update(prog, cfg, state, batch):
        return _update(prog, cfg, state, batch, actor)

    return update


class Transitions(NamedTuple):
    """One update's transitions as the model takes them in (n decisions of its episodes).

    Attributes:
      inputs: (n, D) GP inputs (z, a).
      targets: (n, E) changes of the normalised observation (and the decision's reward last, for
        a learnt reward).
      rewards: (n,) the decisions' rewards (their control steps' rewards summed).
      valid: (n,) bool, the decisions taken wholly before their episode's end.
      obs: (n, obs_dim) the observations the decisions were taken in.
      actions: (n, act_dim) the decisions' actions.
      next_obs: (n, obs_dim) the observations at the decisions' ends.
    """

    inputs: jax.Array
    targets: jax.Array
    rewards: jax.Array
    valid: jax.Array
    obs: jax.Array
    actions: jax.Array
    next_obs: jax.Array


def transitions(prog, cfg, episodes) -> Transitions:
    """The update's episodes as the model's transitions (`decisions`, `Task.features`,
    `targets_of`), in the order `take_in` writes them."""
    task = prog.task
    objective = objectives.for_task(task, cfg.settings.reward)
    obs, nxt, acts = episodes.states, episodes.next_states, episodes.actions
    obs, nxt, acts, valid = decisions(prog.hold, obs, nxt, acts, episodes.alive, episodes.ends)
    d, e = task.feature_dim, task.obs_dim
    xs = jax.vmap(lambda s, a: rollouts.features(prog, s, a))(obs, acts).reshape(-1, d)
    ys = targets_of(task, obs, nxt).reshape(-1, e)
    rewards = decision_rewards(prog.hold, episodes.rewards).reshape(-1)
    valid = valid.reshape(-1)
    if objective.learned:
        ys = jnp.concatenate([ys, rewards[:, None]], axis=1)
    flat = lambda v: v.reshape((-1,) + v.shape[2:])  # noqa: E731
    return Transitions(xs, ys, rewards, valid, flat(obs), flat(acts), flat(nxt))


def model_keys(state):
    """The keys of an update's refit and plan, (k_fit, k_plan), from the state's key (a side
    stream of it: the next update's key is unchanged)."""
    key = jax.random.fold_in(state.key, 7)
    k_fit, k_plan, _ = jax.random.split(key, 3)
    return k_fit, k_plan


def model_errors(prog, cfg, data: ModelData, tr: Transitions):
    """The records `model_error` and `model_reward_error`: the model conditioned on `data` (before
    it takes `tr` in) predicting the transitions `tr`, data it has not seen (1 on the first update,
    whose model is the prior: its prediction is 0), and the objective's reward's error on them
    (the learnt one's before it takes them in, or the stated one's)."""
    task, own = prog.task, cfg.settings
    objective = objectives.for_task(task, own.reward)
    e = task.obs_dim
    model_old, mean_old = build(data, own.inducing)
    pred = jax.vmap(lambda x: predict(model_old, x)[0])(tr.inputs) + mean_old
    model_error = _relative_error(pred[:, :e], tr.targets[:, :e], tr.valid)
    o, a, n = tr.obs, tr.actions, tr.next_obs
    end = None if task.end_fn is None else jax.vmap(task.end_fn)(n).astype(o.dtype)
    reward_pred = jax.vmap(lambda *args: objective.reward(task, prog.hold, *args))(o, a, n, end, pred)
    return model_error, _relative_error(reward_pred, tr.rewards, tr.valid)


RESTART_SCALE = 0.5  # the restarts' perturbation of the initial controller, per parameter


def improve(prog, cfg, model, target_mean, key, controller_params, hallucination, visited=None):
    """The controller's optimisation through the model: the update's plan (`make_plan`, under the
    settings' use of the uncertainty, its particles started from the start distribution and
    the `visited` observations, (obs, valid)) and the optimiser's steps on its simulated return
    (`optimise`), from the current controller and the settings' restarts, the best kept by its
    return on held-aside particles. Returns (params, hallucination, return before, return after)
    of the kept controller, on the plan."""
    own = cfg.settings
    use = uncertainty.get(own.exploration)
    steps = plan_steps(prog, cfg)

    def plan_of(k, n=own.particles):
        n_visited = 0 if visited is None else int(round(own.visited_starts * n))
        return uncertainty.make_plan(prog, cfg, model, k, use, n, steps, visited, n_visited)

    k_plan, k_fresh, k_restart, k_aside = jax.random.split(key, 4)
    # the default search keeps the update's key as its plan's (the records of a run without the
    # search's options are those of the method before them)
    plan = plan_of(key if own.restarts == 1 and not own.fresh_draws else k_plan)
    fresh = (lambda i: plan_of(jax.random.fold_in(k_fresh, i))) if own.fresh_draws else None
    objective = objectives.for_task(prog.task, own.reward)

    def run(params):
        return optimise(
            prog, model, target_mean, plan, params, hallucination,
            num_steps=own.steps, learning_rate=own.learning_rate, beta=own.beta,
            optimistic=use.hallucinates, optimizer=own.optimizer, end_softness=own.end_softness,
            objective=objective, final_rate=own.final_rate, fresh_plan=fresh,
            keep_best=own.keep_best)

    if own.restarts == 1:
        return run(controller_params)
    zeros = prog.controller.init(prog.dtype)
    leaves, treedef = jax.tree_util.tree_flatten(zeros)
    keys = jax.random.split(k_restart, len(leaves))

    def perturbed(leaf, k):
        eps = jax.random.normal(k, (own.restarts - 1,) + leaf.shape, leaf.dtype)
        return leaf[None] + RESTART_SCALE * eps

    others = jax.tree_util.tree_unflatten(treedef, [perturbed(x, k) for x, k in zip(leaves, keys)])
    starts = jax.tree_util.tree_map(lambda c, o: jnp.concatenate([c[None], o]),
                                    controller_params, others)
    params, halluc, before, after = jax.vmap(run)(starts)
    if own.held_aside:
        aside = plan_of(k_aside, own.held_aside)
        score = jax.vmap(lambda c, h: simulate(
            prog, model, target_mean, aside, c, h if use.hallucinates else None, own.beta,
            own.end_softness, objective))(params, halluc)
    else:
        score = after
    best = jnp.argmax(jnp.where(jnp.isfinite(score), score, -jnp.inf))
    pick = lambda t: jax.tree_util.tree_map(lambda x: x[best], t)  # noqa: E731
    return pick(params), pick(halluc), before[0], after[best]


def _update(prog, cfg, state, batch, actor: Actor):
    """Steps 3-4 of gp_model: take in, refit, condition, optimise (module notes)."""
    task, own = prog.task, cfg.settings
    data: ModelData = state.method_state
    e = task.obs_dim
    tr = transitions(prog, cfg, batch.episodes)
    k_fit, k_plan = model_keys(state)
    first = data.count == 0
    model_error, model_reward_error = model_errors(prog, cfg, data, tr)
    data = take_in(data, tr.inputs, tr.targets, tr.valid, tr.obs)
    data = data._replace(log_kernels=refit(k_fit, data, subset_size=own.fit_subset,
                                           num_steps=own.fit_steps, first=first))
    model, target_mean = build(data, own.inducing)
    params, halluc, before, after = improve(prog, cfg, model, target_mean, k_plan,
                                            state.theta.controller, data.hallucination,
                                            (data.observations, data.valid))
    data = data._replace(hallucination=halluc)
    theta = actor.act_with(prog, cfg, state.theta, params)
    kern = jax.vmap(hyperfit.from_log)(data.log_kernels)
    records = dict(
        model_return=after,
        model_gain=after - before,
        model_error=model_error,
        model_reward_error=model_reward_error,
        model_std=jnp.mean(jnp.sqrt(kern.noise_variance[:e])),
        model_lengthscale_action=jnp.exp(jnp.mean(jnp.log(kern.lengthscales[:e, -1]))),
        model_data=jnp.sum(data.valid).astype(prog.dtype),
    )
    return theta, state.opt_state, data, {k: jnp.asarray(v, prog.dtype) for k, v in records.items()}


def check(cfg) -> None:
    """A hold no longer than an episode: the model is of one decision."""
    hold = exploration.hold_steps(cfg.hold_time, config.control_interval(cfg))
    if hold > cfg.episode_length:
        raise ValueError(f"TrainConfig.hold_time: a hold of {hold} control steps is longer than "
                         f"the episode ({cfg.episode_length}); gp_model models one decision")


update = make_update()


def make_method(name: str = "gp_model", actor: Actor = LEARNT_CONTROLLER,
                **declared) -> methods.Method:
    """gp_model's `methods.Method` with `actor`, its settings (`ModelSettings`, shared by every
    method made here) and its tuned presets; `declared` replaces further declarations (a variant
    registered under another name starts without gp_model's presets)."""
    return methods.Method(**{**dict(
        name=name, policy=actor.policy, prior="none", init=init,
        update=update if actor is LEARNT_CONTROLLER else make_update(actor), records=RECORDS,
        explorations=("white", "ou", "coloured"), compare_with=("reinforce", "gp_pg"),
        check=check, explain_exploration="'parameter' noise changes the controller the model "
                                         "optimises",
        eval_held=True, settings=ModelSettings, presets=PRESETS if name == "gp_model" else {},
        policy_optimiser=False), **declared})


methods.register(make_method())
