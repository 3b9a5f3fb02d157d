"""Sweeps over one traced config field x seeds as one compiled program.

The grid (values x seeds) is flattened into one axis of runs: the configs differ only in traced
leaves of `TrainConfig`, so the stacked configs are one more argument of a single program (one for
init, one for a chunk of updates), whatever the number of values. The runs are split over the
devices and run as `gpguided reproduce` runs its seeds (`sharding.per_seed_program`): on a CPU one
device per core, each taking its runs one after another, on an accelerator as one batch. On a
CPU every run's records are therefore those of the same seed and config run alone, bit for bit.
Static fields (sizes, method, controller, ...) fix shapes or the program and cannot be swept this
way: they are refused with a message naming the field. The `gpguided sweep` command is a thin
wrapper over `run_sweep`.

Output directory layout (`write_sweep`):
  config.json          the base config, the swept field and values, seeds
  results.npz          param, values, seeds, per-update records of shape (values, seeds, updates)
  sweep.csv            per value: final performance (mean reward per step over the last 10% of
                       updates), mean and 95% t-interval over seeds, initial performance, updates to
                       90%, mean fresh-BV share, seeds with skipped non-finite gradient estimates
  sweep_<param>.png    final performance vs the value with the 95% band, and the learning curves
"""

from __future__ import annotations

import csv
import json
import os
import sys
import time
from typing import Callable, NamedTuple, Sequence

import jax
import numpy as np

from gpguided_jax import config as config_lib
from gpguided_jax import methods, sharding, summaries
from gpguided_jax import stats as stats_lib
from gpguided_jax import train as train_lib

ALIASES = {"lambda": "age_penalty", "beta": "inverse_temperature", "lr": "learning_rate"}


def sweepable_fields() -> tuple[str, ...]:
    """The scalar traced fields, and every method's traced settings by their flat names."""
    return tuple(f for f in config_lib.TRACED_FIELDS if f != "pendulum") + \
        config_lib.setting_names("traced")


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def resolve_param(name: str) -> str:
    """The `TrainConfig` field a sweep parameter names (aliases: lambda, beta, lr).

    Raises:
      ValueError: naming the field when it is unknown, static, or not a scalar traced field.
    """
    field = ALIASES.get(name, name)
    aliases = ", ".join(f"{a}->{f}" for a, f in ALIASES.items())
    sweepable = sweepable_fields()
    if config_lib.is_static(field):
        raise ValueError(
            f"cannot sweep {name!r}: TrainConfig.{field} is a static field (it fixes shapes or the "
            "compiled program), so each value would need its own program; run one `gpguided "
            f"reproduce`/`make_train` per value instead. Sweepable fields: {', '.join(sweepable)}"
        )
    if field == "pendulum":
        raise ValueError(
            "cannot sweep 'pendulum': TrainConfig.pendulum is a structure of physics parameters, "
            "not one number; sweep a scalar traced field instead: " + ", ".join(sweepable)
        )
    if field not in sweepable:
        raise ValueError(
            f"unknown TrainConfig field {name!r}; sweepable (traced) fields: "
            f"{', '.join(sweepable)} (aliases: {aliases})"
        )
    return field


def even_chunk_size(total: int, max_chunk: int) -> int:
    """The largest divisor of `total` that is <= `max_chunk` (>= 1): every chunk then has the same
    length, so the chunk function compiles once."""
    max_chunk = max(1, min(int(max_chunk), int(total)))
    return max(d for d in range(1, max_chunk + 1) if total % d == 0)


class SweepResult(NamedTuple):
    """A finished sweep.

    Attributes:
      param: the swept `TrainConfig` field.
      values: (V,) its values.
      seeds: (S,) the seeds.
      records: dict field -> (V, S, num_updates) per-update records (`train.UpdateRecord`).
      config: the base `TrainConfig` (the swept field at its preset value).
      rows: per value, the summary dicts of `summarise_sweep`.
      wall_s: wall time of the run in seconds (compilation included).
    """

    param: str
    values: np.ndarray
    seeds: np.ndarray
    records: dict
    config: config_lib.TrainConfig
    rows: list
    wall_s: float


