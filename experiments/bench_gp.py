"""Throughput of the sparse online GP update: JAX (jit + vmap over seeds) vs the NumPy reference.

For every budget M in {50, 100, 200} and every number of seeds in {1, 10, 100}, each seed takes in
the same number of (x, y) pairs one after the other (`sparse_gp.update_batch`, i.e. a `lax.scan`,
vmapped over seeds, compiled once). The NumPy reference (`gp_reference.OnlineGP`) runs the same
streams in a plain Python loop over seeds and pairs. Its rate does not depend on the number of seeds
(one seed after the other), so it is measured on at most `--numpy-seeds` of them and reported as
updates per second; the JAX rate counts all seeds. Times are medians over repeats; the JAX compile
time is measured apart (`jit(...).lower(...).compile()`). Output: JSON on stdout.

Data: pendulum-like state-action features x = (sin phi, cos phi, omega, a) with phi ~ U[0, 2 pi),
omega ~ N(0, 2^2), a ~ U[-5, 5], y = -(phi - pi)^2 - 0.1 omega^2 + noise; novelty tolerance 1e-4, so
nearly every pair joins the set and, once it is full, triggers a deletion (the most expensive path);
lambda = 10 with the exponential age penalty and a timestamp that advances every 150 pairs.

Usage:
  python experiments/bench_gp.py            # full grid
  python experiments/bench_gp.py --quick    # small run (M in {50, 100}, seeds in {1, 10})
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import gp_reference, kernels, sparse_gp

gpguided_jax.enable_x64()  # float64 (the package leaves the choice to its user)

LENGTHSCALES = np.array([0.5, 0.5, 1.0, 2.0])
SIGNAL_VARIANCE = 4.0
NOISE_VARIANCE = 0.01
UPDATE_KWARGS = dict(novelty_tol=1e-4, age_penalty=10.0, age_scale=0.1, age_fn="exp")


def make_stream(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    omega = rng.normal(0.0, 2.0, n)
    action = rng.uniform(-5.0, 5.0, n)
    xs = np.stack([np.sin(phi), np.cos(phi), omega, action], axis=1)
    ys = -((phi - np.pi) ** 2) - 0.1 * omega**2 + 0.1 * rng.normal(size=n)
    return xs, ys


def bench_jax(capacity: int, xs: np.ndarray, ys: np.ndarray, timestamps: np.ndarray, repeats: int):
    hyper = kernels.make_kernel_params(LENGTHSCALES, SIGNAL_VARIANCE, NOISE_VARIANCE)
    input_dim = xs.shape[-1]

    def one_seed(x, y):
        state = sparse_gp.init(capacity, input_dim)
        return sparse_gp.update_batch(state, x, y, hyper, timestamps, unroll=2, **UPDATE_KWARGS)

    fn = jax.jit(jax.vmap(one_seed))
    xs_j, ys_j = jnp.asarray(xs), jnp.asarray(ys)
    t0 = time.perf_counter()
    compiled = fn.lower(xs_j, ys_j).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(xs_j, ys_j))  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(xs_j, ys_j))
        times.append(time.perf_counter() - t0)
    num_bv = np.asarray(sparse_gp.num_basis_vectors(jax.tree.map(lambda a: a[0], out)))
    return compile_s, statistics.median(times), int(num_bv)


def bench_numpy(capacity: int, xs: np.ndarray, ys: np.ndarray, timestamps: np.ndarray, repeats: int):
    times, outcomes = [], {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        for seed in range(xs.shape[0]):
            gp = gp_reference.OnlineGP(
                capacity, xs.shape[-1], LENGTHSCALES, SIGNAL_VARIANCE, NOISE_VARIANCE,
                **UPDATE_KWARGS,
            )
            for i in range(xs.shape[1]):
                o = gp.update(xs[seed, i], ys[seed, i], timestamps[i])
                outcomes[o] = outcomes.get(o, 0) + 1
        times.append(time.perf_counter() - t0)
    total = sum(outcomes.values())
    return statistics.median(times), {k: round(v / total, 3) for k, v in sorted(outcomes.items())}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small run")
    parser.add_argument("--updates", type=int, default=None, help="pairs per seed")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--numpy-seeds", type=int, default=2, help="max seeds run in NumPy")
    args = parser.parse_args(argv)
    capacities = (50, 100) if args.quick else (50, 100, 200)
    seed_counts = (1, 10) if args.quick else (1, 10, 100)
    n = args.updates or (300 if args.quick else 1000)
    repeats = args.repeats or (3 if args.quick else 5)
    timestamps = (np.arange(n) // 150).astype(np.int32)

    results = []
    for capacity in capacities:
        for seeds in seed_counts:
            streams = [make_stream(s, n) for s in range(seeds)]
            xs = np.stack([s[0] for s in streams])
            ys = np.stack([s[1] for s in streams])
            compile_s, jax_s, num_bv = bench_jax(capacity, xs, ys, timestamps, repeats)
            np_seeds = min(seeds, args.numpy_seeds)
            np_s, outcomes = bench_numpy(
                capacity, xs[:np_seeds], ys[:np_seeds], timestamps, max(1, repeats // 2)
            )
            jax_rate = seeds * n / jax_s
            np_rate = np_seeds * n / np_s
            results.append(
                dict(
                    capacity=capacity,
                    seeds=seeds,
                    updates_per_seed=n,
                    jax_updates_per_s=round(jax_rate),
                    numpy_updates_per_s=round(np_rate),
                    ratio=round(jax_rate / np_rate, 2),
                    jax_median_s=round(jax_s, 5),
                    jax_compile_s=round(compile_s, 3),
                    numpy_median_s=round(np_s, 4),
                    numpy_seeds_timed=np_seeds,
                    outcome_fractions=outcomes,
                    final_num_basis_vectors=num_bv,
                )
            )
            print(json.dumps(results[-1]), file=sys.stderr, flush=True)
    report = dict(
        jax_version=jax.__version__,
        numpy_version=np.__version__,
        device=str(jax.devices()[0]),
        device_kind=jax.devices()[0].device_kind,
        platform=platform.platform(),
        cpu_count=os.cpu_count(),
        load_average_after=[round(x, 2) for x in os.getloadavg()],
        dtype="float64",
        update_kwargs=UPDATE_KWARGS,
        results=results,
    )
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
