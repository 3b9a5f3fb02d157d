"""experiments/standard_tasks.py: the environment steps a method's learning episodes used, the tuning,
the retune stage, the held-out stage's resumption and the presets."""

import importlib.util
import math
import os
import types

import numpy as np
from conftest import ROOT


def _script():
    spec = importlib.util.spec_from_file_location(
        "standard_tasks", os.path.join(ROOT, "experiments", "standard_tasks.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_steps_used_sums_the_episodes_lengths_before_their_ends(tmp_path):
    """Two seeds, three updates of 4 episodes of up to 50 steps: the mean length is the mean
    return over the mean reward per step, and the full length where that reward is 0."""
    mean_return = np.array([[[10.0, 20.0, 5.0], [-6.0, 0.0, 50.0]]])  # (methods, seeds, updates)
    mean_reward = np.array([[[1.0, 2.0, 0.5], [-0.5, 0.0, 1.0]]])
    np.savez(tmp_path / "results.npz", mean_return=mean_return, mean_reward=mean_reward)
    cfg = types.SimpleNamespace(episodes_per_update=4, episode_length=50, episode_end="mask",
                                num_updates=3)
    used = _script().steps_used(str(tmp_path), cfg)
    # seed 0: lengths 10, 10, 10; seed 1: 12, 50 (no reward: the full length), 50
    np.testing.assert_array_equal(used, [4 * 30, 4 * 112])
    # restarted episodes fill their slots: every slot is a step
    cfg.episode_end = "restart"
    np.testing.assert_array_equal(_script().steps_used(str(tmp_path), cfg), [600, 600])


def test_the_tuning_searches_the_horizon_as_a_discount_from_the_presets_own(monkeypatch):
    """Each stage of a method's grid is one sweep: the horizon stage sweeps the discount; the
    other fields are the preset's own (not the tuned `config.METHOD_PRESETS`) and the best so
    far."""
    from gpguided_jax import study, tasks

    script = _script()
    calls = []

    def fake_sweep(field, values, *, method, preset, seeds, overrides, progress):
        calls.append((field, list(values), overrides))
        score = 10 * len(calls) + np.arange(len(values), dtype=float)  # the last, later the better
        ret = np.broadcast_to(score[:, None, None], (len(values), len(seeds), 10))
        return types.SimpleNamespace(records={"eval_return": ret})

    monkeypatch.setattr(study.sweep, "run_sweep", fake_sweep)
    res = script.tune_method("pendulum-v1", "reinforce", (100, 101))
    assert [c[0] for c in calls] == ["learning_rate", "discount", "init_log_std"]
    dt = tasks.make_task("gymnax:Pendulum-v1").dt
    assert calls[1][1] == [tasks.discount_for_horizon(h, dt) for h in script.horizons("pendulum-v1")]
    assert calls[0][2] == {"discount_horizon": 1.0}  # the preset's own horizon, not the tuned 0.5
    assert calls[2][2] == {"learning_rate": 0.1, "discount": calls[1][1][1]}
    assert res["chosen"] == {"learning_rate": 0.1, "horizon": 2.0,
                             "init_log_std": math.log(tasks.make_task("gymnax:Pendulum-v1").max_action)}


def _fake_heldout_runs(monkeypatch) -> list:
    """Replaces `study.run_method` by a stand-in that writes a one-update run and records
    (method, overrides) of each call in the list returned."""
    from gpguided_jax import study

    runs = []

    def fake_run(preset, method, seeds, run_dir, overrides, **kw):
        runs.append((method, overrides))
        os.makedirs(run_dir, exist_ok=True)
        np.savez(os.path.join(run_dir, "results.npz"), mean_return=np.ones((1, 1, 3)),
                 mean_reward=np.ones((1, 1, 3)))
        return study.MethodRun({"eval_return": np.ones((1, 3))}, np.arange(3), 2.0)

    monkeypatch.setattr(study, "run_method", fake_run)
    return runs


def test_heldout_skips_a_name_done_with_the_same_seeds_and_settings(tmp_path, monkeypatch):
    from gpguided_jax import study

    script = _script()
    out = str(tmp_path)
    study.write_json(f"{out}/tuning/reinforce.json", {"chosen": {"learning_rate": 0.03}})
    done = {"seeds": [1000], "settings": {"learning_rate": 0.03}, "episode_end": "mask",
            "wall_s": 1.0}
    study.write_json(f"{out}/heldout/reinforce.json", done)
    runs = _fake_heldout_runs(monkeypatch)
    script.heldout("pendulum-v1", out, [1000], ["reinforce"])
    assert runs == []
    study.write_json(f"{out}/tuning/reinforce.json", {"chosen": {"learning_rate": 0.1}})
    script.heldout("pendulum-v1", out, [1000], ["reinforce"])
    assert runs == [("reinforce", {"learning_rate": 0.1, "discount_horizon": 1.0,
                                   "episode_end": "mask"})]
    assert study.read_json(f"{out}/heldout/reinforce.json")["wall_s"] == 2.0


def test_the_presets_hold_the_settings_the_tuning_chose():
    """`config.METHOD_PRESETS[task][method]` is each tuning record's choice on every standard task
    (its horizon as `discount_horizon`) and the fields of the exploration scheme the method chose
    at those settings (the exploration study's `standard-tune` record, where it has one), and
    nothing besides, so that `gpguided reproduce --preset <task>` runs the methods as the studies
    tuned them."""
    import json

    from gpguided_jax import config as C

    script = _script()
    spec = importlib.util.spec_from_file_location(
        "exploration_study", os.path.join(ROOT, "experiments", "exploration_study.py"))
    es = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(es)
    results = os.path.join(ROOT, "docs", "results", "standard")
    tasks = sorted(os.listdir(results))
    assert tasks == ["inverted-double-pendulum", "inverted-pendulum", "mountaincar-continuous",
                     "pendulum-v1"]
    checked, schemes = 0, 0
    for task in tasks:
        path = os.path.join(ROOT, "docs", "results", "exploration", task, "standard_tuning.json")
        with open(path) as f:
            exploration = json.load(f)["methods"]
        for method in script.METHODS:
            path = os.path.join(results, task, "tuning", f"{method}.json")
            with open(path) as f:
                chosen = json.load(f)["chosen"]
            expected = {("discount_horizon" if k == "horizon" else k): v for k, v in chosen.items()}
            if method in exploration:
                expected.update({**es.STANDARD_BASE.get(task, {}),
                                 **es.STANDARD_SCHEMES[task][exploration[method]["chosen"]]})
                schemes += expected != {
                    ("discount_horizon" if k == "horizon" else k): v for k, v in chosen.items()}
            preset = C.METHOD_PRESETS[task].get(method, {})
            assert set(preset) == set(expected), (task, method, preset, expected)
            for k, v in expected.items():
                if isinstance(v, str):
                    assert preset[k] == v, (task, method, k)
                else:
                    assert math.isclose(preset[k], v, rel_tol=1e-12), (task, method, k)
            checked += 1
    assert checked == len(tasks) * len(script.METHODS)
    assert schemes >= 6  # the schemes chosen on Pendulum-v1 and the car beside white


def test_retune_searches_the_critics_own_settings_from_its_tuned_ones(tmp_path, monkeypatch):
    """The retune stage scores gp_critic's tuned settings again, then each stage of `retune_grid`
    over the best so far (a static field: one program per value; the horizon and the learning
    rate: one sweep each); run again, it takes its recorded results and runs only a stage it has
    not tried. `heldout --only gp_critic_retuned` runs its choice over the tuned settings."""
    from gpguided_jax import study

    script = _script()
    out = str(tmp_path)
    tuned = {"critic_learning_rate": 0.03}
    study.write_json(f"{out}/tuning/gp_critic.json", {"chosen": tuned})
    calls = []
    scores = {(): 0.0, ("critic_optimism", -1.0): -5.0, ("critic_optimism", 1.0): 3.0,
              ("critic_window", 4): 1.0, ("critic_window", 16): 2.0, ("gp_capacity", 400): 9.0}

    def fake_sweep(field, values, *, method, preset, seeds, overrides, progress):
        assert method == "gp_critic" and list(seeds) == list(script.TUNING_SEEDS)
        calls.append((field, overrides))
        if field in ("discount", "learning_rate") and len(values) == 2:  # the traced stages
            score = np.array([8.0, 10.0] if field == "discount" else [7.0, 6.0])
        else:
            changed = [(k, v) for k, v in overrides.items() if (k, v) in scores]
            score = np.full(len(values), scores[changed[-1] if changed else ()])
        ret = np.broadcast_to(score[:, None, None], (len(values), len(seeds), 10))
        return types.SimpleNamespace(records={"eval_return": ret})

    monkeypatch.setattr(study.sweep, "run_sweep", fake_sweep)
    script.retune("pendulum-v1", out)
    rec = study.read_json(f"{out}/retune.json")
    best = {**tuned, "critic_optimism": 1.0, "gp_capacity": 400}
    long = {**best, "horizon": 2.0}
    assert [t["settings"] for t in rec["tried"]] == [
        tuned, {**tuned, "critic_optimism": -1.0}, {**tuned, "critic_optimism": 1.0},
        {**tuned, "critic_optimism": 1.0, "critic_window": 4},
        {**tuned, "critic_optimism": 1.0, "critic_window": 16}, best,
        {**best, "horizon": 0.5}, long, {**long, "learning_rate": 0.003},
        {**long, "learning_rate": 0.03}]
    # each static configuration its own program; the horizon and the learning rate one each
    assert len(calls) == 8 and [c[0] for c in calls[-2:]] == ["discount", "learning_rate"]
    assert rec["chosen"] == long
    # again: every stage recorded, nothing runs; with the last stage's record gone, only it runs
    calls.clear()
    script.retune("pendulum-v1", out)
    assert calls == [] and study.read_json(f"{out}/retune.json")["tried"] == rec["tried"]
    study.write_json(f"{out}/retune.json", {**rec, "tried": rec["tried"][:-2]})
    script.retune("pendulum-v1", out)
    assert [c[0] for c in calls] == ["learning_rate"]
    assert study.read_json(f"{out}/retune.json")["tried"] == rec["tried"]
    runs = _fake_heldout_runs(monkeypatch)
    script.heldout("pendulum-v1", out, [1000], ["gp_critic_retuned"])
    assert runs[0][0] == "gp_critic"
    want = script.method_overrides("pendulum-v1", "gp_critic", rec["chosen"])  # horizon: discount
    assert "discount" in want and {k: runs[0][1][k] for k in want} == want
    # a retune that keeps the tuned settings runs nothing again: its row would be gp_critic's
    study.write_json(f"{out}/retune.json", {**rec, "chosen": tuned})
    script.heldout("pendulum-v1", out, [1000], ["gp_critic_retuned"])
    assert len(runs) == 1
