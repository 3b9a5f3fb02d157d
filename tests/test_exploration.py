"""Correlated exploration (gpguided_jax.exploration) and held actions in the training loop.

References: sample statistics against the stated law; the scores against `jax.grad` of the joint
Gaussian density (`jax.scipy.stats.multivariate_normal`); the REINFORCE estimate against a
finite difference of the expected return with common random numbers; held actions against a
hand-written loop over the task's own step.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import multivariate_normal

from gpguided_jax import config as C
from gpguided_jax import exploration as X
from gpguided_jax import train as T

DT = 0.005  # the pendulum's 200 Hz


# ------------------------------------------------------------------------------------------------
# the noise processes
# ------------------------------------------------------------------------------------------------


def _samples(noise, n, dtype, seed=0):
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    eps, xi = jax.vmap(lambda k: noise.sample(k, dtype))(keys)
    return np.asarray(eps, np.float64), np.asarray(xi, np.float64)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_ou_noise_has_unit_variance_and_decays_by_e_at_its_correlation_time(dtype):
    tau = 0.1
    noise = X.make_noise("ou", 200, DT, correlation_time=tau)
    eps, xi = _samples(noise, 4000, dtype)
    n = eps.shape[0]
    # unit variance at every point (the process starts from its stationary law): the mean over
    # the points of the per-point sample variance, whose standard error is at most sqrt(2 / n)
    assert abs(eps.var(axis=0).mean() - 1.0) < 4 * math.sqrt(2 / n)
    assert abs(eps[:, 0].var() - 1.0) < 4 * math.sqrt(2 / n)
    assert abs(eps[:, -1].var() - 1.0) < 4 * math.sqrt(2 / n)
    lag = int(round(tau / DT))  # 20 points: exp(-1) there
    corr = np.mean(eps[:, :-lag] * eps[:, lag:]) / np.mean(eps * eps)
    assert abs(corr - math.exp(-1.0)) < 0.03
    assert abs(np.mean(eps[:, :-1] * eps[:, 1:]) - math.exp(-DT / tau)) < 0.01
    # the innovations are independent standard normal and whiten() recovers them
    np.testing.assert_allclose(np.asarray(noise.whiten(jnp.asarray(eps[0], dtype))), xi[0],
                               rtol=1e-4 if dtype == "float32" else 1e-10, atol=1e-4 if dtype ==
                               "float32" else 1e-10)
    assert abs(np.mean(xi[:, 1:] * xi[:, :-1])) < 4 / math.sqrt(xi[:, 1:].size)
    # its exact correlation matrix is rho^|i-j|
    lags = np.abs(np.arange(200)[:, None] - np.arange(200)[None, :])
    np.testing.assert_allclose(noise.correlation(), np.exp(-lags * DT / tau), rtol=1e-12)


@pytest.mark.parametrize("beta", [0.5, 1.0, 1.5, 2.0])
def test_coloured_noise_has_unit_variance_and_a_spectrum_of_slope_minus_beta(beta):
    d = 256
    noise = X.make_noise("coloured", d, DT, exponent=beta)
    eps, _ = _samples(noise, 3000, "float64", seed=1)
    assert abs(eps.var(axis=0).mean() - 1.0) < 0.1  # points are correlated: a looser bound
    np.testing.assert_allclose(np.diag(noise.correlation()), 1.0, rtol=1e-10)
    # the averaged periodogram of Hann-windowed episodes against frequency, log-log, between the
    # 8th and the 64th frequency (away from the window's reach at low f and aliasing at high f)
    window = np.hanning(d)
    power = np.mean(np.abs(np.fft.rfft(eps * window, axis=1)) ** 2, axis=0)
    f = np.fft.rfftfreq(d)
    band = slice(8, 64)
    slope = np.polyfit(np.log(f[band]), np.log(power[band]), 1)[0]
    assert abs(slope + beta) < 0.15, slope


def test_white_noise_is_its_own_innovation_and_zero_exponent_is_white():
    noise = X.make_noise("white", 30, DT)
    eps, xi = noise.sample(jax.random.PRNGKey(3), jnp.float64)
    np.testing.assert_array_equal(eps, xi)
    np.testing.assert_allclose(X.make_noise("coloured", 30, DT, exponent=0.0).correlation(),
                               np.eye(30), atol=1e-12)


@pytest.mark.parametrize("name,kw", [("ou", dict(correlation_time=0.0)),
                                     ("coloured", dict(exponent=3.5)),
                                     ("pink", {})])
def test_bad_noise_is_refused_in_one_line(name, kw):
    with pytest.raises(ValueError) as e:
        X.make_noise(name, 10, DT, **kw)
    assert "\n" not in str(e.value)


# ------------------------------------------------------------------------------------------------
# the scores against autodiff of the joint density
# ------------------------------------------------------------------------------------------------


def _toy_policy(d, seed):
    """A Gaussian policy over d decisions with given features: m_t = theta . phi_t and
    s_t = exp(w . psi_t), so that both J_m and J_s vary along the episode."""
    rng = np.random.default_rng(seed)
    return rng.normal(size=(d, 3)), 0.3 * rng.normal(size=(d, 2)), rng.normal(size=3), \
        0.2 * rng.normal(size=2)


NOISE_CASES = [("white", {}), ("ou", dict(correlation_time=0.05)),
               ("ou", dict(correlation_time=2.0)),  # rho = 0.9975: nearly a random walk
               ("coloured", dict(exponent=1.0)), ("coloured", dict(exponent=2.0))]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("name,kw", NOISE_CASES)
def test_scores_are_the_gradients_of_the_joint_log_density(name, kw, dtype):
    d = 40
    noise = X.make_noise(name, d, DT, **kw)
    phi, psi, theta, w = (jnp.asarray(v, dtype) for v in _toy_policy(d, 0))
    eps, xi = noise.sample(jax.random.PRNGKey(7), jnp.dtype(dtype))
    mean, std = phi @ theta, jnp.exp(psi @ w)
    actions = mean + std * eps
    j_mean = {"theta": phi / std[:, None], "w": jnp.zeros_like(psi)}
    j_std = {"theta": jnp.zeros_like(phi), "w": psi}  # grad s_t / s_t = psi_t
    scores = X.correlated_scores(noise, eps, xi, j_mean, j_std)

    corr = np.asarray(noise.correlation())

    def log_p(params, t):
        """log p(a_0..a_t): the marginal of the first t+1 points, in float64."""
        m = phi.astype(jnp.float64) @ params["theta"]
        s = jnp.exp(psi.astype(jnp.float64) @ params["w"])
        e = (actions.astype(jnp.float64) - m) / s
        return (multivariate_normal.logpdf(e[:t + 1], jnp.zeros(t + 1), corr[:t + 1, :t + 1])
                - jnp.sum(jnp.log(s[:t + 1])))

    params = {"theta": theta.astype(jnp.float64), "w": w.astype(jnp.float64)}
    rtol = 1e-9 if dtype == "float64" else 2e-3
    for t in (0, 1, d // 2, d - 1):  # the cumulative sums: the gradient of log p(a_0..a_t)
        want = jax.grad(log_p)(params, t)
        for k in ("theta", "w"):
            got = np.asarray(scores[k][:t + 1], np.float64).sum(axis=0)
            scale = np.abs(np.asarray(want[k])).max() + 1.0
            np.testing.assert_allclose(got, np.asarray(want[k]), rtol=0, atol=rtol * scale)
    # the library's own joint density agrees with the reference (float32: the actions' rounding)
    np.testing.assert_allclose(
        float(X.log_density(noise, eps.astype(jnp.float64), std.astype(jnp.float64))),
        float(log_p(params, d - 1)), rtol=1e-9 if dtype == "float64" else 1e-5)


# ------------------------------------------------------------------------------------------------
# REINFORCE with correlated noise: Monte Carlo against a finite difference
# ------------------------------------------------------------------------------------------------


def _linear_problem(noise, params, eps):
    """A scalar linear system x_{t+1} = 0.9 x_t + 0.2 a_t from x_0 = 0, policy a_t = k0 + k1 x_t +
    exp(log_std) eps_t, reward -(x_{t+1} - 1)^2. Returns (total return, scores (D, 3), rewards)."""
    k0, k1, log_std = params[0], params[1], params[2]
    std = jnp.exp(log_std)

    def step(x, e):
        a = k0 + k1 * x + std * e
        x_new = 0.9 * x + 0.2 * a
        return x_new, (x, -(x_new - 1.0) ** 2)

    _, (xs, rewards) = jax.lax.scan(step, jnp.zeros((), eps.dtype), eps)
    return rewards.sum(), xs, rewards


@pytest.mark.slow
@pytest.mark.parametrize("name,kw", [("ou", dict(correlation_time=0.05)),
                                     ("coloured", dict(exponent=1.5))])
def test_reinforce_with_correlated_scores_matches_a_finite_difference(name, kw):
    d, n = 20, 200_000
    noise = X.make_noise(name, d, DT, **kw)
    params = jnp.asarray([0.5, -0.3, math.log(0.7)])
    keys = jax.random.split(jax.random.PRNGKey(11), n)

    def estimates(key):
        eps, xi = noise.sample(key, jnp.float64)
        _, xs, rewards = _linear_problem(noise, params, eps)
        std = jnp.exp(params[2])
        j_mean = jnp.stack([jnp.ones(d), xs, jnp.zeros(d)], axis=1) / std
        j_std = jnp.stack([jnp.zeros(d), jnp.zeros(d), jnp.ones(d)], axis=1)
        to_go = jnp.cumsum(rewards[::-1])[::-1]
        correlated = X.correlated_scores(noise, eps, xi, j_mean, j_std)
        white = eps[:, None] * j_mean + (eps[:, None] ** 2 - 1.0) * j_std  # ignores correlation
        return (correlated * to_go[:, None]).sum(0), (white * to_go[:, None]).sum(0)

    correlated, white = jax.jit(jax.vmap(estimates))(keys)
    # the expected return's gradient: central differences, the same noise on both sides
    eps_all = jax.vmap(lambda k: noise.sample(k, jnp.float64)[0])(keys)

    def expected_return(p):
        return jnp.mean(jax.vmap(lambda e: _linear_problem(noise, p, e)[0])(eps_all))

    h = 1e-4
    fd = np.array([(expected_return(params.at[i].add(h)) - expected_return(params.at[i].add(-h)))
                   / (2 * h) for i in range(3)])
    se = np.asarray(correlated.std(0)) / math.sqrt(n)
    z = np.abs(np.asarray(correlated.mean(0)) - fd) / se
    assert np.all(z < 4.5), (np.asarray(correlated.mean(0)), fd, z)
    # the white-noise score, used with correlated noise, is biased beyond doubt
    z_white = np.abs(np.asarray(white.mean(0)) - fd) / (np.asarray(white.std(0)) / math.sqrt(n))
    assert np.max(z_white) > 10, z_white


# ------------------------------------------------------------------------------------------------
# parameter noise: the scores against autodiff, REINFORCE against a finite difference
# ------------------------------------------------------------------------------------------------


def test_parameter_noise_blocks():
    assert X.make_noise("parameter", 20, DT).block == 20  # one draw per episode
    assert X.make_noise("parameter", 20, DT, resample_time=0.03).block == 6
    assert X.make_noise("parameter", 20, DT, resample_time=0.03).num_blocks == 4
    assert X.make_noise("parameter", 20, DT, resample_time=1e-4).block == 1
    assert X.make_noise("parameter", 20, DT, resample_time=10.0).num_blocks == 1
    with pytest.raises(ValueError, match="resample time"):
        X.make_noise("parameter", 20, DT, resample_time=-1.0)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_parameter_scores_are_the_gradients_of_the_weights_log_density(dtype):
    """Given the visited states the actions are a function of the perturbed weights theta', so
    the episode's log-likelihood is that of theta' ~ N(theta, (sigma / u_max)^2 I) per block;
    its gradient (jax.grad of scipy's normal density) against the summed scores."""
    noise = X.make_noise("parameter", 20, DT, resample_time=0.03)  # 4 blocks of 6, 6, 6, 2
    u_max, log_std = 5.0, jnp.asarray(0.3, dtype)
    rng = np.random.default_rng(3)
    theta = {"w": jnp.asarray(rng.normal(size=7), dtype), "b": jnp.asarray(0.4, dtype)}
    eps = X.sample_parameter_noise(noise, jax.random.PRNGKey(2), theta)
    assert eps["w"].shape == (4, 7) and eps["b"].shape == (4,) and eps["w"].dtype == dtype
    scale = jnp.exp(log_std) / u_max
    perturbed = jax.tree_util.tree_map(
        lambda w, e: (w + scale * e).astype(jnp.float64), theta, eps)

    def log_p(params, ls):
        s = jnp.exp(ls) / u_max
        return sum(jnp.sum(jax.scipy.stats.norm.logpdf(perturbed[k], params[k], s))
                   for k in ("w", "b"))

    params64 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64), theta)
    want_c, want_s = jax.grad(log_p, argnums=(0, 1))(params64, jnp.float64(log_std))
    got_c, got_s = X.parameter_scores(noise, eps, jnp.exp(log_std), u_max)
    assert got_c["w"].shape == (20, 7) and got_s.shape == (20,)
    first = np.arange(20) % 6 == 0
    assert np.all(np.asarray(got_s)[~first] == 0) and np.all(np.asarray(got_c["w"])[~first] == 0)
    rtol = 1e-10 if dtype == "float64" else 1e-4
    for k in ("w", "b"):
        np.testing.assert_allclose(np.asarray(got_c[k], np.float64).sum(0), want_c[k],
                                   rtol=rtol, atol=rtol)
    np.testing.assert_allclose(float(np.asarray(got_s, np.float64).sum()), float(want_s),
                               rtol=rtol, atol=rtol)


