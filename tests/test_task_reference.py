"""The standard tasks against the environments their published reference numbers come from.

The gymnax tasks step as gymnasium's Pendulum-v1 and MountainCarContinuous-v0 do (rl-baselines3-zoo
measures on those): the task's own `reset` and `step` (`tasks.make_task`) beside gymnasium's
environment (`gymnasium.make(id).unwrapped`, set to the task's start state), under the same actions:
random ones (beyond the action bound too, where both clip), actions held at full left and full
right, and bang-bang actions that push along the velocity. The car's held and bang-bang episodes
hit the left wall and reach the goal (checked): gymnasium stops the car at the wall, gymnax 1.0.1's
step does not, and the task applies gymnasium's rule (`tasks.gymnasium_car_wall`).

The brax pendulums are brax's own models, not gymnasium's MuJoCo InvertedPendulum-v5 and
InvertedDoublePendulum-v5; the facts that docs/standard_tasks.md ("What each task is") gives
for both (control time step, integrator, action, reward, end) are checked on both environments'
definitions, without building brax's physics: brax's `step` runs on hand-made physics states.

Cheap by construction: per gymnax task, one compiled program of the episodes (the task's reset and a
`lax.scan` of its step over a fixed action sequence, vmapped over the episodes) and a small one of
the start states, cached for the module; gymnasium steps in NumPy.
"""

import contextlib
import functools
import importlib.util
import io
import sys
import types
import warnings

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from gymnax.environments.classic_control.continuous_mountain_car import EnvState

from gpguided_jax import config, tasks

# task -> (gymnasium's id, the gymnax state's fields that gymnasium's `env.state` holds, in order)
GYMNAX = {
    "gymnax:Pendulum-v1": ("Pendulum-v1", ("theta", "theta_dot")),
    "gymnax:MountainCarContinuous-v0": ("MountainCarContinuous-v0", ("position", "velocity")),
}
# The episodes compared, one row of actions each: random actions in [-1.5 u_max, 1.5 u_max]
# (clipped by both environments); actions held at the bound: the whole episode left, the whole
# episode right, and right for 10 steps, left up to step 70, then right (which takes the car from
# any start to the left wall and then to the goal); and bang-bang feedback (+u_max while the
# velocity is >= 0, else -u_max) that pumps energy in, taking the car to the wall and the goal
# too, and the pendulum to its speed limit. The feedback runs on gymnasium's state; the actions it
# takes are then replayed, as a fixed sequence, through the task.
KINDS = ("random",) * 4 + ("held left", "held right", "held right, left, right") + ("bang-bang",) * 3
# The tolerance of a compared quantity at step t (t = 0 for the first step):
#   |task - gymnasium| <= TOL_STEPS_FACTOR * (t + 1) * eps * scale,
# with scale the largest magnitude the quantity takes in gymnasium's episode and eps the machine
# epsilon of the coarsest dtype that enters the comparison: the actions' (float32, gymnasium's
# action space; both environments compute the action's terms of the step in it), gymnasium's state
# (float32 for the car, which gymnasium rounds to float32 at every step; float64 for the pendulum)
# and the two arrays compared (gymnasium's observations are float32). Here that is float32's
# epsilon throughout. Each step rounds each side at most once at that precision (one rounding to
# float32 moves a value by at most eps / 2 of its magnitude), and these episodes carry a rounding
# forward about unchanged, so the difference grows at most about linearly in the steps taken. The
# factor 4 is a margin over that: the largest |task - gymnasium| / ((t + 1) eps scale) in these
# episodes is about 0.3. A step of different physics shows as a difference of the order of the
# quantity itself: the car's wall rule, its whole velocity (about 1e-2, against a tolerance below
# 1e-4 in the steps where the wall is reached).
TOL_STEPS_FACTOR = 4.0


def _eps(*dtypes):
    return max(float(np.finfo(d).eps) for d in dtypes)


