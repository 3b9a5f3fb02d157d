"""gp_model (`gpguided_jax.model_based`): the model against an exact GP and the DTC equations in
NumPy, its function samples against the posterior, the tasks' stated rewards against the
environments', the simulated return's gradient against finite differences, and the controller
optimised through a learned model against the LQR gain of scipy's Riccati solver."""

from __future__ import annotations

import functools
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from gpguided_jax import config as C
from gpguided_jax import controllers as controllers_lib
from gpguided_jax import kernels, methods, pendulum, rollouts, tasks
from gpguided_jax import model_based as MB
from gpguided_jax import train as T


def _se(a, b, ls, sf2):
    d = (a[:, None, :] - b[None, :, :]) / ls
    return sf2 * np.exp(-0.5 * np.sum(d * d, axis=-1))


def _data(rng, n, d):
    xs = rng.normal(size=(n, d))
    ys = np.sin(xs @ rng.normal(size=d)) + 0.1 * rng.normal(size=n)
    return xs, ys


_condition = jax.jit(MB.condition, static_argnames=("jitter",))


@jax.jit
def _predict(model, xs):
    """The model's latent mean and variance at each of xs: (n, E) each."""
    return jax.vmap(lambda x: MB.predict(model, x))(xs)


@jax.jit
def _fast_variance(model, xs):
    """The variance the optimistic roll-outs use (`fast_variance`, from explicit factors)."""
    factors = MB.variance_factors(model)
    return jax.vmap(lambda x: MB.fast_variance(model, factors, MB.k_star(model, x)))(xs)


KERN = dict(ls=np.array([0.9, 1.3, 0.7]), sf2=1.7, sn2=0.05)


def _kernel(dtype):
    return kernels.make_kernel_params(KERN["ls"], KERN["sf2"], KERN["sn2"], dtype=dtype)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_with_every_input_inducing_the_model_is_the_exact_gp(dtype):
    """Z = the data: the sparse GP's mean and variance (both ways of computing it) are the exact
    GP's (Cholesky in NumPy), and the buffer's unwritten slots (junk, masked) change nothing."""
    rng = np.random.default_rng(0)
    xs, ys = _data(rng, 25, 3)
    junk = rng.normal(size=(7, 3)) * 50.0
    x_all = np.concatenate([xs, junk])
    y_all = np.concatenate([ys, rng.normal(size=7) * 1e3])
    valid = np.arange(32) < 25
    zmask = np.ones(25, bool)
    jitter = 1e-12 if dtype == "float64" else 1e-6
    m = _condition(jnp.asarray(xs, dtype), jnp.asarray(zmask), _kernel(dtype),
                     jnp.asarray(x_all, dtype), jnp.asarray(y_all, dtype), jnp.asarray(valid),
                     jitter=jitter)
    m = jax.tree_util.tree_map(lambda a: a[None], m)._replace(inducing=m.inducing,
                                                             inducing_mask=m.inducing_mask)
    tests_x = rng.normal(size=(9, 3))
    k = _se(xs, xs, KERN["ls"], KERN["sf2"]) + KERN["sn2"] * np.eye(25)
    ks = _se(tests_x, xs, KERN["ls"], KERN["sf2"])
    mean_ref = ks @ np.linalg.solve(k, ys)
    var_ref = KERN["sf2"] - np.sum(ks * np.linalg.solve(k, ks.T).T, axis=1)
    mean, var = (np.asarray(v[:, 0]) for v in _predict(m, jnp.asarray(tests_x, dtype)))
    rtol = 1e-7 if dtype == "float64" else 2e-3
    np.testing.assert_allclose(mean, mean_ref, rtol=rtol, atol=rtol * np.abs(mean_ref).max())
    np.testing.assert_allclose(var, var_ref, rtol=rtol * 10, atol=rtol * KERN["sf2"] * 10)
    fast = np.asarray(_fast_variance(m, jnp.asarray(tests_x, dtype))[:, 0])
    np.testing.assert_allclose(fast, var_ref, rtol=rtol * 10, atol=rtol * KERN["sf2"] * 10)


