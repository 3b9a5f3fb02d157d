"""Summaries of finished runs: final performance, failing seeds, probability of improvement.

For records of shape (seeds, updates) per method (a `reproduce` run's results.npz, a sweep's
runs), NumPy, not traced:

* `final_performance`: per seed, the mean reward per step over the last 10% of updates;
* `summarise`: per method, initial and final performance (mean with its 95% t-interval, IQM with
  its stratified-bootstrap interval), updates to 90% of the way (`updates_to_90pct`), and the
  seeds that failed, by cause (`failing_seeds`, `FAILURE_CAUSES`; the level of doing nothing is
  `zero_torque_reward`);
* `compare`: the probability of improvement P(X > Y) of the pairs the methods declare
  (`methods.comparisons`; rliable);
* `write_csv`, `summary_markdown`, `comparisons_markdown`: summary.csv / comparisons.csv and
  their Markdown tables.
"""

from __future__ import annotations

import csv
import functools
import io
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import checkpoints, methods, pendulum, tasks
from gpguided_jax import config as config_lib
from gpguided_jax import stats as stats_lib

FAILURE_CAUSES = ("nonfinite_grad", "gp_guard", "std_at_bound", "below_zero_torque", "nan_record")


def final_performance(mean_reward: np.ndarray) -> np.ndarray:
    """Per seed: the mean reward per step over the last 10% of updates. (..., updates) -> (...)."""
    tail = max(1, int(round(0.1 * mean_reward.shape[-1])))
    return mean_reward[..., -tail:].mean(axis=-1)


def updates_to_90pct(curves: np.ndarray) -> np.ndarray:
    """Per seed: the first update at which a 10-update moving average has covered 90% of the way
    from its start to the seed's final performance (num_updates if never)."""
    n_updates = curves.shape[-1]
    final = final_performance(curves)
    w = min(10, n_updates)
    smooth = np.stack([np.convolve(c, np.ones(w) / w, mode="valid") for c in curves])
    start = smooth[:, :1]
    target = start + 0.9 * (final[:, None] - start)
    improving = final[:, None] >= start
    reached = np.where(improving, smooth >= target, smooth <= target)
    return np.where(reached.any(axis=1), reached.argmax(axis=1) + w, n_updates)


def zero_torque_reward(cfg: config_lib.TrainConfig, num_episodes: int = 2000, seed: int = 12345) -> float:
    """Mean reward per step of the zero-torque policy on the preset's task (its start states and
    episode length): the level below which a learned policy is worse than doing nothing."""
    keys = jax.random.split(jax.random.PRNGKey(seed), num_episodes)
    return float(jnp.mean(_zero_torque_episode_means(keys, cfg.pendulum, cfg.episode_length)))


@functools.partial(jax.jit, static_argnums=2)
def _zero_torque_episode_means(keys, params: pendulum.PendulumParams, num_steps: int):
    """Per key, one zero-torque episode's mean reward per step. Compiled once per episode length,
    dtype and number of keys (the pendulum's parameters are traced): a process that summarises
    several runs, or the tests, do not compile it again for each."""
    def episode(key):
        traj = pendulum.rollout(key, params, lambda k, s: jnp.zeros((), s.dtype), num_steps)
        return jnp.mean(traj.rewards)

    return jax.vmap(episode)(keys)


def holds_swing_up(cfg: config_lib.TrainConfig) -> bool:
    """Whether the task's episodes last long enough to hold a swing-up (`success_hold_time`):
    then its summary has the success columns (`summarise(..., success=True)`). Only the
    pendulum's: another task's success is its return threshold (`TaskBudget`)."""
    if cfg.env != "pendulum":
        return False
    return cfg.episode_length * float(np.asarray(cfg.pendulum.dt)) >= cfg.success_hold_time


class TaskBudget(NamedTuple):
    """What turns a run's updates into environment steps, and the task's return threshold.

    Attributes:
      steps_per_update: environment steps of one update's episodes (episodes x length).
      fit_steps: environment steps of the GP methods' hyperparameter-fit episodes, spent before
        the first update (0 for REINFORCE).
      threshold: the episode return at which the task counts as solved (None: none).
      return_record: the record of the policy's return: 'eval_return' (the deterministic policy,
        when the config evaluates it) or 'mean_return' (the exploring episodes, when it does not).
    """

    steps_per_update: int
    fit_steps: int
    threshold: float | None
    return_record: str = "eval_return"


def task_budget(cfg: config_lib.TrainConfig) -> TaskBudget:
    """`TaskBudget` of a method's config (its environment's threshold: `tasks.THRESHOLDS`)."""
    fit = cfg.hyperfit_episodes * cfg.episode_length if cfg.uses_gp else 0
    return TaskBudget(cfg.episodes_per_update * cfg.episode_length, fit,
                      tasks.make_task(cfg.env).threshold,
                      "eval_return" if cfg.eval_episodes > 0 else "mean_return")