def _gymnasium_episode(env, start, kind, actions, u_max):
    """Steps gymnasium's environment from `start` ([x, v], float64 as its reset leaves it) until it
    terminates or `actions` run out; the bang-bang kind replaces `actions` by its feedback.
    Returns the actions taken (float32) and per step the observation, state, reward, termination."""
    env.state = np.asarray(start, np.float64)
    taken, obs, states, rewards, ends = [], [], [], [], []
    for t in range(len(actions)):
        a = (u_max if env.state[1] >= 0 else -u_max) if kind == "bang-bang" else actions[t]
        a = np.float32(a)
        o, r, terminated, truncated, _ = env.step(np.array([a], np.float32))
        assert not truncated  # the unwrapped environment: the time limit is the caller's
        taken.append(a)
        obs.append(o)
        states.append(np.array(env.state, np.float64))
        rewards.append(r)
        ends.append(terminated)
        if terminated:
            break
    taken = np.concatenate([taken, np.zeros(len(actions) - len(taken), np.float32)])
    return types.SimpleNamespace(actions=taken, obs=np.array(obs), states=np.array(states),
                                 rewards=np.array(rewards, np.float64), ends=np.array(ends),
                                 state_dtype=env.state.dtype)


@functools.cache
def _episodes(name):
    """Both environments' episodes of `KINDS` for a gymnax task (cached: one compilation each)."""
    gym_id, fields = GYMNAX[name]
    task = tasks.make_task(name)
    cfg = config.preset("tiny", env=name)  # the library's default float64, as the presets run
    n, length = len(KINDS), task.episode_length
    keys = jax.random.split(jax.random.key(20260101), n)

    def reset(key):
        env_state, _ = task.reset(key, cfg)
        return jnp.stack([getattr(env_state, f) for f in fields])

    def episode(key, actions):
        env_state, _ = task.reset(key, cfg)

        def body(env_state, a):
            env_state, obs, reward, done = task.step(key, env_state, a, cfg)
            return env_state, (jnp.stack([getattr(env_state, f) for f in fields]), obs, reward, done)
        return jax.lax.scan(body, env_state, actions)[1]

    starts = np.asarray(jax.jit(jax.vmap(reset))(keys))
    rng = np.random.default_rng(7)
    u = task.max_action
    plan = {"random": lambda: rng.uniform(-1.5 * u, 1.5 * u, length),
            "held left": lambda: np.full(length, -u), "held right": lambda: np.full(length, u),
            "held right, left, right": lambda: np.where((np.arange(length) >= 10)
                                                        & (np.arange(length) < 70), -u, u),
            "bang-bang": lambda: np.zeros(length)}
    env = gymnasium.make(gym_id).unwrapped
    theirs = [_gymnasium_episode(env, s, kind, plan[kind]().astype(np.float32), u)
              for s, kind in zip(starts, KINDS)]
    actions = jnp.asarray(np.stack([e.actions for e in theirs]))
    states, obs, rewards, done = map(np.asarray, jax.jit(jax.vmap(episode))(keys, actions))
    ours = [types.SimpleNamespace(states=states[i], obs=obs[i], rewards=rewards[i], ends=done[i])
            for i in range(n)]
    return task, gymnasium.spec(gym_id), env, ours, theirs


def _check_close(what, ours, theirs, eps):
    """`ours` against `theirs` ((steps, ...)) within the module's tolerance; the message names the
    first step beyond it."""
    ours, theirs = np.asarray(ours, np.float64), np.asarray(theirs, np.float64)
    steps = np.arange(1, len(theirs) + 1).reshape((-1,) + (1,) * (theirs.ndim - 1))
    scale = np.max(np.abs(theirs), axis=0)
    tol = TOL_STEPS_FACTOR * steps * eps * scale
    bad = np.abs(ours - theirs) > tol
    if bad.any():
        t = int(np.argwhere(bad)[0][0])
        raise AssertionError(f"{what}, step {t}: task {ours[t]}, gymnasium {theirs[t]}, "
                             f"difference {np.abs(ours[t] - theirs[t])} > tolerance {tol[t]}")


