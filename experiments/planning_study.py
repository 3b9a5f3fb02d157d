"""gp_model's planning parts on the five tasks: which objective, controller and search bring it to
each task's threshold, by the protocol of `gpguided_jax.study`, extending the model study
(experiments/model_study.py: its budgets, settings, measures, held-out seeds and table rows).

Today's gp_model is the model study's tuned configuration (docs/results/model/<task>/tuning.json).
The parts (`gpguided_jax.model_based`; docs/design.md#model):

  objective   'survival' (the log-probability of not meeting the task's end) and 'saturating'
              (PILCO's saturating cost on the task's declared target) beside the stated reward;
  controller  'rbf_trainable' (centres, widths and weights trained), 'linear_rbf' and 'linear'
              beside today's fixed-centre 'rbf';
  particles   64 particles, half of them started from visited states;
  fresh       a fresh plan at every optimiser step (no common random numbers);
  longer      twice the optimiser steps, the rate decayed to a tenth, the best iterate kept;
  restarts    4 controllers per update (the current one and 3 perturbed), the best on 32
              held-aside particles kept.

Stages, per task; each writes under --out (default docs/results/planning/<task>):

``ablate``  Tuning seeds (100, 101; never reported): today's configuration, then each part's
            variants added to it one at a time (`PARTS`, written before any run). The score is
            the model study's (the measure over the second half of the budget). Writes
            ablation.json (resumed part by part).
``search``  Every part whose best variant beat today's score, combined, then a coordinate search
            around the combination (`SEARCH`). Writes tuning.json; its `chosen` is the preset's.
``heldout`` The chosen configuration on the held-out seeds (1000-1009; 1000-1019 for the
            swing-up), and the fastest to the threshold on the tuning seeds where that is another
            (`fastest`: the aim's criterion, most seeds reaching it, then fewest steps; a second
            rule, added after the ablation had run, because the score can pass over a part that
            reaches the threshold sooner and ends level). Writes heldout/chosen.npz and .json
            (heldout/fastest.*).
``cost``    Where the race against SAC (`gpguided race`) needs it (`COST_TASKS`): around the
            chosen configuration, every pair of inducing inputs and particles of `COST_GRID`
            (gp_model's time per update grows with both; docs/benchmarks.md), on the tuning
            seeds; `cheapest` is the one with the least wall time to the threshold (the median
            over the seeds of the run's seconds per seed in proportion to its steps to it) of
            those that reach it on both seeds, the chosen one on a tie. Writes cost.json; the
            held-out stage then runs it too ('cheapest') where it is another configuration.
``float32`` Where the cost stage ran: the preset's configuration on the held-out seeds in
            float32 (heldout/preset_float32.*), beside its float64 row.
``report``  heldout_table.json: seeds reaching the threshold, environment steps and wall time to
            it, and the objective planned with, beside today's gp_model (the model study's
            held-out run of its tuned choice), SAC and PPO; and the figure.

Usage:
  python experiments/planning_study.py ablate --task inverted-pendulum
  python experiments/planning_study.py search --task inverted-pendulum
  python experiments/planning_study.py heldout --task inverted-pendulum
  python experiments/planning_study.py report --task inverted-pendulum
  python experiments/planning_study.py cost --task pendulum-v1
"""

from __future__ import annotations

import argparse
import json
import os
import time

import model_study as MS  # its figure sets matplotlib's Agg backend
import numpy as np

from gpguided_jax import study

ROOT = MS.ROOT
METHOD = MS.METHOD
TASKS = MS.TASKS

