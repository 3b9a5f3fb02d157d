"""Algorithm 1 end to end as one pure function per seed: `make_train(config) -> train(key)`.

One seed's run is nested `lax.scan`s: updates -> episodes -> steps. One update (`one_update`) is
two parts:

* steps 1-2, the same for every method: `roll_out_and_take_in` acts with the method's policy for
  `episodes_per_update` episodes (`rollouts.rollout`) and, for a method with a Q-GP prior, the GP
  takes in each episode's (x_t, Ret_t) pairs, each stamped with the update index (eq. 12), a
  health check (`sparse_gp.check`) accepting or rejecting the new GP state (a rejected episode
  leaves the GP as it was and is counted in `gp_guard`). The GP is held fixed during an episode;
  a policy that does not read the GP rolls the update's episodes out side by side first;
* steps 3-4, the method's own improvement step, `method.update(prog, cfg, state, batch)` of its
  declared `methods.Method` (the paper's four: `gpguided_jax.policy_gradient`), which returns the
  new policy parameters, optimiser state, the method's own state and its records.

Before the first update a method with a Q-GP prior fits the GP's hyperparameters on
`hyperfit_samples` pairs collected with the initial fixed-noise policy (paper §VI; `fit_prior`).
`jit(vmap(train))(keys)` runs all seeds at once; `train.init` and `train.run_chunk` expose the same
computation in pieces for chunked, resumable runs. Every array is of `config.dtype` (float64 needs
JAX's x64 mode; see `gpguided_jax.enable_x64`).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gpguided_jax import hyperfit, kernels, methods, policies, sparse_gp
from gpguided_jax.config import TrainConfig, validate

# the paper's methods, registered on import; their step pieces are re-exported here
from gpguided_jax.policy_gradient import (  # noqa: F401
    gradient_estimate,
    make_optimizer,
    optimiser_step,
)
from gpguided_jax.rollouts import (  # noqa: F401
    Episode,
    Program,
    alive_mean,
    episode_returns,
    episode_success,
    evaluate,
    features,
    gp_spacing,
    make_controller,
    make_program,
    mean_episode_return,
    policy_context,
    rollout,
    run_episode,
    spread_decisions,
)

FEATURE_DIM = 4  # the pendulum's GP input (sin phi, cos phi, omega, a); a task's: task.feature_dim


class TrainState(NamedTuple):
    """Everything carried from one update to the next (one seed).

    Attributes:
      theta: `PolicyParams`.
      opt_state: the optax state of the policy's ascent step (`()` for a method without one,
        `Method.policy_optimiser`).
      gp: `SparseGPState` (capacity M; None for a method without a Q-GP).
      kernel: fitted `KernelParams` (None for a method without a Q-GP).
      key: PRNG key for the coming updates.
      update_index: () int32, updates done so far (the timestamp of new basis vectors).
      method_state: the method's own state (`Method.init`; `()` for the paper's methods).
    """

    theta: policies.PolicyParams
    opt_state: Any
    gp: sparse_gp.SparseGPState
    kernel: kernels.KernelParams
    key: jax.Array
    update_index: jax.Array
    method_state: Any = ()

class GPPrior(NamedTuple):
    """What the GP methods of one seed share, fitted before learning (paper §VI).

    Attributes:
      kernel: fitted `KernelParams`.
      mean: () constant prior mean of Q_GP: the mean return-to-go of the initial policy's data.
    """

    kernel: kernels.KernelParams
    mean: jax.Array


class UpdateRecord(NamedTuple):
    """Per-update records of the paper's methods (each () per update; stacked to (num_updates,)
    by the scan): `methods.SHARED_RECORDS` and the policy-gradient step's own
    (`policy_gradient.RECORDS`: grad_norm, grad_clipped, nonfinite_grad, std_at_bound).

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

class Batch(NamedTuple):
    """What steps 1-2 hand the method's improvement step.

    Attributes:
      episodes: the update's `Episode`s, leaves with a leading (episodes_per_update,) axis.
      returns: (episodes_per_update, H) their returns-to-go.
      gp: the `SparseGPState` after it has taken the episodes in (unchanged without a Q-GP).
    """

    episodes: Episode
    returns: jax.Array
    gp: sparse_gp.SparseGPState


@functools.cache
def _record_type(fields: tuple[str, ...]):
    if set(fields) == set(UpdateRecord._fields):
        return UpdateRecord
    return NamedTuple("MethodRecord", [(f, jax.Array) for f in fields])


def record_type(method: methods.Method):
    """The NamedTuple of a method's per-update records: `methods.SHARED_RECORDS` and its own
    (`UpdateRecord` for the paper's methods)."""
    return _record_type(methods.SHARED_RECORDS + tuple(method.records))


def record_fields(method_name: str) -> tuple[str, ...]:
    """The names of the records of the method called `method_name`."""
    return record_type(methods.get(method_name))._fields


