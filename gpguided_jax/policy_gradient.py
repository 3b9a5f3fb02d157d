"""The paper's four methods as declared `methods.Method`s: one policy-gradient step per update
(steps 3-4 of Algorithm 1; design: docs/design.md#methods).

  reinforce         eq. 4: returns-to-go weigh the scores of the fixed-noise policy (eq. 1);
  gp_pg             eq. 9: Q_GP(s_t, a_t) replaces the returns, fixed noise;
  guided_variance   eq. 9 with the noise scaled by the GP's variance (eq. 16-19);
  guided_direction  eq. 9 with the Gibbs policy over candidate actions (eq. 20-22).

The three GP methods share their prior (the Q-GP kernel and prior mean), their initial state and
their improvement step: only the policy that acts in the roll-outs differs, so one compiled
program serves all three (`train.make_methods_train`). The step is `gradient_estimate` (eq. 4 or
eq. 9, with the optional baseline) followed by `optimiser_step` (clipped optax ascent, sigma
clipped to [min_std, max_std]).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import optax

from gpguided_jax import estimators, exploration, methods, sparse_gp, tasks

# The improvement step's own records (beside `methods.SHARED_RECORDS`).
RECORDS = ("grad_norm", "grad_clipped", "nonfinite_grad", "std_at_bound")


def make_optimizer(cfg) -> optax.GradientTransformation:
    """The ascent step: global-norm clipping at `max_grad_norm`, then SGD (the paper) or Adam."""
    base = optax.sgd(cfg.learning_rate) if cfg.optimizer == "sgd" else optax.adam(cfg.learning_rate)
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), base)


def _features(prog, states, actions):
    return jax.vmap(prog.task.features)(states, actions)


def gradient_estimate(prog, state, eps, returns, gp, *, q_gp: bool):
    """Step 3: eq. 4 (REINFORCE, `q_gp=False`) or eq. 9 (Q_GP of the updated GP `gp`), optionally
    with a baseline (`use_baseline`: V(s) = Q_GP(s, c(s)), or the batch-mean return-to-go)."""
    static = prog.config
    if q_gp:
        feats = jax.vmap(lambda s, a: _features(prog, s, a))(eps.states, eps.actions)
        predict_mean = jax.vmap(jax.vmap(lambda x: sparse_gp.predict(gp, x, state.kernel)[0]))
        weights = predict_mean(feats)
    else:
        weights = returns
    baseline = None
    if static.use_baseline:
        if q_gp:
            apply = jax.vmap(jax.vmap(lambda s: prog.controller.apply(state.theta.controller, s)))
            baseline = predict_mean(jax.vmap(lambda s, a: _features(prog, s, a))(
                eps.states, apply(eps.states)))
        else:
            baseline = jnp.broadcast_to(returns.mean(axis=0, keepdims=True), returns.shape)
    # the scores after an episode's end are 0 (`rollouts.rollout`), so those steps add nothing
    return estimators.policy_gradient(eps.scores, weights, baseline)


def optimiser_step(state, grad, cfg):
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


def _make_update(q_gp: bool):
    def update(prog, cfg, state, batch):
        """Steps 3-4: one gradient estimate from the update's episodes, one ascent step."""
        grad = gradient_estimate(prog, state, batch.episodes, batch.returns, batch.gp, q_gp=q_gp)
        theta, opt_state, grad_norm, finite, at_bound = optimiser_step(state, grad, cfg)
        records = dict(
            grad_norm=grad_norm,
            grad_clipped=(finite & (grad_norm > cfg.max_grad_norm)).astype(jnp.int32),
            nonfinite_grad=(~finite).astype(jnp.int32),
            std_at_bound=at_bound.astype(jnp.int32),
        )
        return theta, opt_state, state.method_state, records

    return update


def check_hand_gradient(cfg) -> None:
    """The score-function estimators (eq. 4, 9) and the Gaussian policies' scores use the
    controller's hand-derived gradient (`Controller.value_and_grad`): refuse one without it."""
    controller = tasks.make_task(cfg.env).make_controller(cfg.controller)
    if controller.value_and_grad is None:
        raise ValueError(f"TrainConfig.controller: {cfg.method} needs the controller's "
                         f"hand-derived gradient (Controller.value_and_grad), which "
                         f"{cfg.controller!r} does not give")


def no_state(prog, key, cfg):
    """The initial state of a method with no state of its own: ()."""
    del prog, key, cfg
    return ()


reinforce_update = _make_update(q_gp=False)
q_gp_update = _make_update(q_gp=True)

