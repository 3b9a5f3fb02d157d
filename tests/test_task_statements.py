"""Tasks of one's own (`gpguided_jax.task_statements`): the check of a task's statement of its
reward and end that `tasks.register` runs, each problem refused in one line; the statement against
the environment's own steps; a gymnax environment object as a task."""

import jax.numpy as jnp
import numpy as np
import pytest

from gpguided_jax import config, controllers, task_statements, tasks


def _cart(**fields):
    """A point mass on a track of half-length 2 whose episode ends when it leaves it."""
    dt = 0.05

    def end_fn(o):
        return jnp.abs(o[0]) > 2.0

    def reward_fn(o, a, n, end=None):
        end = end_fn(n) if end is None else end
        return -(o[0] ** 2) - 10.0 * end

    def reset(key, cfg):
        x = jnp.array([1.0, 0.0], cfg.dtype)
        return x, x

    def step(key, x, a, cfg):
        a = jnp.clip(a, -1.0, 1.0)
        n = jnp.stack([x[0] + dt * x[1], x[1] + dt * a]).astype(cfg.dtype)
        return n, n, reward_fn(x, a, n).astype(cfg.dtype), end_fn(n)

    def make_controller(name):
        return controllers.make_squashed(
            lambda o: controllers.LinearParams(weights=jnp.concatenate([o, jnp.ones(1, o.dtype)])),
            lambda dtype: controllers.LinearParams(weights=jnp.zeros(3, dtype)), u_max=1.0)

    task = tasks.Task(
        name="test:cart", obs_dim=2, dt=dt, max_action=1.0, episode_length=60, terminates=True,
        threshold=None, reset=reset, step=step,
        features=lambda o, a: jnp.concatenate([o, jnp.reshape(a, (1,)).astype(o.dtype)]),
        feature_dim=3, make_controller=make_controller, obs_centre=np.zeros(2),
        obs_scale=np.ones(2), reward_fn=reward_fn, end_fn=end_fn,
        end_margin=lambda o: jnp.abs(o[0]) - 2.0)
    return task._replace(**fields)


@pytest.fixture
def registered():
    """Names registered by a test, removed after it."""
    names = []
    yield names
    for name in names:
        tasks._REGISTERED.pop(name, None)
    tasks.make_task.cache_clear()


def test_a_whole_statement_has_no_problem_and_registers(registered):
    task = _cart()
    assert task_statements.statement_problem(task) is None
    registered.append(task.name)
    assert tasks.register(task) is task and tasks.make_task("test:cart") is task


def test_a_task_that_states_nothing_has_no_problem():
    assert task_statements.statement_problem(
        _cart(reward_fn=None, end_fn=None, end_margin=None)) is None


@pytest.mark.parametrize("fields,message", [
    (dict(reward_fn=lambda o, a, n: -o[0] ** 2),
     "task 'test:cart' states end_fn, so its reward_fn must take the end too: reward_fn(obs, "
     "action, next_obs, end=None)"),
    (dict(end_fn=None), "task 'test:cart' states end_margin but no end_fn: state end_fn(next_obs)"),
    (dict(reward_fn=lambda o, a, n, end=None: -o ** 2),
     "task 'test:cart': reward_fn must return a scalar (shape ()), got shape (2,)"),
    (dict(end_fn=lambda o: jnp.abs(o) > 2.0),
     "task 'test:cart': end_fn must return a scalar (shape ()), got shape (2,)"),
    (dict(end_margin=lambda o, scale: o[0]),
     "task 'test:cart': end_margin must take (next_obs) and return a scalar; it fails: TypeError"),
    (dict(reward_fn=lambda o, a, n, end=None: o @ jnp.ones(3)),  # written for another task
     "task 'test:cart': reward_fn must take (obs, action, next_obs, end=None) and return a "
     "scalar; it fails: TypeError"),
])
def test_each_problem_of_a_statement_is_refused_in_one_line(fields, message, registered):
    task = _cart(**fields)
    problem = task_statements.statement_problem(task)
    assert problem is not None and problem.startswith(message) and "\n" not in problem, problem
    registered.append(task.name)
    with pytest.raises(tasks.TaskError) as e:
        tasks.register(task)
    assert str(e.value) == problem
    assert "test:cart" not in tasks._REGISTERED


def test_a_reward_without_the_end_is_fine_for_a_task_without_one():
    task = _cart(end_fn=None, end_margin=None, reward_fn=lambda o, a, n: -o[0] ** 2)
    assert task_statements.statement_problem(task) is None


def test_the_statement_against_the_environment(registered):
    """The cart's own statement agrees with its steps; a reward with the wrong sign, or an end at
    the wrong place, is found."""
    registered.append("test:cart")
    tasks.register(_cart())
    good = task_statements.check_against_environment(tasks.make_task("test:cart"), num_episodes=3)
    assert good["reward_error"] < 1e-5 and good["end_disagreements"] == 0
    assert 0 < good["steps"] <= 3 * 60
    registered.append("test:cart-wrong")
    wrong = tasks.register(_cart(name="test:cart-wrong", reward_fn=lambda o, a, n, end=None: o[0] ** 2,
                                 end_fn=lambda o: jnp.abs(o[0]) > 1.05,
                                 end_margin=None))
    bad = task_statements.check_against_environment(wrong, num_episodes=3)
    assert bad["reward_error"] > 0.5 and bad["end_disagreements"] > 0


def test_a_task_that_states_no_reward_is_trained_with_the_reward_learnt(registered):
    """'stated' is refused in one line naming the alternatives; 'auto' and 'learned' are taken."""
    registered.append("test:cart-unstated")
    tasks.register(_cart(name="test:cart-unstated", reward_fn=None))
    with pytest.raises(ValueError) as e:
        config.make_config(env="test:cart-unstated", method="gp_model", model_reward="stated")
    assert "tasks.Task.reward_fn" in str(e.value) and "'learned' or 'auto'" in str(e.value)
    assert "\n" not in str(e.value)
    for reward in ("auto", "learned"):
        config.make_config(env="test:cart-unstated", method="gp_model", model_reward=reward)


@pytest.mark.slow  # the placement's random episodes and the check compile gymnax's step twice
def test_a_gymnax_environment_object_becomes_a_task(registered):
    """gymnax's Pendulum-v1 with other parameters, by `from_gymnax`: the named task's sizes and
    bound, its own name and threshold, and a statement that agrees with its steps."""
    gymnax = pytest.importorskip("gymnax")
    env, params = gymnax.make("Pendulum-v1")
    params = params.replace(m=1.5)
    named = tasks.make_task("gymnax:Pendulum-v1")
    registered.append("test:heavy")
    task = tasks.register(task_statements.from_gymnax(env, params, "test:heavy",
                                                      reward_fn=named.reward_fn, threshold=-300.0))
    assert (task.obs_dim, task.max_action, task.episode_length, task.dt) == (
        named.obs_dim, named.max_action, named.episode_length, named.dt)
    assert task.threshold == -300.0 and task.end_fn is None
    check = task_statements.check_against_environment(task, num_episodes=2)
    assert check["reward_error"] < 1e-3 and check["end_disagreements"] is None
    assert check["steps"] == 2 * task.episode_length


def test_an_environment_with_more_than_one_action_is_refused():
    gymnax = pytest.importorskip("gymnax")
    env, params = gymnax.make("Reacher-misc")
    with pytest.raises(tasks.TaskError, match="not one continuous number"):
        task_statements.from_gymnax(env, params, "test:reacher")
