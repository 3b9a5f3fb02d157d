"""gp_critic (`gpguided_jax.critic`): the closed-form expectation of Q_GP under a Gaussian policy
and its hand-derived gradient against quadrature, Monte Carlo and autodiff; the trust region;
K = 0 as gp_pg; the method against gp_pg on a bandit with a known optimum."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from gpguided_jax import config as C
from gpguided_jax import critic, estimators, kernels, policy_gradient, sparse_gp, tasks
from gpguided_jax import train as T

TOL = {jnp.float32: dict(rtol=2e-4, atol=2e-5), jnp.float64: dict(rtol=1e-9, atol=1e-11)}
# (std, action length-scale): the policy's noise small and large against the critic's scale
SCALES = [(0.05, 1.0), (2.0, 0.3)]


def _random_gp(seed, dtype, slots=9, dim=3, active=7):
    rng = np.random.default_rng(seed)
    mask = np.arange(slots) < active
    gp = sparse_gp.init(slots - 1, dim, dtype, prior_mean=-1.5)
    gp = gp._replace(basis_vectors=jnp.asarray(rng.normal(size=(slots, dim)) * mask[:, None], dtype),
                     alpha=jnp.asarray(rng.normal(size=slots) * mask, dtype),
                     mask=jnp.asarray(mask))
    return gp, rng


def _kernel(dtype, action_scale, dim=3):
    return kernels.make_kernel_params(np.r_[np.full(dim - 1, 0.8), action_scale], 1.7, 0.1,
                                      dtype=dtype)


def _numpy_kernel(kernel, a, b):
    """The ARD squared-exponential kernel between the rows of a (N, D) and b (M, D), float64
    NumPy: (N, M)."""
    z = (a[:, None, :] - b[None]) / np.asarray(kernel.lengthscales, float)
    return float(kernel.signal_variance) * np.exp(-0.5 * np.sum(z * z, axis=-1))


def _numpy_mean(gp, kernel, x):
    """mu_Q at inputs x (N, D) from the GP's definition, in float64 NumPy."""
    k = _numpy_kernel(kernel, x, np.asarray(gp.basis_vectors, float)) * np.asarray(gp.mask)
    return float(gp.prior_mean) + k @ np.asarray(gp.alpha, float)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("std, action_scale", SCALES)
def test_the_expected_q_against_quadrature_and_monte_carlo(dtype, std, action_scale):
    gp, rng = _random_gp(0, dtype)
    kernel = _kernel(dtype, action_scale)
    x_state, mean = rng.normal(size=2), 0.3
    # the library's own predictive mean agrees with the definition used as the reference
    x0 = np.r_[x_state, mean]
    np.testing.assert_allclose(float(sparse_gp.predict(gp, jnp.asarray(x0, dtype), kernel)[0]),
                               _numpy_mean(gp, kernel, x0[None])[0], **TOL[dtype])
    factors = critic.state_factors(gp, kernel, jnp.asarray(x_state, dtype))
    got = float(critic.expected_q(gp, kernel, factors, jnp.asarray(mean, dtype),
                                  jnp.asarray(std, dtype)))
    # a fine grid over +-12 standard deviations (float64 NumPy)
    u = np.linspace(-12.0, 12.0, 48001)
    density = np.exp(-0.5 * u * u) / np.sqrt(2 * np.pi)
    xs = np.column_stack([np.tile(x_state, (u.size, 1)), mean + std * u])
    reference = integrate.trapezoid(density * _numpy_mean(gp, kernel, xs), u)
    np.testing.assert_allclose(got, reference, **TOL[dtype])
    # Monte Carlo over actions, within five standard errors
    draws = mean + std * np.random.default_rng(1).normal(size=40_000)
    values = _numpy_mean(gp, kernel, np.column_stack([np.tile(x_state, (draws.size, 1)), draws]))
    assert abs(got - values.mean()) < 5 * values.std() / np.sqrt(draws.size) + 1e-5


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("std, action_scale", SCALES)
def test_the_hand_derived_gradient_against_autodiff_and_quadrature(dtype, std, action_scale):
    gp, rng = _random_gp(2, dtype)
    kernel = _kernel(dtype, action_scale)
    x_state = jnp.asarray(rng.normal(size=2), dtype)
    factors = critic.state_factors(gp, kernel, x_state)
    mean, log_std = jnp.asarray(-0.4, dtype), jnp.log(jnp.asarray(std, dtype))
    _, d_mean, d_log = jax.jit(critic.expected_q_and_grad)(gp, kernel, factors, mean,
                                                         jnp.exp(log_std))
    auto = jax.jit(jax.grad(lambda m, ls: critic.expected_q(gp, kernel, factors, m, jnp.exp(ls)),
                            argnums=(0, 1)))(mean, log_std)
    np.testing.assert_allclose(float(d_mean), float(auto[0]), **TOL[dtype])
    np.testing.assert_allclose(float(d_log), float(auto[1]), **TOL[dtype])
    if dtype == jnp.float64:
        # d/dmean E[mu(c + std u)] = E[dmu/da], by quadrature of the GP's autodiff gradient
        u, w = np.polynomial.hermite_e.hermegauss(200)
        dmu = jax.jit(jax.vmap(jax.grad(lambda a: sparse_gp.predict(
            gp, jnp.concatenate([x_state, a[None]]), kernel)[0])))(mean + std * jnp.asarray(u))
        np.testing.assert_allclose(float(d_mean), float(np.sum(w * dmu) / np.sqrt(2 * np.pi)),
                                   rtol=1e-6 if std / action_scale < 1 else 1e-2)


