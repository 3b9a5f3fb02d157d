"""Tasks of one's own: a gymnax or brax environment object as a `tasks.Task`, and the check of what
a task states about its reward and its end (docs/own_task.md).

`tasks.make_task` knows the environments by name (``gymnax:<id>``, ``brax:<name>``). An
environment that is an object instead (a gymnax environment with parameters of one's own, a
subclass of gymnax's or brax's `Env`) becomes a task here, with the same normalisation and
controllers as the named ones (`tasks` module notes):

  task = task_statements.from_gymnax(env, params, "heavy-pendulum", reward_fn=..., end_fn=...)
  tasks.register(task)            # then TrainConfig(env="heavy-pendulum"), --env heavy-pendulum

gp_model plans with the task's statement of its reward and end, functions of one transition:

  reward_fn(obs, action, next_obs, end=None) -> ()   the environment's reward (the `end` argument
                                                      only where `end_fn` is stated)
  end_fn(next_obs) -> () bool                         whether the transition ends the episode
  end_margin(next_obs) -> ()                          its signed margin, > 0 where `end_fn` holds,
                                                      in units of the observation's scale
                                                      (`from_gymnax` and `from_brax` take
                                                      end_margin(next_obs, scale): the scale is
                                                      placed when the task is made)

`statement_problem` checks them by abstract evaluation (`jax.eval_shape`, nothing is computed) and
says in one line what to change; `tasks.register` refuses a task with such a problem.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import tasks


def _call_problem(what: str, fn: Callable, args, signature: str) -> str | None:
    """None if `fn(*args)` evaluates abstractly to one scalar; else a line saying what is wrong."""
    try:
        out = jax.eval_shape(fn, *args)
    except Exception as e:  # noqa: BLE001 (the user's function: any error is reported in one line)
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        return f"{what} must take {signature} and return a scalar; it fails: {type(e).__name__}: {first}"
    shape = getattr(out, "shape", None)
    if shape is None or tuple(shape) != ():
        got = f"shape {tuple(shape)}" if shape is not None else type(out).__name__
        return f"{what} must return a scalar (shape ()), got {got}"
    return None


def _takes_end(fn: Callable) -> bool:
    """Whether `fn` can be called with a fourth positional argument (the end)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return True  # not introspectable (a C function, a partial of one): let the call decide
    params = list(sig.parameters.values())
    if any(p.kind is p.VAR_POSITIONAL for p in params):
        return True
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    return len(positional) >= 4


def statement_problem(task: tasks.Task) -> str | None:
    """What is wrong with `task`'s statement of its reward and end (module notes), in one line
    naming the field and what to write; None if nothing is."""
    name = task.name
    obs = jax.ShapeDtypeStruct((task.obs_dim,), jnp.float32)
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    if task.end_margin is not None and task.end_fn is None:
        return (f"task {name!r} states end_margin but no end_fn: state end_fn(next_obs) -> bool, "
                "the end that the margin smooths")
    if task.end_fn is not None:
        problem = _call_problem(f"task {name!r}: end_fn", task.end_fn, (obs,), "(next_obs)")
        if problem:
            return problem
    if task.end_margin is not None:
        problem = _call_problem(f"task {name!r}: end_margin", task.end_margin, (obs,),
                                "(next_obs)")
        if problem:
            return problem
    if task.reward_fn is not None:
        if task.end_fn is not None and not _takes_end(task.reward_fn):
            return (f"task {name!r} states end_fn, so its reward_fn must take the end too: "
                    "reward_fn(obs, action, next_obs, end=None), end the end's indicator or "
                    "probability (None: end_fn(next_obs))")
        args = (obs, scalar, obs) + ((scalar,) if task.end_fn is not None else ())
        signature = "(obs, action, next_obs" + (", end=None)" if task.end_fn is not None else ")")
        problem = _call_problem(f"task {name!r}: reward_fn", task.reward_fn, args, signature)
        if problem:
            return problem
    return None


