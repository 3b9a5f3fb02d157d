"""The swing-up preset is feasible before any learning: the energy-pumping controller swings up
from >= 95% of 100 start states of the preset's distribution, the RBF policy class fitted to it
does too, and the success criterion means what it says."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpguided_jax import config as config_lib
from gpguided_jax import swingup
from gpguided_jax import train as train_lib


@pytest.fixture(scope="module")
def cfg():
    return config_lib.preset("swingup", dtype="float32")


def _rate(cfg, policy_fn, seed=123, n=100):
    return swingup.success_rate(
        jax.random.PRNGKey(seed), cfg.pendulum, policy_fn, cfg.episode_length, n,
        tolerance=float(cfg.success_tolerance), hold_time=cfg.success_hold_time)


def test_preset_keeps_the_paper_physics_and_cannot_lift_directly(cfg):
    p = cfg.pendulum
    assert float(p.dt) == pytest.approx(0.005)  # 200 Hz
    assert float(p.max_torque) == pytest.approx(5.0)
    # a direct lift needs the torque to beat gravity at the horizontal
    assert float(p.max_torque) < float(p.mass * p.gravity * p.length)
    assert np.allclose(np.asarray(p.start_mean), 0.0)  # hanging down


def test_constant_torque_never_succeeds(cfg):
    assert _rate(cfg, lambda k, s: jnp.asarray(5.0, s.dtype), n=20) == 0.0


def test_energy_pumping_controller_swings_up_from_95_percent_of_starts(cfg):
    rate = _rate(cfg, swingup.energy_pumping_policy(cfg.pendulum))
    assert rate >= 0.95, rate


@pytest.mark.slow
def test_fitted_rbf_controller_swings_up_as_often(cfg):
    controller = train_lib.make_controller(cfg)
    theta, mse = swingup.fit_controller(
        controller, cfg.pendulum, swingup.energy_pumping_policy(cfg.pendulum),
        jax.random.PRNGKey(7), episode_length=cfg.episode_length, num_episodes=100)
    assert np.isfinite(mse)

    def deterministic(key, s):
        del key
        return controller.apply(theta, s)

    rate = _rate(cfg, deterministic, seed=321)
    assert rate >= 0.95, (rate, mse)


def test_success_criterion():
    dt = 0.005
    up = jnp.tile(jnp.array([jnp.pi, 0.0]), (300, 1))
    assert bool(swingup.success(up, dt, tolerance=0.3, hold_time=1.0))
    # a single step outside the tolerance inside the last second breaks the hold
    broken = up.at[-50, 0].set(jnp.pi + 0.31)
    assert not bool(swingup.success(broken, dt, tolerance=0.3, hold_time=1.0))
    # ...but not before it
    early = up.at[50, 0].set(0.0)
    assert bool(swingup.success(early, dt, tolerance=0.3, hold_time=1.0))
    # upright is upright after any number of turns (phi is wrapped)
    assert bool(swingup.success(up + jnp.array([4 * jnp.pi, 0.0]), dt, tolerance=0.3, hold_time=1.0))
    with pytest.raises(ValueError, match="shorter than the hold time"):
        swingup.success(up[:100], dt, tolerance=0.3, hold_time=1.0)


def test_swingup_preset_uses_the_tuned_settings():
    """config.METHOD_PRESETS['swingup'] is what the exploration study's tuning chose (tuning seeds
    only); the white-noise study's own choices stay in its record, which its scripts apply."""
    import importlib.util
    import json
    import os

    root = os.path.dirname(os.path.dirname(__file__))
    spec = importlib.util.spec_from_file_location(
        "exploration_study", os.path.join(root, "experiments", "exploration_study.py"))
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    with open(os.path.join(root, "docs", "results", "exploration", "tuning.json")) as f:
        tuning = json.load(f)
    assert set(tuning["methods"]) == {*config_lib.PAPER_METHODS, "gp_critic"}
    for method in tuning["methods"]:
        chosen = tuning["methods"][method]["chosen"]
        cfg = config_lib.preset("swingup", method=method, dtype="float32")
        for field, value in study.settings_of(chosen, chosen["scheme"]).items():
            if field == "discount_horizon":
                field, value = "discount", math.exp(-0.005 / value)
            got = cfg.value(field)
            if isinstance(value, (str, bool)):
                assert got == value, (method, field)
            else:
                assert float(got) == pytest.approx(value, rel=1e-6), (method, field)
    assert not set(tuning["seeds"]) & set(study.HELDOUT_SEEDS)  # never the reported seeds
    with open(os.path.join(root, "docs", "results", "swingup", "tuning.json")) as f:
        white = json.load(f)
    assert not set(white["seeds"]) & set(range(1000, 1010))