@pytest.mark.slow
def test_reinforce_with_parameter_noise_matches_a_finite_difference():
    """The linear system of `_linear_problem` with a = (k + sigma eps_j) . (1, x_t), eps_j drawn
    every 5 of 20 steps (u_max = 1): the REINFORCE estimate with each block's score times the
    return-to-go from its first step, against central differences with common random numbers.
    The per-step Gaussian score of the actions' marginal N(m_t, sigma^2 |(1, x_t)|^2), the
    likelihood that ignores the noise's persistence, is biased."""
    d, n = 20, 200_000
    noise = X.make_noise("parameter", d, DT, resample_time=5 * DT)
    params = jnp.asarray([0.5, -0.3, math.log(0.3)])
    keys = jax.random.split(jax.random.PRNGKey(12), n)
    like = jnp.zeros(2)
    block_of = jnp.arange(d) // noise.block

    def episode(p, eps):
        k, std = p[:2], jnp.exp(p[2])

        def step(x, e):
            feat = jnp.stack([jnp.ones_like(x), x])
            a = (k + std * e) @ feat
            x_new = 0.9 * x + 0.2 * a
            return x_new, (x, a, k @ feat, std * jnp.sqrt(feat @ feat), -(x_new - 1.0) ** 2)

        return jax.lax.scan(step, jnp.zeros(()), eps[block_of])[1]

    def estimates(key):
        eps = X.sample_parameter_noise(noise, key, like)
        xs, a, m, s, rewards = episode(params, eps)
        to_go = jnp.cumsum(rewards[::-1])[::-1]
        j_c, j_s = X.parameter_scores(noise, eps, jnp.exp(params[2]), 1.0)
        scores = jnp.concatenate([j_c, j_s[:, None]], axis=1)
        # the marginal's score: d/dk of log N(a; m, s^2) and d/dlog sigma
        z = (a - m) / s
        feat = jnp.stack([jnp.ones(d), xs], axis=1)
        marginal = jnp.concatenate([z[:, None] * feat / s[:, None], (z * z - 1.0)[:, None]],
                                   axis=1)
        return (scores * to_go[:, None]).sum(0), (marginal * to_go[:, None]).sum(0)

    exact, marginal = jax.jit(jax.vmap(estimates))(keys)
    eps_all = jax.vmap(lambda k: X.sample_parameter_noise(noise, k, like))(keys)

    def expected_return(p):
        return jnp.mean(jax.vmap(lambda e: episode(p, e)[-1].sum())(eps_all))

    h = 1e-4
    fd = np.array([(expected_return(params.at[i].add(h)) - expected_return(params.at[i].add(-h)))
                   / (2 * h) for i in range(3)])
    z = np.abs(np.asarray(exact.mean(0)) - fd) / (np.asarray(exact.std(0)) / math.sqrt(n))
    assert np.all(z < 4.5), (np.asarray(exact.mean(0)), fd, z)
    z_marg = np.abs(np.asarray(marginal.mean(0)) - fd) / (np.asarray(marginal.std(0))
                                                        / math.sqrt(n))
    assert np.max(z_marg) > 10, z_marg