def summarise_sweep(param: str, values: Sequence[float], records: dict) -> list[dict]:
    """Per value: final performance (mean reward per step over the last 10% of updates) with its
    mean and 95% t-interval over seeds, initial performance and updates to 90% (as
    `summaries.summarise`); the mean share of basis vectors added by the latest update (Fig. 1's
    quantity, what lambda acts on); and the number of seeds with skipped non-finite gradient
    estimates (such a run keeps its last finite policy, so its final performance is suspect).

    Args:
      records: dict field -> (V, S, num_updates), with at least mean_reward, fresh_bv_share and
        nonfinite_grad.
    """
    rows = summaries.summarise(
        {str(v): {"mean_reward": records["mean_reward"][i]} for i, v in enumerate(values)})
    out = []
    for i, (v, r) in enumerate(zip(values, rows)):
        r = {k: r[k] for k in ("seeds", "initial_mean", "final_mean", "ci95_low", "ci95_high",
                               "updates_to_90pct")}
        r["fresh_bv_share_mean"] = float(np.mean(records["fresh_bv_share"][i]))
        r["seeds_with_skipped_updates"] = (
            int(np.sum(np.any(records["nonfinite_grad"][i] > 0, axis=-1)))
            if "nonfinite_grad" in records else 0)
        r["seeds_with_gp_guard"] = int(np.sum(np.any(records["gp_guard"][i] > 0, axis=-1)))
        out.append({param: float(v), **r})
    return out


def run_sweep(
    param: str,
    values: Sequence[float],
    *,
    method: str = "gp_pg",
    preset: str = "paper",
    seeds: Sequence[int] = tuple(range(5)),
    overrides: dict | None = None,
    chunk_size: int = 50,
    num_devices: int | None = None,
    progress: Callable[[str], None] = _log,
    seed_loop: str = "auto",
) -> SweepResult:
    """Trains `method` for every (value, seed) pair of the grid as one program.

    Args:
      param: a traced `TrainConfig` field or alias (lambda, beta, lr).
      values: the values of the field (each is validated like any config value).
      method: the training method (static: the same for the whole grid).
      preset: the base preset; `overrides` are further (static or traced) field overrides.
      seeds: integer seeds; every value is run with the same seeds (same initial data and kernel).
      chunk_size: at most this many updates per compiled call (rounded down to a divisor of
        num_updates, so that the chunk compiles once); progress is reported after each.
      num_devices: shard the flattened grid over at most this many devices (default: all; on a
        CPU one device per core needs `gpguided sweep --cpu-devices` or
        `jax.config.update("jax_num_cpu_devices", n)` before JAX starts).
      seed_loop: how each device takes its runs: 'auto' (one after another on a CPU, one batch on
        an accelerator), 'map' or 'vmap' (`sharding.per_seed_program`).

    Returns:
      `SweepResult`.
    """
    field = resolve_param(param)
    owners = methods.setting_owners().get(field, (method,))
    if method not in owners:
        raise ValueError(f"cannot sweep {field!r} for {method}: it is a setting of "
                         f"{' and '.join(owners)}")
    values = [float(v) for v in values]
    seeds = [int(s) for s in seeds]
    if not values:
        raise ValueError("a sweep needs at least one value")
    if not seeds:
        raise ValueError("a sweep needs at least one seed")
    overrides = dict(overrides or {})
    if field in overrides:
        raise ValueError(f"TrainConfig.{field} is swept; do not also override it")
    base = config_lib.preset(preset, method=method, **overrides)
    cfgs = [config_lib.preset(preset, method=method, **{**overrides, field: v}) for v in values]

    t_start = time.perf_counter()
    mesh = sharding.make_mesh(num_devices)
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    grid = [(i, s) for i in range(len(values)) for s in seeds]  # value-major
    n_real = len(grid)
    grid += [grid[-1]] * ((-n_real) % mesh.devices.size)  # duplicates only fill devices
    stacked = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *[cfgs[i] for i, _ in grid])
    train = train_lib.make_train(base)

    def program(fn, donate=False):
        return sharding.per_seed_program(fn, mesh, loop, donate=donate)

    progress(f"[sweep {field}] {method} / {preset}: {len(values)} values x {len(seeds)} seeds = "
             f"{n_real} runs of {base.num_updates} updates, one program on {mesh.devices.size} "
             f"device(s) ({'one run after another' if loop == 'map' else 'one batch'} per device)")
    t0 = time.perf_counter()
    state = _initial_states(train, base, field, seeds, grid, stacked, mesh, program)
    progress(f"[sweep {field}] init (hyperparameter fit) {time.perf_counter() - t0:.1f}s")
    records = _run_chunks(train, base, field, state, sharding.shard(stacked, mesh), n_real,
                          even_chunk_size(base.num_updates, chunk_size), program, progress)
    shape = (len(values), len(seeds), base.num_updates)
    records = {k: v.reshape(shape) for k, v in records.items()}
    rows = summarise_sweep(field, values, records)
    wall = time.perf_counter() - t_start
    progress(f"[sweep {field}] done in {wall:.1f}s")
    for r in rows:
        if r["seeds_with_skipped_updates"]:
            progress(f"[sweep {field}] WARNING: {field}={r[field]:g}: {r['seeds_with_skipped_updates']} "
                     "seed(s) hit non-finite gradient estimates (skipped; the policy stays frozen "
                     "while they last)")
    return SweepResult(field, np.asarray(values), np.asarray(seeds), records, base, rows, wall)


