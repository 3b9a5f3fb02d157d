"""Paper Fig. 1: composition of the basis-vector set as a function of the age penalty lambda.

Protocol (the paper gives no details beyond the figure; these choices are ours):

* Pendulum `gpguided_jax.pendulum` with its default parameters (200 Hz control, |u| <= 5).
* Policy: a ~ N(c(s), sigma^2), c(s) = 5 tanh(theta^T [sin phi, cos phi, omega, 1]), sigma = 1,
  theta_0 ~ N(0, 0.5^2 I). A "policy improvement" is simulated by a Gaussian random walk
  theta <- theta + N(0, 0.1^2 I) (no learning: Fig. 1 is about the GP's bookkeeping, not the policy).
* Per improvement k = 0..59: 3 episodes x 50 steps with the current theta; inputs
  x = (sin phi, cos phi, omega, a), targets the discounted returns-to-go (gamma = 0.95) within the
  episode; every pair is stamped with timestamp k and taken in by `sparse_gp.update_batch`.
* Hyperparameters: fitted once (`hyperfit.fit`, 150 Adam steps) on 600 pairs of the initial policy,
  shared by all lambda values.
* GP: budget M = 20, novelty tolerance 1e-4, exponential age function (eq. 14) with c = 1
  (consecutive 200 Hz states are close, so only a few pairs per improvement are novel enough to
  join the set; with M = 100 the share of the latest improvement cannot exceed ~10%).
* For lambda in {0, 10, 100, 400, 1000} (one `vmap` over lambda, one compiled program) we record,
  after the data of improvement k has been taken in, the share of BVs whose timestamp is k.

Outputs (under --out, default results/fig1): fig1_bv_composition.png and fig1_bv_composition.csv
(columns: improvement, then one column per lambda, in percent, mean over --seeds runs).
"""

from __future__ import annotations

import argparse
import csv
import os

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import gpguided_jax  # noqa: E402
from gpguided_jax import hyperfit, kernels, pendulum, sparse_gp  # noqa: E402

gpguided_jax.enable_x64()  # float64: the package leaves this choice to its user

LAMBDAS = (0.0, 10.0, 100.0, 400.0, 1000.0)


def controller(theta, state):
    psi = jnp.stack([jnp.sin(state[0]), jnp.cos(state[0]), state[1], jnp.ones_like(state[0])])
    return 5.0 * jnp.tanh(theta @ psi)


def collect(key, theta, params, num_episodes, num_steps, sigma, discount):
    """Features (E*T, 4) and discounted returns-to-go (E*T,) for one policy."""

    def policy_fn(k, s):
        return controller(theta, s) + sigma * jax.random.normal(k, (), s.dtype)

    traj = pendulum.batch_rollout(
        jax.random.split(key, num_episodes), params, policy_fn, num_steps
    )

    def returns_to_go(rewards):
        def body(acc, r):
            acc = r + discount * acc
            return acc, acc

        _, ret = jax.lax.scan(body, jnp.zeros((), rewards.dtype), rewards, reverse=True)
        return ret

    rets = jax.vmap(returns_to_go)(traj.rewards)
    feats = jax.vmap(jax.vmap(kernels.state_action_features))(traj.states, traj.actions)
    return feats.reshape(-1, 4), rets.reshape(-1)


def make_run(params, hyper, *, capacity, num_improvements, num_episodes, num_steps, sigma,
             discount, walk_std, novelty_tol, age_scale, age_fn):
    def data_for(key, theta0):
        def body(theta, inputs):
            k_data, k_walk = jax.random.split(inputs)
            xs, ys = collect(k_data, theta, params, num_episodes, num_steps, sigma, discount)
            theta = theta + walk_std * jax.random.normal(k_walk, theta.shape, theta.dtype)
            return theta, (xs, ys)

        _, (xs, ys) = jax.lax.scan(body, theta0, jax.random.split(key, num_improvements))
        return xs, ys  # (K, E*T, 4), (K, E*T)

    def gp_run(xs, ys, lam):
        def body(state, inputs):
            k, x_k, y_k = inputs
            state = sparse_gp.update_batch(
                state, x_k, y_k, hyper, k, novelty_tol=novelty_tol, age_penalty=lam,
                age_scale=age_scale, age_fn=age_fn,
            )
            share = jnp.sum(state.mask & (state.timestamps == k)) / jnp.maximum(
                sparse_gp.num_basis_vectors(state), 1
            )
            return state, share

        state = sparse_gp.init(capacity, xs.shape[-1])
        _, shares = jax.lax.scan(body, state, (jnp.arange(xs.shape[0]), xs, ys))
        return shares

    over_lambdas = jax.vmap(gp_run, in_axes=(None, None, 0))
    return jax.jit(jax.vmap(data_for)), jax.jit(jax.vmap(over_lambdas, in_axes=(0, 0, None)))


