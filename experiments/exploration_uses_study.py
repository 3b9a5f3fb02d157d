"""When the reward must be found, does gp_model's uncertainty guide exploration? Each use of the
model's uncertainty (`model_based.EXPLORATIONS`: today's mean, sample, thompson and optimistic, and
optimistic_reward, optimistic_joint and information; docs/design.md#model) on tasks whose reward
the model must find, by the protocol of `gpguided_jax.study`, extending the model study's
(experiments/model_study.py: its budgets, measures, held-out seeds and table rows) from its tuned
settings (experiments/planning_study.py's `today`: docs/results/model/<task>/tuning.json; the
sparse swing-up from Pendulum-v1's preset, the planning study's choice included).

The tasks (each a preset, `config.PRESETS`; `BASE_TASK`: the model study's task it extends):

  mountaincar-continuous-learned  the car, the reward learnt (`model_reward`); 10 episodes
  swingup-learned                 the paper's swing-up, the reward learnt; 10 episodes, measured
                                  by the success rate
  pendulum-sparse-<rho>           the sparse swing-up (gymnax:Pendulum-v1-sparse-<rho>: H-UCRL's
                                  reward, from hanging) at rho = 0, 0.1, 0.2, the reward learnt;
                                  20 episodes, H-UCRL's budget (sebascuri/hucrl,
                                  exps/inverted_pendulum: TRAIN_EPISODES = 20), and the simulated
                                  roll-outs 4 s (a swing-up from hanging takes about 3.5 s)

The grid (`grid`, written before any run): every use, each at the values of its parameter:
beta (`model_beta`) 0.5, 1, 2 for the three optimistic uses, the information bonus's weight
(`model_information_weight`) at three values per task (`INFORMATION_WEIGHTS`), the mean, sample
and thompson uses as they are. On the sparse swing-up also H-UCRL's own comparison, with the
task's stated reward: the mean model and the hallucinated optimism ('*_stated').

Stages, per task; each writes under --out (default docs/results/exploration_uses/<task>):

``tune``    Tuning seeds (100, 101; never reported): each choice at each of its values, one
            program per choice (its values a traced sweep). The score is the model study's (the
            measure over the second half of the budget, mean over seeds); each choice's value is
            its best. Writes tuning.json (resumed choice by choice).
``heldout`` Held-out seeds (1000-1009; 1000-1019 for the swing-up): each choice at its value,
            through `gpguided reproduce`'s driver. Writes heldout/<choice>.npz and .json, and
            heldout/<choice>_visits.npz: the observations of the first `VISIT_UPDATES` updates'
            episodes, read from the run's final buffer (`ModelData.observations`).
``report``  heldout_table.json (per choice: seeds reaching the threshold, environment steps to it,
            the final measure, and P(improvement) over the mean model with its bootstrap
            interval, `gpguided_jax.stats`) and two figures: docs/figures/
            exploration_uses_<task>.png (the measure against environment steps) and
            exploration_uses_<task>_visits.png (where each choice's first episodes go: the
            states visited per update over the task's state space).

Usage (the tasks: `TASKS`):
  python experiments/exploration_uses_study.py tune --task pendulum-sparse-0.1
  python experiments/exploration_uses_study.py heldout --task pendulum-sparse-0.1
  python experiments/exploration_uses_study.py heldout --task pendulum-sparse-0.1 --only mean
  python experiments/exploration_uses_study.py tune --task pendulum-sparse-0.1 --only mean_stated
  python experiments/exploration_uses_study.py report --task pendulum-sparse-0.1
"""

from __future__ import annotations

import argparse
import os

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import model_study as MS  # noqa: E402
import numpy as np  # noqa: E402
import planning_study as PS  # noqa: E402

from gpguided_jax import checkpoints, model_based, stats, study, tasks  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402
from gpguided_jax import train as train_lib  # noqa: E402

ROOT = MS.ROOT
METHOD = MS.METHOD
SPARSE = tuple(f"pendulum-sparse-{c:g}" for c in tasks.SPARSE_PENDULUM_COSTS)
TASKS = ("mountaincar-continuous-learned", "swingup-learned", *SPARSE)
# the model study's task whose tuned settings each starts from
BASE_TASK = {"mountaincar-continuous-learned": "mountaincar-continuous",
             "swingup-learned": "swingup", **{t: "pendulum-v1" for t in SPARSE}}