# The settings each of the paper's methods was tuned to, per preset (`Method.presets`; applied
# after the preset's own fields and before the caller's overrides), chosen one method at a time.
TUNED: dict[str, dict[str, dict]] = {
    # experiments/exploration_study.py tune (seeds 100-101; docs/exploration.md): correlated
    # exploration or held actions at a larger amplitude, the baseline, the horizon in seconds.
    # guided_variance keeps the age penalty of the white-noise tuning (docs/tuning_swingup.md).
    "swingup": {
        "reinforce": {"learning_rate": 0.03, "use_baseline": True, "init_log_std": math.log(4.0),
                      "discount_horizon": 0.5, "hold_time": 0.5},
        "gp_pg": {"learning_rate": 0.03, "use_baseline": True, "init_log_std": math.log(4.0),
                  "discount_horizon": 0.5, "hold_time": 0.5},
        "guided_variance": {"learning_rate": 0.03, "use_baseline": True, "age_penalty": 10.0,
                            "guided_variance_scale": 16.0, "discount_horizon": 0.5,
                            "hold_time": 0.5},
        "guided_direction": {"learning_rate": 0.03, "use_baseline": True, "candidate_scale": 16.0,
                             "discount_horizon": 0.5, "hold_time": 0.2},
    },
    # experiments/standard_tasks.py tune (seeds 100-101; docs/standard_tasks.md), the horizon in
    # seconds; then the exploration each method chose at those settings on the same seeds
    # (experiments/exploration_study.py standard-tune; docs/exploration.md), white where none is
    # named
    "pendulum-v1": {
        "reinforce": {"learning_rate": 0.03, "discount_horizon": 0.5},
        "gp_pg": {"learning_rate": 0.003, "init_log_std": math.log(2.0), "hold_time": 0.2},
        "guided_variance": {"learning_rate": 0.01},
        "guided_direction": {"learning_rate": 0.03, "discount_horizon": 0.5, "candidate_scale": 1.0},
    },
    "mountaincar-continuous": {  # the horizon in steps (the car's step counts as 1 s)
        "reinforce": {"learning_rate": 0.01, "discount_horizon": 30.0, "init_log_std": 0.0,
                      "exploration": "ou", "noise_correlation_time": 100.0},
        "gp_pg": {"learning_rate": 0.03, "discount_horizon": 300.0, "exploration": "ou",
                  "noise_correlation_time": 10.0},
        "guided_variance": {"learning_rate": 0.003, "guided_variance_scale": 0.25,
                            "hold_time": 10.0},
        "guided_direction": {"learning_rate": 0.01, "discount_horizon": 30.0,
                             "candidate_scale": 0.25, "inverse_temperature": 100.0},
    },
    # brax's pendulums: their exploration was chosen with ended episodes restarted, which their
    # presets therefore hold too
    "inverted-pendulum": {
        "reinforce": {"learning_rate": 0.01, "discount_horizon": 2.0,
                      "init_log_std": math.log(0.25), "episode_end": "restart",
                      "hold_time": 0.08},
        "gp_pg": {"learning_rate": 0.01, "episode_end": "restart", "exploration": "ou",
                  "noise_correlation_time": 0.1},
        "guided_variance": {"learning_rate": 0.003, "guided_variance_scale": 2.0,
                            "episode_end": "restart", "hold_time": 0.08},
        "guided_direction": {"learning_rate": 0.01, "discount_horizon": 2.0,
                             "inverse_temperature": 1.0, "episode_end": "restart"},
    },
    "inverted-double-pendulum": {
        "reinforce": {"learning_rate": 0.01, "init_log_std": math.log(0.25),
                      "episode_end": "restart", "exploration": "ou",
                      "noise_correlation_time": 0.1},
        "gp_pg": {"learning_rate": 0.01, "episode_end": "restart", "exploration": "ou",
                  "noise_correlation_time": 0.1},
        "guided_variance": {"learning_rate": 0.003, "discount_horizon": 2.0,
                            "guided_variance_scale": 0.25, "episode_end": "restart",
                            "hold_time": 0.08},
        "guided_direction": {"learning_rate": 0.01, "discount_horizon": 0.5,
                             "episode_end": "restart"},
    },
}


def _tuned(method: str) -> dict[str, dict]:
    """preset -> `method`'s tuned settings on it (`TUNED`)."""
    return {p: per[method] for p, per in TUNED.items() if method in per}


_ALL_NOISES = exploration.NOISES
_GAUSSIAN_NOISES = tuple(n for n in exploration.NOISES if n != "parameter")

methods.register(methods.Method(
    name="reinforce", policy="fixed_noise", prior="none", init=no_state,
    update=reinforce_update, records=RECORDS, explorations=_ALL_NOISES, paper=True,
    presets=_tuned("reinforce"), check=check_hand_gradient))
methods.register(methods.Method(
    name="gp_pg", policy="fixed_noise", prior="q_gp", init=no_state, update=q_gp_update,
    records=RECORDS, explorations=_ALL_NOISES, compare_with=("reinforce",),
    fit_fields=methods.Q_GP_FIT_FIELDS, paper=True, presets=_tuned("gp_pg"),
    check=check_hand_gradient))
methods.register(methods.Method(
    name="guided_variance", policy="guided_variance", prior="q_gp", init=no_state,
    update=q_gp_update, records=RECORDS, explorations=_GAUSSIAN_NOISES,
    compare_with=("reinforce", "gp_pg"), fit_fields=methods.Q_GP_FIT_FIELDS, paper=True,
    explain_exploration="'parameter' noise perturbs the fixed-noise policy's controller",
    presets=_tuned("guided_variance"), check=check_hand_gradient))
methods.register(methods.Method(
    name="guided_direction", policy="gibbs", prior="q_gp", init=no_state, update=q_gp_update,
    records=RECORDS, explorations=("white",), compare_with=("reinforce", "gp_pg"),
    fit_fields=methods.Q_GP_FIT_FIELDS, paper=True,
    explain_exploration="guided_direction draws its candidates afresh at each decision (hold "
                        "its choice with hold_time)", presets=_tuned("guided_direction"),
    check=check_hand_gradient))
