"""Training throughput: the paper-preset run as one compiled program vs a per-seed NumPy loop.

    python experiments/bench_train.py [--seeds 10] [--methods ...] [--numpy-updates 4]

For each method: compile time and run time of `jit(vmap(train))` over the seeds (the run timed on
a second call with other keys), and seed-steps per second (seeds x updates x episodes x steps /
run time). The NumPy baseline does the same work as `gp_pg` for one seed — pendulum RK4 steps,
the fixed-noise linear policy and its score, the online GP (`gp_reference.OnlineGP`) update with
every (x, return) pair, Q predictions and the SGD step — for `--numpy-updates` updates, and is
extrapolated linearly to all updates and seeds (the hyperparameter fit is excluded from both).
Output: JSON on stdout.
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import bench
from gpguided_jax import config as C
from gpguided_jax import train as T

gpguided_jax.enable_x64()  # float64 (the package leaves the choice to its user)


def numpy_gp_pg_updates(cfg, prior, num_updates, rng):
    """Per-seed NumPy Algorithm 1 (method gp_pg): wall seconds for `num_updates` updates
    (`gpguided_jax.bench.numpy_gp_pg_seconds_per_update`, the loop `gpguided bench` times)."""
    return bench.numpy_gp_pg_seconds_per_update(cfg, prior, num_updates, rng) * num_updates


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--methods", nargs="+", default=list(C.METHODS))
    ap.add_argument("--numpy-updates", type=int, default=20)
    args = ap.parse_args(argv)

    out = {"benchmark": "train", "preset": args.preset, "seeds": args.seeds,
           "jax_version": jax.__version__, "gpguided_jax_version": gpguided_jax.__version__,
           "device": str(jax.devices()[0]), "device_count": jax.device_count(), "methods": {}}
    total_wall = 0.0
    kernel_batch = None
    for method in args.methods:
        cfg = C.preset(args.preset, method=method)
        train = T.make_train(cfg)
        keys = jnp.stack([jax.random.PRNGKey(s) for s in range(args.seeds)])
        if cfg.uses_gp and kernel_batch is None:
            t0 = time.perf_counter()
            kernel_batch = jax.block_until_ready(jax.jit(jax.vmap(train.fit_kernel_for_seed))(keys))
            out["hyperfit_s"] = round(time.perf_counter() - t0, 3)
            total_wall += out["hyperfit_s"]
        kern = kernel_batch if cfg.uses_gp else None
        if kern is not None:
            init = jax.jit(jax.vmap(lambda k, kk, train=train, cfg=cfg: train.init(k, cfg, kk)))
            args_init = (keys, kern)
        else:
            init = jax.jit(jax.vmap(train.init))
            args_init = (keys,)
        run = jax.jit(jax.vmap(lambda s, train=train, cfg=cfg: train.run_chunk(s, cfg, cfg.num_updates)))
        state = jax.block_until_ready(init(*args_init))
        t0 = time.perf_counter()
        compiled = run.lower(state).compile()
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, rec = compiled(state)
        jax.block_until_ready(rec)
        run_s = time.perf_counter() - t0
        steps = args.seeds * cfg.num_updates * cfg.episodes_per_update * cfg.episode_length
        out["methods"][method] = {"compile_s": round(compile_s, 3), "run_s": round(run_s, 3),
                                  "seed_steps_per_s": round(steps / run_s, 1)}
        total_wall += compile_s + run_s

    out["total_wall_s_all_methods"] = round(total_wall, 2)
    if "gp_pg" in out["methods"] and kernel_batch is not None:
        cfg = C.preset(args.preset, method="gp_pg")
        kernel0 = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], kernel_batch)
        secs = numpy_gp_pg_updates(cfg, kernel0, args.numpy_updates, np.random.default_rng(0))
        per_update = secs / args.numpy_updates
        np_total = per_update * cfg.num_updates * args.seeds
        steps = args.seeds * cfg.num_updates * cfg.episodes_per_update * cfg.episode_length
        out["numpy_gp_pg"] = {
            "measured_updates": args.numpy_updates, "seconds_per_update_one_seed": round(per_update, 4),
            "extrapolated_run_s": round(np_total, 1), "seed_steps_per_s": round(steps / np_total, 1)}
        out["ratio_jax_over_numpy_gp_pg"] = round(np_total / out["methods"]["gp_pg"]["run_s"], 1)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
