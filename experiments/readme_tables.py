"""The README's result tables, generated from the committed result files.

Every table in README.md between a pair of markers

    <!-- generated: NAME -->
    ...
    <!-- end: NAME -->

is produced by `TABLES[NAME]()` from files under docs/results/. `--write` rewrites the blocks in
README.md; `--check` (and tests/test_readme.py) fails if any block differs from what its files
give, so a number in a README table is always the number in the file it names.

Usage:
  python experiments/readme_tables.py --write     # after regenerating docs/results (make results)
  python experiments/readme_tables.py --check
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "docs", "results")
README = os.path.join(ROOT, "README.md")
FAILURE_CAUSES = ("nonfinite_grad", "gp_guard", "nan_record", "std_at_bound", "below_zero_torque")


def _rows(path: str) -> list[dict]:
    with open(os.path.join(RESULTS, path), newline="") as f:
        return list(csv.DictReader(f))


def _source(*paths: str) -> str:
    return "Source: " + ", ".join(f"`docs/results/{p}`" for p in paths) + "."


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
    lines.append("")
    lines.append(f"{seeds} seeds per method; zero-torque policy: {zero:.3f} per step. "
                 + _source(f"{run}/summary.csv"))
    return "\n".join(lines)


def improvement_table(run: str = "paper_float64") -> str:
    rows = _rows(f"{run}/comparisons.csv")
    lines = ["| X | Y | P(X > Y) | 95% CI (bootstrap) |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['x']} | {r['y']} | {float(r['p_improvement']):.2f} | "
                     f"[{float(r['ci95_low']):.2f}, {float(r['ci95_high']):.2f}] |")
    lines.append("")
    lines.append(_source(f"{run}/comparisons.csv"))
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
    lines.append("")
    lines.append(_source(*(f"{run}/summary.csv" for run in runs)))
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
    lines.append("")
    lines.append(_source("consistency/consistency.json"))
    return "\n".join(lines)


def bench_table() -> str:
    with open(os.path.join(RESULTS, "bench.json")) as f:
        b = json.load(f)
    t, pr = b["train"], b["paper_run"]
    lines = [f"| figure | median [min, max] of {b['repeats']} runs | target |", "|---|---|---|"]

    def cell(x, unit="s", digits=1):
        return f"{x['median']:.{digits}f} {unit} [{x['min']:.{digits}f}, {x['max']:.{digits}f}]"

    lines.append(f"| whole `gpguided reproduce --preset paper`, {pr['seeds']} seeds, empty compile "
                 f"cache | {cell(pr['cold_s'])} | < 30 s |")
    lines.append(f"| the same, persistent compile cache warm | {cell(pr['warm_s'])} | |")
    for key in ("hyperfit", "hyperfit_alternative"):
        if key in t:
            h = t[key]
            what = "" if key == "hyperfit" else ", the other optimiser (not the default)"
            lines.append(f"| hyperparameter fit, {h.get('optimizer', 'lbfgs')} "
                         f"{h.get('steps', 15)} steps, {t['seeds']} seeds{what} (run; compile "
                         f"{h['compile_s']:.1f} s) | {cell(h['run_s'], digits=2)} | ≤ 3 s |")
    for m, r in t["methods"].items():
        lines.append(f"| {m}: {t['seeds']} seeds x all updates (run; compile {r['compile_s']:.1f} s) "
                     f"| {cell(r['run_s'], digits=2)} | |")
    if "gp_methods_program" in t:
        g = t["gp_methods_program"]
        lines.append(f"| the three GP methods as one program, as `gpguided reproduce` runs them "
                     f"(run; compile {g['compile_s']:.1f} s once for all three) | "
                     + " / ".join(cell(r["run_s"], digits=2) for r in g["methods"].values())
                     + " (" + " / ".join(g["methods"]) + ") | |")
    n = t["numpy_gp_pg"]
    runs = n["seconds_per_update"]["runs"] if "seconds_per_update" in n else 1
    of_runs = f"the median of {runs} runs of" if runs > 1 else "one run of"
    lines.append(f"| gp_pg: per-seed NumPy loop, extrapolated from {of_runs} "
                 f"{n['measured_updates']} updates | {n['extrapolated_run_s']:.1f} s | |")
    lines.append(f"| **gp_pg: JAX over NumPy** | **{n['ratio_jax_over_numpy']:.1f}x** | ≥ 20x |")
    g = b["gp"]
    lines.append(f"| sparse GP update alone (M = {g['capacity']}, {g['seeds']} seeds, as training runs "
                 "them): "
                 f"JAX / NumPy updates per second | {g['jax_updates_per_s']:,.0f} / "
                 f"{g['numpy_updates_per_s']:,.0f} = {g['ratio']:.1f}x | |")
    e = sorted(b["env"].items(), key=lambda kv: int(kv[0].removeprefix("episodes_")))
    lines.append("| pendulum steps per second, "
                 + " / ".join(k.removeprefix("episodes_") for k, _ in e) + " vmapped episodes | "
                 + " / ".join(f"{v['steps_per_s'] / 1e6:.2f} M" for _, v in e) + " | |")
    lines.append("")
    lines.append(f"{b['cpu_count']} CPU cores, jax {b['jax']}, {b['dtype']}, {b['date']}. "
                 + _source("bench.json"))
    return "\n".join(lines)


FIRST_MACHINE = "bench_2026-12-02.json"
SECOND_MACHINE = "bench_2026-12-02_second_machine.json"
THIRD_MACHINE = "bench_2026-12-02_third_machine.json"
ZEN3_MACHINE = "bench_2026-12-03_zen3.json"
ZEN4_SECOND = "bench_2026-12-03_zen4_second.json"
MACHINE_REPORTS = (FIRST_MACHINE, SECOND_MACHINE, THIRD_MACHINE, "bench.json", ZEN3_MACHINE, ZEN4_SECOND)
MACHINE_LABELS = ("the first machine", "the second machine", "a third machine, padded GP buffers",
                  "the table above: the GP methods as one program", "an AMD Zen 3 (AVX2 only)",
                  "another AMD Zen 4, a later stop")


def _figure(get, report, digits):
    """`get(report)` formatted, or a dash for a report written before that figure was measured."""
    try:
        return f"{get(report):.{digits}f}"
    except KeyError:
        return "—"


def bench_machines_table() -> str:
    """The headline figures of the command's reports on this project's machines (same kind: 2
    cores; other CPUs): the first three of 2026-12-02 (the third ran the code with the GP
    update's padded buffers, `sparse_gp.padded_slots`), then `bench.json`, the table above, then
    the two of the later stops of 2026-12-03 (the library's code unchanged since `bench.json`'s,
    but for programs kept per process, which a single command does not reuse)."""
    names = MACHINE_REPORTS
    reports = []
    for name in names:
        with open(os.path.join(RESULTS, name)) as f:
            reports.append(json.load(f))
    rows = [
        ("whole paper run, empty compile cache [s]", lambda b: b["paper_run"]["cold_s"]["median"], 1, "< 30"),
        ("the same, warm cache [s]", lambda b: b["paper_run"]["warm_s"]["median"], 1, ""),
        ("hyperparameter fit, Adam 100 steps, run [s]",
         lambda b: b["train"]["hyperfit"]["run_s"]["median"], 2, "≤ 3"),
        ("hyperparameter fit, L-BFGS 15 steps, run [s]",
         lambda b: b["train"]["hyperfit_alternative"]["run_s"]["median"], 2, ""),
        ("all four methods' runs [s]", lambda b: sum(
            m["run_s"]["median"] for m in b["train"]["methods"].values()), 1, ""),
        ("all four methods' compilation, one program each [s]", lambda b: sum(
            m["compile_s"] for m in b["train"]["methods"].values()), 1, ""),
        ("the same, the GP methods as one program [s]", lambda b: (
            b["train"]["methods"]["reinforce"]["compile_s"]
            + b["train"]["gp_methods_program"]["compile_s"]), 1, ""),
        ("gp_pg run [s]", lambda b: b["train"]["methods"]["gp_pg"]["run_s"]["median"], 2, ""),
        ("NumPy loop, ms per update", lambda b: 1e3 * b["train"]["numpy_gp_pg"][
            "seconds_per_update_one_seed"], 1, ""),
        ("**gp_pg: JAX over NumPy**", lambda b: b["train"]["numpy_gp_pg"]["ratio_jax_over_numpy"],
         1, "≥ 20"),
        ("sparse GP update alone: JAX over NumPy", lambda b: b["gp"]["ratio"], 1, ""),
    ]
    head = "| figure (medians) | " + " | ".join(
        f"{label}, {b['date']}" for label, b in zip(MACHINE_LABELS, reports)) + " | target |"
    lines = [head, "|---" * (len(reports) + 2) + "|"]
    for label, get, digits, target in rows:
        lines.append(f"| {label} | " + " | ".join(_figure(get, b, digits) for b in reports)
                     + f" | {target} |")
    lines.append("")
    lines.append(_source(*names))
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
    lines.append("")
    lines.append(f"Device memory per seed when the seeds run as one batch (slope of XLA's memory "
                 f"analysis, vmap): {batch['device_bytes_per_seed'] / 2**20:.2f} MiB, so about "
                 f"{batch['seeds_in_80_GB']:,} seeds fit in 80 GB (an estimate; no GPU was measured). "
                 + _source(*(f"{name}/scaling.json" for name, _ in runs)))
    return "\n".join(lines)


def profile_table() -> str:
    """Per method, where one update's time goes: the CPU default (profile.json) and, when present,
    the one-batch program it replaced (profile_vmap.json: vmap on one device)."""
    runs = []
    for name in ("profile.json", "profile_vmap.json"):
        path = os.path.join(RESULTS, name)
        if os.path.exists(path):
            with open(path) as f:
                runs.append((name, json.load(f)))
    lines = ["| seed loop | method | one update [ms] | roll-out, fixed noise | roll-out, own policy "
             "| GP update | Q_GP prediction | GP update achieved |",
             "|---|---|---|---|---|---|---|---|"]
    for _, pr in runs:
        loop = f"{pr.get('seed_loop', 'vmap')}, {len(pr['devices'])} device(s)"
        for m, r in pr["methods"].items():
            full = r["full_update_s"]

            def share(k, r=r, full=full):
                return f"{100 * r[k] / full:.0f}%" if k in r else "–"

            gf = (f"{r['gp_update_achieved_gflops_per_s']:.1f} GFLOP/s"
                  if "gp_update_achieved_gflops_per_s" in r else "–")
            lines.append(f"| {loop} | {m} | {r['per_update_ms']:.1f} | {share('rollout_fixed_noise_s')} | "
                         f"{share('rollout_policy_s')} | {share('gp_update_s')} | "
                         f"{share('prediction_s')} | {gf} |")
    pr = runs[0][1]
    h = pr["host"]
    lines.append("")
    lines.append(f"Shares of one update, each part timed alone ({pr['seeds']} seeds, {pr['dtype']}); "
                 f"host work between chunks (records to host, checkpoint of "
                 f"{h['checkpoint_bytes'] / 1e6:.1f} MB written): "
                 f"{1e3 * h['host_s_per_chunk']:.0f} ms per chunk of {h['chunk_updates']} updates. "
                 + _source(*(name for name, _ in runs)))
    return "\n".join(lines)


def swingup_table() -> str:
    with open(os.path.join(RESULTS, "swingup", "heldout.md")) as f:
        return f.read().rstrip("\n") + "\n\n" + _source("swingup/heldout.md")


def slot_padding_table() -> str:
    """`experiments/bench_slot_padding.py`: the GP update and the GP methods' paper runs on padded
    (104) and unpadded (101) slot buffers, timed in turn."""
    with open(os.path.join(RESULTS, "slot_padding.json")) as f:
        r = json.load(f)
    lines = ["| what | dtype | unpadded [s] | padded [s] | padded / unpadded | outputs |",
             "|---|---|---|---|---|---|"]
    for dtype, g in r["gp_update"].items():
        t = g["run_s"]
        lines.append(f"| sparse GP update alone, {r['seeds']} streams × 3000 pairs | {dtype} | "
                     f"{t['unpadded']['median']:.3f} | {t['padded']['median']:.3f} | "
                     f"{g['padded_over_unpadded']:.3f} | same basis vectors: "
                     f"{'yes' if g['same_basis_vectors'] else 'no'} |")
    for dtype, methods in r["train"].items():
        for m, g in methods.items():
            t = g["run_s"]
            lines.append(f"| {m}, whole paper run, {r['seeds']} seeds | {dtype} | "
                         f"{t['unpadded']['median']:.2f} | {t['padded']['median']:.2f} | "
                         f"{g['padded_over_unpadded']:.3f} | max \\|Δ\\| reward/step "
                         f"{g['max_abs_difference_mean_reward']:.0e} |")
    runs = {len(g["run_s"]["padded"]["runs"]) for g in r["gp_update"].values()}
    runs_train = {len(g["run_s"]["padded"]["runs"]) for d in r["train"].values() for g in d.values()}
    lines.append("")
    lines.append(f"Medians of {min(runs)} (GP update) and {min(runs_train)} "
                 f"(training) runs in turn, {r['devices']} devices, {r['date']}. "
                 + _source("slot_padding.json"))
    return "\n".join(lines)


TABLES = {
    "fig5": fig5_table,
    "improvement": improvement_table,
    "failures": failures_table,
    "consistency": consistency_table,
    "bench": bench_table,
    "bench_machines": bench_machines_table,
    "slot_padding": slot_padding_table,
    "profile": profile_table,
    "scaling": scaling_table,
    "swingup": swingup_table,
}
BLOCK = re.compile(r"(<!-- generated: (\w+) -->\n)(.*?)(<!-- end: \2 -->)", re.S)


def render(text: str) -> str:
    """README text with every generated block replaced by what its files give."""
    def sub(m):
        name = m.group(2)
        if name not in TABLES:
            raise KeyError(f"README block {name!r} has no generator; known: {sorted(TABLES)}")
        return m.group(1) + TABLES[name]() + "\n" + m.group(4)

    return BLOCK.sub(sub, text)


def blocks(text: str) -> dict[str, str]:
    return {m.group(2): m.group(3) for m in BLOCK.finditer(text)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite the blocks in README.md")
    mode.add_argument("--check", action="store_true", help="exit 1 if a block is stale")
    args = ap.parse_args(argv)
    with open(README) as f:
        text = f.read()
    new = render(text)
    if args.write:
        with open(README, "w") as f:
            f.write(new)
        print(f"rewrote {len(blocks(new))} blocks in {README}")
        return 0
    stale = [k for k, v in blocks(new).items() if blocks(text).get(k) != v]
    if stale:
        print(f"stale README blocks: {stale}; run python experiments/readme_tables.py --write")
        return 1
    print(f"{len(blocks(text))} README blocks match their files")
    return 0


if __name__ == "__main__":
    sys.exit(main())
