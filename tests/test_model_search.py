"""gp_model's planning objectives, trainable controllers and search options, each against an
independent reference: finite differences, pilco-matlab's formula, a NumPy network with its
gradient derived by hand, optax's schedule written out, and runs of the parts one by one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpguided_jax import config as C
from gpguided_jax import controllers as controllers_lib
from gpguided_jax import model_based as MB
from gpguided_jax import rollouts, tasks

GROWTH, GAIN, LIMIT = 1.1, 0.5, 1.0  # x' = 1.1 x + 0.5 u, the episode ends where |x| > 1


def _balance_task(margin: bool = True) -> tasks.Task:
    """An unstable one-dimensional system that ends where it leaves [-1, 1]; reward 1 a step (a
    survival reward, as brax's inverted pendulum's); target x = 0 (width 0.5)."""

    def reset(key, cfg):
        x = jax.random.uniform(key, (1,), cfg.dtype, -0.2, 0.2)
        return x, x

    def step(key, x, u, cfg):
        del key
        nxt = GROWTH * x + GAIN * u
        return nxt, nxt, jnp.ones((), cfg.dtype), jnp.abs(nxt[0]) > LIMIT

    def make_controller(name, units=0):
        del name, units
        return controllers_lib.make_squashed(
            lambda x: controllers_lib.LinearParams(jnp.concatenate([x, jnp.ones((1,), x.dtype)])),
            lambda dtype: controllers_lib.LinearParams(jnp.zeros((2,), dtype)), 2.0, state_dim=1)

    return tasks.Task(
        name="test:balance" if margin else "test:balance_hard", obs_dim=1, dt=0.1, max_action=2.0,
        episode_length=20, terminates=True, threshold=None, reset=reset, step=step,
        features=lambda x, u: jnp.concatenate([x, jnp.reshape(u, (1,))]), feature_dim=2,
        make_controller=make_controller, obs_centre=np.zeros(1), obs_scale=np.ones(1),
        reward_fn=lambda x, u, nxt, end=None: jnp.ones((), nxt.dtype),
        end_fn=lambda nxt: jnp.abs(nxt[0]) > LIMIT,
        end_margin=(lambda nxt: jnp.abs(nxt[0]) - LIMIT) if margin else None,
        target=lambda x: x, target_width=0.5)


@pytest.fixture(scope="module")
def balance():
    """Both tasks registered, and a model of the system from random transitions (noise-free)."""
    for margin in (True, False):
        tasks.register(_balance_task(margin))
    try:
        cfg = C.make_config(env="test:balance", method="gp_model", controller="linear",
                            episode_length=20, num_updates=2, episodes_per_update=1, hold_time=0.0,
                            model_inducing=40, model_particles=4, model_horizon=1.0)
        prog = rollouts.make_program(cfg)
        rng = np.random.default_rng(0)
        x = rng.uniform(-1.5, 1.5, (80, 1))
        u = rng.uniform(-2.0, 2.0, (80,))
        nxt = GROWTH * x + GAIN * u[:, None]
        data = MB.take_in(MB.init(prog, None, cfg), jnp.asarray(np.c_[x, u]),
                          jnp.asarray(nxt - x), jnp.ones(80, bool), jnp.asarray(x))
        data = data._replace(log_kernels=jax.jit(
            MB.refit, static_argnames=("subset_size", "num_steps"))(
                jax.random.key(1), data, subset_size=80, num_steps=60, first=True))
        model, mean = MB.build(data, 40)
        yield cfg, prog, data, model, mean
    finally:
        for name in ("test:balance", "test:balance_hard"):
            tasks._REGISTERED.pop(name, None)
        tasks.make_task.cache_clear()


def _holding(prog):
    """A controller that holds the system near 0: u = -2 tanh(0.4 x) (every particle survives)."""
    return prog.controller.init(jnp.float64)._replace(weights=jnp.asarray([-0.4, 0.0]))


def test_the_survival_objective_has_a_gradient_where_the_hard_end_has_none(balance):
    """Every particle survives the horizon: the stated 0/1 survival reward's return, with the
    hard end (a task with no margin), has gradient exactly 0; the survival objective's gradient is
    not 0 and matches central finite differences (float64)."""
    cfg, prog, _, model, mean = balance
    params = _holding(prog)
    plan = MB.make_plan(prog, cfg, model, jax.random.key(2), "mean", 4, 10)
    hard = prog._replace(task=tasks.make_task("test:balance_hard"))
    g_hard = jax.grad(lambda p: MB.simulate(hard, model, mean, plan, p,
                                            objective=MB.objectives.STATED))(params)
    assert float(MB.simulate(hard, model, mean, plan, params)) == 10.0  # all survive
    np.testing.assert_array_equal(np.asarray(g_hard.weights), 0.0)

    survival = MB.objectives.SURVIVAL
    f = jax.jit(lambda p: MB.simulate(prog, model, mean, plan, p, end_softness=0.1,
                                      objective=survival))
    g = np.asarray(jax.grad(f)(params).weights)
    assert np.all(np.abs(g) > 0) and float(f(params)) < 0.0
    h = 1e-5
    for i in range(2):
        e = jnp.zeros(2).at[i].set(h)
        fd = (float(f(params._replace(weights=params.weights + e)))
              - float(f(params._replace(weights=params.weights - e)))) / (2 * h)
        assert g[i] == pytest.approx(fd, rel=1e-6, abs=1e-12)


def test_the_survival_objective_is_the_log_probability_of_surviving_each_step(balance):
    """On one particle under the mean model, the objective is sum_t log(1 - sigmoid(m_t / s)) of
    the margins m_t of the states a NumPy roll-out of the model's mean visits."""
    cfg, prog, _, model, mean = balance
    params = _holding(prog)._replace(weights=jnp.asarray([-0.1, 0.05]))
    plan = MB.make_plan(prog, cfg, model, jax.random.key(3), "mean", 1, 8)
    got = float(MB.simulate(prog, model, mean, plan, params, end_softness=0.2,
                            objective=MB.objectives.SURVIVAL))
    x, want = float(plan.start[0, 0]), 0.0
    for _ in range(8):
        u = 2.0 * np.tanh(-0.1 * x + 0.05)
        x = x + float(MB.predict(model, jnp.asarray([x, u]))[0][0] + mean[0])
        want += np.log1p(-1.0 / (1.0 + np.exp(-(abs(x) - LIMIT) / 0.2)))
    assert got == pytest.approx(want, rel=1e-9)


