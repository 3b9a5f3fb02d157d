"""Baselines: brax PPO on the pendulum, the swing-up success criterion, the comparison script."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_script

from gpguided_jax import baselines, pendulum

DT = 0.005
T = 400  # a 2 s episode of the swing-up preset
HOLD = 200  # its last second


def _trajectory(phi):
    phi = np.asarray(phi, float)
    omega = np.gradient(phi, DT)
    return jnp.asarray(np.stack([pendulum.wrap_angle(phi), omega], axis=-1))


def _swing_up_and_hold():
    t = np.arange(T)
    phi = np.where(t < 150, math.pi * t / 150, math.pi + 0.2 * np.sin(t / 10.0))
    return _trajectory(phi)


def _reach_then_fall():
    t = np.arange(T)
    phi = np.clip(math.pi * t / 150, 0, math.pi)  # upright from step 150 ...
    phi = np.where(t >= 300, math.pi + 0.02 * np.maximum(t - 299, 0) ** 1.5, phi)  # ... falls from step 300
    return _trajectory(phi)


def _spin_through_upright():
    return _trajectory(2 * math.pi * 3 * np.arange(T) / T)  # three full turns


def test_success_against_hand_made_trajectories():
    assert bool(baselines.swingup_success(_swing_up_and_hold(), DT))
    assert not bool(baselines.swingup_success(_reach_then_fall(), DT))
    assert not bool(baselines.swingup_success(_spin_through_upright(), DT))
    # upright on the other side of pi (phi slightly above pi, wrapped) also counts
    assert bool(baselines.swingup_success(_trajectory(np.full(T, math.pi + 0.25)), DT))
    # one step out of tolerance within the last second fails; before it does not matter
    for step, expected in [(T - HOLD, False), (T - HOLD - 1, True), (T - 1, False)]:
        phi = np.full(T, math.pi)
        phi[step] = math.pi - 0.31
        assert bool(baselines.swingup_success(_trajectory(phi), DT)) == expected, step


def test_success_jit_vmap_and_hold_time():
    batch = jnp.stack([_swing_up_and_hold(), _reach_then_fall(), _spin_through_upright()])
    flags = jax.jit(jax.vmap(lambda s: baselines.swingup_success(s, DT)))(batch)
    np.testing.assert_array_equal(flags, [True, False, False])
    # upright from 1.25 s before the end: (within 0.3 rad from step 136) a 1.2 s hold
    # is met, a 1.4 s hold is not
    assert bool(baselines.swingup_success(_swing_up_and_hold(), DT, hold_time=1.2))
    assert not bool(baselines.swingup_success(_swing_up_and_hold(), DT, hold_time=1.4))
    with pytest.raises(ValueError, match="shorter than the hold time"):
        baselines.swingup_success(batch[0, :100], DT)


def test_policy_success_rate_of_a_pendulum_at_rest_upright():
    params = pendulum.make_params(start_mean=(math.pi, 0.0), start_std=(0.0, 0.0))
    rate = baselines.policy_success_rate(jax.random.PRNGKey(0), params, lambda k, s: 0.0, 400, 4)
    assert rate == 1.0  # an unperturbed upright pendulum stays (reward noise does not act on it)
    params = pendulum.make_params(start_mean=(0.0, 0.0), start_std=(0.1, 0.1))
    assert baselines.policy_success_rate(jax.random.PRNGKey(0), params, lambda k, s: 0.0, 400, 4) == 0


def test_matched_budget_value():
    x = np.array([100, 200, 300, 400])
    y = np.array([[1.0, 2.0, 3.0, 4.0], [3.0, 4.0, 5.0, 6.0]])
    np.testing.assert_allclose(baselines.matched_budget_value(x, y, 400, window=0.5), [3.5, 5.5])
    np.testing.assert_allclose(baselines.matched_budget_value(x, y, 310), [3.0, 5.0])
    assert np.all(np.isnan(baselines.matched_budget_value(x, y, 350)))  # no point in (315, 350]
    assert np.all(np.isnan(baselines.matched_budget_value(x, y, 1000)))


@pytest.mark.training
def test_train_ppo_tiny_budget_returns_finite_curve():
    """brax's own PPO trainer (`ppo.train`) on `brax_env.PendulumEnv`, through `train_ppo`: the
    environment's brax interface end to end (it was a test of its own in test_brax_env.py)."""
    params = pendulum.make_params(start_mean=(math.pi - 0.5, 0.0), start_std=(0.1, 0.1))
    schedule = dict(num_envs=4, unroll_length=10, batch_size=4, num_minibatches=2)
    result = baselines.train_ppo(params, 161, 20, seed=0, num_evals=3, num_updates_per_batch=1,
                                 num_eval_envs=4, hidden_layers=(8,), **schedule)
    # an iteration is 4 x 2 unrolls of 10 steps = 80 steps; 2 intervals need ceil(161 / 160) = 2
    # iterations each: brax evaluates at 160 and 320 steps, and ran 320 for a budget of 161
    np.testing.assert_array_equal(result.env_steps, [0, 160, 320])
    np.testing.assert_array_equal(baselines.evaluation_steps("ppo", 161, 3, schedule),
                                  result.env_steps)
    assert result.reward_per_step.shape == (3,)
    assert np.all(np.isfinite(result.reward_per_step)) and np.all(result.reward_per_step < 0.5)
    assert result.wall_time > 0
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(result.params))
    rate = baselines.ppo_success_rate(
        jax.random.PRNGKey(1), result, params, 20, 3, deterministic=True, hold_time=0.02
    )
    assert 0.0 <= rate <= 1.0
    assert jax.config.jax_enable_x64  # train_ppo leaves the package's float64 setting as it was


