"""gp_model's seams (`gpguided_jax.model_based`): a new planning objective, use of the model's
uncertainty, optimiser or actor is a value, registered under a name or declared as a method,
that the settings choose; nothing inside the roll-out or the method is edited for it."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from test_model_based import _pendulum_model

from gpguided_jax import config as C
from gpguided_jax import methods, rollouts
from gpguided_jax import model_based as MB
from gpguided_jax import train as T

STEPS = 6


def _constant_controller(prog, bias):
    """The RBF controller's parameters with zero weights: c(s) = u_max tanh(bias) everywhere."""
    zeros = prog.controller.init(jnp.float64)
    return zeros._replace(bias=jnp.asarray(bias, jnp.float64))


@pytest.mark.slow
@pytest.mark.xdist_group("model_pendulum")
def test_an_objective_chosen_by_name_is_what_the_roll_out_sums_and_the_optimiser_climbs(monkeypatch):
    """An action cost -a^2 registered as an objective: the simulated return of a constant action
    a is -T a^2 (by hand), whatever the model; the optimiser brings the action towards 0."""
    cost = MB.Objective("action_cost", False,
                        lambda task, hold, obs, a, nxt, p_end, out: -a ** 2)
    monkeypatch.setitem(MB.OBJECTIVES, "action_cost", cost)
    cfg, _, _, model, mean = _pendulum_model()
    cfg = C.validate(cfg.replace(model_reward="action_cost"))
    with pytest.raises(ValueError, match="model_reward: unknown model reward 'action_costs'"):
        C.validate(cfg.replace(model_reward="action_costs"))
    prog = rollouts.make_program(cfg)
    plan = MB.make_plan(prog, cfg, model, jax.random.key(0), "mean", 3, STEPS)
    params = _constant_controller(prog, 0.4)
    a = prog.controller.u_max * np.tanh(0.4)
    ret = jax.jit(lambda p: MB.simulate(prog, model, mean, plan, p))(params)
    assert float(ret) == pytest.approx(-STEPS * a ** 2, rel=1e-12)
    assert not np.isclose(float(MB.simulate(prog, model, mean, plan, params,
                                            objective=MB.objectives.STATED)), float(ret))
    new, _, before, after = jax.jit(lambda p, h: MB.optimise_controller(
        prog, model, mean, plan, p, h, num_steps=30, learning_rate=0.05, beta=1.0,
        optimistic=False, objective=cost))(params, None)
    assert float(before) == pytest.approx(float(ret)) and float(after) > 0.5 * float(before)
    assert abs(float(new.bias)) < 0.4


@pytest.mark.slow
@pytest.mark.xdist_group("model_pendulum")
def test_a_use_of_the_uncertainty_chosen_by_name_gives_the_particles_their_functions(monkeypatch):
    """A use that gives every particle the zero function: each step then moves the observation by
    the targets' data mean alone, so the return is that of a NumPy roll-out of obs + mean (the
    angle wrapped), rewarded by the task's own reward."""
    frozen = MB.Uncertainty(
        "frozen", lambda model, key, n: jnp.zeros((n,) + model.weights.shape, model.weights.dtype))
    monkeypatch.setitem(MB.USES, "frozen", frozen)
    cfg, _, _, model, mean = _pendulum_model()
    cfg = C.validate(cfg.replace(model_exploration="frozen"))
    prog = rollouts.make_program(cfg)
    plan = MB.make_plan(prog, cfg, model, jax.random.key(1), "frozen", 2, STEPS)
    assert not np.any(np.asarray(plan.noise)) and plan.variance is None
    params = _constant_controller(prog, 0.3)
    ret = float(jax.jit(lambda p: MB.simulate(prog, model, mean, plan, p))(params))
    task, step = prog.task, np.asarray(mean) * np.asarray(prog.task.obs_scale)
    expected = []
    for obs in np.asarray(plan.start):
        total = 0.0
        for _ in range(STEPS):
            nxt = obs + step
            nxt[0] = np.mod(nxt[0], 2 * np.pi)
            total += float(task.reward_fn(obs, None, jnp.asarray(nxt)))
            obs = nxt
        expected.append(total)
    assert ret == pytest.approx(np.mean(expected), rel=1e-9)


@pytest.mark.slow
@pytest.mark.xdist_group("model_pendulum")
def test_an_optimiser_chosen_by_name_takes_its_own_step(monkeypatch):
    """Plain gradient ascent registered as an optimiser: one step is params + lr * the gradient
    of the simulated return (by `jax.grad`)."""
    monkeypatch.setitem(MB.OPTIMISERS, "sgd", MB.Optimiser("sgd", optax.sgd))
    cfg, _, _, model, mean = _pendulum_model()
    cfg = C.validate(cfg.replace(model_optimizer="sgd"))
    prog = rollouts.make_program(cfg)
    plan = MB.make_plan(prog, cfg, model, jax.random.key(2), "mean", 3, STEPS)
    params = jax.tree_util.tree_map(
        lambda p: jnp.asarray(np.random.default_rng(3).normal(size=p.shape) * 0.3),
        prog.controller.init(jnp.float64))
    new, _, _, _ = MB.optimise_controller(prog, model, mean, plan, params, None, num_steps=1,
                                          learning_rate=0.1, beta=1.0, optimistic=False,
                                          optimizer=cfg.settings.optimizer)
    grad = jax.grad(lambda p: MB.simulate(prog, model, mean, plan, p))(params)
    for got, p, g in zip(*map(jax.tree_util.tree_leaves, (new, params, grad))):
        np.testing.assert_allclose(got, p + 0.1 * g, rtol=1e-10, atol=1e-12)


@pytest.mark.training
def test_an_actor_declared_as_a_method_acts_after_every_update():
    """gp_model with another actor, declared under its own name by `make_method`: it shares
    gp_model's settings (by their flat names) and acts with what its actor leaves; here the
    controller with the initial exploration noise kept, where gp_model's drops to min_std."""
    keep_noise = MB.Actor("fixed_noise",
                          lambda prog, cfg, theta, params: theta._replace(controller=params))
    methods.register(MB.make_method("gp_model_exploring", actor=keep_noise))
    try:
        small = dict(num_updates=2, episodes_per_update=1, model_inducing=8, model_steps=2,
                     model_particles=2, model_horizon=0.05, init_log_std=float(np.log(2.0)),
                     min_std=0.05)
        runs = {}
        for m in ("gp_model", "gp_model_exploring"):
            cfg = C.preset("tiny", method=m, **small)
            assert cfg.settings == C.preset("tiny", method="gp_model", **small).settings
            runs[m] = jax.jit(T.make_train(cfg))(jax.random.key(0))
        np.testing.assert_allclose(runs["gp_model_exploring"][0].theta.log_std, np.log(2.0))
        np.testing.assert_allclose(runs["gp_model"][0].theta.log_std, np.log(0.05))
        # the first update's episodes act alike (the same initial policy and draws)
        np.testing.assert_array_equal(runs["gp_model"][1].mean_reward[0],
                                      runs["gp_model_exploring"][1].mean_reward[0])
    finally:
        methods.unregister("gp_model_exploring")
