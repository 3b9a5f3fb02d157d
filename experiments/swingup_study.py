"""The swing-up question: does GP-guided exploration make policy search learn faster? The four
methods against brax PPO and SAC on the swing-up preset, tuned with equal budgets on tuning seeds,
then compared on held-out seeds, by the protocol of `gpguided_jax.study`.

Stages (each writes under --out, default docs/results/swingup):

``tune``  Tuning seeds (100, 101 by default; never reported). Every method and baseline gets the
          same budget: `CONFIGS_PER_METHOD` (8) configurations x the tuning seeds, each a full run
          (the preset's env-step budget). The search is coordinate-wise (`study.coordinate_search`):
          a first stage of four values of the learning rate, then stages of two values of the next
          parameter, each stage keeping the best configuration so far (`GRIDS`, `BASELINE_GRIDS`),
          from the preset's own settings (`study.preset_own`). Our methods' stages are one
          `sweep.run_sweep` each (all values x seeds as one vmapped program). A configuration's
          score is the final success rate of the deterministic controller (mean over the last 10%
          of updates or the last evaluation, mean over seeds), ties broken by the final reward per
          step. Writes tuning.json (every configuration tried, its score, the choice) and
          docs/tuning_swingup.md.
``heldout`` Held-out seeds (1000-1009): each of the four methods alone through `gpguided_jax.reproduce`
          with this study's tuned settings over the preset's own (`white_noise_overrides`; the
          preset's tuned ones, `config.METHOD_PRESETS`, are the exploration study's), into
          methods/<method>/; PPO and SAC per seed with their tuned settings from tuning.json and
          the same environment-step budget. Writes heldout.npz (curves), heldout.json (wall times:
          a method's fit and run, compilation included, as `reproduce` measures them).
``gpfig``  What the GP sees on the swing-up task, early and late (Fig. 2/4 style), and whether
          each GP method's roll-outs reach the upright region sooner (`gp_figure`), seeds
          1000-1002.
``report`` The plot (success rate and reward per step of the deterministic policy against
          environment steps, mean and 95% t-band over seeds) and the steps-to-success table
          (heldout.md, heldout_table.json), from heldout.npz/json.

Curves. Our methods: before every update's step, `eval_episodes` (4) fresh episodes of the
deterministic controller c(s) (records eval_success_rate, eval_reward), at the environment steps
spent when they ran (`study.env_steps`: the GP methods' include the episodes collected for the
hyperparameter fit); success is smoothed by a trailing mean over 5 updates (20 episodes). PPO and
SAC: brax's evaluator with the deterministic policy (mean action) on 64 fresh episodes,
`NUM_EVALS` times per run. Steps to X% success: the first curve point at or above X (per seed); a
seed that never gets there counts as not reached, and the table gives the median over seeds with
its bootstrap interval (infinite where more than half the seeds never reach it) and the number of
seeds that reached it.

Usage:
  python experiments/swingup_study.py tune
  python experiments/swingup_study.py heldout
  python experiments/swingup_study.py report
  python experiments/swingup_study.py gpfig
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import gpguided_jax  # noqa: E402
from gpguided_jax import baselines, checkpoints, methods, sharding, study  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402

CONFIGS_PER_METHOD = 8
TUNING_SEEDS = study.TUNING_SEEDS
HELDOUT_SEEDS = study.HELDOUT_SEEDS
NUM_EVALS = 21
SMOOTH = 5
LN = math.log
# The paper's methods (`methods.paper()`), each with its (parameter, values) stages of the
# coordinate search: 4 + 2 + 2 = 8 configurations per method (guided_direction: 2 + 2 + 2 + 2, as
# it has one more parameter, beta); brax's PPO and SAC (`baselines.NAMES`) with theirs.
METHODS = methods.paper()
GRIDS = {
    "reinforce": [("learning_rate", [0.03, 0.1, 0.3, 1.0]), ("init_log_std", [LN(0.5), LN(3.0)]),
                  ("learning_rate", [0.01, 3.0])],
    "gp_pg": [("learning_rate", [0.03, 0.1, 0.3, 1.0]), ("init_log_std", [LN(0.5), LN(3.0)]),
              ("age_penalty", [10.0, 1000.0])],
    "guided_variance": [("learning_rate", [0.03, 0.1, 0.3, 1.0]),
                        ("guided_variance_scale", [1.0, 9.0]), ("age_penalty", [10.0, 1000.0])],
    "guided_direction": [("learning_rate", [0.1, 0.3]), ("candidate_scale", [1.0, 9.0]),
                         ("age_penalty", [10.0, 1000.0]), ("inverse_temperature", [1.0, 100.0])],
}
BASELINE_GRIDS = {
    "ppo": [("learning_rate", [1e-4, 3e-4, 1e-3, 3e-3]), ("entropy_cost", [1e-4, 1e-2]),
            ("unroll_length", [10, 50])],
    "sac": [("learning_rate", [1e-4, 3e-4, 1e-3, 3e-3]), ("reward_scaling", [0.3, 3.0]),
            ("batch_size", [64, 512])],
}
study.check_budget({**GRIDS, **BASELINE_GRIDS}, CONFIGS_PER_METHOD)


def base_config(method: str, **overrides) -> config_lib.TrainConfig:
    """The swing-up preset's config of `method` (its budget, physics and records)."""
    return config_lib.preset("swingup", method=method, **overrides)