def _initial_states(train, base, field, seeds, grid, stacked, mesh, program):
    """Every run's initial state. The GP prior is fitted once per seed and shared along the value
    axis unless the swept field is one the fit reads (then each run's init fits its own)."""
    keys = sharding.seed_keys([s for _, s in grid])
    if base.uses_gp and field not in methods.get(base.method).fit_fields:
        fit = program(lambda k: train.fit_kernel_for_seed(k, base))
        fit_keys = sharding.seed_keys(sharding.pad_seeds(seeds, mesh.devices.size))
        kern = jax.device_get(fit(sharding.shard(fit_keys, mesh)))
        idx = np.asarray([seeds.index(s) for _, s in grid])
        kern = jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], kern)
        init = program(lambda k, c, kp: train.init(k, c, kp))
        state = init(*sharding.shard((keys, stacked, kern), mesh))
    else:
        init = program(lambda k, c: train.init(k, c))
        state = init(*sharding.shard((keys, stacked), mesh))
    return jax.block_until_ready(state)


def _run_chunks(train, base, field, state, stacked, n_real, n, program, progress) -> dict:
    """All updates, `n` per compiled call, with progress after each: field -> (runs, updates)
    records of the first `n_real` runs (the rest only fill devices)."""
    chunk = program(lambda s, c: train.run_chunk(s, c, n), donate=True)
    records = {k: [] for k in train_lib.record_fields(base.method)}
    t0 = time.perf_counter()
    for done in range(n, base.num_updates + 1, n):
        state, rec = chunk(state, stacked)
        rec = jax.device_get(rec)
        for k in records:
            records[k].append(np.asarray(getattr(rec, k))[:n_real])
        elapsed = time.perf_counter() - t0
        eta = elapsed / done * (base.num_updates - done)
        msg = (f"[sweep {field}] updates {done}/{base.num_updates} | {elapsed:.1f}s | ETA {eta:.0f}s"
               f" | mean reward {np.mean(records['mean_reward'][-1][:, -1]):.3f}")
        bad = int(np.sum(records["nonfinite_grad"][-1])) if "nonfinite_grad" in records else 0
        if bad:
            msg += f" | WARNING: {bad} non-finite gradient estimates skipped"
        progress(msg)
    return {k: np.concatenate(v, axis=1) for k, v in records.items()}


def _x_scale(values: np.ndarray) -> tuple[str, dict]:
    """'log' when the values are positive and span at least a decade; 'symlog' (linear up to the
    smallest positive value) when they also include 0; otherwise 'linear'."""
    v = np.asarray(values, float)
    pos = v[v > 0]
    if len(pos) < 2 or pos.max() / pos.min() < 10 or np.any(v < 0):
        return "linear", {}
    if np.all(v > 0):
        return "log", {}
    return "symlog", {"linthresh": float(pos.min())}