_CONTROLLERS = [{"controller": c} for c in ("rbf_trainable", "linear_rbf", "linear")]
_SEARCH_PARTS = {
    "particles": [{"model_particles": 64, "model_visited_starts": 0.5}],
    "fresh": [{"model_fresh_draws": True}],
    "longer": [{"model_steps": "x2", "model_final_rate": 0.1, "model_keep_best": True}],
    "restarts": [{"model_restarts": 4, "model_held_aside": 32}],
}
# (part, its variants) per task, each variant added alone to today's configuration. The
# objectives a task can plan with: survival where it ends (brax's pendulums; the car's end is its
# goal, not a failure), the saturating cost where it declares a target (all five).
PARTS = {
    "inverted-pendulum": {"objective": [{"model_reward": "survival"},
                                        {"model_reward": "saturating"}],
                          "controller": _CONTROLLERS, **_SEARCH_PARTS},
    # a run costs ten times the single pendulum's here: the objectives and one controller
    "inverted-double-pendulum": {"objective": [{"model_reward": "survival"},
                                               {"model_reward": "saturating"}],
                                 "controller": _CONTROLLERS[1:2]},
    "swingup": {"objective": [{"model_reward": "saturating"}],
                "controller": _CONTROLLERS[:2], **_SEARCH_PARTS},
    "pendulum-v1": {"objective": [{"model_reward": "saturating"}],
                    "controller": _CONTROLLERS[:2], **_SEARCH_PARTS},
    "mountaincar-continuous": {"objective": [{"model_reward": "saturating"}],
                               "controller": _CONTROLLERS[:2], **_SEARCH_PARTS},
}
# the search around the combination: the simulated horizon (x 1/2, x 2) and the end's smoothing
SEARCH = {task: [("model_horizon", ["x0.5", "x2"])] for task in TASKS}
for _task in ("inverted-pendulum", "inverted-double-pendulum"):
    SEARCH[_task] = SEARCH[_task] + [("model_end_softness", [0.3, 1.0])]

# The cost stage's grid, around the chosen configuration (`cost`).
COST_GRID = {"model_inducing": [100, 200, 400], "model_particles": [16, 32, 64]}
COST_TASKS = ("pendulum-v1",)


def today(task: str) -> dict:
    """The model study's tuned settings of `task` (its `chosen`)."""
    path = os.path.join(ROOT, "docs", "results", "model", task, "tuning.json")
    return study.read_json(path)["chosen"]


def resolve(task: str, settings: dict) -> dict:
    """Settings with their relative values ('x2': twice today's) made absolute."""
    base = MS.overrides(task, today(task))
    defaults = MS.config_lib.preset(task, method=METHOD, **base)
    out = {}
    for k, v in settings.items():
        if isinstance(v, str) and v.startswith("x"):
            v = type(defaults.value(k))(defaults.value(k) * float(v[1:]))
        out[k] = v
    return out


def _evaluate(task: str, out: str, settings: dict, runs: str = "runs.json") -> dict:
    """One configuration on the tuning seeds (kept in `runs` as it finishes): its score, and
    per seed the environment steps to the threshold and its wall seconds."""
    runs_path = os.path.join(out, runs)
    full = MS.overrides(task, {**today(task), **resolve(task, settings)})
    key = json.dumps(full, sort_keys=True)
    done = study.read_json(runs_path, {})
    if key not in done:
        record, level, _ = MS.measure(task)
        cfg = MS.config_lib.preset(task, method=METHOD, **full)
        steps = study.env_steps(cfg)

        def score(records):
            ret = np.asarray(records[record], float)
            reach = study.steps_to(steps, ret, level, never=np.nan)
            return {**MS.score_of(task)(records),
                    "steps_to": [None if np.isnan(v) else int(v) for v in reach]}

        start = time.perf_counter()
        result = study.sweep_stage([full], score, method=METHOD, preset=task,
                                   seeds=study.TUNING_SEEDS, progress=study.log)[0]
        result["wall_s"] = time.perf_counter() - start
        done = study.read_json(runs_path, {})
        done[key] = result
        study.write_json(runs_path, done)
    return done[key]


def ablate(task: str, out: str) -> None:
    path = os.path.join(out, "ablation.json")
    rows = [{"part": "today", "settings": {}, **_evaluate(task, out, {})}]
    study.log(f"[{task}] today: {rows[0]}")
    for part, variants in PARTS[task].items():
        for v in variants:
            rows.append({"part": part, "settings": v, **_evaluate(task, out, v)})
            study.log(f"[{task}] {part} {v}: {rows[-1]}")
            study.write_json(path, {"task": task, "seeds": list(study.TUNING_SEEDS),
                                    "today": today(task), "parts": PARTS[task], "rows": rows})
    study.write_json(path, {"task": task, "seeds": list(study.TUNING_SEEDS),
                            "today": today(task), "parts": PARTS[task], "rows": rows})


def combined(task: str, out: str) -> dict:
    """Per part, its best variant where it beat today's score, all together."""
    rows = study.read_json(os.path.join(out, "ablation.json"))["rows"]
    base = rows[0]["score"]
    out_settings = {}
    for part in PARTS[task]:
        best = max((r for r in rows if r["part"] == part), key=lambda r: r["score"])
        if best["score"] > base:
            out_settings.update(best["settings"])
    return out_settings


