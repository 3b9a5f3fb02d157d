"""The task interface (gpguided_jax.tasks): each adapter against its environment's own step, the
masking of early ends, the discount as a horizon, steps to a threshold, the refusals, and tiny runs
on a gymnax and a brax environment from the command line."""

import json
import math
import os

import gymnax  # in the dev extra and the lock: the suite runs the gymnax tasks, never skips them
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, run_script

from gpguided_jax import cli, config, estimators, summaries, tasks, train


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "MountainCarContinuous-v0"])
def test_gymnax_task_steps_as_gymnax_does(env_id):
    """Random actions through the task and through gymnax's own step_env: the same observations,
    rewards and ends, step for step (the task adds nothing but the dtype here: the car's wall,
    which it adds, is beyond these 60 steps; against gymnasium: test_task_reference.py)."""
    task = tasks.make_task(f"gymnax:{env_id}")
    env, params = gymnax.make(env_id)
    cfg = config.preset("tiny", env=task.name, dtype="float32")
    keys = jax.random.split(jax.random.key(7), 60)
    actions = jax.random.uniform(jax.random.key(8), (60,), jnp.float32, -3.0, 3.0)

    def ours(key0):
        s, o = task.reset(key0, cfg)

        def body(s, ka):
            s, o, r, d = task.step(ka[0], s, ka[1], cfg)
            return s, (o, r, d)
        return o, jax.lax.scan(body, s, (keys, actions))[1]

    def theirs(key0):
        o, s = env.reset_env(key0, params)

        def body(s, ka):
            o, s, r, d, _ = env.step_env(ka[0], s, ka[1][None], params)
            return s, (o, r, d)
        return o, jax.lax.scan(body, s, (keys, actions))[1]

    o0, (obs, rew, done) = jax.jit(ours)(jax.random.key(3))
    p0, (pobs, prew, pdone) = jax.jit(theirs)(jax.random.key(3))
    # gymnax computes in the default float dtype (float64 here, x64 being on); the task hands the
    # observations and rewards over in the config's dtype
    f32 = lambda a: np.asarray(a).astype(np.float32)  # noqa: E731
    np.testing.assert_array_equal(o0, f32(p0))
    np.testing.assert_array_equal(obs, f32(pobs))
    np.testing.assert_array_equal(rew, f32(prew).reshape(rew.shape))
    np.testing.assert_array_equal(done, pdone)
    assert task.obs_dim == obs.shape[-1] and task.feature_dim == task.obs_dim + 1
    assert task.max_action == float(env.action_space(params).high)


_BRAX_ADAPTER_CHECK = """
import jax, jax.numpy as jnp, numpy as np
from brax import envs
from gpguided_jax import tasks

adapter = tasks._brax_adapter("inverted_pendulum")
env = envs.get_environment("inverted_pendulum")
actions = jnp.array([0.3, -0.8, 1.0, 0.1, -1.0, 2.5], jnp.float32)

def both(key):
    s, _ = adapter.reset(key)
    b = env.reset(key)

    def body(carry, a):
        s, b = carry
        s, o, r, d = adapter.step(key, s, a)
        b = env.step(b, jnp.clip(a, -1.0, 1.0)[None])
        return (s, b), (o, r, d, b.obs, b.reward, b.done)
    return jax.lax.scan(body, (s, b), actions)[1]

o, r, d, bo, br, bd = jax.jit(both)(jax.random.key(0))
np.testing.assert_array_equal(o, bo)
np.testing.assert_array_equal(r, br)
np.testing.assert_array_equal(d, bd > 0.5)
assert adapter.obs_dim == 4 and adapter.max_action == 1.0 and adapter.dt == env.dt
print("same")
"""


@pytest.mark.slow
def test_brax_adapter_steps_as_brax_does():
    """brax's inverted pendulum through the adapter and through brax's own Env.step (actions in
    brax's range [-1, 1]; beyond it the adapter clips): the same observations, rewards and ends.
    In a subprocess compiling at XLA's level 0, where brax's physics compiles twice as fast (the
    two sides are compiled alike, so their agreement is still exact)."""
    proc = run_script(["-c", _BRAX_ADAPTER_CHECK], fast_compile="level0")
    assert proc.stdout.strip().endswith("same")


