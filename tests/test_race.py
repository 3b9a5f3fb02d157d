"""`gpguided race` (`gpguided_jax.race`): the time to the threshold from timed evaluations, the
medians over seeds, the default budget of SAC, refused input, the command end to end, and the
committed race's generated block against its runs."""

import json
import os
import statistics

import pytest
from conftest import experiment, run_script

from gpguided_jax import cli, race


def test_time_to_threshold_by_hand():
    times = [2.0, 3.5, 5.0, 7.25]
    # never reaching
    assert race.time_to_threshold(times, [-900, -800, -700, -600], -200.0) is None
    assert race.time_to_threshold([], [], -200.0) is None
    # reaching at the first evaluation
    assert race.time_to_threshold(times, [-150, -900, -100, -90], -200.0) == 2.0
    # not monotone: the first evaluation at or above, not the last crossing nor the best
    assert race.time_to_threshold(times, [-300, -199, -250, -100], -200.0) == 3.5
    # at the threshold exactly counts
    assert race.time_to_threshold(times, [-300, -400, -200, -500], -200.0) == 5.0
    assert race.first_reaching([0.5, 0.95, 0.8], 0.9) == 1


def test_median_counts_a_seed_that_never_reaches_as_never():
    assert race.median_or_none([4.0, 1.0, 3.0]) == 3.0
    assert race.median_or_none([4.0, 1.0]) == 2.5
    assert race.median_or_none([1.0, None, 3.0]) == 3.0  # never sorts last
    assert race.median_or_none([1.0, None]) is None  # half the seeds never reach it
    assert race.median_or_none([None, None, 5.0]) is None
    assert race.median_or_none([]) is None


def test_summarise_run_leaves_out_brax_initial_evaluation():
    events = [{"event": "start", "t": 0.5},
              {"event": "evaluation", "t": 10.0, "env_steps": 0, "value": 5.0},
              {"event": "evaluation", "t": 12.0, "env_steps": 100, "value": -300.0},
              {"event": "evaluation", "t": 14.0, "env_steps": 200, "value": -100.0},
              {"event": "end", "t": 15.0}, {"event": "exit", "t": 15.5}]
    sac = race.summarise_run(events, -200.0, skip_initial=True)
    assert (sac["wall_to_threshold_s"], sac["env_steps_to_threshold"]) == (14.0, 200)
    assert sac["total_wall_s"] == 15.5 and sac["start_s"] == 0.5
    assert [e["env_steps"] for e in sac["evaluations"]] == [100, 200]
    gp = race.summarise_run(events, -200.0, skip_initial=False)
    assert (gp["wall_to_threshold_s"], gp["env_steps_to_threshold"]) == (10.0, 0)
    assert race.summarise_run(events, 0.0, skip_initial=True)["wall_to_threshold_s"] is None


def test_default_sac_budget_is_the_held_out_median(tmp_path):
    table = tmp_path / "task" / "heldout_table.json"
    table.parent.mkdir()
    table.write_text(json.dumps({"rows": [{"method": "ppo", "steps_to_threshold_median": 9.0},
                                          {"method": "sac", "steps_to_threshold_median": 5920.0}]}))
    assert race.reported_sac_steps("task", str(tmp_path)) == 5920
    assert race.reported_sac_steps("other", str(tmp_path)) is None
    plan = race.plan("pendulum-v1", seeds=[1000], sac_steps=3000)
    assert plan["sac_steps"] == 3000 and plan["threshold"] == -200.0
    assert plan["sac_steps_source"] == "given"


@pytest.mark.parametrize("args", [
    ["--preset", "no-such-task"],  # unknown preset
    ["--seeds", "0"],
    ["--preset", "tiny"],  # the paper's pendulum: no SAC there through `gpguided baseline`
    ["--cache", "lukewarm"],
    ["--sac-steps", "10"],  # below SAC's replay-buffer prefill
])
def test_bad_input_is_one_line_and_status_2(args, capsys, tmp_path):
    try:
        status = cli.main(["race", *args, "--out", str(tmp_path / "out")])
    except SystemExit as e:
        status = e.code
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert len(err.splitlines()) == 1 and err.startswith("gpguided race: error:"), err
    assert not (tmp_path / "out").exists()


