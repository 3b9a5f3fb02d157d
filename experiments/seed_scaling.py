"""Seed scaling of the paper run on the host it runs on: 10, 30, 100 and 300 seeds.

For each number of seeds S (in its own process, so that its peak memory can be read), float64:
the hyperparameter fit of S seeds (compile and run), then for every method all 400 updates in
chunks of 50 (compile, then the 8 chunks timed). Reported per S: seeds x updates per second per
method, the whole run's wall time (fit + compile + run of every method, without the checkpoint and
figure writing of `gpguided reproduce`), the process's peak resident memory, and XLA's memory
analysis of the largest chunk program (arguments + outputs + temporaries, the memory a device
needs). The per-seed slope of the latter gives the largest batch that fits in one 80 GB
accelerator (an estimate: no GPU was available here; a GPU's own buffers and XLA's GPU kernels
differ from the CPU's).

Above --full-up-to seeds (30) only the first --partial-updates (100) updates of each method are
timed and the run time is extrapolated to 400 (`updates_timed` in the JSON says which).

Writes scaling.json and scaling.png to --out and prints the JSON.

Usage:
  python experiments/seed_scaling.py --seeds 10 30 100 300 --out docs/results/scaling
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

from gpguided_jax.runtime import available_cores, single_threaded_lapack

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHUNK = 50


def measure(num_seeds: int, measured_updates: int | None = None, seed_loop: str = "auto",
            cpu_devices: int = 1) -> dict:
    import jax

    single_threaded_lapack()
    jax.config.update("jax_num_cpu_devices", cpu_devices)
    import numpy as np

    import gpguided_jax
    from gpguided_jax import config as config_lib
    from gpguided_jax import sharding
    from gpguided_jax import train as train_lib

    gpguided_jax.enable_x64()
    mesh = sharding.make_mesh(None, num_seeds)  # as `gpguided reproduce` runs the seeds
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    seeds = sharding.pad_seeds(range(2000, 2000 + num_seeds), mesh.devices.size)
    keys = sharding.shard(sharding.seed_keys(seeds), mesh)  # not a result: throughput only
    out = {"seeds": num_seeds, "devices": int(mesh.devices.size), "seed_loop": loop, "methods": {}}
    cfg_gp = config_lib.preset("paper", method="gp_pg")
    fit = sharding.per_seed_program(train_lib.make_train(cfg_gp).fit_kernel_for_seed, mesh, loop)
    t0 = time.perf_counter()
    compiled_fit = fit.lower(keys).compile()
    out["hyperfit_compile_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    priors = jax.block_until_ready(compiled_fit(keys))
    out["hyperfit_run_s"] = time.perf_counter() - t0
    device_bytes = []
    for method in config_lib.PAPER_METHODS:
        cfg = config_lib.preset("paper", method=method)
        train = train_lib.make_train(cfg)
        if cfg.uses_gp:
            state = sharding.per_seed_program(lambda k, p, t=train, c=cfg: t.init(k, c, p),
                                               mesh, loop)(keys, priors)
        else:
            state = sharding.per_seed_program(lambda k, t=train, c=cfg: t.init(k, c), mesh,
                                               loop)(keys)
        run = sharding.per_seed_program(lambda s, t=train, c=cfg: t.run_chunk(s, c, CHUNK),
                                         mesh, loop)
        t0 = time.perf_counter()
        compiled = run.lower(state).compile()
        compile_s = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        nbytes = (mem.argument_size_in_bytes + mem.output_size_in_bytes
                  + mem.temp_size_in_bytes) if mem is not None else float("nan")
        device_bytes.append(nbytes)
        jax.block_until_ready(state)
        t0 = time.perf_counter()
        finite = True
        done = min(cfg.num_updates, measured_updates or cfg.num_updates)
        for _ in range(done // CHUNK):
            state, rec = compiled(state)
            finite &= bool(np.all(np.isfinite(np.asarray(rec.mean_reward))))
        # a partial run is extrapolated to all updates (a GP update's cost does not grow once the
        # basis is full, which it is within the first chunk)
        run_s = (time.perf_counter() - t0) * cfg.num_updates / (done // CHUNK * CHUNK)
        out["methods"][method] = {"compile_s": compile_s, "run_s": run_s,
                                  "seed_updates_per_s": num_seeds * cfg.num_updates / run_s,
                                  "whole_run_s": compile_s + run_s, "device_bytes": nbytes,
                                  "finite": finite, "updates_timed": done // CHUNK * CHUNK}
    out["whole_paper_run_s"] = (out["hyperfit_compile_s"] + out["hyperfit_run_s"]
                                + sum(m["whole_run_s"] for m in out["methods"].values()))
    out["device_bytes_max"] = max(device_bytes)
    out["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return out


def plot(results: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = [r["seeds"] for r in results]
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(13, 3.8))
    a.plot(seeds, [r["whole_paper_run_s"] for r in results], "o-", color="k", label="all methods")
    for m in results[0]["methods"]:
        a.plot(seeds, [r["methods"][m]["whole_run_s"] for r in results], ".--", label=m)
        b.plot(seeds, [r["methods"][m]["seed_updates_per_s"] for r in results], "o-", label=m)
    a.set(xscale="log", yscale="log", xlabel="seeds", ylabel="wall time of the paper run [s]")
    b.set(xscale="log", yscale="log", xlabel="seeds", ylabel="seeds x updates per second")
    c.plot(seeds, [r["peak_rss_bytes"] / 2**30 for r in results], "o-", label="process peak RSS")
    c.plot(seeds, [r["device_bytes_max"] / 2**30 for r in results], "s-",
           label="XLA memory analysis (largest program)")
    c.set(xscale="log", yscale="log", xlabel="seeds", ylabel="memory [GiB]")
    for ax in (a, b, c):
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    r0 = results[0]
    fig.suptitle(f"Paper preset, float64, 2-core CPU, {r0.get('devices', 1)} device(s), seed loop "
                 f"{r0.get('seed_loop', 'vmap')}: every method's 400 updates")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 30, 100, 300])
    ap.add_argument("--out", default="results/scaling")
    ap.add_argument("--full-up-to", type=int, default=30,
                    help="seed counts above this time only --partial-updates updates and extrapolate "
                         "to 400 (default 30)")
    ap.add_argument("--partial-updates", type=int, default=100)
    ap.add_argument("--seed-loop", default="auto", choices=["auto", "vmap", "map"],
                    help="how each device runs its seeds (as `gpguided reproduce --seed-loop`)")
    ap.add_argument("--cpu-devices", type=int, default=available_cores(),
                    help="JAX CPU devices (default: one per available core, as `gpguided reproduce`)")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--updates", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one is not None:  # the child process
        print(json.dumps(measure(args.one, args.updates, args.seed_loop, args.cpu_devices)))
        return 0
    results = []
    for n in args.seeds:
        extra = ["--updates", str(args.partial_updates)] if n > args.full_up_to else []
        proc = subprocess.run([sys.executable, __file__, "--one", str(n), *extra,
                               "--seed-loop", args.seed_loop, "--cpu-devices", str(args.cpu_devices)],
                              capture_output=True, text=True, cwd=ROOT)
        if proc.returncode != 0:
            raise SystemExit(proc.stderr[-3000:])
        results.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(f"{n} seeds: {results[-1]['whole_paper_run_s']:.1f} s", file=sys.stderr, flush=True)
    # per-seed device memory: slope between the two largest batches
    big, small = results[-1], results[-2] if len(results) > 1 else results[-1]
    per_seed = ((big["device_bytes_max"] - small["device_bytes_max"])
                / max(big["seeds"] - small["seeds"], 1)) if big is not small else \
        big["device_bytes_max"] / big["seeds"]
    report = {"results": results, "device_bytes_per_seed": per_seed,
              "seeds_in_80_GB": int(80e9 // per_seed) if per_seed > 0 else None}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "scaling.json"), "w") as f:
        json.dump(report, f, indent=2)
    plot(results, os.path.join(args.out, "scaling.png"))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
