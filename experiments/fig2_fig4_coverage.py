"""Paper Fig. 2 and Fig. 4, and the state-space coverage of each method.

Protocol (the paper shows one run per panel and gives no details; these choices are ours):

* Every method (reinforce, gp_pg = eq. 9 with fixed noise, guided_variance, guided_direction) is
  trained with the chosen preset for the given seeds: all seeds of a method as one compiled,
  vmapped program (`train.run_chunk`), in `--checkpoints` equal chunks of updates. The GP
  hyperparameters are fitted once per seed and shared by the GP methods, with the same keys as
  `gpguided reproduce` (seeds 0-4 of the paper preset reproduced that command's curves, bitwise
  for reinforce and guided_direction, up to floating-point divergence of the chaotic training for
  the other two: differently compiled programs round differently; that was before `reproduce`
  ran its GP methods as one program by default, which rounds differently again, so compare with
  `gpguided reproduce --gp-program per-method`).
* Visited states: after every chunk, `train.episodes` rolls out the method's own policy
  (controller, noise and GP as they are at that checkpoint, held fixed) for `--eval-episodes`
  episodes, with keys drawn apart from the training keys. The training episodes themselves are not
  returned by `train`, so these checkpoint roll-outs stand for the states a run visits:
  checkpoints x eval_episodes episodes per seed and method, the same number for every method.
* Coverage (`gpguided_jax.analysis.state_coverage`): the share of the cells of a grid over the whole
  state space, phi in [0, 2 pi) in 36 bins of 10 degrees and omega in [-8, 8] rad/s in 32 bins of
  0.5 rad/s (faster states count in the outermost bin), that at least one of those states falls
  in; mean and 95% t-interval over seeds, and its growth over the checkpoints.
* Fig. 2: the GP's latent predictive variance sigma^2(x*) at x* = (s, c(s)) (eq. 6; the guided
  exploration variance of eq. 16 is proportional to it), divided by the fitted signal variance
  sigma_f^2 so that 1 means "the GP knows nothing here", on a log colour scale, after learning,
  for seed `--plot-seed`: gp_pg (fixed noise) vs guided_variance. Dots: the states of the final
  roll-outs; crosses: the state part of the GP's basis vectors.
* Fig. 4: the GP state value V(s) = Q_GP(s, c(s)): gp_pg vs guided_direction. The colour range is
  that of the values at the visited states (V and the returns-to-go, padded): far from its data
  the GP mean extrapolates to values no return reaches, and those regions saturate. The dashed
  contour sigma^2/sigma_f^2 = 0.5 marks where the GP has data.
* Each figure has two rows: the whole state space [0, 2 pi) x [-8, 8], and a box around the
  visited states and basis vectors of the three GP methods and the upright state (padded), the
  same box for every panel.

Outputs (under --out, default results/fig24):
  fig2_variance.png / .csv   grid values (view, method, phi, omega, action c(s), latent variance var,
                             relative variance rel = var / sigma_f^2)
  fig4_value.png / .csv      grid values (view, method, phi, omega, action c(s), value, rel)
  visited_states.csv         final roll-outs of the plot seed: states, actions, rewards, returns-to-go,
                             V_GP and latent variance at (s, c(s))
  coverage.png               (a) coverage per method, mean and 95% CI; (b) coverage vs updates
  coverage.csv / .json       per method and seed, and the summary
  results.npz                per-update training records (methods, seeds, updates), coverage, and the
                             checkpoint roll-out states (methods, seeds, checkpoints, episodes, H, 2)
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import time

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import gpguided_jax  # noqa: E402
from gpguided_jax import analysis, estimators, methods, sharding  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402
from gpguided_jax import stats as stats_lib  # noqa: E402
from gpguided_jax import train as train_lib  # noqa: E402

gpguided_jax.enable_x64()  # float64: the package leaves this choice to its user
from gpguided_jax.sweep import even_chunk_size  # noqa: E402

METHODS = methods.paper()
LABELS = {
    "reinforce": "REINFORCE",
    "gp_pg": "fixed noise (gp_pg)",
    "guided_variance": "guided variance",
    "guided_direction": "guided direction",
}
GRID = dict(num_angle_bins=analysis.NUM_ANGLE_BINS, num_velocity_bins=analysis.NUM_VELOCITY_BINS,
            max_velocity=analysis.MAX_VELOCITY)
_EVAL_STREAM = 0x5EED  # fold_in offset of the evaluation keys (apart from the training keys)


def _log(msg):
    print(msg, flush=True)


def train_with_checkpoints(cfg, seeds, kernels, *, num_checkpoints, eval_episodes):
    """Trains all seeds of one method in equal chunks and rolls the policy out after each chunk.

    One compiled program per method runs a chunk of updates and then the checkpoint roll-outs.

    Returns:
      final TrainState (leading seed axis), records dict (S, U), visited states
      (S, chunks, eval_episodes, H, 2), the final roll-outs (`Episode`, leading seed axis), the
      update count at each checkpoint, and the `train` function.
    """
    train = train_lib.make_train(cfg)
    keys = sharding.seed_keys(seeds)
    if kernels is not None:
        state = jax.jit(jax.vmap(lambda k, kern: train.init(k, cfg, kern)))(keys, kernels)
    else:
        state = jax.jit(jax.vmap(lambda k: train.init(k, cfg)))(keys)
    n = even_chunk_size(cfg.num_updates, math.ceil(cfg.num_updates / num_checkpoints))

    def chunk_and_rollout(state, key, checkpoint):
        state, rec = train.run_chunk(state, cfg, n)
        # evaluation keys: a stream of their own, so the training keys are untouched
        ep = train.episodes(jax.random.fold_in(key, _EVAL_STREAM + checkpoint), state, cfg,
                            eval_episodes)
        return state, rec, ep

    step = jax.jit(jax.vmap(chunk_and_rollout, in_axes=(0, 0, None)))
    visited, recs, updates = [], [], []
    for c in range(cfg.num_updates // n):
        state, rec, ep = step(state, keys, c)
        recs.append(jax.device_get(rec))
        visited.append(np.asarray(ep.states))
        updates.append((c + 1) * n)
    records = {k: np.concatenate([np.asarray(getattr(r, k)) for r in recs], axis=1)
               for k in train_lib.RECORD_FIELDS}
    return state, records, np.stack(visited, axis=1), ep, np.asarray(updates), train


@jax.jit
def _cells_per_checkpoint(visited):
    return jax.vmap(jax.vmap(lambda s: analysis.visited_cells(s, **GRID)))(visited)


def coverage_of_run(visited):
    """Coverage per seed of all checkpoint states, and cumulative coverage per checkpoint.

    Args:
      visited: (S, C, E, H, 2).

    Returns:
      (S,) coverage, (S,) visited cell counts, (S, C) cumulative coverage.
    """
    cells = np.asarray(_cells_per_checkpoint(jnp.asarray(visited)))  # (S, C, A, B)
    cumulative = np.logical_or.accumulate(cells, axis=1)
    cum_share = cumulative.mean(axis=(2, 3))
    counts = cumulative[:, -1].sum(axis=(1, 2))
    return cum_share[:, -1], counts, cum_share


def surface_window(states):
    """A box around the given states (padded), inside [0, 2 pi] x [-8, 8]."""
    phi = np.mod(states[..., 0].ravel(), 2 * math.pi)
    om = states[..., 1].ravel()
    pad_p = max(0.4, 0.3 * np.ptp(phi))
    pad_o = max(0.75, 0.3 * np.ptp(om))
    p = (max(0.0, phi.min() - pad_p), min(2 * math.pi, phi.max() + pad_p))
    o = (max(-analysis.MAX_VELOCITY, om.min() - pad_o), min(analysis.MAX_VELOCITY, om.max() + pad_o))
    return p, o


FULL_WINDOW = ((0.0, 2 * math.pi), (-analysis.MAX_VELOCITY, analysis.MAX_VELOCITY))


def seed_slice(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def bv_states(gp):
    mask = np.asarray(gp.mask)
    bv = np.asarray(gp.basis_vectors)[mask]
    return np.stack([np.mod(np.arctan2(bv[:, 0], bv[:, 1]), 2 * math.pi), bv[:, 2]], axis=1)


def plot_surfaces(rows, path, *, cbar_label, title, norm, cmap, extend="neither", confident=None):
    """A grid of heat maps: `rows` is a list of (row title, phi, omega, panels), each panel a tuple
    (label, z (A, B), visited states (N, 2), basis-vector states (M, 2), relative variance (A, B)).
    `confident`: draw the contour sigma^2/sigma_f^2 = confident (where the GP has data)."""
    n_rows, n_cols = len(rows), len(rows[0][3])
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(5.6 * n_cols, 4.4 * n_rows), squeeze=False)
    for r, (row_title, phi, omega, panels) in enumerate(rows):
        for c, (label, z, visited, bvs, rel) in enumerate(panels):
            ax = axes[r][c]
            mesh = ax.pcolormesh(phi, omega, z.T, shading="auto", norm=norm, cmap=cmap)
            ax.contour(phi, omega, z.T, levels=8, norm=norm, colors="k", linewidths=0.4, alpha=0.4)
            if confident is not None:
                ax.contour(phi, omega, rel.T, levels=[confident], colors="c", linewidths=1.0,
                           linestyles="--")
            ax.scatter(np.mod(visited[:, 0], 2 * math.pi), visited[:, 1], s=5, c="w", alpha=0.8,
                       edgecolors="k", linewidths=0.2, label="visited states (final roll-outs)")
            ax.scatter(bvs[:, 0], bvs[:, 1], s=18, marker="x", c="tab:red", linewidths=0.8,
                       label="basis vectors (state part)")
            ax.plot([math.pi], [0.0], marker="*", ms=12, c="gold", mec="k", ls="", label="upright")
            ax.set_xlim(phi[0], phi[-1])
            ax.set_ylim(omega[0], omega[-1])
            ax.set_xlabel("φ [rad] (π = upright)")
            ax.set_ylabel("ω [rad/s]")
            ax.set_title(f"{label}: {row_title}")
            fig.colorbar(mesh, ax=ax, label=cbar_label, extend=extend)
    handles, labels = axes[-1][0].get_legend_handles_labels()
    if confident is not None:
        handles.append(matplotlib.lines.Line2D([], [], color="c", ls="--"))
        labels.append(f"σ²/σ_f² = {confident:g} (GP has data inside)")
    axes[-1][0].legend(handles, labels, loc="lower left", fontsize=7, framealpha=0.8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_grid_csv(path, columns, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        w.writerows(rows)


GP_METHODS = tuple(m for m in METHODS if m in methods.gp_methods())  # the paper's with a GP


def parse_args(argv=None):
    """(args, seeds, the plot seed)."""
    ap = argparse.ArgumentParser(description="Paper Fig. 2 and Fig. 4, and state coverage per method")
    ap.add_argument("--preset", default="paper", choices=sorted(config_lib.PRESETS))
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds (default 5)")
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--out", default="results/fig24")
    ap.add_argument("--num-updates", type=int, default=None, help="override num_updates (quick runs)")
    ap.add_argument("--checkpoints", type=int, default=10,
                    help="roll-out checkpoints over the run (default 10; rounded to equal chunks)")
    ap.add_argument("--eval-episodes", type=int, default=10, help="episodes per checkpoint (default 10)")
    ap.add_argument("--plot-seed", type=int, default=None, help="seed of Fig. 2/4 (default: the first)")
    ap.add_argument("--grid", type=int, default=61, help="surface grid points per axis (default 61)")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    plot_seed = seeds[0] if args.plot_seed is None else args.plot_seed
    if plot_seed not in seeds:
        ap.error(f"--plot-seed {plot_seed} is not among the seeds {seeds}")
    return args, seeds, plot_seed


def run_methods(cfgs, seeds, args) -> dict:
    """Every method trained with checkpoint roll-outs (`train_with_checkpoints`), the GP methods
    from one hyperparameter fit per seed, and its coverage: method -> dict of the run's parts."""
    t0 = time.perf_counter()
    fit = jax.jit(jax.vmap(train_lib.make_train(cfgs["gp_pg"]).fit_kernel_for_seed))
    kernels = jax.device_get(fit(sharding.seed_keys(seeds)))
    _log(f"hyperparameter fit for {len(seeds)} seeds: {time.perf_counter() - t0:.1f}s")
    runs = {}
    for m in METHODS:
        t0 = time.perf_counter()
        state, records, visited, final_ep, updates, train = train_with_checkpoints(
            cfgs[m], seeds, kernels if cfgs[m].uses_gp else None,
            num_checkpoints=args.checkpoints, eval_episodes=args.eval_episodes)
        cov, counts, cum = coverage_of_run(visited)
        runs[m] = dict(state=state, records=records, visited=visited, final_ep=final_ep,
                       updates=updates, train=train, coverage=cov, cells=counts, cumulative=cum)
        skipped = int(np.sum(np.any(records["nonfinite_grad"] > 0, axis=-1)))
        if skipped:
            _log(f"[{m}] WARNING: {skipped} seed(s) hit non-finite gradient estimates (skipped)")
        _log(f"[{m}] {cfgs[m].num_updates} updates x {len(seeds)} seeds, {len(updates)} checkpoints: "
             f"{time.perf_counter() - t0:.1f}s | final reward "
             f"{records['mean_reward'][:, -max(1, cfgs[m].num_updates // 10):].mean():.3f} | "
             f"coverage {cov.mean():.4f}")
    return runs


