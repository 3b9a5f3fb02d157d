"""gp_model (the GP as a model of the task, `gpguided_jax.model_based`) on the standard tasks,
beside brax's SAC and PPO and the paper's methods, by the protocol of `gpguided_jax.study`.

The budget is the aim's: `BUDGETS` environment steps of learning episodes (one episode an update),
far below the standard tasks' budgets, so the comparison is by the environment steps (and the wall
time) to the threshold: the baselines' and the paper's methods' curves are the standard-tasks
study's held-out runs (docs/results/standard/<task>/heldout), on the same held-out seeds.

Stages, per task; each writes under --out (default docs/results/model/<task>):

``tune``    Tuning seeds (100, 101; never reported): coordinate search over `GRIDS` (written
            before any run), from `BASE`'s settings (`base`: gp_model's preset,
            `config.METHOD_PRESETS`, for the settings the search leaves alone, and `START` for
            those it searches). The score is the run's measure (`MEASURES`:
            the deterministic policy's return, its success rate on the swing-up) over the
            evaluations in the second half of the budget (mean over seeds): it rewards reaching
            the threshold early and staying there. Writes tuning.json.
``heldout`` Held-out seeds (1000-1009; 1000-1019 for the swing-up): gp_model with the tuned
            settings under each of the model's exploration choices (`USES`;
            --only: which), each alone through `gpguided reproduce`'s driver. Writes
            heldout/<choice>.npz and .json (resumes as the standard tasks' study does). With
            --reward learned: the same runs with the reward learnt by the model instead of the
            task's stated one (`model_reward`), heldout/<choice>_learned.npz and .json.
``report``  heldout_table.json (seeds reaching the threshold, environment steps and wall time to
            it, final return, and each choice's probability of improvement over the mean model)
            and the figure (return against environment steps, log axis, beside SAC, PPO and the
            paper's best method), from which `docs_tables.py` renders the table.

Usage:
  python experiments/model_study.py tune --task pendulum-v1
  python experiments/model_study.py heldout --task pendulum-v1
  python experiments/model_study.py heldout --task pendulum-v1 --only thompson --reward learned
  python experiments/model_study.py report --task pendulum-v1
  (--task mountaincar-continuous, inverted-pendulum, inverted-double-pendulum, swingup: the
  same three stages)
"""

from __future__ import annotations

import argparse
import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpguided_jax import baselines, exploration, stats, study, tasks  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
METHOD = "gp_model"
TASKS = ("pendulum-v1", "mountaincar-continuous", "inverted-pendulum", "inverted-double-pendulum",
         "swingup")
# learning steps of a run: the aim's budget (2,000 on Pendulum-v1), one episode an update, and one
# more update whose evaluation is that of the policy after the whole budget
# (the car and the swing-up: 10 episodes)
BUDGETS = {"pendulum-v1": 2000, "mountaincar-continuous": 9990, "inverted-pendulum": 6000,
           "inverted-double-pendulum": 6000, "swingup": 9000}
# the uses of the model's uncertainty this study's grids and held-out runs were written with (the
# uses added after it, `model_based.EXPLORATIONS`, are experiments/exploration_uses_study.py's)
USES = ("mean", "sample", "thompson", "optimistic")
# where the search starts in the settings it searches (`GRIDS`); the settings it leaves alone
# are gp_model's preset's (`base`: one episode an update, the first episode's noise, the floor
# after it, the evaluation episodes, and on brax's pendulums episodes restarted where they end and
# the model's capacity)
START = {
    # brax's inverted pendulum: the simulated roll-outs as long as the standard tasks' other
    # settings allow; its double pendulum as the single one, roll-outs of 4 s (200 steps)
    "inverted-pendulum": dict(model_horizon=8.0),
    "inverted-double-pendulum": dict(model_horizon=4.0),
    # the car: decisions held 5 steps (its step counts as 1 s), simulated roll-outs of 200
    # steps, and the goal's end smoothed at the scale of the observation's spread, so that the
    # goal's bonus is felt from afar (`model_end_softness`)
    "mountaincar-continuous": dict(hold_time=5.0, model_horizon=200.0, model_end_softness=1.0),
    # the swing-up: the controller decides at 10 Hz and holds its action, as PILCO's does, so
    # that the model is of one decision; the simulated roll-outs as long as the episode
    "swingup": dict(hold_time=0.1, model_horizon=4.5)}
