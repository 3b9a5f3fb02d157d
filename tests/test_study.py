"""gpguided_jax.study, the protocol the study scripts share: the coordinate search, the stage
sweep, the resumable held-out record, the preset's own settings, the environment-steps axis and
the report helpers. No training runs: the runs are stand-ins."""

import json
import math
import types

import matplotlib
import numpy as np
import pytest

from gpguided_jax import config as C
from gpguided_jax import methods, study

matplotlib.use("Agg")


# ------------------------------------------------------------------------------------------ search


def test_stages_and_the_tuning_budget():
    grid = [("lr", [1, 2, 3, 4]), (("h", "e"), [(0.5, 1), (2.0, 2)]), ("b", [7, 8])]
    assert study.stages(grid) == [[{"lr": 1}, {"lr": 2}, {"lr": 3}, {"lr": 4}],
                                  [{"h": 0.5, "e": 1}, {"h": 2.0, "e": 2}],
                                  [{"b": 7}, {"b": 8}]]
    assert study.grid_size(grid) == 8
    study.check_budget({"x": grid, "y": [("lr", list(range(8)))]}, 8)
    with pytest.raises(ValueError, match="8 configurations"):
        study.check_budget({"x": grid, "y": [("lr", [1, 2])]}, 8)


def test_coordinate_search_tries_each_stage_over_the_best_so_far():
    """score = -(a - 3)^2 - (b - 20)^2 / 100, from b = 20: stage 1 tries a = 1, 2, 3, 4 and keeps
    a = 3 (score 0); stage 2 tries b = 10, 30 with a = 3 (both -1: stage 1's best stays); stage 3
    tries a = 0, 5 with b = 20 (-9, -4) and a = 3, b = 20 is chosen."""
    calls = []

    def evaluate(configs):
        calls.append([dict(c) for c in configs])
        return [{"score": -(c["a"] - 3) ** 2 - (c["b"] - 20) ** 2 / 100, "n": len(calls)}
                for c in configs]

    grid = [("a", [1, 2, 3, 4]), ("b", [10, 30]), ("a", [0, 5])]
    res = study.coordinate_search(study.stages(grid), evaluate, start={"b": 20})
    assert calls == [[{"b": 20, "a": 1}, {"b": 20, "a": 2}, {"b": 20, "a": 3}, {"b": 20, "a": 4}],
                     [{"b": 10, "a": 3}, {"b": 30, "a": 3}],
                     [{"b": 20, "a": 0}, {"b": 20, "a": 5}]]
    assert [t["settings"] for t in res["tried"]] == [c for stage in calls for c in stage]
    assert [t["n"] for t in res["tried"]] == [1, 1, 1, 1, 2, 2, 3, 3]  # the record keeps it all
    assert res["chosen"] == {"b": 20, "a": 3}


def test_coordinate_search_moves_on_from_a_better_later_stage_and_orders_by_success():
    def evaluate(configs):
        return [{"success": {1: 0.5, 2: 0.5}.get(c["lr"], 0.0) + (0.4 if c.get("x") == 9 else 0),
                 "reward": c["lr"] + c.get("x", 0) / 100} for c in configs]

    res = study.coordinate_search(study.stages([("lr", [1, 2, 3]), ("x", [8, 9])]), evaluate,
                                  key=study.by_success)
    # lr 1 and 2 tie on success: the reward breaks the tie (lr 2); then x = 9 raises success
    assert [t["settings"] for t in res["tried"][3:]] == [{"lr": 2, "x": 8}, {"lr": 2, "x": 9}]
    assert res["chosen"] == {"lr": 2, "x": 9}
    with pytest.raises(ValueError, match="2 results for 3"):
        study.coordinate_search([[{"a": 1}, {"a": 2}, {"a": 3}]], lambda cs: [{"score": 0}] * 2)


