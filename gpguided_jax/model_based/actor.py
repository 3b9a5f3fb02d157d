"""How gp_model acts in the real episodes (design: docs/design.md#model).

An `Actor` is the policy that acts in the roll-outs (`Method.policy`) and what the update leaves
it to act with. LEARNT_CONTROLLER, today's, acts with the controller optimised through the model
and the fixed-noise policy's Gaussian noise: exp(init_log_std) on the first update (the
exploratory episode that gives the model its first data), the floor `min_std` from then on. A
planner that acts is another `Actor`.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp


class Actor(NamedTuple):
    """What acts in the real episodes.

    Attributes:
      policy: the roll-out policy (`policies.POLICY_NAMES`).
      act_with: `act_with(prog, cfg, theta, controller_params) -> theta`, the policy parameters
        for the next update's episodes from the controller the update optimised.
    """

    policy: str
    act_with: Callable


def _learnt_controller(prog, cfg, theta, controller_params):
    return theta._replace(controller=controller_params,
                          log_std=jnp.log(jnp.asarray(cfg.min_std, prog.dtype)))


LEARNT_CONTROLLER = Actor("fixed_noise", _learnt_controller)