# learning steps: the model study's for the car and the swing-up; H-UCRL's 20 episodes of the
# sparse swing-up (200 steps each); one more update evaluates the policy after the whole budget
BUDGETS = {"mountaincar-continuous-learned": MS.BUDGETS["mountaincar-continuous"],
           "swingup-learned": MS.BUDGETS["swingup"], **{t: 4000 for t in SPARSE}}
# what every run of a task sets over the model study's tuned settings: the reward learnt; on the
# sparse swing-up simulated roll-outs of 4 s (the model study's Pendulum-v1 plans 2 s ahead from
# anywhere on the circle; from hanging, a swing-up takes about 3.5 s)
FIXED = {"mountaincar-continuous-learned": {"model_reward": "learned"},
         "swingup-learned": {"model_reward": "learned"},
         **{t: {"model_reward": "learned", "model_horizon": 4.0} for t in SPARSE}}

BETAS = (0.5, 1.0, 2.0)  # beta of the optimistic uses (H-UCRL's default is 1)
# lambda of the information bonus, per task: lambda S = 0.1, 1 and 10 times the reward's scale
# per decision R, S the dynamics' outputs' summed variance per decision over 16 episodes of
# uniformly random actions (the scale of the bonus where the model knows nothing): the car
# S = 0.59 (decisions held 5 steps), R = 1 (the action cost of a decision, at most 0.5, and the
# goal's 100 over an episode's 200 decisions); the swing-up S = 0.22 (held 0.1 s), R = 30 (the
# spread of a decision's reward); the sparse swing-up S = 0.017 from hanging (0.09 over
# Pendulum-v1's own starts), R = 1 (its most a step): 0.05 taken for S
INFORMATION_WEIGHTS = {"mountaincar-continuous-learned": (0.2, 2.0, 20.0),
                       "swingup-learned": (10.0, 100.0, 1000.0),
                       **{t: (2.0, 20.0, 200.0) for t in SPARSE}}
VISIT_UPDATES = 5  # the first updates whose episodes the visits figure shows


def grid(task: str) -> dict[str, list[dict]]:
    """choice -> its configurations (settings over `overrides`' base), each one run of the tuning.
    A choice is a use of the uncertainty (`model_based.EXPLORATIONS`); on the sparse swing-up
    also H-UCRL's comparison with the task's stated reward ('mean_stated', 'optimistic_stated')."""
    values = {"optimistic": [{"model_beta": b} for b in BETAS],
              "optimistic_reward": [{"model_beta": b} for b in BETAS],
              "optimistic_joint": [{"model_beta": b} for b in BETAS],
              "information": [{"model_information_weight": w}
                              for w in INFORMATION_WEIGHTS[task]]}
    out = {use: [{"model_exploration": use, **v} for v in values.get(use, [{}])]
           for use in model_based.EXPLORATIONS}
    if task in SPARSE:
        stated = {"model_reward": "stated"}
        out["mean_stated"] = [{"model_exploration": "mean", **stated}]
        out["optimistic_stated"] = [{"model_exploration": "optimistic", **stated, **v}
                                    for v in values["optimistic"]]
    return out


def updates(task: str) -> int:
    """The updates of a run: the budget in episodes of one update, and one more."""
    episodes = MS.BASE[BASE_TASK[task]]["episodes_per_update"]
    return BUDGETS[task] // (episodes * config_lib.PRESETS[task]["episode_length"]) + 1


def overrides(task: str, settings: dict) -> dict:
    """A run's config overrides: the preset's own values of the fields gp_model's preset of
    `task` sets (its placeholders never enter a run), the model study's tuned configuration of
    the base task (`MS.overrides` of `PS.today`; on the sparse swing-up with the planning study's
    choice as well, `MS.planned`: Pendulum-v1's preset as it stands, from which the sparse task's
    own derives), the budget's updates, `FIXED` and `settings`."""
    base = BASE_TASK[task]
    tuned = {**PS.today(base), **(MS.planned(base) if task in SPARSE else {})}
    return {**study.preset_own(task, METHOD), **MS.overrides(base, tuned),
            "num_updates": updates(task), **FIXED[task], **settings}


def measure(task: str) -> tuple[str, float, str]:
    """(the record a run is measured by, the level to reach, its name): the model study's for
    the swing-up (the success rate, 0.9), else the return against the task's threshold."""
    base = BASE_TASK[task]
    if base in MS.MEASURES:
        return MS.MEASURES[base]
    return "eval_return", tasks.THRESHOLDS[config_lib.PRESETS[task]["env"]], "return"


