"""Tasks: the environments Algorithm 1 trains on, behind one interface (design: docs/design.md#tasks).

A `Task` is a bundle of pure functions over one episode's state, so that the training loop runs it
inside `lax.scan` and `vmap` whatever the environment is:

  env_state, obs = task.reset(key, cfg)
  env_state, obs, reward, done = task.step(key, env_state, action, cfg)

The action is one scalar; the policies act on the observation `obs` ((obs_dim,)); the GP's input is
`task.features(obs, action)`, with the action as its last coordinate (the policies rely on it).

Three kinds of task are supported (`make_task(name)`):

* ``pendulum``: the paper's pendulum (`gpguided_jax.pendulum`), the default. The observation is
  the state [phi, omega]; the controllers and the GP features are the paper's ones. Its physics are
  the config's traced `pendulum` field.
* ``gymnax:<id>``: a gymnax environment with a one-dimensional continuous action, used from gymnax
  itself (``pip install gpguided_jax[gymnax]``): Pendulum-v1 and MountainCarContinuous-v0.
  gymnax's `step_env` (without its automatic reset) steps it. Both tasks are gymnasium's
  environments of the same names, on which the published reference numbers are measured:
  Pendulum-v1 is gymnax's step as it is; MountainCarContinuous-v0 is gymnax's step with
  gymnasium's left wall added (`gymnasium_car_wall`). gymnasium stops a car that reaches the wall
  moving left (its velocity becomes 0 at the position -1.2); gymnax 1.0.1's step zeroes a negative
  velocity at or past the goal instead, and leaves the car at the wall moving left. Its rule at the
  goal changes nothing within an episode: a car is at or past the goal moving left only after a
  step that began past the goal, and it first gets there moving right, which ends the episode
  (tests/test_task_reference.py steps both tasks beside gymnasium's environments).
  ``gymnax:Pendulum-v1-sparse-<rho>`` (rho 0, 0.1, 0.2: `SPARSE_PENDULUM_COSTS`) is Pendulum-v1's
  step from hanging with H-UCRL's sparse swing-up reward less an action cost rho
  (`sparse_pendulum_reward`; `GYMNAX_VARIANTS`: a gymnax environment with another start and
  reward, named by its gymnax id and the variant).
* ``brax:<name>``: a brax environment through brax's own `Env` (``reset(rng)``, ``step(state,
  action)``): inverted_pendulum and inverted_double_pendulum. brax's environments neither take a key
  in `step` nor clip the action; the action is clipped to brax's range [-1, 1] before the step.
  They are brax's own models, not gymnasium's MuJoCo InvertedPendulum-v5 and
  InvertedDoublePendulum-v5: the integrator, the double pendulum's time step and the single
  pendulum's reward at its end differ (docs/standard_tasks.md, "What each task is").

Episodes have a fixed length (`TrainConfig.episode_length`). An environment that terminates early
(a brax pendulum that falls, the car that reaches the goal) is frozen in its last state from then
on: the training loop masks the steps after the end (`Episode.alive`), whose rewards are 0 and which
enter neither the gradient nor the GP. With `TrainConfig.episode_end='restart'` the learning
episodes instead reset the environment after an end and go on in the remaining slots
(`Episode.ends`), each return-to-go stopping at its own end, so that every slot is an environment
step. Rewards are those the environment defines, accumulated undiscounted in `eval_return`.

Observations of a gymnax or brax task are normalised, z = (obs - centre) / scale, with the mean and
standard deviation of the observations that `PLACEMENT_EPISODES` episodes of uniformly random
actions visit (drawn once, with a fixed key, when the task is made). The controllers act on z:
`linear` is c(z) = u_max tanh(w^T (z, 1)); `rbf` has `RBF_CENTRES` centres chosen from those
normalised observations by farthest-point sampling, and one width, the mean distance from a centre
to its nearest neighbour. The GP's input is (z, a). u_max is the environment's action bound.
"""

from __future__ import annotations

import contextlib
import functools
import io
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import controllers as controllers_lib
from gpguided_jax import kernels, pendulum