def coverage_summary(runs, seeds) -> list[dict]:
    """Per method: mean coverage with its 95% t-interval over seeds, and the mean cells visited."""
    summary = []
    for m in METHODS:
        mean, half = stats_lib.t_interval(runs[m]["coverage"])
        summary.append(dict(method=m, coverage_mean=float(mean), ci95_low=float(mean - half),
                            ci95_high=float(mean + half),
                            cells_mean=float(runs[m]["cells"].mean()), seeds=len(seeds)))
    return summary


def write_coverage(args, seeds, runs, summary) -> None:
    """coverage.csv (per method and seed) and coverage.json (the summary and the settings)."""
    n_cells = GRID["num_angle_bins"] * GRID["num_velocity_bins"]
    with open(os.path.join(args.out, "coverage.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "seed", "coverage", "cells_visited", "cells_total"])
        for m in METHODS:
            for s, c, k in zip(seeds, runs[m]["coverage"], runs[m]["cells"]):
                w.writerow([m, s, f"{c:.6f}", int(k), n_cells])
    with open(os.path.join(args.out, "coverage.json"), "w") as f:
        json.dump({
            "preset": args.preset, "seeds": seeds, "grid": GRID, "cells_total": n_cells,
            "checkpoints_at_updates": runs["gp_pg"]["updates"].tolist(),
            "eval_episodes_per_checkpoint": args.eval_episodes,
            "states_per_seed": int(np.prod(runs["gp_pg"]["visited"].shape[1:4])),
            "summary": summary,
            "per_seed": {m: runs[m]["coverage"].tolist() for m in METHODS},
            "cumulative_mean": {m: runs[m]["cumulative"].mean(0).tolist() for m in METHODS},
        }, f, indent=2)


def plot_coverage(path, runs, seeds, summary) -> None:
    """coverage.png: (a) coverage per method with its interval and the seeds, (b) its growth."""
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    x = np.arange(len(METHODS))
    means = np.array([r["coverage_mean"] for r in summary]) * 100
    halves = (np.array([r["ci95_high"] for r in summary]) * 100 - means)
    ax.bar(x, means, yerr=np.nan_to_num(halves), capsize=6, color=[f"C{i}" for i in range(len(METHODS))])
    for i, m in enumerate(METHODS):
        ax.scatter(np.full(len(seeds), i) + np.linspace(-0.15, 0.15, len(seeds)),
                   runs[m]["coverage"] * 100, s=10, c="k", zorder=3)
    ax.set_xticks(x, [LABELS[m] for m in METHODS], rotation=15)
    ax.set_ylabel(f"visited share of the {GRID['num_angle_bins']}×{GRID['num_velocity_bins']} "
                  "state grid [%]")
    ax.set_title(f"(a) state coverage over a run: mean, 95% CI, {len(seeds)} seeds")
    for i, m in enumerate(METHODS):
        mean, half = stats_lib.t_interval(runs[m]["cumulative"] * 100)
        u = runs[m]["updates"]
        ax2.plot(u, mean, "o-", ms=3, c=f"C{i}", label=LABELS[m])
        if len(seeds) > 1:
            ax2.fill_between(u, mean - half, mean + half, color=f"C{i}", alpha=0.2)
    ax2.set_xlabel("gradient updates performed")
    ax2.set_ylabel("cumulative visited share [%]")
    ax2.set_title("(b) coverage of the checkpoint roll-outs so far")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def gp_surfaces(cfgs, runs, ip, grid_points) -> dict:
    """The GP methods' final GPs of seed index `ip` over two (phi, omega) windows (the whole state
    space, and around the visited states and basis vectors): per (view, method) the value, the
    latent variance, the variance relative to sigma_f^2 and the controller's action."""
    final_states = {m: np.asarray(runs[m]["final_ep"].states[ip]).reshape(-1, 2) for m in GP_METHODS}
    final_gp = {m: seed_slice(runs[m]["state"], ip) for m in GP_METHODS}
    zoom = surface_window(np.concatenate(
        [*final_states.values(), *[bv_states(final_gp[m].gp) for m in GP_METHODS], [[math.pi, 0.0]]]))
    views = {"whole state space": FULL_WINDOW, "around the visited states": zoom}
    controller = train_lib.make_controller(cfgs["gp_pg"])  # one controller: one compiled surface
    surface = jax.jit(analysis.gp_surface, static_argnums=2)
    actions = jax.jit(jax.vmap(controller.apply, in_axes=(None, 0)))
    surf = {}  # (view, method) -> dict of (A, B) arrays
    grids = {}
    for view, ((p0, p1), (o0, o1)) in views.items():
        phi, omega = np.linspace(p0, p1, grid_points), np.linspace(o0, o1, grid_points)
        grids[view] = (phi, omega)
        pp, ww = np.meshgrid(phi, omega, indexing="ij")
        grid_states = jnp.asarray(np.stack([pp.ravel(), ww.ravel()], -1))
        for m in GP_METHODS:
            st = final_gp[m]
            value, var = surface(st.gp, st.kernel, controller, st.theta.controller, phi, omega)
            acts = np.asarray(actions(st.theta.controller, grid_states)).reshape(pp.shape)
            surf[view, m] = dict(value=np.asarray(value), var=np.asarray(var),
                                 rel=np.asarray(var) / float(st.kernel.signal_variance), action=acts)
    return dict(final_states=final_states, final_gp=final_gp, zoom=zoom, views=views,
                controller=controller, surf=surf, grids=grids)


def write_visited_states(path, cfgs, runs, ip, surfaces) -> dict:
    """visited_states.csv: the final roll-outs of seed index `ip` with their returns-to-go and the
    GP's value and variance there. Returns per GP method the values and returns seen."""
    rows, visited_vals = [], {}
    returns = jax.jit(jax.vmap(estimators.discounted_returns, in_axes=(0, None)))
    at_states = jax.jit(analysis.gp_at_states, static_argnums=2)
    controller = surfaces["controller"]
    for m in GP_METHODS:
        ep = jax.device_get(seed_slice(runs[m]["final_ep"], ip))
        st = surfaces["final_gp"][m]
        rets = np.asarray(returns(ep.rewards, cfgs[m].discount))
        s_flat = np.asarray(ep.states).reshape(-1, 2)
        v, var = (np.asarray(a) for a in at_states(st.gp, st.kernel, controller,
                                                   st.theta.controller, jnp.asarray(s_flat)))
        visited_vals[m] = np.concatenate([v, rets.ravel()])
        E, H = ep.rewards.shape
        for k in range(E * H):
            e, t = divmod(k, H)
            rows.append([m, e, t, f"{s_flat[k, 0]:.5f}", f"{s_flat[k, 1]:.5f}",
                         f"{ep.actions[e, t]:.5f}", f"{ep.rewards[e, t]:.5f}",
                         f"{rets[e, t]:.5f}", f"{v[k]:.5f}", f"{var[k]:.6g}"])
    write_grid_csv(path, ["method", "episode", "step", "phi", "omega", "action", "reward",
                          "return_to_go", "value_gp", "latent_variance"], rows)
    return visited_vals


def _surface_rows(surfaces, methods, key):
    """`plot_surfaces`'s rows: one per view, one panel per method."""
    surf, grids = surfaces["surf"], surfaces["grids"]
    return [(view, *grids[view],
             [(LABELS[m], surf[view, m][key], surfaces["final_states"][m],
               bv_states(surfaces["final_gp"][m].gp), surf[view, m]["rel"]) for m in methods])
            for view in surfaces["views"]]


def _write_surface_csv(path, surfaces, methods, keys) -> None:
    out = []
    for view in surfaces["views"]:
        phi, omega = surfaces["grids"][view]
        for m in methods:
            d = surfaces["surf"][view, m]
            out += [[view, m, f"{p:.5f}", f"{w:.5f}", f"{d['action'][i, j]:.6g}",
                     *[f"{d[k][i, j]:.6g}" for k in keys]]
                    for i, p in enumerate(phi) for j, w in enumerate(omega)]
    write_grid_csv(path, ["view", "method", "phi", "omega", "action", *keys], out)


def plot_fig2_fig4(out, subtitle, surfaces, visited_vals) -> None:
    """Fig. 2 (latent variance, gp_pg and guided_variance) and Fig. 4 (state value, gp_pg and
    guided_direction): PNG and CSV each."""
    f2 = ("gp_pg", "guided_variance")
    # log colour scale: the variance falls by orders of magnitude where the GP has data
    plot_surfaces(
        _surface_rows(surfaces, f2, "rel"), os.path.join(out, "fig2_variance.png"),
        cbar_label="σ²(s, c(s)) / σ_f²  (log scale)",
        title=f"Fig. 2: GP latent predictive variance at a = c(s) ({subtitle})",
        norm=matplotlib.colors.LogNorm(vmin=1e-3, vmax=1.0, clip=True), cmap="viridis",
        extend="min")
    _write_surface_csv(os.path.join(out, "fig2_variance.csv"), surfaces, f2, ("var", "rel"))

    f4 = ("gp_pg", "guided_direction")
    # colour range: the values seen at the visited states (V and returns-to-go); the GP mean
    # extrapolates far outside it where it has no data, and those regions saturate.
    seen = np.concatenate([visited_vals[m] for m in f4])
    lo, hi = np.percentile(seen, [0.5, 99.5])
    pad = 0.25 * (hi - lo) + 1e-9
    plot_surfaces(
        _surface_rows(surfaces, f4, "value"), os.path.join(out, "fig4_value.png"),
        cbar_label="V(s) = Q_GP(s, c(s))", title=f"Fig. 4: GP state value ({subtitle})",
        norm=matplotlib.colors.Normalize(vmin=lo - pad, vmax=hi + pad), cmap="magma",
        extend="both", confident=0.5)
    _write_surface_csv(os.path.join(out, "fig4_value.csv"), surfaces, f4, ("value", "rel"))


def save_results(path, seeds, runs) -> None:
    """results.npz: coverage, checkpoints, visited states and every record, per method and seed."""
    np.savez(path, methods=np.asarray(METHODS), seeds=np.asarray(seeds),
             coverage=np.stack([runs[m]["coverage"] for m in METHODS]),
             cumulative_coverage=np.stack([runs[m]["cumulative"] for m in METHODS]),
             checkpoint_updates=runs["gp_pg"]["updates"],
             visited_states=np.stack([runs[m]["visited"] for m in METHODS]),
             **{k: np.stack([runs[m]["records"][k] for m in METHODS])
                for k in train_lib.RECORD_FIELDS})


def print_report(summary, surfaces, plot_seed) -> None:
    """The coverage table and a line per GP method's surfaces, to stdout."""
    n_cells = GRID["num_angle_bins"] * GRID["num_velocity_bins"]
    print("| method | coverage (mean) | 95% CI | cells visited (mean) |")
    print("|---|---|---|---|")
    for r in summary:
        print(f"| {r['method']} | {100 * r['coverage_mean']:.2f}% | [{100 * r['ci95_low']:.2f}%, "
              f"{100 * r['ci95_high']:.2f}%] | {r['cells_mean']:.1f} of {n_cells} |")
    for m in GP_METHODS:
        z = surfaces["surf"]["around the visited states", m]
        f = surfaces["surf"]["whole state space", m]
        print(f"{m} (seed {plot_seed}): {len(bv_states(surfaces['final_gp'][m].gp))} basis vectors; "
              f"median sigma^2/sigma_f^2 {np.median(z['rel']):.3g} around the visited states, "
              f"{np.median(f['rel']):.3g} over the whole state space; V around the visited states "
              f"in [{z['value'].min():.1f}, {z['value'].max():.1f}]")
    (p0, p1), (o0, o1) = surfaces["zoom"]
    print(f"zoomed window: phi [{p0:.2f}, {p1:.2f}], omega [{o0:.2f}, {o1:.2f}]")


def main(argv=None):
    args, seeds, plot_seed = parse_args(argv)
    ip = seeds.index(plot_seed)
    os.makedirs(args.out, exist_ok=True)
    overrides = {} if args.num_updates is None else {"num_updates": args.num_updates}
    cfgs = {m: config_lib.preset(args.preset, method=m, **overrides) for m in METHODS}
    t_all = time.perf_counter()
    runs = run_methods(cfgs, seeds, args)
    summary = coverage_summary(runs, seeds)
    write_coverage(args, seeds, runs, summary)
    plot_coverage(os.path.join(args.out, "coverage.png"), runs, seeds, summary)
    surfaces = gp_surfaces(cfgs, runs, ip, args.grid)
    visited_vals = write_visited_states(os.path.join(args.out, "visited_states.csv"), cfgs, runs, ip,
                                        surfaces)
    subtitle = f"{args.preset} preset, seed {plot_seed}, after {cfgs['gp_pg'].num_updates} updates"
    plot_fig2_fig4(args.out, subtitle, surfaces, visited_vals)
    save_results(os.path.join(args.out, "results.npz"), seeds, runs)
    print_report(summary, surfaces, plot_seed)
    print(f"wrote {args.out}/fig2_variance.png, fig4_value.png, coverage.png and CSV/JSON "
          f"({time.perf_counter() - t_all:.0f}s)")


if __name__ == "__main__":
    main()
