"""Algorithm 1 end to end as one pure function per seed: `make_train(config) -> train(key)`.

One seed's run is nested `lax.scan`s: updates -> episodes -> steps. One policy update (Algorithm 1)
is, in order, the functions of this module:

1. `rollout`: act with the method's policy for `episodes_per_update` episodes; the GP is held
   fixed during an episode (a policy that does not read the GP, the fixed-noise policy of
   REINFORCE and gp_pg, rolls the episodes out side by side before the GP takes any of them in);
2. `take_in_episode`: after each episode the GP takes in its (x_t, Ret_t) pairs, each stamped with
   the update index (eq. 12), and a health check (`sparse_gp.check`) accepts or rejects the new
   GP state (a rejected episode leaves the GP as it was and is counted in `gp_guard`);
3. `gradient_estimate`: REINFORCE (eq. 4) with returns-to-go, or eq. 9 with Q_GP(s_t, a_t) from the
   GP after it has taken in this update's episodes; each step's score is the hand-derived
   grad log pi of the policy that chose the action (eq. 1, 17 or 21), evaluated when it acted;
4. `optimiser_step`: one optax ascent step, the global gradient norm clipped at `max_grad_norm`
   (a non-finite estimate is skipped), then the learnable sigma clipped to [min_std, max_std].

Before the first update the GP hyperparameters are fitted on `hyperfit_samples` pairs collected
with the initial fixed-noise policy (paper §VI; `fit_prior`). `jit(vmap(train))(keys)` runs all
seeds at once; `train.init` and `train.run_chunk` expose the same computation in pieces for chunked,
resumable runs. Every array is of `config.dtype` (float64 needs JAX's x64 mode; see
`gpguided_jax.enable_x64`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from gpguided_jax import controllers as controllers_lib
from gpguided_jax import (
    estimators,
    exploration,
    hyperfit,
    kernels,
    pendulum,
    policies,
    sparse_gp,
    swingup,
    tasks,
)
from gpguided_jax.config import TrainConfig, control_interval, validate

_POLICY_OF_METHOD = {
    "reinforce": "fixed_noise",
    "gp_pg": "fixed_noise",
    "guided_variance": "guided_variance",
    "guided_direction": "gibbs",
}
FEATURE_DIM = 4  # the pendulum's GP input (sin phi, cos phi, omega, a); a task's: task.feature_dim


class TrainState(NamedTuple):
    """Everything carried from one update to the next (one seed).

    Attributes:
      theta: `PolicyParams`.
      opt_state: the optax state.
      gp: `SparseGPState` (capacity M).
      kernel: fitted `KernelParams`.
      key: PRNG key for the coming updates.
      update_index: () int32, updates done so far (the timestamp of new basis vectors).
    """

    theta: policies.PolicyParams
    opt_state: Any
    gp: sparse_gp.SparseGPState
    kernel: kernels.KernelParams
    key: jax.Array
    update_index: jax.Array


class GPPrior(NamedTuple):
    """What the GP methods of one seed share, fitted before learning (paper §VI).

    Attributes:
      kernel: fitted `KernelParams`.
      mean: () constant prior mean of Q_GP: the mean return-to-go of the initial policy's data.
    """

    kernel: kernels.KernelParams
    mean: jax.Array


class UpdateRecord(NamedTuple):
    """Per-update records (each () per update; stacked to (num_updates,) by the scan).

    Attributes:
      mean_reward: average reward per step over the update's episodes (Fig. 5a).
      exploration_std: policy exploration standard deviation, mean over visited states (Fig. 5b).
      grad_norm: global norm of the gradient estimate (before clipping).
      grad_clipped: 1 if the norm exceeded `max_grad_norm` and the step was clipped.
      nonfinite_grad: 1 if the gradient estimate was not finite (the step is then skipped).
      std_at_bound: 1 if the learnable sigma ended the step at `min_std` or `max_std`.
      num_basis_vectors: active BVs after the update's GP updates.
      fresh_bv_share: share of BVs stamped with this update (Fig. 1).
      gp_guard: episodes of this update whose GP update failed the health check
        (`sparse_gp.check`) and was therefore not taken in (the GP kept its state).
      gp_mean_error_ratio: the health check's worst |mu(x_t) - Ret_t| over its bound, max over
        the update's episodes (the guard fires above 1; how close a run came to it).
      success_rate: share of the update's (exploring) episodes that end in a held swing-up
        (`swingup.success`; 0 when episodes are shorter than the hold time).
      eval_success_rate: the same for `eval_episodes` fresh episodes of the deterministic
        controller c(s) (0 when eval_episodes = 0).
      eval_reward: their mean reward per step (0 when eval_episodes = 0).
      mean_return: the undiscounted return of the update's (exploring) episodes, their mean.
      eval_return: the undiscounted return of the `eval_episodes` deterministic episodes, their
        mean (0 when eval_episodes = 0): the task's own measure of a policy.
    """

    mean_reward: jax.Array
    exploration_std: jax.Array
    grad_norm: jax.Array
    grad_clipped: jax.Array
    nonfinite_grad: jax.Array
    std_at_bound: jax.Array
    num_basis_vectors: jax.Array
    fresh_bv_share: jax.Array
    gp_guard: jax.Array
    gp_mean_error_ratio: jax.Array
    success_rate: jax.Array
    eval_success_rate: jax.Array
    eval_reward: jax.Array
    mean_return: jax.Array
    eval_return: jax.Array


# The names of a run's records (results.npz, checkpoints, summaries): field -> (seeds, updates).
RECORD_FIELDS = UpdateRecord._fields


class Episode(NamedTuple):
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
    """

    config: TrainConfig
    controller: controllers_lib.Controller
    policy: policies.Policy
    behaviour: policies.Policy
    task: tasks.Task
    hold: int = 1
    noise: exploration.NoiseProcess | None = None

    @property
    def dtype(self):
        return jnp.dtype(self.config.dtype)