def env_steps_axis(budget: TaskBudget, num_updates: int) -> np.ndarray:
    """The environment steps spent (the prior's fit included) when each of `num_updates` records
    of `budget.return_record` was taken: (num_updates,).

    Record u of eval_return evaluates the policy before update u's step, after u updates'
    episodes (so record 0 is the policy before learning, at `fit_steps`); record u of
    mean_return is that of update u's own episodes, which are done after u + 1 updates'. Every
    per-update record of a run shares this axis with its return record."""
    done = np.arange(num_updates) + (budget.return_record == "mean_return")
    return budget.fit_steps + budget.steps_per_update * done


def steps_to_threshold(returns: np.ndarray, budget: TaskBudget) -> np.ndarray:
    """Per seed: the environment steps spent (fit included) when the policy's return (record
    `budget.return_record`) first reaches the threshold; NaN where it never does (or there is no
    threshold). (seeds, updates) -> (seeds,).

    Record u of eval_return evaluates the policy before update u's step, after u updates' episodes;
    record u of mean_return is that of update u's own episodes, after u + 1 updates' episodes."""
    returns = np.asarray(returns, float)
    if budget.threshold is None:
        return np.full(returns.shape[0], np.nan)
    reached = returns >= budget.threshold
    steps = env_steps_axis(budget, returns.shape[-1])
    return np.where(reached.any(axis=-1), steps[reached.argmax(axis=-1)], np.nan)


def failing_seeds(records: dict, zero_torque: float | None) -> dict[str, np.ndarray]:
    """Per cause, a (seeds,) bool array of the seeds that failed (records of one method):

    * nonfinite_grad: any gradient estimate was not finite;
    * gp_guard: the GP health check rejected any episode's update;
    * std_at_bound: the learnable sigma was at min_std or max_std after any update;
    * below_zero_torque: the final performance is below the zero-torque policy's (never, when
      `zero_torque` is None: the level of doing nothing is only computed for the pendulum);
    * nan_record: any record is NaN;
    * any: any of these.
    """
    none = np.zeros(np.shape(records["mean_reward"])[:-1], bool)

    def fired(field):  # a method that does not keep the record never fails by it
        return np.any(np.asarray(records[field]) > 0, axis=-1) if field in records else none

    out = {
        "nonfinite_grad": fired("nonfinite_grad"),
        "gp_guard": fired("gp_guard"),
        "std_at_bound": fired("std_at_bound"),
        "below_zero_torque": (final_performance(records["mean_reward"]) < zero_torque
                              if zero_torque is not None else none),
        "nan_record": np.any(np.stack([np.isnan(np.asarray(records[k], float)).any(-1)
                                       for k in records]), axis=0),
    }
    out["any"] = np.any(np.stack(list(out.values())), axis=0)
    return out


def summarise(records_by_method: dict[str, dict], zero_torque: float | None = None,
              reps: int = stats_lib.DEFAULT_REPS, success: bool = False,
              budgets: dict[str, TaskBudget] | None = None) -> list[dict]:
    """One row per method: initial and final performance (mean reward per step over the first and
    last 10% of updates), the final's mean with its 95% t-interval and its IQM with the 95%
    stratified-bootstrap interval over seeds, the mean updates to 90%, and the failing seeds.

    Args:
      records_by_method: method -> dict field -> (seeds, updates); at least mean_reward (the
        failure counts need the other `UpdateRecord` fields too).
      zero_torque: the zero-torque policy's reward per step (for `below_zero_torque`); None skips
        the failure counts, "no-level" counts every cause but that one.
      success: add the swing-up columns (records success_rate and eval_success_rate): the final
        success rate (last 10% of updates) of the exploring episodes and of the deterministic
        controller c(s), mean over seeds, and the seeds whose final deterministic success rate is
        at least 0.9.
      budgets: method -> `TaskBudget`: add the task's columns (record eval_return): the final
        undiscounted return of the deterministic policy (last 10% of updates per seed), its IQM
        with the stratified-bootstrap interval over seeds, the environment steps per seed to the
        threshold (median over the seeds that reach it) and how many seeds reach it.
    """
    rows = []
    for method, rec in records_by_method.items():
        curves = np.asarray(rec["mean_reward"], float)
        final = final_performance(curves)
        n = len(final)
        mean, half = stats_lib.t_interval(final)
        lo, hi = stats_lib.bootstrap_ci(final, reps=reps) if n > 1 else (np.nan, np.nan)
        tail = max(1, int(round(0.1 * curves.shape[-1])))
        row = dict(
            method=method,
            seeds=n,
            initial_mean=float(curves[:, :tail].mean()),
            final_mean=float(mean),
            ci95_low=float(mean - half),
            ci95_high=float(mean + half),
            final_iqm=stats_lib.iqm(final),
            iqm_ci95_low=lo,
            iqm_ci95_high=hi,
            updates_to_90pct=float(np.mean(updates_to_90pct(curves))),
        )
        if success:
            explore = final_performance(np.asarray(rec["success_rate"], float))
            greedy = final_performance(np.asarray(rec["eval_success_rate"], float))
            row["final_success_rate"] = float(explore.mean())
            row["final_eval_success_rate"] = float(greedy.mean())
            row["seeds_eval_success_90"] = int(np.sum(greedy >= 0.9))
        if budgets is not None and method in budgets:
            returns = np.asarray(rec[budgets[method].return_record], float)
            ret = final_performance(returns)
            rlo, rhi = stats_lib.bootstrap_ci(ret, reps=reps) if n > 1 else (np.nan, np.nan)
            reach = steps_to_threshold(returns, budgets[method])
            row.update(return_of=budgets[method].return_record,
                       final_return_iqm=stats_lib.iqm(ret), return_ci95_low=rlo, return_ci95_high=rhi,
                       final_return_mean=float(ret.mean()),
                       steps_to_threshold_median=float(np.median(reach[np.isfinite(reach)]))
                       if np.isfinite(reach).any() else np.nan,
                       seeds_reaching_threshold=int(np.isfinite(reach).sum()),
                       env_steps=budgets[method].fit_steps
                       + budgets[method].steps_per_update * curves.shape[-1])
        if zero_torque is not None:
            level = None if zero_torque == "no-level" else zero_torque
            fails = failing_seeds(rec, level)
            row["failing_seeds"] = int(fails["any"].sum())
            row.update({f"fail_{c}": int(fails[c].sum()) for c in FAILURE_CAUSES})
            row["zero_torque_reward"] = level if level is not None else np.nan
        rows.append(row)
    return rows


