"""The two loops of `sparse_gp.update_batch` inside training: one GP's pairs taken in as while-loop
segments (`loop="segments"`, the default for one GP since this experiment) against `update` under
`lax.scan` with its per-pair `lax.cond` (`loop="scan"`, what one GP ran before).

Each method's whole run (paper preset, float64, `--seeds` seeds) is compiled twice, as
`gpguided reproduce` compiles it on this CPU (`reproduce.per_seed_program`: seeds over one device
per core, one after another), once with each loop (`train.take_in_episode` calls
`sparse_gp.update_batch`, which this script points at one loop or the other while it traces). The
two programs are timed in turn (A B A B ...), so that their ratio holds when the machine's speed
drifts, and their records are compared: bit for bit (equal until the GP update's padded buffers
of 2026-12-02; since then XLA compiles the two loops' surroundings in the training program
differently, and they agree to rounding) and by their largest difference. Prints JSON (--out also
writes it).

Usage:
  python experiments/bench_gp_loop.py --seeds 10 --out docs/results/gp_loop.json
"""

from __future__ import annotations

import argparse
import functools
import sys
import time

import jax
import numpy as np

import gpguided_jax
from gpguided_jax import bench, reproduce, sparse_gp
from gpguided_jax import config as config_lib
from gpguided_jax import train as train_lib
from gpguided_jax.cli import available_cores, single_threaded_lapack

gpguided_jax.enable_x64()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=["gp_pg", "guided_variance", "guided_direction"])
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    single_threaded_lapack()
    jax.config.update("jax_num_cpu_devices", available_cores())
    mesh, keys = bench.seed_mesh(args.seeds)
    fit = train_lib.make_train(config_lib.preset(args.preset, method="gp_pg")).fit_kernel_for_seed
    priors = reproduce.per_seed_program(fit, mesh)(keys)
    original = sparse_gp.update_batch

    def build(method, loop):
        cfg = config_lib.preset(args.preset, method=method)
        train = train_lib.make_train(cfg)
        state = reproduce.per_seed_program(lambda k, p: train.init(k, cfg, p), mesh)(keys, priors)
        run = reproduce.per_seed_program(lambda s: train.run_chunk(s, cfg, cfg.num_updates), mesh)
        sparse_gp.update_batch = functools.partial(original, loop=loop)
        try:
            t0 = time.perf_counter()
            compiled = run.lower(state).compile()
            return compiled, state, time.perf_counter() - t0
        finally:
            sparse_gp.update_batch = original

    out = {"seeds": args.seeds, "devices": int(mesh.devices.size), "preset": args.preset, "methods": {}}
    for method in args.methods:
        progs = {loop: build(method, loop) for loop in ("scan", "segments")}
        results = {k: jax.device_get(c(s)) for k, (c, s, _) in progs.items()}
        times = bench.timed_in_turn({k: c for k, (c, _, _) in progs.items()},
                                    {k: (s,) for k, (_, s, _) in progs.items()}, args.repeats)
        same = bench.trees_equal(results["scan"], results["segments"])
        diff = max(float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float)), initial=0.0))
                   for a, b in zip(jax.tree.leaves(results["scan"]), jax.tree.leaves(results["segments"]))
                   if np.issubdtype(np.asarray(a).dtype, np.floating))
        row = {k: {"compile_s": progs[k][2], "run_s_median": float(np.median(v)), "run_s": v}
               for k, v in times.items()}
        row["speedup_segments_over_scan"] = row["scan"]["run_s_median"] / row["segments"]["run_s_median"]
        row["records_and_state_equal_bitwise"] = bool(same)
        row["max_abs_float_difference"] = diff
        out["methods"][method] = row
        print(f"{method}: scan {row['scan']['run_s_median']:.2f} s, segments "
              f"{row['segments']['run_s_median']:.2f} s, x{row['speedup_segments_over_scan']:.2f}, "
              f"bitwise {same}", file=sys.stderr, flush=True)
    bench.print_report(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
