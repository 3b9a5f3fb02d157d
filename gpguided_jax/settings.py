"""A method's own settings, declared next to its code (design: docs/design.md#methods).

A method that has settings of its own declares them as a frozen dataclass decorated with
`declare`, names the class in its `methods.Method` (`settings=`), and reads them from
`cfg.settings` inside its pure functions, static and traced alike:

    @settings.declare(static=("steps",), prefix="critic_", aliases={"trust_region": "trust_region"})
    class CriticSettings:
        steps: int = 50
        learning_rate: Any = 0.01
        trust_region: Any = 0.05

        def check(self, cfg) -> None: ...   # raises settings.SettingError naming the setting

The class is a pytree: its *static* fields (they fix shapes or the program) are metadata, the
others are leaves, so that a sweep over a traced setting stays one compiled program
(`jax.vmap` over stacked configs), as for the shared config's own traced fields.

A setting is known outside the method by its *flat name*, the prefix and the field's name
(`critic_steps`, `model_horizon`), or by an alias given for it (`trust_region`): these are the
names that presets, tuning records, `--set` and a run's `config.json` use, so that records kept
under them stay valid whatever the class calls its fields.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np


class SettingError(ValueError):
    """A setting that makes no sense; the message names it by its flat name."""


def declare(cls=None, *, static: tuple[str, ...] = (), prefix: str = "",
            aliases: dict[str, str] | None = None):
    """Makes `cls` a frozen dataclass and a pytree of its traced fields (`static` are metadata).

    Sets on the class: `STATIC` and `TRACED` (field names), `FLAT` (field -> its flat name:
    `prefix` + field, or the key of `aliases` whose value is the field)."""
    def wrap(c):
        c = dataclasses.dataclass(frozen=True)(c)
        names = [f.name for f in dataclasses.fields(c)]
        unknown = set(static) - set(names)
        if unknown:
            raise TypeError(f"{c.__name__}: static fields {sorted(unknown)} are not fields")
        by_field = {v: k for k, v in (aliases or {}).items()}
        if set(by_field) - set(names):
            raise TypeError(f"{c.__name__}: aliases name no field: {sorted(set(by_field) - set(names))}")
        c.STATIC = tuple(n for n in names if n in static)
        c.TRACED = tuple(n for n in names if n not in static)
        c.FLAT = {n: by_field.get(n, prefix + n) for n in names}
        jax.tree_util.register_dataclass(c, data_fields=list(c.TRACED), meta_fields=list(c.STATIC))
        return c

    return wrap if cls is None else wrap(cls)


def flat_names(cls) -> dict[str, str]:
    """flat name -> field of a settings class."""
    return {v: k for k, v in cls.FLAT.items()}


def from_flat(cls, values: dict[str, Any]):
    """An instance of `cls` from flat names (the others at their defaults); `TypeError` for a name
    that is not one of its settings."""
    fields = flat_names(cls)
    unknown = set(values) - set(fields)
    if unknown:
        raise TypeError(f"unknown {cls.__name__} setting(s): {sorted(unknown)}")
    return cls(**{fields[k]: v for k, v in values.items()})


def replace_flat(s, values: dict[str, Any]):
    """`s` with the settings named by their flat names changed."""
    fields = flat_names(type(s))
    return dataclasses.replace(s, **{fields[k]: v for k, v in values.items()})


def to_flat(s, which: str = "all") -> dict[str, Any]:
    """flat name -> value, JSON-ready (arrays as Python numbers or lists); `which`: 'all',
    'static' or 'traced'."""
    if s is None:
        return {}
    cls = type(s)
    names = {"all": cls.STATIC + cls.TRACED, "static": cls.STATIC, "traced": cls.TRACED}[which]
    out = {}
    for n in (n for n in cls.FLAT if n in names):  # in declaration order
        v = getattr(s, n)
        out[cls.FLAT[n]] = v if n in cls.STATIC else np.asarray(v).tolist()
    return out


def cast(s, dtype):
    """`s` with its traced fields as arrays of `dtype`."""
    if s is None:
        return None
    return dataclasses.replace(s, **{n: jnp.asarray(getattr(s, n), dtype) for n in type(s).TRACED})


def describe(cls) -> list[tuple[str, Any, bool]]:
    """(flat name, default, static) of each setting of `cls`, in declaration order."""
    return [(cls.FLAT[f.name], f.default, f.name in cls.STATIC) for f in dataclasses.fields(cls)]


# ------------------------------------------------------------------------------------------------
# Checks: each raises `SettingError` naming the setting by its flat name.
# ------------------------------------------------------------------------------------------------


def fail(name: str, message: str):
    raise SettingError(f"TrainConfig.{name}: {message}")


def _is_value(v) -> bool:
    return not isinstance(v, jax.core.Tracer)


def _integer(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, np.integer))


def choice(name: str, v, choices: tuple, what: str | None = None) -> None:
    if v not in choices:
        fail(name, f"unknown {what or name} {v!r}; choose from {choices}")


def integer(name: str, v, minimum: int) -> None:
    if not _integer(v) or v < minimum:
        fail(name, ("must be a positive integer" if minimum == 1
                    else f"must be an integer >= {minimum}") + f", got {v!r}")


def seconds(name: str, v) -> None:
    """A duration: a number > 0 (static)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
        fail(name, f"must be > 0 seconds, got {v!r}")


def number(name: str, v, ok: Callable[[float], bool] = lambda v: True, what: str = "a finite number",
           allow_inf: bool = False) -> None:
    """A static number, finite (or +inf where allowed) and `ok`."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (
            math.isfinite(v) or (allow_inf and v == math.inf)) or not ok(v):
        fail(name, f"must be {what}, got {v!r}")


def traced(name: str, v, *, positive: bool = False, non_negative: bool = False,
           allow_inf: bool = False) -> None:
    """A traced value (a tracer passes): finite (or +inf where allowed), and its sign."""
    if not _is_value(v):
        return
    arr = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(arr) | (allow_inf & (arr == np.inf))):
        fail(name, f"must be finite, got {v!r}")
    if positive and np.any(arr <= 0):
        fail(name, f"must be > 0, got {v!r}")
    if non_negative and np.any(arr < 0):
        fail(name, f"must be >= 0, got {v!r}")

