"""gp_model's particle roll-outs through the model (design: docs/design.md#model).

`simulate` steps every particle of a `Plan` through the model with the controller, one decision
of `prog.hold` control steps at a time, and sums the planning objective's rewards (`Objective`),
each weighed by the particle's probability of being alive. The objective and the use of the
model's uncertainty are values it is given (the plan's functions, noise, variance factors,
reward bonus and information weight, and `hallucination`), so that neither is a branch on a name
here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpguided_jax.model_based import objectives
from gpguided_jax.model_based.data import next_of
from gpguided_jax.model_based.gp import SparseModel, fast_variance, k_star, mean_at, scaled
from gpguided_jax.model_based.uncertainty import Plan, information_bonus, optimistic_outputs


def objective_of(prog) -> objectives.Objective:
    """The planning objective of a gp_model program: its settings' reward on its task."""
    return objectives.for_task(prog.task, prog.config.settings.reward)


def simulate(prog, model: SparseModel, target_mean, plan: Plan, controller_params,
             hallucination=None, beta=None, end_softness=0.1, objective=None):
    """The mean over particles of the simulated returns: undiscounted sums of the objective's
    rewards over the plan's steps, each weighed by the particle's probability of being alive. A
    model step is one decision of k = `prog.hold` control steps, whose steps in between are not
    simulated. A task with an end margin (`Task.end_margin`) ends a step with probability
    sigmoid(margin / `end_softness`), a smoothed end whose gradient reaches the controller where
    the hard end's is 0 (its reward, where the end enters it, takes that probability too); a task
    with only `end_fn` ends hard. `hallucination`: eta's controller parameters, (E,)-batched (a
    hallucinating use of the uncertainty). `objective`: an `objectives.Objective` (default: the
    program's, `objective_of`). A plan with a `reward_bonus` beta raises the learnt reward to its
    upper confidence bound r + beta sigma_r before the objective reads it; one with an
    `information` weight lambda adds lambda sum_e sigma_e^2 of the dynamics' outputs to each
    decision's reward, weighed by the particle's probability of being alive when it is taken
    (`uncertainty.optimistic_outputs`, `information_bonus`). A plan that does not read the
    variance evaluates the particles' functions by `gp.mean_at`, whose derivative is in closed
    form, so that the reverse pass keeps (E, D) per step instead of the (E, M) kernel rows."""
    task, controller = prog.task, prog.controller
    if hallucination is not None and plan.variance is None:
        raise ValueError("an optimistic roll-out reads the model's variance factors: make its plan "
                         "with a hallucinating use of the uncertainty ('optimistic')")
    objective = objective_of(prog) if objective is None else objective
    noise_std = jnp.sqrt(model.kernels.noise_variance)  # (E,)
    hold, e = prog.hold, task.obs_dim
    row = scaled(model)

    def end_probability(nxt):
        if task.end_margin is not None:
            return jax.nn.sigmoid(task.end_margin(nxt) / end_softness)
        return task.end_fn(nxt).astype(nxt.dtype)

    def particle(obs0, w, eps):
        def step(carry, eps_t):
            obs, alive = carry
            a = controller.apply(controller_params, obs)
            x = task.features(obs, a)
            if plan.variance is None:  # the mean with its closed-form derivative
                out, var = mean_at(row, w, x) + target_mean, None
            else:  # the variance too, from the same kernel rows
                ks = k_star(model, x)
                out = jnp.sum(ks * w, axis=-1) + target_mean
                var = fast_variance(model, plan.variance, ks)
            delta = out[:e] + noise_std[:e] * eps_t[:e]
            if hallucination is not None:
                eta = jax.vmap(lambda p: controller.apply(p, obs))(hallucination) / controller.u_max
                delta = delta + beta * jnp.sqrt(var[:e]) * eta
            if plan.reward_bonus is not None:
                out = optimistic_outputs(out, var, e, plan.reward_bonus)
            nxt = next_of(task, obs, delta)
            p_end = None if task.end_fn is None else end_probability(nxt)
            r = objective.reward(task, hold, obs, a, nxt, p_end, out)
            if p_end is not None and objective.alive_weighted:
                r = alive * r
            if plan.information is not None:
                r = r + alive * information_bonus(var, e, plan.information)
            return (nxt, alive if p_end is None else alive * (1.0 - p_end)), r

        _, rewards = jax.lax.scan(step, (obs0, jnp.ones((), obs0.dtype)), eps)
        return jnp.sum(rewards)

    return jnp.mean(jax.vmap(particle)(plan.start, plan.weights, plan.noise))