# (parameter, values) per stage, applied over the best so far (its default between the values):
# the exploration choice, the simulated horizon (s; default 4), the Adam step (0.01), the
# optimiser steps per update (100), the inducing inputs (200) and L-BFGS in place of Adam
GRIDS = {"pendulum-v1": [("model_exploration", list(USES)),
                         ("model_horizon", [2.0, 8.0]),
                         ("model_learning_rate", [0.003, 0.03]),
                         ("model_steps", [50, 200]),
                         ("model_inducing", [100, 400]),
                         ("model_optimizer", ["lbfgs"])],
         # a smaller grid where a run costs more: the exploration choice and the horizon (8 s)
         "inverted-pendulum": [("model_exploration", list(USES)),
                               ("model_horizon", [4.0, 16.0])],
         "inverted-double-pendulum": [("model_exploration", list(USES)),
                                      ("model_horizon", [2.0, 8.0])],
         # the car: the exploration choice, the end's smoothing, the horizon and the hold
         "mountaincar-continuous": [("model_exploration", list(USES)),
                                    ("model_end_softness", [0.3, 3.0]),
                                    ("model_horizon", [100.0, 400.0]),
                                    ("hold_time", [2.0, 10.0])],
         # the swing-up (from 4.5 s and 0.1 s held, `START`): the exploration choice, the horizon,
         # the hold, the inducing inputs and the optimiser's steps
         "swingup": [("model_exploration", list(USES)),
                     ("model_horizon", [3.0, 6.0]),
                     ("hold_time", [0.05, 0.2]),
                     ("model_inducing", [100, 400]),
                     ("model_steps", [50, 200])]}
# what a run is measured by: the deterministic policy's evaluation return against the task's
# threshold, or (the swing-up) its success rate against the aim's 90%
MEASURES = {"swingup": ("eval_success_rate", 0.9, "success rate")}
STANDARD = os.path.join(ROOT, "docs", "results", "standard")
# brax's baselines, SAC's row first (the aim's comparison), and the standard-tasks study's runs
# of the paper's methods (experiments/standard_tasks.py), restarted or not
BESIDE = tuple(reversed(baselines.NAMES))
PAPER = tuple(f"{m}{end}" for end in ("", "_restart") for m in config_lib.PAPER_METHODS)


def planned(task: str) -> dict:
    """The settings the planning study chose for `task` on top of this study's
    (experiments/planning_study.py: its cost stage's cheapest, docs/results/planning/<task>/
    cost.json, where it ran, else its tuning.json's `chosen`), which the preset holds too: {}
    where it has not run."""
    folder = os.path.join(ROOT, "docs", "results", "planning", task)
    for name, key in (("cost.json", "cheapest"), ("tuning.json", "chosen")):
        path = os.path.join(folder, name)
        if os.path.exists(path):
            return study.read_json(path)[key]
    return {}


def base(task: str) -> dict:
    """The settings every run of `task` starts from: gp_model's preset
    (`config.METHOD_PRESETS[task]['gp_model']`) without the settings the search chose (those of
    `GRIDS[task]`), those the planning study chose after it (`planned`) and the budget's updates,
    and where the search starts in those (`START`)."""
    searched = {p for params, _ in GRIDS[task]
                for p in (params if isinstance(params, (tuple, list)) else (params,))}
    searched |= set(planned(task))
    start = START.get(task, {})
    preset = config_lib.METHOD_PRESETS[task][METHOD]
    kept = {k: start.get(k, v) for k, v in preset.items()
            if k in start or (k not in searched and k != "num_updates")}
    return {**kept, **start}