def _exploration_study():
    """experiments/exploration_study.py as a module."""
    import importlib.util
    import os

    root = os.path.dirname(os.path.dirname(__file__))
    spec = importlib.util.spec_from_file_location(
        "exploration_study", os.path.join(root, "experiments", "exploration_study.py"))
    es = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(es)
    return es


def test_the_exploration_studys_retune_runs_its_choice_only_where_it_differs(tmp_path,
                                                                            monkeypatch):
    """`retune` scores gp_critic's tuned settings again, then `RETUNE_GRID` over the best so far
    (by success, then reward); `heldout` adds the part gp_critic/retuned with its choice, and none
    where the choice is the tuned settings."""
    from gpguided_jax import study

    es = _exploration_study()
    out = str(tmp_path)
    tuned = {"scheme": "hold_0.5s", "critic_learning_rate": 0.01}
    study.write_json(f"{out}/tuning.json", {"methods": {"gp_critic": {"chosen": tuned}}})
    reward = {(): -6.0, ("critic_window", 4): -5.0, ("critic_window", 16): -5.5,
              ("gp_capacity", 400): -7.0}

    def fake_sweep(overrides, score, *, method, preset, seeds):
        assert method == "gp_critic" and preset == "swingup" and list(seeds) == [100, 101]
        out_ = []
        for o in overrides:
            assert o["hold_time"] == 0.5 and o["dtype"] == es.DTYPE
            changed = [(k, o[k]) for k, _ in es.RETUNE_GRID if k in o]
            out_.append({"success": 0.0, "reward": reward[changed[-1] if changed else ()]})
        return out_

    monkeypatch.setattr(study, "sweep_stage", fake_sweep)
    result = es.retune(out)
    assert [t["settings"] for t in result["tried"]] == [
        tuned, {**tuned, "critic_window": 4}, {**tuned, "critic_window": 16},
        {**tuned, "critic_window": 4, "gp_capacity": 400}]
    assert result["chosen"] == {**tuned, "critic_window": 4}
    runs = {}

    def fake_run_parts(path, header, parts, run, log):
        runs.update(parts)

    monkeypatch.setattr(study, "run_parts", fake_run_parts)
    es.heldout(out, ["gp_critic"])
    assert runs[f"gp_critic/{es.RETUNED}"] == {**es.settings_of(tuned, "hold_0.5s"),
                                               "critic_window": 4}
    assert set(runs) == {f"gp_critic/{s}" for s in es.ABLATION["gp_critic"]} | {
        f"gp_critic/{es.RETUNED}"}
    runs.clear()
    study.write_json(f"{out}/retune.json", {**result, "chosen": tuned})
    es.heldout(out, ["gp_critic"])
    assert set(runs) == {f"gp_critic/{s}" for s in es.ABLATION["gp_critic"]}


def test_the_exploration_studys_standard_tune_runs_each_scheme_over_the_tasks_own_base(
        tmp_path, monkeypatch):
    """`standard-tune` runs a method under each scheme of `STANDARD_SCHEMES[task]` it can take, on
    the tuning seeds, with every exploration field set and, on brax's pendulums, its episodes
    restarted (Pendulum-v1's never end early); it chooses the best mean final return, runs no
    scheme twice and keeps what another process recorded for the task meanwhile."""
    import os
    from types import SimpleNamespace

    from gpguided_jax import study

    es = _exploration_study()
    scores = {"inverted-pendulum": {"white": -3.0, "ou_0.1s": 1.0, "ou_0.5s": 2.0,
                                    "hold_0.08s": 0.0}}
    scores["inverted-double-pendulum"] = scores["inverted-pendulum"]
    scores["pendulum-v1"] = {"white": -3.0, "ou_0.5s": 1.0, "ou_2s": 2.0, "hold_0.2s": 0.0}
    calls = []

    def fake_run_method(task, method, seeds, run_dir, overrides, *, dtype):
        if not calls:  # another process records a method of the task meanwhile
            study.record_result(os.path.join(str(tmp_path), task, "standard_tuning.json"),
                                {}, "reinforce", {"chosen": "white"})
        calls.append((task, os.path.basename(run_dir), overrides))
        assert method == "gp_critic" and list(seeds) == [100, 101] and dtype == "float64"
        return SimpleNamespace(records=os.path.basename(run_dir))

    monkeypatch.setattr(study, "run_method", fake_run_method)
    monkeypatch.setattr(study, "final_return", lambda scheme: {"score": score[scheme]})
    for task, end in (("inverted-pendulum", "restart"), ("inverted-double-pendulum", "restart"),
                      ("pendulum-v1", None)):
        calls.clear()
        score = scores[task]
        rec = es.standard_tune(task, str(tmp_path), ["gp_critic"])
        assert [c[1] for c in calls] == list(score)  # parameter noise: not gp_critic's
        for _, name, overrides in calls:
            assert overrides.get("episode_end") == end
            assert overrides["exploration"] == es.STANDARD_SCHEMES[task][name].get(
                "exploration", "white")
            assert overrides["hold_time"] == es.STANDARD_SCHEMES[task][name].get("hold_time", 0.0)
        assert rec["methods"]["gp_critic"]["chosen"] == max(score, key=score.get)
        assert rec["methods"]["reinforce"] == {"chosen": "white"}
        calls.clear()
        es.standard_tune(task, str(tmp_path), ["gp_critic"])
        assert calls == []


