"""gp_model's optimisation of the controller through the simulated roll-outs (design:
docs/design.md#model).

The optimiser is a value (`Optimiser`): ADAM (the gradient clipped to norm 1e3, then Adam) or
LBFGS (optax's L-BFGS with its zoom line search; the plan's common random numbers make the
objective deterministic). `ModelSettings.optimizer` names one (`OPTIMISERS`).
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
OPTIMISERS: dict[str, Optimiser] = {o.name: o for o in (ADAM, LBFGS)}


def optimise(prog, model, target_mean, plan, params, hallucination, *, num_steps: int,
             learning_rate, beta, optimistic: bool, optimizer: str | Optimiser = "adam",
             end_softness=0.1, objective=None):
    """`num_steps` steps of `optimizer` (an `Optimiser` or its name) on the simulated return
    (`simulate` with `objective`) from `params`, and eta's parameters under optimism. A step
    whose value or gradient is not finite is not taken. Returns (params, hallucination, return
    before, return after)."""
    opt_spec = OPTIMISERS[optimizer] if isinstance(optimizer, str) else optimizer

    def objective_fn(p):
        c, h = p
        return -simulate(prog, model, target_mean, plan, c, h if optimistic else None, beta,
                         end_softness, objective)

    value_and_grad = jax.value_and_grad(objective_fn)
    p0 = (params, hallucination)
    opt = opt_spec.make(learning_rate)

    def step(carry, _):
        p, opt_state = carry
        value, g = value_and_grad(p)
        if opt_spec.line_search:
            updates, new_state = opt.update(g, opt_state, p, value=value, grad=g,
                                            value_fn=objective_fn)
        else:
            updates, new_state = opt.update(g, opt_state, p)
        new_p = optax.apply_updates(p, updates)
        ok = jnp.isfinite(value) & jnp.all(jnp.stack(
            [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves((g, new_p))]))
        keep = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(ok, x, y), a, b)  # noqa: E731
        return (keep(new_p, p), keep(new_state, opt_state)), value

    (p, _), values = jax.lax.scan(step, (p0, opt.init(p0)), None, length=num_steps)
    return p[0], p[1], -values[0], -objective_fn(p)