@pytest.mark.parametrize("name", list(GYMNAX))
def test_a_gymnax_task_steps_as_gymnasium_does(name):
    """Observations, the states they come from, rewards and episode ends of the task equal
    gymnasium's, step for step up to gymnasium's end, within float32 rounding (the tolerance
    above); the episode length is gymnasium's time limit."""
    task, spec, env, ours, theirs = _episodes(name)
    assert task.episode_length == spec.max_episode_steps
    if name == "gymnax:MountainCarContinuous-v0":
        # the episodes reach both places where the car's rules act: the left wall, then the goal
        for kind, e in zip(KINDS, theirs):
            if kind in ("held right, left, right", "bang-bang"):
                assert np.any(e.obs[:, 0] == np.float32(env.min_position)) and e.ends[-1], kind
    for i, (kind, o, g) in enumerate(zip(KINDS, ours, theirs)):
        n = len(g.rewards)
        eps = _eps(g.actions.dtype, g.state_dtype, o.obs.dtype, g.obs.dtype, o.rewards.dtype,
                   o.states.dtype)
        where = f"{name}, episode {i} ({kind}, {n} steps)"
        _check_close(f"{where}: observation", o.obs[:n], g.obs, eps)
        _check_close(f"{where}: state", o.states[:n], g.states, eps)
        _check_close(f"{where}: reward", o.rewards[:n], g.rewards, eps)
        np.testing.assert_array_equal(o.ends[:n], g.ends, err_msg=f"{where}: episode end")


def test_the_baselines_car_steps_as_gymnasium_does():
    """brax_env.GymnaxEnv, on which brax's PPO and SAC train, steps the car as gymnasium does: into
    the left wall, where the car stops, and away from it."""
    from gpguided_jax import brax_env  # imported here: it imports brax

    gym_id = GYMNAX["gymnax:MountainCarContinuous-v0"][0]
    env, gym_env = brax_env.GymnaxEnv(gym_id), gymnasium.make(gym_id).unwrapped
    # (position, velocity, action (the car's bound is 1), whether the step ends at the wall)
    cases = [(-1.18, -0.05, -1.0, True), (-1.18, -0.01, 1.0, False), (-0.5, 0.01, 0.3, False)]

    def step(position, velocity, action):
        car = EnvState(position=position, velocity=velocity, time=0)
        before = brax_env.State(pipeline_state=car, obs=jnp.zeros(2, jnp.float32),
                                reward=jnp.zeros(()), done=jnp.zeros(()), metrics={},
                                info={"rng": jax.random.key(1)})
        after = env.step(before, jnp.reshape(action, (1,)))
        return after.obs, after.reward

    p, v, a, _ = (np.array(c) for c in zip(*cases))
    obs, rewards = jax.jit(jax.vmap(step))(p, v, a.astype(np.float32))
    for (position, velocity, action, at_wall), o, r in zip(cases, np.asarray(obs), np.asarray(rewards)):
        gym_env.state = np.array([position, velocity])
        gym_obs, gym_reward, _, _, _ = gym_env.step(np.array([action], np.float32))
        assert (tuple(gym_obs) == (np.float32(gym_env.min_position), 0.0)) == at_wall
        np.testing.assert_allclose(o, gym_obs, rtol=1e-6, atol=1e-9)
        assert float(r) == pytest.approx(gym_reward, rel=1e-6)


# ------------------------------------------------------------------------------------------------
# brax's pendulums beside gymnasium's MuJoCo ones: the definitions, without brax's physics.
# ------------------------------------------------------------------------------------------------

def _brax_env(name):
    """brax's environment, built without compiling or running its physics (its `step` is run below
    on hand-made physics states, `pipeline_step` replaced)."""
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Brax System, piplines")
        from brax import envs

        return envs.get_environment(name)


def _brax_step(env, action, **physics):
    """brax's `env.step` from a physics state with the given fields (q, qd, x), its physics step
    replaced by one that records the control it is given and leaves the state as it is. Returns
    brax's new reward, end and observation, and that control (compiled as one small program: JAX
    would otherwise compile each of the step's operations on its own)."""
    from brax.envs.base import State

    def step(action):
        controls = []

        def pipeline_step(pipeline_state, ctrl):
            controls.append(ctrl)
            return pipeline_state

        env.pipeline_step = pipeline_step
        before = State(pipeline_state=types.SimpleNamespace(**physics), obs=jnp.zeros(1),
                       reward=jnp.zeros(()), done=jnp.zeros(()), metrics={}, info={})
        after = env.step(before, jnp.reshape(action, (1,)))
        return after.reward, after.done, after.obs, controls[0]

    reward, done, obs, control = jax.jit(step)(jnp.float32(action))
    return types.SimpleNamespace(reward=float(reward), done=bool(done), obs=np.asarray(obs)), \
        np.asarray(control)


def _brax_xml_integrator(name):
    from etils import epath

    path = epath.resource_path("brax") / f"envs/assets/{name}.xml"
    return mujoco.MjModel.from_xml_path(str(path)).opt.integrator