def white_noise_overrides(tuning: dict, method: str) -> dict:
    """The config overrides of `method`'s settings chosen by this study's tuning (`tuning`:
    tuning.json) over the preset's own, in place of the preset's tuned ones
    (`config.METHOD_PRESETS['swingup']`, the exploration study's): the held-out runs, the GP
    figure and experiments/swingup_diagnostics.py use these."""
    return study.merge_overrides(study.preset_own("swingup", method),
                                 tuning["methods"][method]["chosen"])


def study_config(tuning: dict, method: str, **overrides) -> config_lib.TrainConfig:
    """`method`'s config with this study's tuned settings (`white_noise_overrides`)."""
    return base_config(method, **study.merge_overrides(white_noise_overrides(tuning, method),
                                                       overrides))


# ------------------------------------------------------------------------------------------ tune


def tune_method(method: str, seeds, dtype: str) -> dict:
    own = study.preset_own("swingup", method)

    def evaluate(configs):
        return study.sweep_stage([{**study.merge_overrides(own, s), "dtype": dtype}
                                  for s in configs], study.final_success,
                                 method=method, preset="swingup", seeds=seeds)

    return study.coordinate_search(study.stages(GRIDS[method]), evaluate, key=study.by_success,
                                   log=lambda m: study.log(f"[tune {method}] {m}"))


def tune_baseline(name: str, seeds) -> dict:
    def evaluate(configs):
        # the final success and reward per step: the last evaluation, of 64 episodes
        return study.baseline_stage(configs, lambda run: study.last_success(run.records),
                                    name=name, cfg=base_config("reinforce", dtype="float32"),
                                    seeds=seeds, num_evals=NUM_EVALS)

    return study.coordinate_search(study.stages(BASELINE_GRIDS[name]), evaluate,
                                   key=study.by_success,
                                   log=lambda m: study.log(f"[tune {name}] {m}"))


