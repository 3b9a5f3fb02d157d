"""The swing-up study (experiments/swingup_study.py): its grids, its settings over the preset's
own, its curves on the environment-steps axis and its smoothing. No training runs."""

import importlib.util
import json
import os
import types

import numpy as np

from gpguided_jax import baselines, methods
from gpguided_jax import config as config_lib
from gpguided_jax import study as study_lib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
spec = importlib.util.spec_from_file_location(
    "swingup_study", os.path.join(ROOT, "experiments", "swingup_study.py"))
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)
RESULTS = os.path.join(ROOT, "docs", "results", "swingup")


def _tuning():
    with open(os.path.join(RESULTS, "tuning.json")) as f:
        return json.load(f)


def test_smoothed_is_a_trailing_mean_over_five_updates():
    x = np.array([[0, 0, 0, 0, 1, 1, 1, 1, 1, 1.0]])
    got = study.smoothed(x, "gp_pg")
    want = [np.mean(x[0, max(0, i - 4): i + 1]) for i in range(10)]
    np.testing.assert_allclose(got[0], want)
    np.testing.assert_array_equal(study.smoothed(x, "ppo"), x)  # brax evaluations: as they are


def test_every_method_and_baseline_has_the_same_tuning_budget():
    counts = {m: sum(len(v) for _, v in g) for m, g in {**study.GRIDS, **study.BASELINE_GRIDS}.items()}
    assert set(counts.values()) == {study.CONFIGS_PER_METHOD}, counts


def test_the_study_settings_apply_over_the_presets_own_and_leave_the_preset_alone(monkeypatch):
    """Each method's config is the preset without its tuned settings (those of the exploration
    study) with this study's choice (tuning.json) over it; the config module is not changed."""
    tuning = _tuning()
    before = json.dumps(config_lib.METHOD_PRESETS, sort_keys=True)
    got = {m: study.study_config(tuning, m, dtype="float32").to_json_dict() for m in study.METHODS}
    assert json.dumps(config_lib.METHOD_PRESETS, sort_keys=True) == before
    for m in study.METHODS:  # the preset without any method's tuned settings
        monkeypatch.delitem(methods.get(m).presets, "swingup", raising=False)
    for m in study.METHODS:
        chosen = tuning["methods"][m]["chosen"]
        assert got[m] == config_lib.preset("swingup", method=m, dtype="float32",
                                           **chosen).to_json_dict(), m


def test_the_tuning_searches_from_the_presets_own_settings(monkeypatch):
    """A method's stages are sweeps over the parameter of each stage, over the preset's own
    settings (not the exploration study's tuned ones) and the best so far."""
    calls = []

    def fake_sweep(field, values, *, method, preset, seeds, overrides, progress):
        calls.append((field, list(values), overrides))
        shape = (len(values), len(seeds), 10)
        success = np.broadcast_to(np.asarray(values, float)[:, None, None], shape)
        return types.SimpleNamespace(records={"eval_success_rate": success / 10,
                                              "eval_reward": np.zeros(shape)})

    monkeypatch.setattr(study_lib.sweep, "run_sweep", fake_sweep)
    res = study.tune_method("reinforce", (100, 101), "float32")
    assert [c[0] for c in calls] == ["learning_rate", "init_log_std", "learning_rate"]
    own = study_lib.preset_own("swingup", "reinforce")
    assert {k: v for k, v in calls[0][2].items() if k != "dtype"} == {
        k: v for k, v in own.items() if k != "learning_rate"}
    assert calls[1][2]["learning_rate"] == 1.0  # the largest scores best here
    assert res["chosen"] == {"learning_rate": 3.0, "init_log_std": np.log(3.0)}
    assert len(res["tried"]) == study.CONFIGS_PER_METHOD


def test_the_held_out_curves_lie_on_the_environment_steps_axis():
    """A method's curves (evaluations of the deterministic policy before each update's step)
    start where its learning starts: at 0 steps, or after the hyperparameter fit's episodes."""
    tuning = _tuning()
    with np.load(os.path.join(RESULTS, "heldout.npz")) as f:
        curves = {k: f[k] for k in f.files}
    for m in study.METHODS:
        cfg = study.study_config(tuning, m, dtype="float32")
        steps = curves[f"{m}_steps"]
        np.testing.assert_array_equal(steps, study_lib.env_steps(cfg))
        fit = cfg.hyperfit_episodes * cfg.episode_length if cfg.uses_gp else 0
        assert steps[0] == fit and curves[f"{m}_success"].shape[1] == len(steps)
    for name in baselines.NAMES:
        assert curves[f"{name}_steps"][0] == 0  # brax evaluates the initial policy first
