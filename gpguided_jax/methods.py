"""The method registry: every learning method is a declared `Method`, a value rather than a branch
(design: docs/design.md#methods).

A `Method` is, like an optax `GradientTransformation`, a small record of pure functions plus what
the method declares about itself:

  method_state = method.init(prog, key, cfg)                                   # its own state
  theta, opt_state, method_state, records = method.update(prog, cfg, state, batch)

`update` is the method's improvement step (steps 3-4 of Algorithm 1): it receives the update's
episodes after the shared steps 1-2 (roll-outs with the method's policy, and the GP take-in when
the method has a Q-GP prior) and returns the new policy parameters, optimiser state, its own state
and its own records. Everything else a driver needs is declared:

  policy          the policy that acts in the roll-outs (`policies.make_policy` name);
  prior           what is fitted before learning: 'none' or 'q_gp' (the kernel and prior mean of
                  the GP of Q(s, a), paper §VI);
  fit_fields      the config fields that prior's fit reads (drivers share one fit between the
                  methods of a run whose fit fields agree);
  records         the method's own per-update records, beside `SHARED_RECORDS`;
  explorations    the exploration schemes it accepts (`exploration.NOISES`);
  compare_with    the methods its results are compared against (probability of improvement);
  check           extra validation of a config of this method (raises `ValueError`);
  paper           whether it is one of the paper's methods (what `gpguided reproduce` runs by
                  default, Fig. 5).

  settings        the class of its own settings (`gpguided_jax.settings.declare`), or None;
  presets         the settings it was tuned to, per preset;
  context         what its policy reads in the roll-outs, made from the method's state (a
                  planner's model); by default the Q-GP's.

`train`, `reproduce`, `sweep`, the summaries and the studies read these declarations; none of them
compares a method's name to a string. The paper's four methods are declared in
`gpguided_jax.policy_gradient`, gp_critic in `gpguided_jax.critic`, gp_model in
`gpguided_jax.model_based`, each registered when its module is imported, and the package imports
them (`gpguided_jax/__init__.py`); a new method is a module with its `Method` and a call of
`register` (a test may register one too). This module is the registry only: it imports no method.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

PRIORS = ("none", "q_gp")

# The records every method has (`train.record_type`): what the shared steps 1-2 and the
# evaluation of the deterministic controller give, whatever the improvement step.
SHARED_RECORDS = (
    "mean_reward", "exploration_std", "num_basis_vectors", "fresh_bv_share", "gp_guard",
    "gp_mean_error_ratio", "success_rate", "eval_success_rate", "eval_reward", "mean_return",
    "eval_return",
)

# The config fields the Q-GP prior's fit reads (`train.fit_prior`): the fixed-noise policy's
# roll-outs from the initial parameters on the task, their returns-to-go and the fit's settings.
Q_GP_FIT_FIELDS = (
    "env", "pendulum", "dtype", "controller", "controller_units", "episode_length", "episode_end",
    "hold_time", "exploration", "noise_correlation_time", "noise_exponent", "noise_resample_time",
    "init_log_std", "discount", "hyperfit_samples", "hyperfit_steps", "hyperfit_optimizer",
    "hyperfit_subset",
)


class Method(NamedTuple):
    """One learning method as the drivers see it (module notes).

    Attributes:
      name: the method's name (`TrainConfig.method`).
      policy: the roll-out policy, a `policies.POLICY_NAMES` entry.
      prior: 'none' or 'q_gp'.
      init: `init(prog, key, cfg) -> method_state`, a pytree (`()` for none).
      update: `update(prog, cfg, state, batch) -> (theta, opt_state, method_state, records)`,
        `records` a dict of () arrays named by `records`.
      records: the names of the method's own records, in order.
      explorations: the exploration schemes the method accepts.
      compare_with: the methods its final performance is compared against.
      check: `check(cfg)` raises `ValueError` for a config this method cannot run (beyond the
        fields every method shares); None: no extra check.
      fit_fields: the config fields its prior's fit reads (empty without a prior).
      explain_exploration: why a scheme outside `explorations` is refused (for the error).
      paper: one of the paper's methods (Fig. 5; `paper()`).
      targets: `targets(prog, cfg, state, ep, returns) -> (H,)`, the targets its GP takes in for
        one episode (state: the update's `TrainState`, ep: the episode, returns: its
        returns-to-go); None: the returns-to-go (the paper's).
      eval_held: its evaluation episodes decide every `hold_time`, as its learning episodes do (a
        controller optimised for held actions, gp_model's); False: at every control step.
      settings: the class of the method's own settings (`settings.declare`), whose instance a
        config of this method holds as `TrainConfig.settings`; None: no settings of its own. Its
        `check(cfg)` validates them with the config they belong to.
      presets: preset name -> the settings the method was tuned to on it (flat names: shared
        fields and its own settings), applied by `config.preset` after the preset's fields.
      policy_optimiser: its update takes the shared optax ascent step on the policy's parameters
        (`TrainState.opt_state`, `policy_gradient.make_optimizer`); False: it keeps no optimiser
        state (`()`).
      context: `context(prog, cfg, state) -> ctx`, what its policy reads in an update's
        roll-outs, made from the update's `TrainState` (a planner's model, built from the
        method's state); None: the Q-GP's `rollouts.policy_context`.
    """

    name: str
    policy: str
    prior: str
    init: Callable[..., Any]
    update: Callable[..., Any]
    records: tuple[str, ...]
    explorations: tuple[str, ...]
    compare_with: tuple[str, ...] = ()
    check: Callable[[Any], None] | None = None
    fit_fields: tuple[str, ...] = ()
    explain_exploration: str = ""
    paper: bool = False
    eval_held: bool = False
    targets: Callable[..., Any] | None = None
    settings: type | None = None
    presets: dict[str, dict] = {}
    policy_optimiser: bool = True
    context: Callable[..., Any] | None = None

    @property
    def uses_gp(self) -> bool:
        """Whether the method has a Q-GP that takes in the update's episodes (steps 1-2)."""
        return self.prior == "q_gp"


_REGISTRY: dict[str, Method] = {}
# the modules of the built-in methods, in the order their methods are listed (the paper's first);
# the package imports them (`gpguided_jax/__init__.py`)
_BUILTIN_MODULES = ("gpguided_jax.policy_gradient", "gpguided_jax.critic",
                    "gpguided_jax.model_based.method")


def register(method: Method, *, replace: bool = False) -> Method:
    """Adds `method` to the registry (returns it). Raises `ValueError` for a name already taken
    (unless `replace`), an unknown prior, or records that clash with `SHARED_RECORDS`."""
    if method.prior not in PRIORS:
        raise ValueError(f"method {method.name!r}: unknown prior {method.prior!r}; choose from {PRIORS}")
    clash = set(method.records) & set(SHARED_RECORDS)
    if clash:
        raise ValueError(f"method {method.name!r}: records {sorted(clash)} are shared records")
    if method.prior == "q_gp" and not method.fit_fields:
        raise ValueError(f"method {method.name!r}: a prior needs the fields its fit reads")
    if method.name in _REGISTRY and not replace:
        raise ValueError(f"method {method.name!r} is already registered")
    if method.settings is not None:  # another class may not take its flat names (one may share
        # it, or extend it: a subclass keeps its base's flat names)
        related = lambda c: issubclass(c, method.settings) or issubclass(method.settings, c)  # noqa: E731
        taken = {}  # each flat name -> the method that first declared it
        for m in _REGISTRY.values():
            if m.name != method.name and m.settings and not related(m.settings):
                for f in m.settings.FLAT.values():
                    taken.setdefault(f, m.name)
        clash = sorted(set(method.settings.FLAT.values()) & set(taken))
        if clash:
            raise ValueError(f"method {method.name!r}: settings {clash} are already "
                             f"{taken[clash[0]]}'s")
    _REGISTRY[method.name] = method
    return method


def unregister(name: str) -> None:
    """Removes a registered method (a test's own)."""
    _REGISTRY.pop(name, None)


def get(name: str) -> Method:
    """The registered `Method` called `name`; `ValueError` naming the choices if there is none."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown method {name!r}; choose from {names()}")
    return _REGISTRY[name]


def _rank(name: str) -> int:
    """The built-in modules' methods in the modules' order, whichever was imported first; then
    the others (a test's), in registration order."""
    module = _REGISTRY[name].update.__module__
    return _BUILTIN_MODULES.index(module) if module in _BUILTIN_MODULES else len(_BUILTIN_MODULES)


def names() -> tuple[str, ...]:
    """Every registered method's name: the built-in ones (the paper's four first), then the
    others, each in registration order."""
    return tuple(sorted(_REGISTRY, key=_rank))  # a stable sort: registration order within a rank


def paper() -> tuple[str, ...]:
    """The paper's methods (Fig. 5), in registration order."""
    return tuple(m for m in names() if _REGISTRY[m].paper)


def gp_methods() -> tuple[str, ...]:
    """The registered methods with a Q-GP prior."""
    return tuple(m for m in names() if _REGISTRY[m].uses_gp)


def comparisons(methods=None) -> tuple[tuple[str, str], ...]:
    """The (x, y) pairs whose probability of improvement P(x > y) is reported: each method
    against the ones it declares in `compare_with`, among `methods` (default: all)."""
    chosen = names() if methods is None else tuple(methods)
    # grouped by the method compared against, so that each group reads as one baseline's column
    return tuple((x, y) for y in chosen for x in chosen
                 if x in _REGISTRY and y in _REGISTRY[x].compare_with)


def fit_inputs(cfg) -> dict | None:
    """The values of the config fields the prior of `cfg.method` reads (JSON-ready), or None for
    a method without a prior: two configs with equal fit inputs share one fitted prior."""
    method = get(cfg.method)
    if not method.fit_fields:
        return None
    full = cfg.to_json_dict()
    return {"prior": method.prior, **{f: full[f] for f in method.fit_fields}}


def shares_program(a: Method, b: Method) -> bool:
    """Whether two methods can be branches of one compiled program (`train.make_methods_train`):
    the same prior, initial state, improvement step and GP targets; only their policies differ."""
    return (a.prior == b.prior and a.init is b.init and a.update is b.update
            and a.targets is b.targets and a.context is b.context)


def setting_owners() -> dict[str, tuple[str, ...]]:
    """flat setting name -> the registered methods whose settings it is (`Method.settings`; methods
    may share a settings class), in the registry's order."""
    out: dict[str, tuple[str, ...]] = {}
    for name in names():
        cls = _REGISTRY[name].settings
        for f in () if cls is None else cls.FLAT.values():
            out[f] = out.get(f, ()) + (name,)
    return out