def check_against_environment(task: tasks.Task, key=None, num_episodes: int = 4,
                              dtype: str = "float32") -> dict:
    """The task's statement against its own steps: `num_episodes` episodes of uniformly random
    actions, compared up to each episode's first end. The task must be registered (or built in).

    Returns a dict: `reward_error`, the largest |reward_fn(obs, action, next_obs) - reward| over
    those steps (None without `reward_fn`); `end_disagreements`, the steps at which `end_fn`
    disagrees with the step's `done` (None without `end_fn`); `steps`, the steps compared. A
    statement that gp_model plans with as the task is has a `reward_error` at rounding level and
    no disagreement."""
    from gpguided_jax import config

    cfg = config.make_config(env=task.name, dtype=dtype)
    key = jax.random.key(0) if key is None else key

    def episode(k):
        k_reset, k_steps = jax.random.split(k)
        env_state, obs = task.reset(k_reset, cfg)

        def body(carry, k_step):
            env_state, obs, alive = carry
            k_act, k_env = jax.random.split(k_step)
            a = jax.random.uniform(k_act, (), obs.dtype, -task.max_action, task.max_action)
            env_state, nxt, r, done = task.step(k_env, env_state, a, cfg)
            stated_r = r if task.reward_fn is None else task.reward_fn(obs, a, nxt)
            stated_end = done if task.end_fn is None else task.end_fn(nxt)
            out = (alive, jnp.abs(jnp.asarray(stated_r, obs.dtype) - r),
                   jnp.asarray(stated_end, bool) != jnp.asarray(done, bool))
            return (env_state, nxt, alive & ~jnp.asarray(done, bool)), out

        _, (alive, err, wrong_end) = jax.lax.scan(
            body, (env_state, obs, jnp.ones((), bool)),
            jax.random.split(k_steps, task.episode_length))
        return alive, err, wrong_end

    alive, err, wrong_end = jax.jit(jax.vmap(episode))(jax.random.split(key, num_episodes))
    alive = np.asarray(alive)
    return {"reward_error": None if task.reward_fn is None else float(np.max(np.asarray(err)[alive])),
            "end_disagreements": (None if task.end_fn is None
                                  else int(np.sum(np.asarray(wrong_end)[alive]))),
            "steps": int(np.sum(alive))}


def _task(name: str, adapter, *, threshold: float | None) -> tasks.Task:
    task = tasks._external_task(name, adapter)
    return task._replace(threshold=threshold)


def from_gymnax(env, params, name: str, *, reward_fn=None, end_fn=None, end_margin=None,
                threshold: float | None = None) -> tasks.Task:
    """A gymnax environment object (`gymnax.environments.environment.Environment`, with its
    `params`) with one continuous action as a `tasks.Task` named `name`: stepped by its
    `step_env` (no automatic reset), its observations normalised and its controllers placed as
    for a named gymnax task. `reward_fn`, `end_fn`: its statement (module notes);
    `end_margin(next_obs, scale)`: the end's signed margin, given the observation's normalisation
    scale (`Task.obs_scale`, placed when the task is made) to divide by; `threshold`: the return
    at which it counts as solved. Refused with `tasks.TaskError` in one line if its action is not
    one continuous number."""
    from gymnax.environments import spaces

    space = env.action_space(params)
    if not isinstance(space, spaces.Box) or int(np.prod(space.shape)) != 1:
        raise tasks.TaskError(f"{name}: the environment's action space is "
                              f"{type(space).__name__} {getattr(space, 'shape', '')}, not one "
                              "continuous number")
    max_action = float(np.max(np.abs([space.low, space.high])))

    def reset(key):
        obs, state = env.reset_env(key, params)
        return state, obs

    def step(key, state, action):
        obs, state, reward, done, _ = env.step_env(key, state, jnp.reshape(action, (1,)), params)
        return state, obs, reward, done

    adapter = tasks._Adapter(
        int(np.prod(env.observation_space(params).shape)), float(getattr(params, "dt", 1.0)),
        max_action, int(params.max_steps_in_episode), reset, step, reward_fn, end_fn, end_margin)
    return _task(name, adapter, threshold=threshold)


def from_brax(env, name: str, *, episode_length: int = 1000, reward_fn=None, end_fn=None,
              end_margin=None, threshold: float | None = None) -> tasks.Task:
    """A brax environment object (`brax.envs.Env`) with one action as a `tasks.Task` named
    `name`, as a named brax task is made (the action clipped to [-1, 1]; `episode_length` steps
    an episode). The statement and `threshold` as `from_gymnax`'s."""
    if env.action_size != 1:
        raise tasks.TaskError(f"{name}: the environment has {env.action_size} continuous actions, "
                              "not one")

    def reset(key):
        s = env.reset(key)
        return s, s.obs

    def step(key, state, action):
        del key  # brax's environments are deterministic given the state
        s = env.step(state, jnp.clip(jnp.reshape(action, (1,)).astype(jnp.float32), -1.0, 1.0))
        return s, s.obs, s.reward, s.done > 0.5

    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Brax System, piplines")
        obs_dim = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs.shape[-1]
    adapter = tasks._Adapter(int(obs_dim), float(env.dt), 1.0, int(episode_length), reset, step,
                             reward_fn, end_fn, end_margin)
    return _task(name, adapter, threshold=threshold)