GYMNAX_ENVS = ("Pendulum-v1", "MountainCarContinuous-v0")
# the action costs rho of the sparse swing-up (`sparse_pendulum_reward`): H-UCRL's figure's
SPARSE_PENDULUM_COSTS = (0.0, 0.1, 0.2)
SPARSE_PENDULUM_IDS = tuple(f"Pendulum-v1-sparse-{c:g}" for c in SPARSE_PENDULUM_COSTS)
BRAX_ENVS = ("inverted_pendulum", "inverted_double_pendulum")
SUPPORTED = ("pendulum", *(f"gymnax:{e}" for e in GYMNAX_ENVS + SPARSE_PENDULUM_IDS),
             *(f"brax:{e}" for e in BRAX_ENVS))

PLACEMENT_EPISODES = 16  # random-action episodes that place the normalisation and RBF centres
PLACEMENT_KEY = 20120610  # their fixed key (the same placement for every seed and method)
RBF_CENTRES = 32


class TaskError(ValueError):
    """An environment that Algorithm 1 cannot train on (unknown, or not a 1-d continuous action)."""


class Task(NamedTuple):
    """One environment behind the training loop's interface (module notes).

    Attributes:
      name: 'pendulum', 'gymnax:<id>' or 'brax:<name>'.
      obs_dim: length of the observation.
      dt: seconds per control step (the discount as a horizon, `discount_for_horizon`, uses it).
      max_action: the action bound u_max; the controllers squash to (-u_max, u_max).
      episode_length: the environment's own episode length in steps.
      terminates: whether an episode can end before `episode_length` (static: the masking is only
        traced for a task that can).
      threshold: the episode return at which the task counts as solved (None: no threshold).
      reset: (key, cfg) -> (env_state, obs).
      step: (key, env_state, action, cfg) -> (env_state, obs, reward, done).
      features: (obs, action) -> (feature_dim,) GP input, the action last.
      feature_dim: length of the GP input.
      make_controller: (name, units=0) -> `controllers.Controller` on observations ('linear',
        'rbf', 'rbf_trainable' or 'linear_rbf'; `units` the trainable network's, 0 its default).
      obs_centre, obs_scale: the normalisation z = (obs - centre) / scale (NumPy; zeros and ones
        for the pendulum, whose controllers and features take the raw state).
      reward_fn: (obs, action, next_obs, end=None) -> the environment's reward as a pure
        function of the transition (its mean, for the paper's pendulum's noisy reward); None
        where the task does not state it. A model of the task (`gpguided_jax.model_based`) plans
        with it. `end`: for a task whose reward depends on its end (the car's goal), the end's
        indicator or a probability in [0, 1] in its place (default: `end_fn(next_obs)`).
      end_fn: (next_obs) -> bool, whether the transition ends the episode, where the end is a
        known function of the observation (None: the task never ends early, or does not say).
      end_margin: (next_obs) -> the signed margin of the end, > 0 where `end_fn` holds, in units
        of the observation's normalisation scale (a model plans with a smoothed end through it).
      angles: the observation coordinates that are angles wrapped to one turn (the model takes
        their differences and sums modulo 2 pi).
      target: (obs) -> the displacement, in the task's units (m), of what the task asks for from
        where it is wanted (the pole's tip from upright, the car from the goal); None where the
        task declares no target. PILCO's saturating cost plans with it (`target_width`).
      target_width: the saturating cost's width sigma_c, in the units of `target`.
    """

    name: str
    obs_dim: int
    dt: float
    max_action: float
    episode_length: int
    terminates: bool
    threshold: float | None
    reset: Callable[..., Any]
    step: Callable[..., Any]
    features: Callable[[jax.Array, jax.Array], jax.Array]
    feature_dim: int
    make_controller: Callable[[str], controllers_lib.Controller]
    obs_centre: np.ndarray
    obs_scale: np.ndarray
    reward_fn: Callable[..., Any] | None = None
    end_fn: Callable[..., Any] | None = None
    angles: tuple[int, ...] = ()
    end_margin: Callable[..., Any] | None = None
    target: Callable[..., Any] | None = None
    target_width: float = 1.0


def discount_for_horizon(horizon_s: float, dt: float) -> float:
    """gamma = exp(-dt / horizon): the discount whose returns weigh the future over `horizon_s`
    seconds (the e-folding time), whatever the control rate. gamma = 0.99 at 200 Hz is a 0.5 s
    horizon, at 20 Hz a 5 s one."""
    if not horizon_s > 0:
        raise ValueError(f"the discount horizon must be > 0 seconds, got {horizon_s!r}")
    return float(np.exp(-dt / horizon_s))


