"""The NumPy reference online GP against the exact GP (it is the oracle of test_sparse_gp.py)."""

import numpy as np
import scipy.linalg

from gpguided_jax import gp_reference


def test_reference_equals_exact_gp_without_budget():
    rng = np.random.default_rng(0)
    n, ls, sf2, sn2 = 30, np.array([1.0, 0.7, 1.5, 1.2]), 1.2, 0.05
    xs, ys = rng.normal(size=(n, 4)), rng.normal(size=n)
    gp = gp_reference.OnlineGP(n, 4, ls, sf2, sn2, novelty_tol=0.0)
    assert all(gp.update(xs[i], ys[i], 0) == "added" for i in range(n))
    z = (xs[:, None] - xs[None]) / ls
    A = sf2 * np.exp(-0.5 * (z * z).sum(-1)) + sn2 * np.eye(n)
    np.testing.assert_allclose(gp.alpha, scipy.linalg.solve(A, ys, assume_a="pos"), rtol=1e-8)
    np.testing.assert_allclose(gp.C, -np.linalg.inv(A), rtol=1e-8, atol=1e-10)


def test_reference_budget_and_outcomes():
    rng = np.random.default_rng(1)
    gp = gp_reference.OnlineGP(5, 2, [1.0, 1.0], 1.0, 0.1, age_penalty=1e3, age_fn="logit")
    outcomes = [gp.update(rng.normal(size=2), 0.0, i // 5) for i in range(30)]
    assert gp.size == 5 and outcomes.count("exchanged") > 0
    assert gp.update(np.array([0.1, 0.2]), 0.1, 6) in ("projected", "exchanged")
    gp.update(gp.basis_vectors[0], 0.3, 7)  # an existing BV: no new direction
    assert gp.size == 5