@pytest.fixture(scope="module")
def mujoco_pendulums():
    """gymnasium's InvertedPendulum-v5 and InvertedDoublePendulum-v5, unwrapped. gymnasium's MuJoCo
    package imports imageio, which it needs only to save rendered frames and which the lock leaves
    out (it comes with gymnasium's [mujoco] extra): a stand-in module lets the package load where
    imageio is missing; nothing here renders."""
    with pytest.MonkeyPatch.context() as mp:
        if importlib.util.find_spec("imageio") is None:
            mp.setitem(sys.modules, "imageio", types.ModuleType("imageio"))
        return {name: gymnasium.make(f"{name}-v5").unwrapped
                for name in ("InvertedPendulum", "InvertedDoublePendulum")}


def _gymnasium_mujoco_step(env, qpos, qvel):
    env.reset(seed=0)
    env.set_state(np.asarray(qpos, np.float64), np.asarray(qvel, np.float64))
    _, reward, terminated, truncated, _ = env.step(np.zeros(1, np.float32))
    assert not truncated
    return reward, terminated


def test_brax_inverted_pendulum_beside_gymnasium_v5(mujoco_pendulums):
    """The same control step, action range and end; the reward differs at the terminal step;
    the integrators differ (docs/standard_tasks.md)."""
    brax_env, gym_env = _brax_env("inverted_pendulum"), mujoco_pendulums["InvertedPendulum"]
    assert float(brax_env.dt) == pytest.approx(0.04) and gym_env.dt == pytest.approx(0.04)
    assert _brax_xml_integrator("inverted_pendulum") == mujoco.mjtIntegrator.mjINT_EULER
    assert gym_env.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert gymnasium.spec("InvertedPendulum-v5").max_episode_steps == 1000
    # brax's action in [-1, 1] is mapped onto the motor's control range, gymnasium's action range
    controls = [float(_brax_step(brax_env, a, q=jnp.zeros(2), qd=jnp.zeros(2))[1][0]) for a in (-1, 1)]
    assert controls == [-3.0, 3.0] == [gym_env.action_space.low[0], gym_env.action_space.high[0]]
    assert float(brax_env.sys.actuator.gear[0]) == gym_env.model.actuator_gear[0, 0] == 100.0
    # the pole beyond 0.2 rad ends the episode in both; brax pays 1 at every step, the terminal one
    # included, gymnasium's v5 1 per step before it and 0 at it
    for angle, ends in ((0.1, False), (0.3, True)):
        state, _ = _brax_step(brax_env, 0.0, q=jnp.array([0.0, angle]), qd=jnp.zeros(2))
        assert (state.reward, state.done) == (1.0, ends)
        assert _gymnasium_mujoco_step(gym_env, [0.0, angle], [0.0, 0.0]) == (0.0 if ends else 1.0, ends)


def test_brax_inverted_pendulum_reward_and_end_as_the_task_states_them():
    """`tasks.BRAX_REWARDS`' reward and end of brax's inverted pendulum (what a model of the task
    plans with) are those of brax's step, from hand-made states on both sides of the end."""
    brax_env = _brax_env("inverted_pendulum")
    reward_fn, end_fn, margin = tasks.BRAX_REWARDS["inverted_pendulum"]
    for angle in (0.0, 0.15, 0.199, 0.201, -0.25, 0.6):
        state, _ = _brax_step(brax_env, 0.3, q=jnp.array([0.1, angle]), qd=jnp.array([0.2, -0.4]))
        obs = jnp.asarray(state.obs)
        assert float(reward_fn(obs, 0.3, obs)) == state.reward
        assert bool(end_fn(obs)) == state.done == bool(margin(obs, jnp.ones(4)) > 0)