def plot_sweep(result: SweepResult, path: str) -> str:
    """Final performance vs the swept value (mean, 95% band over seeds) and the mean learning curve
    of every value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = np.asarray(result.values, float)
    order = np.argsort(values)
    final = np.array([r["final_mean"] for r in result.rows])[order]
    lo = np.array([r["ci95_low"] for r in result.rows])[order]
    hi = np.array([r["ci95_high"] for r in result.rows])[order]
    x = values[order]
    n_seeds = len(result.seeds)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax.plot(x, final, "o-", label="mean over seeds")
    tail = max(1, int(round(0.1 * result.records["mean_reward"].shape[-1])))
    per_seed = result.records["mean_reward"][..., -tail:].mean(-1)[order]  # (V, S)
    ax.scatter(np.repeat(x, n_seeds), per_seed.ravel(), s=8, c="k", alpha=0.5, label="seeds")
    if n_seeds > 1:
        ax.fill_between(x, lo, hi, alpha=0.25, label="95% CI over seeds")
    ax.legend(fontsize=8)
    scale, kw = _x_scale(values)
    ax.set_xscale(scale, **kw)
    ax.set_xlabel(result.param)
    ax.set_ylabel("final performance (mean reward per step,\nlast 10% of updates)")
    ax.grid(alpha=0.3)
    ax.set_title(f"{result.config.method}: {n_seeds} seeds per value")

    curves = result.records["mean_reward"]
    w = min(10, curves.shape[-1])  # moving average: the per-update reward is noisy
    smooth = np.apply_along_axis(lambda c: np.convolve(c, np.ones(w) / w, mode="valid"), -1, curves)
    steps = np.arange(w, curves.shape[-1] + 1)
    for i in order:
        mean, half = stats_lib.t_interval(smooth[i], axis=0)
        line, = ax2.plot(steps, mean, label=f"{result.param}={values[i]:g}")
        if n_seeds > 1 and len(order) <= 3:
            ax2.fill_between(steps, mean - half, mean + half, alpha=0.15, color=line.get_color())
    ax2.set_xlabel("gradient updates performed")
    ax2.set_ylabel("average reward per step of an episode")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    ax2.set_title(f"learning curves (seed mean, {w}-update moving average)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def sweep_markdown(result: SweepResult) -> str:
    lines = [f"| {result.param} | initial | final (mean) | 95% CI | updates to 90% | fresh BV share "
             "| seeds with skipped updates |", "|---|---|---|---|---|---|---|"]
    for r in result.rows:
        lines.append(f"| {r[result.param]:g} | {r['initial_mean']:.3f} | {r['final_mean']:.4f} | "
                     f"[{r['ci95_low']:.3f}, {r['ci95_high']:.3f}] | {r['updates_to_90pct']:.0f} | "
                     f"{100 * r['fresh_bv_share_mean']:.1f}% | {r['seeds_with_skipped_updates']} |")
    return "\n".join(lines)


def write_sweep(result: SweepResult, out_dir: str, *, preset: str | None = None) -> dict:
    """Writes config.json, results.npz, sweep.csv and sweep_<param>.png; returns their paths."""
    os.makedirs(out_dir, exist_ok=True)
    paths = {
        "config": os.path.join(out_dir, "config.json"),
        "results": os.path.join(out_dir, "results.npz"),
        "csv": os.path.join(out_dir, "sweep.csv"),
        "figure": os.path.join(out_dir, f"sweep_{result.param}.png"),
    }
    with open(paths["config"], "w") as f:
        json.dump({"param": result.param, "values": result.values.tolist(),
                   "seeds": result.seeds.tolist(), "preset": preset, "wall_s": result.wall_s,
                   "base_config": result.config.to_json_dict()}, f, indent=2)
    np.savez(paths["results"], param=result.param, values=result.values, seeds=result.seeds,
             **result.records)
    with open(paths["csv"], "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(result.rows[0]))
        w.writeheader()
        w.writerows(result.rows)
    plot_sweep(result, paths["figure"])
    return paths