def test_a_stage_is_one_sweep_over_the_field_its_configurations_differ_in(monkeypatch):
    seen = {}

    def fake_sweep(field, values, *, method, preset, seeds, overrides, progress):
        seen.update(field=field, values=values, method=method, preset=preset, seeds=seeds,
                    overrides=overrides)
        bad = np.zeros((len(values), len(seeds), 3))
        bad[1, 0, 2] = 1  # the second value: one seed's gradient was not finite once
        ret = np.arange(len(values))[:, None, None] + np.zeros((len(values), len(seeds), 3))
        return types.SimpleNamespace(records={"eval_return": ret, "nonfinite_grad": bad,
                                              "gp_guard": np.zeros_like(bad)})

    monkeypatch.setattr(study.sweep, "run_sweep", fake_sweep)
    configs = [{"discount": 0.9, "learning_rate": v, "dtype": "float32"} for v in (0.1, 0.3)]
    out = study.sweep_stage(configs, study.final_return, method="gp_pg", preset="tiny",
                            seeds=(100, 101))
    assert seen == dict(field="learning_rate", values=[0.1, 0.3], method="gp_pg", preset="tiny",
                        seeds=(100, 101), overrides={"discount": 0.9, "dtype": "float32"})
    assert out == [{"score": 0.0, "unhealthy_seeds": 0}, {"score": 1.0, "unhealthy_seeds": 1}]
    with pytest.raises(ValueError, match="differ in one field"):
        study.sweep_stage([{"a": 1, "b": 1}, {"a": 2, "b": 2}], study.final_return,
                          method="gp_pg", preset="tiny", seeds=(100,))


def test_a_stage_over_a_static_field_runs_each_configuration_as_its_own_program(monkeypatch):
    calls = []

    def fake_sweep(field, values, *, method, preset, seeds, overrides, progress):
        calls.append(dict(field=field, values=values, overrides=overrides))
        k = overrides["critic_steps"]
        return types.SimpleNamespace(records={"eval_return": np.full((1, len(seeds), 3), float(k)),
                                              "gp_guard": np.zeros((1, len(seeds), 3))})

    monkeypatch.setattr(study.sweep, "run_sweep", fake_sweep)
    configs = [{"trust_region": 0.2, "critic_steps": k} for k in (10, 200)]
    out = study.sweep_stage(configs, study.final_return, method="gp_critic", preset="tiny",
                            seeds=(100, 101))
    lr = float(C.preset("tiny", method="gp_critic").learning_rate)
    assert calls == [dict(field="learning_rate", values=[lr], overrides=c) for c in configs]
    assert [o["score"] for o in out] == [10.0, 200.0]


# ------------------------------------------------------------------------------------------ config


def test_merge_overrides_keeps_one_spelling_of_the_discount():
    assert study.merge_overrides({"discount_horizon": 1.0, "lr": 1}, {"discount": 0.9}) == \
        {"lr": 1, "discount": 0.9}
    assert study.merge_overrides({"discount": 0.9}, {"lr": 2}, {"discount_horizon": 0.5}) == \
        {"lr": 2, "discount_horizon": 0.5}


def test_preset_own_undoes_the_tuned_settings_without_changing_them(monkeypatch):
    tuned = {"learning_rate": 0.5, "discount_horizon": 0.05, "hold_time": 0.1, "gp_capacity": 8}
    presets = methods.get("gp_pg").presets
    monkeypatch.setitem(presets, "tiny", dict(tuned))
    own = study.preset_own("tiny", "gp_pg")
    # the preset's own gp_capacity, the config's defaults for the rest
    assert own == {"learning_rate": C.TrainConfig.learning_rate, "discount": 0.99,
                   "hold_time": 0.0, "gp_capacity": C.PRESETS["tiny"]["gp_capacity"]}
    assert C.METHOD_PRESETS["tiny"] == {"gp_pg": tuned}
    untuned = C.preset("tiny", method="gp_pg", dtype="float32", **own).to_json_dict()
    monkeypatch.delitem(presets, "tiny")
    assert untuned == C.preset("tiny", method="gp_pg", dtype="float32").to_json_dict()
    assert study.preset_own("tiny", "gp_pg") == {}


