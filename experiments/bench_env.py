"""Pendulum throughput: steps per second for 1, 10 and 1000 vmapped episodes, printed as JSON.

    python experiments/bench_env.py [--steps 2000] [--repeats 5]

Each episode is a `lax.scan` over `--steps` steps of a fixed linear controller with Gaussian noise;
batches are a `vmap` over episode keys; the whole thing is one jitted call. Compilation is timed
separately; the run time is the median of `--repeats` calls.
"""

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp

import gpguided_jax
from gpguided_jax import pendulum

gpguided_jax.enable_x64()  # float64 (the package leaves the choice to its user)


def _policy(key, s):
    return -2.0 * jnp.sin(s[0]) - 0.3 * s[1] + 0.5 * jax.random.normal(key, (), s.dtype)


def bench(batch: int, steps: int, repeats: int, params) -> dict:
    run = jax.jit(
        lambda keys: pendulum.batch_rollout(keys, params, _policy, steps).rewards.sum()
    )
    keys = jax.random.split(jax.random.key(0), batch)
    t0 = time.perf_counter()
    run(keys).block_until_ready()
    compile_s = time.perf_counter() - t0
    times = []
    for i in range(repeats):
        keys = jax.random.split(jax.random.key(i + 1), batch)
        t0 = time.perf_counter()
        run(keys).block_until_ready()
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {
        "episodes": batch,
        "steps_per_episode": steps,
        "compile_and_first_run_s": round(compile_s, 4),
        "median_run_s": round(med, 6),
        "steps_per_second": round(batch * steps / med, 1),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 10, 1000])
    args = ap.parse_args(argv)
    params = pendulum.make_params()
    results = [bench(b, args.steps, args.repeats, params) for b in args.batches]
    print(
        json.dumps(
            {
                "benchmark": "pendulum_env",
                "jax_version": jax.__version__,
                "gpguided_jax_version": gpguided_jax.__version__,
                "device": str(jax.devices()[0]),
                "dtype": str(params.dt.dtype),
                "results": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