def heldout_seeds(task: str) -> list[int]:
    return MS.heldout_seeds(BASE_TASK[task])


def _score(task: str, steps: np.ndarray):
    record, level, _ = measure(task)

    def score(records: dict) -> dict:
        ret = np.asarray(records[record], float)  # (seeds, updates)
        reach = study.steps_to(steps, ret, level, never=np.nan)
        return {"score": float(ret[:, ret.shape[1] // 2:].mean()), "final": float(ret[:, -1].mean()),
                "steps_to": [None if np.isnan(v) else int(v) for v in reach]}

    return score


def tune(task: str, out: str, only=None) -> None:
    """Each choice's configurations on the tuning seeds, one `sweep_stage` (its values differ in
    one traced setting), recorded choice by choice (`study.run_parts`); `only`: these choices
    first (the record keeps the grid's order)."""

    def run(choice, configs):
        full = [overrides(task, c) for c in configs]
        steps = study.env_steps(config_lib.preset(task, method=METHOD, **full[0]))
        results = study.sweep_stage(full, _score(task, steps), method=METHOD, preset=task,
                                    seeds=study.TUNING_SEEDS, progress=study.log)
        tried = [{"settings": c, **r} for c, r in zip(configs, results)]
        return {"tried": tried, "chosen": max(tried, key=study.by_score)["settings"]}

    header = {"task": task, "seeds": list(study.TUNING_SEEDS), "base": overrides(task, {}),
              "budget": BUDGETS[task], "measure": measure(task)[2]}
    everything = grid(task)
    path = os.path.join(out, "tuning.json")
    study.run_parts(path, header, {c: everything[c] for c in (only or everything)}, run,
                    settings_key="grid")
    rec = study.read_json(path)
    rec["runs"] = {c: rec["runs"][c] for c in everything if c in rec["runs"]}
    study.write_json(path, rec)


def chosen(task: str, out: str) -> dict[str, dict]:
    """choice -> the settings its tuning chose."""
    runs = study.read_json(os.path.join(out, "tuning.json"))["runs"]
    return {choice: runs[choice]["chosen"] for choice in grid(task) if choice in runs}


def preset_choice(task: str, out: str) -> dict:
    """The settings the task's preset holds (`model_based.method.PRESETS`): of every choice's
    tuned configuration, the one with the best score on the tuning seeds (the comparisons with
    the task's stated reward, '*_stated', are not candidates: the preset learns the reward);
    ValueError where the tuning has not run every one of them."""
    runs = study.read_json(os.path.join(out, "tuning.json"))["runs"]
    missing = [c for c in grid(task) if not c.endswith("_stated") and c not in runs]
    if missing:
        raise ValueError(f"{task}: the tuning has not run {missing}: no preset to choose yet")
    best = max((t for choice, r in runs.items() if not choice.endswith("_stated")
                for t in r["tried"] if t["settings"] == r["chosen"]), key=study.by_score)
    return best["settings"]


def visits(task: str, settings: dict, run_dir: str, updates_shown: int = VISIT_UPDATES,
           num_seeds: int | None = None):
    """The observations of the first `updates_shown` updates' episodes of a finished run whose
    final state `run_dir` kept (`study.run_method(keep_checkpoints=True)`): (obs (seeds, updates,
    n, obs_dim), kept (seeds, updates, n)), n the decisions of an update, read from the model's
    ring buffer (`ModelData.observations`; `kept` False for a decision after its episode's end
    or overwritten); `num_seeds`: the run's (default: the task's held-out seeds)."""
    cfg = config_lib.preset(task, method=METHOD, **overrides(task, settings))
    train = train_lib.make_train(cfg)
    template = jax.eval_shape(train.init, jax.random.key(0))
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(template)[0]]
    leaf = {k: f"leaf_{paths.index(f'.method_state.{k}')}" for k in ("observations", "valid", "count")}
    seeds = len(heldout_seeds(task)) if num_seeds is None else num_seeds
    with np.load(checkpoints.checkpoint_path(run_dir, METHOD)) as f:  # the seeds, then padding
        obs, valid, count = (f[leaf[k]][:seeds] for k in ("observations", "valid", "count"))
    capacity = obs.shape[1]
    n = cfg.episodes_per_update * (cfg.episode_length // train.program.hold)
    decision = np.arange(updates_shown * n).reshape(updates_shown, n)
    slots = decision % capacity
    kept = valid[:, slots] & (decision[None] >= (count[:, None, None] - capacity))
    return obs[:, slots], kept


def heldout(task: str, out: str, only) -> None:
    seeds = heldout_seeds(task)
    picks = chosen(task, out)
    for choice in only:
        settings = picks[choice]
        meta = {"seeds": seeds, "settings": settings}
        path = os.path.join(out, "heldout", choice)
        if study.finished(path + ".json", **meta):
            study.log(f"[{task} {choice}] done with these seeds and settings: {path}.json")
            continue
        run_dir = os.path.join(out, "runs", choice)
        run = study.run_method(task, METHOD, seeds, run_dir, overrides(task, settings),
                               chunk_size=1, keep_checkpoints=True)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        obs, kept = visits(task, settings, run_dir)
        np.savez(path + "_visits.npz", obs=obs, kept=kept)
        checkpoints.remove_checkpoints(run_dir, METHOD)
        np.savez(path + ".npz", steps=run.env_steps, measure=run.records[measure(task)[0]],
                 model_error=run.records["model_error"],
                 model_reward_error=run.records["model_reward_error"],
                 model_return=run.records["model_return"])
        study.write_json(path + ".json", {**meta, "wall_s": run.wall_s})


# The state-space plane each task's visits are drawn on: (the observation's two coordinates,
# their names, their ranges, the region the reward is paid in).
def _pendulum_v1_plane(obs):
    return np.arctan2(obs[..., 1], obs[..., 0]), obs[..., 2]


PLANES = {
    "mountaincar-continuous-learned": (lambda o: (o[..., 0], o[..., 1]),
                                       ("position", "velocity"), ((-1.2, 0.6), (-0.07, 0.07)),
                                       ((0.45, 0.6), (-0.07, 0.07))),
    "swingup-learned": (lambda o: (o[..., 0], o[..., 1]), ("phi (rad, upright pi)", "omega (rad/s)"),
                        ((0.0, 2 * np.pi), (-12.0, 12.0)), ((np.pi - 0.3, np.pi + 0.3), (-1.0, 1.0))),
    **{t: (_pendulum_v1_plane, ("theta (rad, upright 0)", "theta_dot (rad/s)"),
           ((-np.pi, np.pi), (-8.0, 8.0)), ((-np.arccos(0.95), np.arccos(0.95)), (-0.5, 0.5)))
       for t in SPARSE},
}


def _visits_figure(task: str, out: str, choices: list[str]) -> str:
    plane, names, limits, goal = PLANES[task]
    cols = 3
    rows = -(-len(choices) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    colours = plt.cm.viridis(np.linspace(0, 1, VISIT_UPDATES))
    for ax, choice in zip(axes.flat, choices):
        with np.load(os.path.join(out, "heldout", choice + "_visits.npz")) as f:
            obs, kept = f["obs"], f["kept"]
        for u in range(obs.shape[1]):
            x, y = plane(obs[:, u][kept[:, u]])
            ax.scatter(x, y, s=2, color=colours[u], alpha=0.5, label=f"update {u + 1}")
        ax.add_patch(plt.Rectangle((goal[0][0], goal[1][0]), goal[0][1] - goal[0][0],
                                   goal[1][1] - goal[1][0], fill=False, ec="r", lw=1))
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_title(choice, fontsize=9)
        ax.set_xlabel(names[0], fontsize=8)
        ax.set_ylabel(names[1], fontsize=8)
    for ax in list(axes.flat)[len(choices):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=6, markerscale=4)
    fig.suptitle(f"{task}: the states the first {VISIT_UPDATES} updates' episodes visit, every "
                 "held-out seed (red: where the reward is paid)", fontsize=9)
    fig.tight_layout()
    figure = os.path.join(ROOT, "docs", "figures", f"exploration_uses_{task}_visits.png")
    fig.savefig(figure, dpi=100)
    plt.close(fig)
    return figure


def found_reward(task: str, obs, kept) -> np.ndarray:
    """(seeds, updates) whether an update's episode found where the reward is paid: it visited
    the region `PLANES` marks, or it ended before its last decision (the car's only end is its
    goal, reached after the last decision the buffer keeps). An episode of which the buffer
    keeps no decision (overwritten: `known_episodes`) has not found it."""
    plane, _, _, goal = PLANES[task]
    x, y = plane(obs)
    inside = (x >= goal[0][0]) & (x <= goal[0][1]) & (y >= goal[1][0]) & (y <= goal[1][1])
    ended = known_episodes(kept) & (kept.sum(-1) < kept.shape[-1])
    return np.any(inside & kept, axis=-1) | ended


def known_episodes(kept) -> np.ndarray:
    """(seeds, updates) whether the run's final buffer keeps any decision of an update's episode
    (a ring buffer smaller than the run's decisions has overwritten the first ones)."""
    return np.asarray(kept).any(-1)


def report(task: str, out: str) -> None:
    record, threshold, measure_name = measure(task)
    rows, curves, seeds = [], {}, None
    picks = chosen(task, out)
    for choice in grid(task):
        p = os.path.join(out, "heldout", choice)
        if not os.path.exists(p + ".npz"):
            continue
        with np.load(p + ".npz") as f:
            curves[choice] = (f["steps"], np.asarray(f["measure"], float))
            # what the planner saw: each seed's largest simulated return (the objective's mean
            # over the particles after an update's optimisation), its median over seeds
            simulated = float(np.median(np.nanmax(np.asarray(f["model_return"], float), 1)))
        meta = study.read_json(p + ".json")
        seeds = meta["seeds"]
        rows.append({**MS._row(choice, *curves[choice], threshold, meta["wall_s"], seeds),
                     "settings": picks[choice], "model_return_max": simulated})
        if os.path.exists(p + "_visits.npz"):
            # whether the first update's episode (the exploratory one, before any planning: the
            # same for every use) found the reward, and whether a later one did
            with np.load(p + "_visits.npz") as f:
                found = found_reward(task, f["obs"], f["kept"])
                known = known_episodes(f["kept"])
            reached = np.isfinite(study.steps_to(*curves[choice], threshold, never=np.nan))
            if known[:, 0].all():
                rows[-1].update(found_first=int(found[:, 0].sum()),
                                found_later=int((~found[:, 0] & found[:, 1:].any(1)).sum()),
                                reaching_not_found_first=int((reached & ~found[:, 0]).sum()))
            else:  # the first episodes overwritten: whether any later one found it
                rows[-1].update(found_after_first=int(found[:, 1:].any(1).sum()))
    # each choice against the mean model (with the same reward): P(choice > mean) of the final
    # measure over seeds, and its bootstrap interval
    for row in rows:
        mean_key = "mean_stated" if row["method"].endswith("_stated") else "mean"
        if mean_key in curves and row["method"] != mean_key:
            x, y = curves[row["method"]][1][:, -1], curves[mean_key][1][:, -1]
            row["p_improvement_over_mean"] = stats.probability_of_improvement(x, y)
            row["p_improvement_ci"] = list(stats.probability_of_improvement_ci(x, y))
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, (steps, ret) in curves.items():
        study.plot_band(ax, steps, ret, label=name, ls=":" if name.endswith("_stated") else "-")
    ax.axhline(threshold, color="k", ls="--", lw=0.8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"{measure_name} of the deterministic policy")
    ax.set_title(f"{task}: held-out seeds (mean, 95% t-band)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    figure = os.path.join(ROOT, "docs", "figures", f"exploration_uses_{task}.png")
    fig.savefig(figure, dpi=110)
    plt.close(fig)
    shown = [c for c in curves if os.path.exists(os.path.join(out, "heldout", c + "_visits.npz"))]
    visits_figure = _visits_figure(task, out, shown) if shown else None
    study.write_json(os.path.join(out, "heldout_table.json"), {
        "task": task, "threshold": threshold, "measure": measure_name, "seeds": seeds,
        "budget": BUDGETS[task], "visit_updates": VISIT_UPDATES, "rows": rows})
    study.log(f"wrote {figure}, {visits_figure} and {out}/heldout_table.json")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stage", choices=("tune", "heldout", "report"))
    p.add_argument("--task", choices=TASKS, default="pendulum-sparse-0.1")
    p.add_argument("--out", default=None)
    p.add_argument("--only", nargs="+", default=None,
                   help="tune, heldout: these choices (default: every one of the task's grid)")
    args = p.parse_args(argv)
    unknown = sorted(set(args.only or ()) - set(grid(args.task)))
    if unknown:
        p.error(f"--only: {unknown} not in the grid of {args.task}: {list(grid(args.task))}")
    out = study.set_up(args.out or os.path.join(ROOT, "docs", "results", "exploration_uses",
                                                args.task))
    if args.stage == "tune":
        tune(args.task, out, args.only)
    elif args.stage == "heldout":
        heldout(args.task, out, args.only or list(grid(args.task)))
    else:
        report(args.task, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