def horizon_of_discount(discount: float, dt: float) -> float:
    """The horizon in seconds of a discount per step of dt seconds: -dt / log(gamma)."""
    return float("inf") if discount >= 1.0 else float(-dt / np.log(discount))


# ------------------------------------------------------------------------------------------------
# The paper's pendulum.
# ------------------------------------------------------------------------------------------------

PENDULUM_U_MAX = 5.0  # the controllers' squashing range; the pendulum clips at params.max_torque


def _pendulum_task() -> Task:
    def reset(key, cfg):
        s = pendulum.reset(key, cfg.pendulum)
        return s, s

    def step(key, env_state, action, cfg):
        s, r = pendulum.step(key, env_state, action, cfg.pendulum)
        return s, s, r, jnp.zeros((), bool)

    return Task(
        name="pendulum", obs_dim=2, dt=float(pendulum.DEFAULTS["dt"]), max_action=PENDULUM_U_MAX,
        episode_length=50, terminates=False, threshold=None, reset=reset, step=step,
        features=kernels.state_action_features, feature_dim=4,
        make_controller=lambda name, units=0: controllers_lib.make_controller(
            name, u_max=PENDULUM_U_MAX, **({"units": units} if units else {})),
        obs_centre=np.zeros(2), obs_scale=np.ones(2),
        reward_fn=lambda obs, action, next_obs, end=None: pendulum.reward_mean(next_obs),
        angles=(0,), target=_pendulum_tip_from_upright, target_width=0.5)


def _pendulum_tip_from_upright(obs):
    """The paper's pendulum's tip (1 m) from upright (phi = pi), from the state [phi, omega]."""
    length = float(pendulum.DEFAULTS["length"])
    return length * jnp.stack([jnp.sin(obs[0]), -jnp.cos(obs[0]) - 1.0])


# ------------------------------------------------------------------------------------------------
# gymnax and brax environments: adapters, placement of the normalisation and RBF centres.
# ------------------------------------------------------------------------------------------------

# Episode-return thresholds: gymnasium's for MountainCarContinuous-v0 (90) and the common -200 for
# Pendulum-v1 (gymnasium defines none); brax's pendulums earn 1 per step for up to 1,000 steps as
# gymnasium's MuJoCo ones do (InvertedPendulum-v4: 950); brax's double pendulum earns up to about 9.4
# per step (10 minus distance and velocity penalties), gymnasium's InvertedDoublePendulum-v4 the
# same, with the threshold 9,100.
THRESHOLDS = {"gymnax:Pendulum-v1": -200.0, "gymnax:MountainCarContinuous-v0": 90.0,
              "brax:inverted_pendulum": 950.0, "brax:inverted_double_pendulum": 9100.0}
# The sparse swing-up (200 steps of 0.05 s, a reward of at most 1 a step): swung up and held, 100
# steps' worth of reward upright and still (half the episode) less 100 steps of the full action
# cost, 100 (1 - rho). An energy-pumping controller with a PD catch, tuned by hand on the
# physics, swings up from hanging in about 70 steps and scores 131 at rho = 0 and 122 at 0.2.
THRESHOLDS.update({f"gymnax:{i}": 100.0 * (1.0 - c)
                   for i, c in zip(SPARSE_PENDULUM_IDS, SPARSE_PENDULUM_COSTS)})


class _Adapter(NamedTuple):
    obs_dim: int
    dt: float
    max_action: float
    episode_length: int
    reset: Callable  # key -> (env_state, obs, float32)
    step: Callable  # (key, env_state, action) -> (env_state, obs, reward, done)
    reward_fn: Callable | None = None  # (obs, action, next_obs, end=None) -> reward
    end_fn: Callable | None = None  # next_obs -> bool (`Task.end_fn`)
    end_margin: Callable | None = None  # (next_obs, scale) -> signed margin (`Task.end_margin`)
    target: Callable | None = None  # obs -> displacement from the target (`Task.target`)
    target_width: float = 1.0
    # key -> (env_state, obs): the task's start where it is not `reset`'s (`reset` then places
    # the normalisation and the RBF centres over the environment's own start distribution)
    start: Callable | None = None