def _data_points(seed, n=7, dim=3, spread=1.0):
    """n random GP inputs (the states normal, the actions uniform in [-2, 2], all times `spread`:
    a small spread makes the Gram matrix ill-conditioned) and targets, float64: (xs, ys)."""
    rng = np.random.default_rng(seed)
    xs = np.column_stack([rng.normal(size=(n, dim - 1)), rng.uniform(-2.0, 2.0, size=n)]) * spread
    return xs, rng.normal(size=n)


def _numpy_variance(xs, kernel, x):
    """The exact GP's latent variance k** - k^T (K + sigma_n^2 I)^-1 k at inputs x (N, D), by
    Cholesky in float64 NumPy."""
    from scipy import linalg

    gram = _numpy_kernel(kernel, xs, xs) + float(kernel.noise_variance) * np.eye(len(xs))
    kx = _numpy_kernel(kernel, xs, x)
    return float(kernel.signal_variance) - np.sum(
        kx * linalg.cho_solve(linalg.cho_factor(gram, lower=True), kx), axis=0)


# SCALES, and an ill-conditioned Gram matrix (condition number ~1e7): (std, action scale, spread)
VARIANCE_CASES = [(0.05, 1.0, 1.0), (2.0, 0.3, 1.0), (0.3, 0.7, 0.02)]


@pytest.mark.parametrize("std, action_scale, spread", VARIANCE_CASES)
def test_the_expected_variance_against_quadrature_of_the_exact_gp(std, action_scale, spread):
    """E_a sigma_Q^2 in closed form against the exact GP's variance (Cholesky, NumPy) integrated
    over a fine grid of actions, and its derivative in the mean action against a central
    difference of that integral; float64, which `critic_optimism` requires."""
    dtype = jnp.float64
    kernel = _kernel(dtype, action_scale)
    xs, ys = _data_points(6, spread=spread)
    gp = sparse_gp.exact_state(jnp.asarray(xs), jnp.asarray(ys), kernel, capacity=9)
    correction = sparse_gp.covariance_correction(gp)
    x_state, mean = xs[2, :2] + 0.1 * spread, 0.4 * spread
    factors = critic.state_factors(gp, kernel, jnp.asarray(x_state))

    def reference(m):
        u = np.linspace(-12.0, 12.0, 24001)
        density = np.exp(-0.5 * u * u) / np.sqrt(2 * np.pi)
        grid = np.column_stack([np.tile(x_state, (u.size, 1)), m + std * u])
        return integrate.trapezoid(density * _numpy_variance(xs, kernel, grid), u)

    value = jax.jit(critic.expected_variance)
    got = float(value(gp, kernel, correction, factors, jnp.asarray(mean), jnp.asarray(std)))
    want = reference(mean)
    assert 0.01 < want < float(kernel.signal_variance)  # neither at the data nor away from it
    np.testing.assert_allclose(got, want, rtol=1e-7 if spread < 1 else 1e-9)
    h = 1e-4
    d_mean = jax.grad(lambda m: value(gp, kernel, correction, factors, m, std))(mean)
    np.testing.assert_allclose(float(d_mean), (reference(mean + h) - reference(mean - h)) / (2 * h),
                               rtol=1e-5, atol=1e-9)