def test_the_environment_steps_axis_places_a_record_where_it_was_measured():
    """Record u of the deterministic evaluation: before update u's step, after u updates'
    episodes (the GP methods' fit first); without evaluations the return record is the update's
    own episodes, after u + 1 updates'."""
    for method, fit in (("reinforce", 0), ("gp_pg", 1)):
        cfg = C.preset("tiny", method=method, dtype="float32", eval_episodes=2)
        per_update = cfg.episodes_per_update * cfg.episode_length
        fit_steps = fit * cfg.hyperfit_episodes * cfg.episode_length
        np.testing.assert_array_equal(study.env_steps(cfg),
                                      fit_steps + per_update * np.arange(cfg.num_updates))
        cfg = C.preset("tiny", method=method, dtype="float32")  # no evaluations
        np.testing.assert_array_equal(study.env_steps(cfg),
                                      fit_steps + per_update * np.arange(1, cfg.num_updates + 1))
        assert study.learning_steps(cfg) == cfg.num_updates * per_update


# ----------------------------------------------------------------------------------------- heldout


def test_run_parts_resumes_and_runs_again_what_changed(tmp_path):
    path = str(tmp_path / "heldout.json")
    ran = []

    def run(key, settings):
        ran.append(key)
        if settings.get("fail"):
            raise RuntimeError("stopped")
        return {"wall_s": 2.0, "note": key.upper()} if key == "a/x" else {}

    parts = {"a/x": {"lr": 1.0}, "a/y": {"lr": 2.0, "fail": True}, "b/x": {"lr": (1, 2)}}
    with pytest.raises(RuntimeError, match="stopped"):
        study.run_parts(path, {"seeds": [1000, 1001]}, parts, run, log=lambda m: None)
    with open(path) as f:
        assert json.load(f) == {"seeds": [1000, 1001], "runs": {
            "a/x": {"overrides": {"lr": 1.0}, "wall_s": 2.0, "note": "A/X"}}}
    parts["a/y"] = {"lr": 2.0}
    rec = study.run_parts(path, {"seeds": [1000, 1001]}, parts, run, log=lambda m: None)
    assert ran == ["a/x", "a/y", "a/y", "b/x"]  # a/x was done: not run again
    assert list(rec["runs"]) == ["a/x", "a/y", "b/x"] and rec["runs"]["b/x"]["wall_s"] >= 0
    # the same settings (a tuple as JSON keeps it) are done; changed ones run again
    parts["a/x"] = {"lr": 3.0}
    rec = study.run_parts(path, {"seeds": [1000, 1001]}, parts, run, settings_key="overrides",
                          log=lambda m: None)
    assert ran[4:] == ["a/x"] and rec["runs"]["a/x"]["overrides"] == {"lr": 3.0}
    with pytest.raises(ValueError, match="remove it"):
        study.run_parts(path, {"seeds": [1000]}, parts, run, log=lambda m: None)
    assert study.finished(path, seeds=(1000, 1001)) and not study.finished(path, seeds=[1000])
    assert not study.finished(str(tmp_path / "none.json"))


def test_run_method_reads_its_run_and_reproduces_wall_time(tmp_path, monkeypatch):
    overrides = {"learning_rate": 0.1, "num_updates": 3}

    def fake_reproduce(preset, seeds, methods, out_dir, **kw):
        assert methods == ["gp_pg"] and kw["overrides"] == overrides and kw["dtype"] == "float32"
        np.savez(f"{out_dir}/results.npz", methods=np.asarray(methods),
                 eval_return=np.ones((1, len(seeds), 3)), env_steps=np.array([[4.0, 6.0, 8.0]]))
        return {"complete": True, "wall_s": {"gp_pg": 12.5}}

    monkeypatch.setattr(study.reproduce, "reproduce", fake_reproduce)
    run = study.run_method("tiny", "gp_pg", (1, 2), str(tmp_path), overrides, dtype="float32",
                           progress=lambda m: None)
    assert run.wall_s == 12.5 and run.records["eval_return"].shape == (2, 3)
    # the axis of the run's return record, by hand: the tiny preset's fit of 5 episodes of 20
    # steps, then 2 episodes of 20 per update; it evaluates no policy apart, so its return
    # record is the update's own episodes', taken after u + 1 updates
    assert run.env_steps.tolist() == [140, 180, 220]