def _falling_task(limit=1.025):
    """A task that ends once x > limit: x' = x + a dt + 0.5 dt, reward 1 per step alive."""
    dt = 0.1

    def reset(key, cfg):
        x = jnp.zeros((1,), cfg.dtype)
        return x, x

    def step(key, x, a, cfg):
        x = x + (jnp.clip(a, -1, 1) + 0.5) * dt
        return x, x, jnp.ones((), cfg.dtype), x[0] > limit

    def features(o, a):
        return jnp.concatenate([o, jnp.reshape(a, (1,)).astype(o.dtype)])

    def controller(name):
        return tasks._observation_controller(name, 1.0, np.zeros(1), np.ones(1), np.zeros((2, 1)),
                                             1.0)

    return tasks.Task(name="test:falling", obs_dim=1, dt=dt, max_action=1.0, episode_length=40,
                      terminates=True, threshold=10.0, reset=reset, step=step, features=features,
                      feature_dim=2, make_controller=controller, obs_centre=np.zeros(1),
                      obs_scale=np.ones(1))


def test_steps_after_an_early_end_are_masked():
    """After the end: rewards 0, scores 0, the environment frozen, and the GP takes in none of
    those steps; the records count the return up to the end."""
    tasks.register(_falling_task())
    cfg = config.preset("tiny", method="gp_pg", env="test:falling", episode_length=40,
                        eval_episodes=2)
    prog = train.make_program(cfg)
    prior = train.GPPrior(train.kernels.make_kernel_params(jnp.ones(2), 1.0, 0.1), jnp.zeros(()))
    state = train.initial_state(prog, jax.random.key(0), cfg, prior)
    ctx = train.policy_context(cfg, state.gp, state.kernel)
    ep = jax.jit(lambda k: train.rollout(prog, k, state.theta, ctx, prog.policy, cfg))(
        jax.random.key(1))
    alive = np.asarray(ep.alive)
    n = int(alive.sum())
    assert 10 <= n < 40 and alive[:n].all() and not alive[n:].any()  # ends at x > 1.025
    assert np.asarray(ep.states)[n - 1, 0] <= 1.025 < np.asarray(ep.next_states)[n - 1, 0]
    np.testing.assert_array_equal(np.asarray(ep.rewards), alive.astype(float))
    frozen = np.asarray(ep.next_states)[n - 1]  # the environment stays where it ended
    assert np.all(np.asarray(ep.next_states)[n:] == frozen) and np.all(np.asarray(ep.states)[n:] == frozen)
    for leaf in jax.tree_util.tree_leaves(ep.scores):
        assert np.all(np.asarray(leaf)[n:] == 0) and np.any(np.asarray(leaf)[:n] != 0)
    returns = estimators.discounted_returns(ep.rewards, cfg.discount)
    # compiled: op by op, every operation of the GP's loops would be compiled on its own
    gp, fired, _ = jax.jit(lambda s, e, r: train._take_in(prog, cfg, s, s.gp, e, r))(state, ep,
                                                                                    returns)
    assert int(fired) == 0
    bvs = np.asarray(gp.basis_vectors)[np.asarray(gp.mask)]
    assert len(bvs) > 0 and np.all(bvs[:, 0] <= 1.025)  # no basis vector from beyond the end
    success, reward, ret = jax.jit(lambda k: train.evaluate(prog, k, state.theta, cfg))(
        jax.random.key(2))
    # c(s) = 0 at the zero initial controller: x grows by 0.05 a step and passes 1.025 at step 21
    assert float(ret) == 21.0 and float(reward) == 1.0 and float(success) == 1.0