def main(argv=None):
    parser = argparse.ArgumentParser(description="Reproduce the paper's Fig. 1")
    parser.add_argument("--out", default="results/fig1")
    parser.add_argument("--seed", type=int, default=0, help="base seed")
    parser.add_argument("--seeds", type=int, default=10, help="independent runs averaged")
    parser.add_argument("--improvements", type=int, default=60)
    parser.add_argument("--capacity", type=int, default=20)
    parser.add_argument("--age-scale", type=float, default=1.0)
    parser.add_argument("--age-fn", default="exp", choices=sparse_gp.AGE_FUNCTIONS)
    args = parser.parse_args(argv)

    params = pendulum.make_params()
    key = jax.random.PRNGKey(args.seed)
    k_theta, k_fit, k_data = jax.random.split(key, 3)
    theta0 = 0.5 * jax.random.normal(k_theta, (args.seeds, 4))
    sigma, discount = 1.0, 0.95

    fit_x, fit_y = jax.jit(collect, static_argnums=(3, 4))(
        k_fit, theta0[0], params, 12, 50, sigma, discount
    )
    fit = jax.jit(hyperfit.fit, static_argnames=("num_steps", "optimizer"))(
        fit_x, fit_y, num_steps=150, optimizer="adam")
    hyper = fit.params
    print("fitted hyperparameters:", jax.tree.map(lambda a: np.round(np.asarray(a), 4), hyper))

    data_for, gp_runs = make_run(
        params, hyper, capacity=args.capacity, num_improvements=args.improvements,
        num_episodes=3, num_steps=50, sigma=sigma, discount=discount, walk_std=0.1,
        novelty_tol=1e-4, age_scale=args.age_scale, age_fn=args.age_fn,
    )
    xs, ys = data_for(jax.random.split(k_data, args.seeds), theta0)
    per_seed = 100.0 * np.asarray(gp_runs(xs, ys, jnp.asarray(LAMBDAS)))  # (S, L, K)
    shares = per_seed.mean(0)  # (L, K)
    stderr = per_seed.std(0, ddof=1) / np.sqrt(args.seeds) if args.seeds > 1 else 0 * shares

    os.makedirs(args.out, exist_ok=True)
    csv_path = os.path.join(args.out, "fig1_bv_composition.csv")
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["improvement"] + [f"lambda={lam:g}" for lam in LAMBDAS])
        for k in range(shares.shape[1]):
            writer.writerow([k + 1] + [f"{s:.2f}" for s in shares[:, k]])
    fig, ax = plt.subplots(figsize=(6, 4))
    x = np.arange(1, shares.shape[1] + 1)
    for lam, row, se in zip(LAMBDAS, shares, stderr, strict=True):
        ax.plot(x, row, label=f"λ={lam:g}")
        ax.fill_between(x, row - se, row + se, alpha=0.2)
    ax.set_xlabel("Number of policy improvements")
    ax.set_ylabel("percentage of new basis functions")
    ax.set_ylim(0, 100)
    ax.set_title(f"BV-set composition (M={args.capacity}, g={args.age_fn}, c={args.age_scale:g}; "
                 f"mean ± s.e. over {args.seeds} runs)", fontsize=9)
    ax.legend()
    fig.tight_layout()
    png_path = os.path.join(args.out, "fig1_bv_composition.png")
    fig.savefig(png_path, dpi=120)
    print("mean share over improvements (%):",
          {f"{lam:g}": round(float(r.mean()), 1) for lam, r in zip(LAMBDAS, shares, strict=True)})
    print("wrote", png_path, csv_path)


if __name__ == "__main__":
    main()