def _pairwise_expected_variance(gp, kernel, correction, factors, mean, log_std):
    """E_a sigma_Q^2 from every pair's Gaussian integral taken as it stands (M x M exponentials;
    the form `critic.expected_variance` splits), for autodiff."""
    la2 = kernel.lengthscales[-1] ** 2
    w = la2 + 2.0 * jnp.exp(2.0 * log_std)
    b = gp.basis_vectors[:, -1]
    gap, mid = b[:, None] - b[None, :], 0.5 * (b[:, None] + b[None, :])
    g = jnp.sqrt(la2 / w) * jnp.exp(-0.25 * gap * gap / la2 - (mean - mid) ** 2 / w)
    return kernel.signal_variance + jnp.sum(correction * jnp.outer(factors, factors) * g)


@pytest.mark.parametrize("dtype, std, action_scale", [
    (jnp.float32, 0.01, 0.05), (jnp.float32, 3.0, 5.0), (jnp.float64, *SCALES[0]),
    (jnp.float64, *SCALES[1])])
def test_the_expected_variance_and_its_gradient_against_the_pairwise_integral(dtype, std,
                                                                              action_scale):
    """The split form and its hand-derived derivatives in the mean action and log std against
    the pairs' integral and its autodiff, at small and large std / l_a, in float32 and float64
    (the GP built in float64, then cast)."""
    kernel64 = _kernel(jnp.float64, action_scale)
    xs, ys = _data_points(10)
    gp64 = sparse_gp.exact_state(jnp.asarray(xs), jnp.asarray(ys), kernel64, capacity=12)
    cast = lambda t: jax.tree_util.tree_map(  # noqa: E731
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, t)
    gp, kernel = cast(gp64), cast(kernel64)
    correction = cast(sparse_gp.covariance_correction(gp64))
    factors = critic.state_factors(gp, kernel, jnp.asarray(xs[3, :2] + 0.05, dtype))
    mean, log_std = jnp.asarray(xs[3, 2] + 0.1, dtype), jnp.log(jnp.asarray(std, dtype))
    got = jax.jit(critic.expected_variance_and_grad)(gp, kernel, correction, factors, mean,
                                                     jnp.exp(log_std))
    want = jax.value_and_grad(_pairwise_expected_variance, argnums=(4, 5))(
        gp, kernel, correction, factors, mean, log_std)
    assert float(want[0]) > 1e-3  # not clipped
    tol = dict(rtol=1e-4, atol=1e-5) if dtype == jnp.float32 else dict(rtol=1e-10, atol=1e-12)
    for g, w in zip(got, (want[0],) + want[1]):
        np.testing.assert_allclose(float(g), float(w), **tol)


def test_critic_optimism_is_refused_in_float32():
    with pytest.raises(ValueError, match="critic_optimism: needs dtype 'float64'"):
        C.preset("tiny", method="gp_critic", critic_optimism=1.0, dtype="float32")


def test_optimism_moves_the_policy_towards_the_actions_the_critic_has_not_seen():
    """Data at actions in [-2, -1] only and a flat mean (every return 0, the prior mean 0): the
    surrogate's mean part has nothing to climb, and its variance part grows towards positive
    actions. kappa > 0 raises the mean action, kappa < 0 lowers it, the mean alone leaves it (to
    rounding) where it was."""
    dtype = jnp.float64
    kernel = _kernel(dtype, 0.7)
    controller, states = _controller_and_states(dtype, n=32)
    xs = np.column_stack([np.asarray(states)[:12], np.linspace(-2.0, -1.0, 12)])
    gp = sparse_gp.exact_state(jnp.asarray(xs), jnp.zeros(12, dtype), kernel, capacity=15)
    correction = sparse_gp.covariance_correction(gp)
    theta = T.policies.PolicyParams(controller=controller.init(dtype),
                                    log_std=jnp.asarray(np.log(0.5), dtype))
    factors = jax.vmap(lambda s: critic.state_factors(gp, kernel, s))(states)
    weights = jnp.ones(states.shape[0], dtype)

    def mean_action_after(kappa):  # kappa None: the mean alone
        new, gain, _, _ = critic.improve(
            controller, gp, kernel, theta, theta, states, factors, weights, num_steps=30,
            learning_rate=0.05, trust_region=1.0, min_std=0.5, max_std=0.5, optimism=kappa,
            correction=correction)
        return jnp.mean(jax.vmap(lambda s: controller.apply(new.controller, s))(states)), gain

    start = float(jnp.mean(jax.vmap(lambda s: controller.apply(theta.controller, s))(states)))
    (up, down), (gain_up, gain_down) = jax.jit(jax.vmap(mean_action_after))(jnp.array([1.0, -1.0]))
    flat, _ = jax.jit(lambda: mean_action_after(None))()
    assert float(up) > start + 0.1 and float(down) < start - 0.1, (start, up, down)
    assert abs(float(flat) - start) < 1e-6
    assert float(gain_up) > 0 and float(gain_down) > 0


