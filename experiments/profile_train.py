"""Where the time of a training run goes, per method (paper preset, the seeds run as
`gpguided reproduce` runs them: `reproduce.per_seed_program` over one CPU device per core, each
device taking its seeds one after another by default; `--seed-loop vmap --cpu-devices 1` profiles
the one-batch program instead).

The per-update computation (gpguided_jax.train.one_update) is split into its parts, each compiled
on its own and timed over `--updates` updates for all seeds at a realistic point of a run (the
state after `--warmup` updates, when the GP holds its basis vectors):

* rollout_fixed_noise: the episodes with the fixed-noise policy (pendulum + linear controller),
  side by side as training rolls them out (the policy does not read the GP);
* rollout_policy: the episodes with the method's own policy; the difference to the fixed-noise
  roll-out is the policy's GP work (guided variance: sigma^2 and its gradient at every step;
  Gibbs: the candidates' GP means and the candidate variance);
* gp_update: the sparse GP taking in the episodes' pairs (`take_in_episode`, health check included);
* prediction: Q_GP at the update's state-action pairs (eq. 9's weights);
* full_update: one_update itself (everything, as the training loop runs it).

For the GP update, XLA's cost analysis of one projected GP step (straight-line code; a loop's
cost analysis counts its body once) times the points taken in gives the achieved FLOP/s. Host
work between chunks (the records to the host and the checkpoint write, as
`reproduce.run_method` does them) is timed on its own (`host_overhead`). Prints JSON.

Usage:
  python experiments/profile_train.py --seeds 10 [--methods ...] [--updates 50]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import config as config_lib
from gpguided_jax import distributed, estimators, reproduce, sparse_gp
from gpguided_jax import train as T
from gpguided_jax.cli import available_cores, single_threaded_lapack

gpguided_jax.enable_x64()


def _time(fn, *args, repeats=3):
    out = fn(*args)
    jax.block_until_ready(out)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def _flops(compiled) -> float:
    cost = compiled.cost_analysis()
    if isinstance(cost, list):  # older jax returned one dict per device
        cost = cost[0]
    return float(cost.get("flops", float("nan"))) if cost else float("nan")


def _programs(seeds: list[int], loop: str):
    """(per-seed program maker, sharded seed keys) on the mesh `gpguided reproduce` would use."""
    mesh = reproduce.make_mesh(None, len(seeds))
    if len(seeds) % mesh.devices.size:
        mesh = reproduce.make_mesh(1)
    keys = distributed.shard(reproduce.seed_keys(seeds), mesh)
    return (lambda fn: reproduce.per_seed_program(fn, mesh, loop)), keys


def profile_method(method: str, seeds: list[int], updates: int, warmup: int, dtype: str,
                   loop: str = "auto") -> dict:
    cfg = config_lib.preset("paper", method=method, dtype=dtype)
    prog = T.make_program(cfg)
    train = T.make_train(cfg)
    per_seed, keys = _programs(seeds, loop)
    state = per_seed(lambda k: train.init(k, cfg))(keys)
    state, _ = per_seed(lambda s: train.run_chunk(s, cfg, warmup))(state)
    jax.block_until_ready(state)
    E = cfg.episodes_per_update

    def episodes(state, policy):
        keys = jax.random.split(state.key, E)
        if not policy.reads_gp:  # side by side, as train.one_update rolls them out
            ctx = T.policy_context(cfg, state.gp, state.kernel)
            return jax.vmap(lambda k: T.rollout(prog, k, state.theta, ctx, policy, cfg))(keys)

        def one(gp, key):
            ep = T.rollout(prog, key, state.theta, T.policy_context(cfg, gp, state.kernel), policy, cfg)
            return gp, ep
        return jax.lax.scan(one, state.gp, keys)[1]

    def repeat(body):
        """`body(state) -> state` scanned `updates` times, for every seed, compiled."""
        return per_seed(lambda s: jax.lax.scan(lambda c, _: (body(c), None), s, None,
                                               length=updates)[0])

    def rollout_body(policy):
        def body(s):
            eps = episodes(s, policy)
            # feed something back so the loop is not hoisted: the next key depends on the rewards
            key = jax.random.fold_in(s.key, jnp.sum(eps.rewards > 0).astype(jnp.int32))
            return s._replace(key=key)
        return body

    def data(s):
        eps = episodes(s, prog.policy)
        returns = jax.vmap(estimators.discounted_returns, (0, None))(eps.rewards, cfg.discount)
        return jax.vmap(T._features)(eps.states, eps.actions), returns

    feats, returns = per_seed(data)(state)

    out = {}
    out["rollout_fixed_noise_s"] = _time(repeat(rollout_body(prog.behaviour)), state)
    out["rollout_policy_s"] = _time(repeat(rollout_body(prog.policy)), state)
    if cfg.uses_gp:
        # the same episodes' data every time (the GP keeps changing, as in training)
        gp_fn = per_seed(lambda s, f, r: jax.lax.scan(
            lambda c, _: (_gp(c, f, r), None), s, None, length=updates)[0])

        def _gp(s, f, r):
            gp = s.gp
            for e in range(E):
                gp, _, _ = T.take_in_episode(gp, s.kernel, f[e], r[e], s.update_index, cfg)
            return s._replace(gp=gp)

        out["gp_update_s"] = _time(gp_fn, state, feats, returns)
        pred_fn = per_seed(lambda s, f: jax.lax.scan(
            lambda acc, _: (acc + jnp.sum(jax.vmap(jax.vmap(
                lambda x: sparse_gp.predict(s.gp, x + 1e-9 * acc, s.kernel)[0]))(f)), None),
            jnp.zeros((), s.gp.alpha.dtype), None, length=updates)[0])
        out["prediction_s"] = _time(pred_fn, state, feats)
        # FLOPs of one GP point on the projected path (no insertion: most points once the set is
        # full), from XLA's cost analysis of straight-line code (the cost analysis of a loop counts
        # its body once, so the whole run's count is not usable), for all seeds
        state0 = jax.tree.map(lambda a: np.asarray(a)[0], jax.device_get(state))
        x0, y0 = np.asarray(feats)[0, 0, 0], np.asarray(returns)[0, 0, 0]

        def projected(s, x, y):
            proj = sparse_gp.project(s.gp, x, s.kernel)
            return sparse_gp._projected_update(s.gp, proj, y, s.kernel.noise_variance, True)

        point_flops = len(seeds) * _flops(jax.jit(projected).lower(state0, x0, y0).compile())
        points = updates * E * cfg.episode_length
        out["gp_points"] = points
        out["gp_point_flops_all_seeds"] = point_flops
        out["gp_update_achieved_gflops_per_s"] = point_flops * points / out["gp_update_s"] / 1e9
    full = per_seed(lambda s: train.run_chunk(s, cfg, updates))
    compiled = full.lower(state).compile()
    out["full_update_s"] = _time(compiled, state)
    out["per_update_ms"] = 1e3 * out["full_update_s"] / updates
    return out


def host_overhead(seeds: list[int], chunk: int, loop: str = "auto", repeats: int = 5,
                  preset: str = "paper") -> dict:
    """What `reproduce.run_method` does on the host between two compiled chunks, timed on its own
    on the paper preset's gp_pg state after a chunk of `chunk` updates: the chunk's records
    gathered to the host and appended to the run's, and the checkpoint written
    (`reproduce._save_checkpoint`: every state leaf and record, fsync'd). Until 2026-12-03 this
    was a second `run_method` call's wall time minus its chunks' device time, which counted the
    compilation of that call's new programs as host work (0.52 s per chunk, against ~0.01 s)."""
    cfg = config_lib.preset(preset, method="gp_pg")
    train = T.make_train(cfg)
    per_seed, keys = _programs(seeds, loop)
    state = per_seed(lambda k: train.init(k, cfg))(keys)
    state, rec = per_seed(lambda s: train.run_chunk(s, cfg, chunk))(state)
    jax.block_until_ready(state)
    records = {k: np.zeros((len(seeds), 0)) for k in reproduce.RECORD_FIELDS}
    times = []
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "checkpoint_gp_pg.npz")
        for i in range(repeats):
            t0 = time.perf_counter()
            _, records = reproduce.append_records(records, rec)
            reproduce._save_checkpoint(path, state, records, i + 1, "profile")
            times.append(time.perf_counter() - t0)
        size = os.path.getsize(path)
    return {"method": "gp_pg", "chunk_updates": chunk, "checkpoint_bytes": size,
            "runs_s": times, "host_s_per_chunk": float(np.median(times))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--methods", nargs="+", default=list(config_lib.METHODS))
    ap.add_argument("--updates", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=100)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--seed-loop", default="auto", choices=["auto", "vmap", "map"])
    ap.add_argument("--cpu-devices", type=int, default=available_cores(),
                    help="JAX CPU devices (default: one per available core, as `gpguided reproduce`)")
    args = ap.parse_args(argv)
    single_threaded_lapack()
    jax.config.update("jax_num_cpu_devices", args.cpu_devices)
    seeds = list(range(100, 100 + args.seeds))  # tuning seeds: this is not a result
    result = {"seeds": args.seeds, "updates": args.updates, "warmup": args.warmup, "dtype": args.dtype,
              "jax": jax.__version__, "devices": [str(d) for d in jax.devices()],
              "seed_loop": reproduce.resolve_seed_loop(args.seed_loop, reproduce.make_mesh()),
              "methods": {}}
    for m in args.methods:
        result["methods"][m] = profile_method(m, seeds, args.updates, args.warmup, args.dtype,
                                              args.seed_loop)
        print(m, json.dumps(result["methods"][m]), file=sys.stderr, flush=True)
    result["host"] = host_overhead(seeds, args.updates, args.seed_loop)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