def test_with_fewer_inducing_inputs_it_is_the_dtc_posterior_in_numpy():
    """M < N: mean sigma^-2 k Sigma K_ZX y, variance k** - k K_ZZ^-1 k + k Sigma k, Sigma =
    (K_ZZ + sigma^-2 K_ZX K_XZ)^-1, written directly (the same jitter on K_ZZ), the variance
    both ways; an unused inducing slot changes nothing."""
    rng = np.random.default_rng(1)
    xs, ys = _data(rng, 60, 3)
    z = xs[:8]
    zpad = np.concatenate([z, rng.normal(size=(2, 3))])
    zmask = np.arange(10) < 8
    m = _condition(jnp.asarray(zpad), jnp.asarray(zmask), _kernel("float64"), jnp.asarray(xs),
                     jnp.asarray(ys), jnp.ones(60, bool))
    m = jax.tree_util.tree_map(lambda a: a[None], m)._replace(inducing=m.inducing,
                                                             inducing_mask=m.inducing_mask)
    kzz = _se(z, z, KERN["ls"], KERN["sf2"]) + MB.JITTER * KERN["sf2"] * np.eye(8)
    kzx = _se(z, xs, KERN["ls"], KERN["sf2"])
    sigma = np.linalg.inv(kzz + kzx @ kzx.T / KERN["sn2"])
    xt = rng.normal(size=(6, 3))
    mean, var = _predict(m, jnp.asarray(xt))
    fast = _fast_variance(m, jnp.asarray(xt))
    for i, x in enumerate(xt):
        k = _se(x[None], z, KERN["ls"], KERN["sf2"])[0]
        mean_ref = k @ sigma @ kzx @ ys / KERN["sn2"]
        var_ref = KERN["sf2"] - k @ np.linalg.solve(kzz, k) + k @ sigma @ k
        np.testing.assert_allclose(float(mean[i, 0]), mean_ref, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(float(var[i, 0]), var_ref, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(float(fast[i, 0]), var_ref, rtol=1e-6, atol=1e-9)


def _whitened_least_squares_mean(z, xs, ys, xt, ls, sf2, sn2, jitter):
    """The DTC posterior mean at xt in float64 by another route: the whitened inducing values v
    minimise |y - A^T v|^2 / sn2 + |v|^2 (A = L^-1 K_ZX), solved by NumPy's SVD least squares."""
    m = len(z)
    chol = np.linalg.cholesky(_se(z, z, ls, sf2) + jitter * sf2 * np.eye(m))
    a = np.linalg.solve(chol, _se(z, xs, ls, sf2))
    stacked = np.concatenate([a.T / np.sqrt(sn2), np.eye(m)])
    v = np.linalg.lstsq(stacked, np.concatenate([ys / np.sqrt(sn2), np.zeros(m)]), rcond=None)[0]
    return np.linalg.solve(chol, _se(z, xt, ls, sf2)).T @ v


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("seed", [0, 2])
def test_nearly_noiseless_data_and_long_length_scales_keep_the_model_finite_and_right(dtype, seed):
    """1,000 noiseless targets, 200 inducing inputs, length-scales 2.5 times the inputs' range and
    noise 1e-8 of the signal (a deterministic task's transitions): K_ZZ is nearly singular and
    B = I + A A^T has a condition number near 1e10. In float32 the Cholesky factor of B is not
    finite here; the model's mean is still within 2% of the target's spread of the float64
    reference (same jitter), in float64 within 1e-7."""
    rng = np.random.default_rng(seed)
    n, m, d = 1000, 200, 3
    xs = rng.uniform(-1, 1, size=(n, d))
    ys = np.sin(xs @ rng.normal(size=d))
    ls, sf2, sn2 = np.full(d, 5.0), 1.0, 1e-8
    z, xt = xs[:m], rng.uniform(-1, 1, size=(50, d))
    jitter = max(MB.JITTER, MB.jitter_floor(dtype, m))
    kern = kernels.make_kernel_params(ls, sf2, sn2, dtype=dtype)
    model = _condition(jnp.asarray(z, dtype), jnp.ones(m, bool), kern, jnp.asarray(xs, dtype),
                       jnp.asarray(ys, dtype), jnp.ones(n, bool))
    model = jax.tree_util.tree_map(lambda a: a[None], model)._replace(
        inducing=model.inducing, inducing_mask=model.inducing_mask)
    mean, var = (np.asarray(v[:, 0], np.float64) for v in _predict(model, jnp.asarray(xt, dtype)))
    reference = _whitened_least_squares_mean(z, xs, ys, xt, ls, sf2, sn2, jitter)
    assert np.all(np.isfinite(var)) and np.all(var >= 0)
    tol = 1e-7 if dtype == "float64" else 2e-2
    assert np.max(np.abs(mean - reference)) < tol * np.std(ys), np.max(np.abs(mean - reference))
    if dtype == "float32":  # the case is one the normal equations cannot factor in float32
        a = np.asarray(model.chol_zz[0], np.float64)
        a = np.linalg.solve(a, _se(z, xs, ls, sf2)).astype(np.float32) / np.float32(np.sqrt(sn2))
        b = jnp.eye(m, dtype=jnp.float32) + jnp.asarray(a) @ jnp.asarray(a).T
        assert not bool(jnp.all(jnp.isfinite(jnp.linalg.cholesky(b))))


def test_function_samples_have_the_posterior_mean_and_covariance():
    """f(x) = k(x, Z) w over 20,000 draws of w: its mean is the model's mean and its covariance
    at two inputs k_1 Sigma k_2 (the inducing values' posterior), within Monte-Carlo error."""
    rng = np.random.default_rng(2)
    xs, ys = _data(rng, 40, 3)
    z = xs[:6]
    m = _condition(jnp.asarray(z), jnp.ones(6, bool), _kernel("float64"), jnp.asarray(xs),
                     jnp.asarray(ys), jnp.ones(40, bool))
    m = jax.tree_util.tree_map(lambda a: a[None], m)._replace(inducing=m.inducing,
                                                             inducing_mask=m.inducing_mask)
    w = np.asarray(MB.sample_weights(m, jax.random.key(0), (20000,)))[:, 0]  # (S, M)
    x2 = rng.normal(size=(2, 3))
    kx = _se(x2, z, KERN["ls"], KERN["sf2"])  # (2, M)
    f = w @ kx.T  # (S, 2)
    kzz = _se(z, z, KERN["ls"], KERN["sf2"]) + MB.JITTER * KERN["sf2"] * np.eye(6)
    kzx = _se(z, xs, KERN["ls"], KERN["sf2"])
    sigma = np.linalg.inv(kzz + kzx @ kzx.T / KERN["sn2"])
    cov_ref = kx @ sigma @ kx.T
    mean_ref = kx @ sigma @ kzx @ ys / KERN["sn2"]
    se = np.sqrt(np.diag(cov_ref) / 20000)
    assert np.all(np.abs(f.mean(0) - mean_ref) < 5 * se)
    cov = np.cov(f.T)
    # the sample covariance's standard error: sqrt((s_ii s_jj + s_ij^2) / S)
    cov_se = np.sqrt((np.outer(np.diag(cov_ref), np.diag(cov_ref)) + cov_ref ** 2) / 20000)
    assert np.all(np.abs(cov - cov_ref) < 5 * cov_se)


def _rows_model(rng, dtype, e=3, m=30, d=4):
    """A model of e outputs with their own length-scales over m inducing inputs (a few unused), for
    the roll-outs' mean (`gp.mean_at`); only the fields `mean_at` and `k_star` read."""
    mask = np.ones(m, bool)
    mask[[3, 17]] = False
    kern = kernels.KernelParams(jnp.asarray(rng.uniform(0.3, 2.0, (e, d)), dtype),
                                jnp.asarray(rng.uniform(0.5, 2.0, e), dtype),
                                jnp.asarray(np.full(e, 0.01), dtype))
    return MB.SparseModel(jnp.asarray(rng.normal(size=(m, d)), dtype), jnp.asarray(mask), kern,
                          None, None, None, None)


def _plain_mean(model, fields, w, x):
    """The mean through the kernel rows, differentiated by autodiff (the reference); `fields` the
    model's (inducing inputs, kernels)."""
    return jnp.sum(MB.k_star(model._replace(inducing=fields[0], kernels=fields[1]), x) * w, axis=-1)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_roll_outs_mean_and_its_closed_form_derivative_against_numpy_and_autodiff(dtype):
    """`gp.mean_at` (the simulated roll-outs' model, its derivative in closed form) is sum_m w_em
    k_e(x, z_m) in NumPy, and its derivatives in x, the weights, the length-scales, sigma_f^2 and
    the inducing inputs, forward and reverse, and its Hessian in x are autodiff's through
    `k_star`: at inputs near the data, on an inducing input and far from every one (where the
    kernel rows underflow to 0)."""
    rng = np.random.default_rng(5)
    model = _rows_model(rng, dtype)
    w = jnp.asarray(rng.normal(size=(3, 30)), dtype)
    rtol = 1e-10 if dtype == "float64" else 2e-4

    def mean(mdl, fields, w, x):
        return MB.mean_at(MB.scaled(mdl._replace(inducing=fields[0], kernels=fields[1])), w, x)

    fields = (model.inducing, model.kernels)

    @jax.jit
    def derivatives(fields, w, x):
        """Each function's value, Jacobians in the model's fields, the weights and the input
        (forward and reverse) and Hessian in the input, in one compiled program."""
        out = {}
        for name, f in (("closed", functools.partial(mean, model)),
                        ("autodiff", functools.partial(_plain_mean, model))):
            out[name] = ([jax.jacfwd(f, a)(fields, w, x) for a in (0, 1, 2)]
                         + [jax.jacrev(f, a)(fields, w, x) for a in (0, 1, 2)]
                         + [jax.hessian(f, 2)(fields, w, x)])
        return out

    for x in (rng.normal(size=4), np.asarray(model.inducing[5]), np.full(4, 40.0)):
        x = jnp.asarray(x, dtype)
        kern = model.kernels
        reference = np.array([np.sum(np.where(np.asarray(model.inducing_mask), _se(
            np.asarray(x, np.float64)[None], np.asarray(model.inducing, np.float64),
            np.asarray(kern.lengthscales[e], np.float64), float(kern.signal_variance[e]))[0], 0.0)
            * np.asarray(w[e], np.float64)) for e in range(3)])
        scale = np.max(np.abs(reference)) + 1e-30
        np.testing.assert_allclose(np.asarray(mean(model, fields, w, x), np.float64), reference,
                                   atol=rtol * scale)
        got = derivatives(fields, w, x)
        for g, r in zip(jax.tree_util.tree_leaves(got["closed"]),
                        jax.tree_util.tree_leaves(got["autodiff"]), strict=True):
            g, r = np.asarray(g, np.float64), np.asarray(r, np.float64)
            assert np.all(np.isfinite(g))
            np.testing.assert_allclose(g, r, atol=rtol * (np.max(np.abs(r)) + 1e-30))
    far = jax.grad(lambda x: jnp.sum(mean(model, fields, w, x)))(jnp.full(4, 40.0, dtype))
    assert np.all(np.asarray(far) == 0.0)


def test_the_buffer_keeps_the_newest_transitions_and_the_targets_wrap_angles():
    data = MB.empty_data(5, 2, 1, jnp.float64, ())
    for start in (0, 3, 6):
        x = jnp.arange(start, start + 3, dtype=jnp.float64)
        data = MB.take_in(data, jnp.stack([x, x], 1), x[:, None], jnp.ones(3, bool))
    # 9 written into 5 slots: 5..8, slot i holding the transition written i mod 5
    assert int(data.count) == 9
    assert sorted(np.asarray(data.inputs[:, 0]).tolist()) == [4.0, 5.0, 6.0, 7.0, 8.0]
    task = tasks.make_task("pendulum")
    obs = jnp.array([6.2, 1.0])
    nxt = jnp.array([0.05, 1.2])  # wrapped past 2 pi
    d = MB.targets_of(task, obs, nxt)
    np.testing.assert_allclose(np.asarray(d), [0.05 + 2 * np.pi - 6.2, 0.2], atol=1e-12)
    np.testing.assert_allclose(np.asarray(MB.next_of(task, obs, d)), np.asarray(nxt), atol=1e-12)


def test_held_actions_give_one_transition_per_decision():
    """hold = 3 over 10 steps: decisions at 0, 3, 6 (the last step's incomplete hold dropped),
    each from its first observation to the next observation of its last step, valid only if the
    episode is alive through the hold and no restart falls inside it (a loop in NumPy)."""
    rng = np.random.default_rng(3)
    n, t, hold = 2, 10, 3
    obs = rng.normal(size=(n, t, 2))
    nxt = rng.normal(size=(n, t, 2))
    acts = np.repeat(rng.normal(size=(n, 4)), hold, axis=1)[:, :t]
    alive = np.ones((n, t), bool)
    alive[0, 5:] = False  # episode 0 ends inside its second hold
    ends = np.zeros((n, t), bool)
    ends[1, 7] = True  # a restart inside episode 1's third hold
    for use_ends in (False, True):
        o, x, a, v = MB.decisions(hold, obs, nxt, acts, alive, ends if use_ends else None)
        for i in range(n):
            for j, s in enumerate(range(0, t - hold + 1, hold)):
                np.testing.assert_array_equal(np.asarray(o[i, j]), obs[i, s])
                np.testing.assert_array_equal(np.asarray(x[i, j]), nxt[i, s + hold - 1])
                assert float(a[i, j]) == acts[i, s]
                ok = alive[i, s:s + hold].all() and not (use_ends and ends[i, s:s + hold].any())
                assert bool(v[i, j]) == ok, (i, j, use_ends)
        assert o.shape == (n, t // hold, 2)
    # a decision's reward is its steps' rewards summed
    rewards = rng.normal(size=(n, t))
    r = np.asarray(MB.decision_rewards(hold, jnp.asarray(rewards)))
    assert r.shape == (n, t // hold)
    for i in range(n):
        for j, s in enumerate(range(0, t - hold + 1, hold)):
            assert r[i, j] == pytest.approx(sum(rewards[i, s + k] for k in range(hold)), abs=1e-12)
    # without a hold: every step, the restart's step invalid
    _, _, _, v = MB.decisions(1, obs, nxt, acts, alive, ends)
    np.testing.assert_array_equal(np.asarray(v), alive & ~ends)


# ------------------------------------------------------------------------- the stated rewards


def _random_transitions(task, cfg, key, episodes=4, steps=60, start=None):
    def episode(k):
        k0, ks = jax.random.split(k)
        env_state, obs = task.reset(k0, cfg)
        if start is not None:
            env_state, obs = start(env_state, cfg)

        def body(carry, kk):
            env_state, obs = carry
            ka, ke = jax.random.split(kk)
            a = jax.random.uniform(ka, (), cfg.dtype, -task.max_action, task.max_action)
            env_state, nxt, r, done = task.step(ke, env_state, a, cfg)
            return (env_state, nxt), (obs, a, nxt, r, done)

        _, out = jax.lax.scan(body, (env_state, obs), jax.random.split(ks, steps))
        return out

    out = jax.vmap(episode)(jax.random.split(key, episodes))
    return jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), out)


def _car_near_goal(env_state, cfg):
    s = env_state.replace(position=jnp.float32(0.42), velocity=jnp.float32(0.05))
    return s, jnp.stack([s.position, s.velocity]).astype(cfg.dtype)


@pytest.mark.parametrize("env,start", [
    ("pendulum", None), ("gymnax:Pendulum-v1", None),
    ("gymnax:MountainCarContinuous-v0", None), ("gymnax:MountainCarContinuous-v0", _car_near_goal)])
def test_the_stated_reward_and_end_are_the_environments(env, start):
    """Along random-action roll-outs (before each episode's first end): Task.reward_fn of each
    transition is the environment's reward, and Task.end_fn its end (brax's inverted pendulum's:
    tests/test_task_reference.py, on brax's own step)."""
    task = tasks.make_task(env)
    pend = {"reward_noise_std": 0.0} if env == "pendulum" else None
    cfg = C.make_config(env=env, dtype="float32", pendulum_overrides=pend)
    obs, a, nxt, r, done = _random_transitions(task, cfg, jax.random.key(3), start=start)
    n = obs.shape[0] // 4
    first = np.asarray(jnp.cumsum(done.reshape(4, n), axis=1) - done.reshape(4, n) == 0).reshape(-1)
    stated = np.asarray(jax.vmap(task.reward_fn)(obs, a, nxt))
    np.testing.assert_allclose(stated[first], np.asarray(r)[first], rtol=1e-5, atol=1e-5)
    if task.end_fn is not None:
        ends = np.asarray(jax.vmap(task.end_fn)(nxt))
        np.testing.assert_array_equal(ends[first], np.asarray(done)[first])
        margin = np.asarray(jax.vmap(task.end_margin)(nxt))
        np.testing.assert_array_equal(margin[first] > 0, ends[first])
        # the reward given the end's indicator is the reward
        given = np.asarray(jax.vmap(task.reward_fn)(obs, a, nxt, jnp.asarray(ends)))
        np.testing.assert_allclose(given[first], np.asarray(r)[first], rtol=1e-5, atol=1e-5)
        if start is not None:  # roll-outs that reach the end checked
            assert np.asarray(done)[first].any()
    else:
        assert not np.asarray(done).any()


def test_the_stated_reward_of_a_task_that_states_none_is_refused_in_one_line():
    """A task without `reward_fn`: 'stated' is refused, 'auto' learns it."""
    task = _linear_task()._replace(name="test:unstated", reward_fn=None)
    tasks.register(task)
    try:
        with pytest.raises(ValueError, match="model_reward: .stated. plans with what .*reward_fn"):
            C.make_config(env="test:unstated", method="gp_model", model_reward="stated")
        cfg = C.make_config(env="test:unstated", method="gp_model")
        assert MB.learns_reward(tasks.make_task(cfg.env), cfg)
    finally:
        tasks._REGISTERED.pop("test:unstated", None)
        tasks.make_task.cache_clear()
    with pytest.raises(ValueError, match="model_exploration"):
        C.make_config(method="gp_model", model_exploration="greedy")
    with pytest.raises(ValueError, match="model_reward"):
        C.make_config(method="gp_model", model_reward="guessed")
    assert not MB.learns_reward(tasks.make_task("pendulum"), C.make_config(method="gp_model"))


@pytest.mark.slow
def test_a_learned_reward_predicts_the_stated_one_on_transitions_it_has_not_seen(dtype="float64"):
    """Pendulum-v1, its reward learnt as the model's last output from 400 of 600 random-action
    transitions: on the 200 others, the learnt reward's mean is the task's stated reward (itself
    the environment's: `test_the_stated_reward_and_end_are_the_environments`) within 5% of the
    reward's spread (root mean square), and within 3 of the GP's predictive standard deviations
    at nearly all. (float32's model of such nearly noiseless data: the test below.)"""
    task = tasks.make_task("gymnax:Pendulum-v1")
    cfg = C.make_config(env="gymnax:Pendulum-v1", method="gp_model", dtype=dtype,
                        model_reward="learned", model_inducing=150)
    prog = rollouts.make_program(cfg)
    assert MB.learns_reward(task, cfg)
    obs, a, nxt, r, _ = _random_transitions(task, cfg, jax.random.key(12), episodes=6, steps=100)
    perm = np.random.default_rng(14).permutation(600)
    obs, a, nxt, r = (v[perm] for v in (obs, a, nxt, r))
    seen, unseen = slice(0, 400), slice(400, 600)
    xs = jax.vmap(task.features)(obs, a)
    ys = jnp.concatenate([MB.targets_of(task, obs, nxt), r[:, None]], axis=1)
    data = MB.init(prog, None, cfg)
    assert data.targets.shape[1] == task.obs_dim + 1
    data = MB.take_in(data, xs[seen], ys[seen], jnp.ones(400, bool))
    refit = jax.jit(MB.refit, static_argnames=("subset_size", "num_steps"))
    data = data._replace(log_kernels=refit(jax.random.key(13), data, subset_size=200,
                                           num_steps=200, first=True))
    model, mean = jax.jit(MB.build, static_argnums=1)(data, cfg.settings.inducing)
    mu, var = jax.jit(jax.vmap(lambda x: MB.predict(model, x)))(xs[unseen])
    learned = np.asarray(mu[:, -1] + mean[-1], np.float64)
    sd = np.sqrt(np.asarray(var[:, -1], np.float64) + float(model.kernels.noise_variance[-1]))
    stated = np.asarray(jax.vmap(task.reward_fn)(obs[unseen], a[unseen], nxt[unseen]), np.float64)
    rms = np.sqrt(np.mean((learned - stated) ** 2))
    assert rms < 0.05 * np.std(stated), (rms, np.std(stated))
    assert np.mean(np.abs(learned - stated) < 3 * sd) > 0.95


# ---------------------------------------------------------------- gradients and the LQR gain


@functools.cache
def _pendulum_model():
    """A model of the paper's pendulum (an angle wrapped, the RBF controller) from random
    transitions, its kernels fitted."""
    cfg = C.make_config(method="gp_model", controller="rbf",
                        episode_length=20, num_updates=2, episodes_per_update=1,
                        model_inducing=30, model_particles=3, model_horizon=0.1,
                        pendulum_overrides=dict(start_std=(1.0, 1.0)))
    prog = rollouts.make_program(cfg)
    task = prog.task
    obs, a, nxt, _, _ = _random_transitions(task, cfg, jax.random.key(4), episodes=3, steps=40)
    xs = jax.vmap(task.features)(obs, a)
    data = MB.take_in(MB.init(prog, None, cfg), xs, MB.targets_of(task, obs, nxt),
                      jnp.ones(obs.shape[0], bool))
    refit = jax.jit(MB.refit, static_argnames=("subset_size", "num_steps"))
    data = data._replace(log_kernels=refit(jax.random.key(5), data, subset_size=100,
                                           num_steps=30, first=True))
    model, mean = jax.jit(MB.build, static_argnums=1)(data, cfg.settings.inducing)
    return cfg, prog, data, model, mean


@pytest.mark.slow
@pytest.mark.xdist_group("model_pendulum")  # one worker builds the model both cases read
@pytest.mark.parametrize("exploration", ["sample", "optimistic"])
def test_the_simulated_return_gradient_matches_finite_differences(exploration):
    """jax.grad of the simulated return (particles, sampled functions and transition noise held
    fixed) against central differences along random directions of the controller's and
    hallucination's parameters, float64."""
    cfg, prog, data, model, mean = _pendulum_model()
    plan = MB.make_plan(prog, cfg, model, jax.random.key(6), exploration, 3, MB.plan_steps(prog, cfg))
    rng = np.random.default_rng(7)
    params0 = jax.tree_util.tree_map(lambda p: jnp.asarray(rng.normal(size=p.shape) * 0.3),
                                     prog.controller.init(jnp.float64))
    hall0 = jax.tree_util.tree_map(lambda p: jnp.asarray(rng.normal(size=p.shape) * 0.3),
                                   data.hallucination)
    optimistic = exploration == "optimistic"

    # one program for the value and the gradient (the differences read its value)
    f = jax.jit(jax.value_and_grad(
        lambda p: MB.simulate(prog, model, mean, plan, p[0], p[1] if optimistic else None, 1.5)))

    p0 = (params0, hall0)
    g = f(p0)[1]
    h = 1e-5
    for _ in range(3):
        d = jax.tree_util.tree_map(lambda p: jnp.asarray(rng.normal(size=p.shape)), p0)
        plus = f(jax.tree_util.tree_map(lambda p, v: p + h * v, p0, d))[0]
        minus = f(jax.tree_util.tree_map(lambda p, v: p - h * v, p0, d))[0]
        fd = (plus - minus) / (2 * h)
        ad = sum(jnp.sum(a * b) for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(d)))
        np.testing.assert_allclose(float(ad), float(fd), rtol=1e-5, atol=1e-7)
    if not optimistic:  # the hallucination enters only the optimistic roll-outs
        assert all(float(jnp.max(jnp.abs(x))) == 0.0 for x in jax.tree_util.tree_leaves(g[1]))


LQR = dict(a=1.0, b=0.5, q=1.0, r=0.1, u_max=20.0)


def _linear_task() -> tasks.Task:
    """x' = a x + b u (+ 0.01 N(0, 1)), reward -(q x^2 + r u^2), x0 ~ U(-1, 1)."""
    a, b, q, r, u_max = (LQR[k] for k in ("a", "b", "q", "r", "u_max"))

    def reset(key, cfg):
        x = jax.random.uniform(key, (1,), cfg.dtype, -1.0, 1.0)
        return x, x

    def step(key, x, u, cfg):
        nxt = a * x + b * u + 0.01 * jax.random.normal(key, (1,), cfg.dtype)
        return nxt, nxt, -(q * x[0] ** 2 + r * u ** 2), jnp.zeros((), bool)

    def make_controller(name):
        del name
        return controllers_lib.make_squashed(
            lambda x: controllers_lib.LinearParams(jnp.concatenate([x, jnp.ones((1,), x.dtype)])),
            lambda dtype: controllers_lib.LinearParams(jnp.zeros((2,), dtype)), u_max, state_dim=1)

    return tasks.Task(
        name="test:linear", obs_dim=1, dt=1.0, max_action=u_max, episode_length=30,
        terminates=False, threshold=None, reset=reset, step=step,
        features=lambda x, u: jnp.concatenate([x, jnp.reshape(u, (1,))]), feature_dim=2,
        make_controller=make_controller, obs_centre=np.zeros(1), obs_scale=np.ones(1),
        reward_fn=lambda x, u, nxt: -(q * x[0] ** 2 + r * u ** 2))


@pytest.mark.training
@pytest.mark.parametrize("reward", ["stated", "learned"])
def test_the_controller_optimised_through_a_learned_model_approaches_the_lqr_gain(reward):
    """On x' = x + 0.5 u with cost x^2 + 0.1 u^2: the model learned from two episodes of random
    actions, the linear controller optimised by L-BFGS through 30-step simulated roll-outs from
    the start distribution; its gain -du/dx at 0 is the LQR gain of scipy's discrete Riccati
    solver (the simulated cost is flat near it: 3% of gain is 0.1% of cost). With the cost
    learnt too (the task states none), the same gain: the cost's kernel needs the refit's 200
    steps (at 50 the fit has not converged: its noise is far above the noiseless cost's, and
    the gain is 7% short). The stated cost is exact, so the record of its error is 0, and the
    learnt one's on the first update is the prior's, 1."""
    tasks.register(_linear_task() if reward == "stated" else
                   _linear_task()._replace(reward_fn=None))
    try:
        cfg = C.make_config(env="test:linear", method="gp_model", controller="linear",
                            episode_length=30, num_updates=1, episodes_per_update=2,
                            init_log_std=float(np.log(3.0)), model_particles=32, model_steps=30,
                            model_horizon=30.0, model_inducing=60, model_optimizer="lbfgs",
                            model_fit_steps=50 if reward == "stated" else 200)
        train = T.make_train(cfg)
        state, rec = jax.jit(train)(jax.random.key(8))
        expected_error = 0.0 if reward == "stated" else 1.0
        assert float(rec.model_reward_error[0]) == pytest.approx(expected_error, abs=1e-9)
        w = np.asarray(state.theta.controller.weights)
        gain = -LQR["u_max"] * w[0]  # d/dx u_max tanh(w0 x + w1) at x = 0 (w1 ~ 0)
        a, b, q, r = (np.array([[LQR[k]]]) for k in ("a", "b", "q", "r"))
        p = scipy.linalg.solve_discrete_are(a, b, q, r)
        k_lqr = float((np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a))[0, 0])
        assert abs(w[1]) * LQR["u_max"] < 0.05
        assert gain == pytest.approx(k_lqr, rel=0.03), (gain, k_lqr)
    finally:
        tasks._REGISTERED.pop("test:linear", None)
        tasks.make_task.cache_clear()