def test_the_exploration_studys_standard_stage_records_each_seeds_steps_to_the_threshold(
        tmp_path, monkeypatch):
    """`standard` records, per run whose curves are on this machine, the environment steps (the
    hyperparameter fit's included) at which each seed's deterministic return first reaches the
    task's threshold, null where it never does; without curves, all null where the summary says
    no seed reaches it, and nothing where some do."""
    import os

    import numpy as np

    from gpguided_jax import config as C
    from gpguided_jax import study

    es = _exploration_study()
    task, out = "mountaincar-continuous", str(tmp_path)
    cfg = C.preset(task, method="gp_critic")
    n = len(es.STANDARD_SEEDS)
    curves = np.zeros((1, n, cfg.num_updates))
    curves[0, 0, 3:] = 95.0  # the car's threshold is 90
    curves[0, 1, 7] = 90.0
    os.makedirs(f"{out}/{task}/gp_critic/white")
    np.savez(f"{out}/{task}/gp_critic/white/results.npz", eval_return=curves)
    summary = {"seeds_reaching_threshold": "0"}
    runs = {"gp_critic/white": {"overrides": es.standard_overrides(task, "white"),
                                "summary": {"seeds_reaching_threshold": "2"}},
            "gp_critic/ou_10s": {"overrides": es.standard_overrides(task, "ou_10s"),
                                 "summary": summary},
            "gp_critic/hold_10s": {"overrides": es.standard_overrides(task, "hold_10s"),
                                   "summary": {"seeds_reaching_threshold": "1"}}}
    monkeypatch.setattr(study, "run_parts", lambda *a, **k: {"seeds": list(es.STANDARD_SEEDS),
                                                            "runs": runs})
    meta = es.standard(task, out, ["gp_critic"])
    fit = cfg.hyperfit_episodes * cfg.episode_length
    per_update = cfg.episodes_per_update * cfg.episode_length
    assert meta["runs"]["gp_critic/white"]["steps_to_threshold"] == [
        fit + 3 * per_update, fit + 7 * per_update] + [None] * (n - 2)
    assert meta["runs"]["gp_critic/ou_10s"]["steps_to_threshold"] == [None] * n
    assert "steps_to_threshold" not in meta["runs"]["gp_critic/hold_10s"]


def test_the_exploration_studys_standard_stage_can_run_each_methods_choice_only(tmp_path,
                                                                               monkeypatch):
    """`standard --chosen` runs each method under the scheme its tuning record chose only, with
    the task's base; without it, under every scheme the method can take."""

    from gpguided_jax import study

    es = _exploration_study()
    task, out = "inverted-double-pendulum", str(tmp_path)
    study.write_json(f"{out}/{task}/standard_tuning.json", {"methods": {
        "reinforce": {"chosen": "ou_0.1s"}, "guided_direction": {"chosen": "white"}}})
    seen = {}

    def fake_run_parts(path, header, parts, run, log):
        seen.update(parts)
        return {"seeds": header["seeds"], "runs": {}}

    monkeypatch.setattr(study, "run_parts", fake_run_parts)
    es.standard(task, out, ["reinforce", "guided_direction"], chosen=True)
    assert seen == {"reinforce/ou_0.1s": es.standard_overrides(task, "ou_0.1s"),
                    "guided_direction/white": es.standard_overrides(task, "white")}
    assert seen["reinforce/ou_0.1s"]["episode_end"] == "restart"
    seen.clear()
    es.standard(task, out, ["guided_direction"])
    assert set(seen) == {"guided_direction/white", "guided_direction/hold_0.08s"}
