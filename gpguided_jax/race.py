"""The race (`gpguided race`): gp_model at its preset against brax's SAC on the same task and
seeds, on one machine, by the wall time to the task's threshold as a user pays it.

Each seed of each method runs in a fresh process of its own (`python -m gpguided_jax.race`), so
that the time holds the interpreter's start, JAX's import and every compilation. The parent takes
the launch time (`time.time()`) just before it starts the child and passes it in the environment
(`LAUNCH_VARIABLE`); the child appends one JSON line per event to its events file, each with its
time in seconds since that launch: its own start (the first statement of this module), every
evaluation of the deterministic policy (with its environment steps and return) and its end.

* gp_model runs `gpguided reproduce --preset <task> --methods gp_model --seeds 1` (the same
  driver, `reproduce.reproduce`) one update per compiled chunk; an evaluation's time is that of
  the end of the update whose record holds it (`reproduce.run_method`'s `on_chunk`), so it holds
  that update's own step too: an upper bound, by at most one update.
* SAC runs `gpguided baseline sac --preset <task> --seeds 1 --steps <sac_steps>`
  (`baselines.train_on_task` with the preset's tuned settings); an evaluation's time is that of
  brax's progress call, right after the evaluation. brax's first evaluation, of the initial
  policy at 0 steps, does not count (`baselines.after_initial_evaluation`), as in the tables.

A seed's wall time to the threshold is that of its first counted evaluation at or above the
threshold (`time_to_threshold`); the median over seeds counts a seed that never reaches it as
never (`median_or_none`: None when half the seeds or more do not reach it).

The compile cache: 'cold' runs with an empty cache directory of its own (as a new user's first
run: it compiles everything and writes the cache), 'warm' runs again with the directory the cold
run filled (the cold run is made, unreported, when only 'warm' is asked for). Each (method, seed)
has its own directory, removed after its runs; the seeds run one after another, the two methods
of a seed next to each other, so that a change of the machine's load falls on both.
"""

from __future__ import annotations

import time

_CHILD_START = time.time()  # as early as this process can take it (see `_child_main`)

import json  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from typing import Callable, Sequence  # noqa: E402

LAUNCH_VARIABLE = "GPGUIDED_RACE_LAUNCH"
METHODS = ("gp_model", "sac")
CACHE_STATES = ("cold", "warm")
SAC_EVALS = 26  # `gpguided baseline`'s default
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STANDARD = os.path.join(ROOT, "docs", "results", "standard")


class RaceError(ValueError):
    """A race that cannot run (a task without SAC or gp_model, a budget brax refuses), or a child
    process that failed; its message is one line."""


# ------------------------------------------------------------------------- pure parts: the measure


def time_to_threshold(times: Sequence[float], values: Sequence[float],
                      threshold: float) -> float | None:
    """The time of the first evaluation at or above `threshold`.

    Args:
      times: (E,) seconds at which each evaluation was known, increasing.
      values: (E,) the evaluations (the deterministic policy's return).
      threshold: the level to reach.

    Returns:
      That evaluation's time, or None if no evaluation reaches `threshold`.
    """
    i = first_reaching(values, threshold)
    return None if i is None else float(times[i])


def first_reaching(values: Sequence[float], threshold: float) -> int | None:
    """The index of the first of `values` at or above `threshold` (None: none is)."""
    if len(values) == 0:
        return None
    for i, v in enumerate(values):
        if float(v) >= threshold:
            return i
    return None


