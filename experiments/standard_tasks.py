"""The four methods beside brax's SAC and PPO on the standard tasks (`gpguided_jax.tasks`), each
tuned with the same budget on tuning seeds, then compared on held-out seeds, by the protocol of
`gpguided_jax.study`.

Stages, per task (a preset of `config.PRESETS`: pendulum-v1, mountaincar-continuous,
inverted-pendulum, inverted-double-pendulum); each writes under --out (default
docs/results/standard/<task>):

``tune``    Tuning seeds (100, 101; never reported). Every method and baseline gets the same budget:
            `CONFIGS_PER_METHOD` (8) configurations x the tuning seeds, each a full run of the
            preset's environment steps. Coordinate search (`study.coordinate_search`): a stage of
            four learning rates, then stages of two values of the next parameter, each keeping the
            best configuration so far (`grids`, `baseline_grids`; written before any run), from
            the preset's own settings (`study.preset_own`). The discount is searched as a horizon
            in seconds (`tasks.discount_for_horizon`). The score is the final undiscounted return
            of the deterministic policy (last 10% of evaluations, mean over seeds). Writes
            tuning/<name>.json per method or baseline (--only: which).
``heldout`` Held-out seeds (1000-1009): each method alone through `gpguided reproduce`'s driver
            with its tuned settings over the preset's own, each baseline per seed; wall time per
            method (`reproduce`'s: its fit and run, compilation included). Writes methods/<name>/
            (the run), heldout/<name>.npz (return curves against environment steps,
            `study.env_steps`) and .json. It resumes: a name whose .json holds the same seeds and
            settings is not run again.
``targets`` gp_critic's GP targets on the tuning seeds (`TARGET_GRIDS`; Pendulum-v1 and the car):
            returns-to-go against lambda-returns. Writes targets.json; `heldout --only
            gp_critic_lambda` runs the better lambda-return on the held-out seeds.
``retune``  gp_critic's own settings beyond the shared grid, on the tuning seeds (`retune_grid`):
            a coordinate search from its tuned settings over the critic's uncertainty in the
            score (kappa), the window, the GP's budget M, and its gp_pg step's horizon and
            learning rate. Writes retune.json; `heldout --only
            gp_critic_retuned` runs its choice on the held-out seeds. It spends configurations
            beyond the others' budget, so its row stands beside gp_critic's, not in its place.
``report``  tuning.json (the tuning records gathered), the figure (return of the deterministic
            policy against environment steps, mean and 95% t-band over seeds, the threshold
            dashed) and heldout_table.json, from which `docs_tables.py` renders the tables.

Usage:
  python experiments/standard_tasks.py tune --task pendulum-v1
  python experiments/standard_tasks.py heldout --task pendulum-v1
  python experiments/standard_tasks.py report --task pendulum-v1
  python experiments/standard_tasks.py targets --task pendulum-v1
  python experiments/standard_tasks.py heldout --task pendulum-v1 --only gp_critic_lambda
  python experiments/standard_tasks.py heldout --task pendulum-v1 --only gp_critic_m400
  python experiments/standard_tasks.py retune --task pendulum-v1
  python experiments/standard_tasks.py heldout --task pendulum-v1 --only gp_critic_retuned
"""

from __future__ import annotations

import argparse
import glob
import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpguided_jax import baselines, checkpoints, methods, study, summaries, tasks  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402
from gpguided_jax import stats as stats_lib  # noqa: E402

# the paper's four, and gp_critic (`gpguided_jax.critic`), each with its grid (`grids`), beside
# brax's PPO and SAC (`baselines.NAMES`)
METHODS = (*methods.paper(), "gp_critic")
# On a task whose episodes end early, each method again with the settings tuned above and
# `episode_end='restart'` (an episode that ends is restarted in its remaining slots, so every slot
# is an environment step, as for PPO and SAC): `heldout --only reinforce_restart ...`.
RESTARTED = tuple(f"{m}_restart" for m in METHODS)
# gp_critic's GP targets (`targets` stage): at its tuned settings, the paper's returns-to-go
# against lambda-returns bootstrapped with the GP's mean, lambda a horizon of a quarter and of the
# whole of the task's discount horizon (s; the car's step counts as 1 s). The best on the tuning
# seeds is chosen; `heldout --only gp_critic_lambda` runs the better lambda-return on the held-out
# seeds whichever is chosen, so that the critic's error is reported under both.
TARGET_GRIDS = {"pendulum-v1": [0.25, 1.0], "mountaincar-continuous": [25.0, 100.0]}
# gp_critic at its tuned settings with one more change, on the held-out seeds: the targets stage's
# better lambda-return and the GP's budget M = 400 (the tuning's is the preset's 100), ablations
# after the tuning, not tuned; and the `retune` stage's choice
VARIANTS = {"gp_critic_lambda": ("targets.json", "best"), "gp_critic_m400": {"gp_capacity": 400},
            "gp_critic_retuned": ("retune.json", "chosen")}