def _loss_sat(m, z, w):
    """pilco-matlab's loss/lossSat.m at a known state (s = 0): the expected cost
    1 - exp(-(m - z)' W (m - z) / 2) / sqrt(det(I + s W)), written out in NumPy."""
    d = m - z
    s = np.zeros((len(m), len(m)))
    i_spw = w @ np.linalg.inv(np.eye(len(m)) + s @ w)
    return 1.0 - np.exp(-d @ i_spw @ d / 2) / np.sqrt(np.linalg.det(np.eye(len(m)) + s @ w))


# brax's tasks take their normalisation's episodes to make: the slow tier
@pytest.mark.parametrize("env", ["pendulum", "gymnax:Pendulum-v1",
                                 pytest.param("brax:inverted_pendulum", marks=pytest.mark.slow),
                                 pytest.param("brax:inverted_double_pendulum",
                                              marks=pytest.mark.slow)])
def test_the_saturating_objective_is_pilco_matlab_s_cost_on_the_declared_target(env):
    """A decision's saturating reward is hold x (1 - lossSat) with W = I / width^2 on the task's
    target, at random observations; 1 at the target itself."""
    task = tasks.make_task(env)
    rng = np.random.default_rng(4)
    for _ in range(5):
        obs = jnp.asarray(task.obs_centre + task.obs_scale * rng.normal(size=task.obs_dim))
        d = np.asarray(task.target(obs), np.float64)
        w = np.eye(len(d)) / task.target_width ** 2
        r = MB.objectives.SATURATING.reward(task, 2, obs, 0.0, obs, None, None)
        assert float(r) == pytest.approx(2 * (1 - _loss_sat(d, np.zeros_like(d), w)), rel=1e-10)
    upright = {"pendulum": [np.pi, 0.0], "gymnax:Pendulum-v1": [1.0, 0.0, 0.0]}
    if env in upright:
        assert float(MB.objectives.SATURATING.reward(
            task, 1, None, 0.0, jnp.asarray(upright[env]), None, None)) == pytest.approx(1.0)