def median_or_none(xs: Sequence[float | None]) -> float | None:
    """The median over seeds, a seed that never reached the threshold (None) counting as never:
    None when the median itself is never (half the seeds or more never reach it; a seed that
    never reaches sorts after every time), or when there are no seeds."""
    if not xs:
        return None
    ordered = sorted(xs, key=lambda x: (x is None, 0.0 if x is None else x))
    n = len(ordered)
    middle = ordered[(n - 1) // 2: n // 2 + 1]
    if any(x is None for x in middle):
        return None
    return float(sum(middle) / len(middle))


def summarise_run(events: list[dict], threshold: float, *, skip_initial: bool) -> dict:
    """One child's events (`_child_main`'s lines) as the race reports a run.

    Args:
      events: the child's events, in order.
      threshold: the level to reach.
      skip_initial: leave out the first evaluation (brax's, of the initial policy at 0 steps).

    Returns:
      wall_to_threshold_s (None: never), env_steps_to_threshold (None: never), total_wall_s (the
      last end or exit event's time: the process's exit as `run_child` saw it; None without
      one), start_s (the child's first statement after launch)
      and the counted evaluations [{t, env_steps, value}].
    """
    evals = [e for e in events if e.get("event") == "evaluation"]
    if skip_initial:
        evals = evals[1:]
    values = [e["value"] for e in evals]
    i = first_reaching(values, threshold)
    end = [e["t"] for e in events if e.get("event") in ("end", "exit")]
    start = [e["t"] for e in events if e.get("event") == "start"]
    return dict(wall_to_threshold_s=None if i is None else float(evals[i]["t"]),
                env_steps_to_threshold=None if i is None else int(evals[i]["env_steps"]),
                total_wall_s=float(end[-1]) if end else None,
                start_s=float(start[0]) if start else None,
                evaluations=[{k: e[k] for k in ("t", "env_steps", "value")} for e in evals])


def summarise_cache_state(runs: list[dict]) -> dict:
    """The median over seeds of one method under one cache state (`median_or_none`)."""
    return dict(seeds_reaching=sum(r["wall_to_threshold_s"] is not None for r in runs),
                median_wall_to_threshold_s=median_or_none([r["wall_to_threshold_s"] for r in runs]),
                median_env_steps_to_threshold=median_or_none(
                    [r["env_steps_to_threshold"] for r in runs]),
                median_total_wall_s=median_or_none([r["total_wall_s"] for r in runs]),
                runs=runs)


# ------------------------------------------------------------------------------------ the plan


def reported_sac_steps(preset: str, root: str = STANDARD) -> int | None:
    """SAC's median environment steps to the threshold on the preset's task in the standard
    tasks' held-out table (docs/results/standard/<preset>/heldout_table.json), or None where
    there is none or SAC's median seed did not reach it."""
    path = os.path.join(root, preset, "heldout_table.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        rows = json.load(f).get("rows", [])
    median = next((r.get("steps_to_threshold_median") for r in rows if r.get("method") == "sac"),
                  None)
    return None if median is None else int(round(median))


def plan(preset: str, *, seeds: Sequence[int], sac_steps: int | None = None,
         sac_evals: int = SAC_EVALS, gp_overrides: dict | None = None,
         sac_overrides: dict | None = None, threshold: float | None = None) -> dict:
    """What `race` will run, checked without compiling anything.

    Args:
      preset: a standard task's preset (`config.PRESETS`) on which both gp_model and brax's SAC
        run.
      seeds: the seeds, each method's run of a seed in a process of its own.
      sac_steps: SAC's budget of environment steps (default: SAC's median steps to the
        threshold in the held-out table, `reported_sac_steps`, else the preset's budget, as
        `gpguided baseline` has it).
      sac_evals: SAC's evaluations, the initial policy's included.
      gp_overrides: config fields over gp_model's preset (as `gpguided reproduce --set`).
      sac_overrides: trainer arguments over SAC's tuned settings (as `gpguided baseline --set`).
      threshold: another level than the task's.

    Raises:
      RaceError: the race cannot run as asked.
    """
    from gpguided_jax import baselines
    from gpguided_jax import config as config_lib

    if not seeds:
        raise RaceError("no seeds to race on")
    if preset not in config_lib.PRESETS:
        raise RaceError(f"unknown preset {preset!r}; choose from {sorted(config_lib.PRESETS)}")
    source = "given"
    if sac_steps is None:
        sac_steps, source = reported_sac_steps(preset), "the held-out table's median"
    try:
        # the fields checked (the child runs float64, which this process need not switch on)
        config_lib.preset(preset, method="gp_model", dtype="float32", **(gp_overrides or {}))
        sac = baselines.plan_preset("sac", preset, num_timesteps=sac_steps, num_evals=sac_evals,
                                    overrides=sac_overrides)
    except baselines.BudgetError as e:
        raise RaceError(f"{e} (--sac-steps {e.smallest} or more)") from None
    except (TypeError, ValueError) as e:
        raise RaceError(str(e)) from None
    if sac_steps is None:
        source = "the preset's budget"
    level = sac["threshold"] if threshold is None else float(threshold)
    if level is None:
        raise RaceError(f"{sac['env']} states no threshold; give --threshold")
    return dict(preset=preset, env=sac["env"], threshold=float(level),
                seeds=[int(s) for s in seeds], sac_steps=int(sac["budget"]), sac_steps_source=source,
                sac_evals=int(sac_evals), sac_note=sac["note"], gp_overrides=dict(gp_overrides or {}),
                sac_overrides=dict(sac_overrides or {}))


# --------------------------------------------------------------------------- the parent's side


def child_command(method: str, plan_: dict, seed: int, cache: str, run_dir: str) -> list[str]:
    """The child's command line: this module run as a program, with the run as JSON."""
    run = dict(method=method, preset=plan_["preset"], seed=int(seed), cache=cache,
               run_dir=run_dir, sac_steps=plan_["sac_steps"], sac_evals=plan_["sac_evals"],
               gp_overrides=plan_["gp_overrides"], sac_overrides=plan_["sac_overrides"])
    return [sys.executable, "-m", "gpguided_jax.race", json.dumps(run)]


def run_child(method: str, plan_: dict, seed: int, cache: str, run_dir: str) -> list[dict]:
    """Runs one seed of one method in a fresh process and returns its events (`_child_main`),
    and last the process's exit as the parent saw it. Its output goes to run_dir/log.txt.

    Raises:
      RaceError: the child failed (its last line of output in the message).
    """
    os.makedirs(run_dir, exist_ok=True)
    events_path = os.path.join(run_dir, "events.jsonl")
    if os.path.exists(events_path):
        os.remove(events_path)
    log_path = os.path.join(run_dir, "log.txt")
    with open(log_path, "w") as log:
        launch = time.time()
        proc = subprocess.run(child_command(method, plan_, seed, cache, run_dir),
                              env={**os.environ, LAUNCH_VARIABLE: repr(launch)},
                              stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        exit_s = time.time() - launch
    if proc.returncode != 0:
        with open(log_path) as f:
            lines = [line.strip() for line in f if line.strip()]
        last = lines[-1] if lines else "no output"
        raise RaceError(f"{method} seed {seed} ({cache}) exited with status {proc.returncode}: "
                        f"{last} (the whole log: {log_path})")
    with open(events_path) as f:
        events = [json.loads(line) for line in f if line.strip()]
    return events + [{"event": "exit", "t": exit_s}]


def race(plan_: dict, out_dir: str, *, cache_states: Sequence[str] = CACHE_STATES,
         progress: Callable[[str], None] | None = None) -> dict:
    """Runs the race of `plan_` (`plan`) and writes out_dir/race.json.

    Returns:
      The report: the plan's fields, `cache` and, per method and cache state, the medians over
      seeds (`summarise_cache_state`) and each seed's run (`summarise_run`).
    """
    for state in cache_states:
        if state not in CACHE_STATES:
            raise RaceError(f"unknown cache state {state!r}; choose from {', '.join(CACHE_STATES)}")
    say = progress or (lambda line: None)
    runs = {m: {c: [] for c in cache_states} for m in METHODS}
    # the cold run fills the cache the warm run loads: it runs even when only 'warm' is reported
    states = ["cold"] + (["warm"] if "warm" in cache_states else [])
    for seed in plan_["seeds"]:
        for method in METHODS:
            cache_dir = tempfile.mkdtemp(prefix=f"gpguided-race-{method}-")
            try:
                for state in states:
                    run_dir = os.path.join(out_dir, "runs", f"{method}_{state}_{seed}")
                    events = run_child(method, plan_, seed, cache_dir, run_dir)
                    run = {"seed": int(seed), **summarise_run(events, plan_["threshold"],
                                                              skip_initial=method == "sac")}
                    reached = run["wall_to_threshold_s"]
                    say(f"[race] {method} seed {seed} ({state} cache): "
                        + (f"threshold at {reached:.1f} s, {run['env_steps_to_threshold']} steps"
                           if reached is not None else "threshold not reached")
                        + f"; {run['total_wall_s']:.1f} s in all")
                    if state in cache_states:
                        runs[method][state].append(run)
            finally:
                shutil.rmtree(cache_dir, ignore_errors=True)
    report = {**{k: plan_[k] for k in ("preset", "env", "threshold", "seeds", "sac_steps",
                                       "sac_steps_source", "sac_evals", "gp_overrides",
                                       "sac_overrides")},
              "cache": list(cache_states),
              "methods": {m: {c: summarise_cache_state(runs[m][c]) for c in cache_states}
                          for m in METHODS}}
    os.makedirs(out_dir, exist_ok=True)
    from gpguided_jax import checkpoints

    checkpoints.atomic_write_text(os.path.join(out_dir, "race.json"), json.dumps(report, indent=2))
    return report


def table(report: dict) -> str:
    """The race's medians as a Markdown table."""
    def fmt(x, spec):
        return "never" if x is None else format(x, spec)

    n = len(report["seeds"])
    lines = ["| method | cache | seeds reaching | wall time to threshold [s] | env steps to "
             "threshold | total wall time [s] |", "|---|---|---|---|---|---|"]
    for method, states in report["methods"].items():
        for state, s in states.items():
            lines.append(f"| {method} | {state} | {s['seeds_reaching']}/{n} | "
                         f"{fmt(s['median_wall_to_threshold_s'], '.1f')} | "
                         f"{fmt(s['median_env_steps_to_threshold'], '.0f')} | "
                         f"{fmt(s['median_total_wall_s'], '.1f')} |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- the child's side


def _child_main(run: dict) -> int:
    """One seed of one method, as `gpguided reproduce` or `gpguided baseline sac` runs it, its
    events appended to run_dir/events.jsonl as they happen (times since the parent's launch, or
    since this process's start without one)."""
    from gpguided_jax import runtime

    runtime.single_threaded_lapack()  # before anything loads LAPACK, as `cli.main` does
    launch = float(os.environ.get(LAUNCH_VARIABLE, _CHILD_START))
    events = open(os.path.join(run["run_dir"], "events.jsonl"), "a")

    def emit(event: str, **fields) -> None:
        events.write(json.dumps({"event": event, "t": time.time() - launch, **fields}) + "\n")
        events.flush()

    events.write(json.dumps({"event": "start", "t": _CHILD_START - launch}) + "\n")
    events.flush()
    say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    runtime.set_cpu_devices(None)
    if run["method"] == "gp_model":
        runtime.set_precision("float64")
        runtime.set_compile_cache(run["cache"])
        from gpguided_jax import config as config_lib
        from gpguided_jax import reproduce, summaries

        cfg = config_lib.preset(run["preset"], method="gp_model", dtype="float64",
                                **run["gp_overrides"])
        # the axis of the evaluation records (`study.env_steps`, without importing the studies)
        axis = summaries.env_steps_axis(summaries.task_budget(cfg), cfg.num_updates)

        def on_chunk(method, updates_done, chunk):
            values = chunk["eval_return"][0]  # the one seed's
            first = updates_done - len(values)
            for u, v in enumerate(values, start=first):
                emit("evaluation", env_steps=int(axis[u]), value=float(v))

        reproduce.reproduce(run["preset"], [run["seed"]], ["gp_model"],
                            os.path.join(run["run_dir"], "out"), dtype="float64", chunk_size=1,
                            overrides=run["gp_overrides"], progress=say, on_chunk=on_chunk)
    elif run["method"] == "sac":
        runtime.set_compile_cache(run["cache"])
        from gpguided_jax import baselines

        baselines.run_preset("sac", run["preset"], [run["seed"]],
                             num_timesteps=run["sac_steps"], num_evals=run["sac_evals"],
                             overrides=run["sac_overrides"], progress=say,
                             on_evaluation=lambda step, ret: emit("evaluation", env_steps=step,
                                                                  value=ret))
    else:
        raise ValueError(f"unknown method {run['method']!r}; choose from {', '.join(METHODS)}")
    runtime.report_compile_cache()
    emit("end")
    events.close()
    return 0


if __name__ == "__main__":
    sys.exit(_child_main(json.loads(sys.argv[1])))