@pytest.mark.training
def test_train_sac_tiny_budget_returns_finite_curve_and_success():
    params = pendulum.make_params(start_mean=(0.0, 0.0), start_std=(0.1, 0.1))
    result = baselines.train_sac(params, 401, 250, seed=0, num_evals=2, num_envs=4,
                                 batch_size=16, min_replay_size=62, max_replay_size=1000,
                                 num_eval_envs=4, hidden_layers=(8,))
    # prefill: ceil(62 / 4) = 16 steps of 4 environments = 64; then ceil((401 - 64) / 4) = 85
    # steps of 4 in the one interval: 64 + 340 = 404
    np.testing.assert_array_equal(result.env_steps, [0, 404])
    np.testing.assert_array_equal(
        baselines.evaluation_steps("sac", 401, 2, dict(num_envs=4, min_replay_size=62)),
        result.env_steps)
    assert np.all(np.isfinite(result.reward_per_step))
    # hanging down, 1.25 s episodes: nothing is upright for the last second
    np.testing.assert_array_equal(result.success_rate, np.zeros(2))
    assert jax.config.jax_enable_x64


# ------------------------------------------------------------------------------------------------
# the baselines on the standard tasks: `gpguided baseline`
# ------------------------------------------------------------------------------------------------


def test_baseline_summary_against_a_hand_computation():
    """The first evaluation (the initial policy) is left out; a seed's final return is the mean of
    its last 10% of evaluations; the IQM of 8 seeds is the mean of the middle 4 (scipy's
    trim_mean at 25%); steps to threshold are the first evaluation at or above it."""
    from scipy import stats as sps

    rng = np.random.default_rng(0)
    steps = np.arange(0, 21_000, 1000)  # 21 evaluations: 20 after the initial one
    returns = rng.normal(-400, 50, (8, 21)).cumsum(axis=1) / np.arange(1, 22)
    returns[3, 7:] = -150.0  # seed 3 reaches -200 at the 8th evaluation, 7000 steps
    returns[:, 0] = 0.0  # the initial policy's evaluation would reach it at step 0
    s = baselines.summarise_returns(steps, returns, -200.0)
    finals = returns[:, -2:].mean(axis=1)  # 10% of 20 evaluations
    assert s["final_return_iqm"] == pytest.approx(sps.trim_mean(finals, 0.25), rel=1e-12)
    assert s["final_return_mean"] == pytest.approx(finals.mean(), rel=1e-12)
    assert s["ci95"][0] <= s["final_return_iqm"] <= s["ci95"][1]
    want = [None if not (r[1:] >= -200).any() else int(steps[1:][np.argmax(r[1:] >= -200)])
            for r in returns]
    assert s["steps_to_threshold"] == want and want[3] == 7000
    assert "steps_to_threshold" not in baselines.summarise_returns(steps, returns, None)


def test_trainer_settings_and_the_evaluations_after_learning_started():
    got = baselines.trainer_settings({"horizon": 0.5, "learning_rate": 0.1,
                                      "grad_updates_per_step": 8.0}, 0.05)
    assert got == {"learning_rate": 0.1, "grad_updates_per_step": 8,
                   "discounting": pytest.approx(math.exp(-0.1), rel=1e-12)}
    assert isinstance(got["grad_updates_per_step"], int)
    assert baselines.trainer_settings({"entropy_cost": 0.01}, None) == {"entropy_cost": 0.01}
    steps, curves = baselines.after_initial_evaluation([0, 10, 20], [[1.0, 2.0, 3.0]])
    assert steps.tolist() == [10, 20] and curves.tolist() == [[2.0, 3.0]]


