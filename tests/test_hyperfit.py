"""Tests of the exact GP marginal likelihood and its optax minimisation (design: docs/design.md#gp-model)."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import scipy.stats  # noqa: E402
from jax.test_util import check_grads  # noqa: E402

from gpguided_jax import hyperfit, kernels  # noqa: E402


def _np_gram(xs, ls, sf2):
    z = (xs[:, None, :] - xs[None, :, :]) / ls
    return sf2 * np.exp(-0.5 * np.sum(z * z, -1))


def test_nlml_matches_scipy_density():
    rng = np.random.default_rng(0)
    xs, ys = rng.normal(size=(30, 3)), rng.normal(size=30)
    ls, sf2, sn2 = np.array([0.7, 1.2, 2.0]), 1.3, 0.2
    expected = -scipy.stats.multivariate_normal(
        np.zeros(30), _np_gram(xs, ls, sf2) + sn2 * np.eye(30)
    ).logpdf(ys)
    got = hyperfit.negative_log_marginal_likelihood(
        kernels.make_kernel_params(ls, sf2, sn2), jnp.array(xs), jnp.array(ys), jitter=0.0
    )
    np.testing.assert_allclose(got, expected, rtol=1e-10)


@pytest.mark.slow
def test_check_grads_and_closed_form_gradient():
    rng = np.random.default_rng(1)
    xs, ys = jnp.array(rng.normal(size=(25, 2))), jnp.array(rng.normal(size=25))
    lp = hyperfit.to_log(kernels.make_kernel_params([0.8, 1.5], 1.1, 0.3))
    check_grads(lambda p: hyperfit.nlml_log(p, xs, ys), (lp,), order=1, modes=("fwd", "rev"))
    loss, grads = hyperfit.nlml_and_grad(lp, xs, ys)
    auto = jax.grad(hyperfit.nlml_log)(lp, xs, ys)
    np.testing.assert_allclose(loss, hyperfit.nlml_log(lp, xs, ys), rtol=1e-12)
    for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(auto), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("optimizer,steps", [("lbfgs", 30), ("adam", 250)])
def test_fit_recovers_lengthscales_vmapped_over_seeds(optimizer, steps):
    """Data drawn from a known GP (N = 300, D = 2): lengthscales recovered within 25%."""
    n = 300
    true_ls, true_sf2, true_sn2 = np.array([0.6, 2.0]), 1.5, 0.01
    rng = np.random.default_rng(2)
    xs = rng.uniform(-3, 3, size=(n, 2))
    L = np.linalg.cholesky(_np_gram(xs, true_ls, true_sf2) + 1e-9 * np.eye(n))
    ys = np.stack(
        [L @ r.normal(size=n) + np.sqrt(true_sn2) * r.normal(size=n)
         for r in (np.random.default_rng(s) for s in (10, 11))]
    )
    fit = jax.jit(jax.vmap(lambda y: hyperfit.fit(
        jnp.array(xs), y, num_steps=steps, optimizer=optimizer, learning_rate=0.05)))
    res = fit(jnp.array(ys))
    ls = np.asarray(res.params.lengthscales)
    assert np.all(np.abs(ls / true_ls - 1) < 0.25), ls
    sn2 = np.asarray(res.params.noise_variance)
    assert np.all((sn2 > true_sn2 / 2) & (sn2 < true_sn2 * 2)), sn2
    losses = np.asarray(res.losses)
    assert losses.shape == (2, steps) and np.all(np.isfinite(losses))
    assert np.all(np.asarray(res.final_loss) < losses[:, 0] - 10)


@pytest.mark.parametrize("optimizer", ["lbfgs", "adam"])
def test_fit_guards_keep_it_finite(optimizer):
    # Duplicated inputs, a constant feature and a tiny target scale: bounded and finite.
    rng = np.random.default_rng(3)
    xs = np.concatenate([rng.normal(size=(20, 2)), np.zeros((20, 1))], axis=1)
    xs = np.concatenate([xs, xs])
    ys = 1e-3 * rng.normal(size=40)
    res = jax.jit(lambda x, y: hyperfit.fit(x, y, num_steps=60, learning_rate=0.5,
                                            optimizer=optimizer))(jnp.array(xs), jnp.array(ys))
    for leaf in jax.tree.leaves(res):
        assert np.all(np.isfinite(np.asarray(leaf)))
    lower, upper = hyperfit.parameter_bounds(jnp.array(xs), jnp.array(ys))
    lp = hyperfit.to_log(res.params)
    for v, lo, hi in zip(jax.tree.leaves(lp), jax.tree.leaves(lower), jax.tree.leaves(upper),
                         strict=True):
        assert np.all(np.asarray(v) >= np.asarray(lo) - 1e-9)
        assert np.all(np.asarray(v) <= np.asarray(hi) + 1e-9)


@pytest.mark.slow
def test_lbfgs_reaches_a_likelihood_at_least_as_high_as_adam():
    """15 L-BFGS iterations vs 100 Adam steps (the fit used before) on pendulum-like data with a
    small noise (sigma_f^2/sigma_n^2 ~ 400): the L-BFGS NLML is not higher."""
    rng = np.random.default_rng(4)
    phi, omega, a = rng.uniform(2, 3, 400), rng.normal(0, 0.5, 400), rng.normal(1, 1.5, 400)
    xs = np.stack([np.sin(phi), np.cos(phi), omega, a], 1)
    ys = -10 * (phi - np.pi) ** 2 - omega**2 - 0.1 * a + 0.1 * rng.normal(size=400)
    ys = ys - ys.mean()
    lb = jax.jit(lambda x, y: hyperfit.fit(x, y, num_steps=15))(jnp.array(xs), jnp.array(ys))
    ad = jax.jit(lambda x, y: hyperfit.fit(x, y, num_steps=100, optimizer="adam"))(
        jnp.array(xs), jnp.array(ys))
    assert float(lb.final_loss) <= float(ad.final_loss) + 1e-6 * abs(float(ad.final_loss))
    with pytest.raises(ValueError, match="optimizer"):
        hyperfit.fit(jnp.array(xs), jnp.array(ys), optimizer="newton")


def _longdouble_inverse(A):
    """A^{-1} by Cholesky and forward substitution in np.longdouble (80-bit on x86): a reference
    with 11 more bits than float64, independent of LAPACK and of the blocked code."""
    A = np.asarray(A, np.longdouble)
    n = A.shape[0]
    L = np.zeros_like(A)
    for j in range(n):
        L[j, j] = np.sqrt(A[j, j] - L[j, :j] @ L[j, :j])
        L[j + 1:, j] = (A[j + 1:, j] - L[j + 1:, :j] @ L[j, :j]) / L[j, j]
    X = np.zeros_like(A)
    for i in range(n):
        X[i] = ((np.arange(n) == i) - L[i, :i] @ X[:i]) / L[i, i]
    return X.T @ X


@pytest.mark.slow
@pytest.mark.parametrize("n", [1, 7, 128, 129, 260, 301])
def test_cholesky_inverse_against_an_80_bit_inverse(n):
    """The blocked potri (`cholesky_inverse`) on sizes below, at and above the block size (odd
    splits included), for a well- and an ill-conditioned Gram matrix (cond ~1e2 and ~1e9), in
    float64 and float32, has the error of the plain triangular-solve inverse it replaced (within
    a factor 4): both are set by the conditioning, not by the blocking."""
    rng = np.random.default_rng(n)
    xs = rng.normal(size=(n, 3))
    for noise in (1.0, 1e-7):
        A = _np_gram(xs, np.array([0.8, 1.0, 1.5]), 1.0) + noise * np.eye(n)
        ref = _longdouble_inverse(A)
        scale = float(np.max(np.abs(ref)))
        for dtype in (jnp.float64, jnp.float32):
            L = jnp.linalg.cholesky(jnp.asarray(A, dtype))
            if not bool(jnp.all(jnp.isfinite(L))):
                continue  # float32 cannot factor the ill-conditioned matrix at all
            blocked = np.asarray(jax.jit(hyperfit.cholesky_inverse)(L), np.longdouble)
            L_inv = jax.scipy.linalg.solve_triangular(L, jnp.eye(n, dtype=dtype), lower=True)
            plain = np.asarray(L_inv.T @ L_inv, np.longdouble)
            err_blocked = float(np.max(np.abs(blocked - ref))) / scale
            err_plain = float(np.max(np.abs(plain - ref))) / scale
            eps = float(jnp.finfo(dtype).eps)
            assert err_blocked <= 4 * err_plain + 8 * eps, (noise, dtype, err_blocked, err_plain)
            assert np.allclose(blocked, blocked.T, rtol=0, atol=8 * eps * scale)


def test_closed_form_gradient_on_the_paper_fit_size():
    """nlml_and_grad at N = 500 (the paper preset's subset, where the blocked inverse has two
    levels) against jax.grad of the likelihood."""
    rng = np.random.default_rng(5)
    phi, omega, a = rng.uniform(2, 3, 500), rng.normal(0, 0.5, 500), rng.normal(1, 1.5, 500)
    xs = jnp.array(np.stack([np.sin(phi), np.cos(phi), omega, a], 1))
    ys = jnp.array(-10 * (phi - np.pi) ** 2 - omega**2 + 0.3 * rng.normal(size=500))
    lp = hyperfit.to_log(kernels.make_kernel_params([0.3, 0.1, 0.7, 20.0], 50.0, 0.5))
    loss, grads = jax.jit(hyperfit.nlml_and_grad)(lp, xs, ys)
    auto = jax.jit(jax.grad(hyperfit.nlml_log))(lp, xs, ys)
    np.testing.assert_allclose(loss, hyperfit.nlml_log(lp, xs, ys), rtol=1e-12)
    for a_, b_ in zip(jax.tree.leaves(grads), jax.tree.leaves(auto), strict=True):
        np.testing.assert_allclose(a_, b_, rtol=1e-7, atol=1e-8)
