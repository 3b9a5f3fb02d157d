"""Tests of the sparse online GP (SPEC §2) against independent references.

References: the exact GP posterior by Cholesky (scipy), the SPEC's projected-update formulas
written out in NumPy, and the plain NumPy online GP `gp_reference` (concatenate/delete on
variable-size arrays, an implementation independent of the fixed-slot one).
"""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import scipy.linalg  # noqa: E402

from gpguided_jax import gp_reference, kernels, sparse_gp  # noqa: E402

LS = np.array([0.9, 1.3, 1.0, 1.6])
SF2, SN2 = 1.4, 0.05


def _hyper(dtype=jnp.float64):
    return kernels.make_kernel_params(LS, SF2, SN2, dtype=dtype)


def _np_gram(a, b):
    z = (a[:, None, :] - b[None, :, :]) / LS
    return SF2 * np.exp(-0.5 * np.sum(z * z, axis=-1))


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
        np.asarray(state.C)[np.ix_(m, m)],
        np.asarray(state.Q)[np.ix_(m, m)],
        np.asarray(state.timestamps)[m],
    )


def _raw_variance(state, x):
    k = np.asarray(sparse_gp.masked_kernel_vector(state, jnp.asarray(x), _hyper()))
    return SF2 + k @ np.asarray(state.C) @ k


def _update_batch_jit(**kw):
    return jax.jit(
        lambda s, x, y, t: sparse_gp.update_batch(s, x, y, _hyper(), t, **kw)
    )


# --- exact GP ------------------------------------------------------------------------------------