def _controller_and_states(dtype, n=64):
    rng = np.random.default_rng(5)
    centres = rng.normal(size=(6, 2))
    controller = tasks._observation_controller("rbf", 2.0, np.zeros(2), np.ones(2), centres, 0.7)
    states = jnp.asarray(rng.normal(size=(n, 2)), dtype)
    return controller, states


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_the_surrogate_gradient_through_the_controller_against_autodiff(dtype):
    gp, rng = _random_gp(3, dtype)
    kernel = _kernel(dtype, 0.6)
    controller, states = _controller_and_states(dtype)
    theta = T.policies.PolicyParams(
        controller=jax.tree_util.tree_map(lambda w: jnp.asarray(
            rng.normal(size=w.shape) * 0.5, dtype), controller.init(dtype)),
        log_std=jnp.asarray(np.log(0.7), dtype))
    factors = jax.jit(jax.vmap(lambda s: critic.state_factors(gp, kernel, s)))(states)
    weights = jnp.asarray(rng.uniform(size=states.shape[0]) > 0.2, dtype)

    def value(t):
        c = jax.vmap(lambda s: controller.apply(t.controller, s))(states)
        q = jax.vmap(lambda f, m: critic.expected_q(gp, kernel, f, m, jnp.exp(t.log_std)))(factors, c)
        return jnp.sum(weights * q) / jnp.sum(weights)

    got_value, got = jax.jit(lambda t: critic.surrogate_and_grad(
        controller, gp, kernel, t, states, factors, weights))(theta)
    np.testing.assert_allclose(float(got_value), float(jax.jit(value)(theta)), **TOL[dtype])
    auto = jax.jit(jax.grad(value))(theta)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(auto)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), **TOL[dtype])


@pytest.mark.parametrize("p, q", [((0.3, 0.5), (-0.2, 0.9)), ((0.3, 0.5), (0.301, 0.5005))])
def test_the_gaussian_kl_against_its_integral(p, q):
    def integrand(a):
        lp = -0.5 * ((a - p[0]) / p[1]) ** 2 - np.log(p[1])
        lq = -0.5 * ((a - q[0]) / q[1]) ** 2 - np.log(q[1])
        return np.exp(lp) / np.sqrt(2 * np.pi) * (lp - lq)

    reference, _ = integrate.quad(integrand, -20, 20, epsabs=1e-16, epsrel=1e-12, limit=200)
    np.testing.assert_allclose(float(critic.gaussian_kl(*p, *q)), reference, rtol=1e-8)
    # float32 keeps the relative precision of a small KL
    got32 = critic.gaussian_kl(*(jnp.float32(v) for v in (*p, *q)))
    np.testing.assert_allclose(float(got32), reference, rtol=1e-4)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("delta", [0.001, 0.05])
def test_the_steps_end_within_the_trust_region_and_climb_the_surrogate(dtype, delta):
    gp, rng = _random_gp(4, dtype)
    kernel = _kernel(dtype, 0.5)
    controller, states = _controller_and_states(dtype)
    theta = T.policies.PolicyParams(controller=controller.init(dtype),
                                    log_std=jnp.asarray(np.log(0.8), dtype))
    factors = jax.jit(jax.vmap(lambda s: critic.state_factors(gp, kernel, s)))(states)
    weights = jnp.ones(states.shape[0], dtype)
    improve = jax.jit(lambda t: critic.improve(
        controller, gp, kernel, t, t, states, factors, weights, num_steps=40, learning_rate=0.3,
        trust_region=delta, min_std=0.05, max_std=5.0))
    new, gain, kl, frac = improve(theta)
    assert float(kl) <= delta * (1 + 1e-6)
    np.testing.assert_allclose(float(kl), float(jax.jit(critic.mean_kl, static_argnums=0)(
        controller, theta, new, states, weights)), **TOL[dtype])
    assert float(frac) in [0.0] + [0.5 ** j for j in range(critic.LINE_SEARCH_HALVINGS + 1)]
    assert float(gain) > 0 and float(frac) > 0
    if delta == 0.001:  # 40 steps of 0.3 leave a small region: the line search cut the move
        assert float(frac) < 1