def _numpy_rbf(params, y, u_max, linear):
    """The trainable RBF network in NumPy, its value and its gradient derived by hand."""
    c, logw, w, b, v = (None if p is None else np.asarray(p, np.float64) for p in params)
    ell = np.exp(logw)
    diff = y[None, :] - c
    phi = np.exp(-0.5 * np.sum((diff / ell) ** 2, axis=1))
    z = phi @ w + b + (v @ y if linear else 0.0)
    slope = u_max * (1 - np.tanh(z) ** 2)
    grads = (slope * (w * phi)[:, None] * diff / ell ** 2,
             slope * np.sum((w * phi)[:, None] * diff ** 2 / ell ** 2, axis=0),
             slope * phi, slope, slope * y if linear else np.zeros(0))
    return u_max * np.tanh(z), grads


@pytest.mark.parametrize("env,name", [("pendulum", "rbf_trainable"), ("pendulum", "linear_rbf"),
                                      ("gymnax:Pendulum-v1", "rbf_trainable"),
                                      pytest.param("brax:inverted_pendulum", "linear_rbf",
                                                   marks=pytest.mark.slow)])
def test_the_trainable_rbf_s_value_and_gradient_match_a_numpy_network(env, name):
    """c(s) and d c / d(centres, log widths, weights, bias, linear part) at random parameters,
    jax.grad against the NumPy network's hand-derived gradient (float64)."""
    task = tasks.make_task(env)
    ctrl = task.make_controller(name)
    rng = np.random.default_rng(5)
    p0 = ctrl.init(jnp.float64)
    params = jax.tree_util.tree_map(lambda x: x + 0.3 * jnp.asarray(rng.normal(size=x.shape)), p0)
    obs = jnp.asarray(task.obs_centre + task.obs_scale * rng.normal(size=task.obs_dim))
    if env == "pendulum":
        y = np.array([np.sin(obs[0]), np.cos(obs[0]), obs[1]])
    else:
        y = (np.asarray(obs) - task.obs_centre) / task.obs_scale
    want, want_grads = _numpy_rbf(params, y, ctrl.u_max, name == "linear_rbf")
    value, grads = jax.value_and_grad(ctrl.apply)(params, obs)
    assert float(value) == pytest.approx(want, rel=1e-12)
    assert (grads.linear is None) == (name == "rbf_trainable")
    for got, ref in zip(grads, want_grads):
        if got is not None:
            np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-10, atol=1e-14)


def test_the_trainable_rbf_starts_from_the_start_distribution_and_the_visited_states():
    """On a standard task, a quarter of the units start at observations of the start
    distribution (within its spread), the rest spread over the visited states; the number of
    units is the config's `controller_units`."""
    cfg = C.make_config(env="brax:inverted_pendulum", method="gp_model",
                        controller="rbf_trainable", controller_units=24)
    ctrl = rollouts.make_controller(cfg)
    centres = np.asarray(ctrl.init(jnp.float64).centres)
    assert centres.shape == (24, 4)
    task = tasks.make_task(cfg.env)
    starts = (tasks._start_observations(tasks._brax_adapter("inverted_pendulum"))
              - task.obs_centre) / task.obs_scale
    first = centres[:6]
    assert np.all(np.min(np.abs(first[:, None] - starts[None]).sum(-1), axis=1) < 1e-9)
    with pytest.raises(ValueError, match="controller_units: must be an integer >= 0"):
        C.make_config(env="brax:inverted_pendulum", method="gp_model", controller_units=-1)


def test_a_paper_method_refuses_the_trainable_controller_in_one_line():
    with pytest.raises(ValueError, match="TrainConfig.controller: gp_pg needs"):
        C.make_config(method="gp_pg", controller="rbf_trainable")


