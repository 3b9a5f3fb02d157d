"""Roll-outs and evaluation, whatever the method (design: docs/design.md#algorithm-1).

`make_program(cfg)` bundles the static pieces of one configuration (`Program`: the task, the
controller, the method's policy, the fixed-noise behaviour policy, the hold and the exploration
noise). `rollout` runs one learning episode with a policy under the configuration's exploration
(step 1 of Algorithm 1), `run_episode` is the episode loop beneath it (holds, early ends,
restarts), `episode_returns` gives the returns-to-go, and `evaluate` runs the deterministic
controller c(s) for the records. None of it depends on how a method improves its policy
(`gpguided_jax.methods`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import controllers as controllers_lib
from gpguided_jax import (
    estimators,
    exploration,
    methods,
    pendulum,
    policies,
    swingup,
    tasks,
)
from gpguided_jax.config import TrainConfig, control_interval, validate


class Episode(NamedTuple):
    """One learning episode of a fixed number of steps (leaves gain a leading axis when batched)."""

    states: jax.Array  # (H, obs_dim), the observation each action was taken at
    next_states: jax.Array  # (H, obs_dim), the observation it led to
    actions: jax.Array  # (H,)
    rewards: jax.Array  # (H,), 0 after the episode's end
    scores: policies.PolicyParams  # leaves (H, ...), 0 after the episode's end
    exploration_std: jax.Array  # (H,)
    alive: jax.Array | None  # (H,) bool, True before the end; None for a task that never ends
    # (H,) bool, True at the steps where an episode ended and the environment was restarted
    # (`episode_end='restart'`; alive is then None); None otherwise
    ends: jax.Array | None = None


class Program(NamedTuple):
    """The static pieces of one configuration (what `make_train` closes over).

    Attributes:
      config: the `TrainConfig` whose static fields fix the program.
      controller: the deterministic controller c(s; theta_c).
      policy: the method's policy (fixed noise, guided variance or Gibbs).
      behaviour: the fixed-noise policy that collects the hyperparameter-fit data.
      task: the environment (`tasks.make_task(config.env)`).
      hold: control steps per decision (`config.hold_time`; 1: every step).
      noise: the exploration noise over an episode's decision points (`exploration.make_noise`).
      method: the `methods.Method` of `config.method`.
    """

    config: TrainConfig
    controller: controllers_lib.Controller
    policy: policies.Policy
    behaviour: policies.Policy
    task: tasks.Task
    hold: int = 1
    noise: exploration.NoiseProcess | None = None
    method: methods.Method | None = None

    @property
    def dtype(self):
        return jnp.dtype(self.config.dtype)


def make_controller(cfg: TrainConfig) -> controllers_lib.Controller:
    """The controller of `cfg.controller` on the observations of `cfg.env`."""
    task = tasks.make_task(cfg.env)
    if cfg.controller_units:
        return task.make_controller(cfg.controller, cfg.controller_units)
    return task.make_controller(cfg.controller)


def make_program(cfg: TrainConfig) -> Program:
    """The `Program` of `cfg` (validated): its task, controller, policies, hold and noise."""
    validate(cfg)
    method = methods.get(cfg.method)
    task = tasks.make_task(cfg.env)
    controller = make_controller(cfg)
    make_elsewhere = policies.made_elsewhere(method.policy)  # a planner: made from the program
    policy = None if make_elsewhere else policies.make_policy(
        method.policy, controller, num_candidates=cfg.num_candidates,
        features=task.features, optimism=cfg.optimism)
    dt = control_interval(cfg)
    hold = exploration.hold_steps(cfg.hold_time, dt)
    noise = exploration.make_noise(
        cfg.exploration, exploration.num_decisions(cfg.episode_length, hold), hold * dt,
        correlation_time=cfg.noise_correlation_time, exponent=cfg.noise_exponent,
        resample_time=cfg.noise_resample_time)
    prog = Program(cfg, controller, policy, policies.make_policy("fixed_noise", controller), task,
                   hold, noise, method)
    return prog if make_elsewhere is None else prog._replace(policy=make_elsewhere(prog))


def features(prog: Program, states, actions):
    return jax.vmap(prog.task.features)(states, actions)


def policy_context(cfg: TrainConfig, gp, kernel) -> policies.PolicyContext | None:
    """The `PolicyContext` the training loop gives its policy for a GP state and kernel; None for
    a method without a Q-GP (its policy reads none)."""
    if gp is None:
        return None
    # lambda_v and the candidate scale are given in (N m)^2 where the GP is at its prior variance.
    sf2 = kernel.signal_variance
    return policies.make_context(
        gp,
        kernel,
        variance_scale=cfg.guided_variance_scale / sf2,
        variance_floor=cfg.guided_variance_floor,
        inverse_temperature=cfg.inverse_temperature,
        energy_width=cfg.energy_width,
        candidate_scale=cfg.candidate_scale / sf2,
        candidate_floor=cfg.candidate_floor,
    )


# ------------------------------------------------------------------------------------------------
# The steps of one update, in order.
# ------------------------------------------------------------------------------------------------


def run_episode(prog: Program, key, act, cfg: TrainConfig, num_steps: int, hold: int = 1,
                xs=None, restart: bool = False, memory=None):
    """One episode of `num_steps` steps of the task, acting with `act(key, obs) -> (action, out)`
    (`act(key, obs, x)` with x the decision's entry of `xs`, if given) every `hold` steps and
    holding the action in between. With a policy's `memory` (its value at the episode's start),
    `act(key, obs[, x], memory) -> (action, out, memory)` carries it from one decision to the
    next (through restarts too).

    Returns (obs, next_obs, actions, rewards, alive, outs): the first four with a leading
    (num_steps,) axis, `alive` (num_steps,) bool or None for a task that never ends early, and
    `outs` with a leading axis of decisions, `exploration.num_decisions(num_steps, hold)`. After
    an episode's end the environment stays in its last state, and the rewards are 0 (module notes
    of `gpguided_jax.tasks`). With `restart` (static) the environment is reset after an end and
    the steps go on from the new start; `alive` is then `ends`, (num_steps,) bool, True at the
    steps that ended an episode (whose next_obs is the episode's last observation).
    """
    task = prog.task
    key_reset, key_steps = jax.random.split(key)
    env_state, obs = task.reset(key_reset, cfg)
    call = (lambda k, o, x, *m: act(k, o, *m)) if xs is None else act

    def env_step(carry, key_env, a):
        env_state, obs, alive = carry
        new_state, new_obs, r, done = task.step(key_env, env_state, a, cfg)
        if not task.terminates:
            return (new_state, new_obs, alive), (obs, new_obs, r, alive)
        if restart:
            done = jnp.asarray(done, bool)
            fresh_state, fresh_obs = task.reset(jax.random.fold_in(key_env, 1), cfg)
            pick = lambda fresh, new: jnp.where(done, fresh, new)  # noqa: E731
            carry = (jax.tree_util.tree_map(pick, fresh_state, new_state),
                     pick(fresh_obs, new_obs), alive)
            return carry, (obs, new_obs, r, done)
        keep = lambda new, old: jnp.where(alive, new, old)  # noqa: E731
        carry = (jax.tree_util.tree_map(keep, new_state, env_state), keep(new_obs, obs),
                 alive & ~done)
        return carry, (obs, carry[1], jnp.where(alive, r, jnp.zeros_like(r)), alive)

    def decide(carry_and_memory, key_and_x):
        carry, mem = carry_and_memory
        step_key, x = key_and_x
        key_act, key_env = jax.random.split(step_key)
        if memory is None:
            a, out = call(key_act, carry[1], x)
        else:
            a, out, mem = call(key_act, carry[1], x, mem)
        if hold == 1:
            carry, per_step = env_step(carry, key_env, a)
            return (carry, mem), (per_step, a, out)
        carry, per_step = jax.lax.scan(lambda c, k: env_step(c, k, a), carry,
                                       jax.random.split(key_env, hold))
        return (carry, mem), (per_step, a, out)

    n = exploration.num_decisions(num_steps, hold)
    keys = jax.random.split(key_steps, n)
    _, ((o, o_next, r, alive), a, out) = jax.lax.scan(
        decide, ((env_state, obs, jnp.ones((), bool)), memory), (keys, xs))
    if hold > 1:
        steps = lambda v: v.reshape((n * hold,) + v.shape[2:])[:num_steps]  # noqa: E731
        o, o_next, r, alive = map(steps, (o, o_next, r, alive))
        a = jnp.repeat(a, hold)[:num_steps]
    return o, o_next, a, r, (alive if task.terminates else None), out


def gp_spacing(gp_stride: int, hold: int) -> int:
    """Steps between the pairs an episode gives the GP: the decisions (every `hold` steps) at
    least `gp_stride` steps apart."""
    return -(-gp_stride // hold) * hold


def spread_decisions(values, hold: int, num_steps: int, fill: str = "zero"):
    """Per-decision values (D, ...) as per-step values (num_steps, ...): at the decision steps and
    0 in between (`fill='zero'`, for scores) or held (`fill='hold'`)."""
    if hold == 1:
        return values
    if fill == "hold":
        return jnp.repeat(values, hold, axis=0)[:num_steps]
    padded = jnp.zeros((values.shape[0], hold) + values.shape[1:], values.dtype)
    padded = padded.at[:, 0].set(values)
    return padded.reshape((-1,) + values.shape[1:])[:num_steps]


def rollout(prog: Program, key, theta, ctx, policy, cfg: TrainConfig) -> Episode:
    """Step 1: one episode of `episode_length` steps with `policy` (GP in `ctx` held fixed),
    deciding every `prog.hold` steps with the exploration noise `prog.noise`."""
    hold, noise, length = prog.hold, prog.noise, prog.config.episode_length
    restart = prog.config.episode_end == "restart" and prog.task.terminates
    if (noise is None or noise.name == "white") and policy.memory is not None:
        def act(k, obs, m):  # a policy with memory (a planner's previous plan)
            a, _, score, std, m = policy.act(k, theta, obs, ctx, m)
            return a, (score, std), m

        o, o_next, a, r, alive, (scores, std) = run_episode(
            prog, key, act, cfg, length, hold, restart=restart, memory=policy.memory(theta, ctx))
    elif noise is None or noise.name == "white":
        def act(k, obs):
            a, _, score, std = policy.act(k, theta, obs, ctx)
            return a, (score, std)

        o, o_next, a, r, alive, (scores, std) = run_episode(prog, key, act, cfg, length, hold,
                                                            restart=restart)
    elif noise.name == "parameter":
        # the controller's weights perturbed by a draw per block of decisions, its score at the
        # block's first decision (`exploration.parameter_scores`)
        controller, u_max = prog.controller, prog.controller.u_max
        std_p = jnp.exp(theta.log_std)
        eps = exploration.sample_parameter_noise(noise, jax.random.fold_in(key, 1),
                                                 theta.controller)
        scale = std_p / u_max
        blocks = jnp.arange(noise.length) // noise.block

        def act(k, obs, j):
            del k
            draw = jax.tree_util.tree_map(lambda e: e[j], eps)
            a = controller.apply(exploration.perturbed_parameters(theta.controller, draw, scale),
                                 obs)
            # the action's standard deviation at this state, to first order in the noise
            _, grad = controllers_lib.mean_and_grad(controller, theta.controller, obs)
            sq = sum(jnp.sum(g * g) for g in jax.tree_util.tree_leaves(grad))
            return a, scale * jnp.sqrt(sq)

        o, o_next, a, r, alive, std = run_episode(prog, key, act, cfg, length, hold, xs=blocks,
                                                  restart=restart)
        j_c, j_log_std = exploration.parameter_scores(noise, eps, std_p, u_max)
        scores = policies.PolicyParams(controller=j_c, log_std=j_log_std)
    else:
        # correlated noise: drawn for the whole episode, then each decision's score from the
        # policy's Gaussian parts (`exploration.correlated_scores`)
        eps, xi = noise.sample(jax.random.fold_in(key, 1), prog.dtype)

        def act(k, obs, e):
            del k
            mean, std, j_mean, j_std = policy.gaussian(theta, obs, ctx)
            return mean + std * e, (j_mean, j_std, std)

        o, o_next, a, r, alive, (j_mean, j_std, std) = run_episode(prog, key, act, cfg, length,
                                                                   hold, xs=eps, restart=restart)
        scores = exploration.correlated_scores(noise, eps, xi, j_mean, j_std)
    scores = jax.tree_util.tree_map(lambda g: spread_decisions(g, hold, length), scores)
    std = spread_decisions(std, hold, length, fill="hold")
    if restart:  # every step is an environment step; `alive` holds the ends
        return Episode(o, o_next, a, r, scores, std, None, alive)
    if alive is not None:
        scores = jax.tree_util.tree_map(
            lambda g: g * alive.reshape((-1,) + (1,) * (g.ndim - 1)).astype(g.dtype), scores)
    return Episode(o, o_next, a, r, scores, std, alive)


def episode_returns(ep: Episode, cfg: TrainConfig) -> jax.Array:
    """Returns-to-go of one `Episode` (H,), each stopping at its episode's end."""
    return estimators.discounted_returns(ep.rewards, cfg.discount, ep.ends)


def mean_episode_return(eps: Episode) -> jax.Array:
    """Mean undiscounted return of a batch of episodes (N, H): with restarts, the reward of the
    slots over the episodes in them (the last one cut at the slots' end)."""
    totals = jnp.sum(eps.rewards, axis=1)
    if eps.ends is None:
        return jnp.mean(totals)
    count = jnp.sum(eps.ends, axis=1) + (~eps.ends[:, -1])
    return jnp.sum(totals) / jnp.sum(count).astype(totals.dtype)


def alive_mean(values, alive):
    """Mean of `values` over the steps before the episodes' ends (all of them if alive is None)."""
    if alive is None:
        return jnp.mean(values)
    w = alive.astype(values.dtype)
    return jnp.sum(values * w) / jnp.maximum(jnp.sum(w), 1.0)


def episode_success(prog: Program, next_states, cfg: TrainConfig, rewards=None,
                    ends=None) -> jax.Array:
    """Whether one episode succeeded: on the pendulum, `swingup.success` of its visited states
    (False if it is shorter than the hold time); on another task, its return reaching the task's
    threshold (False without one). With `ends` (restarted episodes in the same slots): whether
    one of them reached it."""
    if prog.task.name != "pendulum":
        if prog.task.threshold is None or rewards is None:
            return jnp.zeros((), bool)
        if ends is None:
            return jnp.sum(rewards) >= prog.task.threshold
        totals = estimators.discounted_returns(rewards, 1.0, ends)  # from each step to its end
        starts = jnp.concatenate([jnp.ones((1,), bool), ends[:-1]])
        return jnp.any(starts & (totals >= prog.task.threshold))
    # the hold time in steps is static: it uses the control interval of make_train's config
    dt = float(np.asarray(prog.config.pendulum.dt))
    if swingup.hold_steps(dt, prog.config.success_hold_time) > next_states.shape[0]:
        return jnp.zeros((), bool)
    return swingup.success(next_states, dt, tolerance=cfg.success_tolerance,
                           hold_time=prog.config.success_hold_time)


def evaluate(prog: Program, key, theta, cfg: TrainConfig):
    """`eval_episodes` fresh episodes of the deterministic controller c(s; theta_c): (success rate,
    mean reward per step, mean undiscounted return); zeros when eval_episodes = 0. The controller
    acts at every control step, or every `prog.hold` steps for a method that declares
    `eval_held`."""
    n = prog.config.eval_episodes
    if n == 0:
        zero = jnp.zeros((), prog.dtype)
        return zero, zero, zero

    def act(k, obs):
        del k
        return prog.controller.apply(theta.controller, obs), ()

    keys = jax.random.split(key, n)
    hold = prog.hold if prog.method is not None and prog.method.eval_held else 1
    if prog.task.name == "pendulum" and hold == 1:
        traj = pendulum.batch_rollout(keys, cfg.pendulum, lambda k, s: act(k, s)[0],
                                      prog.config.episode_length)
        # batch_rollout's states are the states the actions were taken in; the last visited state
        # is final_state: the visited states are states[1:] followed by final_state.
        visited = jnp.concatenate([traj.states[:, 1:], traj.final_state[:, None]], axis=1)
        rewards, alive = traj.rewards, None
    else:
        _, visited, _, rewards, alive, _ = jax.vmap(
            lambda k: run_episode(prog, k, act, cfg, prog.config.episode_length, hold))(keys)
    ok = jax.vmap(lambda v, r: episode_success(prog, v, cfg, r))(visited, rewards)
    return (jnp.mean(ok.astype(prog.dtype)), alive_mean(rewards, alive),
            jnp.mean(jnp.sum(rewards, axis=1)))