def _fake_brax(calls):
    """Stand-ins for brax's trainers that record (trainer, budget, episode length, seed, kwargs)
    and return four evaluations whose values are the seed."""
    from gpguided_jax import baselines

    steps = np.array([0, 100, 200, 300])

    def pendulum(trainer):
        def train(params, budget, length, seed, **kw):
            calls.append((trainer, budget, length, seed, kw))
            return baselines.PPOResult(steps, np.full(4, -seed / 10), 2.0, None, (),
                                       np.full(4, seed / 100))
        return train

    def on_task(name, env, budget, length, seed, **kw):
        calls.append((f"{name} on {env}", budget, length, seed, kw))
        return baselines.TaskResult(steps, np.arange(4.0) + seed, 3.0)

    return {"train_ppo": pendulum("ppo"), "train_sac": pendulum("sac"), "train_on_task": on_task}


def test_run_baseline_runs_each_seed_with_the_methods_budget(monkeypatch):
    """The paper's pendulum: brax's pendulum trainer, its success and reward per step under the
    methods' record names; a standard task: `train_on_task` and its return. The methods' budget
    of learning steps and episode length, the deterministic policy, a horizon as the discount at
    the task's step; the wall time summed over the seeds."""
    from gpguided_jax import baselines, tasks

    calls = []
    for name, fake in _fake_brax(calls).items():
        monkeypatch.setattr(baselines, name, fake)
    cfg = C.preset("tiny", method="reinforce", dtype="float32")
    run = study.run_baseline("sac", cfg, (5, 7), {"learning_rate": 0.1}, num_evals=4,
                             progress=lambda m: None)
    assert [c[:4] for c in calls] == [("sac", 240, 20, 5), ("sac", 240, 20, 7)]
    assert calls[0][4] == {"deterministic_eval": True, "learning_rate": 0.1, "num_evals": 4}
    assert set(run.records) == {"eval_success_rate", "eval_reward"}
    np.testing.assert_allclose(run.records["eval_success_rate"], [[0.05] * 4, [0.07] * 4])
    assert run.env_steps.tolist() == [0, 100, 200, 300]
    assert run.wall_s == 4.0 and run.seed_wall_s == (2.0, 2.0)
    calls.clear()
    cfg = C.preset("pendulum-v1", method="reinforce")
    run = study.run_baseline("ppo", cfg, (1,), {"horizon": 0.5, "grad_updates_per_step": 4.0},
                             num_evals=4, progress=lambda m: None)
    assert calls[0][:4] == ("ppo on gymnax:Pendulum-v1", study.learning_steps(cfg), 200, 1)
    dt = tasks.make_task("gymnax:Pendulum-v1").dt
    assert calls[0][4] == {"deterministic_eval": True, "num_evals": 4, "grad_updates_per_step": 4,
                           "discounting": tasks.discount_for_horizon(0.5, dt)}
    assert list(run.records) == ["eval_return"] and run.records["eval_return"].shape == (1, 4)
    # a stage of its tuning: each configuration on every seed, scored, with its seconds
    calls.clear()
    got = study.baseline_stage([{"learning_rate": 0.1}, {"learning_rate": 0.3}],
                               lambda r: {"score": float(r.records["eval_return"][:, -1].mean())},
                               name="ppo", cfg=cfg, seeds=(1, 2), num_evals=4)
    assert got == [{"score": 4.5, "wall_s": 6.0}] * 2 and len(calls) == 4
    assert study.last_success({"eval_success_rate": [[0.0, 0.5], [1.0, 1.0]],
                               "eval_reward": [[-3.0, -1.0], [-2.0, -2.0]]}) == {
        "success": 0.75, "reward": -1.5}