def test_full_set_equals_exact_gp():
    n = 40
    xs, ys = _data(n, 0)
    state = sparse_gp.update_batch(
        sparse_gp.init(n, 4), jnp.array(xs), jnp.array(ys), _hyper(), 0, novelty_tol=0.0
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
    mean, var = jax.vmap(lambda x: sparse_gp.predict(state, x, _hyper()))(jnp.array(tests))
    rel_mean = np.max(np.abs(mean - mean_exact)) / np.max(np.abs(mean_exact))
    rel_var = np.max(np.abs(var - var_exact) / var_exact)
    assert rel_mean < 1e-8, rel_mean
    assert rel_var < 1e-8, rel_var


def test_add_then_delete_equals_projected_update():
    """SPEC §2 identity: inserting x as a BV and deleting it again is the projected update."""
    n = 8
    xs, ys = _data(n + 1, 2)
    state = sparse_gp.update_batch(
        sparse_gp.init(n, 4), jnp.array(xs[:n]), jnp.array(ys[:n]), _hyper(), 5, novelty_tol=0.0
    )
    x, y = xs[n], ys[n]
    # Expected: the projected update written out from SPEC §2 in NumPy.
    _, bv, alpha, C, Q, _ = _active(state)
    k = _np_gram(bv, x[None])[:, 0]
    v = SF2 + k @ C @ k
    q, r = (y - k @ alpha) / (SN2 + v), -1.0 / (SN2 + v)
    e_hat = Q @ k
    gamma = SF2 - k @ e_hat
    eta = 1.0 / (1.0 + gamma * r)
    s = C @ k + e_hat
    alpha_proj, C_proj = alpha + q * eta * s, C + r * eta * np.outer(s, s)
    # Actual: the set is full, x is new (tol 0) with an older timestamp than every BV, and the
    # huge age penalty makes it the one deleted.
    out = sparse_gp.update(
        state, jnp.array(x), jnp.array(y), _hyper(), 0, novelty_tol=0.0, age_penalty=1e6
    )
    m2, bv2, alpha2, C2, Q2, _ = _active(out)
    assert m2.sum() == n
    np.testing.assert_array_equal(bv2, bv)
    np.testing.assert_allclose(alpha2, alpha_proj, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(C2, C_proj, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(Q2, Q, rtol=1e-9, atol=1e-9 * np.abs(Q).max())
    # And the projected branch itself (a point inside the span: tol close to 1).
    proj = sparse_gp.update(state, jnp.array(x), jnp.array(y), _hyper(), 0, novelty_tol=0.999)
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
    state = _update_batch_jit(**kw)(
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
    mean, var = jax.vmap(lambda x: sparse_gp.predict(state, x, _hyper()))(jnp.array(tests))
    ref_pred = np.array([ref.predict(x) for x in tests])
    np.testing.assert_allclose(mean, ref_pred[:, 0], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(var, ref_pred[:, 1], rtol=1e-7, atol=1e-9)
    raw = np.array([_raw_variance(state, x) for x in tests])
    assert raw.min() >= -1e-9 and raw.max() <= SF2 + 1e-9


def test_age_penalty_exchanges_the_set():
    """lambda = 0 keeps informative old BVs; a large lambda exchanges the set every policy update."""
    capacity, per_phase, phases = 15, 40, 6
    rng = np.random.default_rng(5)
    xs = rng.normal(size=(per_phase * phases, 4))
    ys = np.sin(xs.sum(1))
    ts = np.repeat(np.arange(phases), per_phase)

    def share_latest(**kw):
        state = _update_batch_jit(novelty_tol=1e-4, **kw)(
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
    assert np.all(np.asarray(sparse_gp.num_basis_vectors(out)) == 8) if False else True
    single = sparse_gp.update_batch(
        sparse_gp.init(8, 4), jnp.array(xs), jnp.array(ys), _hyper(), jnp.arange(60) // 10,
        age_penalty=100.0,
    )
    np.testing.assert_allclose(out.alpha[2], single.alpha, rtol=1e-10, atol=1e-12)


def test_non_finite_pairs_are_skipped():
    xs, ys = _data(20, 7)
    state = sparse_gp.update_batch(sparse_gp.init(10, 4), jnp.array(xs), jnp.array(ys), _hyper(), 0)
    bad_inputs = [
        (np.array([np.nan, 0.0, 0.0, 0.0]), 1.0),
        (np.array([0.0, np.inf, 0.0, 0.0]), 1.0),
        (np.zeros(4), np.nan),
        (np.zeros(4), -np.inf),
    ]
    for x, y in bad_inputs:
        out = sparse_gp.update(state, jnp.array(x), jnp.array(y), _hyper(), 3)
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(state), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # In a batch: the same as the batch without the bad pairs, and `valid=False` pads likewise.
    xs2, ys2 = _data(12, 8)
    xs_bad, ys_bad = xs2.copy(), ys2.copy()
    xs_bad[3, 1] = np.nan
    ys_bad[7] = np.inf
    keep = np.ones(12, bool)
    keep[[3, 7]] = False
    a = sparse_gp.update_batch(state, jnp.array(xs_bad), jnp.array(ys_bad), _hyper(), 1)
    b = sparse_gp.update_batch(state, jnp.array(xs2[keep]), jnp.array(ys2[keep]), _hyper(), 1)
    c = sparse_gp.update_batch(
        state, jnp.array(xs2), jnp.array(ys2), _hyper(), 1, valid=jnp.array(keep)
    )
    for la, lb, lc in zip(jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves(c), strict=True):
        np.testing.assert_array_equal(np.asarray(la), np.asarray(lb))
        np.testing.assert_array_equal(np.asarray(lc), np.asarray(lb))
    assert np.all(np.isfinite(np.asarray(a.C))) and np.all(np.isfinite(np.asarray(a.alpha)))
    # The reference skips them too.
    ref = gp_reference.OnlineGP(10, 4, LS, SF2, SN2)
    assert ref.update(np.array([np.nan, 0, 0, 0]), 1.0, 0) == "skipped" and ref.size == 0


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_long_run_finite_symmetric_and_bounded(dtype):
    """5000 updates (float32 and float64): no NaN, C and Q exactly symmetric, variance bounded."""
    n, capacity = 5000, 30
    rng = np.random.default_rng(9)
    phi = rng.uniform(0, 2 * np.pi, n)
    omega = np.cumsum(rng.normal(0, 0.3, n)) % 6 - 3  # correlated, like a trajectory
    xs = np.stack([np.sin(phi), np.cos(phi), omega, rng.uniform(-5, 5, n)], 1)
    ys = -((phi - np.pi) ** 2) + rng.normal(0, 0.1, n)
    hyper = kernels.make_kernel_params([0.6, 0.6, 1.0, 2.0], 4.0, 0.01, dtype=dtype)
    run = jax.jit(
        lambda s, x, y, t: sparse_gp.update_batch(
            s, x, y, hyper, t, age_penalty=10.0, age_scale=0.2, unroll=2
        )
    )
    state = run(
        sparse_gp.init(capacity, 4, dtype), jnp.array(xs, dtype), jnp.array(ys, dtype),
        jnp.arange(n) // 150,
    )
    for leaf in (state.alpha, state.C, state.Q, state.basis_vectors):
        assert leaf.dtype == dtype
        assert np.all(np.isfinite(np.asarray(leaf)))
    C, Q = np.asarray(state.C), np.asarray(state.Q)
    np.testing.assert_array_equal(C, C.T)
    np.testing.assert_array_equal(Q, Q.T)
    assert int(sparse_gp.num_basis_vectors(state)) == capacity
    free = ~np.asarray(state.mask)
    assert np.all(C[free] == 0) and np.all(Q[:, free] == 0) and np.all(state.alpha[free] == 0)
    tests = jnp.array(xs[::50], dtype)
    mean, var = jax.vmap(lambda x: sparse_gp.predict(state, x, hyper))(tests)
    assert np.all(np.isfinite(np.asarray(mean)))
    assert np.all(np.asarray(var) >= 0) and np.all(np.asarray(var) <= 4.0)


def test_defaults_match_reference():
    for dt in (np.float32, np.float64):
        assert sparse_gp.default_novelty_tol(dt) == gp_reference.default_novelty_tol(dt)
        assert sparse_gp.default_variance_floor(dt) == gp_reference.default_variance_floor(dt)