def make_controller(cfg: TrainConfig) -> controllers_lib.Controller:
    """The controller of `cfg.controller` on the observations of `cfg.env`."""
    return tasks.make_task(cfg.env).make_controller(cfg.controller)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    """The ascent step: global-norm clipping at `max_grad_norm`, then SGD (the paper) or Adam."""
    base = optax.sgd(cfg.learning_rate) if cfg.optimizer == "sgd" else optax.adam(cfg.learning_rate)
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), base)


def make_program(cfg: TrainConfig) -> Program:
    validate(cfg)
    task = tasks.make_task(cfg.env)
    controller = task.make_controller(cfg.controller)
    policy = policies.make_policy(
        _POLICY_OF_METHOD[cfg.method], controller, num_candidates=cfg.num_candidates,
        features=task.features, optimism=cfg.optimism)
    dt = control_interval(cfg)
    hold = exploration.hold_steps(cfg.hold_time, dt)
    noise = exploration.make_noise(
        cfg.exploration, exploration.num_decisions(cfg.episode_length, hold), hold * dt,
        correlation_time=cfg.noise_correlation_time, exponent=cfg.noise_exponent,
        resample_time=cfg.noise_resample_time)
    return Program(cfg, controller, policy, policies.make_policy("fixed_noise", controller), task,
                   hold, noise)


def _features(prog: Program, states, actions):
    return jax.vmap(prog.task.features)(states, actions)


