"""The three GP methods as one compiled program (`train.make_gp_methods_train`, what `gpguided
reproduce` runs by default) against one program per method (`train.make_train(cfg).run_chunk`,
`--gp-program per-method`).

Each GP method's whole run (paper preset, float64, `--seeds` seeds, from the same fitted
hyperparameters and initial states) is compiled both ways as `gpguided reproduce` compiles it on
this CPU (`reproduce.per_seed_program`: seeds over one device per core, one after another); the
shared program is compiled once for the three. Each method's two programs are timed in turn
(A B A B ...), so that their ratio holds when the machine's speed drifts, and their records are
compared: the integer ones (GP decisions, clipping, guard) for equality, the floats by their
largest relative difference (they agree to rounding: XLA compiles the two programs differently,
and guided_direction's Gibbs choices amplify the last bits over a run). Prints JSON (--out also
writes it).

Usage:
  python experiments/bench_gp_program.py --seeds 10 --out docs/results/gp_program.json
"""

from __future__ import annotations

import argparse
import functools
import sys
import time

import jax
import numpy as np

import gpguided_jax
from gpguided_jax import bench, reproduce
from gpguided_jax import config as config_lib
from gpguided_jax import train as train_lib
from gpguided_jax.cli import available_cores, single_threaded_lapack

gpguided_jax.enable_x64()


def compare_records(a, b) -> dict:
    """Integer records equal; the floats' largest relative difference, at the first update and
    over the run."""
    ints_equal, first, whole = True, 0.0, 0.0
    for x, y in zip(a, b):
        x, y = np.asarray(x), np.asarray(y)
        if np.issubdtype(x.dtype, np.integer):
            ints_equal &= bool(np.array_equal(x, y))
            continue
        rel = np.abs(x - y) / np.maximum(np.abs(y), 1e-12)
        first, whole = max(first, float(rel[:, 0].max())), max(whole, float(rel.max()))
    return {"integer_records_equal": ints_equal, "max_rel_diff_first_update": first,
            "max_rel_diff": whole}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=list(train_lib.GP_METHODS),
                    choices=train_lib.GP_METHODS, help="the methods to time against their own program")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    single_threaded_lapack()
    jax.config.update("jax_num_cpu_devices", available_cores())
    mesh, keys = bench.seed_mesh(args.seeds)
    cfg0 = config_lib.preset(args.preset, method="gp_pg")
    priors = reproduce.per_seed_program(train_lib.make_train(cfg0).fit_kernel_for_seed, mesh)(keys)
    loop = reproduce.resolve_seed_loop("auto", mesh)
    shared, shared_compile, runs = bench.compiled_gp_methods_program(
        args.preset, args.methods, mesh, loop, keys, priors)
    out = {"seeds": args.seeds, "devices": int(mesh.devices.size), "preset": args.preset,
           "seed_loop": loop, "shared_compile_s": shared_compile, "methods": {}}
    for method, (cfg, (state, *method_args)) in runs.items():
        train = train_lib.make_train(cfg)
        own = reproduce.per_seed_program(
            functools.partial(train.run_chunk, cfg=cfg, num_updates=cfg.num_updates), mesh, loop)
        t0 = time.perf_counter()
        own = own.lower(state).compile()
        own_compile = time.perf_counter() - t0
        programs = {"shared": shared, "own": own}
        inputs = {"shared": (state, *method_args), "own": (state,)}
        records = {k: jax.device_get(p(*inputs[k])[1]) for k, p in programs.items()}
        times = bench.timed_in_turn(programs, inputs, args.repeats)
        row = {"own_compile_s": own_compile,
               **{f"{k}_run_s": {"median": float(np.median(v)), "runs": v} for k, v in times.items()},
               **compare_records(records["shared"], records["own"])}
        row["shared_over_own_run"] = row["shared_run_s"]["median"] / row["own_run_s"]["median"]
        out["methods"][method] = row
        print(f"{method}: shared {row['shared_run_s']['median']:.2f} s, own "
              f"{row['own_run_s']['median']:.2f} s (x{row['shared_over_own_run']:.3f}), compile own "
              f"{own_compile:.1f} s, max rel diff {row['max_rel_diff']:.1e}", file=sys.stderr, flush=True)
    out["own_compile_s_total"] = sum(r["own_compile_s"] for r in out["methods"].values())
    bench.print_report(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
