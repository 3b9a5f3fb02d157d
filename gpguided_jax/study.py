"""The protocol every study shares, so that a study script reads as its grid, its seeds and its
table (experiments/standard_tasks.py, exploration_study.py, swingup_study.py).

The protocol: the grid is written down (and committed) before any of its runs; the tuning seeds
(`TUNING_SEEDS`) are never reported; the held-out seeds (`HELDOUT_SEEDS`, or 1000-1019) give
the reported numbers; every method and baseline has the same budget (`grid_size` configurations
x the tuning seeds, each a full run of the same environment steps); the tuning record is kept,
and the table and figure are generated from the held-out files.

Here:

* Tuning (`coordinate_search`): stages of configurations (`stages` of a grid), each stage's
  configurations applied over the best settings so far, the best configuration seen kept after
  every stage; `search_beyond` searches settings a first tuning left alone, from its choice. A
  method's stage is one `sweep.run_sweep` program (`sweep_stage`), its score a function of the
  records (`final_return`, `final_success`; `by_score`, `by_success` order them). A study
  whose settings are not the preset's tuned ones (`Method.presets`) applies them over the
  preset's own fields (`preset_own`), as explicit overrides: nothing here changes the config
  module.
* Held-out runs: one method alone through `reproduce.reproduce` with explicit overrides
  (`run_method`: its records, its environment-steps axis and its wall time, which
  `reproduce` measures), and the resumable record of a study's runs (`run_parts`, `finished`: a
  part runs again only when its settings changed).
* Baselines (`baselines.NAMES`: brax's PPO and SAC): one per seed on a study's config, with the
  methods' budget of learning steps and the deterministic policy's evaluations, recorded under
  the methods' record names (`run_baseline`); a stage of a baseline's tuning
  (`baseline_stage`, scored as a method's stage is).
* Reports: `env_steps`, `smoothed`, `steps_to`, `median_ci`, `plot_band`, and the JSON files
  (`read_json`, `write_json`).

Environment steps. Every curve of a method lies on one axis, `env_steps`
(`summaries.env_steps_axis`, the axis of `summaries.steps_to_threshold`; results.npz's
`env_steps` is that of the updates' own episodes): a record sits at the experience spent when
it was measured, the hyperparameter fit's episodes included. Record u of the deterministic
policy's evaluation (eval_return, eval_success_rate, eval_reward) evaluates the policy before
update u's step, after u updates' episodes, so record 0 is the policy before any learning, at
the fit's steps; a record of an update's own episodes (mean_return, success_rate) is taken after
u + 1 updates' episodes. brax's baselines count the same way (their first evaluation, of the
initial policy, at 0 steps). Placing the evaluation at the end of its update instead would
credit each policy with one update of experience it had not yet used.
"""

from __future__ import annotations

import json
import os
import sys
import time
from typing import Callable, Iterable, NamedTuple, Sequence

import numpy as np

from gpguided_jax import baselines, checkpoints, reproduce, runtime, summaries, sweep
from gpguided_jax import config as config_lib
from gpguided_jax import methods as methods_lib
from gpguided_jax import stats as stats_lib
from gpguided_jax._x64 import enable_x64

TUNING_SEEDS = (100, 101)
HELDOUT_SEEDS = tuple(range(1000, 1010))
_DISCOUNTS = ("discount", "discount_horizon")  # two spellings of one field: one of them applies


def log(msg: str) -> None:
    """Prints `msg` to stderr with the time of day."""
    print(f"[{time.strftime('%X')}] {msg}", file=sys.stderr, flush=True)


def _silent(msg: str) -> None:
    del msg


def set_up(out: str) -> str:
    """A float64 study stage's process, before its first run: LAPACK single-threaded
    (`runtime.single_threaded_lapack`), the persistent compile cache, JAX's 64-bit mode; and its
    output directory `out`, created. Returns `out`."""
    runtime.single_threaded_lapack()
    runtime.set_compile_cache(runtime.DEFAULT_COMPILE_CACHE)
    enable_x64()
    os.makedirs(out, exist_ok=True)
    return out


# ------------------------------------------------------------------------------------------ files


def read_json(path: str, default=None):
    """The JSON file at `path`, or `default` where there is none."""
    if not os.path.exists(path):
        return default
    with open(path) as f:
        return json.load(f)