def test_the_baseline_presets_hold_the_tuned_settings(monkeypatch):
    import json
    import os

    from conftest import ROOT

    from gpguided_jax import config

    for task, algos in config.BASELINE_PRESETS.items():
        with open(os.path.join(ROOT, "docs", "results", "standard", task, "tuning.json")) as f:
            tuning = json.load(f)["methods"]
        for algo, settings in algos.items():
            assert settings == pytest.approx(tuning[algo]["chosen"]), (task, algo)
    assert baselines.preset_settings("paper", "sac", 0.05) == {}  # no tuning: brax's defaults
    # a horizon in seconds becomes brax's discounting at the task's step: exp(-0.05 / 0.5)
    monkeypatch.setitem(config.BASELINE_PRESETS, "tiny", {"ppo": {"horizon": 0.5}})
    got = baselines.preset_settings("tiny", "ppo", 0.05)
    assert got == {"discounting": pytest.approx(math.exp(-0.1), rel=1e-12)}


@pytest.mark.parametrize("args,message", [
    (["sac", "--preset", "paper"], "the paper's pendulum"),
    (["sac", "--env", "gymnax:CartPole-v1"], "discrete action"),
    (["ppo", "--evals", "1"], "num_evals must be >= 2"),
    # tiny preset: 6 updates x 2 episodes x 20 steps = 240, below SAC's 2000-step prefill
    (["sac", "--preset", "tiny", "--env", "gymnax:Pendulum-v1"],
     "a budget of 240 environment steps: it first fills its replay buffer with 2000 steps "
     "(min_replay_size 2000 from 16 environments) and trains only on the steps beyond them; the "
     "smallest budget is 2001 (--steps 2001 or more)"),
    (["sac", "--preset", "tiny", "--env", "gymnax:Pendulum-v1", "--steps", "2000"],
     "the smallest budget is 2001"),
    # ceil(66 / 4) = 17 steps of 4 environments fill the buffer: 68 steps, so 69 at least
    (["sac", "--preset", "tiny", "--env", "gymnax:Pendulum-v1", "--steps", "68", "--set",
      "num_envs=4", "min_replay_size=66"], "with 68 steps (min_replay_size 66 from 4 "
     "environments) and trains only on the steps beyond them; the smallest budget is 69"),
])
def test_bad_baseline_runs_are_refused_in_one_line(args, message, tmp_path, capsys, monkeypatch):
    """One line on stderr, exit status 2, before anything is set up or compiled: no compilation
    cache, no training, no output directory."""
    from gpguided_jax import cli

    def no_run(*args, **kwargs):
        raise AssertionError("a refused run started")

    monkeypatch.setattr(baselines, "train_on_task", no_run)
    monkeypatch.setattr(cli.runtime, "set_compile_cache", no_run)
    out = tmp_path / "out"
    assert cli.main(["baseline", *args, "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and not out.exists()
    assert captured.err.startswith("gpguided baseline: error: ") and message in captured.err
    assert captured.err.count("\n") == 1 and captured.err.endswith("\n")


def test_a_budget_brax_rounds_up_is_reported_as_run(tmp_path, capsys, monkeypatch):
    """PPO on the tiny preset: brax runs whole iterations of 16 x 5 unrolls of 25 steps = 2000
    steps, at least one per each of the 25 intervals between 26 evaluations, so a budget of 240
    runs 50,000 steps. The command passes brax the budget and the settings unchanged, says so
    before the runs, and reports (line and JSON) the steps that brax's evaluations report (here a
    stand-in for brax that returns them)."""
    import json

    from gpguided_jax import cli

    calls = []

    def fake_brax(algorithm, env, num_timesteps, episode_length, seed, **kwargs):
        calls.append((num_timesteps, kwargs))
        steps = 2000 * np.arange(26)
        return baselines.TaskResult(steps, -1000.0 + steps / 100.0, 1.0)

    monkeypatch.setattr(baselines, "train_on_task", fake_brax)
    out = tmp_path / "bl"
    assert cli.main(["baseline", "ppo", "--preset", "tiny", "--env", "gymnax:Pendulum-v1",
                     "--seeds", "2", "--out", str(out), "--compile-cache", "none"]) == 0
    assert [c[0] for c in calls] == [240, 240] and calls[0][1]["num_evals"] == 26
    assert not set(calls[0][1]) & {"num_envs", "unroll_length", "batch_size", "num_minibatches"}
    captured = capsys.readouterr()
    assert ("[ppo] brax's PPO runs whole iterations of 2000 environment steps, 1 in each of its 25 "
            "evaluation intervals: a budget of 240 runs 50000 steps\n") in captured.err
    assert "ppo on gymnax:Pendulum-v1 (50000 steps run for a budget of 240, 2 seeds)" in captured.out
    meta = json.loads((out / "baseline_ppo.json").read_text())
    assert meta["budget"] == 240 and meta["steps_run"] == 50000 and "num_timesteps" not in meta


# ------------------------------------------------------------------------------------------------
# the steps brax runs for a budget, by hand from brax 0.14.2's ppo/train.py and sac/train.py
# ------------------------------------------------------------------------------------------------


def test_ppo_steps_against_a_hand_computation():
    # defaults: an iteration is 16 x 5 unrolls of 25 steps = 2000; 26 evaluations, 25 intervals
    np.testing.assert_array_equal(baselines.evaluation_steps("ppo", 240, 26),
                                  [2000 * i for i in range(26)])
    # ceil(budget / (25 x 2000)) iterations per interval
    for budget, run in [(1, 50_000), (50_000, 50_000), (50_001, 100_000), (99_000, 100_000),
                        (149_850, 150_000)]:
        assert baselines.steps_run("ppo", budget, 26) == run, budget
    # 4 x 2 unrolls of 10 steps, each action repeated twice: 160 steps an iteration; an interval
    # is 3 epochs (num_resets_per_eval) of ceil(1000 / (2 x 160 x 3)) = 2 iterations = 960 steps
    settings = dict(num_envs=4, unroll_length=10, batch_size=4, num_minibatches=2,
                    action_repeat=2, num_resets_per_eval=3)
    np.testing.assert_array_equal(baselines.evaluation_steps("ppo", 1000, 3, settings),
                                  [0, 960, 1920])
    # one evaluation: no initial one, one interval of ceil(3000 / 2000) = 2 iterations
    np.testing.assert_array_equal(baselines.evaluation_steps("ppo", 3000, 1), [4000])
    assert baselines.smallest_budget("ppo") == 1
    with pytest.raises(baselines.BudgetError, match="at least 1"):
        baselines.steps_run("ppo", 0, 26)
    assert baselines.budget_note("ppo", 50_000, 26) is None
    assert baselines.budget_note("ppo", 99_000, 26) == (
        "brax's PPO runs whole iterations of 2000 environment steps, 2 in each of its 25 "
        "evaluation intervals: a budget of 99000 runs 100000 steps")


def test_sac_steps_against_a_hand_computation():
    # defaults: 16 environments; the prefill, ceil(2000 / 16) = 125 steps of 16 = 2000, counts
    assert baselines.smallest_budget("sac") == 2001
    steps = baselines.evaluation_steps("sac", 2001, 26)  # ceil(1 / (25 x 16)) = 1 step a interval
    np.testing.assert_array_equal(steps, [0] + [2000 + 16 * i for i in range(1, 26)])
    # ceil((99,000 - 2000) / 400) = 243 steps of 16 per interval: 2000 + 25 x 243 x 16
    assert baselines.steps_run("sac", 99_000, 26) == 99_200
    assert baselines.steps_run("sac", 100_000, 26) == 100_000
    # 21 evaluations: ceil(268,000 / 320) = 838 steps of 16 per interval
    assert baselines.steps_run("sac", 270_000, 21) == 2000 + 20 * 838 * 16
    # 3 environments, actions repeated twice: the prefill is ceil(10 / 3) = 4 steps of 3 x 2
    settings = dict(num_envs=3, min_replay_size=10, action_repeat=2)
    assert baselines.smallest_budget("sac", settings) == 25
    np.testing.assert_array_equal(baselines.evaluation_steps("sac", 25, 2, settings), [0, 30])
    np.testing.assert_array_equal(baselines.evaluation_steps("sac", 100, 3, settings),
                                  [0, 24 + 42, 24 + 84])  # ceil(76 / 12) = 7 steps of 6
    for budget in (10, 11, 24):  # brax: refused / assertion fails / no gradient step
        with pytest.raises(baselines.BudgetError, match="the smallest budget is 25$") as e:
            baselines.check_budget("sac", budget, settings)
        assert e.value.smallest == 25
    baselines.check_budget("sac", 25, settings)
    assert baselines.budget_note("sac", 2001, 26) == (
        "brax's SAC fills its replay buffer with 2000 environment steps, then steps its 16 "
        "environments once in each of its 25 evaluation intervals: a budget of 2001 runs 2400 "
        "steps")


def test_the_steps_run_agree_with_what_brax_recorded_in_the_studies():
    """The committed study results hold brax's own step counts (its evaluations' steps) of full
    runs; the formulas give them from the budget, for every configuration the tunings tried
    (none of their grids changes the batch sizes), and the tables take them from there."""
    import json
    import os

    from conftest import ROOT

    results = os.path.join(ROOT, "docs", "results")
    for task in ("pendulum-v1", "mountaincar-continuous", "inverted-pendulum",
                 "inverted-double-pendulum"):
        with open(os.path.join(results, "standard", task, "heldout_table.json")) as f:
            table = json.load(f)
        with open(os.path.join(results, "standard", task, "tuning.json")) as f:
            tuning = json.load(f)
        for name in ("ppo", "sac"):
            with np.load(os.path.join(results, "standard", task, "heldout", f"{name}.npz")) as f:
                recorded = f["steps"]
            row = next(r for r in table["rows"] if r["method"] == name)
            assert row["env_steps"] == recorded[-1]
            configurations = [t["settings"] for t in tuning["methods"][name]["tried"]]
            for settings in configurations:
                np.testing.assert_array_equal(
                    baselines.evaluation_steps(name, tuning["env_steps"], len(recorded),
                                               settings), recorded, err_msg=f"{task} {name}")
    with open(os.path.join(results, "exploration", "baselines.json")) as f:
        runs = json.load(f)["runs"]
    with open(os.path.join(results, "exploration", "baseline_tuning.json")) as f:
        budget = json.load(f)["env_steps"]
    for name in ("ppo", "sac"):
        with np.load(os.path.join(results, "exploration", "heldout", f"{name}.npz")) as f:
            recorded = f["steps"]
        np.testing.assert_array_equal(
            baselines.evaluation_steps(name, budget, len(recorded), runs[name]["settings"]),
            recorded, err_msg=name)


@pytest.mark.training
def test_gpguided_baseline_runs_sac_on_a_gymnax_task(tmp_path, capsys):
    """`gpguided baseline sac` at tiny sizes on gymnax's Pendulum-v1 with the tiny preset's budget:
    the files it writes agree with each other and with its summary line."""
    import json

    from gpguided_jax import cli

    out = tmp_path / "bl"
    assert cli.main(["baseline", "sac", "--preset", "tiny", "--env", "gymnax:Pendulum-v1",
                     "--seeds", "1", "--evals", "3", "--hidden", "8", "--set", "num_envs=4",
                     "batch_size=16", "min_replay_size=66", "max_replay_size=1000",
                     "num_eval_envs=4", "--out", str(out), "--compile-cache", "none"]) == 0
    meta = json.loads((out / "baseline_sac.json").read_text())
    data = np.load(out / "baseline_sac.npz")
    assert meta["env"] == "gymnax:Pendulum-v1" and meta["seeds"] == [1000]
    assert meta["settings"]["min_replay_size"] == 66 and meta["settings"]["num_envs"] == 4
    assert data["returns"].shape == (1, 3) and np.all(np.isfinite(data["returns"]))
    # tiny preset: 6 updates x 2 episodes x 20 steps = 240. brax fills the replay buffer with
    # ceil(66 / 4) = 17 steps of 4 environments = 68, then runs ceil((240 - 68) / (2 x 4)) = 22
    # steps of 4 in each of the 2 intervals: evaluations at 68 + 88 = 156 and 244
    np.testing.assert_array_equal(data["env_steps"], [0, 156, 244])
    assert meta["budget"] == 240 and meta["steps_run"] == 244
    final = float(data["returns"][0, -1])  # 10% of 2 evaluations: the last one
    assert meta["summary"]["final_return_iqm"] == pytest.approx(final)
    captured = capsys.readouterr()
    assert "sac on gymnax:Pendulum-v1 (244 steps run for a budget of 240, 1 seed)" in captured.out
    assert f"final return IQM {final:.1f}" in captured.out
    assert "a budget of 240 runs 244 steps" in captured.err


def test_importing_the_baselines_prints_nothing():
    """brax's import of mujoco prints on stdout that its GPU backend is missing; the command
    line's stdout (a table, or `gpguided bench`'s JSON) must not carry it."""
    proc = run_script(["-c", "import gpguided_jax.baselines, gpguided_jax.tasks"], fast_compile=False)
    assert proc.stdout == "" and proc.stderr == ""