BASE = {task: base(task) for task in TASKS}


def overrides(task: str, settings: dict) -> dict:
    """A run's config overrides: the preset's own values of the fields gp_model's preset tunes
    (`study.preset_own`: the study does not start from its own earlier tuning), `BASE`, the
    budget's updates and `settings`."""
    episodes = BASE[task]["episodes_per_update"]
    length = config_lib.PRESETS[task]["episode_length"]
    updates = BUDGETS[task] // (episodes * length) + 1
    return {**study.preset_own(task, METHOD), **BASE[task], "num_updates": updates, **settings}


def measure(task: str) -> tuple[str, float, str]:
    """(the record a run is measured by, the level to reach, its name)."""
    if task in MEASURES:
        return MEASURES[task]
    return "eval_return", tasks.THRESHOLDS[config_lib.PRESETS[task]["env"]], "return"


def heldout_seeds(task: str) -> list[int]:
    """The held-out seeds: 1000-1009, and 1000-1019 for the swing-up."""
    return list(range(1000, 1020)) if task == "swingup" else list(study.HELDOUT_SEEDS)


def score_of(task: str):
    record = measure(task)[0]

    def score(records: dict) -> dict:
        ret = np.asarray(records[record], float)  # (seeds, updates)
        half = ret.shape[1] // 2
        return {"score": float(ret[:, half:].mean()), "final": float(ret[:, -1].mean())}

    return score


def tune(task: str, out: str) -> None:
    """The coordinate search; each configuration's result is kept in tuning_runs.json as it
    finishes, so that an interrupted search resumes where it stopped."""
    path = os.path.join(out, "tuning.json")
    runs_path = os.path.join(out, "tuning_runs.json")

    def evaluate(configs):
        results = []
        for c in configs:
            done = study.read_json(runs_path, {})
            key = json.dumps(overrides(task, c), sort_keys=True)
            if key not in done:
                done[key] = study.sweep_stage([overrides(task, c)], score_of(task), method=METHOD,
                                              preset=task, seeds=study.TUNING_SEEDS,
                                              progress=study.log)[0]
                study.write_json(runs_path, done)
            results.append(done[key])
        return results

    result = study.coordinate_search(study.stages(GRIDS[task]), evaluate, log=study.log)
    study.write_json(path, {"task": task, "measure": measure(task)[2],
                            "seeds": list(study.TUNING_SEEDS),
                            "grid": GRIDS[task], "base": BASE[task],
                            "budget": BUDGETS[task], **result})
    study.log(f"wrote {path}: {result['chosen']}")


def _name(choice: str, reward: str) -> str:
    """A held-out run's file name: the exploration choice, '_learned' for a learnt reward."""
    return choice + ("_learned" if reward == "learned" else "")


def heldout(task: str, out: str, seeds, only, reward: str = "stated") -> None:
    chosen = study.read_json(os.path.join(out, "tuning.json"), {}).get("chosen", {})
    for choice in only:
        settings = {**chosen, "model_exploration": choice,
                    **({"model_reward": "learned"} if reward == "learned" else {})}
        meta = {"seeds": list(seeds), "settings": settings}
        name = _name(choice, reward)
        path = os.path.join(out, "heldout", name)
        if study.finished(path + ".json", **meta):
            study.log(f"[{task} {name}] done with these seeds and settings: {path}.json")
            continue
        # a chunk per update: an update takes minutes on the brax tasks, and the run reports its
        # progress and saves its checkpoint after each chunk
        run = study.run_method(task, METHOD, seeds, os.path.join(out, "runs", name),
                               overrides(task, settings), chunk_size=1)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        np.savez(path + ".npz", steps=run.env_steps, measure=run.records[measure(task)[0]],
                 model_error=run.records["model_error"],
                 model_reward_error=run.records["model_reward_error"])
        study.write_json(path + ".json", {**meta, "wall_s": run.wall_s})


