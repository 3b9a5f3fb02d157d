"""The hyperparameter fit with OpenBLAS's default thread count against one thread per process.

JAX's CPU Cholesky and triangular solves call the OpenBLAS that SciPy bundles. By default it starts
one thread per core for every call; `gpguided reproduce` also runs one JAX device per core, and
both devices fit their seeds at the same time. Each trial here is a fresh process that fits the
paper preset's hyperparameters for --seeds seeds (1000..., 100 Adam steps on 500 pairs, one device
per core, the seeds one after another on each: exactly the fit of `gpguided reproduce`), with
OPENBLAS_NUM_THREADS unset ("default") or set to 1 ("one_thread"); the two settings run in turn
(A B A B ...) so that their ratio holds when the machine's speed drifts. Reported per setting: the
fit's wall time (median, min, max; compilation excluded) and whether the fitted hyperparameters
were the same bit for bit in every trial of that setting, and across the two settings.

Usage:
  python experiments/bench_lapack_threads.py --seeds 10 --repeats 3 --out docs/results/lapack_threads.json
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import tempfile

import numpy as np

from gpguided_jax import cli

SETTINGS = ("default", "one_thread")

_TRIAL = """
import sys, time
import numpy as np
import jax
from gpguided_jax import cli
jax.config.update("jax_num_cpu_devices", cli.available_cores())
import gpguided_jax
gpguided_jax.enable_x64()
from gpguided_jax import config, distributed, reproduce, train
seeds = int(sys.argv[1])
mesh = reproduce.make_mesh(num_seeds=seeds)
fit = reproduce.per_seed_program(train.make_train(config.preset("paper", method="gp_pg"))
                                 .fit_kernel_for_seed, mesh, "map")
keys = distributed.shard(reproduce.seed_keys(reproduce.pad_seeds(range(1000, 1000 + seeds),
                                                                 mesh.devices.size)), mesh)
compiled = fit.lower(keys).compile()
t0 = time.perf_counter()
prior = jax.block_until_ready(compiled(keys))
seconds = time.perf_counter() - t0
k = prior.kernel
np.save(sys.argv[2], np.concatenate([np.asarray(k.lengthscales).ravel(),
                                     np.asarray(k.signal_variance).ravel(),
                                     np.asarray(k.noise_variance).ravel()]))
print(seconds)
"""


def trial(setting: str, seeds: int, path: str) -> float:
    env = {k: v for k, v in os.environ.items() if k not in cli.LAPACK_THREAD_VARIABLES}
    env.pop("XLA_FLAGS", None)
    if setting == "one_thread":
        env["OPENBLAS_NUM_THREADS"] = "1"
    proc = subprocess.run([sys.executable, "-c", _TRIAL, str(seeds), path], env=env,
                          capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-3000:])
    return float(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    times = {s: [] for s in SETTINGS}
    fitted = {s: [] for s in SETTINGS}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for s in SETTINGS:
                path = os.path.join(tmp, f"{s}_{r}.npy")
                times[s].append(trial(s, args.seeds, path))
                fitted[s].append(np.load(path))
    from gpguided_jax import bench  # after the trials: this process needs no JAX device set-up

    out = {"seeds": args.seeds, "repeats": args.repeats, "cores": cli.available_cores(),
           "date": datetime.date.today().isoformat(), "settings": {}}
    for s in SETTINGS:
        out["settings"][s] = {
            "fit_s": bench._stats(times[s]),
            "same_bits_in_every_trial": all(np.array_equal(f, fitted[s][0]) for f in fitted[s]),
            "max_relative_spread": float(max(np.max(np.abs(f - fitted[s][0]) / np.abs(fitted[s][0]))
                                             for f in fitted[s])),
        }
    out["default_over_one_thread"] = (out["settings"]["default"]["fit_s"]["median"]
                                      / out["settings"]["one_thread"]["fit_s"]["median"])
    out["same_bits_across_settings"] = bool(np.array_equal(fitted["default"][0], fitted["one_thread"][0]))
    bench.print_report(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
