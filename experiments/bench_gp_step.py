"""What bounds one projected step of the sparse GP on this CPU (M = 100, 101 slots, float64).

A projected pair (one that does not join the basis) costs four passes over an 80 kB factor:
w = T k (its novelty), z = Z k, g = Z^T z and the rank-one write of Z (Potter). This times, each
in a compiled loop of many iterations (so that no call overhead is counted):

* `real`: `sparse_gp.update_batch` (the segmented loop) on 50 pairs that are all projected, per pair;
* `four_passes`: a loop of just those four passes (three matrix-vector products and a rank-one
  update), in float64 and float32 (half the bytes);
* `one_matvec`: one 101 x 101 matrix-vector product;
* `twenty_small_ops`: a chain of 20 dependent small operations, per operation (the cost of
  launching one);
* `block`: projected pairs taken in B at a time by the block form of Potter's update
  (F = Z K^T, A = F^T F + sigma_n^2 I = L L^T, Z <- Z - F (L + sigma_n I)^{-T} L^{-1} F^T Z, three
  matrix products and a Cholesky instead of B matrix-vector chains), per pair, with its largest
  difference from the pair-by-pair result. Not used by the library: it is not faster here.

Prints JSON (--out also writes it).

Usage:
  python experiments/bench_gp_step.py --out docs/results/gp_step.json
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import bench, kernels, sparse_gp

gpguided_jax.enable_x64()

M, D, PAIRS = 100, 4, 50


def _timed(f, x, per, repeats):
    """Median over `repeats` runs of the compiled f(x), divided by `per`, in microseconds."""
    g = jax.jit(f)
    jax.block_until_ready(g(x))
    return float(np.median(bench.timed_in_turn({"f": g}, {"f": (x,)}, repeats)["f"])) / per * 1e6


def _block_update(state, k_rows, ys, noise_variance):
    """Block Potter update of alpha and Z with the B rows of k_rows (all projected pairs)."""
    Z = state.alpha_cov_root
    b = k_rows.shape[0]
    F = Z @ k_rows.T
    G = Z.T @ F
    L = jnp.linalg.cholesky(F.T @ F + noise_variance * jnp.eye(b))
    u = jax.scipy.linalg.cho_solve((L, True), ys - state.prior_mean - k_rows @ state.alpha)
    X = jax.scipy.linalg.solve_triangular(L, G.T, lower=True)
    V = L + jnp.sqrt(noise_variance) * jnp.eye(b)
    Y = jax.scipy.linalg.solve_triangular(V, X, lower=True, trans="T")
    return state._replace(alpha=state.alpha + G @ u, alpha_cov_root=Z - F @ Y)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    n_it, reps = args.iterations, args.repeats
    rng = np.random.default_rng(0)
    hyper = kernels.make_kernel_params(jnp.ones(D), 1.0, 0.01)
    full = sparse_gp.init(M, D)
    x0 = jnp.asarray(rng.uniform(-3, 3, (400, D)))
    full = jax.jit(lambda s: sparse_gp.update_batch(s, x0, jnp.sin(x0.sum(1)), hyper, 0))(full)
    active = np.flatnonzero(np.asarray(full.mask))[:PAIRS]
    xs = full.basis_vectors[active] + 1e-4  # next to BVs: every pair is projected
    ys = jnp.sin(xs.sum(1)) + 0.1
    _, info = jax.jit(lambda s: sparse_gp.update_batch(s, xs, ys, hyper, 1, with_info=True,
                                                       loop="segments"))(full)
    assert not bool(jnp.any(info.added)), "the benchmark pairs must all be projected"

    def repeat(body):
        return lambda s: jax.lax.fori_loop(0, n_it, lambda i, c: body(c), s)

    out = {"capacity": M, "slots": M + 1, "pairs": PAIRS, "iterations": n_it, "repeats": reps,
           "jax": jax.__version__}
    out["real_us_per_pair"] = _timed(
        repeat(lambda s: sparse_gp.update_batch(s, xs, ys, hyper, 1, loop="segments")), full,
        n_it * PAIRS, reps)

    def four(dtype):
        T = full.gram_inv_root.astype(dtype)
        v0 = jnp.ones(M + 1, dtype)

        def body(c):
            v, Z = c
            w = T @ v
            z = Z @ v
            g = z @ Z
            return (w + z) * 0.5, Z - 1e-6 * z[:, None] * g[None, :]

        return _timed(repeat(body), (v0, full.alpha_cov_root.astype(dtype)), n_it, reps)

    out["four_passes_us"] = {"float64": four(jnp.float64), "float32": four(jnp.float32)}
    P = full.gram_inv_root
    out["one_matvec_us"] = _timed(repeat(lambda v: P @ v * 0.5 + 0.5), jnp.ones(M + 1), n_it, reps)

    def small(c):
        s = c[0]
        for _ in range(20):
            s = jnp.dot(c[:4], c[:4] * s) * 1e-3 + 1.0
        return c * (1 + 1e-9 * s)

    out["small_op_us"] = _timed(repeat(small), jnp.ones(M + 1), n_it * 20, reps)

    k_all = jnp.where(full.mask[None, :], kernels.gram(xs, full.basis_vectors, hyper), 0.0)
    seq = jax.jit(lambda s: sparse_gp.update_batch(s, xs, ys, hyper, 1, loop="segments"))(full)
    out["block"] = {}
    for b in (10, 25, 50):
        def blocks(s, b=b):
            for j in range(0, PAIRS, b):
                s = _block_update(s, k_all[j:j + b], ys[j:j + b], hyper.noise_variance)
            return s

        got = jax.jit(blocks)(full)
        err = float(jnp.max(jnp.abs(sparse_gp.alpha_covariance(got) - sparse_gp.alpha_covariance(seq))))
        out["block"][str(b)] = {
            "us_per_pair": _timed(repeat(blocks), full, n_it * PAIRS, reps),
            "max_cov_alpha_difference": err,
            "max_alpha_difference": float(jnp.max(jnp.abs(got.alpha - seq.alpha))),
        }
    print(f"real {out['real_us_per_pair']:.2f} us/pair, four passes {out['four_passes_us']}, "
          f"block {[(b, round(v['us_per_pair'], 2)) for b, v in out['block'].items()]}",
          file=sys.stderr)
    bench.print_report(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
