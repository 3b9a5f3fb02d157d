"""Tests for gpguided_jax.estimators: returns-to-go, the eq. 4 / eq. 9 estimators against a
NumPy reference, unbiasedness on a one-step task with a closed-form gradient, the optax ascent
step, jit/vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree
from scipy import stats

import gpguided_jax
from gpguided_jax import controllers, estimators, kernels, policies, sparse_gp

gpguided_jax.enable_x64()

requires_x64 = pytest.mark.skipif(not jax.config.jax_enable_x64, reason="needs float64")


def _numpy_returns(r, gamma):
    H = len(r)
    return np.array([sum(gamma**i * r[t + i] for i in range(H - t)) for t in range(H)])


@pytest.mark.parametrize("gamma", [0.0, 0.5, 0.99, 1.0])
def test_discounted_returns_matches_numpy(gamma):
    r = np.random.default_rng(0).normal(size=(3, 7))
    got = jax.jit(jax.vmap(estimators.discounted_returns, (0, None)))(jnp.asarray(r), gamma)
    for n in range(3):
        np.testing.assert_allclose(got[n], _numpy_returns(r[n], gamma), rtol=1e-12, atol=1e-12)


def _random_scores(rng, N, H):
    return {"a": jnp.asarray(rng.normal(size=(N, H))), "b": jnp.asarray(rng.normal(size=(N, H, 3)))}


def test_policy_gradient_matches_numpy_and_baseline():
    rng = np.random.default_rng(1)
    N, H = 4, 6
    scores = _random_scores(rng, N, H)
    weights = rng.normal(size=(N, H))
    baseline = rng.normal(size=(N, H))
    got = jax.jit(estimators.policy_gradient)(scores, jnp.asarray(weights))
    np.testing.assert_allclose(got["a"], np.sum(np.asarray(scores["a"]) * weights) / N, rtol=1e-12)
    expected_b = np.einsum("nhk,nh->k", np.asarray(scores["b"]), weights) / N
    np.testing.assert_allclose(got["b"], expected_b, rtol=1e-12)
    with_baseline = estimators.gp_policy_gradient(scores, jnp.asarray(weights), jnp.asarray(baseline))
    reference = estimators.policy_gradient(scores, jnp.asarray(weights - baseline))
    for key in ("a", "b"):
        np.testing.assert_allclose(with_baseline[key], reference[key], rtol=1e-12)


def test_reinforce_uses_discounted_returns_to_go():
    rng = np.random.default_rng(2)
    N, H, gamma = 3, 5, 0.9
    scores = _random_scores(rng, N, H)
    rewards = rng.normal(size=(N, H))
    got = jax.jit(estimators.reinforce_gradient)(scores, jnp.asarray(rewards), gamma)
    returns = np.stack([_numpy_returns(rewards[n], gamma) for n in range(N)])
    expected = np.einsum("nhk,nh->k", np.asarray(scores["b"]), returns) / N
    np.testing.assert_allclose(got["b"], expected, rtol=1e-12)
    # Batched over seeds with vmap.
    stacked = jax.tree_util.tree_map(lambda x: jnp.stack([x, 2 * x]), scores)
    batched = jax.vmap(estimators.reinforce_gradient, (0, None, None))(
        stacked, jnp.asarray(rewards), gamma
    )
    np.testing.assert_allclose(batched["b"][1], 2 * got["b"], rtol=1e-12)


def test_ascent_step_sgd_and_adam():
    params = {"w": jnp.array([1.0, -2.0]), "b": jnp.array(0.5)}
    grad = {"w": jnp.array([0.3, -0.1]), "b": jnp.array(2.0)}
    sgd = optax.sgd(0.1)
    new, _ = jax.jit(estimators.ascent_step, static_argnums=0)(sgd, params, sgd.init(params), grad)
    np.testing.assert_allclose(new["w"], params["w"] + 0.1 * grad["w"], rtol=1e-12)
    np.testing.assert_allclose(new["b"], params["b"] + 0.1 * grad["b"], rtol=1e-12)
    adam = optax.adam(0.01)
    new, state = estimators.ascent_step(adam, params, adam.init(params), grad)
    # Adam's first step moves every coordinate by ~lr in the direction of ascent.
    np.testing.assert_allclose(new["w"] - params["w"], 0.01 * jnp.sign(grad["w"]), rtol=1e-4)
    assert int(state[0].count) == 1


# ------------------------------------------------------------------------------------------------
# Unbiasedness on a one-step task: R(s, a) = -(a - a*)^2 + eps, eps ~ N(0, sigma_r^2), H = 1.
# With a ~ N(c, v):  J = E[R] = -((c - a*)^2 + v), so grad J is known in closed form.
# ------------------------------------------------------------------------------------------------

STATE = jnp.array([1.0, 0.5])
TARGET = 1.5
REWARD_STD = 2.0
NUM_BATCHES, NUM_EPISODES = 2000, 10
ALPHA = 0.01  # family-wise significance level of the CI check, Bonferroni over the components


def _theta(controller):
    return policies.PolicyParams(
        controller=controllers.LinearParams(weights=jnp.array([0.2, -0.1, 0.05, 0.1])),
        log_std=jnp.log(jnp.asarray(0.7)),
    )


def _one_step_batches(policy, theta, ctx, key, q_fn=None, baseline=None):
    """Per-batch REINFORCE (eq. 4) and GP (eq. 9) estimates, flattened: (NUM_BATCHES, P) each.

    Every draw is one episode of one step; draws are vmapped flat and reshaped to
    (batches, episodes, steps = 1).
    """
    k_act, k_noise = jax.random.split(key)
    total = NUM_BATCHES * NUM_EPISODES
    keys = jax.random.split(k_act, total)
    actions, aux = jax.vmap(policy.sample, (0, None, None, None))(keys, theta, STATE, ctx)
    scores = jax.vmap(policy.grad_log_prob, (None, None, 0, None, 0))(
        theta, STATE, actions, ctx, aux
    )
    shape = (NUM_BATCHES, NUM_EPISODES, 1)
    scores = jax.tree_util.tree_map(lambda x: x.reshape(shape + x.shape[1:]), scores)
    exact_q = -((actions - TARGET) ** 2)
    rewards = exact_q + REWARD_STD * jax.random.normal(k_noise, actions.shape)
    q_values = exact_q if q_fn is None else q_fn(actions)
    rewards, q_values = rewards.reshape(shape), q_values.reshape(shape)
    b = None if baseline is None else jnp.broadcast_to(baseline, shape)
    reinforce = jax.vmap(estimators.reinforce_gradient, (0, 0, None, 0 if b is not None else None))(
        scores, rewards, 0.9, b
    )
    gp = jax.vmap(estimators.gp_policy_gradient)(scores, q_values)
    flat = jax.vmap(lambda g: ravel_pytree(g)[0])
    return np.asarray(flat(reinforce)), np.asarray(flat(gp))


def _assert_contains(estimates, truth, name):
    mean = estimates.mean(axis=0)
    se = estimates.std(axis=0, ddof=1) / np.sqrt(len(estimates))
    mask = se > 0  # components with no randomness (scores identically 0) must be exact
    z = stats.norm.ppf(1.0 - ALPHA / (2 * max(mask.sum(), 1)))
    np.testing.assert_allclose(mean[~mask], truth[~mask], atol=1e-12)
    outside = np.abs(mean - truth)[mask] > z * se[mask]
    assert not outside.any(), (name, mean, truth, se)


def _variance_ratio(reinforce, gp):
    return float(reinforce.var(axis=0, ddof=1).sum() / gp.var(axis=0, ddof=1).sum())


def _exact_gp_at_state(actions, targets, hyper):
    xs = jax.vmap(kernels.state_action_features, (None, 0))(STATE, actions)
    # 300 actions at one state: K is numerically singular; only alpha (exact) matters here.
    return sparse_gp.exact_state(xs, targets, hyper, jitter=1e-10)


@pytest.mark.slow
@requires_x64
def test_unbiased_fixed_noise_reinforce_and_gp_estimators(capsys):
    controller = controllers.linear_controller()
    policy = policies.make_policy("fixed_noise", controller)
    theta = _theta(controller)
    ctx = policies.make_context(sparse_gp.init(2, 4), kernels.make_kernel_params(jnp.ones(4)))
    c, dc = controller.value_and_grad(theta.controller, STATE)
    sigma2 = jnp.exp(2 * theta.log_std)
    truth = np.asarray(ravel_pytree(policies.PolicyParams(
        controller=jax.tree_util.tree_map(lambda g: -2.0 * (c - TARGET) * g, dc),
        log_std=-2.0 * sigma2,
    ))[0])

    reinforce, gp_exact = _one_step_batches(policy, theta, ctx, jax.random.PRNGKey(0))
    _assert_contains(reinforce, truth, "reinforce")
    _assert_contains(gp_exact, truth, "gp (exact Q)")
    ratio_exact = _variance_ratio(reinforce, gp_exact)
    assert ratio_exact > 1.0

    # A GP fitted to 300 independent noisy samples (exact GP posterior mean as Q_GP).
    hyper = kernels.make_kernel_params(jnp.array([1.0, 1.0, 1.0, 1.5]), 20.0, REWARD_STD**2)
    k_fit_a, k_fit_r = jax.random.split(jax.random.PRNGKey(1))
    fit_actions = c + 1.5 * jax.random.normal(k_fit_a, (300,))
    fit_targets = -((fit_actions - TARGET) ** 2) + REWARD_STD * jax.random.normal(k_fit_r, (300,))
    gp_state = _exact_gp_at_state(fit_actions, fit_targets, hyper)
    q_fn = jax.vmap(lambda a: policies.gp_mean(gp_state, hyper, STATE, a))
    reinforce2, gp_fitted = _one_step_batches(policy, theta, ctx, jax.random.PRNGKey(2), q_fn)
    ratio_fitted = _variance_ratio(reinforce2, gp_fitted)
    # A fitted GP is biased by its fit error: require the mean within 10% of |grad J|.
    bias = np.abs(gp_fitted.mean(axis=0) - truth).max() / np.abs(truth).max()
    assert bias < 0.1, bias
    assert ratio_fitted > 1.0

    # Baseline b(s) = V(s) = -((c - a*)^2 + sigma^2) (a function of the state only): still
    # unbiased, lower variance.
    reinforce_b, _ = _one_step_batches(
        policy, theta, ctx, jax.random.PRNGKey(0), None, -((c - TARGET) ** 2 + sigma2)
    )
    _assert_contains(reinforce_b, truth, "reinforce with baseline")
    ratio_baseline = _variance_ratio(reinforce, reinforce_b)
    assert ratio_baseline > 1.0
    with capsys.disabled():
        print(
            f"\n[estimators] variance ratio REINFORCE / GP: exact Q {ratio_exact:.2f}, "
            f"fitted GP {ratio_fitted:.2f} (GP bias {bias:.3f} of |grad J|); "
            f"REINFORCE / REINFORCE with baseline {ratio_baseline:.2f}"
        )


@pytest.mark.slow
@requires_x64
def test_unbiased_guided_variance_reinforce():
    """REINFORCE with the eq. 17 score (incl. the 1/2 and the path through sigma^2_GP) is
    unbiased for grad J = -grad[(c - a*)^2 + sigma^2_GP(c)], taken here by autodiff."""
    controller = controllers.linear_controller()
    policy = policies.make_policy("guided_variance", controller)
    theta = _theta(controller)
    hyper = kernels.make_kernel_params(jnp.array([1.0, 1.0, 1.0, 0.8]), 1.0, 0.05)
    gp_state = _exact_gp_at_state(jnp.array([-1.0, 0.8, 1.2, 2.5]), jnp.zeros(4), hyper)
    ctx = policies.make_context(gp_state, hyper, variance_scale=2.0, variance_floor=1e-4)

    def objective(th):
        c = controller.apply(th.controller, STATE)
        return -((c - TARGET) ** 2 + policies.guided_variance(controller, th.controller, STATE, ctx))

    truth = np.asarray(ravel_pytree(jax.grad(objective)(theta))[0])
    _, dvar, _, _ = policies.guided_variance_and_grad(controller, theta.controller, STATE, ctx)
    assert float(jnp.max(jnp.abs(ravel_pytree(dvar)[0]))) > 0.05  # the variance path matters
    reinforce, gp_exact = _one_step_batches(policy, theta, ctx, jax.random.PRNGKey(3))
    _assert_contains(reinforce, truth, "guided reinforce")
    _assert_contains(gp_exact, truth, "guided gp (exact Q)")