def search(task: str, out: str) -> None:
    start = combined(task, out)
    result = study.search_beyond(start, SEARCH[task],
                                 lambda configs: [_evaluate(task, out, c) for c in configs],
                                 log=study.log)
    chosen = resolve(task, result["chosen"])
    study.write_json(os.path.join(out, "tuning.json"), {
        "task": task, "seeds": list(study.TUNING_SEEDS), "today": today(task),
        "combined": start, "grid": SEARCH[task], **result, "chosen": chosen})
    study.log(f"[{task}] chosen: {chosen}")


def fastest(task: str, out: str) -> dict:
    """The aim's criterion on the tuning seeds: of every configuration the ablation and the search
    ran, the one with the most seeds reaching the threshold, then the fewest environment steps to
    it (their median); ties go to the earlier row (today's first). Its settings beyond today's."""
    rows = study.read_json(os.path.join(out, "ablation.json"))["rows"]
    tuning = study.read_json(os.path.join(out, "tuning.json"))
    tried = [{"settings": r["settings"], "steps_to": r["steps_to"]} for r in tuning["tried"]]

    def key(r):
        reach = [v for v in r["steps_to"] if v is not None]
        return (-len(reach), float(np.median(reach)) if reach else np.inf)

    best = min(rows + tried, key=key)
    return resolve(task, best["settings"])


def _wall_to_threshold(row: dict, budget: int) -> float | None:
    """A tuning run's wall time to the threshold: the median over its seeds of the run's seconds
    per seed in proportion to the steps to it (the model study's measure, `MS._row`); None
    unless every seed reaches it."""
    steps = row["steps_to"]
    if any(v is None for v in steps):
        return None
    return float(np.median([row["wall_s"] / len(steps) * v / budget for v in steps]))


def cost(task: str, out: str) -> None:
    """Every pair of `COST_GRID` around the chosen configuration on the tuning seeds, all run
    here (cost_runs.json: the wall times of one code and one machine), and the cheapest."""
    chosen = study.read_json(os.path.join(out, "tuning.json"))["chosen"]
    budget = MS.BUDGETS[task]
    (f1, values1), (f2, values2) = COST_GRID.items()
    rows = []
    for v1 in values1:
        for v2 in values2:
            grid_point = {f1: v1, f2: v2}
            row = {"settings": grid_point,
                   **_evaluate(task, out, {**chosen, **grid_point}, runs="cost_runs.json")}
            row["wall_to_threshold_s"] = _wall_to_threshold(row, budget)
            rows.append(row)
            study.log(f"[{task}] cost {grid_point}: {row}")
    own = {f: chosen.get(f, MS.config_lib.preset(task, method=METHOD, **MS.overrides(
        task, today(task))).value(f)) for f in COST_GRID}
    base = next(r for r in rows if r["settings"] == own)
    timed = [r for r in rows if r["wall_to_threshold_s"] is not None] or [base]
    # the least wall time to the threshold, the chosen configuration on a tie
    best = min(timed, key=lambda r: (r["wall_to_threshold_s"] or 0.0, r is not base))
    study.write_json(os.path.join(out, "cost.json"), {
        "task": task, "seeds": list(study.TUNING_SEEDS), "base": chosen, "grid": COST_GRID,
        "rows": rows, "cheapest": {**chosen, **best["settings"]}})
    study.log(f"[{task}] cheapest: {best['settings']}")


def heldout(task: str, out: str) -> None:
    """The held-out runs of the chosen configuration ('chosen': the score's), of the fastest to
    the threshold on the tuning seeds ('fastest': `fastest`) and of the cheapest (`cost`) where
    each is another one."""
    chosen = study.read_json(os.path.join(out, "tuning.json"))["chosen"]
    runs = {"chosen": chosen}
    quickest = fastest(task, out)

    def same(a, b):
        return MS.overrides(task, {**today(task), **a}) == MS.overrides(task, {**today(task), **b})

    if not same(quickest, chosen):
        runs["fastest"] = quickest
    cost_path = os.path.join(out, "cost.json")
    if os.path.exists(cost_path):
        cheapest = study.read_json(cost_path)["cheapest"]
        if not any(same(cheapest, r) for r in runs.values()):
            runs["cheapest"] = cheapest
    for name, extra in runs.items():
        _heldout_run(task, out, name, {**today(task), **extra})