def _pendulum_v1_reward(params):
    """Pendulum-v1's reward of the state an action is taken in, -(theta^2 + 0.1 theta_dot^2 +
    0.001 u^2), theta in (-pi, pi] read from the observation (cos theta, sin theta, theta_dot) and
    u the torque clipped to the bound."""
    def reward(obs, action, next_obs, end=None):
        del next_obs, end
        theta = jnp.arctan2(obs[1], obs[0])
        u = jnp.clip(action, -params.max_torque, params.max_torque)
        return -(theta ** 2 + 0.1 * obs[2] ** 2 + 0.001 * u ** 2)
    return reward, None, None


def _pendulum_v1_target(obs):
    """Pendulum-v1's tip (1 m) from upright, from (cos theta, sin theta, theta_dot)."""
    return jnp.stack([obs[1], obs[0] - 1.0])


def _car_target(obs):
    """The car's position from the goal (0.45)."""
    return obs[:1] - 0.45


def _car_reward(params):
    """MountainCarContinuous-v0's reward, -0.1 a^2 + 100 at the goal, and its end: the car at or
    past the goal position moving right (observation (position, velocity))."""
    def at_goal(next_obs):
        return (next_obs[0] >= params.goal_position) & (next_obs[1] >= params.goal_velocity)

    def margin(next_obs, scale):
        return jnp.minimum((next_obs[0] - params.goal_position) / scale[0],
                           (next_obs[1] - params.goal_velocity) / scale[1])

    def reward(obs, action, next_obs, end=None):
        del obs
        e = at_goal(next_obs) if end is None else end
        return -0.1 * action ** 2 + 100.0 * jnp.asarray(e, next_obs.dtype)
    return reward, at_goal, margin


# The gymnax tasks whose reward and end are stated as functions of the transition.
GYMNAX_REWARDS = {"Pendulum-v1": _pendulum_v1_reward, "MountainCarContinuous-v0": _car_reward}
# Their targets and the saturating cost's widths (pilco-matlab's pendulum: 0.5 m on a 1 m pole;
# the car: a fifth of the valley between the start and the goal).
GYMNAX_TARGETS = {"Pendulum-v1": (_pendulum_v1_target, 0.5),
                  "MountainCarContinuous-v0": (_car_target, 0.2)}


def tolerance(x, lower, upper, margin):
    """rllib's `tolerance` (sebascuri/rllib, rllib/reward/utilities.py), which H-UCRL's rewards
    are built of: 1 on [lower, upper], outside it 0.1^(d / margin)^2 at the distance d from the
    interval (its `gaussian` with value 0.1 at d = margin)."""
    half = 0.5 * (upper - lower)
    d = jnp.maximum(jnp.abs(x - (lower + half)) - half, 0.0) / margin
    return jnp.exp(jnp.log(0.1) * d * d)


def sparse_pendulum_reward(obs, action, next_obs=None, end=None, *, action_cost: float,
                           max_torque: float = 2.0):
    """H-UCRL's sparse swing-up reward (Curi, Berkenkamp & Krause, NeurIPS 2020; sebascuri/hucrl,
    exps/inverted_pendulum/util.py, `PendulumReward`) of the state an action is taken in, from
    Pendulum-v1's observation (cos theta, sin theta, theta_dot), theta = 0 upright:

      tol(cos theta; [0.95, 1], 0.1) tol(theta_dot; [-0.5, 0.5], 0.5)
        + rho (tol(u / u_max; [-0.1, 0.1], 0.1) - 1),

    `tolerance` rllib's, rho = `action_cost`, u the torque clipped to the bound u_max (hucrl's
    action is in units of its bound: its model clamps it to [-1, 1]). The state's part is 1
    within about 18 degrees of upright and 0.5 rad/s of still, and below 1e-40 hanging; the
    action's part costs rho for any torque past 0.3 u_max, nothing within 0.1 u_max.
    rllib's own PendulumSwingUp-v0 (rllib/environment/mujoco/pendulum_swing_up.py, sparse=True)
    has the same form with the angle's margin 0.3 and the raw torque in the action's."""
    del next_obs, end
    u = jnp.clip(action, -max_torque, max_torque) / max_torque
    upright = tolerance(obs[0], 0.95, 1.0, 0.1) * tolerance(obs[2], -0.5, 0.5, 0.5)
    return upright + action_cost * (tolerance(u, -0.1, 0.1, 0.1) - 1.0)


SPARSE_PENDULUM_START = 0.01  # the start's spread about hanging and still (rllib's swing-up's)


