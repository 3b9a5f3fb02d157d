"""gp_model: the GP as a model of the task, the controller optimised through simulated roll-outs
(design: docs/design.md#model).

Where the paper's GP models Q(s, a), this method's GPs model the task's dynamics, as PILCO
(Deisenroth & Rasmussen 2011) and its particle successors (PIPPS, MC-PILCO) do. The package is
split where the field splits such a method (nrontsis/PILCO: models, controllers, rewards;
mbrl-lib: models, planning), each seam a value passed in rather than a branch inside the
roll-out:

  data          the transitions the model takes in, and its ring buffer;
  gp            the GP per output: the refit, the conditioning, predictions and drawn functions;
  objectives    the planning objective (`Objective`: the task's stated reward, or a learnt one);
  uncertainty   the uses of the model's uncertainty (`Uncertainty`: mean, sample, thompson,
                optimistic, optimistic_reward, optimistic_joint, information) and the plan of
                one update's particles;
  rollout       the particle roll-outs through the model;
  optimise      the controller's optimisation (`Optimiser`: Adam, L-BFGS);
  actor         what acts in the real episodes (`Actor`: the learnt controller);
  method        the method itself: its settings (`ModelSettings`), presets, `init`, `update`;
  planner       gp_mpc: a planner that acts (CEM or MPPI through the model at every decision),
                declared with `make_method` beside gp_model (`PlannerSettings`).

Importing the package registers both methods.
"""

from gpguided_jax.model_based import actor, data, gp, method, objectives, optimise, rollout, uncertainty
from gpguided_jax.model_based.actor import Actor
from gpguided_jax.model_based.data import (
    ModelData,
    decision_rewards,
    decisions,
    empty_data,
    next_of,
    take_in,
    targets_of,
    wrap,
)
from gpguided_jax.model_based.gp import (
    JITTER,
    SparseModel,
    build,
    condition,
    farthest_points,
    fast_variance,
    jitter_floor,
    k_star,
    mean_at,
    predict,
    refit,
    sample_weights,
    scaled,
    variance_factors,
)
from gpguided_jax.model_based.method import (
    RECORDS,
    ModelSettings,
    Transitions,
    improve,
    init,
    learns_reward,
    make_method,
    model_errors,
    model_keys,
    plan_steps,
    transitions,
    update,
)
from gpguided_jax.model_based.objectives import OBJECTIVES, Objective, stated_reward
from gpguided_jax.model_based.optimise import OPTIMISERS, Optimiser
from gpguided_jax.model_based.optimise import optimise as optimise_controller
from gpguided_jax.model_based.planner import PLANNER, SEQUENCE_OPTIMISERS, PlannerSettings, planner_steps
from gpguided_jax.model_based.rollout import simulate
from gpguided_jax.model_based.uncertainty import USES, Plan, Uncertainty, make_plan

# the names of the uses of the uncertainty and of the optimisers (`ModelSettings`' choices)
EXPLORATIONS = tuple(USES)
OPTIMIZERS = tuple(OPTIMISERS)

__all__ = [
    "EXPLORATIONS", "JITTER", "OBJECTIVES", "OPTIMISERS", "OPTIMIZERS", "RECORDS", "USES", "Actor",
    "actor", "build", "condition", "data", "decision_rewards", "decisions", "empty_data",
    "farthest_points", "fast_variance", "gp", "improve", "init", "jitter_floor", "k_star",
    "learns_reward", "make_method", "make_plan", "mean_at", "method", "model_errors", "model_keys",
    "ModelData", "ModelSettings", "next_of", "Objective", "objectives", "optimise",
    "optimise_controller", "Optimiser", "Plan", "plan_steps", "predict", "refit", "rollout",
    "sample_weights", "scaled", "simulate", "SparseModel", "stated_reward", "take_in", "targets_of",
    "Transitions", "transitions", "Uncertainty", "uncertainty", "update", "variance_factors", "wrap",
    # gp_mpc
    "planner", "PLANNER", "PlannerSettings", "planner_steps", "SEQUENCE_OPTIMISERS",
]