def _heldout_run(task: str, out: str, name: str, settings: dict, dtype: str = "float64") -> None:
    """One configuration on the held-out seeds: heldout/<name>.npz and .json."""
    seeds = MS.heldout_seeds(task)
    meta = {"seeds": seeds, "settings": settings, **({"dtype": dtype} if dtype != "float64" else {})}
    path = os.path.join(out, "heldout", name)
    if study.finished(path + ".json", **meta):
        study.log(f"[{task}] done with these seeds and settings: {path}.json")
        return
    run = study.run_method(task, METHOD, seeds, os.path.join(out, "runs", name),
                           MS.overrides(task, settings), dtype=dtype, chunk_size=1)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    np.savez(path + ".npz", steps=run.env_steps, measure=run.records[MS.measure(task)[0]],
             model_error=run.records["model_error"],
             model_return=run.records["model_return"])
    study.write_json(path + ".json", {**meta, "wall_s": run.wall_s})


def float32(task: str, out: str) -> None:
    """The preset's configuration (`MS.planned` over today's) on the held-out seeds in float32:
    heldout/preset_float32.*, beside its float64 row."""
    _heldout_run(task, out, "preset_float32", {**today(task), **MS.planned(task)}, "float32")


def objective_of(settings: dict) -> str:
    return settings.get("model_reward", "stated")


def report(task: str, out: str) -> None:
    record, threshold, measure_name = MS.measure(task)
    rows, curves = [], {}
    for name, label in (("chosen", "gp_model (planning parts, by score)"),
                        ("fastest", "gp_model (planning parts, by steps to it)"),
                        ("cheapest", "gp_model (planning parts, by wall time to it)"),
                        ("preset_float32", "gp_model (the preset, float32)")):
        path = os.path.join(out, "heldout", name)
        if not os.path.exists(path + ".json"):
            continue
        meta = study.read_json(path + ".json")
        seeds = meta["seeds"]
        with np.load(path + ".npz") as f:
            steps, ret = f["steps"], np.asarray(f["measure"], float)
            error = np.asarray(f["model_error"], float)
            simulated = np.asarray(f["model_return"], float)
        # the diagnostics beside each gp_model row: the model's error on the last update's new
        # transitions before it took them in (1 - R^2), and the simulated return the last
        # update's optimisation reached, medians over seeds
        rows.append({**MS._row(label, steps, ret, threshold, meta["wall_s"], seeds),
                     "objective": objective_of(meta["settings"]), "settings": meta["settings"],
                     "model_error_last": float(np.median(error[:, -1])),
                     "model_return_last": float(np.median(simulated[:, -1]))})
        curves[label] = (steps, ret)
    choice = today(task).get("model_exploration", "mean")
    old = os.path.join(ROOT, "docs", "results", "model", task, "heldout", choice)
    if os.path.exists(old + ".npz"):
        with np.load(old + ".npz") as f:
            curves["gp_model (today)"] = (f["steps"], np.asarray(f["measure"], float))
            old_error = np.asarray(f["model_error"], float)
        old_meta = study.read_json(old + ".json")
        if old_meta["seeds"] == seeds:
            rows.append({**MS._row("gp_model (today)", *curves["gp_model (today)"], threshold,
                                   old_meta["wall_s"], seeds), "objective": "stated",
                         "model_error_last": float(np.median(old_error[:, -1]))})
            run = os.path.join(ROOT, "docs", "results", "model", task, "runs", choice,
                               "results.npz")
            if os.path.exists(run):
                with np.load(run) as f:
                    rows[-1]["model_return_last"] = float(np.median(f["model_return"][0][:, -1]))
    others = MS._others(task, seeds)
    for name in MS.BESIDE:
        if name in others:
            s, r, wall = others[name]
            rows.append({**MS._row(name, s, r, threshold, wall, seeds), "objective": "task's reward"})
            curves[name] = (s, r)
    figure = MS.heldout_figure(task, curves, threshold, measure_name, seeds,
                               f"planning_{task}.png")
    study.write_json(os.path.join(out, "heldout_table.json"), {
        "task": task, "threshold": threshold, "measure": measure_name, "seeds": seeds,
        "budget": MS.BUDGETS[task], "rows": rows})
    study.log(f"wrote {figure} and {out}/heldout_table.json")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stage", choices=("ablate", "search", "cost", "heldout", "float32", "report"))
    p.add_argument("--task", choices=TASKS, default="inverted-pendulum")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.stage in ("cost", "float32") and args.task not in COST_TASKS:
        p.error(f"the {args.stage} stage runs on {', '.join(COST_TASKS)}, not {args.task}")
    out = study.set_up(args.out or os.path.join(ROOT, "docs", "results", "planning", args.task))
    {"ablate": ablate, "search": search, "cost": cost, "heldout": heldout, "float32": float32,
     "report": report}[args.stage](
        args.task, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