def _row(name, steps, ret, threshold, wall_s, seeds):
    reach = study.steps_to(steps, ret, threshold, never=np.nan)
    ok = np.isfinite(reach)
    per_seed = wall_s / ret.shape[0]
    # wall time to the threshold: the run's seconds per seed, in proportion to its steps
    wall_to = per_seed * reach / steps[-1]
    return dict(method=name, seeds=int(ret.shape[0]), seeds_reaching=int(ok.sum()),
                steps_to_threshold=[None if not f else int(v) for v, f in zip(reach, ok)],
                steps_to_threshold_median=float(np.median(reach[ok])) if ok.any() else None,
                wall_to_threshold_median=float(np.median(wall_to[ok])) if ok.any() else None,
                final_mean=float(ret[:, -1].mean()), env_steps=int(steps[-1]),
                seeds_above_at_end=int(np.sum(ret[:, -1] >= threshold)),
                wall_s_per_seed=float(per_seed))


def _horizon_steps(task: str) -> int:
    """The tuned simulated roll-outs' steps (decisions of the hold)."""
    cfg = config_lib.preset(task, method=METHOD)
    dt = config_lib.control_interval(cfg)
    return int(round(cfg.settings.horizon / (dt * exploration.hold_steps(cfg.hold_time, dt))))


def _others(task: str, seeds: list) -> dict:
    """The baselines' and the paper's methods' held-out curves on these seeds (the swing-up's: on
    those of them its study ran): name -> (steps, curves (seeds, evaluations), wall seconds)."""
    others = {}
    if task == "swingup":
        path = os.path.join(ROOT, "docs", "results", "swingup", "heldout")
        meta = study.read_json(path + ".json")
        if not set(meta["seeds"]) <= set(seeds):
            return others
        with np.load(path + ".npz") as f:
            for name in meta["wall_s"]:
                steps, ret = f[f"{name}_steps"], np.asarray(f[f"{name}_success"], float)
                if name in baselines.NAMES:
                    steps, ret = baselines.after_initial_evaluation(steps, ret)
                others[name] = (steps, ret, meta["wall_s"][name])
        return others
    for name in (*BESIDE, *PAPER):
        p = os.path.join(STANDARD, task, "heldout", name)
        if not os.path.exists(p + ".npz"):
            continue
        with np.load(p + ".npz") as f:
            steps, ret = f["steps"], np.asarray(f["return"], float)
        meta = study.read_json(p + ".json")
        if meta["seeds"] != seeds:
            continue
        if name in baselines.NAMES:
            steps, ret = baselines.after_initial_evaluation(steps, ret)
        others[name] = (steps, ret, meta["wall_s"])
    return others