# ------------------------------------------------------------------------------------------------
# held actions and the training loop
# ------------------------------------------------------------------------------------------------


def test_hold_steps_and_decisions():
    assert X.hold_steps(0.0, DT) == 1
    assert X.hold_steps(0.025, DT) == 5
    assert X.hold_steps(0.001, DT) == 1  # at least one step
    assert X.num_decisions(20, 1) == 20
    assert X.num_decisions(20, 3) == 7  # the last decision holds for 2 steps
    spread = T.spread_decisions(jnp.arange(1.0, 8.0), 3, 20)
    np.testing.assert_array_equal(spread[:7], [1, 0, 0, 2, 0, 0, 3])
    assert spread.shape == (20,) and float(spread.sum()) == 28.0
    held = T.spread_decisions(jnp.arange(1.0, 8.0), 3, 20, fill="hold")
    np.testing.assert_array_equal(held, np.repeat(np.arange(1.0, 8.0), 3)[:20])


def _tiny(**kw):
    return C.preset("tiny", method="reinforce", **kw)


def test_held_actions_step_the_task_as_a_hand_written_loop():
    # 3 steps per decision, 7 decisions over 20 steps; no reward noise, so the replay's rewards
    # do not depend on the step's key
    cfg = _tiny(hold_time=0.015, pendulum_overrides=dict(reward_noise_std=0.0))
    prog = T.make_program(cfg)
    assert prog.hold == 3 and prog.noise.length == 7
    calls = []

    def act(k, obs):
        calls.append(1)  # traced once per decision body
        a = jnp.sin(obs.sum()) + jax.random.normal(k, (), obs.dtype)
        return a, a

    key = jax.random.PRNGKey(4)
    o, o_next, a, r, alive, outs = T.run_episode(prog, key, act, cfg, 20, 3)
    assert a.shape == (20,) and outs.shape == (7,) and o.shape[0] == 20
    np.testing.assert_array_equal(np.asarray(a), np.repeat(np.asarray(outs), 3)[:20])
    # replay: the same starting state, the held actions through the task's own step
    env_state, obs = prog.task.reset(jax.random.split(key)[0], cfg)
    for t in range(20):
        np.testing.assert_allclose(np.asarray(o[t]), np.asarray(obs), rtol=1e-12)
        env_state, obs, reward, _ = prog.task.step(jax.random.PRNGKey(0), env_state, a[t], cfg)
        np.testing.assert_allclose(float(r[t]), float(reward), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(o_next[t]), np.asarray(obs), rtol=1e-12)


