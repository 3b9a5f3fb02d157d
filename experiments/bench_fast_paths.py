"""This project's two faster paths of 2026-12-02 against what they replaced, timed in turn.

* ``fit``: the hyperparameter fit's likelihood gradient with A^{-1} from `hyperfit.cholesky_inverse`
  (blocked matrix products, what `hyperfit.nlml_and_grad` does) against the gradient as it was
  before: a triangular solve of the Cholesky factor with the identity and the full product
  L^{-T} L^{-1} (`plain_nlml_and_grad` below). The paper preset's fit of the seeds is compiled
  once with each (`hyperfit.nlml_and_grad` pointed at one or the other while it traces).
* ``rollouts``: REINFORCE's and gp_pg's whole run with the update's episodes rolled out side by
  side (the fixed-noise policy does not read the GP; what `train.one_update` does) against one
  after another with the GP taking each in before the next (what every policy did before; the
  path a policy that reads the GP takes, chosen here by marking the policy `reads_gp=True`).

Both compiled as `gpguided reproduce` compiles them (`reproduce.per_seed_program`: one device per
core, the seeds one after another), timed in turn (A B A B ...) so that their ratio holds when the
machine's speed drifts, and their outputs compared (largest relative difference of the fitted
hyperparameters; largest absolute difference of the records). Prints JSON (--out also writes it).

Usage:
  python experiments/bench_fast_paths.py --seeds 10 --out docs/results/fast_paths.json
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import bench, hyperfit, kernels, reproduce
from gpguided_jax import config as config_lib
from gpguided_jax import train as train_lib
from gpguided_jax.cli import available_cores, single_threaded_lapack

gpguided_jax.enable_x64()


def plain_nlml_and_grad(log_hyper, xs, ys, jitter=1e-8):
    """`hyperfit.nlml_and_grad` as it was before the blocked inverse (the same formulas)."""
    hyper = hyperfit.from_log(log_hyper)
    n = xs.shape[0]
    eye = jnp.eye(n, dtype=xs.dtype)
    K = kernels.gram(xs, xs, hyper)
    L = jnp.linalg.cholesky(K + (hyper.noise_variance + jitter * hyper.signal_variance) * eye)
    L_inv = jax.scipy.linalg.solve_triangular(L, eye, lower=True)
    z = L_inv @ ys
    a = L_inv.T @ z
    A_inv = L_inv.T @ L_inv
    loss = 0.5 * z @ z + jnp.sum(jnp.log(jnp.diagonal(L))) + 0.5 * n * math.log(2 * math.pi)
    WK = (A_inv - jnp.outer(a, a)) * K
    trace_w = jnp.trace(A_inv) - a @ a
    row_sums = jnp.sum(WK, axis=1)
    quad = jnp.sum(xs * (WK @ xs), axis=0)
    sq_sums = 2.0 * (row_sums @ (xs * xs)) - 2.0 * quad
    grad_ls = 0.5 * sq_sums / hyper.lengthscales**2
    grad_sf = 0.5 * (jnp.sum(WK) + jitter * hyper.signal_variance * trace_w)
    grad_sn = 0.5 * hyper.noise_variance * trace_w
    return loss, hyperfit.LogParams(grad_ls, grad_sf, grad_sn)


def _in_turn(progs: dict, args: dict, repeats: int) -> dict:
    times = bench.timed_in_turn(progs, args, repeats)
    return {k: {"run_s_median": float(np.median(v)), "run_s": v} for k, v in times.items()}


def bench_fit(mesh, keys, repeats: int, preset: str = "paper") -> dict:
    cfg = config_lib.preset(preset, method="gp_pg")
    progs, fitted = {}, {}
    for name, grad in (("plain", plain_nlml_and_grad), ("blocked", hyperfit.nlml_and_grad)):
        # a new program per variant (a new function to trace), traced with `grad` in place
        fit = reproduce.per_seed_program(train_lib.make_train(cfg).fit_kernel_for_seed, mesh)
        original = hyperfit.nlml_and_grad
        hyperfit.nlml_and_grad = grad
        try:
            progs[name] = fit.lower(keys).compile()
        finally:
            hyperfit.nlml_and_grad = original
        fitted[name] = jax.device_get(progs[name](keys))
    row = _in_turn(progs, {k: (keys,) for k in progs}, repeats)
    rel = max(float(np.max(np.abs(a - b) / np.abs(b)))
              for a, b in zip(jax.tree.leaves(fitted["blocked"]), jax.tree.leaves(fitted["plain"])))
    row["speedup_blocked_over_plain"] = row["plain"]["run_s_median"] / row["blocked"]["run_s_median"]
    row["max_relative_difference_of_fitted_hyperparameters"] = rel
    return row


def _rollout_programs(method, mesh, keys, priors, preset):
    """(state, {variant: compiled whole run}) for one method, the two roll-out paths."""
    cfg = config_lib.preset(preset, method=method)
    train = train_lib.make_train(cfg)
    state = bench.initial_states(cfg, mesh, keys, priors)
    progs = {}
    for name, reads_gp in (("one_after_another", True), ("side_by_side", False)):
        prog = train.program._replace(policy=train.program.policy._replace(reads_gp=reads_gp))

        def run(s, prog=prog):
            return jax.lax.scan(lambda st, _: train_lib.one_update(prog, cfg, st), s, None,
                                length=cfg.num_updates)

        progs[name] = reproduce.per_seed_program(run, mesh).lower(state).compile()
    return state, progs


def bench_rollouts(mesh, keys, repeats: int, preset: str = "paper") -> dict:
    out = {}
    priors = reproduce.per_seed_program(
        train_lib.make_train(config_lib.preset(preset, method="gp_pg")).fit_kernel_for_seed,
        mesh)(keys)
    for method in ("reinforce", "gp_pg"):
        state, progs = _rollout_programs(method, mesh, keys, priors, preset)
        records = {k: jax.device_get(c(state)[1]) for k, c in progs.items()}
        row = _in_turn(progs, {k: (state,) for k in progs}, repeats)
        row["speedup_side_by_side"] = (row["one_after_another"]["run_s_median"]
                                       / row["side_by_side"]["run_s_median"])
        row["max_abs_record_difference"] = max(
            float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))))
            for a, b in zip(records["side_by_side"], records["one_after_another"]))
        out[method] = row
        print(f"{method}: x{row['speedup_side_by_side']:.2f}", file=sys.stderr, flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    single_threaded_lapack()
    jax.config.update("jax_num_cpu_devices", available_cores())
    mesh, keys = bench.seed_mesh(args.seeds)
    t0 = time.perf_counter()
    out = {"seeds": args.seeds, "devices": int(mesh.devices.size), "date": time.strftime("%Y-%m-%d"),
           "jax": jax.__version__, "preset": args.preset,
           "fit": bench_fit(mesh, keys, args.repeats, args.preset),
           "rollouts": bench_rollouts(mesh, keys, args.repeats, args.preset)}
    out["wall_s"] = time.perf_counter() - t0
    bench.print_report(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
