"""The paper's Fig. 3: the Gibbs action-selection policy (eq. 20) at one state.

At a state s with c(s) = 0 (the linear controller at its zero initialisation), a GP is built whose
mean Q_GP(s, a) over a in [-6, 6] has two peaks (an exact GP on a grid of actions at s, targets
from a two-bump function in negative reward units, as the pendulum's returns are). Panel (a)

gpguided_jax.enable_x64()
plots over a dense action grid the min-max normalised Q~, the energy
E = Q~ exp(-a^2 / (2 sigma_e^2)) and pi = softmax(beta E) (beta = 10; pi is shown scaled to a
maximum of 1); panel (b) the histogram of actions selected by `policies.gibbs_policy` over
10 000 draws, each with its own K candidates a_j ~ N(c(s), sigma^2_cand).

Writes fig3_gibbs_policy.png, fig3_curves.csv and fig3_histogram.csv under --out.

Usage: python experiments/fig3_gibbs_policy.py [--out results/fig3] [--seed 0]
"""

import argparse
import os

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpguided_jax import controllers, kernels, policies, sparse_gp  # noqa: E402

STATE = (np.pi / 2, 1.0)  # any state: the controller is zero everywhere
ACTION_RANGE = 6.0


def two_peaked_q(a):
    """Raw (negative) Q over actions with two bumps, the higher at a = -2."""
    return (
        -8.0
        + 5.0 * np.exp(-0.5 * ((a + 2.0) / 0.8) ** 2)
        + 3.5 * np.exp(-0.5 * ((a - 2.5) / 0.9) ** 2)
    )


def build_gp(state, num_points=25):
    """An exact GP over actions at `state` (every basis vector at this state), in the sparse GP's
    state form (docs/design.md#sparse-gp)."""
    actions = np.linspace(-ACTION_RANGE, ACTION_RANGE, num_points)
    xs = jax.vmap(kernels.state_action_features, (None, 0))(state, jnp.asarray(actions))
    hyper = kernels.make_kernel_params(jnp.array([1.0, 1.0, 1.0, 0.7]), 10.0, 0.01)
    gp = sparse_gp.exact_state(xs, jnp.asarray(two_peaked_q(actions)), hyper, jitter=1e-10)
    return gp, hyper


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/fig3")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--draws", type=int, default=10_000)
    parser.add_argument("--beta", type=float, default=10.0)
    parser.add_argument("--energy-width", type=float, default=2.0, help="sigma_e")
    parser.add_argument("--candidates", type=int, default=64, help="K")
    parser.add_argument(
        "--candidate-std", type=float, default=3.0, help="sqrt of the candidate-variance floor"
    )
    return parser.parse_args()


def gibbs_at_state(args):
    """The Gibbs policy at STATE with zero controller weights (c(s) = 0): (a) Q_GP, its min-max
    normalisation, the energy and pi over a dense action grid; (b) the selections of the policy's
    own sampler. Returns (grid, q, q_tilde, energy, pi, actions, aux, mean_action)."""
    state = jnp.asarray(STATE)
    controller = controllers.linear_controller()
    theta = policies.init_params(controller)  # zero weights: c(s) = 0
    gp, hyper = build_gp(state)
    ctx = policies.make_context(
        gp,
        hyper,
        inverse_temperature=args.beta,
        energy_width=args.energy_width,
        candidate_scale=1.0,
        candidate_floor=args.candidate_std**2,
    )
    mean_action = controller.apply(theta.controller, state)
    assert float(mean_action) == 0.0

    # (a) curves over a dense action grid.
    grid = jnp.linspace(-ACTION_RANGE, ACTION_RANGE, 481)
    q = jax.vmap(policies.gp_mean, (None, None, None, 0))(gp, hyper, state, grid)
    q_tilde = policies.normalise_q(q)
    energy, pi = policies.gibbs_distribution(grid, q_tilde, mean_action, ctx)

    # (b) selections by the policy's own sampler.
    policy = policies.make_policy("gibbs", controller, num_candidates=args.candidates)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.draws)
    actions, aux = jax.jit(jax.vmap(policy.sample, (0, None, None, None)))(
        keys, theta, state, ctx
    )
    return grid, q, q_tilde, energy, pi, np.asarray(actions), aux, mean_action


def main():
    args = parse_args()
    os.makedirs(args.out, exist_ok=True)
    grid, q, q_tilde, energy, pi, actions, aux, mean_action = gibbs_at_state(args)
    edges = np.linspace(-ACTION_RANGE - 0.25, ACTION_RANGE + 0.25, 51)
    counts, _ = np.histogram(actions, bins=edges)

    curves = np.stack(
        [np.asarray(grid), np.asarray(q), np.asarray(q_tilde), np.asarray(energy), np.asarray(pi)],
        axis=1,
    )
    np.savetxt(
        os.path.join(args.out, "fig3_curves.csv"),
        curves,
        delimiter=",",
        header="action,q_gp,q_tilde,energy,pi",
        comments="",
    )
    np.savetxt(
        os.path.join(args.out, "fig3_histogram.csv"),
        np.stack([edges[:-1], edges[1:], counts], axis=1),
        delimiter=",",
        header="bin_left,bin_right,count",
        comments="",
        fmt=["%.4f", "%.4f", "%d"],
    )

    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(11, 4))
    ax_a.plot(grid, q_tilde, label=r"$\tilde Q_{GP}(s,a)$ (min-max normalised)")
    ax_a.plot(grid, energy, label=r"$E(s,a)$")
    ax_a.plot(grid, pi / jnp.max(pi), label=r"$\pi(a|s)$ (scaled to max 1)")
    ax_a.plot([float(mean_action)], [0.0], "k*", markersize=12, label=r"$c_\theta(s)$")
    ax_a.set_xlabel("action a")
    ax_a.set_title(rf"(a) Gibbs policy, $\beta$ = {args.beta:g}, $\sigma_e$ = {args.energy_width:g}")
    ax_a.legend(fontsize=8)
    ax_b.hist(actions, bins=edges, color="tab:orange")
    ax_b.set_xlabel("selected action")
    ax_b.set_ylabel("selection frequency")
    ax_b.set_title(f"(b) {args.draws} selections, K = {args.candidates} candidates")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "fig3_gibbs_policy.png"), dpi=120)

    summary = (
        f"argmax Q~ at a = {float(grid[jnp.argmax(q_tilde)]):.2f}, "
        f"argmax E at a = {float(grid[jnp.argmax(energy)]):.2f}; "
        f"selected actions: mean {actions.mean():.2f}, std {actions.std():.2f}, "
        f"share in (-4, 0): {np.mean((actions > -4) & (actions < 0)):.2f}, "
        f"share in (0.5, 4.5): {np.mean((actions > 0.5) & (actions < 4.5)):.2f}; "
        f"mean candidate std {float(jnp.sqrt(jnp.mean(aux.variance))):.2f}"
    )
    print(summary)
    print(f"wrote {args.out}/fig3_gibbs_policy.png, fig3_curves.csv, fig3_histogram.csv")


if __name__ == "__main__":
    main()