@pytest.mark.parametrize("reward,lacks", [("survival", "end_margin"), ("saturating", "target")])
def test_an_objective_a_task_cannot_give_is_refused_in_one_line(reward, lacks):
    with pytest.raises(ValueError, match=f"model_reward: '{reward}' plans with what "
                                         f"test:bare does not declare: tasks.Task.{lacks}"):
        tasks.register(_balance_task(False)._replace(name="test:bare", target=None))
        try:
            C.make_config(env="test:bare", method="gp_model", model_reward=reward)
        finally:
            tasks._REGISTERED.pop("test:bare", None)
            tasks.make_task.cache_clear()


def test_the_decaying_rate_is_a_cosine_to_the_final_fraction():
    """rate(lr, T, f)(t) = lr (f + (1 - f)(1 + cos(pi t / T)) / 2), written out."""
    sched = MB.optimise.rate(0.1, 50, 0.2)
    for t in (0, 10, 25, 49, 50):
        assert float(sched(t)) == pytest.approx(0.1 * (0.2 + 0.8 * (1 + np.cos(np.pi * t / 50)) / 2))
    assert float(MB.optimise.rate(0.1, 50)(30)) == pytest.approx(0.1)


@pytest.mark.slow  # a compilation per replayed iterate
def test_keep_best_returns_the_best_iterate_seen_on_the_plan(balance):
    """With a step size far too large, the last iterate is worse than one seen before it;
    keep_best returns an iterate whose simulated return is the best of every iterate's (each
    evaluated afresh), and reports it."""
    cfg, prog, _, model, mean = balance
    plan = MB.make_plan(prog, cfg, model, jax.random.key(6), "mean", 4, 10)
    params = prog.controller.init(jnp.float64)
    kw = dict(num_steps=12, learning_rate=3.0, beta=1.0, optimistic=False,
              objective=MB.objectives.STATED, end_softness=0.1)
    last, _, _, after_last = MB.optimise_controller(prog, model, mean, plan, params, None, **kw)
    best, _, _, after_best = MB.optimise_controller(prog, model, mean, plan, params, None,
                                                    keep_best=True, **kw)
    f = lambda p: float(MB.simulate(prog, model, mean, plan, p, end_softness=0.1))  # noqa: E731
    assert float(after_best) == pytest.approx(f(best), rel=1e-12)
    assert float(after_last) == pytest.approx(f(last), rel=1e-12)
    # every iterate of the run without keep_best, replayed one step at a time
    seen = [f(params)]
    p = params
    for n in range(1, 13):
        p, _, _, _ = MB.optimise_controller(prog, model, mean, plan, params, None,
                                            **{**kw, "num_steps": n})
        seen.append(f(p))
    assert f(best) == pytest.approx(max(seen), rel=1e-9)


def test_restarts_keep_the_controller_with_the_best_return_on_the_held_aside_particles(balance):
    """improve with 3 restarts and held-aside particles returns one of the three runs (each
    reproduced alone from its start), the one whose return on the held-aside plan is the best."""
    cfg, prog, data, model, mean = balance
    cfg = C.validate(cfg.replace(model_restarts=3, model_held_aside=5, model_steps=5,
                                 model_learning_rate=0.2))
    key = jax.random.key(7)
    params, _, before, after = MB.improve(prog, cfg, model, mean, key,
                                          prog.controller.init(jnp.float64), data.hallucination)
    own = cfg.settings
    k_plan, _, k_restart, k_aside = jax.random.split(key, 4)
    plan = MB.make_plan(prog, cfg, model, k_plan, "mean", own.particles, MB.plan_steps(prog, cfg))
    aside = MB.make_plan(prog, cfg, model, k_aside, "mean", 5, MB.plan_steps(prog, cfg))
    zeros = prog.controller.init(jnp.float64)
    eps = jax.random.normal(jax.random.split(k_restart, 1)[0], (2, 2), jnp.float64)
    starts = [zeros] + [zeros._replace(weights=zeros.weights + MB.method.RESTART_SCALE * e)
                        for e in eps]
    runs, scores = [], []
    for s in starts:
        p, _, _, _ = MB.optimise_controller(
            prog, model, mean, plan, s, None, num_steps=5, learning_rate=0.2, beta=1.0,
            optimistic=False, objective=MB.objectives.STATED, end_softness=own.end_softness)
        runs.append(p)
        scores.append(float(MB.simulate(prog, model, mean, aside, p, end_softness=own.end_softness)))
    best = int(np.argmax(scores))
    np.testing.assert_allclose(np.asarray(params.weights), np.asarray(runs[best].weights),
                               rtol=1e-10)
    assert float(before) == pytest.approx(float(MB.simulate(prog, model, mean, plan, zeros,
                                                            end_softness=own.end_softness)))
    assert len({round(s, 6) for s in scores}) == 3