def tuning_markdown(report: dict) -> str:
    lines = [
        "# Tuning record: swing-up preset",
        "",
        "Generated by `python experiments/swingup_study.py tune` "
        f"(tuning seeds {report['seeds']}, never reported; {report['dtype']}). Every method and "
        f"baseline had the same budget: {CONFIGS_PER_METHOD} configurations x "
        f"{len(report['seeds'])} seeds, each a full run of {report['env_steps']:,} environment "
        "steps. Coordinate search from the preset's own settings: each stage tries the listed "
        "values of one parameter with the best settings so far and keeps the best configuration "
        "seen; the score is the final "
        "success rate of the deterministic policy, ties broken by its final reward per step "
        "(swing-up: about -2.9 for the energy-pumping controller, -6.6 for constant full torque, "
        "-9.2 for zero torque).",
        "",
    ]
    for name, r in report["methods"].items():
        lines += [f"## {name}", "", "| settings | success | reward per step |", "|---|---|---|"]
        for t in r["tried"]:
            s = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                          for k, v in t["settings"].items())
            lines.append(f"| {s} | {t['success']:.2f} | {t['reward']:.3f} |")
        c = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                      for k, v in r["chosen"].items())
        lines += ["", f"Chosen: {c}.", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------- heldout


def heldout(out: str, seeds, tuning: dict, dtype: str, only=None) -> None:
    """Each method alone and each baseline per seed on the held-out seeds, into heldout.npz and
    heldout.json. With `only`, those of them alone; the others' curves stay as the files hold
    them (for the same seeds)."""
    curves, meta = {}, {"seeds": list(seeds), "wall_s": {}}
    npz, js = os.path.join(out, "heldout.npz"), os.path.join(out, "heldout.json")
    if only is not None and os.path.exists(npz):
        kept = study.read_json(js)
        if kept["seeds"] != list(seeds):
            raise ValueError(f"{js} holds seeds {kept['seeds']}, not {list(seeds)}")
        with np.load(npz) as f:
            curves = {k: f[k] for k in f.files if k.rsplit("_", 1)[0] not in only}
        meta["wall_s"] = {k: v for k, v in kept["wall_s"].items() if k not in only}
    names = (*METHODS, *baselines.NAMES)
    for name in (n for n in names if only is None or n in only):
        if name in METHODS:  # each alone: its wall time holds its own fit and compilation
            run = study.run_method("swingup", name, seeds, os.path.join(out, "methods", name),
                                   white_noise_overrides(tuning, name), dtype=dtype, chunk_size=20)
        else:
            run = study.run_baseline(name, base_config("reinforce", dtype=dtype), seeds,
                                     tuning["methods"][name]["chosen"], num_evals=NUM_EVALS)
        curves[f"{name}_steps"] = run.env_steps
        curves[f"{name}_success"] = run.records["eval_success_rate"]
        curves[f"{name}_reward"] = run.records["eval_reward"]
        meta["wall_s"][name] = run.wall_s
    order = [f"{n}_{k}" for n in names for k in ("steps", "success", "reward")]
    checkpoints.atomic_savez(npz, **{k: curves[k] for k in order if k in curves})
    study.write_json(js, {"seeds": meta["seeds"], "wall_s": {
        n: meta["wall_s"][n] for n in names if n in meta["wall_s"]}})


# ---------------------------------------------------------------------------------------- report


def smoothed(success: np.ndarray, name: str) -> np.ndarray:
    """Our methods' per-update success (4 episodes) as a trailing mean over SMOOTH updates; the
    baselines' evaluations (64 episodes each) as they are."""
    return success if name in baselines.NAMES else study.smoothed(success, SMOOTH)


def report(out: str) -> str:
    with np.load(os.path.join(out, "heldout.npz")) as f:
        curves = {k: f[k] for k in f.files}
    meta = study.read_json(os.path.join(out, "heldout.json"))
    names = [*METHODS, *baselines.NAMES]
    rows = []
    for n in names:
        steps, succ = curves[f"{n}_steps"], smoothed(curves[f"{n}_success"], n)
        row = dict(method=n, seeds=int(succ.shape[0]))
        for level in (0.5, 0.9):
            per_seed = study.steps_to(steps, succ, level, tol=1e-9)
            med, lo, hi = study.median_ci(per_seed)
            key = f"steps_to_{int(level * 100)}"
            row[key] = per_seed.tolist()
            row[key + "_median"], row[key + "_low"], row[key + "_high"] = med, lo, hi
            row[key + "_reached"] = int(np.isfinite(per_seed).sum())
        row["final_success"] = float(succ[:, -1].mean())
        row["final_reward"] = float(curves[f"{n}_reward"][:, -1].mean())
        row["wall_s"] = meta["wall_s"][n]
        rows.append(row)
    study.write_json(os.path.join(out, "heldout_table.json"), rows)

    def fmt(r, key):
        k, n = r[key + "_reached"], r["seeds"]
        if k == 0:
            return f"0/{n}"
        f = lambda v: "∞" if not np.isfinite(v) else f"{v / 1000:.0f}k"  # noqa: E731
        got = [v for v in r[key] if np.isfinite(v)]
        m, lo, hi = (r[key + s] for s in ("_median", "_low", "_high"))
        return (f"{k}/{n}; median {f(m)} [{f(lo)}, {f(hi)}]; reached at "
                f"{f(min(got))}–{f(max(got))}" if k > 1 else f"{k}/{n}; at {f(got[0])}")

    md = ["| method | 50% success: seeds; steps (median over all seeds [95% CI]; range where "
          "reached) | 90% success: the same | final success | final reward/step | wall time [s] |",
          "|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['method']} | {fmt(r, 'steps_to_50')} | {fmt(r, 'steps_to_90')} | "
                  f"{r['final_success']:.2f} | {r['final_reward']:.3f} | {r['wall_s']:.0f} |")
    text = "\n".join(md)
    checkpoints.atomic_write_text(os.path.join(out, "heldout.md"), text + "\n")

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.2))
    for i, n in enumerate(names):
        steps = curves[f"{n}_steps"]
        for ax, y in ((a, smoothed(curves[f"{n}_success"], n)), (b, curves[f"{n}_reward"])):
            study.plot_band(ax, steps, y, alpha=0.15, color=f"C{i}", label=n, lw=1.5)
    a.set(xlabel="environment steps", ylabel="swing-up success (deterministic policy)",
          ylim=(-0.03, 1.03))
    b.set(xlabel="environment steps", ylabel="reward per step (deterministic policy)")
    b.axhline(-2.86, color="k", ls=":", lw=1, label="energy pumping")
    b.axhline(-6.57, color="gray", ls="--", lw=1, label="constant +5 N m")
    for ax in (a, b):
        ax.grid(alpha=0.3)
    b.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"Swing-up preset, held-out seeds {meta['seeds'][0]}-{meta['seeds'][-1]}: "
                 "mean and 95% t-band")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "swingup_comparison.png"), dpi=120)
    plt.close(fig)
    return text