def heldout_figure(task: str, curves: dict, threshold: float, measure_name: str, seeds: list,
                   name: str) -> str:
    """The held-out curves (name -> (steps, curves (seeds, evaluations))) against environment
    steps on a log axis, gp_model's solid and the others dotted, with the threshold; written to
    docs/figures/<name>. Returns its path."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, (steps, ret) in curves.items():
        study.plot_band(ax, steps, ret, label=label, ls="-" if label.startswith("gp_model") else ":")
    ax.axhline(threshold, color="k", ls="--", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("environment steps (log)")
    ax.set_ylabel(f"{measure_name} of the deterministic policy")
    fewer = {c[1].shape[0] for n, c in curves.items() if not n.startswith("gp_model")} - {len(seeds)}
    ax.set_title(f"{task}: {len(seeds)} held-out seeds (mean, 95% t-band)" if not fewer else
                 f"{task}: held-out seeds, {len(seeds)} for gp_model, {min(fewer)} for the others "
                 "(mean, 95% t-band)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    figure = os.path.join(ROOT, "docs", "figures", name)
    fig.savefig(figure, dpi=110)
    plt.close(fig)
    return figure


def report(task: str, out: str) -> None:
    record, threshold, measure_name = measure(task)
    rows, curves = [], {}
    runs = [(c, r) for r in ("stated", "learned") for c in USES]
    for choice, reward in runs:
        p = os.path.join(out, "heldout", _name(choice, reward))
        label = f"gp_model ({choice}{', reward learned' if reward == 'learned' else ''})"
        if os.path.exists(p + ".npz"):
            with np.load(p + ".npz") as f:
                curves[label] = (f["steps"], np.asarray(f["measure"], float))
                error = np.asarray(f["model_error"], float)  # (seeds, updates)
                reward_error = (np.asarray(f["model_reward_error"], float)
                                if reward == "learned" else None)
            meta = study.read_json(p + ".json")
            rows.append(_row(label, *curves[label], threshold, meta["wall_s"], meta["seeds"]))
            # the model's error on each update's new transitions before it took them in, 1 - R^2:
            # the median over seeds, at the second update and at the last (and the learnt
            # reward's)
            rows[-1]["model_error_second"] = float(np.median(error[:, 1]))
            rows[-1]["model_error_last"] = float(np.median(error[:, -1]))
            if reward_error is not None:
                rows[-1]["reward_error_second"] = float(np.median(reward_error[:, 1]))
                rows[-1]["reward_error_last"] = float(np.median(reward_error[:, -1]))
            # the simulated return after the last update's optimisation, median over seeds, and
            # its ceiling where the reward is bounded per step (brax's pendulum: 1 per step)
            run = os.path.join(out, "runs", _name(choice, reward), "results.npz")
            if os.path.exists(run):
                with np.load(run) as f:
                    rows[-1]["model_return_last"] = float(np.median(f["model_return"][0][:, -1]))
    seeds = meta["seeds"]
    others = _others(task, seeds)
    paper_best = max((n for n in PAPER if n in others),
                     key=lambda n: study.final(others[n][1]).mean(), default=None)
    for name in (*BESIDE, paper_best):
        if name is not None and name in others:
            steps, ret, wall_s = others[name]
            rows.append(_row(name, steps, ret, threshold, wall_s, seeds))
            curves[name] = others[name][:2]
    # each exploration choice against the mean model: P(choice > mean) of the final returns
    mean_key = "gp_model (mean)"
    if mean_key in curves:
        for row in rows:
            name = row["method"]
            if name.startswith("gp_model (") and name != mean_key:
                row["p_improvement_over_mean"] = stats.probability_of_improvement(
                    curves[name][1][:, -1], curves[mean_key][1][:, -1])
    figure = heldout_figure(task, curves, threshold, measure_name, seeds, f"model_{task}.png")
    study.write_json(os.path.join(out, "heldout_table.json"), {
        "task": task, "threshold": threshold, "measure": measure_name, "seeds": seeds,
        "budget": BUDGETS[task], "horizon_steps": _horizon_steps(task),
        "paper_best": paper_best, "rows": rows})
    study.log(f"wrote {figure} and {out}/heldout_table.json")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stage", choices=("tune", "heldout", "report"))
    p.add_argument("--task", choices=TASKS, default="pendulum-v1")
    p.add_argument("--out", default=None)
    p.add_argument("--only", nargs="+", default=list(USES),
                   choices=USES)
    p.add_argument("--reward", choices=("stated", "learned"), default="stated",
                   help="heldout: the task's stated reward (default) or one the model learns")
    args = p.parse_args(argv)
    out = study.set_up(args.out or os.path.join(ROOT, "docs", "results", "model", args.task))
    if args.stage == "tune":
        tune(args.task, out)
    elif args.stage == "heldout":
        heldout(args.task, out, heldout_seeds(args.task), args.only, args.reward)
    else:
        report(args.task, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