def _sparse_pendulum(action_cost: float):
    """Pendulum-v1 as the sparse swing-up with action cost rho (`sparse_pendulum_reward`): gymnax's
    step, its reward replaced; each episode starts hanging, theta = pi + U(-0.01, 0.01), theta_dot =
    U(-0.01, 0.01) (H-UCRL's starts at (pi, 0) exactly, rllib's swing-up within 0.01 of it), where
    gymnax draws theta over the whole circle. gymnax's start still places the normalisation and
    the RBF centres (`_Adapter.start`), so that they cover the upright states the reward pays."""

    def variant(env, params, adapter: _Adapter) -> _Adapter:
        reward = functools.partial(sparse_pendulum_reward, action_cost=action_cost,
                                   max_torque=float(params.max_torque))

        def start(key):
            k_reset, k_near = jax.random.split(key)
            _, state = env.reset_env(k_reset, params)
            dtype = state.theta.dtype  # gymnax's (float64 in JAX's 64-bit mode)
            near = jax.random.uniform(k_near, (2,), dtype, -SPARSE_PENDULUM_START,
                                      SPARSE_PENDULUM_START)
            state = state.replace(theta=jnp.asarray(np.pi, dtype) + near[0], theta_dot=near[1])
            return state, env.get_obs(state)

        def step(key, state, action):
            before = env.get_obs(state)
            state, obs, _, done = adapter.step(key, state, action)
            return state, obs, reward(before, jnp.reshape(action, ())), done

        return adapter._replace(step=step, start=start, reward_fn=reward)

    return variant


# gymnax environments with another start and reward: id -> (gymnax's id, the variant of its
# adapter, `variant(env, params, adapter) -> adapter`)
GYMNAX_VARIANTS = {i: ("Pendulum-v1", _sparse_pendulum(c))
                   for i, c in zip(SPARSE_PENDULUM_IDS, SPARSE_PENDULUM_COSTS)}


def _gymnax_adapter(env_id: str) -> _Adapter:
    try:
        import gymnax
    except ImportError as e:
        raise TaskError(f"gymnax:{env_id} needs gymnax: pip install 'gpguided_jax[gymnax]' ({e})") from e
    from gymnax.environments import spaces

    name = env_id
    env_id, variant = GYMNAX_VARIANTS.get(name, (name, None))
    if env_id not in gymnax.registered_envs:
        raise TaskError(f"unknown environment 'gymnax:{env_id}'; {_supported_line()}")
    env, params = gymnax.make(env_id)
    space = env.action_space(params)
    if not isinstance(space, spaces.Box) or int(np.prod(space.shape)) != 1:
        kind = "a discrete" if isinstance(space, spaces.Discrete) else f"the {type(space).__name__}"
        raise TaskError(f"gymnax:{env_id} has {kind} action space {getattr(space, 'shape', '')}; "
                        f"{_supported_line()}")
    max_action = float(np.max(np.abs([space.low, space.high])))

    def reset(key):
        obs, state = env.reset_env(key, params)
        return state, obs

    correct = GYMNASIUM_CORRECTIONS.get(env_id)

    def step(key, state, action):
        obs, state, reward, done, _ = env.step_env(key, state, jnp.reshape(action, (1,)), params)
        if correct is not None:
            state, obs = correct(env, state, params)
        return state, obs, reward, done

    dt = float(getattr(params, "dt", 1.0))  # an environment without a time (the car): 1 s a step
    stated = GYMNAX_REWARDS[env_id](params) if env_id in GYMNAX_REWARDS else (None, None, None)
    target = GYMNAX_TARGETS.get(env_id, (None, 1.0))
    adapter = _Adapter(int(np.prod(env.observation_space(params).shape)), dt, max_action,
                       int(params.max_steps_in_episode), reset, step, *stated, *target)
    return adapter if variant is None else variant(env, params, adapter)


def gymnasium_car_wall(env, state, params):
    """gymnasium's left wall on the state gymnax's MountainCarContinuous-v0 step returns: a car at
    the wall (its position clipped to `min_position`) moving left stops, as in gymnasium's
    ``if position == min_position and velocity < 0: velocity = 0``. gymnax 1.0.1's step leaves it
    moving left. The reward and the end are gymnax's as they are: both depend on the velocity only
    at the goal, far from the wall. Returns the state and its observation."""
    stopped = (state.position <= params.min_position) & (state.velocity < 0)
    state = state.replace(velocity=jnp.where(stopped, jnp.zeros_like(state.velocity), state.velocity))
    return state, env.get_obs(state)