def compare(records_by_method: dict[str, dict], pairs=None,
            reps: int = stats_lib.DEFAULT_REPS) -> list[dict]:
    """Probability of improvement P(X > Y) of final performance, with its 95% bootstrap interval,
    for the pairs whose methods were both run (default: the pairs the methods declare,
    `methods.comparisons`)."""
    if pairs is None:
        pairs = methods.comparisons(records_by_method)
    rows = []
    for x, y in pairs:
        if x in records_by_method and y in records_by_method:
            fx = final_performance(np.asarray(records_by_method[x]["mean_reward"], float))
            fy = final_performance(np.asarray(records_by_method[y]["mean_reward"], float))
            lo, hi = stats_lib.probability_of_improvement_ci(fx, fy, reps=reps)
            rows.append(dict(x=x, y=y, p_improvement=stats_lib.probability_of_improvement(fx, fy),
                             ci95_low=lo, ci95_high=hi))
    return rows


def write_csv(rows: list[dict], path: str) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    checkpoints.atomic_write_text(path, buf.getvalue())


def summary_markdown(rows: list[dict]) -> str:
    succ = bool(rows) and "final_success_rate" in rows[0]
    head = ("| method | initial | final (mean) | 95% CI | final (IQM) | 95% CI (bootstrap) | "
            "updates to 90% | failing seeds |")
    rule = "|---|---|---|---|---|---|---|---|"
    if succ:
        head += " success (exploring) | success (c(s)) | seeds >= 90% |"
        rule += "---|---|---|"
    task = bool(rows) and "final_return_iqm" in rows[0]
    if task:
        of = "c(s)" if rows[0]["return_of"] == "eval_return" else "exploring episodes"
        head += f" return of {of} (IQM) | 95% CI | steps to threshold (median) | seeds reaching it |"
        rule += "---|---|---|---|"
    lines = [head, rule]
    for r in rows:
        fails = r.get("failing_seeds", "")
        if fails != "":
            causes = ", ".join(f"{c} {r['fail_' + c]}" for c in FAILURE_CAUSES if r["fail_" + c])
            fails = f"{fails}/{r['seeds']}" + (f" ({causes})" if causes else "")
        line = (f"| {r['method']} | {r['initial_mean']:.3f} | {r['final_mean']:.3f} | "
                f"[{r['ci95_low']:.3f}, {r['ci95_high']:.3f}] | {r['final_iqm']:.3f} | "
                f"[{r['iqm_ci95_low']:.3f}, {r['iqm_ci95_high']:.3f}] | "
                f"{r['updates_to_90pct']:.0f} | {fails} |")
        if succ:
            line += (f" {r['final_success_rate']:.2f} | {r['final_eval_success_rate']:.2f} | "
                     f"{r['seeds_eval_success_90']}/{r['seeds']} |")
        if task:
            reach = r["steps_to_threshold_median"]
            line += (f" {r['final_return_iqm']:.1f} | [{r['return_ci95_low']:.1f}, "
                     f"{r['return_ci95_high']:.1f}] | {'-' if np.isnan(reach) else f'{reach:,.0f}'} | "
                     f"{r['seeds_reaching_threshold']}/{r['seeds']} |")
        lines.append(line)
    return "\n".join(lines)


def comparisons_markdown(rows: list[dict]) -> str:
    lines = ["| X | Y | P(X > Y) | 95% CI (bootstrap) |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['x']} | {r['y']} | {r['p_improvement']:.2f} | "
                     f"[{r['ci95_low']:.2f}, {r['ci95_high']:.2f}] |")
    return "\n".join(lines)