# ----------------------------------------------------------------------------------------- gpfig

GP_METHODS = tuple(m for m in METHODS if m in methods.gp_methods())  # the GP's paper methods
UPRIGHT_BAND = 0.5  # rad: "in the upright region"


def gp_figure(out: str, seeds, dtype: str, tuning: dict, chunk: int = 10, episodes: int = 5) -> dict:
    """What the GP sees, early and late (Fig. 2/4 on the swing-up task), and how soon each method's
    roll-outs reach the upright region.

    Each GP method is trained with its tuned settings (`tuning`: tuning.json) on `seeds` (held-out
    seeds; nothing is chosen here) in chunks of `chunk` updates; after every chunk `episodes`
    roll-outs of the method's own policy (GP and theta held fixed, keys apart from training) give the share of
    steps within UPRIGHT_BAND of upright and the highest point reached (max of -cos phi, 1 =
    upright). For the first seed, the GP's relative variance sigma^2/sigma_f^2 and its value
    V(s) = Q_GP(s, c(s)) on a (phi, omega) grid, with the visited states, after the first chunk
    ("early") and the last ("late").
    """
    phi = np.linspace(-math.pi / 2, 3 * math.pi / 2, 73)
    omega = np.linspace(-8.0, 8.0, 65)
    curves, snaps = _gp_runs(seeds, dtype, tuning, chunk, episodes, phi, omega)
    _plot_gp_early_late(os.path.join(out, "swingup_gp_early_late.png"), snaps, phi, omega,
                        seeds, episodes)
    _plot_upright_region(os.path.join(out, "swingup_upright_region.png"), curves, seeds, episodes)
    summary = {m: {"updates": curves[m]["updates"].tolist(),
                   "upright_share_mean": curves[m]["upright_share"].mean(0).tolist(),
                   "height_mean": curves[m]["height"].mean(0).tolist()} for m in GP_METHODS}
    summary["seeds"] = list(seeds)
    study.write_json(os.path.join(out, "gp_figure.json"), summary)
    return summary


