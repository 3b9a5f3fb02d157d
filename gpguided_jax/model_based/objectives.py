"""gp_model's planning objective: the reward its simulated roll-outs sum (design:
docs/design.md#model).

An `Objective` is a value passed to the roll-out (`rollout.simulate`), not a branch inside it;
`OBJECTIVES` names them for `ModelSettings.reward`:

  STATED   the task's own statement as a function of the transition (`Task.reward_fn`);
  LEARNED  one more GP output on the same input (z, a), whose target is the reward of a decision
           (its control steps' rewards summed), in the same buffer, refit and conditioning as the
           dynamics' outputs. The roll-out reads a decision's reward from that output (its mean,
           or the particle's drawn function).

A new objective (a cost on a declared target, a survival margin) is a new `Objective`, added to
`OBJECTIVES` under its name.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp


class Objective(NamedTuple):
    """The reward of one simulated decision.

    Attributes:
      name: the objective's name (`ModelSettings.reward` names the built-in ones).
      learned: whether the model learns the reward as one more output (the buffer then holds a
        last target column: the decision's reward).
      reward: `reward(task, hold, obs, action, next_obs, p_end, outputs) -> ()`, the decision's
        reward from its transition, the probability (or indicator) that it ends the episode
        (None for a task that never ends early) and the model's outputs at the decision's input
        (the particle's function, with the learnt reward last when `learned`).
    """

    name: str
    learned: bool
    reward: Callable


def stated_reward(task, hold: int, obs, action, nxt, end=None):
    """A decision's reward from the task's statement (`Task.reward_fn`): `hold` times the reward of
    the transition to the decision's end, of which only the last control step can end the episode
    (an end's bonus counts once). `end`: the end's indicator or probability (None: a task that
    never ends early)."""
    if end is None:
        return hold * task.reward_fn(obs, action, nxt)
    r = task.reward_fn(obs, action, nxt, end)
    if hold > 1:  # the hold's other steps do not end it
        r = r + (hold - 1) * task.reward_fn(obs, action, nxt, jnp.zeros_like(end))
    return r


def _stated(task, hold, obs, action, nxt, p_end, outputs):
    del outputs
    return stated_reward(task, hold, obs, action, nxt, p_end)


def _learned(task, hold, obs, action, nxt, p_end, outputs):
    del hold, obs, action, nxt, p_end
    return outputs[task.obs_dim]


STATED = Objective("stated", False, _stated)
LEARNED = Objective("learned", True, _learned)
OBJECTIVES: dict[str, Objective] = {o.name: o for o in (STATED, LEARNED)}
AUTO = "auto"  # the task's stated reward where it states one, else the learnt one


def names() -> tuple[str, ...]:
    """The choices of `ModelSettings.reward`: 'auto' and every objective's name."""
    return (AUTO, *OBJECTIVES)


def for_task(task, reward: str) -> Objective:
    """The objective named `reward` (`names()`) on `task`: 'auto' is STATED where the task states
    its reward, LEARNED otherwise."""
    if reward == AUTO:
        return LEARNED if task.reward_fn is None else STATED
    return OBJECTIVES[reward]