@pytest.fixture(scope="module")
def critic_registered():
    assert "gp_critic" in C.METHODS  # a built-in method, named in the registry
    return "gp_critic"


@pytest.mark.training
def test_with_no_critic_steps_it_is_gp_pg_bit_for_bit(critic_registered):
    """On the same update's batch (steps 1-2 are shared), gp_critic's step with K = 0 is gp_pg's
    bit for bit; with K > 0 it moves further, and with critic_optimism elsewhere."""
    prior = T.GPPrior(kernels.make_kernel_params(np.ones(4), 0.5, 0.05), jnp.asarray(-1.0))
    cfgs = {k: C.preset("tiny", method=critic_registered, critic_steps=k) for k in (0, 2)}
    cfgs["optimistic"] = cfgs[2].replace(critic_optimism=1.0)
    cfgs["window"] = cfgs[2].replace(critic_window=2)
    progs = {k: T.make_program(c) for k, c in cfgs.items()}
    state = T.initial_state(progs[0], jax.random.PRNGKey(4), cfgs[0], prior)
    assert state.method_state == () and critic.init(progs["window"], None, cfgs["window"]).weights.sum() == 0

    @jax.jit
    def updates(state):
        keys = jax.random.split(jax.random.PRNGKey(5), cfgs[0].episodes_per_update)
        gp, eps, returns, _, _ = T.roll_out_and_take_in(progs[0], cfgs[0], state, keys)
        batch = T.Batch(eps, returns, gp)
        # window W = 2 holding: other states at weight 0, this update's own states again, other
        # states
        own = eps.states[:, ::progs[0].hold].reshape(1, -1, eps.states.shape[-1])
        ones = jnp.ones(own.shape[:2], own.dtype)
        windows = (critic.Window(own + 0.5, 0.0 * ones), critic.Window(own, ones),
                   critic.Window(own + 0.5, ones))
        windowed = [critic.critic_update(progs["window"], cfgs["window"],
                                         state._replace(method_state=w), batch) for w in windows]
        return (policy_gradient.q_gp_update(progs[0], cfgs[0], state, batch),
                *(critic.critic_update(progs[k], cfgs[k], state, batch)
                  for k in (0, 2, "optimistic")),
                (eps, returns), windowed)

    ((theta, opt, _, rec), (theta0, opt0, _, rec0), (theta5, _, _, rec5), (theta_o, _, _, rec_o),
     (eps, returns), windowed) = updates(state)
    for a, b in zip(jax.tree_util.tree_leaves((theta, opt)), jax.tree_util.tree_leaves((theta0, opt0))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for f, v in rec.items():
        np.testing.assert_array_equal(np.asarray(v), np.asarray(rec0[f]), f)
    assert float(rec0["critic_step_fraction"]) == 0.0 and float(rec5["critic_step_fraction"]) > 0
    # the critic's error on the update's episodes (those of the batch above), by the GP before it
    # took them in: 1 - R^2
    x = jax.vmap(jax.vmap(progs[0].task.features))(eps.states, eps.actions).reshape(-1, 4)
    mu = np.asarray(jax.jit(jax.vmap(lambda xi: sparse_gp.predict(state.gp, xi, state.kernel)[0]))(x))
    ret = np.asarray(returns).reshape(-1)
    expected = np.sum((ret - mu) ** 2) / np.sum((ret - ret.mean()) ** 2)
    np.testing.assert_allclose(float(rec0["critic_error"]), expected, rtol=1e-9)
    assert float(rec0["action_lengthscale"]) == float(state.kernel.lengthscales[-1])
    assert not np.array_equal(np.asarray(theta.controller.weights), np.asarray(theta5.controller.weights))
    # with critic_optimism the surrogate's steps differ from the mean's
    assert all(np.isfinite(float(v)) for v in rec_o.values())
    assert not np.array_equal(np.asarray(theta_o.controller.weights),
                              np.asarray(theta5.controller.weights))
    # a window of updates: an empty one, or one that repeats the update's states, leaves the
    # weighted means over the states, and so the step, as they are; other states move it
    for (theta_w, _, window, rec_w), same in zip(windowed, (True, True, False)):
        close = np.allclose(np.asarray(theta_w.controller.weights),
                            np.asarray(theta5.controller.weights), rtol=1e-8, atol=1e-10)
        assert close == same, (same, rec_w["critic_step_fraction"], rec5["critic_step_fraction"])
        # the window the next update reads holds this update's decision states and weights
        np.testing.assert_array_equal(np.asarray(window.states[0]),
                                      np.asarray(eps.states[:, ::progs[0].hold]).reshape(-1, 2))
        assert np.all(np.asarray(window.weights) == 1.0)


# ------------------------------------------------------------------------------------------------
# A bandit with a known optimum: a one-dimensional constant observation, reward -(a - A*)^2.
# ------------------------------------------------------------------------------------------------

OPTIMUM = 0.6


def _bandit_task():
    def reset(key, cfg):
        del key, cfg
        return jnp.zeros(()), jnp.zeros((1,))

    def step(key, state, action, cfg):
        del key, cfg
        a = jnp.clip(action, -1.0, 1.0)
        return state, jnp.zeros((1,)), -(a - OPTIMUM) ** 2, jnp.zeros((), bool)

    def features(obs, action):
        return jnp.concatenate([obs, jnp.reshape(action, (1,)).astype(obs.dtype)])

    def controller(name):
        del name
        return tasks._observation_controller("linear", 1.0, np.zeros(1), np.ones(1),
                                             np.zeros((2, 1)), 1.0)

    return tasks.Task(name="test:bandit", obs_dim=1, dt=1.0, max_action=1.0, episode_length=4,
                      terminates=False, threshold=None, reset=reset, step=step, features=features,
                      feature_dim=2, make_controller=controller, obs_centre=np.zeros(1),
                      obs_scale=np.ones(1))


@pytest.mark.training
def test_on_a_bandit_it_reaches_the_optimum_in_fewer_updates_than_gp_pg(critic_registered):
    """The deterministic action c = tanh(b) reaches within 0.05 of A* = 0.6; gp_critic in fewer
    updates than gp_pg at the same learning rate, on each of two seeds."""
    tasks.register(_bandit_task())
    common = dict(env="test:bandit", episode_length=4, episodes_per_update=4, num_updates=20,
                  discount=1e-3, eval_episodes=1, optimizer="adam", learning_rate=0.01,
                  init_log_std=np.log(0.5), hyperfit_samples=64, gp_capacity=16)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    # a fixed prior for both (the kernel's action length-scale about the reward's curvature)
    prior = T.GPPrior(kernels.make_kernel_params([1.0, 0.5], 0.5, 0.01), jnp.asarray(-0.5))
    first = {}
    for method in ("gp_pg", critic_registered):
        cfg = C.preset("tiny", method=method, **common)
        train = T.make_train(cfg)
        _, rec = jax.jit(jax.vmap(lambda k, t=train, c=cfg: t.run_chunk(t.init(k, c, prior), c)))(
            keys)
        # eval_return = -4 (c - A*)^2 for the 4 steps of the deterministic episode
        close = np.asarray(rec.eval_return) >= -4 * 0.05 ** 2
        first[method] = np.where(close.any(axis=1), close.argmax(axis=1), cfg.num_updates)
    assert np.all(first[critic_registered] < cfg.num_updates), first
    assert np.all(first[critic_registered] < first["gp_pg"]), first


# ------------------------------------------------------------------------------------------------
# Bootstrapped targets: lambda-returns with the GP's own mean.
# ------------------------------------------------------------------------------------------------


def _forward_lambda_returns(r, q, gamma, lam):
    """The lambda-return's forward view, float64 NumPy, for an episode cut at its length H: the
    n-step returns G_t^(n) = sum_{k<n} gamma^k r_{t+k} + gamma^n q_{t+n-1}, weighed (1 - lambda)
    lambda^(n-1) for n < H - t and lambda^(H-t-1) for the longest, whose bootstrap is q_{H-1}."""
    h = len(r)
    out = np.zeros(h)
    def n_step(t, n):
        return sum(gamma ** k * r[t + k] for k in range(n)) + gamma ** n * q[t + n - 1]

    for t in range(h):
        longest = h - t
        out[t] = (sum((1 - lam) * lam ** (n - 1) * n_step(t, n) for n in range(1, longest))
                  + lam ** (longest - 1) * n_step(t, longest))
    return out


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("lam", [0.0, 0.6, 1.0])
def test_lambda_returns_against_their_forward_view(dtype, lam):
    """The backward recursion against the forward view's weighted n-step returns; with a cut
    (an episode's end) at step 5, the steps up to it are an episode that ends there (nothing
    bootstrapped: its last value 0) and those after it one of their own."""
    rng = np.random.default_rng(int(lam * 10))
    h, gamma = 12, 0.9
    r, q = rng.normal(size=h), rng.normal(size=h)
    f = jax.jit(estimators.lambda_returns)
    got = f(jnp.asarray(r, dtype), jnp.asarray(q, dtype), jnp.zeros(h, bool), gamma, lam)
    np.testing.assert_allclose(np.asarray(got), _forward_lambda_returns(r, q, gamma, lam),
                               **TOL[dtype])
    cut = np.zeros(h, bool)
    cut[5] = True
    got = np.asarray(f(jnp.asarray(r, dtype), jnp.asarray(q, dtype), jnp.asarray(cut), gamma, lam))
    q_ended = q[:6].copy()
    q_ended[-1] = 0.0
    np.testing.assert_allclose(got[:6], _forward_lambda_returns(r[:6], q_ended, gamma, lam),
                               **TOL[dtype])
    np.testing.assert_allclose(got[6:], _forward_lambda_returns(r[6:], q[6:], gamma, lam),
                               **TOL[dtype])


@pytest.mark.training
def test_lambda_targets_bootstrap_with_the_gp_the_update_started_from():
    """`critic_targets='lambda'`: the values are mu_Q of the update's starting GP (NumPy, from
    its definition) at each next state with the next action, the controller's action where the
    episode is cut at its length; lambda = exp(-dt / horizon). 'returns' leaves the returns-to-go
    as they are, and the GP the update ends with differs between the two."""
    cfg = C.preset("tiny", method="gp_critic", critic_targets="lambda", critic_lambda_horizon=0.02)
    prog = T.make_program(cfg)
    gp, rng = _random_gp(11, jnp.float64, slots=9, dim=4)
    kernel = _kernel(jnp.float64, 1.0, dim=4)
    prior = T.GPPrior(kernel, jnp.asarray(-1.5))
    state = T.initial_state(prog, jax.random.PRNGKey(4), cfg, prior)
    weights = jnp.asarray(rng.normal(size=state.theta.controller.weights.shape) * 0.3)
    state = state._replace(gp=gp, theta=state.theta._replace(
        controller=state.theta.controller._replace(weights=weights)))
    h = cfg.episode_length
    ep = T.Episode(states=None, next_states=jnp.asarray(rng.normal(size=(h, 2))),
                   actions=jnp.asarray(rng.normal(size=h)), rewards=jnp.asarray(rng.normal(size=h)),
                   scores=None, exploration_std=None, alive=None)
    returns = jnp.asarray(rng.normal(size=h))
    got = np.asarray(critic.bootstrapped_targets(prog, cfg, state, ep, returns))
    last = float(prog.controller.apply(state.theta.controller, ep.next_states[-1]))
    actions = np.r_[np.asarray(ep.actions)[1:], last]
    x = np.asarray(jax.vmap(prog.task.features)(ep.next_states, jnp.asarray(actions)))
    q = _numpy_mean(gp, kernel, x)
    lam = np.exp(-C.control_interval(cfg) / 0.02)
    expected = _forward_lambda_returns(np.asarray(ep.rewards), q, float(cfg.discount), lam)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-10)
    as_paper = cfg.replace(critic_targets="returns")
    np.testing.assert_array_equal(
        np.asarray(critic.bootstrapped_targets(T.make_program(as_paper), as_paper, state, ep,
                                               returns)), np.asarray(returns))

    @jax.jit
    def take_in(state):
        keys = jax.random.split(jax.random.PRNGKey(5), cfg.episodes_per_update)
        return [T.roll_out_and_take_in(T.make_program(c), c, state, keys)[0].alpha
                for c in (cfg, as_paper)]

    bootstrapped, paper = take_in(state)
    assert not np.allclose(np.asarray(bootstrapped), np.asarray(paper))