# The gymnax environments whose step differs from gymnasium's environment of the same name, with
# what is applied after gymnax's step: (env, state, params) -> (state, observation). The tasks
# and `brax_env.GymnaxEnv` (brax's trainers) both apply it.
GYMNASIUM_CORRECTIONS = {"MountainCarContinuous-v0": gymnasium_car_wall}


def _brax_adapter(name: str) -> _Adapter:
    # brax's import says on stdout that mujoco's optional GPU backend (warp) is missing, and its
    # environments warn that brax is in maintenance: neither concerns these CPU runs
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Brax System, piplines")
        from brax import envs

        if name not in envs._envs:
            raise TaskError(f"unknown environment 'brax:{name}'; {_supported_line()}")
        env = envs.get_environment(name)
    if env.action_size != 1:
        raise TaskError(f"brax:{name} has {env.action_size} continuous actions, not one; "
                        f"{_supported_line()}")

    def reset(key):
        s = env.reset(key)
        return s, s.obs

    def step(key, state, action):
        del key  # brax's environments are deterministic given the state
        a = jnp.clip(jnp.reshape(action, (1,)).astype(jnp.float32), -1.0, 1.0)
        s = env.step(state, a)
        return s, s.obs, s.reward, s.done > 0.5

    # the observation's size by abstract evaluation: brax's `observation_size` resets the
    # environment op by op, which compiles each of its physics' operations (seconds on a CPU)
    obs_dim = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs.shape[-1]
    return _Adapter(int(obs_dim), float(env.dt), 1.0, 1000, reset, step,
                    *BRAX_REWARDS.get(name, (None, None, None)),
                    *BRAX_TARGETS.get(name, (None, 1.0)))


def _inverted_pendulum_reward(obs, action, next_obs, end=None):
    """brax's inverted pendulum pays 1 per step, the falling one included."""
    del obs, action, end
    return jnp.ones((), next_obs.dtype)


def _inverted_pendulum_end(next_obs):
    """brax's inverted pendulum falls when the pole's angle (observation 1) leaves [-0.2, 0.2]."""
    return jnp.abs(next_obs[1]) > 0.2


def _inverted_pendulum_margin(next_obs, scale):
    return (jnp.abs(next_obs[1]) - 0.2) / scale[1]


def _double_pendulum_tip(obs):
    """The tip's position (x, height) in m from brax's double pendulum's observation (the cart's
    x, the sines and the cosines of the two hinges' angles, ...): each pole is 0.6 m, the upper
    one's angle relative to the lower's."""
    x0, s1, s2, c1, c2 = (obs[i] for i in range(5))
    return x0 + 0.6 * (s1 + s1 * c2 + c1 * s2), 0.6 * (c1 + c1 * c2 - s1 * s2)


def _inverted_double_pendulum_reward(obs, action, next_obs, end=None):
    """brax's inverted double pendulum: 10 unless the step ends the episode, less 0.01 x^2 +
    (height - 2)^2 of the tip and 1e-3 v1^2 + 5e-3 v2^2 of the hinges' speeds (observations 6
    and 7, which the observation clips to +-10: brax's own reward while they are within it)."""
    del obs, action
    x, height = _double_pendulum_tip(next_obs)
    e = _inverted_double_pendulum_end(next_obs) if end is None else end
    v1, v2 = next_obs[6], next_obs[7]
    return (10.0 * (1.0 - jnp.asarray(e, next_obs.dtype)) - (0.01 * x ** 2 + (height - 2.0) ** 2)
            - (1e-3 * v1 ** 2 + 5e-3 * v2 ** 2))


def _inverted_double_pendulum_end(next_obs):
    """brax's inverted double pendulum ends when the tip is at or below 1 m."""
    return _double_pendulum_tip(next_obs)[1] <= 1.0


def _inverted_double_pendulum_margin(next_obs, scale):
    """The end's margin, 1 m less the tip's height, in units of the height's spread as the
    cosines' spreads give it (0.6 m times their sum)."""
    return (1.0 - _double_pendulum_tip(next_obs)[1]) / (0.6 * (scale[3] + scale[4]))


# The brax tasks whose reward and end are stated as functions of the transition.
BRAX_REWARDS = {"inverted_pendulum": (_inverted_pendulum_reward, _inverted_pendulum_end,
                                      _inverted_pendulum_margin),
                "inverted_double_pendulum": (_inverted_double_pendulum_reward,
                                             _inverted_double_pendulum_end,
                                             _inverted_double_pendulum_margin)}