@functools.cache
def _initial_state(method):
    cfg = C.preset("tiny", method=method, hold_time=0.015)
    return jax.jit(T.make_train(cfg).init)(jax.random.PRNGKey(0), cfg)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["reinforce", "guided_variance"])
@pytest.mark.parametrize("exploration", ["white", "ou"])
def test_rollout_scores_sit_at_decision_points_and_std_is_held(method, exploration):
    cfg = C.preset("tiny", method=method, hold_time=0.015, exploration=exploration)
    prog = T.make_program(cfg)
    state = _initial_state(method)  # the exploration does not change the initial state's shapes
    ctx = T.policy_context(cfg, state.gp, state.kernel)
    ep = T.rollout(prog, jax.random.PRNGKey(1), state.theta, ctx, prog.policy, cfg)
    actions, std = np.asarray(ep.actions), np.asarray(ep.exploration_std)
    for start in range(0, 20, 3):
        block = slice(start, min(start + 3, 20))
        assert np.all(actions[block] == actions[start])
        assert np.all(std[block] == std[start])
    off = np.ones(20, bool)
    off[::3] = False
    leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(ep.scores)]
    assert all(np.all(leaf[off] == 0) and np.all(np.isfinite(leaf)) for leaf in leaves)
    assert any(np.any(leaf[~off] != 0) for leaf in leaves)


