"""Why a CPU runs its seeds one after another: the sparse GP update on the benchmark stream of
`gpguided bench` (M = 100, 3000 points per seed, float64), 10 seeds on one device,

* as one vmapped batch and one seed after another (`lax.map`): microseconds per seed and point;
* how often the insertion branch runs: the fraction of points that join the basis for one seed,
  and the fraction of steps at which at least one of the batch's seeds has a point that joins
  (a batch runs the insertion branch then, for every seed);
* one seed after another with the two loops of `sparse_gp.update_batch`: the while-loop segments
  (`loop="segments"`, what one GP runs) and `update` under `lax.scan` with its per-pair `lax.cond`
  (`loop="scan"`, what one GP ran before), whose results are the same bit for bit.

The programs are timed in turn (A B C A B C ...), so that their ratios hold when the machine's
speed drifts.

Prints JSON (--out also writes it).

Usage:
  python experiments/bench_seed_loop.py --out docs/results/seed_loop.json
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import bench, kernels, reproduce, sparse_gp

gpguided_jax.enable_x64()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--points", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    s = bench.GP_SETTINGS
    hyper = kernels.make_kernel_params(s["lengthscales"], s["signal_variance"], s["noise_variance"])
    kw = dict(novelty_tol=s["novelty_tol"], age_penalty=s["age_penalty"], age_scale=s["age_scale"])
    n = args.points
    streams = [bench._pendulum_stream(n, i) for i in range(args.seeds)]
    xs = jnp.asarray(np.stack([a for a, _ in streams]))
    ys = jnp.asarray(np.stack([b for _, b in streams]))
    ts = jnp.arange(n) // 150

    def one(loop):  # the GP comes in as an argument, as training's carried GP does
        return lambda gp, x, y: sparse_gp.update_batch(gp, x, y, hyper, ts, with_info=True,
                                                       loop=loop, **kw)

    mesh = reproduce.make_mesh(1)
    out = {"seeds": args.seeds, "points_per_seed": n, "capacity": 100, "device": str(jax.devices()[0])}
    programs = {"vmap": reproduce.per_seed_program(one("auto"), mesh, "vmap"),
                "map": reproduce.per_seed_program(one("auto"), mesh, "map"),
                "map_scan_loop": reproduce.per_seed_program(one("scan"), mesh, "map")}
    gp0 = jax.tree.map(lambda a: jnp.stack([a] * args.seeds), sparse_gp.init(100, 4))
    results = {k: jax.block_until_ready(run(gp0, xs, ys)) for k, run in programs.items()}
    times = bench.timed_in_turn(programs, {k: (gp0, xs, ys) for k in programs}, args.repeats)
    for k in programs:
        t = float(np.median(times[k]))
        out[k] = {"run_s": t, "us_per_seed_and_point": 1e6 * t / (n * args.seeds)}
    info = results["map"][1]
    added = np.asarray(info.added)  # (seeds, points), the same in every loop
    out["joins_fraction_one_seed"] = float(added.mean())
    out["any_seed_joins_fraction"] = float(added.any(axis=0).mean())
    out["map_speedup"] = out["vmap"]["run_s"] / out["map"]["run_s"]
    out["segments_speedup_over_scan_loop"] = out["map_scan_loop"]["run_s"] / out["map"]["run_s"]
    out["segments_equal_scan_loop_bitwise"] = bench.trees_equal(results["map"], results["map_scan_loop"])
    bench.print_report(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
