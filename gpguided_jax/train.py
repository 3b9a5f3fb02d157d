"""Algorithm 1 end to end as one pure function per seed: `make_train(config) -> train(key)`.

One seed's run is nested `lax.scan`s: updates -> episodes -> steps. Per update (Algorithm 1):

1. for each of the `episodes_per_update` episodes: act with the method's policy (the GP is held
   fixed during an episode), then take the episode's (x_t, Ret_t) pairs into the sparse GP, each
   stamped with the update index (eq. 12);
2. estimate the gradient: REINFORCE (eq. 4) with returns-to-go, or eq. 9 with Q_GP(s_t, a_t) from
   the GP after it has taken in this update's episodes; the score of each step is the hand-derived
   grad log pi of the policy that chose the action (eq. 1, 17 or 21), evaluated when it acted;
3. one optax ascent step.

Before the first update the GP hyperparameters are fitted on `hyperfit_samples` pairs collected
with the initial fixed-noise policy (paper §VI). `jit(vmap(train))(keys)` runs all seeds at once;
`init` and `run_chunk` expose the same computation in pieces for chunked, resumable runs.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from gpguided_jax import controllers as controllers_lib
from gpguided_jax import estimators, hyperfit, kernels, pendulum, policies, sparse_gp
from gpguided_jax.config import TrainConfig, validate

_POLICY_OF_METHOD = {
    "reinforce": "fixed_noise",
    "gp_pg": "fixed_noise",
    "guided_variance": "guided_variance",
    "guided_direction": "gibbs",
}


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
      grad_norm: global norm of the gradient estimate.
      num_basis_vectors: active BVs after the update's GP updates.
      fresh_bv_share: share of BVs stamped with this update (Fig. 1).
      nonfinite_grad: 1 if the gradient estimate was not finite (the step is then skipped).
      gp_resets: episodes of this update whose GP update produced a non-finite state and was
        therefore not taken in (the GP kept its state from before the episode).
    """

    mean_reward: jax.Array
    exploration_std: jax.Array
    grad_norm: jax.Array
    num_basis_vectors: jax.Array
    fresh_bv_share: jax.Array
    nonfinite_grad: jax.Array
    gp_resets: jax.Array


class Episode(NamedTuple):
    states: jax.Array  # (H, 2)
    actions: jax.Array  # (H,)
    rewards: jax.Array  # (H,)
    scores: policies.PolicyParams  # leaves (H, ...)
    exploration_std: jax.Array  # (H,)


def make_controller(cfg: TrainConfig) -> controllers_lib.Controller:
    u_max = 5.0  # the controller's squashing range; the environment clips at params.max_torque
    return controllers_lib.make_controller(cfg.controller, u_max=u_max)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    if cfg.optimizer == "sgd":
        return optax.sgd(cfg.learning_rate)
    return optax.adam(cfg.learning_rate)


def _features(states, actions):
    return jax.vmap(kernels.state_action_features)(states, actions)


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


