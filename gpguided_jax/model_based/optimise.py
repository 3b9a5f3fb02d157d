"""gp_model's optimisation of the controller through the simulated roll-outs (design:
docs/design.md#model).

The optimiser is a value (`Optimiser`): ADAM (the gradient clipped to norm 1e3, then Adam, its
rate cosine-decayed to a fraction `final_rate` of the first over the steps) or LBFGS (optax's
L-BFGS with its zoom line search; the plan's common random numbers make the objective
deterministic). `ModelSettings.optimizer` names one (`OPTIMISERS`).

Two choices of the search (`ModelSettings`): `fresh_draws` draws a new plan (start states,
functions, noise) at every step, a stochastic gradient over the start distribution, where common
random numbers fix one plan for the whole update; `keep_best` keeps the iterate with the best
simulated return seen (early stopping on the simulated return), not the last one.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from gpguided_jax.model_based.rollout import simulate


class Optimiser(NamedTuple):
    """An optimiser of the simulated return.

    Attributes:
      name: its name (`ModelSettings.optimizer`).
      make: `make(learning_rate) -> optax.GradientTransformation`.
      line_search: whether its `update` takes the objective's value and function too (optax's
        `GradientTransformationExtraArgs` of a line search).
    """

    name: str
    make: Callable
    line_search: bool = False


ADAM = Optimiser("adam", lambda lr: optax.chain(optax.clip_by_global_norm(1e3), optax.adam(lr)))
LBFGS = Optimiser("lbfgs", lambda lr: optax.lbfgs(), line_search=True)


def rate(learning_rate, num_steps: int, final_rate=1.0):
    """The step size: `learning_rate` cosine-decayed to `learning_rate * final_rate` over
    `num_steps` steps (final_rate 1: constant)."""
    return optax.cosine_decay_schedule(learning_rate, max(num_steps, 1), final_rate)
OPTIMISERS: dict[str, Optimiser] = {o.name: o for o in (ADAM, LBFGS)}


def optimise(prog, model, target_mean, plan, params, hallucination, *, num_steps: int,
             learning_rate, beta, optimistic: bool, optimizer: str | Optimiser = "adam",
             end_softness=0.1, objective=None, final_rate=1.0, fresh_plan=None,
             keep_best: bool = False):
    """`num_steps` steps of `optimizer` (an `Optimiser` or its name) on the simulated return
    (`simulate` with `objective`) from `params`, and eta's parameters under optimism. A step
    whose value or gradient is not finite is not taken. `fresh_plan`: `fresh_plan(i) -> Plan`,
    the plan of step i (None: `plan` at every step); `keep_best`: return the iterate whose
    simulated return was the best seen (module notes). Returns (params, hallucination, return
    before, return after), both on `plan`."""
    opt_spec = OPTIMISERS[optimizer] if isinstance(optimizer, str) else optimizer

    def objective_on(pl):
        def objective_fn(p):
            c, h = p
            return -simulate(prog, model, target_mean, pl, c, h if optimistic else None, beta,
                             end_softness, objective)
        return objective_fn

    objective_fn = objective_on(plan)
    p0 = (params, hallucination)
    opt = opt_spec.make(rate(learning_rate, num_steps, final_rate))
    inf = jnp.asarray(jnp.inf, jnp.result_type(float))

    def step(carry, i):
        p, opt_state, best_p, best = carry
        step_fn = objective_fn if fresh_plan is None else objective_on(fresh_plan(i))
        value, g = jax.value_and_grad(step_fn)(p)
        if opt_spec.line_search:
            updates, new_state = opt.update(g, opt_state, p, value=value, grad=g,
                                            value_fn=step_fn)
        else:
            updates, new_state = opt.update(g, opt_state, p)
        new_p = optax.apply_updates(p, updates)
        ok = jnp.isfinite(value) & jnp.all(jnp.stack(
            [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves((g, new_p))]))
        keep = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(ok, x, y), a, b)  # noqa: E731
        better = jnp.isfinite(value) & (value < best)  # p's value (the iterate before the step)
        best_p = jax.tree_util.tree_map(lambda x, y: jnp.where(better, x, y), p, best_p)
        return (keep(new_p, p), keep(new_state, opt_state), best_p,
                jnp.where(better, value, best).astype(best.dtype)), value

    init = (p0, opt.init(p0), p0, inf.astype(jnp.result_type(*jax.tree_util.tree_leaves(p0))))
    (p, _, best_p, best), values = jax.lax.scan(step, init, jnp.arange(num_steps))
    last = objective_fn(p)
    if keep_best:
        if fresh_plan is not None:  # the values seen were on other plans: compare on `plan`
            best = objective_fn(best_p)
        p = jax.tree_util.tree_map(lambda x, y: jnp.where(best < last, x, y), best_p, p)
        last = jnp.minimum(best, last)
    before = values[0] if fresh_plan is None else objective_fn(p0)
    return p[0], p[1], -before, -last