def __getattr__(name):
    if name == "GP_METHODS":  # the registered methods with a Q-GP prior
        return methods.gp_methods()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")



# ------------------------------------------------------------------------------------------------
# One update: the shared steps 1-2, then the method's improvement step.
# ------------------------------------------------------------------------------------------------


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


def _take_in(prog: Program, cfg: TrainConfig, state: TrainState, gp, ep: Episode, returns):
    """Step 2 for one episode of this update (a no-op without a GP): (gp, fired, error_ratio)."""
    static = prog.config
    fired, error_ratio = jnp.zeros((), jnp.int32), jnp.zeros((), prog.dtype)
    if prog.method.uses_gp:
        # the decisions at least gp_stride steps apart join the GP (gp_stride 1, no hold: every
        # step; with a hold longer than the stride, every decision)
        k = gp_spacing(static.gp_stride, prog.hold)
        valid = None if ep.alive is None else ep.alive[::k]
        if prog.method.targets is not None:  # the method's own targets (`Method.targets`)
            returns = prog.method.targets(prog, cfg, state, ep, returns)
        gp, fired, health = take_in_episode(
            gp, state.kernel, features(prog, ep.states, ep.actions)[::k], returns[::k],
            state.update_index, cfg, valid)
        error_ratio = health.mean_error_ratio
    return gp, fired, error_ratio


def rollout_context(prog: Program, cfg: TrainConfig, state: TrainState, gp):
    """What the method's policy reads in the update's roll-outs: its own context made from the
    state (`Method.context`: a planner's model) or the Q-GP's, `gp` (`policy_context`)."""
    if prog.method.context is not None:
        return prog.method.context(prog, cfg, state)
    return policy_context(cfg, gp, state.kernel)


def _side_by_side(prog: Program, cfg: TrainConfig, state: TrainState, keys):
    """The update's episodes of a policy that does not read the GP, rolled out as one batch (the
    same draws as one after another), and their returns-to-go."""
    ctx = rollout_context(prog, cfg, state, state.gp)
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
            ctx = rollout_context(prog, cfg, state, gp)
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
        ctx = rollout_context(progs[0], cfg, state, gp)  # one context: `shares_program`

        def own(p):
            ep = rollout(p, key_e, state.theta, ctx, p.policy, cfg)
            return ep, episode_returns(ep, cfg)

        ep, returns = jax.lax.switch(method_index, [
            (lambda: pre) if s else (lambda p=p: own(p)) for p, s in zip(progs, side)])
        gp, fired, error_ratio = _take_in(progs[0], cfg, state, gp, ep, returns)
        return gp, (ep, returns, fired, error_ratio)

    gp, (eps, returns, fired, error_ratio) = jax.lax.scan(episode, state.gp, (keys, batch))
    return gp, eps, returns, fired, error_ratio


def update_keys(prog: Program, state: TrainState):
    """An update's keys from the state's: (the next update's key, the keys of the update's
    `episodes_per_update` episodes, the key of its evaluation episodes)."""
    key, key_eps = jax.random.split(state.key)
    key_eval = jax.random.fold_in(key_eps, 1)  # a side stream: the episodes' keys stay as they were
    return key, jax.random.split(key_eps, prog.config.episodes_per_update), key_eval


def one_update(prog: Program, cfg: TrainConfig, state: TrainState, roll_out=None):
    """key -> roll-outs and GP take-in (steps 1-2) -> the method's improvement step (3-4) ->
    records.

    `roll_out(cfg, state, keys)` replaces steps 1-2 (default: `roll_out_and_take_in` with
    `prog`'s policy; `make_methods_train` passes the switched one).
    """
    method = prog.method
    key, keys, key_eval = update_keys(prog, state)
    t = state.update_index
    if roll_out is None:
        gp, eps, returns, fired, error_ratio = roll_out_and_take_in(prog, cfg, state, keys)
    else:
        gp, eps, returns, fired, error_ratio = roll_out(cfg, state, keys)
    theta, opt_state, method_state, own = method.update(prog, cfg, state, Batch(eps, returns, gp))

    if gp is None:  # no Q-GP: no basis vectors
        n_bv, fresh = jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32)
    else:
        n_bv, fresh = sparse_gp.num_basis_vectors(gp), jnp.sum(gp.mask & (gp.timestamps == t))
    successes = jax.vmap(lambda v, r, e: episode_success(prog, v, cfg, r, e))(
        eps.next_states, eps.rewards, eps.ends)
    eval_success, eval_reward, eval_return = evaluate(prog, key_eval, state.theta, cfg)
    record = record_type(method)(
        mean_reward=alive_mean(eps.rewards, eps.alive),
        exploration_std=alive_mean(eps.exploration_std, eps.alive),
        num_basis_vectors=n_bv,
        fresh_bv_share=jnp.where(n_bv > 0, fresh / jnp.maximum(n_bv, 1), 0.0).astype(prog.dtype),
        gp_guard=jnp.sum(fired),
        gp_mean_error_ratio=jnp.max(error_ratio),
        success_rate=jnp.mean(successes.astype(prog.dtype)),
        eval_success_rate=eval_success,
        eval_reward=eval_reward,
        mean_return=mean_episode_return(eps),
        eval_return=eval_return,
        **own,
    )
    return TrainState(theta, opt_state, gp, state.kernel, key, t + 1, method_state), record


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
    xs = jax.vmap(lambda s, a: features(prog, s, a))(eps.states, eps.actions).reshape(-1, d)
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
    """The state before the first update: the prior (fitted here unless given) and its GP for a
    method with a Q-GP (None for another), the initial policy, its optimiser state (for a method
    that takes the ascent step) and the method's own."""
    static, method = prog.config, prog.method
    key_fit, key_run = jax.random.split(key)
    gp = kernel = None
    if method.uses_gp:
        if prior is None:
            prior = fit_prior(prog, key_fit, cfg)
        prior = jax.tree_util.tree_map(lambda a: jnp.asarray(a, prog.dtype), prior)
        gp = sparse_gp.init(static.gp_capacity, prog.task.feature_dim, prog.dtype,
                            prior_mean=prior.mean)
        kernel = prior.kernel
    theta = initial_theta(prog, cfg)
    opt_state = make_optimizer(cfg).init(theta) if method.policy_optimiser else ()
    method_state = method.init(prog, jax.random.fold_in(key_fit, 2), cfg)
    return TrainState(theta, opt_state, gp, kernel, key_run, jnp.zeros((), jnp.int32),
                      method_state)


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
        ctx = rollout_context(prog, cfg, state, state.gp)
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

