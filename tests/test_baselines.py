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


def test_train_ppo_tiny_budget_returns_finite_curve():
    """brax's own PPO trainer (`ppo.train`) on `brax_env.PendulumEnv`, through `train_ppo`: the
    environment's brax interface end to end (it was a test of its own in test_brax_env.py)."""
    params = pendulum.make_params(start_mean=(math.pi - 0.5, 0.0), start_std=(0.1, 0.1))
    per_iter = baselines.ppo_steps_per_iteration(4, 10, 4, 2)
    result = baselines.train_ppo(
        params,
        2 * per_iter,
        20,
        seed=0,
        num_evals=3,
        num_envs=4,
        unroll_length=10,
        batch_size=4,
        num_minibatches=2,
        num_updates_per_batch=1,
        num_eval_envs=4,
        hidden_layers=(8,),
    )
    np.testing.assert_array_equal(result.env_steps, [0, per_iter, 2 * per_iter])
    assert result.reward_per_step.shape == (3,)
    assert np.all(np.isfinite(result.reward_per_step)) and np.all(result.reward_per_step < 0.5)
    assert result.wall_time > 0
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(result.params))
    rate = baselines.ppo_success_rate(
        jax.random.PRNGKey(1), result, params, 20, 3, deterministic=True, hold_time=0.02
    )
    assert 0.0 <= rate <= 1.0
    assert jax.config.jax_enable_x64  # train_ppo leaves the package's float64 setting as it was


def test_train_sac_tiny_budget_returns_finite_curve_and_success():
    params = pendulum.make_params(start_mean=(0.0, 0.0), start_std=(0.1, 0.1))
    result = baselines.train_sac(params, 400, 250, seed=0, num_evals=2, num_envs=4,
                                 batch_size=16, min_replay_size=64, max_replay_size=1000,
                                 num_eval_envs=4, hidden_layers=(8,))
    assert result.env_steps[0] == 0 and result.env_steps[-1] >= 400
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
])
def test_bad_baseline_runs_are_refused_in_one_line(args, message, tmp_path):
    from gpguided_jax import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["baseline", *args, "--out", str(tmp_path), "--compile-cache", "none"])
    assert message in str(e.value) and "\n" not in str(e.value)


def test_gpguided_baseline_runs_sac_on_a_gymnax_task(tmp_path, capsys):
    """`gpguided baseline sac` at tiny sizes on gymnax's Pendulum-v1 with the tiny preset's budget:
    the files it writes agree with each other and with its summary line."""
    import json

    from gpguided_jax import cli

    out = tmp_path / "bl"
    assert cli.main(["baseline", "sac", "--preset", "tiny", "--env", "gymnax:Pendulum-v1",
                     "--seeds", "1", "--evals", "3", "--hidden", "8", "--set", "num_envs=4",
                     "batch_size=16", "min_replay_size=64", "max_replay_size=1000",
                     "num_eval_envs=4", "--out", str(out), "--compile-cache", "none"]) == 0
    meta = json.loads((out / "baseline_sac.json").read_text())
    data = np.load(out / "baseline_sac.npz")
    assert meta["env"] == "gymnax:Pendulum-v1" and meta["seeds"] == [1000]
    assert meta["settings"]["min_replay_size"] == 64 and meta["settings"]["num_envs"] == 4
    assert data["returns"].shape == (1, 3) and np.all(np.isfinite(data["returns"]))
    assert data["env_steps"][0] == 0 and data["env_steps"][-1] >= meta["num_timesteps"]
    # tiny preset: 6 updates x 2 episodes x 20 steps
    assert meta["num_timesteps"] == 6 * 2 * 20
    final = float(data["returns"][0, -1])  # 10% of 2 evaluations: the last one
    assert meta["summary"]["final_return_iqm"] == pytest.approx(final)
    assert f"final return IQM {final:.1f}" in capsys.readouterr().out


def test_importing_the_baselines_prints_nothing():
    """brax's import of mujoco prints on stdout that its GPU backend is missing; the command
    line's stdout (a table, or `gpguided bench`'s JSON) must not carry it."""
    proc = run_script(["-c", "import gpguided_jax.baselines, gpguided_jax.tasks"], fast_compile=False)
    assert proc.stdout == "" and proc.stderr == ""