def _inverted_pendulum_target(obs):
    """brax's inverted pendulum's pole tip (0.6 m) from upright over the rail's centre, from (the
    cart's x, the pole's angle, ...)."""
    return jnp.stack([obs[0] + 0.6 * jnp.sin(obs[1]), 0.6 * (jnp.cos(obs[1]) - 1.0)])


def _inverted_double_pendulum_target(obs):
    """brax's double pendulum's tip from upright over the rail's centre (1.2 m high)."""
    x, height = _double_pendulum_tip(obs)
    return jnp.stack([x, height - 1.2])


# Their targets and the saturating cost's widths (pilco-matlab's cart-pole: 0.25 m on a 0.6 m
# pole; its double pendulum: 0.5 m).
BRAX_TARGETS = {"inverted_pendulum": (_inverted_pendulum_target, 0.25),
                "inverted_double_pendulum": (_inverted_double_pendulum_target, 0.5)}


def _supported_line() -> str:
    return ("Algorithm 1 trains on environments with one continuous action, such as "
            + ", ".join(SUPPORTED))


def _random_action_observations(adapter: _Adapter) -> np.ndarray:
    """The observations (before the end of each episode) of `PLACEMENT_EPISODES` episodes of
    uniformly random actions in [-u_max, u_max], in float32: (n, obs_dim)."""
    def episode(key):
        key_reset, key_steps = jax.random.split(key)
        env_state, obs = adapter.reset(key_reset)

        def body(carry, k):
            env_state, obs, alive = carry
            k_act, k_env = jax.random.split(k)
            a = jax.random.uniform(k_act, (), jnp.float32, -adapter.max_action, adapter.max_action)
            new_state, new_obs, _, done = adapter.step(k_env, env_state, a)
            env_state = jax.tree_util.tree_map(lambda n, o: jnp.where(alive, n, o), new_state, env_state)
            return (env_state, jnp.where(alive, new_obs, obs), alive & ~done), (obs, alive)

        _, (obs_seq, alive) = jax.lax.scan(
            body, (env_state, obs, jnp.ones((), bool)),
            jax.random.split(key_steps, adapter.episode_length))
        return obs_seq, alive

    keys = jax.random.split(jax.random.key(PLACEMENT_KEY), PLACEMENT_EPISODES)
    with jax.default_device(jax.devices("cpu")[0]):
        obs, alive = jax.jit(jax.vmap(episode))(keys)
    obs, alive = np.asarray(obs, np.float64), np.asarray(alive)
    return obs.reshape(-1, obs.shape[-1])[alive.reshape(-1)]


farthest_point_centres = controllers_lib.farthest_point_centres
START_DRAWS = 64  # start observations drawn when a task is made (the trainable RBF's centres)


def _start_observations(adapter: _Adapter) -> np.ndarray:
    """`START_DRAWS` observations of the task's start distribution, with a fixed key: (n,
    obs_dim)."""
    keys = jax.random.split(jax.random.key(PLACEMENT_KEY + 1), START_DRAWS)
    start = adapter.start or adapter.reset
    with jax.default_device(jax.devices("cpu")[0]):
        obs = jax.jit(jax.vmap(lambda k: start(k)[1]))(keys)
    return np.asarray(obs, np.float64)