@pytest.mark.cli
def test_race_end_to_end(tmp_path):
    """Both methods on Pendulum-v1 at tiny budgets, one seed, cold and warm, with a threshold
    every evaluation reaches: race.json's structure, and times that are positive and ordered."""
    out = tmp_path / "race"
    proc = run_script(["-m", "gpguided_jax.cli", "race", "--preset", "pendulum-v1", "--seeds", "1",
                       "--seed-start", "1000", "--cache", "cold,warm", "--threshold=-1e9",
                       "--sac-steps", "200", "--sac-evals", "3",
                       "--sac-set", "min_replay_size=64", "num_envs=4", "batch_size=16",
                       "grad_updates_per_step=1", "num_eval_envs=2",
                       "--gp-set", "num_updates=2", "episode_length=50", "model_steps=5",
                       "model_inducing=20", "eval_episodes=1", "--out", out], timeout=300)
    report = json.loads((out / "race.json").read_text())
    assert report["seeds"] == [1000] and report["cache"] == ["cold", "warm"]
    assert report["sac_steps"] == 200 and report["threshold"] == -1e9
    assert set(report["methods"]) == {"gp_model", "sac"}
    for method, states in report["methods"].items():
        assert set(states) == {"cold", "warm"}
        for state, s in states.items():
            assert s["seeds_reaching"] == 1
            (run,) = s["runs"]
            assert run["seed"] == 1000
            evals = run["evaluations"]
            times = [e["t"] for e in evals]
            steps = [e["env_steps"] for e in evals]
            assert len(evals) == 2 and times == sorted(times) and steps == sorted(steps)
            assert 0 < run["start_s"] < run["wall_to_threshold_s"] <= run["total_wall_s"]
            # every evaluation reaches it: the first counted one is the time to the threshold
            assert run["wall_to_threshold_s"] == times[0]
            assert run["env_steps_to_threshold"] == steps[0]
            assert s["median_wall_to_threshold_s"] == run["wall_to_threshold_s"]
            assert s["median_total_wall_s"] == run["total_wall_s"]
            assert os.path.exists(out / "runs" / f"{method}_{state}_1000" / "events.jsonl")
    # brax's evaluation of the initial policy, at 0 steps, is left out; gp_model's first record
    # is its policy before learning
    assert report["methods"]["sac"]["cold"]["runs"][0]["env_steps_to_threshold"] > 0
    assert report["methods"]["gp_model"]["cold"]["runs"][0]["env_steps_to_threshold"] == 0
    assert "| gp_model | warm | 1/1 |" in proc.stdout and "| sac | cold | 1/1 |" in proc.stdout


@pytest.mark.parametrize("task", experiment("docs_tables").RACE_TASKS)
def test_the_committed_race_block_holds_the_medians_of_its_runs(task):
    """The generated race block of the README and the benchmarks page, against race.json's runs
    recomputed here: each method's and cache state's seeds reaching the threshold (from each run's
    evaluations) and the median over seeds of its wall time to it (a seed that never reaches it
    counting as never)."""
    tables = experiment("docs_tables")
    path = os.path.join(tables.RESULTS, "race", task, "race.json")
    with open(path) as f:
        report = json.load(f)
    block = tables.race_table(task)
    n = len(report["seeds"])
    for method, states in report["methods"].items():
        for state, s in states.items():
            times = []
            for run in s["runs"]:
                hit = [e["t"] for e in run["evaluations"]
                       if e["value"] >= report["threshold"]
                       and not (method == "sac" and e["env_steps"] == 0)]
                times.append(hit[0] if hit else float("inf"))
            reaching = sum(t < float("inf") for t in times)
            median = statistics.median(times)
            cell = "never" if median == float("inf") else f"{median:.1f}"
            assert f"| {method} | {state} | {reaching}/{n} | {cell} |" in block
    readme = open(os.path.join(tables.ROOT, "README.md")).read()
    assert block in readme
