"""The swing-up study's curve arithmetic: smoothing and steps to a success level."""

import importlib.util
import os

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
spec = importlib.util.spec_from_file_location(
    "swingup_study", os.path.join(ROOT, "experiments", "swingup_study.py"))
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def test_smoothed_is_a_trailing_mean_over_five_updates():
    x = np.array([[0, 0, 0, 0, 1, 1, 1, 1, 1, 1.0]])
    got = study.smoothed(x, "gp_pg")
    want = [np.mean(x[0, max(0, i - 4): i + 1]) for i in range(10)]
    np.testing.assert_allclose(got[0], want)
    np.testing.assert_array_equal(study.smoothed(x, "ppo"), x)  # brax evaluations: as they are


def test_steps_to_level():
    steps = np.array([10, 20, 30, 40])
    succ = np.array([[0.0, 0.5, 1.0, 1.0], [0.0, 0.0, 0.0, 0.2], [0.9, 0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(study.steps_to(steps, succ, 0.5), [20, np.inf, 10])
    np.testing.assert_array_equal(study.steps_to(steps, succ, 0.9), [30, np.inf, 10])
    med, lo, hi = study.median_ci(np.array([1.0, 2.0, 3.0, np.inf, np.inf]))
    assert med == 3.0 and lo <= med <= hi


def test_every_method_and_baseline_has_the_same_tuning_budget():
    counts = {m: sum(len(v) for _, v in g) for m, g in {**study.GRIDS, **study.BASELINE_GRIDS}.items()}
    assert set(counts.values()) == {study.CONFIGS_PER_METHOD}, counts