def _observation_controller(name: str, u_max: float, centre, scale, rbf_centres, rbf_width,
                           visited=None, starts=None, units: int = 0):
    obs_dim = len(centre)

    if name in ("rbf_trainable", "linear_rbf"):
        # centres started from the start distribution (a quarter) and the visited states
        m = units or len(rbf_centres)
        n_start = 0 if starts is None else min(m // 4, len(starts))
        z_start = (starts - centre) / scale if n_start else np.zeros((0, obs_dim))
        chosen = np.concatenate([farthest_point_centres(z_start, n_start)[:n_start],
                                 farthest_point_centres(visited, m - n_start)])

        def embed(obs):
            return (obs - jnp.asarray(centre, obs.dtype)) / jnp.asarray(scale, obs.dtype)
        return controllers_lib.trainable_rbf_controller(
            embed, chosen, controllers_lib.mean_gap(chosen), u_max, linear=name == "linear_rbf")
    if name == "linear":
        def features_fn(obs):
            z = (obs - jnp.asarray(centre, obs.dtype)) / jnp.asarray(scale, obs.dtype)
            return controllers_lib.LinearParams(weights=jnp.concatenate([z, jnp.ones((1,), obs.dtype)]))

        def zeros_fn(dtype):
            return controllers_lib.LinearParams(weights=jnp.zeros((obs_dim + 1,), dtype))
    elif name == "rbf":
        def features_fn(obs):
            z = (obs - jnp.asarray(centre, obs.dtype)) / jnp.asarray(scale, obs.dtype)
            d = (z[None, :] - jnp.asarray(rbf_centres, obs.dtype)) / rbf_width
            return controllers_lib.RBFParams(weights=jnp.exp(-0.5 * jnp.sum(d * d, axis=-1)),
                                             bias=jnp.ones((), obs.dtype))

        def zeros_fn(dtype):
            return controllers_lib.RBFParams(weights=jnp.zeros((len(rbf_centres),), dtype),
                                             bias=jnp.zeros((), dtype))
    else:
        raise ValueError(f"unknown controller {name!r}; choose from {sorted(controllers_lib.CONTROLLERS)}")
    return controllers_lib.make_squashed(features_fn, zeros_fn, u_max, state_dim=obs_dim)


def _external_task(name: str, adapter: _Adapter) -> Task:
    obs = _random_action_observations(adapter)
    centre = obs.mean(axis=0)
    scale = obs.std(axis=0)
    scale = np.where(scale > 1e-6, scale, 1.0)  # a coordinate that never moved is left as it is
    z = (obs - centre) / scale
    rbf_centres = farthest_point_centres(z, RBF_CENTRES)
    rbf_width = controllers_lib.mean_gap(rbf_centres)
    starts = _start_observations(adapter)
    start = adapter.start or adapter.reset

    def reset(key, cfg):
        env_state, o = start(key)
        return env_state, jnp.asarray(o, cfg.dtype)

    def step(key, env_state, action, cfg):
        env_state, o, r, done = adapter.step(key, env_state, action)
        return env_state, jnp.asarray(o, cfg.dtype), jnp.asarray(r, cfg.dtype), jnp.asarray(done, bool)

    def features(o, action):
        zz = (o - jnp.asarray(centre, o.dtype)) / jnp.asarray(scale, o.dtype)
        return jnp.concatenate([zz, jnp.reshape(jnp.asarray(action, o.dtype), (1,))])

    return Task(
        name=name, obs_dim=adapter.obs_dim, dt=adapter.dt, max_action=adapter.max_action,
        episode_length=adapter.episode_length, terminates=True, threshold=THRESHOLDS.get(name),
        reset=reset, step=step, features=features, feature_dim=adapter.obs_dim + 1,
        make_controller=lambda c, units=0: _observation_controller(
            c, adapter.max_action, centre, scale, rbf_centres, rbf_width, z, starts, units),
        obs_centre=centre, obs_scale=scale, reward_fn=adapter.reward_fn, end_fn=adapter.end_fn,
        end_margin=(None if adapter.end_margin is None else
                    lambda o: adapter.end_margin(o, jnp.asarray(scale, o.dtype))),
        target=adapter.target, target_width=adapter.target_width)


_REGISTERED: dict[str, Task] = {}


def register(task: Task) -> Task:
    """Makes a `Task` written by hand trainable by name (`TrainConfig.env = task.name`): any JAX
    environment with one continuous action, given as the module notes describe."""
    if task.name in SUPPORTED or task.name.partition(":")[0] in ("gymnax", "brax"):
        raise TaskError(f"the name {task.name!r} is taken by a built-in environment")
    _REGISTERED[task.name] = task
    make_task.cache_clear()
    return task


@functools.cache
def make_task(name: str = "pendulum") -> Task:
    """The `Task` of an environment name ('pendulum', 'gymnax:<id>', 'brax:<name>'; `SUPPORTED`),
    or one `register`ed. Raises `TaskError` with one line naming what is supported for anything
    else."""
    if name in _REGISTERED:
        return _REGISTERED[name]
    if name == "pendulum":
        return _pendulum_task()
    kind, _, env = name.partition(":")
    if kind == "gymnax":
        return _external_task(name, _gymnax_adapter(env))
    if kind == "brax":
        return _external_task(name, _brax_adapter(env))
    raise TaskError(f"unknown environment {name!r}; {_supported_line()}")