def _gp_runs(seeds, dtype, tuning, chunk, episodes, phi, omega):
    """`gp_figure`'s runs: per GP method the upright share and height after every chunk
    (curves), and the first seed's GP over the (phi, omega) grid after the first and the last
    chunk (snaps, keyed (method, 'early' or 'late'))."""
    from gpguided_jax import analysis
    from gpguided_jax import train as train_lib

    keys = sharding.seed_keys(seeds)
    gp_pg = study_config(tuning, "gp_pg", dtype=dtype)
    fit = jax.jit(jax.vmap(train_lib.make_train(gp_pg).fit_kernel_for_seed))
    priors = fit(keys)
    curves, snaps = {}, {}
    for m in GP_METHODS:
        cfg = study_config(tuning, m, dtype=dtype)
        train = train_lib.make_train(cfg)
        state = jax.jit(jax.vmap(lambda k, p, t=train, c=cfg: t.init(k, c, p)))(keys, priors)

        def step(st, key, c, t=train, cf=cfg):
            st, _ = t.run_chunk(st, cf, chunk)
            ep = t.episodes(jax.random.fold_in(key, 0x5EED + c), st, cf, episodes)
            return st, ep.states

        step = jax.jit(jax.vmap(step, in_axes=(0, 0, None)))
        share, height = [], []
        for c in range(cfg.num_updates // chunk):
            state, visited = step(state, keys, c)
            visited = np.asarray(visited)  # (S, E, H, 2)
            up = np.abs(np.mod(visited[..., 0], 2 * math.pi) - math.pi) < UPRIGHT_BAND
            share.append(up.mean(axis=(1, 2)))
            height.append((-np.cos(visited[..., 0])).max(axis=(1, 2)))
            if c in (0, cfg.num_updates // chunk - 1):
                st0 = jax.tree_util.tree_map(lambda x: x[0], state)
                controller = train_lib.make_controller(cfg)
                value, var = analysis.gp_surface(st0.gp, st0.kernel, controller,
                                                 st0.theta.controller, phi, omega)
                snaps[m, "early" if c == 0 else "late"] = dict(
                    rel=np.asarray(var) / float(st0.kernel.signal_variance),
                    value=np.asarray(value), visited=visited[0].reshape(-1, 2),
                    updates=(c + 1) * chunk)
        curves[m] = dict(updates=chunk * np.arange(1, cfg.num_updates // chunk + 1),
                         upright_share=np.stack(share, 1), height=np.stack(height, 1))
        study.log(f"[gpfig {m}] upright share by chunk (mean over seeds): "
            f"{np.round(curves[m]['upright_share'].mean(0), 3).tolist()}")
    return curves, snaps


def _plot_gp_early_late(path, snaps, phi, omega, seeds, episodes) -> None:
    """Per GP method (rows): the relative variance and the value, early and late (columns)."""
    fig, axes = plt.subplots(3, 4, figsize=(19, 12))
    pw = lambda v: np.mod(v + math.pi / 2, 2 * math.pi) - math.pi / 2  # noqa: E731 (axis range)
    vals = np.concatenate([snaps[k]["value"].ravel() for k in snaps])
    vlo, vhi = np.percentile(vals, [2, 98])
    for r, m in enumerate(GP_METHODS):
        for c, (when, key, norm, cmap, label) in enumerate((
                ("early", "rel", matplotlib.colors.LogNorm(1e-3, 1.0, clip=True), "viridis", "σ²/σ_f²"),
                ("late", "rel", matplotlib.colors.LogNorm(1e-3, 1.0, clip=True), "viridis", "σ²/σ_f²"),
                ("early", "value", matplotlib.colors.Normalize(vlo, vhi), "magma", "V(s)"),
                ("late", "value", matplotlib.colors.Normalize(vlo, vhi), "magma", "V(s)"))):
            ax, snap = axes[r][c], snaps[m, when]
            mesh = ax.pcolormesh(phi, omega, snap[key].T, shading="auto", norm=norm, cmap=cmap)
            v = snap["visited"]
            ax.scatter(pw(v[:, 0]), v[:, 1], s=1, c="w", alpha=0.5)
            ax.plot([math.pi], [0], "*", ms=12, c="gold", mec="k")
            ax.set(xlim=(phi[0], phi[-1]), ylim=(omega[0], omega[-1]), xlabel="φ [rad] (π = upright)",
                   ylabel="ω [rad/s]", title=f"{m}: {label}, after {snap['updates']} updates")
            fig.colorbar(mesh, ax=ax)
    fig.suptitle(f"Swing-up: what the GP sees, early and late (seed {seeds[0]}; white: states of "
                 f"{episodes} roll-outs of the method's own policy; star: upright)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_upright_region(path, curves, seeds, episodes) -> None:
    """Per GP method: the upright share and the highest point reached, after every chunk."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for i, m in enumerate(GP_METHODS):
        u = curves[m]["updates"]
        for ax, key in ((a, "upright_share"), (b, "height")):
            ax.plot(u, curves[m][key].mean(0), "o-", ms=3, lw=2, color=f"C{i + 1}",
                    label=f"{m} (mean)")
            ax.plot(u, curves[m][key].T, "-", lw=0.7, alpha=0.5, color=f"C{i + 1}")
    a.set(xlabel="updates", ylabel=f"share of steps within {UPRIGHT_BAND} rad of upright",
          ylim=(-0.02, 1.02))
    b.set(xlabel="updates", ylabel="highest point reached (-cos φ; 1 = upright)", ylim=(-1.05, 1.05))
    b.axhline(1.0, color="gold", lw=1.5, label="upright")
    b.axhline(0.0, color="gray", ls=":", lw=1, label="horizontal")
    for ax in (a, b):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Swing-up: does guided exploration reach the upright region sooner? "
                 f"({len(seeds)} seeds: thin lines; {episodes} roll-outs per seed and point)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage", choices=("tune", "heldout", "report", "gpfig"))
    ap.add_argument("--out", default="docs/results/swingup")
    ap.add_argument("--dtype", default="float32", choices=config_lib.DTYPES)
    ap.add_argument("--only", nargs="+", default=None,
                    help="tune or run held out only these methods/baselines")
    args = ap.parse_args(argv)
    if args.dtype == "float64":
        gpguided_jax.enable_x64()
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "tuning.json")
    if args.stage == "tune":
        header = {"seeds": list(TUNING_SEEDS), "dtype": args.dtype,
                  "env_steps": study.learning_steps(base_config("reinforce", dtype=args.dtype))}
        for name in args.only or [*METHODS, *baselines.NAMES]:
            t0 = time.perf_counter()
            result = (tune_baseline(name, TUNING_SEEDS) if name in baselines.NAMES
                      else tune_method(name, TUNING_SEEDS, args.dtype))
            rep = study.record_result(path, header, name,
                                      {**result, "wall_s": time.perf_counter() - t0})
        checkpoints.atomic_write_text(os.path.join("docs", "tuning_swingup.md"), tuning_markdown(rep))
    elif args.stage == "heldout":
        heldout(args.out, HELDOUT_SEEDS, study.read_json(path), args.dtype, args.only)
        print(report(args.out))
    elif args.stage == "gpfig":
        gp_figure(args.out, HELDOUT_SEEDS[:3], args.dtype, study.read_json(path))
    else:
        print(report(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
