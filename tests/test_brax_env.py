"""The brax adapter: the Env interface and brax's training wrappers (brax's PPO on it:
tests/test_baselines.py, test_train_ppo_tiny_budget_returns_finite_curve)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
from brax import envs
from brax.envs.wrappers import training

from gpguided_jax import brax_env, pendulum


def test_registered_and_interface():
    brax_env.register()
    env = envs.get_environment(brax_env.ENV_NAME)
    assert isinstance(env, brax_env.PendulumEnv)
    assert env.observation_size == 3 and env.action_size == 1
    assert isinstance(env.backend, str)
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    phi, omega, streak = state.pipeline_state
    assert streak == 0
    np.testing.assert_allclose(state.obs, [math.sin(phi), math.cos(phi), omega], rtol=1e-6)


def test_step_matches_library_pendulum_with_scaled_action():
    params = pendulum.make_params(reward_noise_std=0.0)
    env = brax_env.PendulumEnv(params)
    state = env.reset(jax.random.PRNGKey(1))
    s0 = state.pipeline_state[:2]
    nxt = env.step(state, jnp.array([0.4]))
    expected, r = pendulum.step(jax.random.key(0), s0, 0.4 * 5.0, params)
    np.testing.assert_allclose(nxt.pipeline_state[:2], expected, rtol=1e-12)
    np.testing.assert_allclose(nxt.reward, r, rtol=1e-12)
    # action beyond [-1, 1] is clipped at the torque limit
    a = env.step(state, jnp.array([3.0])).pipeline_state
    b = env.step(state, jnp.array([1.0])).pipeline_state
    np.testing.assert_array_equal(a, b)


def test_training_wrap_auto_resets_physical_state():
    env = brax_env.PendulumEnv(pendulum.make_params(dtype=jnp.float32))
    wrapped = training.wrap(env, episode_length=5, action_repeat=1)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    state = jax.jit(wrapped.reset)(keys)
    first = state.pipeline_state
    step = jax.jit(wrapped.step)
    for i in range(5):
        state = step(state, jnp.ones((3, 1)))
        if i < 4:
            assert not np.allclose(state.pipeline_state, first)
    # after episode_length steps the episode is done and AutoResetWrapper restored the start state
    assert np.all(np.asarray(state.done) == 1)
    np.testing.assert_array_equal(state.pipeline_state, first)
    np.testing.assert_allclose(state.obs[:, 2], first[:, 1])


def test_success_metric_is_the_swingup_criterion_on_the_last_step():
    """Under brax's episode wrapper, `success` is 1 exactly on the last step of an episode that
    ended with `hold_steps` steps within the tolerance of upright (as `swingup.success`). (Without
    the auto-reset wrapper, which would replace the last state by the next episode's first.)"""
    from gpguided_jax import swingup

    params = pendulum.make_params(dtype=jnp.float32, start_mean=(0.0, 0.0), start_std=(0.2, 0.2),
                                  reward_noise_std=0.0)
    length, hold = 900, 200
    env = brax_env.PendulumEnv(params, episode_length=length, hold_steps=hold)
    wrapped = training.VmapWrapper(training.EpisodeWrapper(env, length, 1))
    pump = swingup.energy_pumping_policy(params)
    keys = jax.random.split(jax.random.PRNGKey(3), 4)

    def run(state):
        def body(st, _):
            a = jax.vmap(lambda s: pump(None, s[:2]))(st.pipeline_state) / params.max_torque
            st = wrapped.step(st, a[:, None])
            return st, (st.metrics["success"], st.pipeline_state[:, :2])
        return jax.lax.scan(body, state, None, length=length)

    with jax.enable_x64(False):
        state = wrapped.reset(keys)
        _, (success, states) = jax.jit(run)(state)
    success, states = np.asarray(success), np.asarray(states)
    assert np.all(success[:-1] == 0)
    for i in range(4):
        expected = bool(swingup.success(jnp.asarray(states[:, i]), 0.005, hold_time=1.0))
        assert success[-1, i] == float(expected)
    assert success[-1].sum() >= 3  # the energy-pumping controller swings up from these starts