def test_parameter_noise_rollout_acts_with_the_perturbed_controller():
    """Held for 3 steps, a draw every 3 decisions: each decision's action is the controller's with
    that block's perturbed weights at the observed state, the scores sit at the blocks' first
    decisions, and the learnable sigma moves the actions."""
    cfg = C.preset("tiny", method="reinforce", hold_time=0.015, exploration="parameter",
                   noise_resample_time=0.045)
    prog = T.make_program(cfg)
    assert prog.hold == 3 and prog.noise.length == 7 and prog.noise.block == 3
    state = _initial_state("reinforce")
    theta, ctx = state.theta, T.policy_context(cfg, state.gp, state.kernel)
    key = jax.random.PRNGKey(6)
    ep = T.rollout(prog, key, theta, ctx, prog.policy, cfg)
    eps = X.sample_parameter_noise(prog.noise, jax.random.fold_in(key, 1), theta.controller)
    scale = float(jnp.exp(theta.log_std)) / prog.controller.u_max
    for t in range(20):
        j = (t // 3) // 3
        w = jax.tree_util.tree_map(lambda c, e, j=j: c + scale * e[j], theta.controller, eps)
        np.testing.assert_allclose(float(ep.actions[t]),
                                   float(prog.controller.apply(w, ep.states[t - t % 3])),
                                   rtol=1e-12)
    starts = np.zeros(20, bool)
    starts[[0, 9, 18]] = True
    leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(ep.scores)]
    assert all(np.all(leaf[~starts] == 0) and np.all(leaf[starts] != 0) for leaf in leaves)
    wider = theta._replace(log_std=theta.log_std + 1.0)
    ep2 = T.rollout(prog, key, wider, ctx, prog.policy, cfg)
    assert not np.allclose(np.asarray(ep.actions), np.asarray(ep2.actions))