@pytest.mark.parametrize("reward", ["stated", "learned"])
def test_a_held_step_counts_its_reward_k_times_and_an_end_s_bonus_once(reward):
    """A model that moves x by 1 a decision (its mean: zero weights, target mean 1), decisions
    held 3 steps, reward -1 a step and 10 more at the end (x >= 2.5, a hard end): x = 1, 2, 3,
    the third decision ending the episode, so the simulated return is -3 - 3 + (9 - 2) = 1.
    With the reward learnt, a decision's reward is the model's last output (its mean here: -2.5
    a decision, whatever the task states), so the return is 3 (-2.5)."""
    base = _linear_task()
    task = base._replace(
        name="test:held_end", reset=lambda key, cfg: (jnp.zeros((1,), cfg.dtype),) * 2,
        reward_fn=lambda x, u, nxt, end=None: -1.0 + 10.0 * jnp.asarray(end, x.dtype),
        end_fn=lambda nxt: nxt[0] >= 2.5)
    tasks.register(task)
    try:
        cfg = C.make_config(env="test:held_end", method="gp_model", controller="linear",
                            episode_length=30, num_updates=1, episodes_per_update=1,
                            hold_time=3.0, model_particles=2, model_horizon=15.0,
                            model_inducing=4, model_reward=reward)
        prog = rollouts.make_program(cfg)
        assert prog.hold == 3 and MB.plan_steps(prog, cfg) == 5
        outputs = 1 + (reward == "learned")
        xs = jnp.asarray(np.random.default_rng(0).normal(size=(4, 2)))
        data = MB.take_in(MB.init(prog, None, cfg), xs, jnp.zeros((4, outputs)), jnp.ones(4, bool))
        model, _ = jax.jit(MB.build, static_argnums=1)(data, 4)
        assert model.weights.shape[0] == outputs
        assert float(jnp.max(jnp.abs(model.weights))) == 0.0
        plan = MB.make_plan(prog, cfg, model, jax.random.key(0), "mean", 2, 5)
        means = jnp.array([1.0, -2.5][:outputs])
        ret = jax.jit(lambda m, p, c: MB.simulate(prog, m, means, p, c))(
            model, plan, prog.controller.init(jnp.float64))
        assert float(ret) == pytest.approx(1.0 if reward == "stated" else -7.5, abs=1e-12)
    finally:
        tasks._REGISTERED.pop("test:held_end", None)
        tasks.make_task.cache_clear()


