"""The paper's four methods against brax PPO on the same pendulum, by environment steps.

For one preset (same physics, reward, start-state distribution and episode length for every
method), this script
  1. runs the four methods with `gpguided_jax.reproduce.reproduce` (or loads a finished run with
     `--from DIR`), timing each method;
  2. trains brax PPO (`gpguided_jax.baselines.train_ppo`, hyperparameters in
     `baselines.PPO_DEFAULTS`) per seed with the methods' environment-step budget
     (num_updates x episodes_per_update x episode_length) and with `--ppo-multipliers` times it;
  3. plots reward per step against environment steps (mean and 95% t-band over seeds; the methods'
     per-update points as a trailing mean over `--smooth` updates, 20 by default): panel (a) up
     to the methods' budget, panel (b) on a log axis up to the largest PPO budget;
  4. writes a table (Markdown + CSV) of reward per step at matched budgets and the wall time;
  5. if the episodes last at least twice `--hold-time`, evaluates swing-up success
     (`baselines.swingup_success`: |phi - pi| < 0.3 rad at every step of the last second) on
     `--eval-episodes` fresh episodes per seed: GP methods and REINFORCE with their own exploring
     policy (`train.episodes` of the final TrainState, "stochastic") and with the controller mean
     c(s) ("deterministic"); PPO with its policy's sampled actions ("stochastic") and with its
     mean action ("deterministic").

Environment steps of a GP method include the `hyperfit_samples` steps (whole episodes) collected
with the initial policy for the hyperparameter fit; REINFORCE has none. A method's point at update
k sits at the steps consumed by the end of update k's episodes, and its value is the average
reward per step of those (exploring) episodes, as in Fig. 5. A PPO point is brax's evaluation of
the policy after that many steps, on 64 fresh episodes with sampled actions.

Reward per step "at budget B" is the mean of a curve's points in (0.9 B, B] (for sparse PPO
evaluations: the last point in that window); "-" where the run did not reach B.

Wall times include compilation. The methods' time is that of one program running all seeds
(vmapped) on the machine; PPO's is the sum of its per-seed runs (one compiled program per run).

Outputs under --out: compare_<preset>.png, compare_<preset>.md, compare_<preset>.csv,
ppo_<preset>.npz (curves), success_<preset>.csv (if evaluated), gp/ (the reproduce run, unless
--from).

Usage:
  python experiments/compare_ppo.py --preset paper --seeds 0 1 2 3 4 --out results/compare_ppo
  python experiments/compare_ppo.py --preset swingup --seeds 0 1 2 --num-updates 50 \\
      --ppo-multipliers 1 10 --out results/compare_ppo
  python experiments/compare_ppo.py --preset paper --from results/paper --seeds 0 1 2 ...
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import gpguided_jax  # noqa: E402
from gpguided_jax import baselines  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402
from gpguided_jax import reproduce as reproduce_lib  # noqa: E402
from gpguided_jax import train as train_lib  # noqa: E402

gpguided_jax.enable_x64()  # float64: the package leaves this choice to its user

PPO_STEPS_PER_ITERATION = baselines.ppo_steps_per_iteration(
    baselines.PPO_DEFAULTS["num_envs"],
    baselines.PPO_DEFAULTS["unroll_length"],
    baselines.PPO_DEFAULTS["batch_size"],
    baselines.PPO_DEFAULTS["num_minibatches"],
)
MAX_EVALS = 31


def log(msg: str) -> None:
    print(f"[{time.strftime('%X')}] {msg}", file=sys.stderr, flush=True)


def method_env_steps(cfg: config_lib.TrainConfig, num_updates: int) -> np.ndarray:
    """(num_updates,) environment steps consumed by the end of each update, hyperfit included."""
    per_update = cfg.episodes_per_update * cfg.episode_length
    offset = cfg.hyperfit_episodes * cfg.episode_length if cfg.uses_gp else 0
    return offset + per_update * np.arange(1, num_updates + 1)


def num_evals_for(budget: int) -> int:
    """Evaluations (initial one included) so that every evaluation interval is a whole number of
    PPO iterations that divides the budget's iterations: at most MAX_EVALS."""
    iters = max(1, -(-budget // PPO_STEPS_PER_ITERATION))
    best = 1
    for d in range(1, min(iters, MAX_EVALS - 1) + 1):
        if iters % d == 0:
            best = d
    return best + 1


# --------------------------------------------------------------------------- GP methods


def run_methods(preset, seeds, overrides, out_dir, methods=config_lib.METHODS):
    """reproduce() of `methods` into out_dir; returns (results dict, per-method wall times,
    hyperfit time)."""
    stamps = []

    def progress(msg):
        stamps.append((time.perf_counter(), msg))
        log(msg)

    t0 = time.perf_counter()
    # one program per method, so that each method's wall time includes its own compilation
    res = reproduce_lib.reproduce(
        preset, seeds, list(methods), out_dir, overrides=overrides, progress=progress,
        gp_program="per_method",
    )
    if not res["complete"]:
        raise RuntimeError("reproduce did not finish")
    # Attribute each span between progress messages to the method that reported at its end.
    walls = {m: 0.0 for m in methods}
    hyperfit = 0.0
    prev = t0
    for t, msg in stamps:
        if msg.startswith("hyperparameter fit"):
            hyperfit += t - prev
        else:
            m = msg[1 : msg.index("]")]
            walls[m] += t - prev
        prev = t
    timings = {"wall_s": walls, "hyperfit_wall_s": hyperfit, "seeds": list(seeds)}
    with open(os.path.join(out_dir, "timings.json"), "w") as f:
        json.dump(timings, f, indent=2)
    return timings


def load_methods(run_dir):
    with np.load(os.path.join(run_dir, "results.npz")) as f:
        results = {k: f[k] for k in f.files}
    tpath = os.path.join(run_dir, "timings.json")
    timings = None
    if os.path.exists(tpath):
        with open(tpath) as f:
            timings = json.load(f)
    return results, timings


def load_final_states(run_dir, cfg, num_seeds):
    """The TrainStates after the last chunk, from reproduce's checkpoint_<method>.npz (leading
    seed axis cut to num_seeds)."""
    train = train_lib.make_train(cfg)
    path = os.path.join(run_dir, f"checkpoint_{cfg.method}.npz")
    with np.load(path) as f:
        n_leaves = sum(k.startswith("leaf_") for k in f.files)
        n_padded = f["leaf_0"].shape[0] if n_leaves else 0
        keys = reproduce_lib.seed_keys(list(range(n_padded)))
        template = jax.eval_shape(jax.vmap(lambda k: train.init(k, cfg)), keys)
        treedef = jax.tree_util.tree_structure(template)
        if treedef.num_leaves != n_leaves:
            raise ValueError(f"{path}: {n_leaves} leaves, expected {treedef.num_leaves}")
        leaves = [f[f"leaf_{i}"] for i in range(n_leaves)]
    for got, want in zip(leaves, jax.tree_util.tree_leaves(template)):
        if got.shape != want.shape:
            raise ValueError(f"{path}: leaf shape {got.shape} != {want.shape}")
    state = jax.tree_util.tree_unflatten(treedef, leaves)
    return train, jax.tree_util.tree_map(lambda x: x[:num_seeds], state)


def method_success(run_dir, cfg, num_seeds, key, num_episodes, hold_time):
    """(stochastic, deterministic) success rates per seed: (seeds,), (seeds,)."""
    train, states = load_final_states(run_dir, cfg, num_seeds)
    dt = float(np.asarray(cfg.pendulum.dt))
    ok = jax.vmap(lambda s: baselines.swingup_success(s, dt, hold_time=hold_time))

    @jax.jit
    def per_seed(key, state):
        key_sto, key_det = jax.random.split(key)
        eps = train.episodes(key_sto, state, cfg, num_episodes)
        sto = jnp.mean(ok(eps.states))
        mean_fn = lambda _, s: train.controller.apply(state.theta.controller, s)  # noqa: E731
        det = jnp.mean(
            baselines.success_flags(
                key_det, cfg.pendulum, mean_fn, cfg.episode_length, num_episodes, hold_time=hold_time
            )
        )
        return sto, det

    keys = jax.random.split(key, num_seeds)
    sto, det = jax.lax.map(lambda a: per_seed(*a), (keys, states))
    return np.asarray(sto), np.asarray(det)


# --------------------------------------------------------------------------- PPO


def run_ppo(cfg, seeds, budgets, *, success_episodes=0, hold_time=1.0):
    """Per budget: env_steps (E,), curves (seeds, E), wall (seeds,), success (seeds, 2) or None."""
    out = {}
    for budget in budgets:
        curves, walls, succ = [], [], []
        steps = None
        for s in seeds:
            r = baselines.train_ppo(
                cfg.pendulum, budget, cfg.episode_length, s, num_evals=num_evals_for(budget)
            )
            log(
                f"[ppo x{budget}] seed {s}: {r.env_steps[-1]} steps, {r.wall_time:.1f}s, "
                f"reward/step {r.reward_per_step[0]:.3f} -> {r.reward_per_step[-1]:.3f}"
            )
            steps = r.env_steps if steps is None else steps
            curves.append(r.reward_per_step)
            walls.append(r.wall_time)
            if success_episodes:
                key = jax.random.PRNGKey(10_000 + s)
                succ.append(
                    [
                        baselines.ppo_success_rate(
                            key,
                            r,
                            cfg.pendulum,
                            cfg.episode_length,
                            success_episodes,
                            deterministic=det,
                            hold_time=hold_time,
                        )
                        for det in (False, True)
                    ]
                )
        out[budget] = dict(
            env_steps=steps,
            curves=np.stack(curves),
            wall=np.asarray(walls),
            success=np.asarray(succ) if succ else None,
        )
    return out


# --------------------------------------------------------------------------- outputs


def smooth(x, y, window):
    """Trailing moving average over `window` points of each row of y; x at the window's end."""
    window = max(1, min(int(window), y.shape[-1]))
    kernel = np.ones(window) / window
    ys = np.stack([np.convolve(row, kernel, mode="valid") for row in y])
    return x[window - 1 :], ys


def plot(curves, budget, preset, num_seeds, path, smooth_updates=1):
    """curves: list of (label, env_steps (E,), values (seeds, E), is_ppo). The methods' curves
    (one point per update, 3 episodes each) are smoothed over `smooth_updates` updates per seed."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.6))
    for ax, log_x in zip(axes, (False, True)):
        for i, (label, x, y, is_ppo) in enumerate(curves):
            if not is_ppo:
                x, y = smooth(x, y, smooth_updates)
            if not log_x and x[0] > budget * 1.2:
                continue
            mean, half = baselines.ci95(y, axis=0)
            keep = slice(None) if log_x else x <= budget * 1.05 + 3000
            style = dict(ls="--", marker="o", ms=3) if is_ppo else {}
            (line,) = ax.plot(x[keep], mean[keep], label=label, color=f"C{i}", **style)
            ax.fill_between(
                x[keep], (mean - half)[keep], (mean + half)[keep], color=line.get_color(), alpha=0.2
            )
        ax.set_xlabel("environment steps" + (" (log scale)" if log_x else ""))
        ax.set_ylabel("average reward per step of an episode")
        ax.grid(alpha=0.3)
        if log_x:
            ax.set_xscale("symlog", linthresh=budget / 10)
    axes[0].axvline(budget, color="k", lw=0.8, ls=":")
    axes[0].set_title(f"(a) {preset}: the methods' budget ({budget:,} steps)")
    axes[1].set_title(f"(b) {preset}: with PPO at larger budgets")
    axes[1].legend(fontsize=8, loc="lower right")
    note = f"; methods smoothed over {smooth_updates} updates" if smooth_updates > 1 else ""
    fig.suptitle(
        f"{preset} preset: mean and 95% CI over {num_seeds} seeds{note}; PPO: "
        "evaluation on 64 episodes (sampled actions)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def fmt(mean, half):
    if not np.isfinite(mean):
        return "–"
    return f"{mean:.3f} ± {half:.3f}" if np.isfinite(half) and half > 0 else f"{mean:.3f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="paper", choices=sorted(config_lib.PRESETS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--num-updates", type=int, default=None, help="override the preset's")
    ap.add_argument(
        "--from", dest="from_dir", default=None, help="load the methods from a finished reproduce output dir"
    )
    ap.add_argument("--methods", nargs="+", default=list(config_lib.METHODS),
                    choices=list(config_lib.METHODS), help="the paper's methods to run (default: all)")
    ap.add_argument("--ppo-multipliers", type=float, nargs="+", default=[1, 10])
    ap.add_argument("--eval-episodes", type=int, default=20, help="per seed, for success")
    ap.add_argument("--hold-time", type=float, default=1.0, help="s upright at the end (success)")
    ap.add_argument(
        "--smooth",
        type=int,
        default=20,
        help="plot the methods' curves as a trailing mean over this many updates",
    )
    ap.add_argument(
        "--reuse-ppo", action="store_true", help="load PPO from --out/ppo_<preset>.npz instead of training it"
    )
    ap.add_argument("--out", default="results/compare_ppo")
    args = ap.parse_args(argv)

    preset = args.preset
    overrides = {} if args.num_updates is None else {"num_updates": args.num_updates}
    cfgs = {m: config_lib.preset(preset, method=m, **overrides) for m in config_lib.METHODS}
    cfg0 = cfgs["reinforce"]
    os.makedirs(args.out, exist_ok=True)

    # ---- the paper's methods
    if args.from_dir:
        run_dir = args.from_dir
        results, timings = load_methods(run_dir)
    else:
        run_dir = os.path.join(args.out, f"gp_{preset}")
        run_methods(preset, args.seeds, overrides, run_dir, args.methods)
        results, timings = load_methods(run_dir)
    methods = [str(m) for m in results["methods"]]
    seeds = [int(s) for s in results["seeds"]]
    if args.from_dir and seeds != list(args.seeds):
        log(f"using the seeds of {run_dir}: {seeds}")
    num_updates = results["mean_reward"].shape[-1]
    if num_updates != cfg0.num_updates:
        raise ValueError(f"{run_dir} has {num_updates} updates; pass --num-updates {num_updates}")
    budget = cfg0.num_updates * cfg0.episodes_per_update * cfg0.episode_length
    episode_seconds = cfg0.episode_length * float(np.asarray(cfg0.pendulum.dt))
    do_success = episode_seconds >= 2 * args.hold_time and args.eval_episodes > 0

    # ---- PPO
    budgets = sorted({int(round(m * budget)) for m in args.ppo_multipliers})
    ppo_path = os.path.join(args.out, f"ppo_{preset}.npz")
    if args.reuse_ppo:
        with np.load(ppo_path) as f:
            ppo = {
                int(b): {
                    k: (f[f"{k}_{b}"] if f"{k}_{b}" in f.files else None)
                    for k in ("env_steps", "curves", "wall", "success")
                }
                for b in f["budgets"]
            }
        if sorted(ppo) != budgets:
            raise ValueError(f"{ppo_path} has budgets {sorted(ppo)}, expected {budgets}")
    else:
        ppo = run_ppo(
            cfg0,
            seeds,
            budgets,
            success_episodes=args.eval_episodes if do_success else 0,
            hold_time=args.hold_time,
        )
    np.savez(
        ppo_path,
        budgets=np.asarray(budgets),
        **{f"{k}_{b}": v for b, d in ppo.items() for k, v in d.items() if v is not None},
    )

    # ---- curves, table
    curves = [
        (m, method_env_steps(cfgs[m], num_updates), results["mean_reward"][i], False)
        for i, m in enumerate(methods)
    ]
    for b in budgets:
        curves.append((f"PPO ({b:,} steps)", ppo[b]["env_steps"], ppo[b]["curves"], True))
    fig_path = os.path.join(args.out, f"compare_{preset}.png")
    plot(curves, budget, preset, len(seeds), fig_path, args.smooth)

    columns = sorted({budget // 4, budget // 2, budget, *budgets})
    walls = (timings or {}).get("wall_s", {})
    rows = []
    for label, x, y, is_ppo in curves:
        row = {"method": label}
        for c in columns:
            mean, half = baselines.ci95(baselines.matched_budget_value(x, y, c), axis=0)
            row[f"reward@{c}"], row[f"ci95@{c}"] = float(mean), float(half)
        row["env_steps_done"] = int(x[-1])
        if is_ppo:
            b = int(label.split("(")[1].split(" ")[0].replace(",", ""))
            row["wall_s"] = float(ppo[b]["wall"].sum())
        else:
            row["wall_s"] = float(walls.get(label, np.nan))
        rows.append(row)
    stem = os.path.join(args.out, f"compare_{preset}")
    with open(stem + ".csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)

    md = [
        f"Preset `{preset}`: {num_updates} updates × {cfg0.episodes_per_update} episodes × "
        f"{cfg0.episode_length} steps = {budget:,} environment steps per method; seeds {seeds}. "
        "Average reward per step at matched environment-step budgets (mean ± 95% CI half-width "
        "over seeds; mean of the curve's points in (0.9 B, B]).",
        "",
        "| method | " + " | ".join(f"{c:,} steps" for c in columns) + " | steps done | wall [s] |",
        "|---" * (len(columns) + 3) + "|",
    ]
    for r in rows:
        cells = [fmt(r[f"reward@{c}"], r[f"ci95@{c}"]) for c in columns]
        wall = f"{r['wall_s']:.0f}" if np.isfinite(r["wall_s"]) else "n/a"
        md.append(f"| {r['method']} | " + " | ".join(cells) + f" | {r['env_steps_done']:,} | {wall} |")
    if timings:
        md += [
            "",
            f"The methods' steps include {cfg0.hyperfit_episodes * cfg0.episode_length:,} "
            "hyperfit steps (REINFORCE: none). Wall time: one vmapped program over all seeds "
            f"per method, compilation included; the shared hyperparameter fit took "
            f"{timings['hyperfit_wall_s']:.0f} s more. PPO: sum of the per-seed runs.",
        ]

    # ---- success
    if do_success:
        key = jax.random.PRNGKey(20_000)
        srows = []
        for m in methods:
            sto, det = method_success(run_dir, cfgs[m], len(seeds), key, args.eval_episodes, args.hold_time)
            srows.append((m, sto, det))
            log(f"[success] {m}: stochastic {sto.mean():.2f}, deterministic {det.mean():.2f}")
        for b in budgets:
            s = ppo[b]["success"]
            srows.append((f"PPO ({b:,} steps)", s[:, 0], s[:, 1]))
        with open(os.path.join(args.out, f"success_{preset}.csv"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["method", "policy", *[f"seed_{s}" for s in seeds], "mean"])
            for m, sto, det in srows:
                w.writerow([m, "stochastic", *sto, sto.mean()])
                w.writerow([m, "deterministic", *det, det.mean()])
        md += [
            "",
            f"Swing-up success: |φ − π| < 0.3 rad at every step of the last "
            f"{args.hold_time:g} s of a {episode_seconds:g} s episode, on {args.eval_episodes} "
            "fresh episodes per seed from the start distribution (mean over seeds; "
            "in brackets the lowest and highest seed).",
            "",
            "| method | stochastic policy | deterministic (mean action) |",
            "|---|---|---|",
        ]
        for m, sto, det in srows:
            md.append(
                f"| {m} | {sto.mean():.2f} [{sto.min():.2f}, {sto.max():.2f}] | "
                f"{det.mean():.2f} [{det.min():.2f}, {det.max():.2f}] |"
            )
    with open(stem + ".md", "w") as f:
        f.write("\n".join(md) + "\n")
    print("\n".join(md))
    log(f"wrote {fig_path}, {stem}.md, {stem}.csv")
    return {"figure": fig_path, "markdown": stem + ".md", "csv": stem + ".csv", "rows": rows}


if __name__ == "__main__":
    main()