def make_train(config: TrainConfig):
    """Builds the pure training functions of one static configuration.

    Returns `train(key, cfg=config) -> (TrainState, UpdateRecord)`: the whole run (records have a
    leading (num_updates,) axis); `cfg` may differ from `config` in traced fields only, so
    `jax.jit(jax.vmap(train))(keys)` runs seeds and `jax.vmap(train)(keys, stacked_cfgs)` sweeps.
    The pieces hang on it as attributes:
      - `train.init(key, cfg=config, prior=None) -> TrainState`: hyperparameter fit (skipped when a
        `GPPrior` is given, or for REINFORCE) and initial state.
      - `train.run_chunk(state, cfg=config, num_updates=...) -> (TrainState, UpdateRecord)`.
      - `train.fit_kernel_for_seed(key, cfg=config) -> GPPrior`, `train.collect(...)`.
      - `train.episodes(key, state, cfg=config, num_episodes=3) -> Episode`: roll out the
        method's policy at a given state (visited states for figures, evaluation).
    """
    validate(config)
    static = config
    controller = make_controller(static)
    policy = policies.make_policy(
        _POLICY_OF_METHOD[static.method], controller, num_candidates=static.num_candidates
    )
    behaviour = policies.make_policy("fixed_noise", controller)
    H = static.episode_length
    E = static.episodes_per_update

    def _check(cfg: TrainConfig):
        if cfg.static_dict() != static.static_dict():
            raise ValueError(
                "a config passed to train/run_chunk must match make_train's static fields: "
                f"{cfg.static_dict()} != {static.static_dict()}"
            )

    def rollout(key, theta, ctx, pol, cfg) -> Episode:
        key_reset, key_steps = jax.random.split(key)
        s0 = pendulum.reset(key_reset, cfg.pendulum)

        def body(s, step_key):
            key_act, key_reward = jax.random.split(step_key)
            a, aux = pol.sample(key_act, theta, s, ctx)
            score = pol.grad_log_prob(theta, s, a, ctx, aux)
            std = pol.exploration_std(theta, s, ctx, aux)
            s_next, r = pendulum.step(key_reward, s, a, cfg.pendulum)
            return s_next, (s, a, r, score, std)

        _, (s, a, r, scores, std) = jax.lax.scan(body, s0, jax.random.split(key_steps, H))
        return Episode(s, a, r, scores, std)

    def initial_theta(cfg):
        return policies.init_params(controller, log_std=cfg.init_log_std)

    def collect(key, cfg=config):
        """(x, Ret) pairs from the initial fixed-noise policy: (n_episodes * H, 4), (n * H,)."""
        theta = initial_theta(cfg)
        gp = sparse_gp.init(1, 4)
        dummy_kernel = kernels.make_kernel_params(jnp.ones(4))
        ctx = policy_context(cfg, gp, dummy_kernel)
        keys = jax.random.split(key, static.hyperfit_episodes)
        eps = jax.vmap(lambda k: rollout(k, theta, ctx, behaviour, cfg))(keys)
        returns = jax.vmap(estimators.discounted_returns, in_axes=(0, None))(eps.rewards, cfg.discount)
        xs = jax.vmap(_features)(eps.states, eps.actions).reshape(-1, 4)
        return xs, returns.reshape(-1)

    def fit_prior(key, cfg=config) -> GPPrior:
        key_data, key_subset = jax.random.split(key)
        xs, ys = collect(key_data, cfg)
        mean = jnp.mean(ys)  # the prior mean of Q_GP; the kernel is fitted to centred returns
        n = min(static.hyperfit_subset, xs.shape[0])
        if n < xs.shape[0]:
            idx = jax.random.choice(key_subset, xs.shape[0], (n,), replace=False)
            xs, ys = xs[idx], ys[idx]
        kernel = hyperfit.fit(xs, ys - mean, num_steps=static.hyperfit_steps).params
        return GPPrior(kernel, mean)

    def init(key, cfg=config, prior: GPPrior | None = None):
        _check(cfg)
        key_fit, key_run = jax.random.split(key)
        if prior is None:
            if static.uses_gp:
                prior = fit_prior(key_fit, cfg)
            else:  # unused by REINFORCE
                prior = GPPrior(kernels.make_kernel_params(jnp.ones(4)), jnp.zeros(()))
        theta = initial_theta(cfg)
        opt_state = make_optimizer(cfg).init(theta)
        gp = sparse_gp.init(static.gp_capacity, 4, prior_mean=prior.mean)
        return TrainState(theta, opt_state, gp, prior.kernel, key_run, jnp.zeros((), jnp.int32))

    def one_update(cfg, state: TrainState, _):
        key, key_eps = jax.random.split(state.key)
        t = state.update_index

        def episode(gp, key_e):
            ep = rollout(key_e, state.theta, policy_context(cfg, gp, state.kernel), policy, cfg)
            returns = estimators.discounted_returns(ep.rewards, cfg.discount)
            reset = jnp.zeros((), jnp.int32)
            if static.uses_gp:
                new_gp = sparse_gp.update_batch(
                    gp,
                    _features(ep.states, ep.actions),
                    returns,
                    state.kernel,
                    t,
                    novelty_tol=cfg.novelty_tol,
                    age_penalty=cfg.age_penalty,
                    age_scale=cfg.age_scale,
                    age_fn=static.age_fn,
                )
                # Last line of defence: never let a diverged GP state into the policy.
                healthy = jnp.all(jnp.isfinite(new_gp.alpha)) & jnp.all(jnp.isfinite(new_gp.C))
                gp = jax.tree_util.tree_map(lambda n, o: jnp.where(healthy, n, o), new_gp, gp)
                reset = (~healthy).astype(jnp.int32)
            return gp, (ep, returns, reset)

        gp, (eps, returns, resets) = jax.lax.scan(episode, state.gp, jax.random.split(key_eps, E))

        if static.uses_gp:
            feats = jax.vmap(_features)(eps.states, eps.actions)
            predict_mean = jax.vmap(jax.vmap(lambda x: sparse_gp.predict(gp, x, state.kernel)[0]))
            weights = predict_mean(feats)
        else:
            weights = returns
        baseline = None
        if static.use_baseline:
            if static.uses_gp:
                c = jax.vmap(jax.vmap(lambda s: controller.apply(state.theta.controller, s)))(eps.states)
                v_feats = jax.vmap(_features)(eps.states, c)
                baseline = predict_mean(v_feats)
            else:
                baseline = jnp.broadcast_to(returns.mean(axis=0, keepdims=True), returns.shape)
        grad = estimators.policy_gradient(eps.scores, weights, baseline)
        grad_norm = optax.global_norm(grad)
        finite = jnp.isfinite(grad_norm)
        safe_grad = jax.tree_util.tree_map(lambda g: jnp.where(finite, g, 0.0), grad)
        theta, opt_state = estimators.ascent_step(
            make_optimizer(cfg), state.theta, state.opt_state, safe_grad
        )
        theta = jax.tree_util.tree_map(lambda new, old: jnp.where(finite, new, old), theta, state.theta)
        theta = theta._replace(
            log_std=jnp.clip(theta.log_std, jnp.log(cfg.min_std), jnp.log(cfg.max_std))
        )

        n_bv = sparse_gp.num_basis_vectors(gp)
        fresh = jnp.sum(gp.mask & (gp.timestamps == t))
        record = UpdateRecord(
            mean_reward=jnp.mean(eps.rewards),
            exploration_std=jnp.mean(eps.exploration_std),
            grad_norm=grad_norm,
            num_basis_vectors=n_bv,
            fresh_bv_share=jnp.where(n_bv > 0, fresh / jnp.maximum(n_bv, 1), 0.0),
            nonfinite_grad=(~finite).astype(jnp.int32),
            gp_resets=jnp.sum(resets),
        )
        new_state = TrainState(theta, opt_state, gp, state.kernel, key, t + 1)
        return new_state, record

    def run_chunk(state, cfg=config, num_updates=static.num_updates):
        _check(cfg)
        return jax.lax.scan(lambda s, x: one_update(cfg, s, x), state, None, length=num_updates)

    def train(key, cfg=config):
        return run_chunk(init(key, cfg), cfg, static.num_updates)

    def episodes(key, state: TrainState, cfg=config, num_episodes: int = 3) -> Episode:
        """Episodes of the method's policy at `state` (theta and GP held fixed): fields gain a
        leading (num_episodes,) axis. For figures of visited states and for evaluation."""
        ctx = policy_context(cfg, state.gp, state.kernel)
        keys = jax.random.split(key, num_episodes)
        return jax.vmap(lambda k: rollout(k, state.theta, ctx, policy, cfg))(keys)

    def fit_kernel_for_seed(key, cfg=config) -> GPPrior:
        """The `GPPrior` (kernel and prior mean) that `init(key, cfg)` would fit; it depends only on
        the seed and the initial policy, so every GP method of a seed can share it."""
        return fit_prior(jax.random.split(key)[0], cfg)

    train.init = init
    train.run_chunk = run_chunk
    train.fit_prior = fit_prior
    train.fit_kernel_for_seed = fit_kernel_for_seed
    train.collect = collect
    train.episodes = episodes
    train.controller = controller
    train.policy = policy
    train.config = config
    return train