def write_json(path: str, obj) -> None:
    """Writes `obj` to `path` as indented JSON, atomically, creating its directory."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    checkpoints.atomic_write_text(path, json.dumps(obj, indent=2))


def record_result(path: str, header: dict, name: str, result: dict) -> dict:
    """Adds `name`'s `result` to the record at `path` (a tuning record: `header`'s fields and
    `methods`, name -> result), creating it with `header` where there is none; returns it."""
    rec = read_json(path) or {**header, "methods": {}}
    rec.update(header)
    rec["methods"][name] = result
    write_json(path, rec)
    return rec


# ----------------------------------------------------------------------------------------- config


def merge_overrides(*overrides: dict) -> dict:
    """Config overrides, later ones first: a discount given either way (`discount`, or
    `discount_horizon` in seconds) replaces the other spelling of an earlier one."""
    out: dict = {}
    for o in overrides:
        if any(k in o for k in _DISCOUNTS):
            out = {k: v for k, v in out.items() if k not in _DISCOUNTS}
        out.update(o)
    return out


def preset_own(preset: str, method: str) -> dict:
    """The overrides that give `method` the preset's own values of the fields that
    `method`'s tuned settings on `preset` set (`Method.presets`; the preset's field, else the
    config's or the method's default):
    a study's settings applied over them do not depend on another study's tuning."""
    own = config_lib.PRESETS[preset]
    defaults = config_lib.field_defaults(method)
    out: dict = {}
    for field in methods_lib.get(method).presets.get(preset, {}):
        if field in _DISCOUNTS:
            key = next((k for k in _DISCOUNTS if k in own), "discount")
            out[key] = own.get(key, defaults["discount"])
        elif field in own:
            out[field] = own[field]
        elif field in defaults:
            out[field] = defaults[field]
        else:
            raise ValueError(f"{method}'s preset {preset!r} (Method.presets) sets {field!r}, "
                             "which has no value of the preset's own to return to")
    return out


def env_steps(cfg: config_lib.TrainConfig) -> np.ndarray:
    """(num_updates,) environment steps spent when each of a run's records of the policy's return
    (and the per-update records that share its axis) was taken: `summaries.env_steps_axis`."""
    return summaries.env_steps_axis(summaries.task_budget(cfg), cfg.num_updates)


def learning_steps(cfg: config_lib.TrainConfig) -> int:
    """Environment steps of a run's updates (the hyperparameter fit's excluded): the budget every
    method and baseline of a study gets."""
    return cfg.num_updates * cfg.episodes_per_update * cfg.episode_length


# ----------------------------------------------------------------------------------------- tuning


def stages(grid: Sequence[tuple]) -> list[list[dict]]:
    """The configurations of each stage of a grid, as settings to apply over the best so far.

    Args:
      grid: (parameter, values) per stage; a tuple of parameters takes tuples of values (the
        listed combinations).
    """
    out = []
    for params, values in grid:
        if isinstance(params, (tuple, list)):
            out.append([dict(zip(params, v)) for v in values])
        else:
            out.append([{params: v} for v in values])
    return out


def grid_size(grid: Sequence[tuple]) -> int:
    """The number of configurations a grid tries (its tuning budget, in full runs per seed)."""
    return sum(len(values) for _, values in grid)


def check_budget(grids: dict, size: int) -> None:
    """Raises `ValueError` unless every grid of `grids` (name -> grid) tries `size`
    configurations."""
    sizes = {name: grid_size(g) for name, g in grids.items()}
    if set(sizes.values()) - {size}:
        raise ValueError(f"every method and baseline tries {size} configurations: {sizes}")


def by_score(tried: dict):
    """Sort key of a configuration scored by one number (`score`)."""
    return tried["score"]


def by_success(tried: dict):
    """Sort key of a configuration scored by its success rate (to 3 decimals), ties broken by its
    reward per step."""
    return round(tried["success"], 3), tried["reward"]


def coordinate_search(stage_list: Iterable[list[dict]], evaluate: Callable[[list[dict]], list],
                      *, key: Callable = by_score, start: dict | None = None,
                      log: Callable[[str], None] = _silent) -> dict:
    """Coordinate search: each stage's configurations over the best settings so far.

    Args:
      stage_list: per stage, the settings each configuration changes (`stages`).
      evaluate: maps a stage's full settings (one dict per configuration) to one dict per
        configuration: its scores and whatever else the record keeps (wall time, health).
      key: orders the configurations tried (`by_score`, `by_success`); the largest is chosen, the
        first one tried among equals.
      start: the settings of the first stage's configurations besides their own.
      log: receives a line per configuration.

    Returns:
      {'tried': [{'settings': ..., **scores}, ...] in the order tried, 'chosen': the settings of
      the best configuration tried}.
    """
    chosen = dict(start or {})
    tried: list[dict] = []
    for stage in stage_list:
        configs = [{**chosen, **change} for change in stage]
        results = list(evaluate(configs))
        if len(results) != len(configs):
            raise ValueError(f"evaluate returned {len(results)} results for {len(configs)} "
                             "configurations")
        for settings, result in zip(configs, results):
            tried.append({"settings": settings, **result})
            log(f"{settings}: {result}")
        chosen = dict(max(tried, key=key)["settings"])
    return {"tried": tried, "chosen": chosen}


def search_beyond(tuned: dict, grid: Sequence[tuple], evaluate: Callable[[list[dict]], list],
                  *, key: Callable = by_score, log: Callable[[str], None] = _silent,
                  done: Sequence[dict] = ()) -> dict:
    """A second coordinate search over settings a first tuning left alone (a `retune` stage): the
    tuned settings scored again as its first stage, so that every change is set beside them on
    the same footing, then `grid`'s stages over the best so far. Arguments and result as
    `coordinate_search`'s; `done`: records of an earlier search (its 'tried'), whose results a
    stage takes instead of running again where it tries exactly their settings, so that a grid
    grown by a stage runs only what is new."""
    recorded = {json.dumps(t["settings"], sort_keys=True):
                {k: v for k, v in t.items() if k != "settings"} for t in done}

    def evaluate_new(configs):
        keys = [json.dumps(c, sort_keys=True) for c in configs]
        if all(k in recorded for k in keys):
            return [recorded[k] for k in keys]
        return evaluate(configs)

    return coordinate_search([[{}]] + stages(grid), evaluate_new, key=key, start=tuned, log=log)


def unhealthy_seeds(records: dict) -> int:
    """Seeds of one configuration whose gradient was ever not finite, plus those whose GP health
    check ever fired (records (seeds, updates))."""
    return int(sum(np.sum(np.any(np.asarray(records[k]) > 0, axis=-1))
                   for k in ("nonfinite_grad", "gp_guard") if k in records))


def final_return(records: dict) -> dict:
    """{'score': the final return of the deterministic policy (`summaries.final_performance`),
    mean over seeds}."""
    return {"score": float(final(records["eval_return"]).mean())}


def final_success(records: dict) -> dict:
    """{'success', 'reward'}: the final success rate and reward per step of the deterministic
    policy, means over seeds."""
    return {"success": float(final(records["eval_success_rate"]).mean()),
            "reward": float(final(records["eval_reward"]).mean())}


def last_success(records: dict) -> dict:
    """{'success', 'reward'}: the success rate and reward per step of the deterministic policy at
    the last evaluation, means over seeds (a baseline's evaluations, of many episodes each)."""
    return {"success": float(np.asarray(records["eval_success_rate"])[:, -1].mean()),
            "reward": float(np.asarray(records["eval_reward"])[:, -1].mean())}


def sweep_stage(configs: list[dict], score: Callable[[dict], dict], *, method: str, preset: str,
                seeds: Sequence[int], progress: Callable[[str], None] = _silent) -> list[dict]:
    """A stage of a method's tuning as one `sweep.run_sweep` program.

    Args:
      configs: the config overrides of each configuration; they differ in one field (a traced
        one: one program for the stage; a static one: one program per configuration), or the
        stage has one configuration.
      score: maps one configuration's records ((seeds, updates) each) to its scores.

    Returns:
      Per configuration, its scores and `unhealthy_seeds`.
    """
    fields = list(dict.fromkeys(k for c in configs for k in c))
    missing = object()
    varying = [k for k in fields
               if any(c.get(k, missing) != configs[0].get(k, missing) for c in configs)]
    if len(varying) != 1 and len(configs) > 1:
        raise ValueError(f"a sweep's configurations differ in one field, these in {varying}")
    field = varying[0] if varying else None  # None: a stage of one configuration
    common = {k: configs[0][k] for k in fields if k != field}
    if field is None or config_lib.is_static(field):
        # a static field fixes the program: each configuration is its own one-value sweep
        recs = []
        for c in configs:
            lr = float(config_lib.preset(preset, method=method, **c).learning_rate)
            res = sweep.run_sweep("learning_rate", [lr], method=method, preset=preset,
                                  seeds=seeds, overrides={k: v for k, v in c.items()
                                                          if k != "learning_rate"},
                                  progress=progress)
            recs.append({k: v[0] for k, v in res.records.items()})
    else:
        res = sweep.run_sweep(field, [c[field] for c in configs], method=method, preset=preset,
                              seeds=seeds, overrides=common, progress=progress)
        recs = [{k: v[i] for k, v in res.records.items()} for i in range(len(configs))]
    return [{**score(rec), "unhealthy_seeds": unhealthy_seeds(rec)} for rec in recs]


def baseline_stage(configs: list[dict], score: Callable[["BaselineRun"], dict], *, name: str,
                   cfg: config_lib.TrainConfig, seeds: Sequence[int],
                   num_evals: int) -> list[dict]:
    """A stage of a baseline's tuning: each configuration's settings run on every seed
    (`run_baseline`).

    Args:
      configs: the settings of each configuration (`run_baseline`'s).
      score: maps one configuration's `BaselineRun` to its scores.

    Returns:
      Per configuration, its scores and `wall_s` (its seeds' seconds).
    """
    out = []
    for settings in configs:
        run = run_baseline(name, cfg, seeds, settings, num_evals=num_evals, progress=_silent)
        out.append({**score(run), "wall_s": run.wall_s})
    return out


# ---------------------------------------------------------------------------------------- heldout


class MethodRun(NamedTuple):
    """One method's run (`run_method`).

    Attributes:
      records: every record of the run, (seeds, updates) each.
      env_steps: (updates,) the environment steps of each record (`env_steps`).
      wall_s: seconds of its hyperparameter fit (when it made one) and its run, compilation
        included, as `reproduce.reproduce` measured them.
    """

    records: dict
    env_steps: np.ndarray
    wall_s: float


def run_method(preset: str, method: str, seeds: Sequence[int], run_dir: str, overrides: dict, *,
               dtype: str = "float64", chunk_size: int = 50, gp_program: str = "per_method",
               progress: Callable[[str], None] = log,
               keep_checkpoints: bool = False) -> MethodRun:
    """`method` alone on `seeds` with the preset and `overrides`, through `reproduce.reproduce`
    into `run_dir` (resumed from its checkpoint there, if any).

    `gp_program`: `reproduce`'s; 'per_method' (the default) compiles the method's own program, so
    that its wall time holds its own compilation, 'shared' the GP methods' one program (compiled
    once per process; the records agree to rounding). `keep_checkpoints`: `reproduce`'s (the
    final state stays in `run_dir`, for what a study reads of it)."""
    out = reproduce.reproduce(preset, seeds, [method], run_dir, dtype=dtype, chunk_size=chunk_size,
                              overrides=overrides, progress=progress, gp_program=gp_program,
                              keep_checkpoints=keep_checkpoints)
    if not out["complete"]:
        raise RuntimeError(f"{method} did not finish in {run_dir}")
    with np.load(os.path.join(run_dir, "results.npz")) as f:
        records = {k: f[k][0] for k in f.files if f[k].ndim == 3}
    # the axis of the run's return record (results.npz's env_steps is that of the updates' own
    # episodes, one update later than the deterministic policy's evaluations)
    cfg = config_lib.preset(preset, method=method, dtype=dtype, **overrides)
    return MethodRun(records, env_steps(cfg), float(out["wall_s"][method]))


class BaselineRun(NamedTuple):
    """One baseline's runs (`run_baseline`), one per seed.

    Attributes:
      records: the deterministic policy's evaluations, (seeds, evaluations) each, under the
        methods' record names: eval_return on a standard task; eval_success_rate and eval_reward
        (per step) on the paper's pendulum.
      env_steps: (evaluations,) the environment steps of each evaluation, the initial policy's
        (at 0) first (`baselines.after_initial_evaluation` leaves it out).
      wall_s: seconds of all the seeds' runs, compilation included.
      seed_wall_s: the same per seed.
    """

    records: dict
    env_steps: np.ndarray
    wall_s: float
    seed_wall_s: tuple


def run_baseline(name: str, cfg: config_lib.TrainConfig, seeds: Sequence[int], settings: dict, *,
                 num_evals: int, progress: Callable[[str], None] = log) -> BaselineRun:
    """brax's `name` (`baselines.NAMES`) on `cfg`'s task, one run per seed, with the methods'
    budget (`learning_steps(cfg)`) and episode length.

    Args:
      cfg: a study's config; its task (the paper's pendulum: `baselines.train_ppo` / `train_sac`,
        which record the swing-up success; a standard task: `baselines.train_on_task`), budget
        and episode length apply.
      settings: the trainer's settings over `baselines.PPO_DEFAULTS` / `SAC_DEFAULTS`, a
        'horizon' in seconds as the discount at `cfg`'s control interval
        (`baselines.trainer_settings`); the evaluations are the deterministic policy's (the mean
        action), as the methods' eval records are.
      num_evals: evaluations per run, the initial policy's included.
      progress: receives a line per seed.
    """
    dt = config_lib.control_interval(cfg) if "horizon" in settings else None
    kwargs = {"deterministic_eval": True, **baselines.trainer_settings(settings, dt)}
    budget = learning_steps(cfg)
    records, walls, steps = {}, [], None
    for seed in seeds:
        if cfg.env == "pendulum":
            train = {"ppo": baselines.train_ppo, "sac": baselines.train_sac}[name]
            r = train(cfg.pendulum, budget, cfg.episode_length, seed, num_evals=num_evals, **kwargs)
            got = {"eval_success_rate": r.success_rate, "eval_reward": r.reward_per_step}
        else:
            r = baselines.train_on_task(name, cfg.env, budget, cfg.episode_length, seed,
                                        num_evals=num_evals, **kwargs)
            got = {"eval_return": r.episode_return}
        for k, v in got.items():
            records.setdefault(k, []).append(v)
        walls.append(float(r.wall_time))
        steps = r.env_steps if steps is None else steps  # every seed's: brax's schedule
        progress(f"[{name}] seed {seed}: {r.env_steps[-1]} steps, {r.wall_time:.0f}s, "
                 + ", ".join(f"{k} {v[-1]:.3f}" for k, v in got.items()))
    return BaselineRun({k: np.stack(v) for k, v in records.items()}, np.asarray(steps),
                       float(sum(walls)), tuple(walls))


def _as_json(obj):
    return json.loads(json.dumps(obj))


def finished(path: str, **expected) -> bool:
    """Whether the JSON record at `path` exists and holds each of `expected`'s items (compared
    as JSON)."""
    rec = read_json(path)
    return rec is not None and all(rec.get(k) == _as_json(v) for k, v in expected.items())


def run_parts(path: str, header: dict, parts: dict, run: Callable[[str, dict], dict], *,
              settings_key: str = "overrides", log: Callable[[str], None] = log) -> dict:
    """Runs each part of a study that its record does not hold with the same settings.

    The record at `path` is `header`'s fields and `runs`: key -> {settings_key: settings,
    'wall_s': seconds, ...}, written after each part, so that a stopped stage resumes at the part
    it stopped in, and a part whose settings changed runs again.

    Args:
      header: the record's own fields (its seeds, at least); an existing record with other values
        of them is refused.
      parts: key -> settings, in the order to run.
      run: (key, settings) -> the part's record entries besides its settings; its `wall_s`, if
        absent, is the call's time.

    Returns:
      The record.

    Raises:
      ValueError: the record at `path` was made with another header (other seeds).
    """
    rec = read_json(path) or {**_as_json(header), "runs": {}}
    other = {k: rec.get(k) for k, v in header.items() if rec.get(k) != _as_json(v)}
    if other:
        raise ValueError(f"{path} holds runs with {other}, not {header}: remove it to start "
                         "afresh")
    for key, settings in parts.items():
        if rec["runs"].get(key, {}).get(settings_key) == _as_json(settings):
            continue
        t0 = time.perf_counter()
        entry = dict(run(key, settings) or {})
        wall = entry.pop("wall_s", time.perf_counter() - t0)
        rec["runs"][key] = {settings_key: settings, "wall_s": wall, **entry}
        write_json(path, rec)
        log(f"{key}: {wall:.0f}s")
    return rec


# ---------------------------------------------------------------------------------------- reports


def critic_diagnostics(runs: dict, path: str, figure: str | None = None) -> None:
    """What would limit gp_critic in held-out runs, written to `path` (JSON): for each run
    (name -> its results.npz) that records the critic, over its seeds, the critic's error on
    returns it had not seen (1 - R^2) over the first 10% and the last 10% of updates, the action
    length-scale of its kernel, and the fraction of the surrogate's move the trust region let
    through and the mean KL over the last 10%. A run whose results.npz is not here is left out;
    with none, the earlier file is kept.

    `figure`: also draw, per update, the medians over seeds of the critic's error, the fraction of
    the move taken and the mean KL, a line per run, into this PNG file."""
    rows, lines = [], {}
    for name, results in runs.items():
        if not os.path.exists(results):
            continue
        with np.load(results) as f:
            if "critic_error" not in f.files:
                continue
            rec = {k: np.asarray(f[k][0], float) for k in
                   ("critic_error", "action_lengthscale", "critic_step_fraction", "critic_kl")}
        tail = max(1, int(round(0.1 * rec["critic_error"].shape[1])))
        ls = rec["action_lengthscale"][:, 0]
        rows.append(dict(
            method=name, seeds=int(ls.size),
            error_first=float(np.median(rec["critic_error"][:, :tail])),
            error_last=float(np.median(rec["critic_error"][:, -tail:])),
            lengthscale_median=float(np.median(ls)), lengthscale_min=float(ls.min()),
            lengthscale_max=float(ls.max()),
            fraction_last=float(np.median(rec["critic_step_fraction"][:, -tail:])),
            kl_last=float(np.median(rec["critic_kl"][:, -tail:]))))
        lines[name] = rec
    if rows:
        write_json(path, {"rows": rows})
    if lines and figure is not None:
        _critic_figure(lines, figure)


def _critic_figure(runs: dict, figure: str) -> None:
    import matplotlib.pyplot as plt

    panels = (("critic_error", "critic error 1 − R² (unseen returns)", "log"),
              ("critic_step_fraction", "fraction of the move taken", "log"),
              ("critic_kl", "mean KL after the steps [nats]", "linear"))
    fig, axes = plt.subplots(1, len(panels), figsize=(12, 3.4))
    for ax, (key, label, scale) in zip(axes, panels):
        for name, rec in runs.items():
            med = np.median(rec[key], axis=0)
            ax.plot(np.arange(1, med.size + 1), np.maximum(med, 1e-4) if scale == "log" else med,
                    label=name)
        ax.set_yscale(scale)
        ax.set_xlabel("update")
        ax.set_title(label, fontsize=9)
    axes[0].axhline(1.0, color="k", ls="--", lw=0.8)  # no better than the returns' mean
    axes[0].legend(fontsize=7)
    fig.suptitle("gp_critic, median over held-out seeds", fontsize=9)
    fig.tight_layout()
    fig.savefig(figure, dpi=100)
    plt.close(fig)


def final(curves) -> np.ndarray:
    """Per seed: the mean of the last 10% of a curve's points ((seeds, points) -> (seeds,))."""
    return summaries.final_performance(np.asarray(curves, float))


def smoothed(curves: np.ndarray, window: int = 5) -> np.ndarray:
    """(seeds, points) trailing means over `window` points (fewer at the start)."""
    curves = np.asarray(curves, float)
    n = curves.shape[1]
    c = np.cumsum(np.pad(curves, ((0, 0), (1, 0))), axis=1)
    ends = np.arange(1, n + 1)
    return (c[:, 1:] - c[:, np.maximum(ends - window, 0)]) / np.minimum(ends, window)


def steps_to(steps: np.ndarray, curves: np.ndarray, level: float, *, tol: float = 0.0,
             never: float = np.inf) -> np.ndarray:
    """Per seed: the first of `steps` at which the curve is at least `level` - `tol` (`never`
    where it never is). (points,), (seeds, points) -> (seeds,)."""
    hit = np.asarray(curves) >= level - tol
    return np.where(hit.any(1), np.asarray(steps)[hit.argmax(1)], never)


def median_ci(x: np.ndarray, reps: int = 10_000, seed: int = 0) -> tuple[float, float, float]:
    """The median and its percentile-bootstrap 95% interval (inf entries: never reached; the
    quantiles are sample points, so that inf - inf never arises)."""
    rng = np.random.default_rng(seed)
    boots = np.median(rng.choice(x, size=(reps, len(x)), replace=True), axis=1)
    lo, hi = (float(np.quantile(boots, p, method="nearest")) for p in (0.025, 0.975))
    return float(np.median(x)), lo, hi


def plot_band(ax, steps: np.ndarray, curves: np.ndarray, alpha: float = 0.2, **line) -> None:
    """The mean over seeds of (seeds, points) `curves` against `steps`, with its 95% t-band, on
    the matplotlib axes `ax` (`line`: the line's keywords; the band takes its colour)."""
    mean, half = stats_lib.t_interval(np.asarray(curves, float))
    (drawn,) = ax.plot(steps, mean, **line)
    ax.fill_between(steps, mean - half, mean + half, facecolor=drawn.get_color(), alpha=alpha)