def test_hyperfit_takes_every_step_of_held_actions_and_the_gp_decisions_apart():
    cfg = _tiny(hold_time=0.015)
    assert cfg.hyperfit_episodes == math.ceil(100 / 20)  # as without a hold
    prog = T.make_program(cfg)
    xs, ys, valid = T.collect_valid(prog, jax.random.PRNGKey(2), cfg)
    assert xs.shape == (cfg.hyperfit_episodes * 20, 4) and ys.shape[0] == xs.shape[0]
    assert valid is None
    actions = np.asarray(xs[:, -1]).reshape(cfg.hyperfit_episodes, 20)
    assert np.all(actions[:, 1:3] == actions[:, :1])  # held for 3 steps
    assert np.any(actions[:, 3] != actions[:, 0])
    # the GP's pairs: decisions at least gp_stride steps apart
    assert [T.gp_spacing(stride, hold) for stride, hold in
            ((1, 1), (5, 1), (5, 3), (5, 5), (5, 100), (1, 3))] == [1, 5, 6, 5, 100, 3]


def test_white_without_hold_is_the_paper_rollout():
    """The default exploration is the paper's: the rollout equals one through `policy.act` alone,
    one decision per step, whatever the noise fields say while `exploration` is 'white'."""
    cfg = _tiny()
    other = _tiny(noise_correlation_time=0.1, noise_exponent=2.0)
    prog, prog_other = T.make_program(cfg), T.make_program(other)
    assert prog.hold == 1 and prog.noise.name == "white"
    state = T.make_train(cfg).init(jax.random.PRNGKey(0), cfg)
    theta, ctx = state.theta, T.policy_context(cfg, state.gp, state.kernel)
    key = jax.random.PRNGKey(5)
    ep = T.rollout(prog, key, theta, ctx, prog.policy, cfg)
    ep2 = T.rollout(prog_other, key, theta, ctx, prog_other.policy, other)
    for a, b in zip(jax.tree_util.tree_leaves(ep), jax.tree_util.tree_leaves(ep2)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # and by hand: each step's action, score and std are policy.act's with that step's key
    key_reset, key_steps = jax.random.split(key)
    env_state, obs = prog.task.reset(key_reset, cfg)
    for t, step_key in enumerate(jax.random.split(key_steps, 20)):
        key_act, key_env = jax.random.split(step_key)
        a, _, score, std = prog.policy.act(key_act, theta, obs, ctx)
        np.testing.assert_allclose(float(ep.actions[t]), float(a), rtol=1e-12)
        np.testing.assert_allclose(float(ep.exploration_std[t]), float(std), rtol=1e-12)
        for got, want in zip(jax.tree_util.tree_leaves(ep.scores), jax.tree_util.tree_leaves(score)):
            np.testing.assert_allclose(np.asarray(got[t]), np.asarray(want), rtol=1e-10, atol=1e-12)
        env_state, obs, _, _ = prog.task.step(key_env, env_state, a, cfg)


@pytest.mark.parametrize("fields,word", [
    (dict(exploration="pink"), "exploration"),
    (dict(method="guided_direction", exploration="ou"), "guided_direction"),
    (dict(noise_correlation_time=0.0), "noise_correlation_time"),
    (dict(noise_exponent=-1.0), "noise_exponent"),
    (dict(hold_time=-0.1), "hold_time"),
    (dict(hold_time=float("nan")), "hold_time"),
    (dict(method="guided_variance", exploration="parameter"), "reinforce and gp_pg only"),
    (dict(exploration="parameter", noise_resample_time=-0.5), "noise_resample_time"),
])
def test_bad_exploration_settings_are_refused_naming_the_field(fields, word):
    with pytest.raises(ValueError) as e:
        C.preset("tiny", **fields)
    assert word in str(e.value) and "\n" not in str(e.value)
