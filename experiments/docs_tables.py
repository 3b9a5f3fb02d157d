"""The documentation's result tables, generated from the committed result files.

Every table in README.md and docs/*.md between a pair of markers

    <!-- generated: NAME -->
    ...
    <!-- end: NAME -->

is produced by `TABLES[NAME]()` from files under docs/results/ and docs/figures/. `--write`
rewrites the blocks in place; `--check` (and tests/test_docs.py) fails if any block differs from
what its files give, so a number in a documentation table is always the number in the file it
names. A block may appear in several documents (the Fig. 5 table is in the README and on the
results page).

A block holds its table and a short caption of what its files give (seeds, budgets, thresholds,
its source; `_caption`); the prose that says what the table's columns measure stands in the page
beside the block, and carries no number of its own.

Usage:
  python experiments/docs_tables.py --write     # after regenerating result files (make results)
  python experiments/docs_tables.py --check
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import math
import os
import re
import sys

from gpguided_jax import race as race_lib
from gpguided_jax.baselines import NAMES as BASELINES

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "docs", "results")
FIGURES = os.path.join(ROOT, "docs", "figures")
FAILURE_CAUSES = ("nonfinite_grad", "gp_guard", "nan_record", "std_at_bound", "below_zero_torque")


def documents() -> list[str]:
    """README.md and every Markdown page of the documentation site (docs/*.md)."""
    return [os.path.join(ROOT, "README.md")] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))


def _rows(path: str, base: str | None = None) -> list[dict]:
    with open(os.path.join(base or RESULTS, path), newline="") as f:
        return list(csv.DictReader(f))


def _source(*paths: str, folder: str = "docs/results") -> str:
    return "Source: " + ", ".join(f"`{folder}/{p}`" for p in paths) + "."


# a word that would open a list, a quote or a heading at the start of a line
_OPENS_BLOCK = re.compile(r"(?:[-+*]|#{1,6}|\d{1,9}[.)]|>.*)$")


def _caption(*parts: str, width: int = 100) -> str:
    """A table's generated caption: `parts` (sentences of what its files give, and its source)
    as one paragraph in lines of at most `width` characters, a code span never broken and no line
    opening a Markdown block."""
    words = re.findall(r"(?:[^\s`]|`[^`]*`)+", " ".join(p for p in parts if p))
    lines = [""]
    for word in words:
        if lines[-1] and len(lines[-1]) + 1 + len(word) > width and not _OPENS_BLOCK.match(word):
            lines.append(word)
        else:
            lines[-1] = f"{lines[-1]} {word}".lstrip()
    return "\n".join(lines)


def _seed_range(seeds) -> str:
    return f"{seeds[0]}–{seeds[-1]}"


def fig5_table(run: str = "paper_float64") -> str:
    rows = _rows(f"{run}/summary.csv")
    lines = ["| method | final, IQM | 95% CI (stratified bootstrap) | final, mean | 95% CI (t) | "
             "first 10% of updates | updates to 90% |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        f = {k: float(v) for k, v in r.items() if k != "method"}
        lines.append(
            f"| {r['method']} | {f['final_iqm']:.3f} | [{f['iqm_ci95_low']:.3f}, {f['iqm_ci95_high']:.3f}] | "
            f"{f['final_mean']:.3f} | [{f['ci95_low']:.3f}, {f['ci95_high']:.3f}] | "
            f"{f['initial_mean']:.3f} | {f['updates_to_90pct']:.0f} |")
    seeds = int(rows[0]["seeds"])
    zero = float(rows[0]["zero_torque_reward"])
    lines += ["", _caption(f"{seeds} seeds per method; zero-torque policy: {zero:.3f} per step.",
                           _source(f"{run}/summary.csv"))]
    return "\n".join(lines)


def improvement_table(run: str = "paper_float64") -> str:
    rows = _rows(f"{run}/comparisons.csv")
    lines = ["| X | Y | P(X > Y) | 95% CI (bootstrap) |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['x']} | {r['y']} | {float(r['p_improvement']):.2f} | "
                     f"[{float(r['ci95_low']):.2f}, {float(r['ci95_high']):.2f}] |")
    lines += ["", _caption(_source(f"{run}/comparisons.csv"))]
    return "\n".join(lines)


def failures_table(runs=("paper_float64", "paper_float32")) -> str:
    header = ("| method | dtype | seeds | non-finite gradient | GP guard fired | NaN in a record | "
              "σ at a clip bound | final below zero-torque | failing seeds (any) |")
    lines = [header, "|---|---|---|---|---|---|---|---|---|"]
    by_run = {run: _rows(f"{run}/summary.csv") for run in runs}
    methods = [r["method"] for r in by_run[runs[0]]]
    for m in methods:
        for run in runs:
            r = next(x for x in by_run[run] if x["method"] == m)
            dtype = run.rsplit("_", 1)[-1]
            cells = " | ".join(r[f"fail_{c}"] for c in FAILURE_CAUSES)
            lines.append(f"| {m} | {dtype} | {r['seeds']} | {cells} | {r['failing_seeds']} |")
    lines += ["", _caption(_source(*(f"{run}/summary.csv" for run in runs)))]
    return "\n".join(lines)


def consistency_table() -> str:
    with open(os.path.join(RESULTS, "consistency", "consistency.json")) as f:
        c = json.load(f)
    lines = ["| method | seeds | batch vs alone (CPU default, map): max \\|Δ\\| reward/step | "
             "batch vs alone (one vmapped batch): max \\|Δ\\| reward/step | "
             "batch vs alone (vmap): max \\|Δ\\| final | "
             "float32 vs float64: median \\|Δ\\| final | max \\|Δ\\| final | IQM float64 [95% CI] | "
             "IQM float32 [95% CI] |", "|---|---|---|---|---|---|---|---|---|"]
    for m, b in c["batch_vs_alone"].items():
        d = c["f32_vs_f64"][m]
        v = c["batch_vs_alone_vmap"][m]
        lines.append(
            f"| {m} | {b['seeds']} / {d['seeds']} | {b['max_abs_curve_diff']:.1e} | "
            f"{v['max_abs_curve_diff']:.1e} | "
            f"{v['max_abs_final_diff']:.1e} | {d['median_abs_final_diff']:.4f} | "
            f"{d['max_abs_final_diff']:.4f} | {d['iqm_f64']:.3f} [{d['iqm_ci_f64'][0]:.3f}, "
            f"{d['iqm_ci_f64'][1]:.3f}] | {d['iqm_f32']:.3f} [{d['iqm_ci_f32'][0]:.3f}, "
            f"{d['iqm_ci_f32'][1]:.3f}] |")
    lines += ["", _caption(_source("consistency/consistency.json"))]
    return "\n".join(lines)


def coverage_table() -> str:
    """Figs. 2 and 4's state coverage: share of a (phi, omega) grid visited by the roll-outs."""
    with open(os.path.join(FIGURES, "coverage.json")) as f:
        c = json.load(f)
    g = c["grid"]
    lines = [f"| method | coverage | 95% CI | cells visited (of {c['cells_total']}) |",
             "|---|---|---|---|"]
    for r in c["summary"]:
        lines.append(f"| {r['method']} | {100 * r['coverage_mean']:.2f}% | "
                     f"[{100 * r['ci95_low']:.2f}, {100 * r['ci95_high']:.2f}]% | {r['cells_mean']:.1f} |")
    lines += ["", _caption(
        f"Grid {g['num_angle_bins']} × {g['num_velocity_bins']} over φ ∈ [0, 2π), "
        f"ω ∈ [−{g['max_velocity']:g}, {g['max_velocity']:g}] rad/s; mean and 95% CI over "
        f"{len(c['seeds'])} seeds ({_seed_range(c['seeds'])}), "
        f"{c['eval_episodes_per_checkpoint']} roll-outs after every "
        f"{c['checkpoints_at_updates'][0]} updates.", _source("coverage.json", folder="docs/figures"))]
    return "\n".join(lines)


def fig1_table() -> str:
    """Fig. 1: mean share of basis vectors added under the latest policy, per age penalty."""
    rows = _rows("fig1_bv_composition.csv", FIGURES)
    columns = [k for k in rows[0] if k != "improvement"]
    lines = ["| λ | " + " | ".join(k.split("=", 1)[1] for k in columns) + " |",
             "|---" * (len(columns) + 1) + "|"]
    lines.append(f"| mean share over the {len(rows)} improvements | " + " | ".join(
        f"{sum(float(r[k]) for r in rows) / len(rows):.1f}%" for k in columns) + " |")
    lines += ["", _caption(_source("fig1_bv_composition.csv", folder="docs/figures"))]
    return "\n".join(lines)


def _sweep_table(name: str, label: str) -> str:
    rows = _rows(name, FIGURES)
    param = next(iter(rows[0]))
    lines = [f"| {label} | final (mean) | 95% CI (t) | updates to 90% | share of basis vectors from the "
             "latest update |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {float(r[param]):g} | {float(r['final_mean']):.3f} | "
                     f"[{float(r['ci95_low']):.3f}, {float(r['ci95_high']):.3f}] | "
                     f"{float(r['updates_to_90pct']):.0f} | {100 * float(r['fresh_bv_share_mean']):.1f}% |")
    lines += ["", _caption(f"{rows[0]['seeds']} seeds per value.", _source(name, folder="docs/figures"))]
    return "\n".join(lines)


def sweep_lambda_table() -> str:
    return _sweep_table("sweep_age_penalty.csv", "λ")


def sweep_beta_table() -> str:
    return _sweep_table("sweep_inverse_temperature.csv", "β")


def gradient_check_table() -> str:
    """`experiments/gradient_check.py`: hand-derived scores against jax.grad and jax.jacfwd."""
    with open(os.path.join(RESULTS, "gradient_check.json")) as f:
        g = json.load(f)
    lines = ["| policy | equation | controller | max vs jax.grad | median vs jax.grad | max vs jax.jacfwd |",
             "|---|---|---|---|---|---|"]
    for r in g["rows"]:
        lines.append(f"| {r['policy']} | {r['equation']} | {r['controller']} | {r['max_vs_grad']:.1e} | "
                     f"{r['median_vs_grad']:.1e} | {r['max_vs_jacfwd']:.1e} |")
    lines += ["", _caption(f"{g['cases']} random cases per row, {g['dtype']}.",
                           _source("gradient_check.json"))]
    return "\n".join(lines)


def bench_table() -> str:
    """`gpguided bench`'s report (docs/results/bench.json) as one table."""
    with open(os.path.join(RESULTS, "bench.json")) as f:
        b = json.load(f)
    t, pr = b["train"], b["paper_run"]
    lines = [f"| figure | median [min, max] of {b['repeats']} runs |", "|---|---|"]

    def cell(x, unit="s", digits=1):
        return f"{x['median']:.{digits}f} {unit} [{x['min']:.{digits}f}, {x['max']:.{digits}f}]"

    lines.append(f"| whole `gpguided reproduce --preset paper`, {pr['seeds']} seeds, empty compile "
                 f"cache | {cell(pr['cold_s'])} |")
    lines.append(f"| the same, persistent compile cache warm | {cell(pr['warm_s'])} |")
    for key in ("hyperfit", "hyperfit_alternative"):
        if key in t:
            h = t[key]
            what = " (the default)" if key == "hyperfit" else " (the option)"
            lines.append(f"| hyperparameter fit, {h.get('optimizer', 'lbfgs')} "
                         f"{h.get('steps', 15)} steps{what}, {t['seeds']} seeds (run; compile "
                         f"{h['compile_s']:.1f} s) | {cell(h['run_s'], digits=2)} |")
    for m, r in t["methods"].items():
        lines.append(f"| {m}, its own program: {t['seeds']} seeds x all updates (run; compile "
                     f"{r['compile_s']:.1f} s) | {cell(r['run_s'], digits=2)} |")
    if "gp_methods_program" in t:
        g = t["gp_methods_program"]
        lines.append(f"| the three GP methods as one program, as `gpguided reproduce` runs them "
                     f"(run; compile {g['compile_s']:.1f} s once for all three) | "
                     + " / ".join(cell(r["run_s"], digits=2) for r in g["methods"].values())
                     + " (" + " / ".join(g["methods"]) + ") |")
    if "in_process_total_s" in t:
        lines.append(f"| the fit, compilation and runs of all four methods in one process, as "
                     f"`gpguided reproduce` compiles them | {t['in_process_total_s']:.1f} s |")
    n = t["numpy_gp_pg"]
    runs = n["seconds_per_update"]["runs"] if "seconds_per_update" in n else 1
    of_runs = f"the median of {runs} runs of" if runs > 1 else "one run of"
    lines.append(f"| gp_pg: per-seed NumPy loop, extrapolated from {of_runs} "
                 f"{n['measured_updates']} updates | {n['extrapolated_run_s']:.1f} s |")
    lines.append(f"| **gp_pg: JAX over NumPy** | **{n['ratio_jax_over_numpy']:.1f}x** |")
    for m, row in b.get("capacity", {}).get("capacities", {}).items():
        c = b["capacity"]
        lines.append(f"| one update at GP budget M = {m} ({c['preset']} preset, {c['seeds']} seeds; "
                     + " / ".join(row) + ") | "
                     + " / ".join(cell(r["per_update_s"], digits=3) for r in row.values()) + " |")
    g = b["gp"]
    lines.append(f"| sparse GP update alone (M = {g['capacity']}, {g['seeds']} seeds, as training runs "
                 "them): "
                 f"JAX / NumPy updates per second | {g['jax_updates_per_s']:,.0f} / "
                 f"{g['numpy_updates_per_s']:,.0f} = {g['ratio']:.1f}x |")
    e = sorted(b["env"].items(), key=lambda kv: int(kv[0].removeprefix("episodes_")))
    lines.append("| pendulum steps per second, "
                 + " / ".join(k.removeprefix("episodes_") for k, _ in e) + " vmapped episodes | "
                 + " / ".join(f"{v['steps_per_s'] / 1e6:.2f} M" for _, v in e) + " |")
    lines += ["", _caption(f"{b['cpu_count']} CPU cores, jax {b['jax']}, {b['dtype']}.",
                           _source("bench.json"))]
    return "\n".join(lines)


# gp_model's parts in `gpguided bench`'s ``model`` section (`bench.MODEL_PARTS`), as the table
# names them
MODEL_PART_LABELS = {
    "episodes": "the update's episodes",
    "take_in": "take-in (transitions into the buffer)",
    "condition_before": "conditioning on the old data, and the error record",
    "refit": "refit of the kernels",
    "condition_after": "conditioning after the take-in",
    "optimise": "the controller's optimisation (plan and steps)",
    "evaluation": "the evaluation episodes",
}


def _duration(seconds: float) -> str:
    """A duration in s (from 1 s) or ms, to three significant figures (whole units from 100)."""
    value, unit = (seconds, "s") if seconds >= 1.0 else (seconds * 1e3, "ms")
    digits = max(0, 2 - math.floor(math.log10(value))) if value > 0 else 2
    return f"{value:.{digits}f} {unit}"


def bench_model_table() -> str:
    """`gpguided bench`'s ``model`` section (docs/results/bench.json): each part of gp_model's
    update per seed, compile apart, per task and dtype; the tasks' settings; the whole update's
    time over the seed counts."""
    with open(os.path.join(RESULTS, "bench.json")) as f:
        m = json.load(f)["model"]
    tasks = m["tasks"]
    dtypes = list(next(iter(tasks.values())))
    lines = ["| task | part | " + " | ".join(f"{d}: run per seed (share) | {d}: compile"
                                               for d in dtypes) + " |",
             "|---|---|" + "---|---|" * len(dtypes)]
    def share(r, x):  # per seed, and its share of the whole update
        pct = 100 * x / r["update"]["run_s"]["median"]
        return f"{_duration(x / r['seeds'])} ({'<1' if pct < 0.5 else f'{pct:.0f}'}%)"

    cells = {part: (lambda r, p=part: f"{share(r, r['parts'][p]['run_s']['median'])} | "
                                      f"{r['parts'][p]['compile_s']:.1f} s")
             for part in MODEL_PART_LABELS}
    cells["sum of the parts"] = lambda r: (f"{share(r, r['parts_sum_s'])} | "
                                           f"{r['parts_compile_sum_s']:.1f} s")
    cells["**the whole update**"] = lambda r: (f"**{_duration(r['update']['per_seed_s'])}** | "
                                               f"{r['update']['compile_s']:.1f} s")
    for task, by_dtype in tasks.items():
        for key, cell in cells.items():
            lines.append(f"| {task} | {MODEL_PART_LABELS.get(key, key)} | "
                         + " | ".join(cell(by_dtype[d]) for d in dtypes) + " |")
    first = next(iter(next(iter(tasks.values())).values()))
    lines += ["", _caption(
        f"Medians of {m['repeats']} runs of each program on {first['seeds']} seeds "
        f"({first['devices']} devices), from the state after {first['warm_updates']} "
        f"update{'' if first['warm_updates'] == 1 else 's'}, "
        f"divided by the seeds; {m['cpu_count']} CPU cores, jax {m['jax']}.")]
    lines += ["", "| task | transitions in the buffer (of) | episodes × steps, evaluation "
              "episodes | inducing inputs × outputs | refit: Adam steps on points | particles × "
              "simulated steps | optimiser steps |", "|---|---|---|---|---|---|---|"]
    for task, by_dtype in tasks.items():
        r = next(iter(by_dtype.values()))
        c = r["settings"]
        lines.append(f"| {task} | {r['buffer_transitions']:,.0f} ({c['capacity']:,}) | "
                     f"{c['episodes']} × {c['episode_length']:,}, {c['eval_episodes']} | "
                     f"{c['inducing']} × {c['outputs']} | {c['fit_steps']} on {c['fit_subset']} | "
                     f"{c['particles']} × {c['plan_steps']} | {c['steps']} |")
    sc = m["seed_scaling"]
    lines += ["", "| seeds | devices | compile | one update, all seeds: median [min, max] | "
              "per seed |", "|---|---|---|---|---|"]
    for r in sc["rows"]:
        t = r["run_s"]
        lines.append(f"| {r['seeds']} | {r['devices']} | {r['compile_s']:.1f} s | "
                     f"{_duration(t['median'])} [{_duration(t['min'])}, {_duration(t['max'])}] | "
                     f"{_duration(r['per_seed_s'])} |")
    load = ", ".join(f"{x:.1f}" for x in m["load_average_after"])
    lines += ["", _caption(f"The whole update on {sc['task']}, {sc['dtype']}, medians of "
                           f"{sc['rows'][0]['run_s']['runs']} runs. The machine's load average "
                           f"after the section (1, 5 and 15 minutes): {load}.",
                           _source("bench.json"))]
    return "\n".join(lines)


SCALING_RUNS = ("scaling", "scaling_vmap")  # the CPU default; one vmapped batch on one device


def scaling_table() -> str:
    """One row per (run, seeds): the CPU default (`--seed-loop map`, one device per core) and the
    one-batch path an accelerator runs (`vmap`, one device), whose memory gives the 80 GB estimate."""
    runs = []
    for name in SCALING_RUNS:
        path = os.path.join(RESULTS, name, "scaling.json")
        if os.path.exists(path):
            with open(path) as f:
                runs.append((name, json.load(f)))
    methods = list(runs[0][1]["results"][0]["methods"])
    lines = ["| seed loop | seeds | whole paper run [s] | "
             + " | ".join(f"{m} seeds·updates/s" for m in methods)
             + " | peak RSS [GiB] | XLA memory, largest program [MiB] | updates timed |",
             "|---|---|---|" + "---|" * len(methods) + "---|---|---|"]
    for _, sc in runs:
        for r in sc["results"]:
            timed = min(m.get("updates_timed", 400) for m in r["methods"].values())
            loop = f"{r.get('seed_loop', 'vmap')}, {r.get('devices', 1)} device(s)"
            lines.append(f"| {loop} | {r['seeds']} | {r['whole_paper_run_s']:.0f} | "
                         + " | ".join(f"{r['methods'][m]['seed_updates_per_s']:.0f}" for m in methods)
                         + f" | {r['peak_rss_bytes'] / 2**30:.2f} | {r['device_bytes_max'] / 2**20:.0f} | "
                         + ("all 400" if timed >= 400 else f"{timed} (extrapolated)") + " |")
    batch = dict(runs).get("scaling_vmap", runs[0][1])
    lines += ["", _caption(
        f"Device memory per seed when the seeds run as one batch (vmap): "
        f"{batch['device_bytes_per_seed'] / 2**20:.2f} MiB, so about {batch['seeds_in_80_GB']:,} "
        "seeds fit in 80 GB.", _source(*(f"{name}/scaling.json" for name, _ in runs)))]
    return "\n".join(lines)


def swingup_table() -> str:
    with open(os.path.join(RESULTS, "swingup", "heldout.md")) as f:
        return f.read().rstrip("\n") + "\n\n" + _source("swingup/heldout.md")


def swingup_warm_table() -> str:
    """The swing-up diagnostics: started from the fitted controller, does each method keep it?"""
    with open(os.path.join(RESULTS, "swingup", "diagnostics.json")) as f:
        d = json.load(f)
    low, tuned = d["warm_start_lr_0.003"], d["warm_start"]
    methods = [m for m in low if isinstance(low[m], dict)]
    lines = ["| method | success, first 10 updates (lr 0.003) | success, last 10 updates (lr 0.003) | "
             "reward/step, last 10 updates (lr 0.003) | success, last 10 updates (tuned lr) |",
             "|---|---|---|---|---|"]
    for m in methods:
        a, b = low[m], tuned[m]
        lines.append(f"| {m} | {a['first_10_updates_success']:.2f} | {a['final_success']:.2f} | "
                     f"{a['final_reward']:.2f} | {b['final_success']:.2f} |")
    lines += ["", _caption(f"Seeds {_seed_range(d['seeds'])}.", _source("swingup/diagnostics.json"))]
    return "\n".join(lines)


def swingup_sac_table() -> str:
    """The swing-up diagnostics: SAC with a longer horizon, outside the tuning grid."""
    with open(os.path.join(RESULTS, "swingup", "diagnostics.json")) as f:
        d = json.load(f)["sac_long_horizon"]
    lines = ["| seed | best success [environment steps] | final success |", "|---|---|---|"]
    for r in d["runs"]:
        best = max(range(len(r["success"])), key=lambda i: r["success"][i])
        lines.append(f"| {r['seed']} | {r['success'][best]:.2f} [{r['env_steps'][best] / 1e3:.0f}k] | "
                     f"{r['success'][-1]:.2f} |")
    s = d["settings"]
    lines += ["", _caption(
        f"brax SAC, discount {s['discounting']:g}, {s['grad_updates_per_step']} gradient steps per "
        f"environment step, learning rate {s['learning_rate']:g}, reward scale "
        f"{s['reward_scaling']:g}; deterministic success.", _source("swingup/diagnostics.json"))]
    return "\n".join(lines)


def _steps(v) -> str:
    return "–" if v is None else f"{v / 1000:.1f}k"


def _rounded_up(budget: int, steps_run: dict[str, int], where: str = "") -> str:
    """' (brax rounds it up to whole iterations: ppo ran 100,000 steps, sac 99,200)': the steps
    brax's PPO and SAC ran for `budget`, as their evaluations recorded them, where they differ
    from it; '' where none does."""
    differ = [(name, int(steps)) for name, steps in steps_run.items() if int(steps) != budget]
    if not differ:
        return ""
    ran = ", ".join(f"{name} {'ran ' if i == 0 else ''}{steps:,}{' steps' if i == 0 else ''}"
                    for i, (name, steps) in enumerate(differ))
    return f" (brax rounds it up to whole iterations: {ran}{where})"


def standard_table(task: str) -> str:
    """`experiments/standard_tasks.py report`: the held-out comparison on one standard task."""
    path = os.path.join("standard", task, "heldout_table.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    used = all("steps_used_median" in r for r in d["rows"])  # a task whose episodes end early
    lines = ["| method | final return, IQM | 95% CI (stratified bootstrap) | final return, mean | "
             "steps to threshold, median | seeds reaching it | "
             + ("environment steps used, median | " if used else "") + "wall time |",
             "|---|---|---|---|---|---|" + ("---|" if used else "") + "---|"]
    for r in d["rows"]:
        lines.append(f"| {r['method']} | {r['final_return_iqm']:.1f} | [{r['ci95_low']:.1f}, "
                     f"{r['ci95_high']:.1f}] | {r['final_return_mean']:.1f} | "
                     f"{_steps(r['steps_to_threshold_median'])} | {r['seeds_reaching']}/{r['seeds']} | "
                     + (f"{_steps(r['steps_used_median'])} | " if used else "")
                     + f"{r['wall_s']:.0f} s |")
    ran = {r["method"]: r["env_steps"] for r in d["rows"] if r["method"] in BASELINES}
    lines += ["", _caption(
        f"Held-out seeds {_seed_range(d['seeds'])}; a budget of {d['budget']:,} environment steps of "
        f"learning for every method{_rounded_up(d['budget'], ran)}, and {d['fit_steps']:,} more for "
        f"the GP methods' hyperparameter fit; threshold {d['threshold']:g}.",
        f"Published: {d['reference']}." if d.get("reference") else "", _source(path))]
    return "\n".join(lines)


def standard_critic_table(task: str) -> str:
    """`experiments/standard_tasks.py report`: what would limit the critic, on one task."""
    return critic_table(os.path.join("standard", task, "critic_diagnostics.json"))


STANDARD_TASKS = ("pendulum-v1", "mountaincar-continuous", "inverted-pendulum",
                  "inverted-double-pendulum")  # with a comparison


def retune_table(path: str) -> str:
    """A `retune` stage's record (`experiments/standard_tasks.py retune`, `exploration_study.py
    retune`): gp_critic's own settings on the tuning seeds, each change from its tuned settings
    and its score (the final return, or the final success and reward per step)."""
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    start = d["tried"][0]["settings"]
    by_success = "success" in d["tried"][0]
    score = "final success | final reward/step" if by_success else "score (tuning seeds)"
    lines = [f"| change from the tuned settings | {score} | unhealthy seeds | chosen |",
             "|---|---|---|---|" + ("---|" if by_success else "")]
    for t in d["tried"]:
        change = {k: v for k, v in t["settings"].items() if start.get(k) != v}
        name = ", ".join(f"{k} = {v:g}" for k, v in change.items()) or "none (the tuned settings)"
        value = (f"{t['success']:.2f} | {t['reward']:.3f}" if by_success else f"{t['score']:.1f}")
        lines.append(f"| {name} | {value} | {t['unhealthy_seeds']} | "
                     f"{'yes' if t['settings'] == d['chosen'] else ''} |")
    lines += ["", _caption(f"Tuning seeds {d['seeds']}.", _source(path))]
    return "\n".join(lines)


def standard_targets_table(task: str) -> str:
    """`experiments/standard_tasks.py targets`: gp_critic's GP targets on the tuning seeds."""
    path = os.path.join("standard", task, "targets.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    lines = ["| targets | λ horizon [s] | score (tuning seeds) | chosen |", "|---|---|---|---|"]
    for t in d["tried"]:
        s = t["settings"]
        horizon = f"{s['critic_lambda_horizon']:g}" if s["critic_targets"] == "lambda" else "–"
        name = "returns-to-go" if s["critic_targets"] == "returns" else "λ-returns"
        lines.append(f"| {name} | {horizon} | {t['score']:.1f} | "
                     f"{'yes' if s == d['chosen'] else ''} |")
    lines += ["", _caption(f"Tuning seeds {d['seeds']}.", _source(path))]
    return "\n".join(lines)


def critic_table(path: str) -> str:
    """`study.critic_diagnostics`' file: what would limit the critic in a study's runs."""
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    lines = ["| method | critic error 1 − R², first 10% of updates | last 10% | action length-scale, "
             "median [min, max] over seeds | fraction of the move taken, last 10% | mean KL, last "
             "10% |", "|---|---|---|---|---|---|"]
    for r in d["rows"]:
        lines.append(f"| {r['method']} | {r['error_first']:.2f} | {r['error_last']:.2f} | "
                     f"{r['lengthscale_median']:.2f} [{r['lengthscale_min']:.2f}, "
                     f"{r['lengthscale_max']:.2f}] | {r['fraction_last']:.3f} | {r['kl_last']:.3f} |")
    lines += ["", _caption(f"Held-out seeds, {d['rows'][0]['seeds']} per method.", _source(path))]
    return "\n".join(lines)


def _settings(settings: dict) -> str:
    """A tuning record's settings as 'field=value, ...' (floats to 4 significant digits)."""
    return ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                     for k, v in settings.items())


def standard_tuning_table(task: str) -> str:
    """`experiments/standard_tasks.py tune`: every configuration tried on the tuning seeds."""
    path = os.path.join("standard", task, "tuning.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    lines = ["| method | settings | final return (tuning seeds) | chosen |", "|---|---|---|---|"]
    for name, r in d["methods"].items():
        for t in r["tried"]:
            settings = _settings(t["settings"])
            lines.append(f"| {name} | {settings} | {t['score']:.1f} | "
                         f"{'yes' if t['settings'] == r['chosen'] else ''} |")
    # every baseline configuration of the grid runs as the held-out run does (same batch sizes)
    heldout = os.path.join("standard", task, "heldout_table.json")
    with open(os.path.join(RESULTS, heldout)) as f:
        ran = {r["method"]: r["env_steps"] for r in json.load(f)["rows"]
               if r["method"] in BASELINES and r["method"] in d["methods"]}
    note = _rounded_up(d["env_steps"], ran)
    lines += ["", _caption(f"Tuning seeds {d['seeds']}, {'a budget of ' if note else ''}"
                           f"{d['env_steps']:,} environment steps per run{note}.",
                           _source(path, *([heldout] if note else [])))]
    return "\n".join(lines)


def exploration_reach_table() -> str:
    """`experiments/exploration_study.py reach`: what each scheme reaches before any learning."""
    path = os.path.join("exploration", "reach.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    amp_fields = ("init_log_std", "guided_variance_scale", "candidate_scale")

    def amplitude(r):
        if "init_log_std" in r:
            return f"σ = {math.exp(r['init_log_std']):.3g} N·m"
        k = next(k for k in amp_fields if k in r)
        return f"{k} = {r[k]:g} (N·m)²"

    lines = ["| method | exploration | amplitude | above horizontal | within 0.3 rad of upright |",
             "|---|---|---|---|---|"]
    for r in d["rows"]:
        lines.append(f"| {r['method']} | {r['scheme']} | {amplitude(r)} | "
                     f"{r['above_horizontal']:.0%} | {r['near_upright']:.0%} |")
    lines += ["", _caption(f"{d['episodes_per_seed']} episodes per seed, seeds "
                           f"{_seed_range(d['seeds'])}.", _source(path))]
    return "\n".join(lines)


def exploration_tuning_table() -> str:
    """`experiments/exploration_study.py tune`: every configuration tried on the tuning seeds."""
    path = os.path.join("exploration", "tuning.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    lines = ["| method | exploration | horizon [s] | learning rate | success | reward per step | "
             "chosen |", "|---|---|---|---|---|---|---|"]
    for name, r in d["methods"].items():
        for t in r["tried"]:
            s = t["settings"]
            rate = f"{s['learning_rate']:.3g}" + (f"; critic {s['critic_learning_rate']:.3g}"
                                                   if "critic_learning_rate" in s else "")
            lines.append(f"| {name} | {s['scheme']} | {s['discount_horizon']:g} | {rate} | "
                         f"{t['success']:.2f} | {t['reward']:.3f} | "
                         f"{'yes' if s == r['chosen'] else ''} |")
    lines += ["", _caption(f"Tuning seeds {d['seeds']} ({d['dtype']}), {d['env_steps']:,} "
                           "environment steps per run.", _source(path))]
    return "\n".join(lines)


def exploration_baseline_tuning_table() -> str:
    """`experiments/exploration_study.py baselines-tune`: brax PPO's and SAC's configurations."""
    path = os.path.join("exploration", "baseline_tuning.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    lines = ["| baseline | settings | success | reward per step | chosen |", "|---|---|---|---|---|"]
    for name, r in d["methods"].items():
        for t in r["tried"]:
            s = ", ".join(f"{k} {v:g}" for k, v in t["settings"].items())
            lines.append(f"| {name} | {s} | {t['success']:.2f} | {t['reward']:.3f} | "
                         f"{'yes' if t['settings'] == r['chosen'] else ''} |")
    import numpy as np

    # the steps run at the chosen settings, as the held-out runs' evaluations recorded them (the
    # grid's other unroll lengths run other iterations)
    heldout = {name: os.path.join("exploration", "heldout", f"{name}.npz") for name in d["methods"]}
    ran = {}
    for name, p in heldout.items():
        with np.load(os.path.join(RESULTS, p)) as f:
            ran[name] = int(f["steps"][-1])
    note = _rounded_up(d["env_steps"], ran, where=", at the chosen settings")
    lines += ["", _caption(f"Tuning seeds {d['seeds']}, {'a budget of ' if note else ''}"
                           f"{d['env_steps']:,} environment steps per run{note}.",
                           _source(path, *(heldout.values() if note else ())))]
    return "\n".join(lines)


def _steps_cell(c: dict, seeds: int) -> str:
    if c["seeds"] == 0:
        return f"0/{seeds}"
    fmt = lambda v: "∞" if not math.isfinite(v) else f"{v / 1000:.0f}k"  # noqa: E731
    return (f"{c['seeds']}/{seeds}; median {fmt(c['median'])} "
            f"[{fmt(c['ci'][0])}, {fmt(c['ci'][1])}]")


def exploration_table() -> str:
    """`experiments/exploration_study.py report`: the held-out ablation, scheme x method."""
    path = os.path.join("exploration", "heldout_table.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    n = len(d["seeds"])
    lines = ["| method | exploration | tuned choice | 50% success: seeds; steps [95% CI] | "
             "90% success: the same | final success | final reward/step | action length-scale "
             "[N·m] | wall time |", "|---|---|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        ls = "–" if r["action_length_scale"] is None else f"{r['action_length_scale']:.3g}"
        scheme = r["scheme"] if r["scheme"] != "retuned" else (
            "its retune's choice: " + ", ".join(f"{k} = {r['settings'][k]:g}" for k in
                                                ("critic_window", "gp_capacity")
                                                if k in r["settings"]))
        lines.append(f"| {r['method']} | {scheme} | {'yes' if r['chosen'] else ''} | "
                     f"{_steps_cell(r['steps_to_50'], n)} | {_steps_cell(r['steps_to_90'], n)} | "
                     f"{r['final_success']:.2f} | {r['final_reward']:.3f} | {ls} | "
                     f"{r['wall_s']:.0f} s |")
    lines += ["", _caption(f"Held-out seeds {_seed_range(d['seeds'])}.", _source(path))]
    if d["guidance"]:
        lines += ["", "| exploration | P(guided_variance > gp_pg), final reward | 95% CI |",
                  "|---|---|---|"]
        for g in d["guidance"]:
            lines.append(f"| {g['scheme']} | {g['p']:.2f} | [{g['ci'][0]:.2f}, {g['ci'][1]:.2f}] |")
    return "\n".join(lines)


def exploration_standard_table(task: str) -> str:
    """`experiments/exploration_study.py standard --task <task>`: each method at its tuned
    settings under each exploration scheme."""
    path = os.path.join("exploration", task, "standard.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    n = len(d["seeds"])
    tuning_path = os.path.join("exploration", task, "standard_tuning.json")
    with open(os.path.join(RESULTS, tuning_path)) as f:
        tuning = json.load(f)
    chosen = {m: r["chosen"] for m, r in tuning["methods"].items()}
    lines = ["| method | exploration | chosen on the tuning seeds | final return, IQM [95% CI] | "
             "seeds reaching the threshold | steps to threshold, median | wall time |",
             "|---|---|---|---|---|---|---|"]
    for key, run in d["runs"].items():
        method, scheme = key.split("/")
        r = run["summary"]
        steps = float(r["steps_to_threshold_median"])
        mark = "yes" if chosen.get(method) == scheme else ""
        lines.append(f"| {method} | {scheme} | {mark} | {float(r['final_return_iqm']):.1f} "
                     f"[{float(r['return_ci95_low']):.1f}, {float(r['return_ci95_high']):.1f}] | "
                     f"{r['seeds_reaching_threshold']}/{n} | "
                     f"{'–' if math.isnan(steps) else f'{steps:,.0f}'} | {run['wall_s']:.0f} s |")
    lines += ["", _caption(f"Held-out seeds {_seed_range(d['seeds'])}; tuning seeds "
                           f"{_seed_range(tuning['seeds'])}.", _source(path, tuning_path))]
    schemes = list(dict.fromkeys(t["scheme"] for r in tuning["methods"].values()
                                 for t in r["tried"]))
    lines += ["", "| method | " + " | ".join(schemes) + " | chosen |",
              "|---|" + "---|" * (len(schemes) + 1)]
    for method, r in tuning["methods"].items():
        score = {t["scheme"]: t["score"] for t in r["tried"]}
        lines.append(f"| {method} | " + " | ".join(
            f"{score[k]:.1f}" if k in score else "–" for k in schemes) + f" | {r['chosen']} |")
    if d.get("guidance"):
        lines += ["", "| exploration | P(guided_variance > gp_pg), final return | 95% CI |",
                  "|---|---|---|"]
        for g in d["guidance"]:
            lines.append(f"| {g['scheme']} | {g['p']:.2f} | [{g['ci'][0]:.2f}, {g['ci'][1]:.2f}] |")
    return "\n".join(lines)


def _chosen_run(runs: dict, chosen: dict, method: str):
    """(method, scheme, IQM, CI low, CI high, seeds reaching, per-seed steps to the threshold,
    wall time) of `method`'s run under its chosen scheme in an exploration study's standard
    record, or None."""
    run = runs["runs"].get(f"{method}/{chosen.get(method)}")
    if run is None:
        return None
    r = run["summary"]
    return (method, chosen[method], float(r["final_return_iqm"]), float(r["return_ci95_low"]),
            float(r["return_ci95_high"]), int(r["seeds_reaching_threshold"]),
            run["steps_to_threshold"], run["wall_s"])


def _explored_row(task, n, method, scheme, iqm, lo, hi, reaching, steps, wall) -> str:
    from gpguided_jax import study  # the bootstrap interval of a median with "never" in it

    med, slo, shi = study.median_ci([math.inf if s is None else s for s in steps])
    fmt = lambda v: "∞" if not math.isfinite(v) else f"{v / 1000:.1f}k"  # noqa: E731
    return (f"| {task} | {method} | {scheme} | {iqm:.1f} [{lo:.1f}, {hi:.1f}] | {reaching}/{n} | "
            f"{fmt(med)} [{fmt(slo)}, {fmt(shi)}] | {wall:.0f} s |")


def explored_critic_table() -> str:
    """gp_critic under the exploration it chose on the tuning seeds, on each standard task, beside
    the paper's method that ends highest on the held-out seeds under its own choice (among those
    run there), and brax's SAC and PPO (`experiments/exploration_study.py standard-tune` and
    `standard`; `experiments/standard_tasks.py heldout`)."""
    from gpguided_jax.config import PAPER_METHODS

    lines = ["| task | method | exploration | final return, IQM [95% CI] | seeds reaching the "
             "threshold | steps to it, median [95% CI] | wall time |",
             "|---|---|---|---|---|---|---|"]
    paths, seeds = [], set()
    for task in STANDARD_TASKS:
        runs_path = os.path.join("exploration", task, "standard.json")
        tuning_path = os.path.join("exploration", task, "standard_tuning.json")
        table_path = os.path.join("standard", task, "heldout_table.json")
        paths += [runs_path, tuning_path, table_path]
        with open(os.path.join(RESULTS, runs_path)) as f:
            runs = json.load(f)
        with open(os.path.join(RESULTS, tuning_path)) as f:
            chosen = {m: r["chosen"] for m, r in json.load(f)["methods"].items()}
        with open(os.path.join(RESULTS, table_path)) as f:
            baselines = {r["method"]: r for r in json.load(f)["rows"] if r["method"] in BASELINES}
        n, seeds = len(runs["seeds"]), seeds | set(runs["seeds"])
        paper = [r for r in (_chosen_run(runs, chosen, m) for m in PAPER_METHODS) if r]
        for r in [_chosen_run(runs, chosen, "gp_critic"),
                  max(paper, key=lambda r: r[2]) if paper else None]:
            if r is not None:
                lines.append(_explored_row(task, n, *r))
        for name in BASELINES:
            b = baselines[name]
            lines.append(_explored_row(
                task, n, name, "its own", b["final_return_iqm"], b["ci95_low"], b["ci95_high"],
                sum(s is not None for s in b["steps_to_threshold"]), b["steps_to_threshold"],
                b["wall_s"]))
    lines += ["", _caption(f"Held-out seeds {_seed_range(sorted(seeds))}.", _source(*paths))]
    return "\n".join(lines)


def model_table(task: str) -> str:
    """`experiments/model_study.py report`: gp_model's exploration choices on held-out seeds,
    beside SAC, PPO and the paper's best method."""
    path = os.path.join("model", task, "heldout_table.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    measure = d["measure"]
    learned = any("reward_error_last" in r for r in d["rows"])  # runs with the reward learnt
    lines = ["| method | seeds reaching the threshold | environment steps to it, median | "
             f"wall time to it, median | final {measure}, mean | seeds above it at the end | "
             "P(better than the mean model) | model error 1 − R², second update / last | "
             + ("learnt reward's error, second update / last | " if learned else "")
             + "simulated return, last update |",
             "|---|---|---|---|---|---|---|---|---|" + ("---|" if learned else "")]
    for r in d["rows"]:
        wall = r.get("wall_to_threshold_median")
        p = r.get("p_improvement_over_mean")
        err = (f"{r['model_error_second']:.3f} / {r['model_error_last']:.3f}"
               if "model_error_last" in r else "–")
        final = f"{r['final_mean']:.2f}" if measure == "success rate" else f"{r['final_mean']:.1f}"
        lines.append(f"| {r['method']} | {r['seeds_reaching']}/{r['seeds']} | "
                     f"{_steps(r['steps_to_threshold_median'])} | "
                     f"{'–' if wall is None else f'{wall:.0f} s'} | {final} | "
                     f"{r['seeds_above_at_end']}/{r['seeds']} | "
                     f"{'–' if p is None else f'{p:.2f}'} | {err} | "
                     + ((f"{r['reward_error_second']:.3f} / {r['reward_error_last']:.3f} | "
                         if "reward_error_last" in r else "– | ") if learned else "")
                     + (f"{r['model_return_last']:.1f} |" if "model_return_last" in r else "– |"))
    lines += ["", _caption(
        f"Held-out seeds {_seed_range(d['seeds'])}; threshold: a {measure} of {d['threshold']:g}; "
        f"the paper's best method here: {d['paper_best']}; gp_model ran {d['budget']:,} "
        f"environment steps of learning, its planning horizon {d['horizon_steps']} steps.",
        _source(path))]
    return "\n".join(lines)


def model_tuning_table(task: str) -> str:
    """`experiments/model_study.py tune`: every configuration tried on the tuning seeds."""
    path = os.path.join("model", task, "tuning.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    measure = d["measure"]
    lines = ["| settings | score (tuning seeds) | final " + measure + " | chosen |",
             "|---|---|---|---|"]
    for t in d["tried"]:
        settings = _settings(t["settings"]) or "(the defaults)"
        digits = 2 if measure == "success rate" else 1
        lines.append(f"| {settings} | {t['score']:.{digits}f} | {t['final']:.{digits}f} | "
                     f"{'yes' if t['settings'] == d['chosen'] else ''} |")
    lines += ["", _caption(f"Tuning seeds {d['seeds']}, {d['budget']:,} environment steps of "
                           "learning per run.", _source(path))]
    return "\n".join(lines)


def planning_ablation_table(task: str) -> str:
    """`experiments/planning_study.py ablate` and `search`: today's gp_model, each part added
    alone, then the search around their combination, on the tuning seeds."""
    path = os.path.join("planning", task, "ablation.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    tuning_path = os.path.join(RESULTS, "planning", task, "tuning.json")
    search = []
    if os.path.exists(tuning_path):
        with open(tuning_path) as f:
            t = json.load(f)
        search = [("search", r) for r in t["tried"]]
    digits = 2 if task == "swingup" else 1
    lines = ["| part | settings added to today's | score (tuning seeds) | seeds reaching the "
             "threshold | environment steps to it | wall time of the run |",
             "|---|---|---|---|---|---|"]
    for part, r in [(r["part"], r) for r in d["rows"]] + search:
        reach = [v for v in r["steps_to"] if v is not None]
        lines.append(f"| {part} | {_settings(r['settings']) or '–'} | {r['score']:.{digits}f} | "
                     f"{len(reach)}/{len(r['steps_to'])} | "
                     f"{', '.join(f'{v:,}' for v in reach) or '–'} | {r['wall_s']:.0f} s |")
    lines += ["", _caption(f"Tuning seeds {d['seeds']}; today's settings: "
                           f"{_settings(d['today'])}.", _source(path))]
    return "\n".join(lines)


def planning_cost_table(task: str) -> str:
    """`experiments/planning_study.py cost`: inducing inputs x particles around the chosen
    configuration on the tuning seeds, with the wall time to the threshold."""
    path = os.path.join("planning", task, "cost.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    fields = list(d["grid"])
    lines = ["| " + " | ".join(fields) + " | score (tuning seeds) | environment steps to the "
             "threshold | wall time of the run | wall time to the threshold, median | "
             "cheapest |", "|" + "---|" * (len(fields) + 5)]
    cheapest = {f: d["cheapest"][f] for f in fields}
    for r in d["rows"]:
        reach = [v for v in r["steps_to"] if v is not None]
        wall = r["wall_to_threshold_s"]
        lines.append("| " + " | ".join(str(r["settings"][f]) for f in fields)
                     + f" | {r['score']:.1f} | {', '.join(f'{v:,}' for v in reach) or '–'} | "
                     f"{r['wall_s']:.0f} s | {'–' if wall is None else f'{wall:.1f} s'} | "
                     f"{'yes' if r['settings'] == cheapest else ''} |")
    others = {k: v for k, v in d["base"].items() if k not in fields}
    lines += ["", _caption(f"Tuning seeds {d['seeds']}, the two seeds of a run one after the "
                           "other in one program, compilation included; around the chosen "
                           f"configuration ({_settings(others)}).", _source(path))]
    return "\n".join(lines)


def planning_table(task: str) -> str:
    """`experiments/planning_study.py report`: the chosen parts on held-out seeds beside today's
    gp_model, SAC and PPO, with the objective each planned with."""
    path = os.path.join("planning", task, "heldout_table.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    measure = d["measure"]
    lines = ["| method | planned with | seeds reaching the threshold | environment steps to it, "
             f"median | wall time to it, median | final {measure}, mean | seeds above it at the "
             "end | model error, last update | simulated return, last update |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        wall = r.get("wall_to_threshold_median")
        final = f"{r['final_mean']:.2f}" if measure == "success rate" else f"{r['final_mean']:.1f}"
        error, simulated = r.get("model_error_last"), r.get("model_return_last")
        lines.append(f"| {r['method']} | {r['objective']} | {r['seeds_reaching']}/{r['seeds']} | "
                     f"{_steps(r['steps_to_threshold_median'])} | "
                     f"{'–' if wall is None else f'{wall:.0f} s'} | {final} | "
                     f"{r['seeds_above_at_end']}/{r['seeds']} | "
                     f"{'–' if error is None else f'{error:.3f}'} | "
                     f"{'–' if simulated is None else f'{simulated:.1f}'} |")
    settings = "; ".join(f"{r['method']}: {_settings(r['settings'])}" for r in d["rows"]
                         if "settings" in r)
    lines += ["", _caption(f"Held-out seeds {_seed_range(d['seeds'])}; threshold: a {measure} of "
                           f"{d['threshold']:g}; the model error is 1 − R² of the model's "
                           "predictions of the last update's new transitions before it took them "
                           "in; the simulated return is the planning objective's mean over the "
                           "particles after the last update's optimisation, in its own units; "
                           f"both the median over seeds. Settings: {settings}.", _source(path))]
    return "\n".join(lines)


_EXPLORATION_USES_HEAD = ("| use | its setting | seeds reaching the threshold | environment steps to "
                          "it, median | final {measure}, mean | seeds above it at the end | "
                          "P(better than the mean model) [95% interval] | seeds whose first "
                          "episode found the reward | of the others: found by a later episode / "
                          "reaching the threshold | simulated return, the largest of a run |")


def _exploration_uses_cells(r: dict, measure: str) -> str:
    """An exploration-uses row's cells, from its use on (without the leading '|')."""
    final = f"{r['final_mean']:.2f}" if measure == "success rate" else f"{r['final_mean']:.1f}"
    p, ci = r.get("p_improvement_over_mean"), r.get("p_improvement_ci")
    setting = {k: v for k, v in r["settings"].items()
               if k not in ("model_exploration", "model_reward")}
    return (f" {r['method']} | {_settings(setting) or '–'} | "
            f"{r['seeds_reaching']}/{r['seeds']} | "
            f"{_steps(r['steps_to_threshold_median'])} | {final} | "
            f"{r['seeds_above_at_end']}/{r['seeds']} | "
            + ("–" if p is None else f"{p:.2f} [{ci[0]:.2f}, {ci[1]:.2f}]") + " | "
            + _found_cells(r) + f" {_simulated(r.get('model_return_max'))} |")


def _found_cells(r: dict) -> str:
    """The two cells of where the episodes found the reward: the first episode's seeds, then of
    the others those a later episode found and those reaching the threshold; '–' for the first
    where the run's buffer no longer holds it (the later episodes' seeds only)."""
    if "found_first" in r:
        return (f"{r['found_first']}/{r['seeds']} | {r['found_later']} / "
                f"{r['reaching_not_found_first']} |")
    if "found_after_first" in r:
        return f"– | {r['found_after_first']} / – |"
    return "– | – |"


def _simulated(v) -> str:
    """A simulated return: 0 where it is below any reward a step can pay (a reward that
    underflows), else to 3 significant digits."""
    return "–" if v is None else "0" if abs(v) < 1e-12 else f"{v:.3g}"


def _exploration_uses_caption(d: dict, rows: list, threshold: str) -> str:
    return (f"Held-out seeds {_seed_range(d['seeds'])}; threshold: {threshold}; "
            f"{d['budget']:,} environment steps of learning, the reward learnt"
            + (" (the rows '*_stated': the task's stated reward)"
               if _stated(r["method"] for r in rows) else "")
            + "; P(better) compares the final measure over seeds with the mean model's with the "
            "same reward (bootstrap interval); an episode found the reward where it entered the "
            "region that pays it, or ended at the goal, within the first "
            f"{d.get('visit_updates', 5)} updates"
            + ("; '–' for the first episode: the run's buffer no longer holds it, and the next "
               "cell counts the seeds whose later episodes found the reward"
               if any("found_after_first" in r for r in rows) else "")
            + "; the simulated return is each seed's largest planning objective (its mean over "
            "the particles after an update's optimisation, in the objective's units), the median "
            "over seeds.")


def _stated(choices) -> bool:
    """Whether an exploration-uses table's choices hold a comparison with the task's stated
    reward."""
    return any(c.endswith("_stated") for c in choices)


def exploration_uses_table(task: str) -> str:
    """`experiments/exploration_uses_study.py report`: each use of the model's uncertainty on
    held-out seeds, with P(improvement) over the mean model."""
    path = os.path.join("exploration_uses", task, "heldout_table.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    lines = [_EXPLORATION_USES_HEAD.format(measure=d["measure"]), "|---" * 10 + "|"]
    lines += ["|" + _exploration_uses_cells(r, d["measure"]) for r in d["rows"]]
    lines += ["", _caption(_exploration_uses_caption(
        d, d["rows"], f"a {d['measure']} of {d['threshold']:g}"), _source(path))]
    return "\n".join(lines)


def exploration_uses_sparse_table() -> str:
    """`experiments/exploration_uses_study.py report` on the sparse swing-up at each action cost
    that has held-out runs (`SPARSE_TASKS`), in one table: a row per action cost and use."""
    paths, rows, d = [], [], None
    for task in SPARSE_TASKS:
        path = os.path.join("exploration_uses", task, "heldout_table.json")
        if not os.path.exists(os.path.join(RESULTS, path)):
            continue
        with open(os.path.join(RESULTS, path)) as f:
            d = json.load(f)
        paths.append(path)
        rho = task.removeprefix("pendulum-sparse-")
        rows += [(rho, f"{d['threshold']:g}", r) for r in d["rows"]]
    lines = ["| action cost ρ | threshold |" + _EXPLORATION_USES_HEAD.format(
        measure=d["measure"]).removeprefix("|"), "|---" * 12 + "|"]
    lines += [f"| {rho} | {threshold} |" + _exploration_uses_cells(r, d["measure"])
              for rho, threshold, r in rows]
    lines += ["", _caption(_exploration_uses_caption(
        d, [r for *_, r in rows], f"a {d['measure']} of 100 (1 − ρ)"), _source(*paths))]
    return "\n".join(lines)


def exploration_uses_tuning_table(task: str) -> str:
    """`experiments/exploration_uses_study.py tune`: every use at each of its values on the
    tuning seeds, and the value chosen."""
    path = os.path.join("exploration_uses", task, "tuning.json")
    with open(os.path.join(RESULTS, path)) as f:
        d = json.load(f)
    measure = d["measure"]
    digits = 2 if measure == "success rate" else 1
    lines = ["| use | its setting | score (tuning seeds) | final " + measure + " | seeds reaching "
             "the threshold | chosen |", "|---|---|---|---|---|---|"]
    for choice, run in d["runs"].items():
        for t in run["tried"]:
            setting = {k: v for k, v in t["settings"].items()
                       if k not in ("model_exploration", "model_reward")}
            reach = sum(v is not None for v in t["steps_to"])
            picked = t["settings"] == run["chosen"] and len(run["tried"]) > 1
            lines.append(f"| {choice} | {_settings(setting) or '–'} | {t['score']:.{digits}f} | "
                         f"{t['final']:.{digits}f} | {reach}/{len(t['steps_to'])} | "
                         f"{'yes' if picked else ''} |")
    stated = " (the rows '*_stated': the task's stated reward)" if _stated(d["runs"]) else ""
    lines += ["", _caption(f"Tuning seeds {d['seeds']}, {d['budget']:,} environment steps of "
                           f"learning per run, the reward learnt{stated}; the score is the "
                           "measure's mean over the second half of the run.", _source(path))]
    return "\n".join(lines)


# with an exploration-uses study (experiments/exploration_uses_study.py: its tuning record and
# held-out runs)
EXPLORATION_USES_TASKS = ("mountaincar-continuous-learned",)
# the sparse swing-up's action costs' tasks, in one table (`exploration_uses_sparse_table`)
SPARSE_TASKS = ("pendulum-sparse-0", "pendulum-sparse-0.1", "pendulum-sparse-0.2")
# with a gp_model study (its tuning record and held-out runs)
MODEL_TASKS = ("pendulum-v1", "mountaincar-continuous", "inverted-pendulum",
               "inverted-double-pendulum", "swingup")
# with a planning study (experiments/planning_study.py: its ablation, search and held-out runs)
PLANNING_TASKS = ("inverted-pendulum", "swingup", "pendulum-v1", "mountaincar-continuous")
PLANNING_COST_TASKS = ("pendulum-v1",)  # with the planning study's cost stage
# The methods at a glance (README.md and the site's home page): per registered method, what its
# GP models, what it is good for, and the command that runs it as tuned.
METHODS_AT_A_GLANCE = {
    "reinforce": ("nothing (Monte-Carlo returns, eq. 4)", "the baseline the GP methods are compared with",
                  "paper"),
    "gp_pg": ("Q(s, a): its mean replaces the returns in the gradient (eq. 9)",
              "the paper's critic alone, fixed noise", "paper"),
    "guided_variance": ("Q(s, a): its variance scales the exploratory noise (eq. 16–19)",
                        "the paper's best on its pendulum", "paper"),
    "guided_direction": ("Q(s, a): a Gibbs policy over candidate actions (eq. 20–22)",
                         "exploring by the GP's value of actions", "paper"),
    "gp_critic": ("Q(s, a): many steps on its expectation, in a KL trust region",
                  "more improvement per episode", "pendulum-v1"),
    "gp_model": ("the dynamics (and the reward, where the task states none)",
                 "few environment steps on smooth tasks", "pendulum-v1"),
    "gp_mpc": ("the dynamics; a planner acts through it at every decision",
               "model predictive control (untuned)", "pendulum-v1"),
}


def methods_table() -> str:
    """The methods at a glance: every method the library registers (`methods.names()`, those a
    test registers left out), in the registry's order; a library method without its row in
    `METHODS_AT_A_GLANCE` is an error."""
    from gpguided_jax import methods

    names = [n for n in methods.names()
             if methods.get(n).update.__module__.startswith("gpguided_jax.")]
    if set(names) != set(METHODS_AT_A_GLANCE):
        raise KeyError(f"METHODS_AT_A_GLANCE lists {sorted(METHODS_AT_A_GLANCE)}, the registry "
                       f"{sorted(names)}: give each method its row")
    lines = ["| method | what its GP models | good for | the command that runs it |",
             "|---|---|---|---|"]
    for name in names:
        models, good, preset = METHODS_AT_A_GLANCE[name]
        lines.append(f"| `{name}` | {models} | {good} | "
                     f"`gpguided reproduce --preset {preset} --methods {name}` |")
    return "\n".join(lines)


HEADLINE_TASKS = {"pendulum-v1": "Pendulum-v1", "mountaincar-continuous": "MountainCarContinuous-v0",
                  "inverted-pendulum": "brax inverted_pendulum",
                  "inverted-double-pendulum": "brax inverted_double_pendulum",
                  "swingup": "the swing-up"}


def headline_rows() -> list[dict]:
    """Per task of `HEADLINE_TASKS`, from the gp_model study's held-out table
    (model/<task>/heldout_table.json, which reads SAC's, PPO's and the paper's methods' runs from
    the standard tasks' and the swing-up studies' files): the task's threshold and the rows of
    gp_model under its tuned use of the uncertainty (model/<task>/tuning.json) with the planning
    study's choice where it ran (planning/<task>/heldout_table.json), the best of the paper's
    methods, SAC and PPO."""
    out = []
    for task, label in HEADLINE_TASKS.items():
        with open(os.path.join(RESULTS, "model", task, "heldout_table.json")) as f:
            d = json.load(f)
        with open(os.path.join(RESULTS, "model", task, "tuning.json")) as f:
            choice = json.load(f)["chosen"]["model_exploration"]
        rows = {r["method"]: r for r in d["rows"]}
        gp_model = rows[f"gp_model ({choice})"]
        # the preset holds the planning study's choice where it ran: its held-out row (that of
        # its cost stage's cheapest where that ran)
        planning = os.path.join(RESULTS, "planning", task, "heldout_table.json")
        if os.path.exists(planning):
            with open(planning) as f:
                planned = {r["method"]: r for r in json.load(f)["rows"]}
            gp_model = planned.get("gp_model (planning parts, by wall time to it)",
                                   planned["gp_model (planning parts, by score)"])
        out.append(dict(task=task, label=label, measure=d["measure"], threshold=d["threshold"],
                        seeds=d["seeds"], choice=choice, gp_model=gp_model,
                        paper=rows[d["paper_best"]], sac=rows["sac"], ppo=rows["ppo"]))
    return out


def _headline_cell(r: dict) -> str:
    return (f"{_steps(r['steps_to_threshold_median'])} of {_steps(r['env_steps'])}, "
            f"{r['seeds_reaching']}/{r['seeds']}")


def headline_table() -> str:
    """The README's headline: per task, environment steps to its threshold and the seeds reaching
    it, for gp_model, the paper's best method, SAC and PPO (`headline_rows`)."""
    rows = headline_rows()
    lines = ["| task | threshold | gp_model | the paper's best | SAC | PPO |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['label']} | {r['measure']} {r['threshold']:g} | "
                     f"{_headline_cell(r['gp_model'])} | {r['paper']['method']}: "
                     f"{_headline_cell(r['paper'])} | {_headline_cell(r['sac'])} | "
                     f"{_headline_cell(r['ppo'])} |")
    choices = ", ".join(f"{r['label']} {r['choice']}" for r in rows)
    first = min(s for r in rows for s in r["seeds"])
    restart = any(r["paper"]["method"].endswith("_restart") for r in rows)
    lines += ["", _caption(
        "Each cell: the median environment steps to the threshold over the seeds that reach it, "
        f"of the steps the run took, and the seeds reaching it. Held-out seeds from {first}. "
        f"gp_model as its preset runs it: its use of the model's uncertainty ({choices}) and the "
        "planning study's choice; the paper's best: the best of its four methods by final return"
        + (" (_restart: its episodes restarted after an end)." if restart else "."),
        "Source: `docs/results/model/<task>/heldout_table.json` and "
        "`docs/results/planning/<task>/heldout_table.json`, one per task.")]
    return "\n".join(lines)


# the tasks whose race is committed (docs/results/race/<task>)
RACE_TASKS = ("pendulum-v1", "mountaincar-continuous", "inverted-pendulum")


def race_table(task: str = "pendulum-v1") -> str:
    """`gpguided race`'s medians on `task` (docs/results/race/<task>/race.json)."""
    path = os.path.join("race", task, "race.json")
    with open(os.path.join(RESULTS, path)) as f:
        report = json.load(f)
    return race_lib.table(report) + "\n\n" + _caption(
        f"gp_model at its {report['preset']} preset"
        + (f" with {_settings(report['gp_overrides'])}" if report.get("gp_overrides") else "")
        + f" and brax's SAC on {report['env']} to the "
        f"threshold {report['threshold']:g}, held-out seeds {_seed_range(report['seeds'])}, each "
        "seed of each method in a fresh process on the same machine: medians over the seeds of "
        "the wall time from the process's launch to the first evaluation at or above the "
        "threshold (compilation included; a seed that never reaches it counts as never), of the "
        f"environment steps there and of the whole run. SAC's budget: {report['sac_steps']:,} "
        f"steps ({report['sac_steps_source']}).", _source(path))


TABLES = {
    "fig5": fig5_table,
    "improvement": improvement_table,
    "failures": failures_table,
    "consistency": consistency_table,
    "coverage": coverage_table,
    "fig1": fig1_table,
    "sweep_lambda": sweep_lambda_table,
    "sweep_beta": sweep_beta_table,
    "gradient_check": gradient_check_table,
    "bench": bench_table,
    "bench_model": bench_model_table,
    **{f"race_{t.replace('-', '_')}": (lambda t=t: race_table(t)) for t in RACE_TASKS},
    "scaling": scaling_table,
    "swingup": swingup_table,
    "swingup_warm": swingup_warm_table,
    "swingup_sac": swingup_sac_table,
    "exploration_reach": exploration_reach_table,
    "exploration_tuning": exploration_tuning_table,
    "exploration_baseline_tuning": exploration_baseline_tuning_table,
    "exploration": exploration_table,
    "exploration_mountaincar": lambda: exploration_standard_table("mountaincar-continuous"),
    "exploration_pendulum_v1": lambda: exploration_standard_table("pendulum-v1"),
    "exploration_inverted_pendulum": lambda: exploration_standard_table("inverted-pendulum"),
    "exploration_inverted_double_pendulum":
        lambda: exploration_standard_table("inverted-double-pendulum"),
    "standard_critic_explored": explored_critic_table,
    **{f"standard_{t.replace('-', '_')}": (lambda t=t: standard_table(t)) for t in STANDARD_TASKS},
    **{f"standard_targets_{t.replace('-', '_')}": (lambda t=t: standard_targets_table(t))
       for t in ("pendulum-v1", "mountaincar-continuous")},
    **{f"standard_retune_{t.replace('-', '_')}": (
        lambda t=t: retune_table(os.path.join("standard", t, "retune.json")))
       for t in STANDARD_TASKS},
    "exploration_retune": lambda: retune_table(os.path.join("exploration", "retune.json")),
    "exploration_critic": lambda: critic_table(os.path.join("exploration",
                                                            "critic_diagnostics.json")),
    **{f"standard_critic_{t.replace('-', '_')}": (lambda t=t: standard_critic_table(t))
       for t in STANDARD_TASKS},
    **{f"standard_tuning_{t.replace('-', '_')}": (lambda t=t: standard_tuning_table(t))
       for t in STANDARD_TASKS},
    **{f"model_{t.replace('-', '_')}": (lambda t=t: model_table(t)) for t in MODEL_TASKS},
    **{f"model_tuning_{t.replace('-', '_')}": (lambda t=t: model_tuning_table(t))
       for t in MODEL_TASKS},
    **{f"exploration_uses_{t.replace('-', '_')}": (lambda t=t: exploration_uses_table(t))
       for t in EXPLORATION_USES_TASKS},
    **{f"exploration_uses_tuning_{t.replace('-', '_').replace('.', '_')}": (
        lambda t=t: exploration_uses_tuning_table(t))
       for t in EXPLORATION_USES_TASKS + SPARSE_TASKS},
    "exploration_uses_sparse": exploration_uses_sparse_table,
    "headline": headline_table,
    "methods": methods_table,
    **{f"planning_ablation_{t.replace('-', '_')}": (lambda t=t: planning_ablation_table(t))
       for t in PLANNING_TASKS},
    **{f"planning_{t.replace('-', '_')}": (lambda t=t: planning_table(t)) for t in PLANNING_TASKS},
    **{f"planning_cost_{t.replace('-', '_')}": (lambda t=t: planning_cost_table(t))
       for t in PLANNING_COST_TASKS},
}
BLOCK = re.compile(r"(<!-- generated: (\w+) -->\n)(.*?)(<!-- end: \2 -->)", re.S)


def render(text: str) -> str:
    """`text` with every generated block replaced by what its files give."""
    def sub(m):
        name = m.group(2)
        if name not in TABLES:
            raise KeyError(f"block {name!r} has no generator; known: {sorted(TABLES)}")
        return m.group(1) + TABLES[name]() + "\n" + m.group(4)

    return BLOCK.sub(sub, text)


def blocks(text: str) -> dict[str, str]:
    return {m.group(2): m.group(3) for m in BLOCK.finditer(text)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite the blocks in README.md and docs/*.md")
    mode.add_argument("--check", action="store_true", help="exit 1 if a block is stale")
    args = ap.parse_args(argv)
    stale, count = [], 0
    for path in documents():
        with open(path) as f:
            text = f.read()
        new = render(text)
        count += len(blocks(text))
        rel = os.path.relpath(path, ROOT)
        if args.write and new != text:
            with open(path, "w") as f:
                f.write(new)
            print(f"rewrote the blocks of {rel}")
        stale += [f"{rel}:{k}" for k, v in blocks(new).items() if blocks(text).get(k) != v]
    if args.write:
        print(f"{count} blocks in {len(documents())} documents")
        return 0
    if stale:
        print(f"stale blocks: {stale}; run python experiments/docs_tables.py --write")
        return 1
    print(f"{count} blocks match their files")
    return 0


if __name__ == "__main__":
    sys.exit(main())
