"""The pendulum, and gymnax's environments, behind brax's `Env` interface, so brax's own trainers
(PPO, SAC) run on them (`PendulumEnv`, `GymnaxEnv`, `task_env`).

Observation (sin phi, cos phi, omega); action in [-1, 1] scaled to the torque limit. The physical
state [phi, omega], followed by the number of consecutive steps spent within the success tolerance
of upright, lives in `State.pipeline_state`, which is where brax's `AutoResetWrapper` stores and
restores the first state of an episode. The reward-noise key is carried in `State.info["rng"]`.
Episodes never terminate by themselves (`done` = 0): brax's `EpisodeWrapper` truncates them.

Metrics (summed over an episode by brax's evaluator): `upright_error` |phi - pi|, and `success`,
1 on the last step of an episode (`episode_length`, counted by the `EpisodeWrapper`) if the
pendulum has been within `tolerance` of upright for the last `hold_steps` steps
(`swingup.success`), so its episode sum is the swing-up success of the episode.
"""

from __future__ import annotations

import contextlib
import io

import jax
import jax.numpy as jnp
import numpy as np

# brax imports mujoco, whose import says on stdout that its optional GPU backend (warp) is
# missing: a line that does not concern these CPU runs, and stdout carries the command's output
with contextlib.redirect_stdout(io.StringIO()):
    from brax.envs.base import Env, State

from gpguided_jax import pendulum  # noqa: E402

ENV_NAME = "gpguided_pendulum"


def observe(state: jax.Array) -> jax.Array:
    """(sin phi, cos phi, omega) of a pendulum state [phi, omega]."""
    return jnp.stack([jnp.sin(state[0]), jnp.cos(state[0]), state[1]])


class PendulumEnv(Env):
    """brax `Env` adapter for `gpguided_jax.pendulum`.

    Args:
      params: `PendulumParams`; defaults to `pendulum.make_params()` in float32 (brax's networks
        run in float32).
      backend: reported by the `backend` property; the physics is this module's own RK4.
    """

    def __init__(self, params: pendulum.PendulumParams | None = None, backend: str = "jax", *,
                 episode_length: int = 0, hold_steps: int = 200, tolerance: float = 0.3):
        self._params = params if params is not None else pendulum.make_params(dtype=jnp.float32)
        self._backend = backend
        self._episode_length = int(episode_length)
        self._hold_steps = int(hold_steps)
        self._tolerance = float(tolerance)

    @property
    def params(self) -> pendulum.PendulumParams:
        return self._params

    def reset(self, rng: jax.Array) -> State:
        key_reset, key_next = jax.random.split(rng)
        s = pendulum.reset(key_reset, self._params)
        zero = jnp.zeros((), s.dtype)
        return State(
            pipeline_state=jnp.concatenate([s, zero[None]]),
            obs=observe(s),
            reward=zero,
            done=zero,
            metrics={"upright_error": jnp.abs(s[0] - jnp.pi), "success": zero},
            info={"rng": key_next},
        )

    def step(self, state: State, action: jax.Array) -> State:
        key_noise, key_next = jax.random.split(state.info["rng"])
        torque = jnp.reshape(action, ()) * self._params.max_torque
        s, reward = pendulum.step(key_noise, state.pipeline_state[:2], torque, self._params)
        state.info.update(rng=key_next)
        upright = jnp.abs(pendulum.wrap_angle(s[0]) - jnp.pi) < self._tolerance
        streak = jnp.where(upright, state.pipeline_state[2] + 1, 0.0).astype(s.dtype)
        steps_after = state.info.get("steps", jnp.zeros(())) + 1  # EpisodeWrapper's count
        last = (self._episode_length > 0) & (steps_after == self._episode_length)
        success = (last & (streak >= self._hold_steps)).astype(s.dtype)
        # Update in place: wrappers (e.g. the evaluator) add their own metric keys to this dict.
        state.metrics.update(upright_error=jnp.abs(s[0] - jnp.pi), success=success)
        return state.replace(
            pipeline_state=jnp.concatenate([s, streak[None]]),
            obs=observe(s),
            reward=reward.astype(state.reward.dtype),
            done=jnp.zeros_like(state.done),
        )

    @property
    def observation_size(self) -> int:
        return 3

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return self._backend


def register() -> None:
    """Registers `PendulumEnv` with brax under the name `gpguided_pendulum` (idempotent)."""
    from brax import envs

    envs.register_environment(ENV_NAME, PendulumEnv)


class GymnaxEnv(Env):
    """A gymnax environment with one continuous action behind brax's `Env`, so that brax's
    trainers run on the tasks of `gpguided_jax.tasks` (`task_env`).

    The action is in [-1, 1] (brax's policies squash to it), scaled to the environment's bound.
    gymnax's own state is `State.pipeline_state` (brax's `AutoResetWrapper` restores it at an
    episode's end), its step key `State.info["rng"]`. gymnax's time limit is lifted: brax's
    `EpisodeWrapper` truncates the episodes instead, so that `done` is a true termination (the car
    at the flag) and a trainer bootstraps its value at the time limit. The step is the task's:
    gymnax's, with gymnasium's rule where gymnax's differs (`tasks.GYMNASIUM_CORRECTIONS`: the
    car's left wall). Observations and rewards are float32.
    """

    def __init__(self, env_id: str, backend: str = "jax"):
        import gymnax

        from gpguided_jax import tasks

        self._correct = tasks.GYMNASIUM_CORRECTIONS.get(env_id)
        self._env, params = gymnax.make(env_id)
        space = self._env.action_space(params)
        self._max_action = float(max(abs(float(space.low)), abs(float(space.high))))
        self._params = params.replace(max_steps_in_episode=2**30)
        self._obs_size = int(np.prod(self._env.observation_space(params).shape))
        self._backend = backend

    def reset(self, rng: jax.Array) -> State:
        key_reset, key_next = jax.random.split(rng)
        obs, s = self._env.reset_env(key_reset, self._params)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=s, obs=jnp.asarray(obs, jnp.float32), reward=zero, done=zero,
                     metrics={}, info={"rng": key_next})

    def step(self, state: State, action: jax.Array) -> State:
        key, key_next = jax.random.split(state.info["rng"])
        a = jnp.reshape(jnp.clip(action, -1.0, 1.0), (1,)) * self._max_action
        obs, s, reward, done, _ = self._env.step_env(key, state.pipeline_state, a, self._params)
        if self._correct is not None:
            s, obs = self._correct(self._env, s, self._params)
        state.info.update(rng=key_next)
        return state.replace(pipeline_state=s, obs=jnp.asarray(obs, jnp.float32),
                             reward=jnp.asarray(reward, jnp.float32),
                             done=jnp.asarray(done, jnp.float32))

    @property
    def observation_size(self) -> int:
        return self._obs_size

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return self._backend


def task_env(name: str) -> Env:
    """The brax `Env` of a task name of `gpguided_jax.tasks` other than the paper's pendulum:
    brax's own environment for 'brax:<name>', `GymnaxEnv` for 'gymnax:<id>'."""
    kind, _, env = name.partition(":")
    if kind == "gymnax":
        return GymnaxEnv(env)
    if kind == "brax":
        from brax import envs

        return envs.get_environment(env)
    raise ValueError(f"no brax Env for the task {name!r} (pendulum: PendulumEnv)")
