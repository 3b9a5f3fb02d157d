"""Summary statistics (gpguided_jax.stats) against SciPy, the independent reference."""

import math

import numpy as np
import pytest
from scipy import stats as sp_stats

from gpguided_jax import stats


@pytest.mark.parametrize("shape,axis", [((10,), 0), ((7,), 0), ((100,), 0), ((50, 13), 1),
                                        ((13, 50), 0), ((4, 3), 1)])
@pytest.mark.parametrize("cut", [0.0, 0.1, 0.25, 0.49])
def test_trim_mean_is_scipys_bit_for_bit(shape, axis, cut):
    rng = np.random.default_rng(sum(shape) + int(100 * cut))
    a = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4, size=shape)
    a.flat[::3] = a.flat[0]  # ties
    np.testing.assert_array_equal(stats.trim_mean(a, cut, axis=axis),
                                  sp_stats.trim_mean(a, cut, axis=axis))


@pytest.mark.parametrize("df", [1, 2, 9, 99, 1000])
@pytest.mark.parametrize("q", [0.5, 0.9, 0.975, 0.995])
def test_t_quantile_is_scipys_bit_for_bit(q, df):
    assert stats.t_quantile(q, df) == sp_stats.t.ppf(q, df)


def test_t_interval_is_scipys_bit_for_bit():
    x = np.array([[1.0, 2.0], [2.0, 4.0], [3.0, 9.0]])
    mean, half = stats.t_interval(x)
    np.testing.assert_allclose(mean, [2.0, 5.0])
    np.testing.assert_array_equal(half, sp_stats.t.ppf(0.975, 2) * x.std(0, ddof=1) / math.sqrt(3))
    _, half90 = stats.t_interval(x[:, 1], confidence=0.9)
    assert half90 == sp_stats.t.ppf(0.95, 2) * x[:, 1].std(ddof=1) / math.sqrt(3)
    assert np.isnan(stats.t_interval(np.array([1.0]))[1])


def test_trim_mean_refuses_a_proportion_above_one_half():
    with pytest.raises(ValueError, match="too big"):
        stats.trim_mean(np.arange(4.0), 0.8)


def test_iqm_by_hand():
    assert stats.iqm([1, 2, 3, 5]) == 2.5
    assert stats.iqm([100.0, 1, 2, 3, 4, 5, 6, -100]) == pytest.approx(3.5)  # 2 cut each end


def test_probability_of_improvement_is_mann_whitney_u_over_nm():
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 5, 12).astype(float), rng.integers(0, 5, 9).astype(float)  # with ties
    u = sp_stats.mannwhitneyu(x, y, alternative="greater").statistic
    assert stats.probability_of_improvement(x, y) == pytest.approx(u / (12 * 9), abs=1e-15)


def test_bootstrap_interval_brackets_the_iqm_and_is_reproducible():
    x = np.random.default_rng(1).normal(size=30)
    lo, hi = stats.bootstrap_ci(x, reps=2000)
    assert lo < stats.iqm(x) < hi
    assert (lo, hi) == stats.bootstrap_ci(x, reps=2000)
    lo_p, hi_p = stats.probability_of_improvement_ci(x + 1.0, x, reps=2000)
    assert 0.5 < lo_p <= hi_p <= 1.0