# gp_critic's `retune` stage: from its tuned settings, first those settings alone (their score
# again, the search's start), then kappa pessimistic and optimistic, a window of 4 and 16
# updates' states, M = 400, and its gp_pg step's horizon and learning rate (the shared grid
# leaves them at the preset's own); each stage over the best so far (`study.search_beyond`)
def retune_grid(task: str) -> list:
    return [("critic_optimism", [-1.0, 1.0]), ("critic_window", [4, 16]), ("gp_capacity", [400]),
            ("horizon", horizons(task)), ("learning_rate", [0.003, 0.03])]
CONFIGS_PER_METHOD = 8
TUNING_SEEDS = study.TUNING_SEEDS
HELDOUT_SEEDS = study.HELDOUT_SEEDS
NUM_EVALS = 26  # 25 intervals: brax PPO (2,000 steps an iteration) then stops at exactly 100k steps
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Published reference numbers (rl-baselines3-zoo, benchmark.md: one run each, the mean and
# standard deviation of its evaluation episodes), to set the table beside.
REFERENCES = {
    "pendulum-v1": "rl-baselines3-zoo, benchmark.md (one run each, deterministic policy): SAC "
                   "−157.0 ± 88.7 and TD3 −151.9 ± 90.2 after 20k steps, PPO −172.2 ± 104.2 after "
                   "100k",
    "mountaincar-continuous": "rl-baselines3-zoo, benchmark.md (one run each, deterministic "
                              "policy): SAC 94.7 ± 1.1 after 50k steps, TD3 93.5 ± 0.1 after 300k, "
                              "PPO 88.3 ± 2.6 after 20k",
    "inverted-pendulum": "rl-baselines3-zoo's benchmark.md has no row for MuJoCo's "
                         "InvertedPendulum; gymnasium counts InvertedPendulum-v4 solved at 950 "
                         "over its 1,000 steps",
    "inverted-double-pendulum": "rl-baselines3-zoo's benchmark.md has no row for MuJoCo's "
                                "InvertedDoublePendulum; gymnasium counts "
                                "InvertedDoublePendulum-v4 solved at 9,100 over its 1,000 steps",
}


def horizons(task: str) -> list[float]:
    """The two horizons (seconds; the car's steps count as seconds) the tuning tries beside the
    preset's own."""
    return [30.0, 300.0] if task == "mountaincar-continuous" else [0.5, 2.0]


def grids(task: str) -> dict:
    """(parameter, values) stages per method: 4 + 2 + 2 = 8 configurations (guided_direction:
    2 + 2 + 2 + 2). 'horizon' is the discount as a horizon; noise scales are in units of the
    action bound u (its square for variances). gp_critic's grid is over its own settings, from
    the preset's (its gp_pg step's learning rate, horizon and noise): the surrogate's step size,
    the trust region delta (nats of mean KL; 0.05 between the two) and the surrogate steps per
    update K (50 between the two; each value its own program, K fixing the program)."""
    u = tasks.make_task(config_lib.PRESETS[task]["env"]).max_action
    lr = ("learning_rate", [0.003, 0.01, 0.03, 0.1])
    h = ("horizon", horizons(task))
    return {
        "reinforce": [lr, h, ("init_log_std", [math.log(0.25 * u), math.log(u)])],
        "gp_pg": [lr, h, ("init_log_std", [math.log(0.25 * u), math.log(u)])],
        "guided_variance": [lr, h, ("guided_variance_scale", [0.25 * u * u, 2.0 * u * u])],
        "guided_direction": [("learning_rate", [0.01, 0.03]), h,
                             ("candidate_scale", [0.25 * u * u, 2.0 * u * u]),
                             ("inverse_temperature", [1.0, 100.0])],
        "gp_critic": [("critic_learning_rate", [0.003, 0.01, 0.03, 0.1]),
                      ("trust_region", [0.01, 0.2]), ("critic_steps", [10, 200])],
    }


def baseline_grids(task: str) -> dict:
    h = ("horizon", horizons(task))
    return {
        # rl-baselines3-zoo: SAC lr 1e-3 on Pendulum-v1, one gradient step per environment step
        # (16 parallel environments: 16 steps per environment step of brax's loop)
        "sac": [("learning_rate", [1e-4, 3e-4, 1e-3, 3e-3]), ("grad_updates_per_step", [4, 16]), h],
        # rl-baselines3-zoo: PPO gamma 0.9 on Pendulum-v1 (a 0.5 s horizon at 20 Hz), lr 1e-3
        "ppo": [("learning_rate", [1e-4, 3e-4, 1e-3, 3e-3]), h, ("entropy_cost", [1e-4, 1e-2])],
    }


def _discount(task: str, horizon: float) -> float:
    return tasks.discount_for_horizon(horizon, tasks.make_task(config_lib.PRESETS[task]["env"]).dt)


def method_overrides(task: str, method: str, settings: dict) -> dict:
    """The config overrides of a method's settings (a 'horizon' as its discount) over the preset's
    own."""
    return study.merge_overrides(
        study.preset_own(task, method),
        {("discount" if k == "horizon" else k): (_discount(task, v) if k == "horizon" else v)
         for k, v in settings.items()})


def budget(task: str) -> int:
    return study.learning_steps(baseline_config(task))


# ------------------------------------------------------------------------------------------ tune


def tune_method(task: str, method: str, seeds) -> dict:
    def evaluate(configs):
        return study.sweep_stage([method_overrides(task, method, s) for s in configs],
                                 study.final_return, method=method, preset=task, seeds=seeds)

    return study.coordinate_search(study.stages(grids(task)[method]), evaluate,
                                   log=lambda m: study.log(f"[tune {task} {method}] {m}"))


def baseline_config(task: str) -> config_lib.TrainConfig:
    """The config whose task, budget and episode length the baselines run with."""
    return config_lib.preset(task, method="reinforce")


def baseline_score(run: study.BaselineRun) -> dict:
    """{'score': the final return of the deterministic policy (its evaluations after learning
    started), mean over seeds}, as a method's (`study.final_return`)."""
    _, ret = baselines.after_initial_evaluation(run.env_steps, run.records["eval_return"])
    return study.final_return({"eval_return": ret})


def tune_baseline(task: str, name: str, seeds) -> dict:
    def evaluate(configs):
        return study.baseline_stage(configs, baseline_score, name=name, cfg=baseline_config(task),
                                    seeds=seeds, num_evals=NUM_EVALS)

    return study.coordinate_search(study.stages(baseline_grids(task)[name]), evaluate,
                                   log=lambda m: study.log(f"[tune {task} {name}] {m}"))


def tune(task: str, out: str, only: list[str]) -> None:
    """Tunes each of `only`, writing tuning/<name>.json (one file each, so that methods and
    baselines can be tuned by separate processes); `report` gathers them into tuning.json."""
    for name in only:
        study.log(f"[tune {task}] {name}")
        result = (tune_baseline(task, name, TUNING_SEEDS) if name in baselines.NAMES
                  else tune_method(task, name, TUNING_SEEDS))
        grid = (baseline_grids(task) if name in baselines.NAMES else grids(task))[name]
        study.write_json(os.path.join(out, "tuning", f"{name}.json"), {"grid": grid, **result})


def gather_tuning(task: str, out: str) -> dict:
    """tuning.json: every tuned method's and baseline's record, in a fixed order."""
    methods = {}
    for name in (*METHODS, *baselines.NAMES):
        rec = study.read_json(os.path.join(out, "tuning", f"{name}.json"))
        if rec is not None:
            methods[name] = rec
    report = {"task": task, "seeds": list(TUNING_SEEDS), "env_steps": budget(task),
              "methods": methods}
    study.write_json(os.path.join(out, "tuning.json"), report)
    return report


# --------------------------------------------------------------------------------------- heldout


def heldout(task: str, out: str, seeds, only: list[str], part: str | None = None) -> None:
    """Each of `only` on the held-out seeds with its tuned settings (tuning/<name>.json; the
    preset's own without one), into heldout/<name>.npz and .json; a name whose .json holds these
    seeds and settings is not run again. `part` 'K/N': a baseline's seeds K, K + N, ... only, into
    heldout/<name>.partK.npz (N processes share the seeds; `report` joins the parts)."""
    suffix = ""
    if part is not None:
        k, n = map(int, part.split("/"))
        seeds, suffix = list(seeds)[k::n], f".part{k}"
    for name in only:
        method, end = _method_and_end(name)
        settings = study.read_json(os.path.join(out, "tuning", f"{method}.json"),
                                   {}).get("chosen", {})
        if name in VARIANTS:  # gp_critic's tuned settings and the variant's change
            change = VARIANTS[name]
            if isinstance(change, tuple):  # a stage's record: the settings under its key
                file, key = change
                change = study.read_json(os.path.join(out, file))[key]
            if {**settings, **change} == settings:  # e.g. a retune that kept them
                study.log(f"[{task} {name}] changes nothing in gp_critic's tuned settings: its "
                          "held-out run is gp_critic's")
                continue
            settings = {**settings, **change}
        meta = {"seeds": list(seeds), "settings": settings}
        if method in METHODS:
            meta["episode_end"] = end
        path = os.path.join(out, "heldout", f"{name}{suffix}")
        if study.finished(path + ".json", **meta):
            study.log(f"[{task} {name}] done with these seeds and settings: {path}.json")
            continue
        if method in METHODS:  # alone: its wall time includes its fit and compilation
            run_dir = os.path.join(out, "methods", name)
            overrides = {**method_overrides(task, method, settings), "episode_end": end}
            run = study.run_method(task, method, seeds, run_dir, overrides, chunk_size=25,
                                   gp_program="shared")
            meta["wall_s"] = run.wall_s
            curves = {"return": run.records["eval_return"], "steps": run.env_steps,
                      "steps_used": steps_used(run_dir, config_lib.preset(task, method=method,
                                                                          **overrides))}
        else:
            run = study.run_baseline(name, baseline_config(task), seeds, settings,
                                     num_evals=NUM_EVALS, progress=lambda m: study.log(f"[{task}] {m}"))
            curves = {"steps": run.env_steps, "return": run.records["eval_return"]}
            meta["wall_s"] = run.wall_s
        os.makedirs(os.path.dirname(path), exist_ok=True)
        checkpoints.atomic_savez(path + ".npz", **curves)
        study.write_json(path + ".json", meta)


def _join_parts(out: str, name: str) -> None:
    """heldout/<name>.npz and .json from its parts (in seed order; wall time: the parts' sum), when
    it has parts and no whole file."""
    base = os.path.join(out, "heldout", name)
    parts = sorted(glob.glob(base + ".part*.npz"))
    if os.path.exists(base + ".npz") or not parts:
        return
    curves, metas = [], []
    for p in parts:
        with np.load(p) as f:
            curves.append({k: f[k] for k in f.files})
        metas.append(study.read_json(p[:-4] + ".json"))
    seeds = [s for m in metas for s in m["seeds"]]
    order = np.argsort(seeds)
    ret = np.concatenate([c["return"] for c in curves])[order]
    checkpoints.atomic_savez(base + ".npz", steps=curves[0]["steps"], **{"return": ret})
    study.write_json(base + ".json", {"seeds": sorted(seeds), "settings": metas[0]["settings"],
                                      "wall_s": float(sum(m["wall_s"] for m in metas))})


# ---------------------------------------------------------------------------------------- report


def _method_and_end(name: str) -> tuple[str, str]:
    """(method, episode_end) of a name of METHODS, RESTARTED, VARIANTS or baselines.NAMES."""
    if name.endswith("_restart"):
        return name[: -len("_restart")], "restart"
    if name in VARIANTS:
        return "gp_critic", "mask"
    return name, "mask"


def targets(task: str, out: str) -> None:
    """gp_critic at its tuned settings (tuning/gp_critic.json) with each GP target of
    `TARGET_GRIDS` on the tuning seeds, one stage: returns-to-go, and lambda-returns at each
    horizon. Writes targets.json: what was tried, the choice, and the best lambda-return."""
    tuned = study.read_json(os.path.join(out, "tuning", "gp_critic.json"))["chosen"]
    stages = [[{**tuned, "critic_targets": "returns"}],  # one program, then one for the horizons
              [{**tuned, "critic_targets": "lambda", "critic_lambda_horizon": h}
               for h in TARGET_GRIDS[task]]]
    tried = []
    for configs in stages:
        results = study.sweep_stage([method_overrides(task, "gp_critic", c) for c in configs],
                                    study.final_return, method="gp_critic", preset=task,
                                    seeds=TUNING_SEEDS)
        tried += [dict(settings=c, **r) for c, r in zip(configs, results)]
    for t in tried:
        study.log(f"[targets {task}] {t['settings']}: {t['score']:.1f}")
    best = max((t for t in tried if t["settings"]["critic_targets"] == "lambda"),
               key=study.by_score)
    study.write_json(os.path.join(out, "targets.json"), {
        "task": task, "seeds": list(TUNING_SEEDS), "grid": TARGET_GRIDS[task], "tried": tried,
        "chosen": max(tried, key=study.by_score)["settings"],
        "best": {k: best["settings"][k] for k in ("critic_targets", "critic_lambda_horizon")}})


def retune(task: str, out: str) -> None:
    """gp_critic's `retune_grid` on the tuning seeds, a coordinate search from its tuned
    settings (tuning/gp_critic.json), which are scored again as its first stage. Writes
    retune.json: the grid, what was tried and the choice."""
    tuned = study.read_json(os.path.join(out, "tuning", "gp_critic.json"))["chosen"]

    def evaluate(configs):
        return study.sweep_stage([method_overrides(task, "gp_critic", c) for c in configs],
                                 study.final_return, method="gp_critic", preset=task,
                                 seeds=TUNING_SEEDS)

    path = os.path.join(out, "retune.json")
    done = study.read_json(path, {}).get("tried", [])  # a grown grid runs only its new stages
    result = study.search_beyond(tuned, retune_grid(task), evaluate, done=done,
                                 log=lambda m: study.log(f"[retune {task}] {m}"))
    study.write_json(path, {"task": task, "seeds": list(TUNING_SEEDS), "grid": retune_grid(task),
                            **result})


def steps_used(run_dir: str, cfg) -> np.ndarray:
    """(seeds,) environment steps that a method's learning episodes used. On a task that ends
    early the compiled roll-out keeps its full length, so the budget counts every slot; the steps
    used are, per update, the episodes times their mean length, which is the mean return over the
    mean reward per step (both over the steps before the end; the full length where the reward
    per step is 0). With `episode_end='restart'` every slot is a step."""
    if cfg.episode_end == "restart":
        with np.load(os.path.join(run_dir, "results.npz")) as f:
            seeds = f["mean_return"].shape[1]
        return np.full(seeds, float(cfg.num_updates * cfg.episodes_per_update
                                    * cfg.episode_length))
    with np.load(os.path.join(run_dir, "results.npz")) as f:
        ret, rew = np.asarray(f["mean_return"][0], float), np.asarray(f["mean_reward"][0], float)
    length = np.where(rew != 0, ret / np.where(rew != 0, rew, 1.0), cfg.episode_length)
    return cfg.episodes_per_update * length.sum(axis=-1)


def report(task: str, out: str) -> None:
    gather_tuning(task, out)
    curves, meta = {}, {"wall_s": {}}
    for n in (*METHODS, *RESTARTED, *VARIANTS, *baselines.NAMES):
        _join_parts(out, n)
        path = os.path.join(out, "heldout", f"{n}.npz")
        if os.path.exists(path):
            with np.load(path) as f:
                curves[f"{n}_steps"], curves[f"{n}_return"] = f["steps"], f["return"]
                if "steps_used" in f:
                    curves[f"{n}_used"] = f["steps_used"]
            m = study.read_json(path[:-4] + ".json")
            meta["wall_s"][n], meta["seeds"] = m["wall_s"], m["seeds"]
    threshold = tasks.THRESHOLDS[config_lib.PRESETS[task]["env"]]
    terminates = tasks.make_task(config_lib.PRESETS[task]["env"]).terminates
    names = [n for n in (*METHODS, *RESTARTED, *VARIANTS, *baselines.NAMES)
             if f"{n}_return" in curves]
    rows = []
    fig, ax = plt.subplots(figsize=(7, 4))
    for n in names:
        steps, ret = curves[f"{n}_steps"], np.asarray(curves[f"{n}_return"], float)
        if n in baselines.NAMES:
            steps, ret = baselines.after_initial_evaluation(steps, ret)
        final = study.final(ret)
        lo, hi = stats_lib.bootstrap_ci(final)
        reach = study.steps_to(steps, ret, threshold, never=np.nan)
        rows.append(dict(method=n, seeds=int(ret.shape[0]), final_return_iqm=stats_lib.iqm(final),
                         ci95_low=lo, ci95_high=hi, final_return_mean=float(final.mean()),
                         steps_to_threshold=[None if np.isnan(v) else int(v) for v in reach],
                         steps_to_threshold_median=(float(np.median(reach[np.isfinite(reach)]))
                                                    if np.isfinite(reach).any() else None),
                         seeds_reaching=int(np.isfinite(reach).sum()), env_steps=int(steps[-1]),
                         wall_s=float(meta["wall_s"][n])))
        if terminates and (n in baselines.NAMES or f"{n}_used" in curves):
            # the baselines step the environment for their whole budget
            used = (curves[f"{n}_used"] if n not in baselines.NAMES
                    else np.full(ret.shape[0], float(steps[-1])))
            rows[-1]["steps_used_median"] = float(np.median(used))
        study.plot_band(ax, steps, ret, label=n, ls=":" if n in RESTARTED else "-")
    ax.axhline(threshold, color="k", ls="--", lw=0.8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("return of the deterministic policy")
    ax.set_title(f"{task}: {len(meta['seeds'])} held-out seeds (mean, 95% t-band)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    figure = os.path.join(ROOT, "docs", "figures", f"standard_{task}.png")
    fig.savefig(figure, dpi=110)
    plt.close(fig)
    fit_steps = summaries.task_budget(config_lib.preset(task, method="gp_pg")).fit_steps
    study.write_json(os.path.join(out, "heldout_table.json"), {
        "task": task, "threshold": threshold, "seeds": meta["seeds"], "rows": rows,
        "budget": budget(task), "fit_steps": fit_steps, "reference": REFERENCES.get(task)})
    study.log(f"wrote {figure} and {out}/heldout_table.json")
    study.critic_diagnostics({n: os.path.join(out, "methods", n, "results.npz")
                              for n in (*METHODS, *RESTARTED, *VARIANTS) if n in names},
                             os.path.join(out, "critic_diagnostics.json"),
                             os.path.join(ROOT, "docs", "figures", f"standard_critic_{task}.png"))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("stage", choices=["tune", "targets", "retune", "heldout", "report"])
    p.add_argument("--task", required=True, choices=[t for t in config_lib.PRESETS
                                                     if "env" in config_lib.PRESETS[t]])
    p.add_argument("--out", default=None, help="default docs/results/standard/<task>")
    p.add_argument("--part", default=None, metavar="K/N",
                   help="heldout: a baseline's seeds K, K + N, ... only (N processes at once)")
    p.add_argument("--only", nargs="+", default=[*METHODS, *baselines.NAMES],
                   choices=[*METHODS, *RESTARTED, *VARIANTS, *baselines.NAMES],
                   help="tune, heldout: these methods and baselines (heldout: also "
                   "<method>_restart, the method with episode_end='restart', and gp_critic's "
                   "variants: gp_critic_lambda, gp_critic_m400, gp_critic_retuned)")
    args = p.parse_args(argv)
    if args.stage == "tune" and set(args.only) & {*RESTARTED, *VARIANTS}:
        p.error("tune: the restarted methods and gp_critic's variants take the settings tuned "
                "for their method")
    if args.stage == "targets" and args.task not in TARGET_GRIDS:
        p.error(f"targets: the grid covers {', '.join(TARGET_GRIDS)}")
    out = study.set_up(args.out or os.path.join(ROOT, "docs", "results", "standard", args.task))
    if args.stage == "tune":
        tune(args.task, out, args.only)
    elif args.stage == "targets":
        targets(args.task, out)
    elif args.stage == "retune":
        retune(args.task, out)
    elif args.stage == "heldout":
        heldout(args.task, out, HELDOUT_SEEDS, args.only, args.part)
    else:
        report(args.task, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