@pytest.mark.slow
def test_its_evaluation_episodes_hold_the_action_as_its_learning_episodes_do():
    """gp_model's controller is optimised for actions held `hold_time`: its evaluation on the
    paper's pendulum (start fixed, reward noise off) holds them 20 steps, as a loop of the
    pendulum's own step does, and differs from deciding at every step."""
    cfg = C.make_config(method="gp_model", controller="rbf", episode_length=200, num_updates=1,
                        episodes_per_update=1, eval_episodes=2, hold_time=0.1,
                        pendulum_overrides=dict(start_std=(0.0, 0.0), reward_noise_std=0.0,
                                                start_mean=(0.3, 0.0)))
    prog = rollouts.make_program(cfg)
    assert prog.hold == 20 and methods.get("gp_model").eval_held
    rng = np.random.default_rng(11)
    params = jax.tree_util.tree_map(lambda p: jnp.asarray(rng.normal(size=p.shape)),
                                    prog.controller.init(jnp.float64))
    theta = types.SimpleNamespace(controller=params)
    _, _, ret = rollouts.evaluate(prog, jax.random.key(0), theta, cfg)
    step = jax.jit(lambda s, a: pendulum.step(jax.random.key(1), s, a, cfg.pendulum))
    apply = jax.jit(prog.controller.apply)
    s, total = jnp.array([0.3, 0.0]), 0.0
    for _ in range(10):
        a = apply(params, s)
        for _ in range(20):
            s, r = step(s, a)
            total += float(r)
    assert float(ret) == pytest.approx(total, rel=1e-12)
    every_step = rollouts.evaluate(prog._replace(method=methods.get("gp_pg")), jax.random.key(0),
                                   theta, cfg)[2]
    assert abs(float(every_step) - total) > 1e-6 * abs(total), (float(every_step), total)


