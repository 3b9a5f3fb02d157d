"""Tests of the sparse online GP (design: docs/design.md#sparse-gp) against independent references.

References: the exact GP posterior by Cholesky (scipy); Csato and Opper's projected-update formulas
written out in NumPy; the closed-form projected-process (DTC) posterior of a fixed basis; and the
plain NumPy online GP `gp_reference` (Csato-Opper's own Q/C recursion on variable-size arrays), run
in np.longdouble (80-bit) as the high-precision oracle of long and ill-conditioned streams.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpguided_jax import gp_reference, kernels, sparse_gp

LS = np.array([0.9, 1.3, 1.0, 1.6])
SF2, SN2 = 1.4, 0.05
EXACT = dict(noise_novelty=0.0, collapse_fraction=1e-30)  # every point joins (with novelty_tol 0)


# the health check compiled once per shape and dtype, as training runs it (op by op it would
# compile each of its operations anew for every shape)
_check = jax.jit(sparse_gp.check)

def _hyper(dtype=jnp.float64, ls=LS, sf2=SF2, sn2=SN2):
    return kernels.make_kernel_params(ls, sf2, sn2, dtype=dtype)


def _np_gram(a, b, ls=LS, sf2=SF2):
    z = (a[:, None, :] - b[None, :, :]) / ls
    return sf2 * np.exp(-0.5 * np.sum(z * z, axis=-1))


def _data(n, seed, d=4):
    rng = np.random.default_rng(seed)
    xs = rng.normal(size=(n, d))
    ys = np.sin(xs @ np.array([1.0, -0.5, 0.3, 0.8])[:d]) + 0.1 * rng.normal(size=n)
    return xs, ys


def _active(state):
    m = np.asarray(state.mask)
    return (
        m,
        np.asarray(state.basis_vectors)[m],
        np.asarray(state.alpha)[m],
        np.asarray(sparse_gp.covariance_correction(state))[np.ix_(m, m)],
        np.asarray(sparse_gp.gram_inverse(state))[np.ix_(m, m)],
        np.asarray(state.timestamps)[m],
    )


@jax.jit
def _predict_all(state, xs, hyper):
    return jax.vmap(lambda x: sparse_gp.predict(state, x, hyper))(xs)


def _predict(state, xs, hyper):
    """Predictions at the rows of xs (one compiled program per shape and dtype: the state and
    hyperparameters are arguments, not constants)."""
    mean, var = _predict_all(state, jnp.asarray(xs), hyper)
    return np.asarray(mean, np.float64), np.asarray(var, np.float64)


@functools.partial(jax.jit, static_argnames="age_fn")
def _update_batch_args(state, xs, ys, ts, hyper, traced, age_fn):
    return sparse_gp.update_batch(state, xs, ys, hyper, ts, with_info=True, age_fn=age_fn, **traced)


def _update_batch_jit(hyper=None, novelty_tol=0.0, age_penalty=0.0, age_scale=1.0, age_fn="exp"):
    """`update_batch` with info, compiled, as a function of (state, xs, ys, timestamps). The
    hyperparameters and the traceable settings (`update_with_info`'s defaults unless given) are
    arguments of one compiled program per shape, dtype and age function, as training passes
    them: the tests that differ only in their values share it. Python floats stay Python
    floats (weakly typed), so they promote as the same constants would."""
    hyper = hyper if hyper is not None else _hyper()
    traced = dict(novelty_tol=float(novelty_tol), age_penalty=float(age_penalty),
                  age_scale=float(age_scale))
    return lambda s, x, y, t: _update_batch_args(s, x, y, t, hyper, traced, age_fn)


def _same_set(a, b, decimals=9):
    return sorted(map(tuple, np.round(a, decimals))) == sorted(map(tuple, np.round(b, decimals)))


# --- exact GP ------------------------------------------------------------------------------------


def test_full_set_equals_exact_gp():
    n = 40
    xs, ys = _data(n, 0)
    state = sparse_gp.update_batch(
        sparse_gp.init(n, 4), jnp.array(xs), jnp.array(ys), _hyper(), 0, **EXACT
    )
    m, bv, alpha, C, Q, _ = _active(state)
    assert m.sum() == n
    np.testing.assert_array_equal(bv, xs)  # slots filled in order while nothing is deleted
    A = _np_gram(xs, xs) + SN2 * np.eye(n)
    cho = scipy.linalg.cho_factor(A)
    alpha_exact = scipy.linalg.cho_solve(cho, ys)
    A_inv = scipy.linalg.cho_solve(cho, np.eye(n))
    np.testing.assert_allclose(alpha, alpha_exact, rtol=1e-8, atol=1e-8 * np.abs(alpha_exact).max())
    np.testing.assert_allclose(C, -A_inv, rtol=1e-8, atol=1e-8 * np.abs(A_inv).max())
    K_inv = np.linalg.inv(_np_gram(xs, xs))
    np.testing.assert_allclose(Q, K_inv, rtol=1e-6, atol=1e-8 * np.abs(K_inv).max())
    tests = np.random.default_rng(1).normal(size=(50, 4))
    Ks = _np_gram(tests, xs)
    mean_exact = Ks @ alpha_exact
    var_exact = SF2 - np.sum(Ks * scipy.linalg.cho_solve(cho, Ks.T).T, axis=1)
    for s in (state, sparse_gp.exact_state(jnp.array(xs), jnp.array(ys), _hyper())):
        mean, var = _predict(s, tests, _hyper())
        assert np.max(np.abs(mean - mean_exact)) / np.max(np.abs(mean_exact)) < 1e-8
        assert np.max(np.abs(var - var_exact) / var_exact) < 1e-8


def test_add_then_delete_equals_projected_update():
    """Inserting x as a BV and deleting it again is the projected update (design:
    docs/design.md#sparse-gp)."""
    n = 8
    xs, ys = _data(n + 1, 2)
    state = sparse_gp.update_batch(
        sparse_gp.init(n, 4), jnp.array(xs[:n]), jnp.array(ys[:n]), _hyper(), 5, **EXACT
    )
    x, y = xs[n], ys[n]
    # Expected: the projected update of Csato and Opper, written out in NumPy.
    _, bv, alpha, C, Q, _ = _active(state)
    k = _np_gram(bv, x[None])[:, 0]
    v = SF2 + k @ C @ k
    q, r = (y - k @ alpha) / (SN2 + v), -1.0 / (SN2 + v)
    e_hat = Q @ k
    gamma = SF2 - k @ e_hat
    eta = 1.0 / (1.0 + gamma * r)
    s = C @ k + e_hat
    alpha_proj, C_proj = alpha + q * eta * s, C + r * eta * np.outer(s, s)
    # Actual: the set is full, x is new with an older timestamp than every BV, and the huge age
    # penalty makes it the one deleted.
    out, info = sparse_gp.update_with_info(
        state, jnp.array(x), jnp.array(y), _hyper(), 0, age_penalty=1e6, **EXACT
    )
    assert bool(info.added) and int(info.deleted_slot) == int(info.inserted_slot) == n
    m2, bv2, alpha2, C2, Q2, _ = _active(out)
    assert m2.sum() == n
    np.testing.assert_array_equal(bv2, bv)
    np.testing.assert_allclose(alpha2, alpha_proj, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(C2, C_proj, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(Q2, Q, rtol=1e-9, atol=1e-9 * np.abs(Q).max())
    # And the projected branch itself (a point inside the span: tolerance close to 1).
    proj = sparse_gp.update(state, jnp.array(x), jnp.array(y), _hyper(), 0, novelty_tol=0.999,
                            **EXACT)
    _, _, alpha3, C3, _, _ = _active(proj)
    np.testing.assert_allclose(alpha3, alpha_proj, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(C3, C_proj, rtol=1e-10, atol=1e-12)


# --- against the NumPy reference ------------------------------------------------------------------


@pytest.mark.parametrize(
    "age_fn,age_penalty,age_scale", [("exp", 0.0, 1.0), ("exp", 0.3, 0.5), ("logit", 0.2, 1.0)]
)
def test_matches_numpy_reference_with_budget(age_fn, age_penalty, age_scale):
    n, capacity = 160, 20
    xs, ys = _data(n, 3)
    ts = np.arange(n) // 25
    kw = dict(novelty_tol=1e-3, age_penalty=age_penalty, age_scale=age_scale, age_fn=age_fn)
    state, _ = _update_batch_jit(**kw)(
        sparse_gp.init(capacity, 4), jnp.array(xs), jnp.array(ys), jnp.array(ts)
    )
    ref = gp_reference.OnlineGP(capacity, 4, LS, SF2, SN2, **kw)
    outcomes = [ref.update(xs[i], ys[i], ts[i]) for i in range(n)]
    assert outcomes.count("exchanged") > 50  # the deletion path is exercised
    assert int(sparse_gp.num_basis_vectors(state)) == ref.size == capacity
    m, bv, _, _, _, t = _active(state)
    # Same basis vectors (as sets: the slot order differs from the reference's list order).
    order_j = np.lexsort(bv.T[::-1])
    order_r = np.lexsort(ref.basis_vectors.T[::-1])
    np.testing.assert_array_equal(bv[order_j], ref.basis_vectors[order_r])
    np.testing.assert_array_equal(t[order_j], ref.timestamps[order_r])
    tests = np.random.default_rng(4).normal(size=(300, 4)) * 1.2
    mean, var = _predict(state, tests, _hyper())
    ref_pred = np.array([ref.predict(x) for x in tests])
    np.testing.assert_allclose(mean, ref_pred[:, 0], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(var, ref_pred[:, 1], rtol=1e-7, atol=1e-9)
    assert var.min() >= 0 and var.max() <= SF2 * (1 + 1e-12)


# --- long adversarial streams ---------------------------------------------------------------------

# Pendulum-like data: 200 Hz trajectories (consecutive inputs nearly equal), exact repeats and
# near-duplicates of earlier inputs (with fresh noise on their targets), returns of size ~30 with
# observation noise 0.1: sigma_f^2 / sigma_n^2 = 3000. This is the regime in which the first
# implementation (a stored inverse Q and k** + k^T C k) diverged while staying finite.
PEND_LS = np.array([0.3, 0.3, 1.0, 3.0])
PEND_SF2, PEND_SN2 = 30.0, 0.01


def _pendulum_stream(n, seed, duplicate_share=0.3):
    rng = np.random.default_rng(seed)
    phi = np.pi - 0.5 + np.cumsum(rng.normal(0, 0.01, n))
    omega = np.cumsum(rng.normal(0, 0.02, n)) % 4 - 2
    a = np.clip(rng.normal(2, 1.5, n), -6, 6)
    xs = np.stack([np.sin(phi), np.cos(phi), omega, a], 1)
    ys = -10 * (phi - np.pi) ** 2 - 10 * omega**2 / 16 - 0.1 * a**2 - 5 + rng.normal(0, 0.1, n)
    dup = rng.random(n) < duplicate_share
    src = np.minimum(rng.integers(0, n, n), np.arange(n))
    jitter = np.where(rng.random((n, 1)) < 0.5, 0.0, rng.normal(0, 1e-6, (n, 4)))
    xs[dup] = xs[src[dup]] + jitter[dup]
    ys[dup] = ys[src[dup]] + rng.normal(0, 0.1, dup.sum())
    return xs, ys


def _replay_in_longdouble(xs, ys, ts, info, capacity, hyper, prior_mean, **kw):
    """The NumPy reference in 80-bit arithmetic, forced along the JAX run's decisions."""
    ref = gp_reference.OnlineGP(
        capacity, xs.shape[1], np.asarray(hyper.lengthscales, np.float64),
        float(hyper.signal_variance), float(hyper.noise_variance), prior_mean=prior_mean,
        dtype=np.longdouble, **kw)
    info = jax.tree.map(np.asarray, info)
    slots = []  # the JAX slot of each entry of the reference's BV list
    for i in range(len(ys)):
        if info.added[i]:
            slots.append(int(info.inserted_slot[i]))
        d = int(info.deleted_slot[i])
        index = slots.index(d) if d >= 0 else None
        ref.update(xs[i], ys[i], ts[i], force=(bool(info.added[i]), index))
        if index is not None:
            slots.pop(index)
    return ref


def _gram_condition(state, hyper):
    m = np.asarray(state.mask)
    B = np.asarray(state.basis_vectors, np.float64)[m]
    K = _np_gram(B, B, np.asarray(hyper.lengthscales, np.float64), float(hyper.signal_variance))
    return np.linalg.cond(K), m.sum()


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("age_penalty", [0.0, 10.0])
def test_long_adversarial_stream_matches_80bit_replay(dtype, age_penalty):
    """10^4 updates of pendulum-like data with repeats and near-duplicates, capacity exhausted
    (thousands of exchanges), sigma_f^2/sigma_n^2 = 3000, in float64 and float32.

    The float64/float32 state is compared with Csato-Opper's recursion replayed in 80-bit
    arithmetic along the same decisions (which point joins, which BV goes), so the comparison
    measures rounding only. Tolerances: float64 1e-6 of the data scale max|y - m0| + sigma_f;
    float32 3% of it (measured 0.3-2%: a mean k^T alpha sums terms of size eps * cond(K_B) larger
    than the result, cond(K_B) ~ 1e4-1e5 at the float32 novelty threshold). Variances: 1e-8 of
    sigma_f^2 in float64, 1e-3 in float32.
    """
    n, capacity = 10_000, 50
    xs, ys = _pendulum_stream(n, 0)
    ts = np.arange(n) // 150
    hyper = _hyper(dtype, PEND_LS, PEND_SF2, PEND_SN2)
    m0 = float(np.mean(ys[:150]))
    kw = dict(novelty_tol=1e-4, age_penalty=age_penalty, age_scale=1.0)
    state, info = _update_batch_jit(hyper, **kw)(
        sparse_gp.init(capacity, 4, dtype, prior_mean=m0), jnp.array(xs, dtype),
        jnp.array(ys, dtype), jnp.array(ts))
    assert int(np.sum(np.asarray(info.deleted_slot) >= 0)) > 1000  # the budget is exhausted
    xq = np.asarray(jnp.array(xs, dtype), np.float64)  # the inputs as the run saw them
    yq = np.asarray(jnp.array(ys, dtype), np.float64)
    ref = _replay_in_longdouble(xq, yq, ts, info, capacity, hyper,
                                float(jnp.asarray(m0, dtype)), **kw)
    assert _same_set(np.asarray(state.basis_vectors, np.float64)[np.asarray(state.mask)],
                     ref.basis_vectors.astype(np.float64))
    tests = xq[::37]
    mean, var = _predict(state, jnp.array(tests, dtype), hyper)
    ref_pred = np.array([ref.predict(x) for x in tests]).astype(np.float64)
    scale = np.max(np.abs(ys - m0)) + np.sqrt(PEND_SF2)
    mean_tol, var_tol = (1e-6, 1e-8) if dtype == jnp.float64 else (0.03, 1e-3)
    assert np.max(np.abs(mean - ref_pred[:, 0])) <= mean_tol * scale
    assert np.max(np.abs(var - ref_pred[:, 1])) <= var_tol * PEND_SF2
    assert var.min() >= 0 and ref_pred[:, 1].min() > 0
    # Conditioning of the kept basis: cond(K_B) <= n^2 k** / (collapse_fraction gamma_min).
    cond, nbv = _gram_condition(state, hyper)
    gamma_min = float(sparse_gp.novelty_threshold(hyper, dtype, 1e-4))
    assert cond <= nbv**2 * PEND_SF2 / (0.5 * gamma_min), cond
    health = _check(state, hyper, jnp.array(xs[-150:], dtype), jnp.array(ys[-150:], dtype))
    assert bool(health.finite) and bool(health.posterior_below_prior)


def _dtc_posterior(bv, xs, ys, tests, ls, sf2, sn2, m0):
    """Projected-process (DTC) posterior with basis bv, data (xs, ys), by Cholesky in float64."""
    Kb = _np_gram(bv, bv, ls, sf2)
    Kbx = _np_gram(bv, xs, ls, sf2)
    A = Kb + Kbx @ Kbx.T / sn2
    cA, cK = scipy.linalg.cho_factor(A), scipy.linalg.cho_factor(Kb)
    Ks = _np_gram(tests, bv, ls, sf2)
    mean = m0 + Ks @ scipy.linalg.cho_solve(cA, Kbx @ (ys - m0)) / sn2
    var = (sf2 - np.sum(Ks * scipy.linalg.cho_solve(cK, Ks.T).T, axis=1)
           + np.sum(Ks * scipy.linalg.cho_solve(cA, Ks.T).T, axis=1))
    return mean, var


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("sf2_over_sn2", [3e3, 1e6])
def test_repeated_inputs_match_the_projected_process_posterior(dtype, sf2_over_sn2):
    """12 well-separated BVs, then 10^4 exact repeats and near-duplicates (1e-6 apart) of them with
    noisy targets, sigma_f^2/sigma_n^2 up to 1e6. Every later point is projected, so the online
    GP must equal the closed-form DTC posterior of the 12 BVs given all the data (Cholesky,
    float64). The posterior variance at the BVs shrinks to ~sigma_n^2 / 800 (~1e-9 sigma_f^2 at
    1e6): the cancellation that gave the first implementation wrong-signed variances."""
    rng = np.random.default_rng(11)
    sf2 = 2.0
    sn2 = sf2 / sf2_over_sn2
    ls = np.array([0.7, 0.7, 0.7, 0.7])
    bv = np.array([[i % 3, (i // 3) % 2, i // 6, 0.5 * i] for i in range(12)], float) * 1.5
    f = lambda x: np.sin(x @ np.array([0.6, -0.4, 0.3, 0.2]))  # noqa: E731
    n = 10_000
    idx = rng.integers(0, 12, n)
    near = np.where(rng.random((n, 1)) < 0.5, 0.0, rng.normal(0, 1e-6, (n, 4)))
    xs = np.concatenate([bv, bv[idx] + near])
    ys = f(xs) + np.sqrt(sn2) * rng.normal(size=len(xs))
    m0 = -0.3
    hyper = _hyper(dtype, ls, sf2, sn2)
    state, info = _update_batch_jit(hyper)(
        sparse_gp.init(20, 4, dtype, prior_mean=m0), jnp.array(xs, dtype), jnp.array(ys, dtype),
        jnp.zeros(len(xs), jnp.int32))
    added = np.asarray(info.added)
    assert added[:12].all() and not added[12:].any()
    tests = np.concatenate([bv, bv + 0.3 * rng.normal(size=bv.shape), rng.normal(size=(30, 4)) * 2])
    mean, var = _predict(state, jnp.array(tests, dtype), hyper)
    xq = np.asarray(jnp.array(xs, dtype), np.float64)
    yq = np.asarray(jnp.array(ys, dtype), np.float64)
    mean_ref, var_ref = _dtc_posterior(xq[:12], xq, yq, tests, ls, sf2, sn2, m0)
    assert var.min() >= 0
    if dtype == jnp.float64:
        np.testing.assert_allclose(mean, mean_ref, rtol=0, atol=1e-7)
        np.testing.assert_allclose(var, var_ref, rtol=1e-5, atol=1e-9 * sf2)
    else:
        np.testing.assert_allclose(mean, mean_ref, rtol=0, atol=2e-3)
        np.testing.assert_allclose(var, var_ref, rtol=0, atol=2e-4 * sf2)
    # The mean stays within the data's range plus a few prior standard deviations.
    assert mean.min() >= ys.min() - 3 * np.sqrt(sf2) and mean.max() <= ys.max() + 3 * np.sqrt(sf2)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_one_input_repeated_ten_thousand_times(dtype):
    """The extreme duplicate: one x, 10^4 noisy observations. The posterior is that of a scalar
    Gaussian: mean (sum y)/(n + sigma_n^2/sigma_f^2),
    variance sigma_n^2 sigma_f^2/(n sigma_f^2 + sigma_n^2)."""
    n, sf2, sn2 = 10_000, 5.0, 1e-3
    rng = np.random.default_rng(3)
    x = np.array([0.3, -0.2, 1.0, 2.0])
    ys = 1.7 + np.sqrt(sn2) * rng.normal(size=n)
    hyper = _hyper(dtype, LS, sf2, sn2)
    state, info = _update_batch_jit(hyper)(sparse_gp.init(5, 4, dtype), jnp.array(np.tile(x, (n, 1)), dtype),
                                           jnp.array(ys, dtype), jnp.zeros(n, jnp.int32))
    assert int(np.sum(np.asarray(info.added))) == 1
    mean, var = _predict(state, jnp.array(x[None], dtype), hyper)
    yq = np.asarray(jnp.array(ys, dtype), np.float64)
    exact_mean = yq.sum() / (n + sn2 / sf2)
    exact_var = sn2 * sf2 / (n * sf2 + sn2)
    rtol = 1e-9 if dtype == jnp.float64 else 2e-3
    assert abs(mean[0] - exact_mean) <= rtol * abs(exact_mean)
    assert abs(var[0] - exact_var) <= rtol * exact_var * (1 if dtype == jnp.float64 else 50)


# Measured over 100 random streams of the generator below (relative to the data scale and to
# sigma_f^2): float64 mean error median 8e-12, max 7.7e-6, variance max 3.7e-8; float32 mean
# median 6e-6, max 4e-4, variance max 2.8e-5. The largest errors come with sigma_f^2/sigma_n^2 ~ 1e6
# and nearly collinear basis vectors. A diverged state is off by O(1) or more.
REPLAY_TOL = {jnp.float64: (1e-4, 1e-6), jnp.float32: (1e-2, 1e-3)}  # (mean, variance)


@jax.jit
def _update_batch_traced(state, xs, ys, ts, hyper, age_penalty):
    """`update_batch` with the hyperparameters and the age penalty as arguments: one compiled
    program per budget and dtype, whatever the example draws."""
    return sparse_gp.update_batch(state, xs, ys, hyper, ts, with_info=True, novelty_tol=0.0,
                                  age_penalty=age_penalty, age_scale=0.5)


@pytest.mark.slow
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    log_ratio=st.floats(1.0, 6.0),
    duplicate_share=st.floats(0.0, 0.9),
    capacity=st.sampled_from([3, 12]),  # a tiny and a roomy budget: each is a compile
    age_penalty=st.sampled_from([0.0, 0.5, 50.0]),
)
def test_state_is_never_finite_but_wrong(seed, log_ratio, duplicate_share, capacity, age_penalty):
    """Property: on any stream (clusters, repeats, near-duplicates, sigma_f^2/sigma_n^2 from 10 to
    1e6, any budget and age penalty), in float64 and float32, the state after every prefix is
    finite with variances >= 0 and its posterior below its prior, and at the end it agrees with
    Csato-Opper's recursion replayed in 80-bit arithmetic along the same decisions."""
    rng = np.random.default_rng(seed)
    n = 240
    centres = rng.normal(size=(4, 4)) * 1.5
    spread = rng.choice([1e-7, 1e-3, 0.3], n)[:, None]
    xs = centres[rng.integers(0, 4, n)] + rng.normal(size=(n, 4)) * spread
    dup = rng.random(n) < duplicate_share
    src = np.minimum(rng.integers(0, n, n), np.arange(n))
    xs[dup] = xs[src[dup]]
    sf2 = float(np.exp(rng.normal(0, 1)))
    sn2 = sf2 * 10.0 ** (-log_ratio)
    ys = 3 * np.sin(xs @ rng.normal(size=4)) + np.sqrt(sn2) * rng.normal(size=n)
    ts = np.arange(n) // 30
    kw = dict(novelty_tol=0.0, age_penalty=age_penalty, age_scale=0.5)
    for dtype in (jnp.float64, jnp.float32):
        hyper = _hyper(dtype, LS, sf2, sn2)
        state, infos = sparse_gp.init(capacity, 4, dtype), []
        for lo in range(0, n, 80):  # check after every prefix of 80
            sl = slice(lo, lo + 80)
            state, info = _update_batch_traced(state, jnp.array(xs[sl], dtype), jnp.array(ys[sl], dtype),
                                               jnp.array(ts[sl]), hyper, jnp.asarray(age_penalty, dtype))
            infos.append(info)
            health = _check(state, hyper, jnp.array(xs[sl], dtype), jnp.array(ys[sl], dtype))
            assert bool(health.finite) and bool(health.posterior_below_prior), health
            mean, var = _predict(state, jnp.array(xs[::7], dtype), hyper)
            assert np.all(np.isfinite(mean)) and var.min() >= 0
        info = jax.tree.map(lambda *a: np.concatenate(a), *infos)
        xq = np.asarray(jnp.array(xs, dtype), np.float64)
        yq = np.asarray(jnp.array(ys, dtype), np.float64)
        ref = _replay_in_longdouble(xq, yq, ts, info, capacity, hyper, 0.0, **kw)
        mean, var = _predict(state, jnp.array(xq[::7], dtype), hyper)
        ref_pred = np.array([ref.predict(x) for x in xq[::7]]).astype(np.float64)
        mean_tol, var_tol = REPLAY_TOL[dtype]
        assert np.max(np.abs(mean - ref_pred[:, 0])) <= mean_tol * (np.max(np.abs(ys)) + np.sqrt(sf2))
        assert np.max(np.abs(var - ref_pred[:, 1])) <= var_tol * sf2


def test_health_check_catches_finite_but_wrong_states():
    xs, ys = _data(60, 12)
    hyper = _hyper()
    state = sparse_gp.update_batch(sparse_gp.init(20, 4), jnp.array(xs), jnp.array(ys), hyper, 0)
    assert bool(_check(state, hyper, jnp.array(xs), jnp.array(ys)).ok)
    diverged = state._replace(alpha=state.alpha * 1e6)  # finite, mean far off (the 1e179 failure)
    h = _check(diverged, hyper, jnp.array(xs), jnp.array(ys))
    assert bool(h.finite) and not bool(h.mean_in_range) and not bool(h.ok)
    inflated = state._replace(alpha_cov_root=state.alpha_cov_root * 3.0)  # posterior above prior
    assert not bool(_check(inflated, hyper, jnp.array(xs), jnp.array(ys)).ok)
    nan = state._replace(gram_inv_root=state.gram_inv_root.at[0, 0].set(jnp.nan))
    assert not bool(_check(nan, hyper, jnp.array(xs), jnp.array(ys)).ok)


def test_novelty_threshold_follows_dtype_and_noise():
    h = _hyper(jnp.float64, LS, 2.0, 0.5)
    assert float(sparse_gp.novelty_threshold(h, jnp.float64, 0.0)) == pytest.approx(0.01 * 0.5)
    assert float(sparse_gp.novelty_threshold(h, jnp.float64, 0.1)) == pytest.approx(0.2)
    h32 = _hyper(jnp.float32, LS, 2.0, 1e-6)
    assert float(sparse_gp.novelty_threshold(h32, jnp.float32, 0.0)) == pytest.approx(2e-3)
    h64 = _hyper(jnp.float64, LS, 2.0, 1e-6)
    assert float(sparse_gp.novelty_threshold(h64, jnp.float64, 0.0)) == pytest.approx(2e-6)
    assert sparse_gp.resolution(jnp.float32) == gp_reference.resolution(np.float32)
    assert sparse_gp.resolution(jnp.float64) == gp_reference.resolution(np.float64)


def test_age_penalty_exchanges_the_set():
    """lambda = 0 keeps informative old BVs; a large lambda exchanges the set every policy update."""
    capacity, per_phase, phases = 15, 40, 6
    rng = np.random.default_rng(5)
    xs = rng.normal(size=(per_phase * phases, 4))
    ys = np.sin(xs.sum(1))
    ts = np.repeat(np.arange(phases), per_phase)

    def share_latest(**kw):
        state, _ = _update_batch_jit(novelty_tol=1e-4, **kw)(
            sparse_gp.init(capacity, 4), jnp.array(xs), jnp.array(ys), jnp.array(ts)
        )
        m = np.asarray(state.mask)
        return np.mean(np.asarray(state.timestamps)[m] == phases - 1)

    base = share_latest(age_penalty=0.0)
    assert base < 0.6, base
    for age_fn, scale in (("exp", 1.0), ("logit", 1.0)):
        share = share_latest(age_penalty=1e3, age_scale=scale, age_fn=age_fn)
        assert share >= 0.99, (age_fn, share)
        mid = share_latest(age_penalty=1e-3, age_scale=scale, age_fn=age_fn)
        assert base - 1e-9 <= mid <= share + 1e-9


def test_age_function_guards():
    t = jnp.array([0, 3, 1000, 7, 0], jnp.int32)
    mask = jnp.array([True, True, True, True, False])
    g = sparse_gp.age_function(t, mask, jnp.asarray(1.0), "exp")
    assert np.all(np.isfinite(g)) and g[0] == 1.0 and g[1] == pytest.approx(np.exp(3.0))
    assert g[2] >= g[3] >= g[1] >= g[0] and g[4] == 0.0
    g32 = sparse_gp.age_function(t, mask, jnp.asarray(1.0, jnp.float32), "exp")
    assert g32.dtype == jnp.float32 and np.all(np.isfinite(g32 * 1e3))
    gl = sparse_gp.age_function(t, mask, jnp.asarray(2.0), "logit", 1e-3)
    tau = np.clip(np.array([0, 3, 1000, 7]) / 1000, 1e-3, 1 - 1e-3)
    np.testing.assert_allclose(gl[:4], 2.0 * np.log(tau / (1 - tau)), rtol=1e-12)
    zero = sparse_gp.age_function(jnp.zeros(4, jnp.int32), mask[:4], jnp.asarray(1.0), "logit")
    assert np.all(np.isfinite(zero)) and np.ptp(np.asarray(zero)) == 0.0
    with pytest.raises(ValueError):
        sparse_gp.age_function(t, mask, 1.0, "linear")


# --- transforms, compilation, numerics ------------------------------------------------------------


@pytest.mark.slow
def test_jit_vmap_and_plain_agree_and_no_recompile():
    capacity, n = 10, 30
    streams = [_data(n, s) for s in range(3)]
    xs = np.stack([s[0] for s in streams])
    ys = np.stack([s[1] for s in streams])
    kw = dict(novelty_tol=1e-3, age_penalty=0.5, age_fn="logit")
    plain = [
        sparse_gp.update_batch(sparse_gp.init(capacity, 4), xs[i], ys[i], _hyper(), 2, **kw)
        for i in range(3)
    ]
    batched = jax.jit(
        jax.vmap(
            lambda x, y: sparse_gp.update_batch(sparse_gp.init(capacity, 4), x, y, _hyper(), 2, **kw)
        )
    )(jnp.array(xs), jnp.array(ys))
    for i in range(3):
        for a, b in zip(jax.tree.leaves(plain[i]), jax.tree.leaves(batched), strict=True):
            np.testing.assert_allclose(np.asarray(b[i], float), np.asarray(a, float), rtol=1e-10,
                                       atol=1e-12)

    traces = []

    def step(state, x, y, t, lam):
        traces.append(1)
        return sparse_gp.update(state, x, y, _hyper(), t, age_penalty=lam, age_fn="exp")

    jitted = jax.jit(step)
    state = sparse_gp.init(capacity, 4)
    for i in range(4):  # new values of every traced argument, same shapes
        state = jitted(state, jnp.array(xs[0, i]), jnp.array(ys[0, i]), jnp.int32(i), 0.1 * i)
    jax.block_until_ready(state)
    assert len(traces) == 1
    assert jitted._cache_size() == 1


@pytest.mark.slow
def test_sweep_over_age_penalty_is_one_vmap():
    xs, ys = _data(60, 6)
    lams = jnp.array([0.0, 1.0, 100.0])
    run = jax.jit(
        jax.vmap(
            lambda lam: sparse_gp.update_batch(
                sparse_gp.init(8, 4), jnp.array(xs), jnp.array(ys), _hyper(),
                jnp.arange(60) // 10, age_penalty=lam,
            )
        )
    )
    out = run(lams)
    assert out.alpha.shape == (3, 9)
    assert np.all(np.asarray(jax.vmap(sparse_gp.num_basis_vectors)(out)) == 8)
    single = sparse_gp.update_batch(
        sparse_gp.init(8, 4), jnp.array(xs), jnp.array(ys), _hyper(), jnp.arange(60) // 10,
        age_penalty=100.0,
    )
    np.testing.assert_allclose(out.alpha[2], single.alpha, rtol=1e-10, atol=1e-12)


@pytest.mark.slow
def test_non_finite_pairs_are_skipped():
    xs, ys = _data(12, 7)  # as many pairs as the batch below: one compiled program for both
    # compiled (op by op, every operation of the loops would be compiled on its own)
    update_batch = jax.jit(sparse_gp.update_batch)
    update = jax.jit(sparse_gp.update)
    state = update_batch(sparse_gp.init(10, 4), jnp.array(xs), jnp.array(ys), _hyper(), 0)
    bad_inputs = [
        (np.array([np.nan, 0.0, 0.0, 0.0]), 1.0),
        (np.array([0.0, np.inf, 0.0, 0.0]), 1.0),
        (np.zeros(4), np.nan),
        (np.zeros(4), -np.inf),
    ]
    for x, y in bad_inputs:
        out = update(state, jnp.array(x), jnp.array(y), _hyper(), 3)
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(state), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # In a batch: the same as the batch without the bad pairs, and `valid=False` pads likewise.
    xs2, ys2 = _data(12, 8)
    xs_bad, ys_bad = xs2.copy(), ys2.copy()
    xs_bad[3, 1] = np.nan
    ys_bad[7] = np.inf
    keep = np.ones(12, bool)
    keep[[3, 7]] = False
    a = update_batch(state, jnp.array(xs_bad), jnp.array(ys_bad), _hyper(), 1)
    b = update_batch(state, jnp.array(xs2[keep]), jnp.array(ys2[keep]), _hyper(), 1)
    c = update_batch(
        state, jnp.array(xs2), jnp.array(ys2), _hyper(), 1, valid=jnp.array(keep)
    )
    for la, lb, lc in zip(jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves(c), strict=True):
        np.testing.assert_array_equal(np.asarray(la), np.asarray(lb))
        np.testing.assert_array_equal(np.asarray(lc), np.asarray(lb))
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in (a.alpha, a.alpha_cov_root))
    # The reference skips them too.
    ref = gp_reference.OnlineGP(10, 4, LS, SF2, SN2)
    assert ref.update(np.array([np.nan, 0, 0, 0]), 1.0, 0) == "skipped" and ref.size == 0


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_buffers_keep_their_dtype_and_free_slots_stay_zero(dtype):
    xs, ys = _pendulum_stream(3000, 4)
    hyper = _hyper(dtype, PEND_LS, PEND_SF2, PEND_SN2)
    state, _ = _update_batch_jit(hyper, age_penalty=10.0, age_scale=0.2)(
        sparse_gp.init(30, 4, dtype), jnp.array(xs, dtype), jnp.array(ys, dtype),
        jnp.arange(3000) // 150)
    for leaf in (state.alpha, state.gram_inv_root, state.alpha_cov_root, state.basis_vectors):
        assert leaf.dtype == dtype and np.all(np.isfinite(np.asarray(leaf)))
    assert int(sparse_gp.num_basis_vectors(state)) == 30
    free = ~np.asarray(state.mask)
    for X in (np.asarray(state.gram_inv_root), np.asarray(state.alpha_cov_root)):
        assert np.all(X[free] == 0) and np.all(X[:, free] == 0)
    assert np.all(np.asarray(state.alpha)[free] == 0)


# --- the two loops of update_batch --------------------------------------------------------------


def _adversarial_stream(n, seed, dtype):
    """Pendulum-like inputs with runs of duplicates, near-duplicates, NaN/inf pairs and padding."""
    rng = np.random.default_rng(seed)
    xs, ys = _data(n, seed)
    dup = rng.random(n) < 0.3
    xs[1:][dup[1:]] = xs[:-1][dup[1:]] + 1e-9 * rng.normal(size=(int(dup[1:].sum()), 4))
    xs[rng.random(n) < 0.02] = np.nan
    ys[rng.random(n) < 0.02] = np.inf
    valid = rng.random(n) > 0.05
    return jnp.asarray(xs, dtype), jnp.asarray(ys, dtype), jnp.asarray(valid)


# each case compiles four loops: the two dtypes and the two age functions, each once
@pytest.mark.slow
@pytest.mark.parametrize("age_fn, capacity, dtype", [("exp", 12, jnp.float64),
                                                     ("logit", 30, jnp.float32)])
def test_segmented_loop_equals_scanned_updates_bit_for_bit(age_fn, capacity, dtype):
    """One GP takes in a batch through while-loop segments (no per-pair lax.cond), or through the
    scanned loop (`update_with_info`'s steps under lax.scan), both on buffers padded to a multiple
    of 8 slots: the same state and info, bit for bit, on a stream that fills the budget, exchanges
    BVs, and holds duplicates, non-finite and padded pairs. `update_with_info` pair by pair (no
    padding) and a vmapped batch: the same decisions, the numbers equal to rounding."""
    n = 600
    xs, ys, valid = _adversarial_stream(n, 3, dtype)
    ts = jnp.arange(n) // 40
    kw = dict(novelty_tol=1e-4, age_penalty=5.0, age_scale=0.3, age_fn=age_fn)
    hyper = _hyper(dtype)
    state0 = sparse_gp.init(capacity, 4, dtype, prior_mean=0.2)
    seg = jax.jit(lambda s, x, y: sparse_gp.update_batch(
        s, x, y, hyper, ts, valid=valid, with_info=True, **kw))(state0, xs, ys)

    def scanned(s, x, y):  # update_with_info pair by pair: the reference loop
        def body(c, inp):
            return sparse_gp.update_with_info(c, inp[0], inp[1], hyper, inp[2], valid=inp[3], **kw)
        return jax.lax.scan(body, s, (x, y, ts, valid))

    ref = jax.jit(scanned)(state0, xs, ys)
    scan = jax.jit(lambda s, x, y: sparse_gp.update_batch(
        s, x, y, hyper, ts, valid=valid, with_info=True, loop="scan", **kw))(state0, xs, ys)
    batched = jax.jit(jax.vmap(lambda s, x, y: sparse_gp.update_batch(
        s, x, y, hyper, ts, valid=valid, with_info=True, **kw)))(
        *jax.tree.map(lambda a: jnp.stack([a, a]), (state0, xs, ys)))
    info = ref[1]
    assert int(info.added.sum()) > capacity and int((info.deleted_slot >= 0).sum()) > 0
    assert sparse_gp.padded_slots(capacity + 1) > capacity + 1  # the loops do pad here
    for got, want in zip(jax.tree.leaves(seg), jax.tree.leaves(scan)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    # Pair by pair, and the vmapped loop: the same decisions (which pairs join, which slots they
    # take and free), and float leaves equal to rounding, normwise. Padded and unpadded buffers,
    # and batched products, round differently (how depends on the CPU's vector width), and after
    # 600 updates an entry 1e3 times smaller than the largest can differ in its second digit in
    # float32, so an elementwise relative bound is no bound a backward-stable update promises. The
    # forward error of a backward-stable recursion is cond(K_B) times its backward error, so the
    # bound is sqrt(m) cond(K_B) eps of the leaf's largest entry, m the BVs kept, cond(K_B) their
    # Gram matrix's condition number (113 and 1.3e3 here). The differences found stay below
    # cond(K_B) eps, and how large they are depends on the CPU's vector width, so a fixed
    # multiple of eps is no bound.
    cond, kept = _gram_condition(ref[0], hyper)
    tol = np.sqrt(kept) * cond * float(jnp.finfo(dtype).eps)
    for got, want in [(a, b) for other in (jax.tree.map(lambda a: jnp.stack([a, a]), seg), batched)
                      for a, b in zip(jax.tree.leaves(other), jax.tree.leaves(ref))]:
        got, want = np.asarray(got)[1], np.asarray(want)
        if not np.issubdtype(want.dtype, np.floating) or want.shape == (capacity + 1, 4):
            np.testing.assert_array_equal(got, want)  # decisions, slots, stamps and the BVs
            continue
        got, want = got.astype(float), want.astype(float)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
        fin = np.isfinite(want)
        assert np.max(np.abs(got - want)[fin], initial=0.0) <= tol * np.max(np.abs(want[fin]),
                                                                            initial=0.0)


def test_update_batch_refuses_unknown_keywords():
    with pytest.raises(TypeError, match="novelty"):
        sparse_gp.update_batch(sparse_gp.init(3, 4), jnp.zeros((2, 4)), jnp.zeros(2), _hyper(), 0,
                               novelty=1e-3)
    with pytest.raises(ValueError, match="age_fn"):
        sparse_gp.update_batch(sparse_gp.init(3, 4), jnp.zeros((2, 4)), jnp.zeros(2), _hyper(), 0,
                               age_fn="linear")
