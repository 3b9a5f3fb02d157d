"""Tests for gpguided_jax.policies: hand-derived scores against autodiff (property-based, with
edge cases), check_grads, the Gibbs sampler against softmax(beta E) by chi-square, sampling
distributions, exploration std, jit/vmap/scan, float32.

GP states are built directly as exact GPs over a few basis vectors (alpha = (K + s2 I)^-1 y,
C = -(K + s2 I)^-1, some slots masked off), independent of the online-update code.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from jax.flatten_util import ravel_pytree
from jax.test_util import check_grads
from scipy import stats

import gpguided_jax
from gpguided_jax import controllers, kernels, policies, sparse_gp

gpguided_jax.enable_x64()

requires_x64 = pytest.mark.skipif(not jax.config.jax_enable_x64, reason="needs float64")

SLOTS = 8
NUM_CANDIDATES = 16
CONTROLLER_NAMES = ("linear", "rbf")
_CONTROLLERS = {name: controllers.make_controller(name) for name in CONTROLLER_NAMES}


@functools.lru_cache(maxsize=None)
def get_policy(policy_name, controller_name, num_candidates=NUM_CANDIDATES):
    """One Policy object per configuration, so that jitted functions taking it as a static
    argument compile once for the whole module."""
    return policies.make_policy(
        policy_name, _CONTROLLERS[controller_name], num_candidates=num_candidates
    )


def exact_gp(key, state, action_centre, n_active, alpha_scale=1.0, dtype=jnp.float64):
    """An exact GP on `n_active` of SLOTS basis vectors scattered around (state, action_centre).

    Args:
      key: PRNG key.
      state: (2,) the query state; basis states are drawn near it so that k(x*) is not ~0.
      action_centre: () basis actions are drawn as action_centre + N(0, 2^2).
      n_active: number of active slots (the rest are masked off); may be traced.
      alpha_scale: multiplies alpha (0 gives an all-zero mean: every candidate Q is equal).
    """
    k_state, k_action, k_y, k_hyper = jax.random.split(key, 4)
    states = state + jax.random.normal(k_state, (SLOTS, 2), dtype) * jnp.array([0.5, 1.0], dtype)
    actions = action_centre + 2.0 * jax.random.normal(k_action, (SLOTS,), dtype)
    basis = jax.vmap(kernels.state_action_features)(states, actions)
    log_ls = jax.random.uniform(k_hyper, (4,), dtype, jnp.log(0.3), jnp.log(3.0))
    hyper = kernels.make_kernel_params(jnp.exp(log_ls), 2.0, 0.1, dtype=dtype)
    y = 3.0 * jax.random.normal(k_y, (SLOTS,), dtype) - 5.0
    gp = sparse_gp.exact_state(basis, y, hyper, capacity=SLOTS, num_active=n_active)
    gp = gp._replace(alpha=alpha_scale * gp.alpha)
    return gp, hyper


def random_theta(controller, key, log_scale, log_std, dtype=jnp.float64):
    flat, unravel = ravel_pytree(controller.init(dtype))
    weights = jnp.exp(log_scale) * jax.random.normal(key, flat.shape, dtype)
    return policies.PolicyParams(controller=unravel(weights), log_std=jnp.asarray(log_std, dtype))


def relative_error(hand, auto):
    """Norm-wise relative difference max|hand - auto| / max|auto| over the flattened pytree."""
    hand, auto = ravel_pytree(hand)[0], ravel_pytree(auto)[0]
    diff = jnp.max(jnp.abs(hand - auto))
    scale = jnp.max(jnp.abs(auto))
    return jnp.where(diff == 0.0, 0.0, diff / jnp.maximum(scale, 1e-300))


DEFAULT_CASE = dict(
    phi=0.7,
    omega=-1.3,
    log_w_scale=np.log(0.5),
    log_std=np.log(0.8),
    log_var_scale=np.log(3.0),
    log_floor=np.log(1e-6),
    n_active=5,
    action_mode=0,
    alpha_scale=1.0,
    beta=10.0,
    log_energy_width=0.0,
    log_cand_scale=0.0,
    log_cand_floor=np.log(1e-2),
)


def _case_inputs(case):
    return {k: jnp.asarray(v, jnp.int32 if k in ("n_active", "action_mode") else jnp.float64)
            for k, v in case.items()}


def build_case(policy, controller, key, p):
    """theta, state, action, ctx, aux for one random case (p: dict of scalars)."""
    k_theta, k_gp, k_sample = jax.random.split(key, 3)
    state = jnp.stack([p["phi"], p["omega"]])
    theta = random_theta(controller, k_theta, p["log_w_scale"], p["log_std"])
    mean_action = controller.apply(theta.controller, state)
    gp, hyper = exact_gp(k_gp, state, mean_action, p["n_active"], p["alpha_scale"])
    ctx = policies.make_context(
        gp,
        hyper,
        variance_scale=jnp.exp(p["log_var_scale"]),
        variance_floor=jnp.exp(p["log_floor"]),
        inverse_temperature=p["beta"],
        energy_width=jnp.exp(p["log_energy_width"]),
        candidate_scale=jnp.exp(p["log_cand_scale"]),
        candidate_floor=jnp.exp(p["log_cand_floor"]),
    )
    action, aux = policy.sample(k_sample, theta, state, ctx)
    u_max = controller.u_max
    action = jnp.select(
        [p["action_mode"] == 1, p["action_mode"] == 2], [u_max, -u_max], action
    ).astype(action.dtype)
    return theta, state, action, ctx, aux


# The policy and controller are NamedTuples of functions, hashable, hence static arguments.
jit_build_case = jax.jit(build_case, static_argnums=(0, 1))


@functools.lru_cache(maxsize=None)
def score_error_fn(policy_name, controller_name):
    controller = _CONTROLLERS[controller_name]
    policy = get_policy(policy_name, controller_name)

    @jax.jit
    def fn(key, p):
        theta, state, action, ctx, aux = jit_build_case(policy, controller, key, p)
        hand = policy.grad_log_prob(theta, state, action, ctx, aux)
        forward = jax.jacfwd(policy.log_prob)(theta, state, action, ctx, aux)
        reverse = jax.grad(policy.log_prob)(theta, state, action, ctx, aux)
        return relative_error(hand, forward), relative_error(hand, reverse), ravel_pytree(hand)[0]

    return fn


_case_strategy = dict(
    seed=st.integers(0, 2**31 - 1),
    phi=st.floats(-10.0, 10.0),
    omega=st.floats(-15.0, 15.0),
    log_w_scale=st.floats(-7.0, 4.0),  # large: c(s) saturated at the torque limit
    log_std=st.floats(-9.0, 4.0),  # fixed-noise sigma from 1e-4 to 55
    log_var_scale=st.floats(np.log(1e-8), np.log(1e6)),  # tiny and large guided variances
    log_floor=st.floats(np.log(1e-12), np.log(1e2)),  # sometimes the floor is active
    n_active=st.integers(0, SLOTS),  # 0: empty GP (all candidate Q equal)
    action_mode=st.sampled_from([0, 0, 1, 2]),  # sampled, +u_max, -u_max
    alpha_scale=st.sampled_from([0.0, 1.0, 30.0]),  # 0: all candidate Q equal
    beta=st.floats(0.1, 100.0),
    log_energy_width=st.floats(np.log(0.05), np.log(20.0)),
    log_cand_scale=st.floats(np.log(1e-3), np.log(1e3)),
    log_cand_floor=st.floats(np.log(1e-6), np.log(10.0)),
)

EDGE_CASES = [
    dict(DEFAULT_CASE, action_mode=1),  # action at +torque limit
    dict(DEFAULT_CASE, action_mode=2, log_w_scale=np.log(80.0)),  # c saturated, a at -limit
    dict(DEFAULT_CASE, log_std=-9.0, log_var_scale=np.log(1e-8), log_floor=np.log(1e-12)),
    dict(DEFAULT_CASE, log_std=4.0, log_var_scale=np.log(1e6)),  # large variances
    dict(DEFAULT_CASE, alpha_scale=0.0),  # all candidate Q equal
    dict(DEFAULT_CASE, n_active=0),  # empty GP
    dict(DEFAULT_CASE, log_floor=np.log(1e2)),  # variance floor active
]


def _with_edge_examples(test):
    for case in EDGE_CASES:
        test = example(seed=0, **case)(test)
    return test


def _every_policy_and_case(max_examples):
    """Every policy x controller, over `max_examples` property-based cases plus the edge cases."""

    def wrap(test):
        test = _with_edge_examples(given(**_case_strategy)(test))
        test = settings(max_examples=max_examples, deadline=None, derandomize=True)(test)
        test = pytest.mark.parametrize("policy_name", policies.POLICY_NAMES)(test)
        return requires_x64(pytest.mark.parametrize("controller_name", CONTROLLER_NAMES)(test))

    return wrap


@_every_policy_and_case(max_examples=25)
def test_grad_log_prob_matches_autodiff(policy_name, controller_name, seed, **case):
    """Hand score == autodiff score to 1e-8 relative (norm-wise, float64), against both
    reverse-mode (jax.grad) and forward-mode (jax.jacfwd) autodiff of log_prob.

    For the Gibbs policy this holds even when pi_J -> 1 (score O(1 - pi_J) << its terms)
    because both log_prob and the hand score are written relative to the selected candidate.
    """
    rel_fwd, rel_rev, hand = score_error_fn(policy_name, controller_name)(
        jax.random.PRNGKey(seed), _case_inputs(case)
    )
    assert bool(jnp.all(jnp.isfinite(hand)))
    assert float(rel_fwd) <= 1e-8, (policy_name, controller_name, float(rel_fwd))
    assert float(rel_rev) <= 1e-8, (policy_name, controller_name, float(rel_rev))


@functools.lru_cache(maxsize=None)
def variance_grad_error_fn(controller_name):
    controller = _CONTROLLERS[controller_name]
    policy = get_policy("guided_variance", controller_name)

    @jax.jit
    def fn(key, p):
        theta, state, _, ctx, _ = jit_build_case(policy, controller, key, p)
        variance, grad, _, _ = policies.guided_variance_and_grad(
            controller, theta.controller, state, ctx
        )
        auto_variance, auto = jax.value_and_grad(policies.guided_variance, argnums=1)(
            controller, theta.controller, state, ctx
        )
        return relative_error(grad, auto), variance - auto_variance, ravel_pytree(grad)[0]

    return fn


@requires_x64
@pytest.mark.parametrize("controller_name", CONTROLLER_NAMES)
@settings(max_examples=25, deadline=None, derandomize=True)
@_with_edge_examples
@given(**_case_strategy)
def test_guided_variance_gradient_eq19(controller_name, seed, **case):
    rel, value_diff, _ = variance_grad_error_fn(controller_name)(
        jax.random.PRNGKey(seed), _case_inputs(case)
    )
    assert float(value_diff) == 0.0
    assert float(rel) <= 1e-8


def test_guided_variance_gradient_is_nonzero_and_zero_on_floor():
    # Away from the floor the path through sigma^2_GP contributes; on the floor it is exactly 0.
    fn = variance_grad_error_fn("linear")
    key = jax.random.PRNGKey(11)
    _, _, grad = fn(key, _case_inputs(DEFAULT_CASE))
    assert float(jnp.max(jnp.abs(grad))) > 1e-3
    _, _, grad_floor = fn(key, _case_inputs(dict(DEFAULT_CASE, log_floor=np.log(1e2))))
    assert float(jnp.max(jnp.abs(grad_floor))) == 0.0


def test_guided_variance_on_floor_equals_fixed_noise_with_floor_variance():
    controller = _CONTROLLERS["linear"]
    guided = get_policy("guided_variance", "linear")
    fixed = get_policy("fixed_noise", "linear")
    case = _case_inputs(dict(DEFAULT_CASE, log_floor=np.log(1e2)))
    theta, state, action, ctx, aux = jit_build_case(guided, controller, jax.random.PRNGKey(2), case)
    assert float(aux.variance) == pytest.approx(1e2)
    theta_fixed = theta._replace(log_std=0.5 * jnp.log(ctx.variance_floor))
    g_guided = guided.grad_log_prob(theta, state, action, ctx, aux)
    g_fixed = fixed.grad_log_prob(theta_fixed, state, action, ctx, aux)
    np.testing.assert_allclose(
        ravel_pytree(g_guided.controller)[0], ravel_pytree(g_fixed.controller)[0], rtol=1e-12
    )
    np.testing.assert_allclose(
        guided.log_prob(theta, state, action, ctx, aux),
        fixed.log_prob(theta_fixed, state, action, ctx, aux),
        rtol=1e-12,
    )


def test_factor_one_half_in_eq17():
    # The printed eq. 17 lacks the 1/2: dropping it must disagree with autodiff.
    controller = _CONTROLLERS["linear"]
    policy = get_policy("guided_variance", "linear")
    case = _case_inputs(dict(DEFAULT_CASE, log_var_scale=np.log(30.0)))
    theta, state, action, ctx, aux = jit_build_case(policy, controller, jax.random.PRNGKey(5), case)
    variance, grad_var, mean_action, grad_mean = policies.guided_variance_and_grad(
        controller, theta.controller, state, ctx
    )
    diff = action - mean_action
    printed = jax.tree_util.tree_map(
        lambda gm, gv: diff / variance * gm + (diff**2 - variance) / variance**2 * gv,
        grad_mean,
        grad_var,
    )
    auto = jax.grad(policy.log_prob)(theta, state, action, ctx, aux).controller
    hand = policy.grad_log_prob(theta, state, action, ctx, aux).controller
    assert float(relative_error(hand, auto)) < 1e-10
    assert float(relative_error(printed, auto)) > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("controller_name", CONTROLLER_NAMES)
@pytest.mark.parametrize("policy_name", policies.POLICY_NAMES)
def test_check_grads_log_prob(policy_name, controller_name):
    controller = _CONTROLLERS[controller_name]
    policy = get_policy(policy_name, controller_name)
    theta, state, action, ctx, aux = jit_build_case(
        policy, controller, jax.random.PRNGKey(7), _case_inputs(DEFAULT_CASE)
    )
    check_grads(
        jax.jit(lambda th: policy.log_prob(th, state, action, ctx, aux)),
        (theta,),
        order=1,
        modes=("fwd", "rev"),
    )


# ------------------------------------------------------------------------------------------------
# Sampling.
# ------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_gibbs_selection_frequencies_chi_square():
    """20 000 selections vs softmax(beta E) at fixed candidates; chi-square at alpha = 0.001."""
    controller = _CONTROLLERS["linear"]
    policy = get_policy("gibbs", "linear")
    case = _case_inputs(dict(DEFAULT_CASE, beta=5.0, log_cand_floor=np.log(4.0)))
    theta, state, _, ctx, aux = jit_build_case(policy, controller, jax.random.PRNGKey(3), case)
    energy, probs = policies.gibbs_distribution(
        aux.candidates, aux.normalised_q, aux.mean_action, ctx
    )
    np.testing.assert_allclose(probs, aux.probs, rtol=1e-12)
    keys = jax.random.split(jax.random.PRNGKey(2024), 20_000)
    draws = jax.jit(jax.vmap(policies.gibbs_select, (0, None, None)))(
        keys, energy, ctx.inverse_temperature
    )
    observed = np.bincount(np.asarray(draws), minlength=NUM_CANDIDATES).astype(float)
    expected = 20_000 * np.asarray(probs)
    # Pool categories with expected count < 5 into one bin (chi-square validity).
    small = expected < 5.0
    obs = np.append(observed[~small], observed[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    if exp[-1] == 0.0:
        obs, exp = obs[:-1], exp[:-1]
    assert (~small).sum() >= 4  # the test is not vacuous
    _, p_value = stats.chisquare(obs, exp * obs.sum() / exp.sum())
    assert p_value > 1e-3, p_value


def test_gibbs_sample_consistency():
    controller = _CONTROLLERS["rbf"]
    policy = get_policy("gibbs", "rbf")
    theta, state, action, ctx, aux = jit_build_case(
        policy, controller, jax.random.PRNGKey(4), _case_inputs(DEFAULT_CASE)
    )
    assert aux.candidates.shape == (NUM_CANDIDATES,)
    assert float(action) == float(aux.candidates[aux.index])
    assert float(jnp.sum(aux.probs)) == pytest.approx(1.0)
    assert float(jnp.min(aux.normalised_q)) == 0.0 and float(jnp.max(aux.normalised_q)) == 1.0
    np.testing.assert_allclose(
        policy.log_prob(theta, state, action, ctx, aux), jnp.log(aux.probs[aux.index]), rtol=1e-10
    )
    expected_var = max(float(policies.gp_latent_variance(ctx.gp, ctx.kernel, state,
                                                         aux.mean_action)), 0.0)
    assert float(aux.variance) == pytest.approx(max(expected_var, 1e-2), rel=1e-12)
    # Exploration std: std of pi over the candidates.
    p, a = np.asarray(aux.probs), np.asarray(aux.candidates)
    expected_std = np.sqrt(p @ (a - p @ a) ** 2)
    assert float(policy.exploration_std(theta, state, ctx, aux)) == pytest.approx(expected_std)


@requires_x64
@pytest.mark.parametrize("optimism", [0.0, 0.5, 3.0])
def test_optimistic_candidate_scores_against_an_exact_gp(optimism):
    """guided_direction's candidates scored by mean + kappa sd of the GP: against the exact GP's
    posterior by Cholesky in NumPy, on the candidates the sampler drew; the normalised scores
    and the Gibbs probabilities follow from them."""
    key = jax.random.PRNGKey(11)
    k_x, k_y, k_draw = jax.random.split(key, 3)
    n = 6
    xs = np.asarray(jax.random.normal(k_x, (n, 4)), float) * [0.6, 0.6, 1.0, 1.5]
    ys = np.asarray(jax.random.normal(k_y, (n,)), float) * 3.0 - 5.0
    ls, sf2, sn2 = np.array([0.8, 0.9, 1.3, 1.1]), 2.0, 0.1
    hyper = kernels.make_kernel_params(ls, sf2, sn2)
    gp = sparse_gp.exact_state(jnp.asarray(xs), jnp.asarray(ys), hyper, capacity=SLOTS)
    ctx = policies.make_context(gp, hyper, candidate_scale=4.0)
    controller = _CONTROLLERS["linear"]
    policy = policies.make_policy("gibbs", controller, num_candidates=NUM_CANDIDATES,
                                  optimism=optimism)
    state = jnp.array([0.4, -0.3])
    theta = random_theta(controller, jax.random.PRNGKey(2), 0.0, 0.0)
    _, aux = jax.jit(policy.sample)(k_draw, theta, state, ctx)

    def k(a, b):
        z = (a[:, None, :] - b[None, :, :]) / ls
        return sf2 * np.exp(-0.5 * np.sum(z * z, axis=-1))

    x_star = np.stack([np.asarray(kernels.state_action_features(state, a)) for a in
                       np.asarray(aux.candidates)])
    chol = np.linalg.cholesky(k(xs, xs) + sn2 * np.eye(n))
    solve = lambda b: np.linalg.solve(chol.T, np.linalg.solve(chol, b))  # noqa: E731
    ks = k(x_star, xs)
    mean = ks @ solve(ys)
    var = sf2 - np.einsum("ij,ji->i", ks, solve(ks.T))
    score = mean + optimism * np.sqrt(var)
    expected = (score - score.min()) / (score.max() - score.min())
    np.testing.assert_allclose(aux.normalised_q, expected, rtol=1e-9, atol=1e-12)
    d = np.asarray(aux.candidates - aux.mean_action)
    energy = expected * np.exp(-0.5 * d * d)
    p = np.exp(10.0 * (energy - energy.max()))
    np.testing.assert_allclose(aux.probs, p / p.sum(), rtol=1e-9)
    if optimism:  # the optimism changes the choice's distribution
        plain = policies.normalise_q(jnp.asarray(mean))
        assert np.max(np.abs(np.asarray(plain) - expected)) > 1e-3


def test_optimism_must_be_non_negative():
    with pytest.raises(ValueError, match="optimism"):
        policies.make_policy("gibbs", _CONTROLLERS["linear"], optimism=-1.0)


def test_normalise_q():
    q = jnp.array([-10.0, -3.0, -7.0, -3.0])
    np.testing.assert_allclose(policies.normalise_q(q), [0.0, 1.0, 3.0 / 7.0, 1.0])
    np.testing.assert_array_equal(policies.normalise_q(jnp.full((5,), -4.2)), jnp.ones(5))
    # A range of a few ulps is numerical noise, treated as flat.
    q_noise = jnp.array([-4.2, -4.2 * (1 + 1e-15), -4.2])
    np.testing.assert_array_equal(policies.normalise_q(q_noise), jnp.ones(3))


def test_all_equal_q_energy_is_neighbourhood_term():
    controller = _CONTROLLERS["linear"]
    policy = get_policy("gibbs", "linear")
    theta, state, _, ctx, aux = jit_build_case(
        policy, controller, jax.random.PRNGKey(8), _case_inputs(dict(DEFAULT_CASE, alpha_scale=0))
    )
    np.testing.assert_array_equal(aux.normalised_q, jnp.ones(NUM_CANDIDATES))
    d = aux.candidates - aux.mean_action
    np.testing.assert_allclose(
        aux.probs, jax.nn.softmax(ctx.inverse_temperature * jnp.exp(-0.5 * d * d)), rtol=1e-12
    )


@pytest.mark.parametrize("policy_name", ["fixed_noise", "guided_variance"])
def test_gaussian_sampling_distribution_and_log_prob(policy_name):
    controller = _CONTROLLERS["linear"]
    policy = get_policy(policy_name, "linear")
    theta, state, _, ctx, _ = jit_build_case(
        policy, controller, jax.random.PRNGKey(9), _case_inputs(DEFAULT_CASE)
    )
    keys = jax.random.split(jax.random.PRNGKey(10), 20_000)
    actions, aux = jax.jit(jax.vmap(policy.sample, (0, None, None, None)))(keys, theta, state, ctx)
    mean, var = float(aux.mean_action[0]), float(aux.variance[0])
    assert mean == pytest.approx(float(controller.apply(theta.controller, state)))
    if policy_name == "fixed_noise":
        assert var == pytest.approx(float(jnp.exp(2 * theta.log_std)))
    else:
        assert var == pytest.approx(float(policies.guided_variance(
            controller, theta.controller, state, ctx)))
    z = (np.asarray(actions) - mean) / np.sqrt(var)
    assert stats.kstest(z, "norm").pvalue > 1e-3
    a0 = actions[0]
    aux0 = jax.tree_util.tree_map(lambda x: x[0], aux)
    np.testing.assert_allclose(
        policy.log_prob(theta, state, a0, ctx, aux0),
        stats.norm.logpdf(float(a0), mean, np.sqrt(var)),
        rtol=1e-10,
    )
    assert float(policy.exploration_std(theta, state, ctx, aux0)) == pytest.approx(np.sqrt(var))


def test_sampled_actions_are_not_clipped():
    controller = _CONTROLLERS["linear"]
    policy = get_policy("fixed_noise", "linear")
    theta = policies.init_params(controller, log_std=jnp.log(20.0))
    gp = sparse_gp.init(4, 4, jnp.float64)
    ctx = policies.make_context(gp, kernels.make_kernel_params(jnp.ones(4)))
    keys = jax.random.split(jax.random.PRNGKey(0), 200)
    actions, _ = jax.vmap(policy.sample, (0, None, None, None))(keys, theta, jnp.zeros(2), ctx)
    assert float(jnp.max(jnp.abs(actions))) > controller.u_max


def test_gp_helpers_agree_with_sparse_gp_predict():
    state = jnp.array([1.0, 0.5])
    gp, hyper = exact_gp(jax.random.PRNGKey(12), state, 0.3, 6)
    actions = jnp.array([-2.0, 0.3, 1.7])
    xs = jax.vmap(kernels.state_action_features, (None, 0))(state, actions)
    mean, var = jax.vmap(sparse_gp.predict, (None, 0, None))(gp, xs, hyper)
    ours_mean = jax.vmap(policies.gp_mean, (None, None, None, 0))(gp, hyper, state, actions)
    ours_var = jax.vmap(policies.gp_latent_variance, (None, None, None, 0))(
        gp, hyper, state, actions
    )
    np.testing.assert_allclose(ours_mean, mean, rtol=1e-12)
    np.testing.assert_allclose(ours_var, var, rtol=1e-12)
    many = policies.gp_means_over_actions(gp, hyper, state, actions)  # the Gibbs candidates' Q
    np.testing.assert_allclose(many, mean, rtol=1e-12)
    gp_masked = gp._replace(mask=gp.mask.at[2].set(False))  # an inactive slot is not read
    np.testing.assert_allclose(
        policies.gp_means_over_actions(gp_masked, hyper, state, actions),
        jax.vmap(policies.gp_mean, (None, None, None, 0))(gp_masked, hyper, state, actions),
        rtol=1e-12)


@functools.lru_cache(maxsize=None)
def act_vs_parts_fn(policy_name, controller_name):
    controller = _CONTROLLERS[controller_name]
    policy = get_policy(policy_name, controller_name)

    @jax.jit
    def fn(key, p):
        theta, state, _, ctx, _ = jit_build_case(policy, controller, key, p)
        k_act = jax.random.fold_in(key, 7)
        action, aux, score, std = policy.act(k_act, theta, state, ctx)
        action_s, aux_s = policy.sample(k_act, theta, state, ctx)
        score_s = policy.grad_log_prob(theta, state, action_s, ctx, aux_s)
        std_s = policy.exploration_std(theta, state, ctx, aux_s)
        return (action, aux, score, std), (action_s, aux_s, score_s, std_s)

    return fn


@pytest.mark.slow
@_every_policy_and_case(max_examples=15)
def test_act_equals_sample_score_and_std(policy_name, controller_name, seed, **case):
    """`act` (what the training loop calls at every step, with the GP and the controller evaluated
    once) gives the action, aux, score and exploration std of `sample`, `grad_log_prob` and
    `exploration_std` called one after another, to rounding (the same key, the same draws)."""
    fused, parts = act_vs_parts_fn(policy_name, controller_name)(
        jax.random.PRNGKey(seed), _case_inputs(case))
    (action, aux, score, std), (action_s, aux_s, score_s, std_s) = fused, parts
    assert int(aux.index) == int(aux_s.index)
    np.testing.assert_allclose(action, action_s, rtol=1e-12, atol=1e-12)
    for a, b in zip(jax.tree.leaves(aux), jax.tree.leaves(aux_s), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert float(relative_error(score, score_s)) < 1e-9
    np.testing.assert_allclose(std, std_s, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# jit / vmap / scan, float32.
# ------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("policy_name", policies.POLICY_NAMES)
def test_jit_vmap_and_scan(policy_name):
    controller = _CONTROLLERS["rbf"]
    policy = get_policy(policy_name, "rbf")
    theta, state, _, ctx, _ = jit_build_case(
        policy, controller, jax.random.PRNGKey(13), _case_inputs(DEFAULT_CASE)
    )
    states = state + jax.random.normal(jax.random.PRNGKey(14), (6, 2))
    keys = jax.random.split(jax.random.PRNGKey(15), 6)
    sample_v = jax.jit(jax.vmap(policy.sample, (0, None, 0, None)))
    actions, aux = sample_v(keys, theta, states, ctx)
    grads = jax.jit(jax.vmap(policy.grad_log_prob, (None, 0, 0, None, 0)))(
        theta, states, actions, ctx, aux
    )
    logps = jax.jit(jax.vmap(policy.log_prob, (None, 0, 0, None, 0)))(
        theta, states, actions, ctx, aux
    )
    assert bool(jnp.all(jnp.isfinite(logps)))
    stds = jax.vmap(policy.exploration_std, (None, 0, None, 0))(theta, states, ctx, aux)
    sample_1, grad_1 = jax.jit(policy.sample), jax.jit(policy.grad_log_prob)
    for i in (0, 5):
        a_i, aux_i = sample_1(keys[i], theta, states[i], ctx)
        np.testing.assert_allclose(actions[i], a_i, rtol=1e-12)
        g_i = grad_1(theta, states[i], a_i, ctx, aux_i)
        np.testing.assert_allclose(
            ravel_pytree(jax.tree_util.tree_map(lambda x, i=i: x[i], grads))[0],
            ravel_pytree(g_i)[0],
            rtol=1e-9,
            atol=1e-12,
        )
    assert bool(jnp.all(stds > 0))

    # Inside lax.scan, as the training loop will use it.
    def step(carry, key):
        s, score_sum = carry
        a, aux_t = policy.sample(key, theta, s, ctx)
        g = policy.grad_log_prob(theta, s, a, ctx, aux_t)
        score_sum = jax.tree_util.tree_map(jnp.add, score_sum, g)
        return (s + 0.01 * jnp.array([s[1], a]), score_sum), (a, aux_t)

    zeros = jax.tree_util.tree_map(jnp.zeros_like, theta)
    (_, total), (acts, auxs) = jax.jit(lambda k: jax.lax.scan(step, (state, zeros), k))(
        jax.random.split(jax.random.PRNGKey(16), 5)
    )
    assert acts.shape == (5,)
    assert bool(jnp.all(jnp.isfinite(ravel_pytree(total)[0])))


@pytest.mark.slow
@pytest.mark.parametrize("policy_name", policies.POLICY_NAMES)
def test_float32_runs_without_nan(policy_name):
    controller = _CONTROLLERS["linear"]
    policy = get_policy(policy_name, "linear")
    state = jnp.array([0.4, -2.0], jnp.float32)
    gp, hyper = exact_gp(jax.random.PRNGKey(17), state, 0.0, 5, dtype=jnp.float32)
    ctx = policies.make_context(gp, hyper, variance_floor=1e-6)
    theta = random_theta(controller, jax.random.PRNGKey(18), jnp.log(0.5), -0.5, jnp.float32)
    action, aux = jax.jit(policy.sample)(jax.random.PRNGKey(19), theta, state, ctx)
    grad = jax.jit(policy.grad_log_prob)(theta, state, action, ctx, aux)
    auto = jax.grad(policy.log_prob)(theta, state, action, ctx, aux)
    assert action.dtype == jnp.float32
    flat = ravel_pytree(grad)[0]
    assert flat.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(flat)))
    assert float(relative_error(grad, auto)) < 1e-4


def test_make_policy_names():
    controller = _CONTROLLERS["linear"]
    assert policies.make_policy("guided_direction", controller).name == "gibbs"
    with pytest.raises(ValueError):
        policies.make_policy("nope", controller)
