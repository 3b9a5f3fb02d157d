"""How far a seed's learning curve moves (1) when it runs alone instead of in a batch of seeds, and
(2) between float32 and float64.

(1) Batch vs alone: every method on the paper preset for seeds S, once together and once per seed
    alone (a batch of one), float64, for each way a device can run its seeds
    (`sharding.per_seed_program`): 'map' (one seed after another, the CPU default: the seed's
    program is the same in both, so the results should agree bit for bit) and 'vmap' (one batch,
    what an accelerator runs: XLA compiles a different program for each batch size, so results
    can differ in the last bits, and training can amplify that). Reported per method: the
    largest |difference| of the per-update mean reward over all seeds and updates, and of the final
    performance (mean over the last 10% of updates), and the number of seeds that differ at all.
(2) float32 vs float64: from two finished `gpguided reproduce` runs on the same seeds (`--f64`,
    `--f32`: their output directories). Random draws are dtype-independent (gpguided_jax._random),
    so a seed sees the same noise in both; the curves differ through rounding (and the
    hyperparameter fit, which is done in each run's dtype). Reported per method: the median and
    largest per-seed |difference| of the final performance, the final IQMs with their bootstrap
    intervals, and whether the intervals overlap.

Prints JSON and writes it (and a markdown table) to --out.

Usage:
  python experiments/consistency.py --seeds 1000 1001 ... --f64 results/paper --f32 results/paper_f32
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import numpy as np

import gpguided_jax
from gpguided_jax import checkpoints, sharding, summaries
from gpguided_jax import config as config_lib
from gpguided_jax import stats as stats_lib
from gpguided_jax import train as train_lib
from gpguided_jax.runtime import single_threaded_lapack

gpguided_jax.enable_x64()


def batch_vs_alone(method: str, seeds: list[int], preset: str, overrides: dict,
                   seed_loop: str = "map") -> dict:
    cfg = config_lib.preset(preset, method=method, **overrides)
    train = train_lib.make_train(cfg)
    mesh = sharding.make_mesh(1)
    fit = sharding.per_seed_program(train.fit_kernel_for_seed, mesh, seed_loop)
    run = sharding.per_seed_program(
        lambda k, p: train.run_chunk(train.init(k, cfg, p), cfg)[1].mean_reward, mesh, seed_loop)
    run_plain = sharding.per_seed_program(lambda k: train(k)[1].mean_reward, mesh, seed_loop)
    keys = sharding.seed_keys(seeds)
    t0 = time.perf_counter()
    if cfg.uses_gp:
        # each side fits its own hyperparameters, as a `gpguided reproduce` of one seed would
        priors = fit(keys)
        priors_alone = [fit(keys[i:i + 1]) for i in range(len(seeds))]
        batch = np.asarray(run(keys, priors))
        alone = np.concatenate([np.asarray(run(keys[i:i + 1], priors_alone[i]))
                                for i in range(len(seeds))])
        fit_diff = max(float(np.max(np.abs(np.asarray(a)[0] - np.asarray(b)[i])))
                       for i, pa in enumerate(priors_alone)
                       for a, b in zip(jax.tree.leaves(pa), jax.tree.leaves(priors)))
    else:
        batch = np.asarray(run_plain(keys))
        alone = np.concatenate([np.asarray(run_plain(keys[i:i + 1])) for i in range(len(seeds))])
        fit_diff = 0.0
    curve = np.abs(batch - alone)
    final = np.abs(summaries.final_performance(batch) - summaries.final_performance(alone))
    return dict(
        seeds=len(seeds),
        seed_loop=seed_loop,
        max_abs_curve_diff=float(curve.max()),
        max_abs_final_diff=float(final.max()),
        median_abs_final_diff=float(np.median(final)),
        seeds_that_differ=int(np.sum(curve.max(axis=1) > 0)),
        max_abs_hyperfit_diff=fit_diff,
        wall_s=time.perf_counter() - t0,
    )


def f32_vs_f64(dir64: str, dir32: str) -> dict:
    a, b = np.load(os.path.join(dir64, "results.npz")), np.load(os.path.join(dir32, "results.npz"))
    if list(a["seeds"]) != list(b["seeds"]):
        raise SystemExit("the two runs must use the same seeds")
    out = {}
    for i, m in enumerate(a["methods"]):
        j = list(b["methods"]).index(m)
        f64 = summaries.final_performance(a["mean_reward"][i])
        f32 = summaries.final_performance(b["mean_reward"][j])
        d = np.abs(f64 - f32)
        ci64, ci32 = stats_lib.bootstrap_ci(f64), stats_lib.bootstrap_ci(f32)
        out[str(m)] = dict(
            seeds=len(f64),
            median_abs_final_diff=float(np.median(d)),
            max_abs_final_diff=float(d.max()),
            max_abs_curve_diff=float(np.max(np.abs(a["mean_reward"][i] - b["mean_reward"][j]))),
            iqm_f64=stats_lib.iqm(f64), iqm_ci_f64=ci64,
            iqm_f32=stats_lib.iqm(f32), iqm_ci_f32=ci32,
            intervals_overlap=bool(ci64[0] <= ci32[1] and ci32[0] <= ci64[1]),
            failing_seeds_f64=int(summaries.failing_seeds(
                {k: a[k][i] for k in train_lib.RECORD_FIELDS}, -np.inf)["any"].sum()),
            failing_seeds_f32=int(summaries.failing_seeds(
                {k: b[k][j] for k in train_lib.RECORD_FIELDS}, -np.inf)["any"].sum()),
        )
    return out


def markdown(result: dict) -> str:
    lines = []
    for key in ("batch_vs_alone", "batch_vs_alone_vmap"):
        if key not in result:
            continue
        lines += ["| method | seed loop | seeds | max |Δ| reward/step (any update) | max |Δ| final | "
                  "seeds that differ |", "|---|---|---|---|---|---|"]
        for m, r in result[key].items():
            lines.append(f"| {m} | {r.get('seed_loop', 'vmap')} | {r['seeds']} | "
                         f"{r['max_abs_curve_diff']:.2e} | {r['max_abs_final_diff']:.2e} | "
                         f"{r['seeds_that_differ']} |")
        lines.append("")
    if "f32_vs_f64" in result:
        lines += ["| method | seeds | median |Δ final| | max |Δ final| | IQM float64 [95% CI] | "
                  "IQM float32 [95% CI] | intervals overlap |", "|---|---|---|---|---|---|---|"]
        for m, r in result["f32_vs_f64"].items():
            lines.append(
                f"| {m} | {r['seeds']} | {r['median_abs_final_diff']:.4f} | {r['max_abs_final_diff']:.4f} | "
                f"{r['iqm_f64']:.3f} [{r['iqm_ci_f64'][0]:.3f}, {r['iqm_ci_f64'][1]:.3f}] | "
                f"{r['iqm_f32']:.3f} [{r['iqm_ci_f32'][0]:.3f}, {r['iqm_ci_f32'][1]:.3f}] | "
                f"{'yes' if r['intervals_overlap'] else 'NO'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    single_threaded_lapack()  # as `gpguided reproduce`, whose runs (2) compares
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1000, 1010)))
    ap.add_argument("--methods", nargs="+", default=list(config_lib.PAPER_METHODS))
    ap.add_argument("--num-updates", type=int, default=None, help="override (quick runs)")
    ap.add_argument("--f64", default=None, help="a float64 reproduce output directory")
    ap.add_argument("--f32", default=None, help="a float32 reproduce output directory (same seeds)")
    ap.add_argument("--skip-batch", action="store_true", help="only the float32-vs-float64 part")
    ap.add_argument("--out", default="results/consistency")
    args = ap.parse_args(argv)
    overrides = {} if args.num_updates is None else {"num_updates": args.num_updates}
    result: dict = {"preset": args.preset}
    if not args.skip_batch:
        for key, loop in (("batch_vs_alone", "map"), ("batch_vs_alone_vmap", "vmap")):
            result[key] = {}
            for m in args.methods:
                result[key][m] = batch_vs_alone(m, args.seeds, args.preset, overrides, loop)
                print(f"[{m}, {loop}] {result[key][m]}", file=sys.stderr, flush=True)
    if args.f64 and args.f32:
        result["f32_vs_f64"] = f32_vs_f64(args.f64, args.f32)
    os.makedirs(args.out, exist_ok=True)
    checkpoints.atomic_write_text(os.path.join(args.out, "consistency.json"), json.dumps(result, indent=2))
    checkpoints.atomic_write_text(os.path.join(args.out, "consistency.md"), markdown(result) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