def test_it_is_a_registered_method_the_drivers_take():
    m = methods.get("gp_model")
    assert "gp_model" in C.METHODS and "gp_model" not in C.PAPER_METHODS
    assert m.prior == "none" and set(MB.RECORDS) <= set(T.record_fields("gp_model"))


def test_a_smoothed_end_tends_to_the_hard_end_and_passes_a_gradient():
    """A task that ends when x > 0.5 and pays 1 per step: with the end's temperature small the
    simulated return is the hard end's; with a temperature the return's gradient in the
    controller is not 0, where the hard end's is."""
    base = _linear_task()
    task = base._replace(
        name="test:linear_end", reward_fn=lambda x, u, nxt, end=None: jnp.ones((), x.dtype),
        end_fn=lambda nxt: nxt[0] > 0.5, end_margin=lambda nxt: nxt[0] - 0.5)
    tasks.register(task)
    try:
        cfg = C.make_config(env="test:linear_end", method="gp_model", controller="linear",
                            episode_length=30, num_updates=1, episodes_per_update=1,
                            model_particles=8, model_horizon=10.0, model_inducing=30)
        prog = rollouts.make_program(cfg)
        rng = np.random.default_rng(9)
        x = jnp.asarray(rng.uniform(-2, 2, size=(60, 1)))
        u = jnp.asarray(rng.uniform(-3, 3, size=60))
        nxt = LQR["a"] * x + LQR["b"] * u[:, None]
        data = MB.take_in(MB.init(prog, None, cfg), jnp.concatenate([x, u[:, None]], 1),
                          MB.targets_of(task, x, nxt), jnp.ones(60, bool))
        refit = jax.jit(MB.refit, static_argnames=("subset_size", "num_steps"))
        data = data._replace(log_kernels=refit(jax.random.key(1), data, subset_size=60,
                                               num_steps=30, first=True))
        model, mean = jax.jit(MB.build, static_argnums=1)(data, 30)
        plan = MB.make_plan(prog, cfg, model, jax.random.key(2), "mean", 8, 10)
        params = controllers_lib.LinearParams(jnp.array([0.01, 0.02]))
        hard_prog = prog._replace(task=task._replace(end_margin=None))
        def hard_return(p):
            return MB.simulate(hard_prog, model, mean, plan, p)

        def soft_return(p, softness):
            return MB.simulate(prog, model, mean, plan, p, end_softness=softness)

        hard = jax.jit(hard_return)(params)
        soft = jax.jit(soft_return)(params, 1e-6)
        assert 1.0 < float(hard) < 10.0  # some particles end within the horizon, not all at once
        np.testing.assert_allclose(float(soft), float(hard), rtol=1e-6)
        g_hard = jax.jit(jax.grad(hard_return))(params)
        g_soft = jax.jit(jax.grad(soft_return))(params, 0.1)
        assert float(jnp.max(jnp.abs(g_hard.weights))) == 0.0
        assert float(jnp.max(jnp.abs(g_soft.weights))) > 1e-3
    finally:
        tasks._REGISTERED.pop("test:linear_end", None)
        tasks.make_task.cache_clear()