def test_set_up_prepares_a_float64_stage_and_its_directory(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(study.runtime, "single_threaded_lapack", lambda: calls.append("lapack"))
    monkeypatch.setattr(study.runtime, "set_compile_cache", lambda d: calls.append(("cache", d)))
    monkeypatch.setattr(study, "enable_x64", lambda: calls.append("x64"))
    out = str(tmp_path / "a" / "b")
    assert study.set_up(out) == out and (tmp_path / "a" / "b").is_dir()
    assert calls == ["lapack", ("cache", study.runtime.DEFAULT_COMPILE_CACHE), "x64"]


def test_record_result_adds_one_name(tmp_path):
    path = str(tmp_path / "tuning.json")
    study.record_result(path, {"seeds": [100, 101]}, "ppo", {"chosen": {"lr": 1}})
    rec = study.record_result(path, {"seeds": [100, 101]}, "sac", {"chosen": {"lr": 2}})
    assert rec == study.read_json(path) == {"seeds": [100, 101], "methods": {
        "ppo": {"chosen": {"lr": 1}}, "sac": {"chosen": {"lr": 2}}}}


# ----------------------------------------------------------------------------------------- reports


def test_smoothed_is_a_trailing_mean():
    x = np.array([[0, 0, 0, 0, 1, 1, 1, 1, 1, 1.0]])
    want = [np.mean(x[0, max(0, i - 4): i + 1]) for i in range(10)]
    np.testing.assert_allclose(study.smoothed(x, 5)[0], want)


def test_steps_to_level_and_the_median_interval():
    steps = np.array([10, 20, 30, 40])
    succ = np.array([[0.0, 0.5, 1.0, 1.0], [0.0, 0.0, 0.0, 0.2], [0.9, 0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(study.steps_to(steps, succ, 0.5), [20, np.inf, 10])
    np.testing.assert_array_equal(study.steps_to(steps, succ, 0.9), [30, np.inf, 10])
    np.testing.assert_array_equal(study.steps_to(steps, succ - 1e-12, 0.9, tol=1e-9, never=np.nan),
                                  [30, np.nan, 10])
    med, lo, hi = study.median_ci(np.array([1.0, 2.0, 3.0, np.inf, np.inf]))
    assert med == 3.0 and lo <= med <= hi
    assert study.final(np.arange(20.0)[None]).tolist() == [18.5]


def test_plot_band_draws_the_mean_and_its_band_in_one_colour():
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    study.plot_band(ax, np.arange(3), np.array([[0.0, 1, 2], [2, 3, 4]]), label="m", color="C3")
    (line,) = ax.get_lines()
    np.testing.assert_allclose(line.get_ydata(), [1, 2, 3])
    band = ax.collections[0]
    assert np.allclose(band.get_facecolor()[0][:3], matplotlib.colors.to_rgb("C3"))
    plt.close(fig)
    assert math.isclose(band.get_alpha(), 0.2)


def test_critic_diagnostics_reads_each_run_that_records_the_critic(tmp_path):
    """Medians over seeds of the first and last 10% of updates (a loop in NumPy), the action
    length-scale over seeds; a run without the critic's records, or not here, is left out."""
    rng = np.random.default_rng(0)
    seeds, updates = 3, 20
    rec = {k: rng.uniform(size=(1, seeds, updates)) for k in
           ("critic_error", "critic_step_fraction", "critic_kl")}
    rec["action_lengthscale"] = rng.uniform(1, 2, size=(1, seeds, 1))
    np.savez(tmp_path / "critic.npz", **rec)
    np.savez(tmp_path / "plain.npz", eval_return=np.zeros((1, seeds, updates)))
    out = tmp_path / "diag.json"
    study.critic_diagnostics({"a": str(tmp_path / "critic.npz"), "b": str(tmp_path / "plain.npz"),
                              "c": str(tmp_path / "absent.npz")}, str(out),
                             str(tmp_path / "diag.png"))
    assert (tmp_path / "diag.png").stat().st_size > 0
    (row,) = json.loads(out.read_text())["rows"]
    first = [rec["critic_error"][0, s, u] for s in range(seeds) for u in range(2)]
    last = [rec["critic_kl"][0, s, u] for s in range(seeds) for u in range(18, 20)]
    assert row["method"] == "a" and row["seeds"] == seeds
    assert row["error_first"] == pytest.approx(float(np.median(first)))
    assert row["kl_last"] == pytest.approx(float(np.median(last)))
    assert row["lengthscale_max"] == pytest.approx(float(rec["action_lengthscale"].max()))
