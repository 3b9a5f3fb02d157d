"""The sparse GP's update on buffers padded to a multiple of 8 slots against unpadded, in turn.

`sparse_gp.update_batch`'s loops widen the buffers from M + 1 = 101 slots to 104
(`sparse_gp.padded_slots`, `sparse_gp.SLOT_MULTIPLE = 8`); with `SLOT_MULTIPLE = 1` they run on
the 101 slots as before. Each figure compiles both variants in one process (the module constant
set while each traces) and times them in turn (A B A B ...), so that their ratio holds when the
machine's speed drifts:

* ``gp_update``: `gpguided bench`'s sparse-GP figure (M = 100, 10 pendulum-like streams of 3000
  pairs, the seeds over the devices and one after another on each), float64 and float32;
* ``train``: each GP method's whole paper-preset run for the seeds, compiled as `gpguided
  reproduce` compiles it (`reproduce.per_seed_program`), float64 (float32 with --float32-train).

The outputs are compared as well: the largest absolute difference of the records' mean reward
(rounding, amplified by the training loop), and whether the GP streams' basis-vector sets agree.
Prints JSON (--out also writes it).

Usage:
  python experiments/bench_slot_padding.py --seeds 10 --out docs/results/slot_padding.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import bench, distributed, reproduce, sparse_gp
from gpguided_jax import config as config_lib
from gpguided_jax import train as train_lib
from gpguided_jax.cli import available_cores, single_threaded_lapack

VARIANTS = {"unpadded": 1, "padded": 8}


def _compiled_variants(build) -> tuple[dict, dict]:
    """({variant: build()}, {variant: slots the update works on for M = 100}), with
    `sparse_gp.SLOT_MULTIPLE` set while each is traced and compiled."""
    original = sparse_gp.SLOT_MULTIPLE
    out, slots = {}, {}
    try:
        for name, multiple in VARIANTS.items():
            sparse_gp.SLOT_MULTIPLE = multiple
            out[name] = build()
            slots[name] = sparse_gp.padded_slots(101)
    finally:
        sparse_gp.SLOT_MULTIPLE = original
    return out, slots


def _ratio_report(times: dict) -> dict:
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"run_s": {k: {"median": med[k], "min": min(v), "max": max(v), "runs": v}
                      for k, v in times.items()},
            "padded_over_unpadded": med["padded"] / med["unpadded"]}


def bench_gp_update(mesh, dtype, repeats: int, seeds: int = 10, n: int = 3000) -> dict:
    xs, ys, _ = bench.gp_streams(seeds, n, dtype)
    xs, ys = distributed.shard((xs, ys), mesh)
    progs, slots = _compiled_variants(
        lambda: bench.gp_stream_program(mesh, n, 100, dtype).lower(xs, ys).compile())
    outs = {k: p(xs, ys) for k, p in progs.items()}
    times = bench.timed_in_turn(progs, {k: (xs, ys) for k in progs}, repeats)
    report = _ratio_report(times)
    report["us_per_pair_and_seed"] = {k: 1e6 * v["median"] / (n * seeds)
                                      for k, v in report["run_s"].items()}
    report["same_basis_vectors"] = bool(np.array_equal(np.asarray(outs["padded"].basis_vectors),
                                                       np.asarray(outs["unpadded"].basis_vectors)))
    report["slots"] = slots
    return report


def bench_train(mesh, keys, dtype: str, methods, repeats: int, preset: str = "paper") -> dict:
    cfg = config_lib.preset(preset, method="gp_pg", dtype=dtype)
    fit = reproduce.per_seed_program(train_lib.make_train(cfg).fit_kernel_for_seed, mesh)
    priors = fit(keys)
    out = {}
    for method in methods:
        c = config_lib.preset(preset, method=method, dtype=dtype)
        train = train_lib.make_train(c)
        state = bench.initial_states(c, mesh, keys, priors)

        def build(train=train, c=c, state=state):
            run = reproduce.per_seed_program(lambda s: train.run_chunk(s, c, c.num_updates), mesh)
            return run.lower(state).compile()

        progs, _ = _compiled_variants(build)
        outs = {k: p(state) for k, p in progs.items()}
        times = bench.timed_in_turn(progs, {k: (state,) for k in progs}, repeats)
        report = _ratio_report(times)
        report["max_abs_difference_mean_reward"] = float(np.max(np.abs(
            np.asarray(outs["padded"][1].mean_reward) - np.asarray(outs["unpadded"][1].mean_reward))))
        out[method] = report
        print(f"{method} {dtype}: padded/unpadded {report['padded_over_unpadded']:.3f}",
              file=sys.stderr, flush=True)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--gp-repeats", type=int, default=21)
    parser.add_argument("--train-repeats", type=int, default=5)
    parser.add_argument("--methods", nargs="+", default=["gp_pg", "guided_variance",
                                                         "guided_direction"])
    parser.add_argument("--quick", action="store_true",
                        help="tiny sizes, float64 only, the tiny preset's gp_pg, one run of each (tests)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    single_threaded_lapack()
    cores = available_cores()
    jax.config.update("jax_num_cpu_devices", cores)
    jax.config.update("jax_enable_x64", True)
    seeds = 2 if args.quick else args.seeds
    mesh, keys = bench.seed_mesh(seeds)
    t0 = time.perf_counter()
    report = {"date": time.strftime("%Y-%m-%d"), "jax": jax.__version__, "seeds": seeds,
              "devices": int(mesh.devices.size), "quick": args.quick,
              "slot_multiple": {k: v for k, v in VARIANTS.items()}}
    n = 200 if args.quick else 3000
    gp_repeats = 1 if args.quick else args.gp_repeats
    dtypes = ("float64",) if args.quick else ("float64", "float32")
    report["gp_update"] = {d: bench_gp_update(mesh, getattr(jnp, d), gp_repeats, seeds, n)
                           for d in dtypes}
    report["preset"] = "tiny" if args.quick else "paper"
    report["train"] = {"float64": bench_train(
        mesh, keys, "float64", ["gp_pg"] if args.quick else args.methods,
        1 if args.quick else args.train_repeats, report["preset"])}
    report["wall_s"] = time.perf_counter() - t0
    bench.print_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