def _model_study():
    import importlib.util
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = importlib.util.spec_from_file_location(
        "model_study", os.path.join(root, "experiments", "model_study.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module, os.path.join(root, "docs", "results", "model")


def test_the_presets_hold_the_model_study_s_tuned_settings():
    """`gpguided reproduce --preset <task> --methods gp_model` runs it as the study did: the base
    settings its tuning ran from, its budget's updates and the settings the tuning chose
    (docs/results/model/<task>/tuning.json), then the planning study's
    (docs/results/planning/<task>/tuning.json), and the study's runs start from the preset's own.
    The study reads the settings it does not search from the preset (`model_study.base`), so the
    preset's are those of the tuning record's base."""
    import json
    import os

    study, results = _model_study()
    for task in study.TASKS:
        path = os.path.join(results, task, "tuning.json")
        if not os.path.exists(path):
            continue
        with open(path) as f:
            record = json.load(f)
        chosen = record["chosen"]
        assert study.BASE[task] == pytest.approx(record["base"]), task
        # and on top of them, the planning study's choice (experiments/planning_study.py)
        expected = {**study.BASE[task], "num_updates": study.overrides(task, {})["num_updates"],
                    **chosen, **study.planned(task)}
        assert C.METHOD_PRESETS[task]["gp_model"] == pytest.approx(expected), task
        if task.startswith("inverted"):
            continue  # building a brax task compiles its physics; the gymnax task checks the rest
        # a run of the study gives the config the preset gives
        cfg = C.preset(task, method="gp_model",
                       **study.overrides(task, {**chosen, **study.planned(task)}))
        assert cfg.to_json_dict() == C.preset(task, method="gp_model").to_json_dict()


@pytest.mark.training
def test_a_run_resumed_from_its_checkpoint_equals_one_uninterrupted(tmp_path):
    """`reproduce` of gp_model (tiny preset, held actions, chunks of 2 of its 6 updates): stopped
    after one chunk and resumed from the checkpoint (the model's buffer and kernels in it), the
    records equal the uninterrupted run's bit for bit."""
    from gpguided_jax import reproduce as R

    kw = dict(preset="tiny", seeds=[0, 1], chunk_size=2, methods=["gp_model"],
              overrides=dict(hold_time=0.01, model_inducing=8, model_steps=5, model_particles=2,
                             model_horizon=0.05, eval_episodes=1))
    R.reproduce(out_dir=str(tmp_path / "full"), progress=lambda m: None, **kw)
    part = R.reproduce(out_dir=str(tmp_path / "part"), max_chunks=1, progress=lambda m: None, **kw)
    assert not part["complete"]
    msgs = []
    assert R.reproduce(out_dir=str(tmp_path / "part"), progress=msgs.append, **kw)["complete"]
    assert any("resuming" in m for m in msgs)
    a, b = np.load(tmp_path / "full" / "results.npz"), np.load(tmp_path / "part" / "results.npz")
    for k in ("eval_return", "mean_return", *MB.RECORDS):
        assert np.isfinite(a[k][0]).all(), k
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert np.asarray(a["model_data"])[0, :, -1].min() > np.asarray(a["model_data"])[0, :, 1].max()


def test_the_cost_stage_s_cheapest_is_the_least_wall_time_to_the_threshold_and_the_preset():
    """experiments/planning_study.py's cost stage (docs/results/planning/<task>/cost.json): every
    pair of its committed grid ran once; its `cheapest` is recomputed here from each run's own
    steps to the threshold and wall seconds (the median over the seeds of the run's seconds per
    seed times steps to it over the budget, among the runs reaching it on every seed), and the
    preset holds it."""
    import itertools
    import json
    import os

    from conftest import ROOT, experiment

    planning = experiment("planning_study")
    for task in planning.COST_TASKS:
        path = os.path.join(ROOT, "docs", "results", "planning", task, "cost.json")
        with open(path) as f:
            record = json.load(f)
        assert record["grid"] == planning.COST_GRID
        fields = list(planning.COST_GRID)
        ran = [tuple(r["settings"][k] for k in fields) for r in record["rows"]]
        assert sorted(ran) == sorted(itertools.product(*planning.COST_GRID.values()))
        budget = planning.MS.BUDGETS[task]
        times = {}
        for r, key in zip(record["rows"], ran):
            steps = r["steps_to"]
            if all(v is not None for v in steps):
                times[key] = sorted(r["wall_s"] / len(steps) * v / budget for v in steps)
                n = len(steps)
                times[key] = (times[key][(n - 1) // 2] + times[key][n // 2]) / 2
        assert times, "no configuration reached the threshold on every tuning seed"
        best = min(times, key=times.get)
        assert {k: record["cheapest"][k] for k in fields} == dict(zip(fields, best))
        preset = C.METHOD_PRESETS[task]["gp_model"]
        assert {k: preset[k] for k in fields} == dict(zip(fields, best))