def policy_context(cfg: TrainConfig, gp, kernel) -> policies.PolicyContext:
    """The `PolicyContext` the training loop gives its policy for a GP state and kernel."""
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
                xs=None, restart: bool = False):
    """One episode of `num_steps` steps of the task, acting with `act(key, obs) -> (action, out)`
    (`act(key, obs, x)` with x the decision's entry of `xs`, if given) every `hold` steps and
    holding the action in between.

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
    call = (lambda k, o, x: act(k, o)) if xs is None else act

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

    def decide(carry, key_and_x):
        step_key, x = key_and_x
        key_act, key_env = jax.random.split(step_key)
        a, out = call(key_act, carry[1], x)
        if hold == 1:
            carry, per_step = env_step(carry, key_env, a)
            return carry, (per_step, a, out)
        carry, per_step = jax.lax.scan(lambda c, k: env_step(c, k, a), carry,
                                       jax.random.split(key_env, hold))
        return carry, (per_step, a, out)

    n = exploration.num_decisions(num_steps, hold)
    keys = jax.random.split(key_steps, n)
    _, ((o, o_next, r, alive), a, out) = jax.lax.scan(
        decide, (env_state, obs, jnp.ones((), bool)), (keys, xs))
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
    if noise is None or noise.name == "white":
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
            _, grad = controller.value_and_grad(theta.controller, obs)
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


def _mean_episode_return(eps: Episode) -> jax.Array:
    """Mean undiscounted return of a batch of episodes (N, H): with restarts, the reward of the
    slots over the episodes in them (the last one cut at the slots' end)."""
    totals = jnp.sum(eps.rewards, axis=1)
    if eps.ends is None:
        return jnp.mean(totals)
    count = jnp.sum(eps.ends, axis=1) + (~eps.ends[:, -1])
    return jnp.sum(totals) / jnp.sum(count).astype(totals.dtype)


def _alive_mean(values, alive):
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
    mean reward per step, mean undiscounted return); zeros when eval_episodes = 0."""
    n = prog.config.eval_episodes
    if n == 0:
        zero = jnp.zeros((), prog.dtype)
        return zero, zero, zero

    def act(k, obs):
        del k
        return prog.controller.apply(theta.controller, obs), ()

    keys = jax.random.split(key, n)
    if prog.task.name == "pendulum":
        traj = pendulum.batch_rollout(keys, cfg.pendulum, lambda k, s: act(k, s)[0],
                                      prog.config.episode_length)
        # batch_rollout's states are the states the actions were taken in; the last visited state
        # is final_state: the visited states are states[1:] followed by final_state.
        visited = jnp.concatenate([traj.states[:, 1:], traj.final_state[:, None]], axis=1)
        rewards, alive = traj.rewards, None
    else:
        _, visited, _, rewards, alive, _ = jax.vmap(
            lambda k: run_episode(prog, k, act, cfg, prog.config.episode_length))(keys)
    ok = jax.vmap(lambda v, r: episode_success(prog, v, cfg, r))(visited, rewards)
    return (jnp.mean(ok.astype(prog.dtype)), _alive_mean(rewards, alive),
            jnp.mean(jnp.sum(rewards, axis=1)))


def take_in_episode(gp, kernel, xs, returns, update_index, cfg: TrainConfig, valid=None):
    """Step 2: the GP takes in one episode's (x_t, Ret_t); rejected if the result is unhealthy.

    Returns:
      (gp, guard_fired, health): the new GP (or the old one if `sparse_gp.check` failed), 0/1,
      and the `sparse_gp.Health` of the new GP. `valid`: (N,) bool, the pairs to take in (the
      steps before the episode's end); None: all.
    """
    new_gp = sparse_gp.update_batch(
        gp, xs, returns, kernel, update_index, valid=valid,
        novelty_tol=cfg.novelty_tol,
        age_penalty=cfg.age_penalty,
        age_scale=cfg.age_scale,
        age_fn=cfg.age_fn,
    )
    health = sparse_gp.check(new_gp, kernel, xs, returns, valid)
    gp = jax.tree_util.tree_map(lambda n, o: jnp.where(health.ok, n, o), new_gp, gp)
    return gp, (~health.ok).astype(jnp.int32), health


def gradient_estimate(prog: Program, state: TrainState, eps: Episode, returns, gp):
    """Step 3: eq. 4 (REINFORCE) or eq. 9 (Q_GP of the updated GP), optionally with a baseline."""
    static = prog.config
    if static.uses_gp:
        feats = jax.vmap(lambda s, a: _features(prog, s, a))(eps.states, eps.actions)
        predict_mean = jax.vmap(jax.vmap(lambda x: sparse_gp.predict(gp, x, state.kernel)[0]))
        weights = predict_mean(feats)
    else:
        weights = returns
    baseline = None
    if static.use_baseline:
        if static.uses_gp:
            apply = jax.vmap(jax.vmap(lambda s: prog.controller.apply(state.theta.controller, s)))
            baseline = predict_mean(jax.vmap(lambda s, a: _features(prog, s, a))(
                eps.states, apply(eps.states)))
        else:
            baseline = jnp.broadcast_to(returns.mean(axis=0, keepdims=True), returns.shape)
    # the scores after an episode's end are 0 (`rollout`), so those steps add nothing
    return estimators.policy_gradient(eps.scores, weights, baseline)


def optimiser_step(state: TrainState, grad, cfg: TrainConfig):
    """Step 4: clipped ascent step; skipped if the estimate is not finite; sigma clipped.

    Returns:
      (theta, opt_state, grad_norm, finite, at_bound).
    """
    grad_norm = optax.global_norm(grad)
    finite = jnp.isfinite(grad_norm)
    safe_grad = jax.tree_util.tree_map(lambda g: jnp.where(finite, g, 0.0), grad)
    theta, opt_state = estimators.ascent_step(
        make_optimizer(cfg), state.theta, state.opt_state, safe_grad
    )
    keep = lambda new, old: jnp.where(finite, new, old)  # noqa: E731
    theta = jax.tree_util.tree_map(keep, theta, state.theta)
    opt_state = jax.tree_util.tree_map(keep, opt_state, state.opt_state)
    lo, hi = jnp.log(cfg.min_std), jnp.log(cfg.max_std)
    log_std = jnp.clip(theta.log_std, lo, hi)
    at_bound = (log_std <= lo) | (log_std >= hi)
    return theta._replace(log_std=log_std), opt_state, grad_norm, finite, at_bound


def _take_in(prog: Program, cfg: TrainConfig, state: TrainState, gp, ep: Episode, returns):
    """Step 2 for one episode of this update (a no-op without a GP): (gp, fired, error_ratio)."""
    static = prog.config
    fired, error_ratio = jnp.zeros((), jnp.int32), jnp.zeros((), prog.dtype)
    if static.uses_gp:
        # the decisions at least gp_stride steps apart join the GP (gp_stride 1, no hold: every
        # step; with a hold longer than the stride, every decision)
        k = gp_spacing(static.gp_stride, prog.hold)
        valid = None if ep.alive is None else ep.alive[::k]
        gp, fired, health = take_in_episode(
            gp, state.kernel, _features(prog, ep.states, ep.actions)[::k], returns[::k],
            state.update_index, cfg, valid)
        error_ratio = health.mean_error_ratio
    return gp, fired, error_ratio


def _side_by_side(prog: Program, cfg: TrainConfig, state: TrainState, keys):
    """The update's episodes of a policy that does not read the GP, rolled out as one batch (the
    same draws as one after another), and their returns-to-go."""
    ctx = policy_context(cfg, state.gp, state.kernel)
    eps = jax.vmap(lambda k: rollout(prog, k, state.theta, ctx, prog.policy, cfg))(keys)
    returns = jax.vmap(episode_returns, in_axes=(0, None))(eps, cfg)
    return eps, returns


def roll_out_and_take_in(prog: Program, cfg: TrainConfig, state: TrainState, keys):
    """Steps 1-2 of one update: its episodes and the GP that has taken them in.

    Returns:
      (gp, eps, returns, fired, error_ratio), the last four with a leading (episodes,) axis.
    """
    if prog.policy.reads_gp:
        # Each episode acts with the GP that has taken in the episodes before it.
        def episode(gp, key_e):
            ctx = policy_context(cfg, gp, state.kernel)
            ep = rollout(prog, key_e, state.theta, ctx, prog.policy, cfg)
            returns = episode_returns(ep, cfg)
            gp, fired, error_ratio = _take_in(prog, cfg, state, gp, ep, returns)
            return gp, (ep, returns, fired, error_ratio)

        gp, (eps, returns, fired, error_ratio) = jax.lax.scan(episode, state.gp, keys)
        return gp, eps, returns, fired, error_ratio
    # The policy does not read the GP: the episodes are rolled out side by side, then the GP
    # takes them in in order.
    eps, returns = _side_by_side(prog, cfg, state, keys)

    def take_in_one(gp, ep_and_returns):
        gp, fired, error_ratio = _take_in(prog, cfg, state, gp, *ep_and_returns)
        return gp, (fired, error_ratio)

    gp, (fired, error_ratio) = jax.lax.scan(take_in_one, state.gp, (eps, returns))
    return gp, eps, returns, fired, error_ratio


def roll_out_and_take_in_switched(progs, method_index, cfg: TrainConfig, state: TrainState, keys):
    """`roll_out_and_take_in` with the policy of `progs[method_index]` (a traced index), so that
    one program serves every method of `progs`: the GP update, the gradient and the optimiser
    step are traced once, and only the roll-outs are branches of a `lax.switch`.

    A policy that does not read the GP rolls the update's episodes out side by side before the
    GP takes any of them in, as in `roll_out_and_take_in` (a `lax.switch` whose other branches
    return zeros); then every method's episodes go through one scan, in which an episode is
    either rolled out with the GP taken in so far or read from the side-by-side batch.
    """
    side = [not p.policy.reads_gp for p in progs]
    template = jax.eval_shape(lambda: _side_by_side(progs[0], cfg, state, keys))
    zeros = lambda: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), template)  # noqa: E731
    if any(side):
        batch = jax.lax.switch(method_index, [
            (lambda p=p: _side_by_side(p, cfg, state, keys)) if s else zeros
            for p, s in zip(progs, side)])
    else:
        batch = zeros()

    def episode(gp, xs):
        key_e, pre = xs
        ctx = policy_context(cfg, gp, state.kernel)

        def own(p):
            ep = rollout(p, key_e, state.theta, ctx, p.policy, cfg)
            return ep, episode_returns(ep, cfg)

        ep, returns = jax.lax.switch(method_index, [
            (lambda: pre) if s else (lambda p=p: own(p)) for p, s in zip(progs, side)])
        gp, fired, error_ratio = _take_in(progs[0], cfg, state, gp, ep, returns)
        return gp, (ep, returns, fired, error_ratio)

    gp, (eps, returns, fired, error_ratio) = jax.lax.scan(episode, state.gp, (keys, batch))
    return gp, eps, returns, fired, error_ratio


def one_update(prog: Program, cfg: TrainConfig, state: TrainState, roll_out=None):
    """key -> roll-outs and GP updates (steps 1-2) -> gradient (3) -> optimiser (4) -> record.

    `roll_out(cfg, state, keys)` replaces steps 1-2 (default: `roll_out_and_take_in` with
    `prog`'s policy; `make_gp_methods_train` passes the switched one).
    """
    static = prog.config
    key, key_eps = jax.random.split(state.key)
    key_eval = jax.random.fold_in(key_eps, 1)  # a side stream: the episodes' keys stay as they were
    t = state.update_index
    keys = jax.random.split(key_eps, static.episodes_per_update)
    if roll_out is None:
        gp, eps, returns, fired, error_ratio = roll_out_and_take_in(prog, cfg, state, keys)
    else:
        gp, eps, returns, fired, error_ratio = roll_out(cfg, state, keys)
    grad = gradient_estimate(prog, state, eps, returns, gp)
    theta, opt_state, grad_norm, finite, at_bound = optimiser_step(state, grad, cfg)

    n_bv = sparse_gp.num_basis_vectors(gp)
    fresh = jnp.sum(gp.mask & (gp.timestamps == t))
    successes = jax.vmap(lambda v, r, e: episode_success(prog, v, cfg, r, e))(
        eps.next_states, eps.rewards, eps.ends)
    eval_success, eval_reward, eval_return = evaluate(prog, key_eval, state.theta, cfg)
    record = UpdateRecord(
        mean_reward=_alive_mean(eps.rewards, eps.alive),
        exploration_std=_alive_mean(eps.exploration_std, eps.alive),
        grad_norm=grad_norm,
        grad_clipped=(finite & (grad_norm > cfg.max_grad_norm)).astype(jnp.int32),
        nonfinite_grad=(~finite).astype(jnp.int32),
        std_at_bound=at_bound.astype(jnp.int32),
        num_basis_vectors=n_bv,
        fresh_bv_share=jnp.where(n_bv > 0, fresh / jnp.maximum(n_bv, 1), 0.0).astype(prog.dtype),
        gp_guard=jnp.sum(fired),
        gp_mean_error_ratio=jnp.max(error_ratio),
        success_rate=jnp.mean(successes.astype(prog.dtype)),
        eval_success_rate=eval_success,
        eval_reward=eval_reward,
        mean_return=_mean_episode_return(eps),
        eval_return=eval_return,
    )
    return TrainState(theta, opt_state, gp, state.kernel, key, t + 1), record


# ------------------------------------------------------------------------------------------------
# Initialisation: the hyperparameter fit and the initial state.
# ------------------------------------------------------------------------------------------------


def initial_theta(prog: Program, cfg: TrainConfig) -> policies.PolicyParams:
    return policies.init_params(prog.controller, log_std=cfg.init_log_std, dtype=prog.dtype)


def collect(prog: Program, key, cfg: TrainConfig):
    """(x, Ret) pairs from the initial fixed-noise policy: (n_episodes * H, D), (n * H,). On a
    task that ends early the pairs after an episode's end are among them, with return 0
    (`collect_valid` says which)."""
    return collect_valid(prog, key, cfg)[:2]


def collect_valid(prog: Program, key, cfg: TrainConfig):
    """`collect`'s pairs and (n * H,) bool, which of them come before their episode's end (None for
    a task that never ends early)."""
    theta = initial_theta(prog, cfg)
    d = prog.task.feature_dim
    gp = sparse_gp.init(1, d, prog.dtype)
    dummy_kernel = kernels.make_kernel_params(jnp.ones(d), dtype=prog.dtype)
    ctx = policy_context(cfg, gp, dummy_kernel)
    keys = jax.random.split(key, prog.config.hyperfit_episodes)
    eps = jax.vmap(lambda k: rollout(prog, k, theta, ctx, prog.behaviour, cfg))(keys)
    returns = jax.vmap(episode_returns, in_axes=(0, None))(eps, cfg)
    # every step's pair, held actions too (a held action's pair is its value for the rest of the
    # hold): the fit sees the exploration's actions at the cost in episodes of white noise
    xs = jax.vmap(lambda s, a: _features(prog, s, a))(eps.states, eps.actions).reshape(-1, d)
    valid = None if eps.alive is None else eps.alive.reshape(-1)
    return xs, returns.reshape(-1), valid


def fit_subset(prog: Program, key, cfg: TrainConfig):
    """The hyperparameter fit's data: every collected (x, Ret) pair and the indices of the random
    subset of `hyperfit_subset` pairs the likelihood is taken on (None: all pairs, when there are
    no more) and which pairs come before their episode's end. Returns (xs, ys, idx, valid)."""
    key_data, key_subset = jax.random.split(key)
    xs, ys, valid = collect_valid(prog, key_data, cfg)
    n = min(prog.config.hyperfit_subset, xs.shape[0])
    if valid is not None:
        # the subset is drawn from the pairs before their episode's end; with fewer of them than
        # n, the subset repeats them (a repeated pair only sharpens the noise estimate slightly)
        p = valid.astype(prog.dtype)
        return xs, ys, jax.random.choice(key_subset, xs.shape[0], (n,), replace=True,
                                         p=p / jnp.maximum(jnp.sum(p), 1.0)), valid
    if n == xs.shape[0]:
        return xs, ys, None, None
    return xs, ys, jax.random.choice(key_subset, xs.shape[0], (n,), replace=False), None


class FitData(NamedTuple):
    """The hyperparameter fit's data as `fit_prior` uses it (N collected pairs, n in the subset).

    Attributes:
      xs: (N, D) every collected input.
      ys: (N,) their returns-to-go, centred on `mean`.
      fit_xs: (n, D) the subset the likelihood is taken on.
      fit_ys: (n,) its centred returns.
      mean: () the mean return of all N pairs, the prior mean of Q_GP.
    """

    xs: jax.Array
    ys: jax.Array
    fit_xs: jax.Array
    fit_ys: jax.Array
    mean: jax.Array


def fit_data(prog: Program, key, cfg: TrainConfig) -> FitData:
    """`fit_subset`'s pairs with the returns centred on their mean (the kernel is fitted to centred
    returns), and the subset taken."""
    xs, ys, idx, valid = fit_subset(prog, key, cfg)
    if valid is None:
        mean = jnp.mean(ys)
    else:
        w = valid.astype(ys.dtype)
        mean = jnp.sum(ys * w) / jnp.maximum(jnp.sum(w), 1.0)
    fit_xs, fit_ys = (xs, ys) if idx is None else (xs[idx], ys[idx])
    return FitData(xs, ys - mean, fit_xs, fit_ys - mean, mean)


def fit_prior(prog: Program, key, cfg: TrainConfig) -> GPPrior:
    """The GP's kernel (exact marginal likelihood on a random subset, paper §VI) and prior mean."""
    static = prog.config
    data = fit_data(prog, key, cfg)
    kernel = hyperfit.fit(data.fit_xs, data.fit_ys, num_steps=static.hyperfit_steps,
                          optimizer=static.hyperfit_optimizer).params
    return GPPrior(kernel, data.mean)


def initial_state(prog: Program, key, cfg: TrainConfig, prior: GPPrior | None = None) -> TrainState:
    static = prog.config
    key_fit, key_run = jax.random.split(key)
    if prior is None:
        if static.uses_gp:
            prior = fit_prior(prog, key_fit, cfg)
        else:  # unused by REINFORCE
            prior = GPPrior(kernels.make_kernel_params(jnp.ones(prog.task.feature_dim), dtype=prog.dtype),
                            jnp.zeros((), prog.dtype))
    prior = jax.tree_util.tree_map(lambda a: jnp.asarray(a, prog.dtype), prior)
    theta = initial_theta(prog, cfg)
    opt_state = make_optimizer(cfg).init(theta)
    # REINFORCE never reads its GP: a one-slot placeholder keeps the state's structure small.
    capacity = static.gp_capacity if static.uses_gp else 1
    gp = sparse_gp.init(capacity, prog.task.feature_dim, prog.dtype, prior_mean=prior.mean)
    return TrainState(theta, opt_state, gp, prior.kernel, key_run, jnp.zeros((), jnp.int32))


# ------------------------------------------------------------------------------------------------
# The public entry point.
# ------------------------------------------------------------------------------------------------


def make_train(config: TrainConfig):
    """Builds the pure training functions of one static configuration.

    Returns `train(key, cfg=config) -> (TrainState, UpdateRecord)`: the whole run (records have a
    leading (num_updates,) axis); `cfg` may differ from `config` in traced fields only, so
    `jax.jit(jax.vmap(train))(keys)` runs seeds and `jax.vmap(train)(keys, stacked_cfgs)` sweeps.
    The pieces hang on it as attributes:
      - `train.init(key, cfg=config, prior=None) -> TrainState`: hyperparameter fit (skipped when a
        `GPPrior` is given, or for REINFORCE) and initial state.
      - `train.run_chunk(state, cfg=config, num_updates=...) -> (TrainState, UpdateRecord)`.
      - `train.fit_kernel_for_seed(key, cfg=config) -> GPPrior`, `train.collect(key, cfg)`.
      - `train.episodes(key, state, cfg=config, num_episodes=3) -> Episode`: roll out the
        method's policy at a given state (visited states for figures, evaluation).
    """
    prog = make_program(config)
    static = config

    def _check(cfg: TrainConfig):
        if cfg.static_dict() != static.static_dict():
            raise ValueError(
                "a config passed to train/run_chunk must match make_train's static fields: "
                f"{cfg.static_dict()} != {static.static_dict()}"
            )

    def init(key, cfg=config, prior: GPPrior | None = None):
        _check(cfg)
        return initial_state(prog, key, cfg, prior)

    def run_chunk(state, cfg=config, num_updates=static.num_updates):
        _check(cfg)
        return jax.lax.scan(lambda s, _: one_update(prog, cfg, s), state, None, length=num_updates)

    def train(key, cfg=config):
        return run_chunk(init(key, cfg), cfg, static.num_updates)

    def episodes(key, state: TrainState, cfg=config, num_episodes: int = 3) -> Episode:
        """Episodes of the method's policy at `state` (theta and GP held fixed): fields gain a
        leading (num_episodes,) axis. For figures of visited states and for evaluation."""
        ctx = policy_context(cfg, state.gp, state.kernel)
        keys = jax.random.split(key, num_episodes)
        return jax.vmap(lambda k: rollout(prog, k, state.theta, ctx, prog.policy, cfg))(keys)

    def fit_kernel_for_seed(key, cfg=config) -> GPPrior:
        """The `GPPrior` (kernel and prior mean) that `init(key, cfg)` would fit; it depends only on
        the seed and the initial policy, so every GP method of a seed can share it."""
        return fit_prior(prog, jax.random.split(key)[0], cfg)

    train.init = init
    train.run_chunk = run_chunk
    train.fit_prior = lambda key, cfg=config: fit_prior(prog, key, cfg)
    train.fit_kernel_for_seed = fit_kernel_for_seed
    train.collect = lambda key, cfg=config: collect(prog, key, cfg)
    train.episodes = episodes
    train.program = prog
    train.controller = prog.controller
    train.policy = prog.policy
    train.config = config
    return train


# ------------------------------------------------------------------------------------------------
# Every GP method of a configuration as one program.
# ------------------------------------------------------------------------------------------------

GP_METHODS = ("gp_pg", "guided_variance", "guided_direction")


def gp_methods_key(cfg: TrainConfig) -> TrainConfig:
    """`cfg` with its method set to the first GP method: the configs of the GP methods of one
    static configuration then share a pytree structure, and so one `make_gp_methods_train`
    program (the method is its `method_index` argument)."""
    if not cfg.uses_gp:
        raise ValueError(f"make_gp_methods_train runs the GP methods {GP_METHODS}, not {cfg.method!r}")
    return cfg.replace(method=GP_METHODS[0])


def make_gp_methods_train(config: TrainConfig):
    """One program for every GP method (`GP_METHODS`) of `config`'s static fields.

    Returns `run_chunk(state, method_index, cfg, num_updates=config.num_updates) -> (TrainState,
    UpdateRecord)`: the updates of `make_train(cfg).run_chunk` for the method
    `GP_METHODS[method_index]`, where `method_index` is a traced () int32 and `cfg` a traced
    argument (pass `gp_methods_key(method_cfg)`: any GP method's config with these static fields).
    The GP update, the gradient, the optimiser step and the records are traced once for all
    methods; each method's roll-outs are a branch of a `lax.switch`
    (`roll_out_and_take_in_switched`). `gpguided reproduce` runs its GP methods this way, which
    compiles one program instead of three. The records are those of `make_train(cfg).run_chunk`
    to rounding (XLA compiles the two programs differently), with the same draws.
    """
    key = gp_methods_key(config)
    progs = tuple(make_program(key.replace(method=m)) for m in GP_METHODS)

    def run_chunk(state, method_index, cfg=key, num_updates=config.num_updates):
        if cfg.static_dict() != key.static_dict():
            raise ValueError(
                "the config passed to make_gp_methods_train's run_chunk must be gp_methods_key of a "
                f"config with its static fields: {cfg.static_dict()} != {key.static_dict()}")
        roll_out = lambda c, s, keys: roll_out_and_take_in_switched(progs, method_index, c, s, keys)  # noqa: E731
        return jax.lax.scan(lambda s, _: one_update(progs[0], cfg, s, roll_out), state, None,
                            length=num_updates)

    run_chunk.config = key
    run_chunk.methods = GP_METHODS
    return run_chunk