def program_family(cfg: TrainConfig) -> tuple[str, ...]:
    """The registered methods that can share one compiled program with `cfg`'s method
    (`methods.shares_program`) and accept `cfg`'s other fields: the branches of
    `make_methods_train`. A method's records then do not depend on which of them a run asks for."""
    own = methods.get(cfg.method)
    family = []
    for name in methods.names():
        if not methods.shares_program(methods.get(name), own):
            continue
        try:
            validate(cfg.replace(method=name))
        except ValueError:
            continue
        family.append(name)
    return tuple(family)


def methods_key(cfg: TrainConfig) -> TrainConfig:
    """`cfg` with its method set to the first of its `program_family`: the configs of a family's
    methods with the same static fields then share a pytree structure, and so one
    `make_methods_train` program (the method is its `method_index` argument)."""
    return cfg.replace(method=program_family(cfg)[0])


def method_index(cfg: TrainConfig) -> int:
    """`cfg.method`'s branch in the `make_methods_train` program of `methods_key(cfg)`."""
    return program_family(cfg).index(cfg.method)


def make_methods_train(config: TrainConfig):
    """One program for every method of `program_family(config)` with `config`'s static fields.

    Returns `run_chunk(state, method_index, cfg, num_updates=config.num_updates) -> (TrainState,
    records)`: the updates of `make_train(cfg).run_chunk` for the method `run_chunk.methods[
    method_index]`, where `method_index` is a traced () int32 (`method_index(method_cfg)`) and
    `cfg` a traced argument (pass `methods_key(method_cfg)`). The take-in, the improvement step
    and the records are traced once for all of them; each method's roll-outs are a branch of a
    `lax.switch` (`roll_out_and_take_in_switched`). `gpguided reproduce` runs the GP methods this
    way, which compiles one program instead of three. The records are those of
    `make_train(cfg).run_chunk` to rounding (XLA compiles the two programs differently), with
    the same draws.
    """
    key = methods_key(config)
    family = program_family(key)
    progs = tuple(make_program(key.replace(method=m)) for m in family)

    def run_chunk(state, method_index, cfg=key, num_updates=config.num_updates):
        if cfg.static_dict() != key.static_dict():
            raise ValueError(
                "the config passed to make_methods_train's run_chunk must be methods_key of a "
                f"config with its static fields: {cfg.static_dict()} != {key.static_dict()}")
        roll_out = lambda c, s, keys: roll_out_and_take_in_switched(progs, method_index, c, s, keys)  # noqa: E731
        return jax.lax.scan(lambda s, _: one_update(progs[0], cfg, s, roll_out), state, None,
                            length=num_updates)

    run_chunk.config = key
    run_chunk.methods = family
    return run_chunk


def gp_methods_key(cfg: TrainConfig) -> TrainConfig:
    """`methods_key` of a config of a method with a Q-GP prior (`ValueError` for another)."""
    if not methods.get(cfg.method).uses_gp:
        raise ValueError(f"make_gp_methods_train runs the methods with a Q-GP prior "
                         f"{methods.gp_methods()}, not {cfg.method!r}")
    return methods_key(cfg)


def make_gp_methods_train(config: TrainConfig):
    """`make_methods_train` for a method with a Q-GP prior (`ValueError` for another)."""
    gp_methods_key(config)
    return make_methods_train(config)