def test_an_episode_that_ends_restarts_in_its_slots():
    """`episode_end='restart'`: after each end the environment starts again, every slot has its
    reward and score, each return-to-go stops at its episode's end (against a NumPy recursion),
    the GP takes in pairs of the later episodes, the records count returns per episode, and the
    evaluation still runs one episode."""
    tasks.register(_falling_task())
    h = 80
    cfg = config.preset("tiny", method="gp_pg", env="test:falling", episode_length=h,
                        eval_episodes=2, episode_end="restart", discount=0.9)
    prog = train.make_program(cfg)
    prior = train.GPPrior(train.kernels.make_kernel_params(jnp.ones(2), 1.0, 0.1), jnp.zeros(()))
    state = train.initial_state(prog, jax.random.key(0), cfg, prior)
    ctx = train.policy_context(cfg, state.gp, state.kernel)
    eps = jax.jit(jax.vmap(lambda k: train.rollout(prog, k, state.theta, ctx, prog.policy, cfg)))(
        jax.random.split(jax.random.key(1), 2))
    assert eps.alive is None
    ep = jax.tree_util.tree_map(lambda v: v[0], eps)
    ends = np.asarray(ep.ends)
    x, x_next = np.asarray(ep.states)[:, 0], np.asarray(ep.next_states)[:, 0]
    assert ends.sum() >= 2  # each episode ends after about 21 steps
    np.testing.assert_array_equal(ends, x_next > 1.025)  # an end exactly where the task ends it
    starts = np.concatenate([[True], ends[:-1]])
    np.testing.assert_array_equal(x[starts], 0.0)  # each episode starts from the reset
    np.testing.assert_array_equal(np.asarray(ep.rewards), 1.0)  # every slot is a step
    for leaf in jax.tree_util.tree_leaves(ep.scores):
        assert np.all(np.any(np.asarray(leaf).reshape(h, -1) != 0, axis=1))
    returns = np.asarray(train.episode_returns(ep, cfg))
    expected, ret = np.zeros(h), 0.0
    for t in range(h - 1, -1, -1):
        ret = 1.0 + (0.0 if ends[t] else 0.9 * ret)
        expected[t] = ret
    np.testing.assert_allclose(returns, expected, rtol=1e-12)
    gp, fired, _ = jax.jit(lambda s, e, r: train._take_in(prog, cfg, s, s.gp, e, r))(  # compiled
        state, ep, jnp.asarray(returns))
    assert int(fired) == 0
    bvs = np.asarray(gp.basis_vectors)[np.asarray(gp.mask)][:, 0]
    later = x[np.flatnonzero(ends)[0] + 2:]  # the second episode on, past its start
    assert np.isclose(bvs[:, None], later[None, :], rtol=0, atol=1e-12).any()
    # the records' mean return: per episode (the last one cut at the slots' end), not per slots
    all_ends = np.asarray(eps.ends)
    episodes = all_ends.sum() + (~all_ends[:, -1]).sum()
    assert float(train.mean_episode_return(eps)) == pytest.approx(2 * h / episodes, rel=1e-12)
    success, reward, ret = jax.jit(lambda k: train.evaluate(prog, k, state.theta, cfg))(
        jax.random.key(2))
    assert float(ret) == 21.0 and float(success) == 1.0  # one episode, as with masking
    # a training episode succeeds when one of the episodes in its slots reaches the threshold
    # (10, a reward of 1 per step), not their total
    def success_of(ends):
        return bool(train.episode_success(prog, ep.next_states, cfg, ep.rewards,
                                          jnp.asarray(ends)))

    assert not success_of(np.arange(h) % 5 == 4)  # sixteen episodes of 5 steps
    assert success_of(np.arange(h) % 10 == 9)  # eight of 10
    assert success_of(np.arange(h) == 4)  # one of 5, then one of 75 cut at the slots' end


def test_discount_as_a_horizon_in_seconds():
    assert tasks.discount_for_horizon(0.5, 0.005) == pytest.approx(math.exp(-0.01))
    assert tasks.horizon_of_discount(0.99, 0.005) == pytest.approx(0.4975, rel=1e-3)
    assert tasks.horizon_of_discount(0.99, 0.05) == pytest.approx(4.975, rel=1e-3)
    cfg = config.preset("swingup", method="gp_pg", discount_horizon=2.0)
    assert float(cfg.discount) == pytest.approx(math.exp(-0.005 / 2.0))
    cfg = config.preset("pendulum-v1", method="gp_pg")
    assert float(cfg.discount) == pytest.approx(math.exp(-0.05 / 1.0))
    assert float(config.preset("pendulum-v1", discount=0.9).discount) == pytest.approx(0.9)
    with pytest.raises(ValueError, match="horizon must be > 0"):
        config.preset("tiny", discount_horizon=0.0)


def test_steps_to_threshold_counts_the_steps_spent():
    budget = summaries.TaskBudget(steps_per_update=1000, fit_steps=2000, threshold=-200.0)
    returns = np.array([[-900, -300, -150, -100], [-900, -800, -700, -600]], float)
    reach = summaries.steps_to_threshold(returns, budget)
    assert reach[0] == 2000 + 2 * 1000 and np.isnan(reach[1])
    explore = budget._replace(return_record="mean_return")
    assert summaries.steps_to_threshold(returns, explore)[0] == 2000 + 3 * 1000
    none = summaries.steps_to_threshold(returns, budget._replace(threshold=None))
    assert np.isnan(none).all()