def test_visited_starts_draw_the_last_particles_from_the_valid_observations(balance):
    """make_plan with a share of visited starts: the last particles start at valid buffered
    observations only; with no valid row yet, every particle starts from the start distribution."""
    cfg, prog, _, model, _ = balance
    obs = jnp.arange(10.0)[:, None] + 5.0
    valid = jnp.asarray([False, True, False, True] + [False] * 6)
    plan = MB.make_plan(prog, cfg, model, jax.random.key(8), "mean", 8, 3, (obs, valid), 4)
    assert set(np.asarray(plan.start[4:, 0]).tolist()) <= {6.0, 8.0}
    assert np.all(np.abs(np.asarray(plan.start[:4])) <= 0.2)
    none = MB.make_plan(prog, cfg, model, jax.random.key(8), "mean", 8, 3,
                        (obs, jnp.zeros(10, bool)), 4)
    assert np.all(np.abs(np.asarray(none.start)) <= 0.2)


def test_fresh_draws_optimise_on_another_plan_at_every_step(balance):
    """fresh_plan(i) is the plan of step i: given the update's own plan at every step, the run
    is the common-random-numbers one; given other plans, it moves differently."""
    cfg, prog, _, model, mean = balance
    plan = MB.make_plan(prog, cfg, model, jax.random.key(9), "mean", 4, 10)
    params = _holding(prog)._replace(weights=jnp.asarray([0.0, 0.3]))
    kw = dict(num_steps=6, learning_rate=0.1, beta=1.0, optimistic=False,
              objective=MB.objectives.STATED, end_softness=0.1)
    crn = MB.optimise_controller(prog, model, mean, plan, params, None, **kw)[0]
    same = MB.optimise_controller(prog, model, mean, plan, params, None,
                                  fresh_plan=lambda i: plan, **kw)[0]
    np.testing.assert_allclose(np.asarray(same.weights), np.asarray(crn.weights), rtol=1e-12)
    other = MB.optimise_controller(
        prog, model, mean, plan, params, None, **kw,
        fresh_plan=lambda i: MB.make_plan(prog, cfg, model, jax.random.fold_in(
            jax.random.key(10), i), "mean", 4, 10))[0]
    assert not np.allclose(np.asarray(other.weights), np.asarray(crn.weights))


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["rbf_trainable", "linear_rbf"])
def test_gp_model_trains_with_a_trainable_controller_and_every_search_option(controller):
    """A whole run (two updates) on the paper's pendulum with a trainable controller, the
    saturating objective and every option of the search: its records are finite, the real
    episodes act with the controller (their noise's score needs its gradient, by autodiff) and
    the update moved its centres and widths."""
    from gpguided_jax import train as T

    cfg = C.make_config(method="gp_model", controller=controller, episode_length=20,
                        num_updates=2, episodes_per_update=1, model_inducing=20, hold_time=0.02,
                        model_particles=4, model_horizon=0.2, model_steps=3,
                        model_reward="saturating", model_visited_starts=0.5,
                        model_fresh_draws=True, model_keep_best=True, model_restarts=2,
                        model_held_aside=2, model_final_rate=0.1)
    state, rec = jax.jit(T.make_train(cfg))(jax.random.key(11))
    for name in ("model_return", "model_gain", "eval_return" if cfg.eval_episodes else "mean_reward"):
        assert np.all(np.isfinite(np.asarray(getattr(rec, name)))), name
    start = rollouts.make_controller(cfg).init(jnp.float64)
    assert not np.allclose(np.asarray(state.theta.controller.centres), np.asarray(start.centres))
    assert not np.allclose(np.asarray(state.theta.controller.log_widths),
                           np.asarray(start.log_widths))