def test_brax_inverted_double_pendulum_reward_and_end_as_the_task_states_them():
    """`tasks.BRAX_REWARDS`' reward and end of brax's double pendulum, functions of the
    observation (the tip from the hinges' sines and cosines), are those of brax's step, from
    states whose bodies brax's own forward kinematics places, on both sides of the end."""
    from brax import kinematics

    env = _brax_env("inverted_double_pendulum")
    reward_fn, end_fn, margin = tasks.BRAX_REWARDS["inverted_double_pendulum"]
    forward = jax.jit(kinematics.forward)
    ends = []
    for q, qd in (([0.1, 0.0, 0.0], [0.0, 0.0, 0.0]), ([0.2, 0.3, -0.5], [0.1, 2.0, -3.0]),
                  ([-0.3, 0.5, 0.2], [0.5, -4.0, 6.0]), ([0.0, 0.45, 0.0], [0.0, 1.0, 1.0]),
                  ([0.4, 0.8, 0.4], [-1.0, 9.0, -9.5])):
        q, qd = jnp.array(q), jnp.array(qd)
        x, _ = forward(env.sys, q, qd)
        state, _ = _brax_step(env, 0.3, q=q, qd=qd, x=x)
        obs = jnp.asarray(state.obs)
        assert float(reward_fn(obs, 0.3, obs)) == pytest.approx(state.reward, rel=1e-5, abs=1e-4)
        assert bool(end_fn(obs)) == state.done == bool(margin(obs, jnp.ones(8)) > 0)
        ends.append(state.done)
    assert ends == [False, False, True, False, True]


def _double_pendulum_reward(x, y, v1, v2):
    """The reward and end that both define: the tip at (x, y) m, the hinges' speeds v1, v2."""
    end = bool(y <= 1)
    return 10.0 * (not end) - (0.01 * x**2 + (y - 2) ** 2) - (1e-3 * v1**2 + 5e-3 * v2**2), end


def test_brax_inverted_double_pendulum_beside_gymnasium_v5(mujoco_pendulums):
    """The same reward, end and action; the control step (and so an episode's duration), the
    start, the observation and the integrators differ (docs/standard_tasks.md)."""
    brax_env, gym_env = _brax_env("inverted_double_pendulum"), mujoco_pendulums["InvertedDoublePendulum"]
    assert float(brax_env.dt) == pytest.approx(0.02) and gym_env.dt == pytest.approx(0.05)
    assert _brax_xml_integrator("inverted_double_pendulum") == mujoco.mjtIntegrator.mjINT_EULER
    assert gym_env.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert gymnasium.spec("InvertedDoublePendulum-v5").max_episode_steps == 1000
    # the action is the motor's control in both, in [-1, 1], at the same gear
    assert float(_brax_step(brax_env, 0.5, q=jnp.zeros(3), qd=jnp.zeros(3),
                            x=_bodies_at(0.0, 1.2))[1][0]) == 0.5
    assert [gym_env.action_space.low[0], gym_env.action_space.high[0]] == [-1.0, 1.0]
    assert np.all(np.asarray(brax_env.sys.actuator.ctrl_range) == [[-1.0, 1.0]])
    assert float(brax_env.sys.actuator.gear[0]) == gym_env.model.actuator_gear[0, 0] == 500.0
    # the reward and end, on brax's step from hand-made states (tip up, tip down) ...
    for x, y in ((0.1, 1.2), (0.3, 0.9)):
        state, _ = _brax_step(brax_env, 0.0, q=jnp.zeros(3), qd=jnp.array([0.0, 2.0, -3.0]),
                              x=_bodies_at(x, y))
        reward, end = _double_pendulum_reward(x, y, 2.0, -3.0)
        assert state.reward == pytest.approx(reward, rel=1e-6) and state.done == end
        assert state.obs.shape == (8,)  # x, sin and cos of the two angles, three speeds
    # ... and on gymnasium's, from an upright and a folded pole
    ends = []
    for qpos, qvel in (([0.0, 0.0, 0.0], [0.0, 2.0, -3.0]), ([0.0, 1.5, 0.0], [0.0, 0.0, 0.0])):
        reward, end = _gymnasium_mujoco_step(gym_env, qpos, qvel)
        x, _, y = gym_env.data.site_xpos[0]
        v1, v2 = gym_env.data.qvel[1:3]
        assert (reward, end) == pytest.approx(_double_pendulum_reward(x, y, v1, v2), rel=1e-12)
        ends.append(end)
    assert ends == [False, True]
    assert gym_env.observation_space.shape == (9,)  # and the cart's constraint force


def _bodies_at(x, y):
    """brax's body transforms (cart, pole, upper pole) with the upper pole's frame placed so that
    the tip, 0.6 m along it, is at (x, y)."""
    from brax import base

    pos = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [x, 0.0, y - 0.6]])
    return base.Transform(pos=pos, rot=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (3, 1)))