@pytest.mark.parametrize("env,message", [
    ("gymnax:CartPole-v1", "gymnax:CartPole-v1 has a discrete action space"),
    ("brax:ant", "brax:ant has 8 continuous actions, not one"),
    ("mujoco:Pendulum", "unknown environment 'mujoco:Pendulum'"),
    ("gymnax:NoSuchEnv-v0", "unknown environment 'gymnax:NoSuchEnv-v0'"),
])
def test_unsupported_environments_are_refused_in_one_line(env, message, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["reproduce", "--preset", "tiny", "--env", env, "--compile-cache", "none"])
    err = str(exc.value.code)
    assert message in err and "gymnax:Pendulum-v1" in err and "\n" not in err


# brax's physics compiles slowly on a CPU: its run trains REINFORCE alone, which needs no
# hyperparameter fit (one program fewer with brax's step in it); the GP methods on an environment
# that ends early are the car's run here and test_steps_after_an_early_end_are_masked
@pytest.mark.cli
@pytest.mark.parametrize("env,methods", [("gymnax:MountainCarContinuous-v0", ["reinforce", "gp_pg"]),
                                         ("brax:inverted_pendulum", ["reinforce"])])
def test_a_tiny_run_on_a_standard_environment_from_the_command_line(env, methods, tmp_path):
    """`gpguided reproduce --env ... --preset tiny`: the summary has the task's return columns,
    returns within what the environment can give, and the records are finite."""
    out = tmp_path / "run"
    run_script(["-m", "gpguided_jax.cli", "reproduce", "--preset", "tiny", "--env", env,
                "--seeds", "2", "--methods", *methods, "--out", out])
    import csv
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [r["method"] for r in rows] == methods
    res = np.load(out / "results.npz")
    ret = res["mean_return"]
    assert np.isfinite(ret).all()
    length = config.preset("tiny").episode_length
    if env.startswith("brax"):  # 1 per step until the pole falls
        assert np.all((ret >= 1) & (ret <= length))
    else:  # -0.1 a^2 per step, +100 at the goal
        assert np.all(ret <= 100)
    cfg = config.preset("tiny", method="gp_pg")
    for i, r in enumerate(rows):
        assert r["return_of"] == "mean_return"  # the tiny preset evaluates no deterministic episodes
        # the last 10% of 6 updates is the last one; the mean over the two seeds
        assert float(r["final_return_mean"]) == pytest.approx(float(ret[i, :, -1].mean()), rel=1e-12)
        fit = cfg.hyperfit_episodes * length if r["method"] == "gp_pg" else 0
        assert int(r["env_steps"]) == fit + cfg.num_updates * cfg.episodes_per_update * length


@pytest.mark.parametrize("task,dt", [("pendulum-v1", 0.05), ("mountaincar-continuous", 1.0),
                                     ("inverted-pendulum", 0.04),
                                     ("inverted-double-pendulum", 0.02)])
def test_the_standard_presets_hold_the_tuned_settings(task, dt):
    """`gpguided reproduce --preset <task>` runs each method as the tuning chose
    (docs/results/standard/<task>/tuning.json; its horizons are the presets' discount_horizon),
    under the exploration it chose after (tests/test_standard_tasks.py checks those fields)."""
    with open(os.path.join(ROOT, "docs", "results", "standard", task, "tuning.json")) as f:
        tuning = json.load(f)
    tuned = [m for m in tuning["methods"] if m in config.METHODS]  # the baselines apart
    assert set(config.PAPER_METHODS) <= set(tuned)
    for method in tuned:
        chosen = {("discount_horizon" if k == "horizon" else k): v
                  for k, v in tuning["methods"][method]["chosen"].items()}
        preset = config.METHOD_PRESETS[task][method]
        assert {k: preset.get(k) for k in chosen} == pytest.approx(chosen), method
        if task.startswith("inverted"):
            # building a brax task compiles its physics (a quarter of a minute); that the preset
            # applies these settings is checked on the gymnax tasks
            continue
        cfg = config.preset(task, method=method)
        for field, value in preset.items():  # the exploration's fields too
            if isinstance(value, str):
                assert cfg.value(field) == value, (method, field)
            elif field != "discount_horizon":
                assert float(cfg.value(field)) == pytest.approx(value), (method, field)
        horizon = chosen.get("discount_horizon", config.PRESETS[task]["discount_horizon"])
        assert float(cfg.discount) == pytest.approx(math.exp(-dt / horizon))
