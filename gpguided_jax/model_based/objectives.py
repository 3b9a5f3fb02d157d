"""gp_model's planning objective: the reward its simulated roll-outs sum (design:
docs/design.md#model).

An `Objective` is a value passed to the roll-out (`rollout.simulate`), not a branch inside it;
`OBJECTIVES` names them for `ModelSettings.reward`:

  STATED   the task's own statement as a function of the transition (`Task.reward_fn`);
  LEARNED  one more GP output on the same input (z, a), whose target is the reward of a decision
           (its control steps' rewards summed), in the same buffer, refit and conditioning as the
           dynamics' outputs. The roll-out reads a decision's reward from that output (its mean,
           or the particle's drawn function).
  SURVIVAL the log-probability of surviving, sum_t log(1 - p_end,t), with the end's smoothed
           probability p_end = sigmoid(margin / end_softness) from the task's own end condition
           (`Task.end_margin`). Where every particle survives, the 0/1 survival reward is flat and
           its gradient 0; this one's is -p_end / end_softness per step, never 0.
  SATURATING PILCO's saturating cost on the target the task declares (`Task.target`,
           `Task.target_width` sigma_c): a decision earns hold * exp(-|d|^2 / (2 sigma_c^2)),
           1 less pilco-matlab's `lossSat` cost, at the decision's end (1 - cost, not -cost, so
           that an episode's end loses what the rest would have earned, as the task's own
           survival reward does).

The evaluation is always the task's own reward, whichever objective planned. A new objective is a
new `Objective`, added to `OBJECTIVES` under its name.
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
      alive_weighted: whether the roll-out weighs a decision's reward by the particle's
        probability of being alive when it is taken (False: the objective accounts for the end
        itself, as SURVIVAL's log-probability does).
      needs: what the task must declare for it: (attribute of `Task`, what it is), each checked
        before a run starts.
    """

    name: str
    learned: bool
    reward: Callable
    alive_weighted: bool = True
    needs: tuple = ()


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


def saturating_cost(d, width):
    """pilco-matlab's `lossSat` at a known state: 1 - exp(-d^T W d / 2), W = I / width^2, for the
    displacement d from the target."""
    return 1.0 - jnp.exp(-0.5 * jnp.sum(d * d) / width ** 2)


def _survival(task, hold, obs, action, nxt, p_end, outputs):
    del task, hold, obs, action, nxt, outputs
    # log(1 - p): p < 1 in exact arithmetic, but it rounds to 1 for a far-gone particle
    return jnp.log1p(-jnp.minimum(p_end, 1.0 - jnp.finfo(p_end.dtype).eps))


def _saturating(task, hold, obs, action, nxt, p_end, outputs):
    del obs, action, p_end, outputs
    return hold * (1.0 - saturating_cost(task.target(nxt), task.target_width))


STATED = Objective("stated", False, _stated, needs=(("reward_fn", "its reward as a function of "
                                                    "the transition"),))
LEARNED = Objective("learned", True, _learned)
SURVIVAL = Objective("survival", False, _survival, alive_weighted=False,
                     needs=(("end_margin", "the signed margin of its end condition"),))
SATURATING = Objective("saturating", False, _saturating,
                       needs=(("target", "a target, the displacement from it in its units"),))
OBJECTIVES: dict[str, Objective] = {o.name: o for o in (STATED, LEARNED, SURVIVAL, SATURATING)}
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


def missing(task, objective: Objective) -> str | None:
    """What `task` lacks for `objective`, as a phrase naming the `Task` attribute to add (None:
    nothing)."""
    for attr, what in objective.needs:
        if getattr(task, attr) is None:
            return f"tasks.Task.{attr}: {what}"
    return None
