"""Exploration that can find a swing-up: the four methods and gp_critic on the swing-up preset with
temporally correlated noise and held actions (design: docs/design.md#exploration), by the protocol
of `gpguided_jax.study`.

The grid below was written down before any of its runs. Each method's settings apply over the
preset's tuned ones (`config.METHOD_PRESETS['swingup']`, this study's choice).

Stages (each writes under --out, default docs/results/exploration):

``reach``   What exploration reaches before any learning: each method's initial policy (the RBF
            controller at its initial weights, the GP empty), 20 episodes for each of 10 seeds, per
            scheme in `REACH_SCHEMES` and amplitude: the share of episodes that rise above
            horizontal at some step, and that come within 0.3 rad of upright. Writes reach.json.
``tune``    Tuning seeds 100-101 (never reported): every method gets the same budget,
            `CONFIGS_PER_METHOD` (12) configurations x 2 seeds, each a full run of the preset
            (270,000 environment steps): scheme x learning rate x horizon (`GRID`), at the larger
            amplitude of `AMPLITUDE`, with the baseline. Score: the final deterministic success
            rate, ties broken by the final reward per step. Writes tuning.json.
``heldout`` Held-out seeds 1000-1019: each method with its chosen settings, and the ablation: the
            same method and settings under every scheme it can take (`ABLATION`). One
            `gpguided_jax.reproduce` run per (method, scheme) under heldout/. Writes heldout.json
            (each run's settings and wall time; it resumes: a run recorded with the same settings
            is not run again).
``retune``  gp_critic's own settings beyond the shared grid, on the tuning seeds (`RETUNE_GRID`): a
            coordinate search from its tuned settings, scored again first, over the window and
            the GP's budget M (kappa needs float64; the study runs in float32). Writes
            retune.json; ``heldout`` then runs its choice as gp_critic/retuned, where it differs
            from the tuned settings. It spends configurations beyond the others' budget, so its
            row stands beside gp_critic's.
``report``  heldout_table.json (steps to 50% and 90% success on `study.env_steps`, final success
            and reward per cell; the guidance against the same correlated noise unguided), the
            figure, and the action length-scale fitted under each scheme.

``baselines-tune``  brax PPO and SAC re-tuned for this study on the tuning seeds, with the methods'
            budget (`CONFIGS_PER_METHOD` configurations x 2 seeds, full runs): horizon,
            exploration and learning parameters (`BASELINE_GRID`). Writes baseline_tuning.json.
``baselines``  Both with their chosen settings on the held-out seeds, into heldout/<name>.npz;
            `report` sets them beside the methods. Writes baselines.json (it resumes, as
            ``heldout``).

``standard-tune``  On a standard task (--task, `STANDARD_SCHEMES`): the scheme each method
            would choose at its tuned settings for that task, on the tuning seeds (mean final
            return). Writes <task>/standard_tuning.json.
``standard``  Each method under each of the task's schemes (with --chosen, the one its tuning
            chose) on held-out seeds 1000-1009. Writes <task>/standard.json (it resumes, as
            ``heldout``).

Usage:
  python experiments/exploration_study.py reach
  python experiments/exploration_study.py tune
  python experiments/exploration_study.py heldout
  python experiments/exploration_study.py retune
  python experiments/exploration_study.py baselines-tune
  python experiments/exploration_study.py baselines
  python experiments/exploration_study.py report
  python experiments/exploration_study.py standard-tune --task inverted-pendulum
  python experiments/exploration_study.py standard --task inverted-pendulum
"""

from __future__ import annotations

import argparse
import csv
import json
import math
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
from gpguided_jax import baselines, checkpoints, methods, runtime, study, summaries  # noqa: E402
from gpguided_jax import config as config_lib  # noqa: E402
from gpguided_jax import stats as stats_lib  # noqa: E402
from gpguided_jax import train as train_lib  # noqa: E402

# the paper's four (`GRID`) and gp_critic (`gpguided_jax.critic`: gp_pg's step and K steps
# against the GP critic), which the reach stage leaves out (its initial policy is gp_pg's)
PAPER_METHODS = methods.paper()
METHODS = (*PAPER_METHODS, "gp_critic")
TUNING_SEEDS = study.TUNING_SEEDS
HELDOUT_SEEDS = tuple(range(1000, 1020))
REACH_SEEDS = tuple(range(1000, 1010))
REACH_EPISODES = 20
LN = math.log

# The exploration schemes (TrainConfig overrides).
SCHEMES = {
    "white": {},
    "ou_0.5s": {"exploration": "ou", "noise_correlation_time": 0.5},
    "coloured_2": {"exploration": "coloured", "noise_exponent": 2.0},
    "hold_0.05s": {"hold_time": 0.05},
    "hold_0.2s": {"hold_time": 0.2},
    "hold_0.5s": {"hold_time": 0.5},
    "parameter_episode": {"exploration": "parameter"},
    "parameter_0.5s": {"exploration": "parameter", "noise_resample_time": 0.5},
    "parameter_0.2s": {"exploration": "parameter", "noise_resample_time": 0.2},
    # guided_direction's optimistic score (mean + kappa sd of the GP), its choices held 0.2 s
    "hold_0.2s_optimism_1": {"hold_time": 0.2, "optimism": 1.0},
    "hold_0.2s_optimism_3": {"hold_time": 0.2, "optimism": 3.0},
}
REACH_SCHEMES = {
    "white": {},
    "ou 0.2 s": {"exploration": "ou", "noise_correlation_time": 0.2},
    "ou 0.5 s": {"exploration": "ou", "noise_correlation_time": 0.5},
    "ou 1 s": {"exploration": "ou", "noise_correlation_time": 1.0},
    "coloured 1": {"exploration": "coloured", "noise_exponent": 1.0},
    "coloured 1.5": {"exploration": "coloured", "noise_exponent": 1.5},
    "coloured 2": {"exploration": "coloured", "noise_exponent": 2.0},
    "hold 0.05 s": {"hold_time": 0.05},
    "hold 0.2 s": {"hold_time": 0.2},
    "hold 0.5 s": {"hold_time": 0.5},
    # the controller's weights perturbed (reinforce and gp_pg only): per episode, or redrawn
    "parameter, per episode": {"exploration": "parameter"},
    "parameter 0.5 s": {"exploration": "parameter", "noise_resample_time": 0.5},
    "parameter 0.2 s": {"exploration": "parameter", "noise_resample_time": 0.2},
}
# Every scheme sets both exploration fields, so that it replaces whatever the preset holds.
SCHEME_BASE = {"exploration": "white", "hold_time": 0.0}
SCHEMES = {k: {**SCHEME_BASE, **v} for k, v in SCHEMES.items()}
REACH_SCHEMES = {k: {**SCHEME_BASE, **v} for k, v in REACH_SCHEMES.items()}
# The exploration amplitude of each method: the fixed noise's initial sigma (N m), the guided
# variance's variance where the GP knows nothing, the Gibbs candidates' spread (both (N m)^2).
# The reach stage tries both; the tuning holds the larger (the smaller never rises above
# horizontal under any scheme).
AMPLITUDE = {
    "reinforce": ("init_log_std", [LN(1.5), LN(4.0)]),
    "gp_pg": ("init_log_std", [LN(1.5), LN(4.0)]),
    "gp_critic": ("init_log_std", [LN(1.5), LN(4.0)]),
    "guided_variance": ("guided_variance_scale", [2.25, 16.0]),
    "guided_direction": ("candidate_scale", [2.25, 16.0]),
}
HORIZONS = (0.5, 2.0)  # seconds: the preset's 0.99 per 5 ms step, and four times it
# The grid: scheme x learning rate x horizon = 2 x 3 x 2 = 12 configurations per method, with the
# baseline on (`use_baseline`). The schemes are the two that reach highest before learning.
# A first grid (the preset's learning rate and a tenth of it, no baseline, schemes ou_0.5s,
# coloured_2 and hold_0.2s) was stopped after REINFORCE, every one of whose 12 configurations
# ended at the constant-torque reward with no success: its record is tuning_first_grid.json.
LEARNING_RATES = (0.003, 0.01, 0.03)
GRID = {
    "reinforce": ("ou_0.5s", "hold_0.5s"),
    "gp_pg": ("ou_0.5s", "hold_0.5s"),
    "guided_variance": ("ou_0.5s", "hold_0.5s"),
    "guided_direction": ("hold_0.2s", "hold_0.5s"),  # white only: its choice is held
    "gp_critic": ("ou_0.5s", "hold_0.5s"),
}
FIXED = {"use_baseline": True}
# gp_critic's grid is over its own step size (critic_learning_rate, default 0.01, between the
# values) in place of the learning rate, which stays at the rate every one of the four chose
# (0.03, tuning.json); K and the trust region at their defaults (50 steps, 0.05 nats)
RATES = {m: ("learning_rate", LEARNING_RATES) for m in PAPER_METHODS}
RATES["gp_critic"] = ("critic_learning_rate", (0.003, 0.01, 0.03))
FIXED_OF = {"gp_critic": {"learning_rate": 0.03}}
CONFIGS_PER_METHOD = 12
# The parameter-noise schemes (reinforce and gp_pg only) and guided_direction's optimistic
# scores were added to the ablation after the tuning above, at each method's chosen learning
# rate, horizon and amplitude; they were not tuned.
ABLATION = {
    "reinforce": ("white", "ou_0.5s", "coloured_2", "hold_0.5s", "parameter_episode",
                  "parameter_0.5s", "parameter_0.2s"),
    "gp_pg": ("white", "ou_0.5s", "coloured_2", "hold_0.5s", "parameter_episode",
              "parameter_0.5s", "parameter_0.2s"),
    "guided_variance": ("white", "ou_0.5s", "coloured_2", "hold_0.5s"),
    "guided_direction": ("white", "hold_0.2s", "hold_0.5s", "hold_0.2s_optimism_1",
                         "hold_0.2s_optimism_3"),
    "gp_critic": ("white", "ou_0.5s", "hold_0.5s"),
}
DTYPE = "float32"
# gp_critic's `retune` stage (as experiments/standard_tasks.py's): a window of 4 and 16 updates'
# states, then M = 400, each stage over the best so far from its tuned settings; its held-out run
# is the part gp_critic/RETUNED
RETUNE_GRID = [("critic_window", [4, 16]), ("gp_capacity", [400])]
RETUNED = "retuned"

# brax PPO and SAC (`baselines-tune`): the same budget as each method, CONFIGS_PER_METHOD
# configurations x the tuning seeds, by coordinate search from the white-noise study's choice
# (`BASELINE_START`, docs/results/swingup/tuning.json): each stage tries its values with the best
# settings so far and keeps the best configuration seen. A stage over two parameters tries the
# listed pairs. The horizon is in seconds (brax's discount at the preset's 5 ms step: 0.5 s is the
# 0.99 of the white-noise study, 5 s is 0.999). Exploration: PPO's entropy cost; SAC learns its
# entropy weight against a target entropy, so its reward scale sets how much exploration a unit
# of return is worth, and its gradient steps per environment step how fast it leaves the noise.
# Each run is evaluated NUM_EVALS times, the initial policy included, as in the swing-up study.
NUM_EVALS = 21
BASELINE_START = {"ppo": {"learning_rate": 0.003},
                  "sac": {"learning_rate": 0.001, "reward_scaling": 3.0}}
BASELINE_GRID = {
    "ppo": [(("horizon", "entropy_cost"), [(0.5, 1e-3), (2.0, 1e-3), (5.0, 1e-3),
                                           (0.5, 1e-2), (2.0, 1e-2), (5.0, 1e-2)]),
            ("learning_rate", [0.001, 0.01]), ("unroll_length", [10, 50]),
            ("gae_lambda", [0.9, 0.99])],
    "sac": [(("horizon", "grad_updates_per_step"), [(0.5, 1), (2.0, 1), (5.0, 1),
                                                    (0.5, 8), (2.0, 8), (5.0, 8)]),
            ("learning_rate", [0.0003, 0.003]), ("reward_scaling", [1.0, 10.0]),
            ("grad_updates_per_step", [4, 16])],
}

# The standard tasks (`standard` stage): each method at its tuned settings for the task
# (config.METHOD_PRESETS) under each scheme it can take, seeds 1000-1009, no further tuning.
# MountainCarContinuous-v0's step counts as 1 s (an episode is 999 steps, a swing of the car
# about a hundred): OU noise of a tenth and of a whole swing, actions held for 10 steps, and the
# controller's weights perturbed once per episode.
STANDARD_SEEDS = tuple(range(1000, 1010))
STANDARD_DTYPE = "float64"  # as experiments/standard_tasks.py ran the white-noise comparison
STANDARD_SCHEMES = {
    # Pendulum-v1 at 20 Hz (a swing of about 2 s): OU noise of a quarter and of a whole swing,
    # actions held for 0.2 s (4 steps), and the controller's weights perturbed once per episode.
    "pendulum-v1": {
        "white": {},
        "ou_0.5s": {"exploration": "ou", "noise_correlation_time": 0.5},
        "ou_2s": {"exploration": "ou", "noise_correlation_time": 2.0},
        "hold_0.2s": {"hold_time": 0.2},
        "parameter_episode": {"exploration": "parameter"},
    },
    "mountaincar-continuous": {
        "white": {},
        "ou_10s": {"exploration": "ou", "noise_correlation_time": 10.0},
        "ou_100s": {"exploration": "ou", "noise_correlation_time": 100.0},
        "hold_10s": {"hold_time": 10.0},
        "parameter_episode": {"exploration": "parameter"},
    },
}
# brax's pendulums (steps of 0.04 s and 0.02 s): a pole left alone falls in about half a second
# (its time constant, (l/g)^1/2 for its 0.6 m, is a quarter of one), so OU noise of a fifth and of
# the whole fall, actions held for 0.08 s (2 and 4 steps), and the controller's weights perturbed
# once per episode
STANDARD_SCHEMES["inverted-pendulum"] = STANDARD_SCHEMES["inverted-double-pendulum"] = {
    "white": {},
    "ou_0.1s": {"exploration": "ou", "noise_correlation_time": 0.1},
    "ou_0.5s": {"exploration": "ou", "noise_correlation_time": 0.5},
    "hold_0.08s": {"hold_time": 0.08},
    "parameter_episode": {"exploration": "parameter"},
}
# What a task's standard runs hold beside the scheme: on brax's pendulums an episode that ends is
# restarted in its remaining slots, so that every slot is an environment step (as for PPO and
# SAC; a masked episode that falls early spends the rest of its length of budget unused)
STANDARD_BASE = {"inverted-pendulum": {"episode_end": "restart"},
                 "inverted-double-pendulum": {"episode_end": "restart"}}


def schemes_of(method: str, schemes: dict) -> list[str]:
    """The schemes of `schemes` whose exploration the method accepts (its declared
    `explorations`: guided_direction white noise, held or not, only; parameter noise reinforce and
    gp_pg only)."""
    accepts = methods.get(method).explorations
    return [name for name, scheme in schemes.items()
            if scheme.get("exploration", "white") in accepts]


def standard_overrides(task: str, scheme: str) -> dict:
    """The overrides of a standard task's run under `scheme` (over the method's tuned settings)."""
    return {**SCHEME_BASE, **STANDARD_BASE.get(task, {}), **STANDARD_SCHEMES[task][scheme]}


log = study.log


def preset(method: str, **overrides) -> config_lib.TrainConfig:
    return config_lib.preset("swingup", method=method, dtype=DTYPE, **overrides)


# ------------------------------------------------------------------------------------------ reach


def reach(out: str) -> dict:
    """Share of the initial policy's episodes above horizontal / near upright, per method, scheme
    and amplitude. The rows of an earlier reach.json are kept, and only the missing ones run."""
    path = os.path.join(out, "reach.json")
    done = {(r["method"], r["scheme"], r[AMPLITUDE[r["method"]][0]]): r
            for r in study.read_json(path, {"rows": []})["rows"]}
    rows = []
    for method in PAPER_METHODS:
        field, amplitudes = AMPLITUDE[method]
        for name in schemes_of(method, REACH_SCHEMES):
            scheme = REACH_SCHEMES[name]
            for amp in amplitudes:
                if (method, name, amp) in done:
                    rows.append(done[(method, name, amp)])
                    continue
                cfg = preset(method, **scheme, **{field: amp})
                above, upright = _reach_one(cfg)
                rows.append(dict(method=method, scheme=name, **{field: amp},
                                 above_horizontal=above, near_upright=upright))
                log(f"[reach] {method} {name} {field}={amp:.3g}: above {above:.2f}, "
                    f"upright {upright:.2f}")
    res = {"seeds": list(REACH_SEEDS), "episodes_per_seed": REACH_EPISODES, "rows": rows}
    study.write_json(path, res)
    return res


def _reach_one(cfg) -> tuple[float, float]:
    prog = train_lib.make_program(cfg)
    state = jax.jit(train_lib.make_train(cfg).init)(jax.random.PRNGKey(REACH_SEEDS[0]), cfg)
    ctx = train_lib.policy_context(cfg, state.gp, state.kernel)
    keys = jnp.stack([jax.random.split(jax.random.PRNGKey(s), REACH_EPISODES)
                      for s in REACH_SEEDS]).reshape(-1, 2)

    @jax.jit
    def heights(key):
        ep = train_lib.rollout(prog, key, state.theta, ctx, prog.policy, cfg)
        off_upright = jnp.abs(ep.next_states[:, 0] - jnp.pi)  # phi in [0, 2 pi), 0 hanging
        return jnp.any(off_upright < jnp.pi / 2), jnp.any(off_upright < 0.3)

    above, upright = jax.lax.map(heights, keys)
    return float(jnp.mean(above)), float(jnp.mean(upright))


# ------------------------------------------------------------------------------------------- tune


def tune(out: str, only=None) -> dict:
    """The grid (`GRID`: scheme x horizon x learning rate, `RATES`) of each method on the tuning
    seeds: a coordinate search whose every stage sets every parameter (one stage per scheme and
    horizon, its learning rates one sweep). Writes tuning.json."""
    header = {"seeds": list(TUNING_SEEDS), "dtype": DTYPE,
              "env_steps": study.learning_steps(preset("reinforce"))}
    rep = None
    for method in only or METHODS:
        field, amplitudes = AMPLITUDE[method]
        rate, rates = RATES[method]
        grid = [[{"scheme": scheme, **FIXED, **FIXED_OF.get(method, {}), field: amplitudes[-1],
                  "discount_horizon": horizon, rate: lr} for lr in rates]
                for scheme in GRID[method] for horizon in HORIZONS]

        def evaluate(configs, method=method):
            overrides = [{**SCHEMES[c["scheme"]], **{k: v for k, v in c.items() if k != "scheme"},
                          "dtype": DTYPE} for c in configs]
            return study.sweep_stage(overrides, study.final_success, method=method,
                                     preset="swingup", seeds=TUNING_SEEDS)

        t0 = time.perf_counter()
        result = study.coordinate_search(grid, evaluate, key=study.by_success,
                                         log=lambda m, method=method: log(f"[tune {method}] {m}"))
        assert len(result["tried"]) == CONFIGS_PER_METHOD
        rep = study.record_result(os.path.join(out, "tuning.json"), header, method,
                                  {**result, "wall_s": time.perf_counter() - t0})
    return rep


# ---------------------------------------------------------------------------------------- heldout


def settings_of(chosen: dict, scheme: str) -> dict:
    """The config overrides of a method's chosen settings with `scheme` in place of its own."""
    s = {k: v for k, v in chosen.items() if k != "scheme"}
    return {**s, **SCHEMES[scheme]}


def heldout(out: str, only=None) -> dict:
    """Each method of `only` under each scheme of its ablation, with its chosen settings, on the
    held-out seeds: one run each under heldout/<method>/<scheme>/, recorded in heldout.json (a run
    whose settings are recorded there is not run again)."""
    tuning = study.read_json(os.path.join(out, "tuning.json"))
    parts = {f"{m}/{scheme}": settings_of(tuning["methods"][m]["chosen"], scheme)
             for m in only or METHODS for scheme in ABLATION[m]}
    retuned = study.read_json(os.path.join(out, "retune.json"))
    if ("gp_critic" in (only or METHODS) and retuned is not None
            and retuned["chosen"] != tuning["methods"]["gp_critic"]["chosen"]):
        chosen = retuned["chosen"]
        parts[f"gp_critic/{RETUNED}"] = settings_of(chosen, chosen["scheme"])

    def run(key, overrides):
        run = study.run_method("swingup", key.split("/")[0], HELDOUT_SEEDS,
                               os.path.join(out, "heldout", key), overrides, dtype=DTYPE,
                               chunk_size=20)
        return {"wall_s": run.wall_s}

    return study.run_parts(os.path.join(out, "heldout.json"), {"seeds": list(HELDOUT_SEEDS)},
                           parts, run, log=lambda m: log(f"[heldout] {m}"))


def retune(out: str) -> dict:
    """gp_critic's `RETUNE_GRID` on the tuning seeds, from its tuned settings (tuning.json), which
    are scored again as the first stage. Writes retune.json."""
    tuned = study.read_json(os.path.join(out, "tuning.json"))["methods"]["gp_critic"]["chosen"]

    def evaluate(configs):
        overrides = [{**settings_of(c, c["scheme"]), "dtype": DTYPE} for c in configs]
        return study.sweep_stage(overrides, study.final_success, method="gp_critic",
                                 preset="swingup", seeds=TUNING_SEEDS)

    result = study.search_beyond(tuned, RETUNE_GRID, evaluate, key=study.by_success,
                                 log=lambda m: log(f"[retune] {m}"))
    study.write_json(os.path.join(out, "retune.json"), {
        "seeds": list(TUNING_SEEDS), "dtype": DTYPE, "grid": RETUNE_GRID, **result})
    return result


# -------------------------------------------------------------------------------------- baselines


def baselines_tune(out: str, only=None) -> dict:
    """Coordinate search of each baseline (`BASELINE_GRID`) from `BASELINE_START` on the tuning
    seeds. Writes baseline_tuning.json."""
    header = {"seeds": list(TUNING_SEEDS), "env_steps": study.learning_steps(preset("reinforce"))}
    rep = None
    for name in only or baselines.NAMES:
        t0 = time.perf_counter()

        def evaluate(configs, name=name):  # the final success: the last evaluation, of 64 episodes
            return study.baseline_stage(configs, lambda run: study.last_success(run.records),
                                        name=name, cfg=preset("reinforce"), seeds=TUNING_SEEDS,
                                        num_evals=NUM_EVALS)

        result = study.coordinate_search(study.stages(BASELINE_GRID[name]), evaluate,
                                         key=study.by_success, start=BASELINE_START[name],
                                         log=lambda m, name=name: log(f"[tune {name}] {m}"))
        assert len(result["tried"]) == CONFIGS_PER_METHOD
        rep = study.record_result(os.path.join(out, "baseline_tuning.json"), header, name,
                                  {**result, "wall_s": time.perf_counter() - t0})
    return rep


def baselines_heldout(out: str, only=None) -> dict:
    """Each baseline of `only` with its chosen settings on the held-out seeds, into
    heldout/<name>.npz; recorded in baselines.json (a baseline whose settings are recorded there
    is not run again)."""
    tuning = study.read_json(os.path.join(out, "baseline_tuning.json"))

    def run(name, settings):
        run = study.run_baseline(name, preset("reinforce"), HELDOUT_SEEDS, settings,
                                 num_evals=NUM_EVALS, progress=lambda m: log(f"[heldout] {m}"))
        os.makedirs(os.path.join(out, "heldout"), exist_ok=True)
        checkpoints.atomic_savez(os.path.join(out, "heldout", f"{name}.npz"), steps=run.env_steps,
                                 success=run.records["eval_success_rate"],
                                 reward=run.records["eval_reward"])
        return {"wall_s": run.wall_s}

    parts = {name: tuning["methods"][name]["chosen"] for name in only or baselines.NAMES}
    return study.run_parts(os.path.join(out, "baselines.json"), {"seeds": list(HELDOUT_SEEDS)},
                           parts, run, settings_key="settings",
                           log=lambda m: log(f"[heldout] {m}"))


# ----------------------------------------------------------------------------------------- report


def _curves(out: str, method: str, scheme: str, overrides: dict):
    """A run's deterministic success and reward per step, on `study.env_steps`."""
    with np.load(os.path.join(out, "heldout", method, scheme, "results.npz")) as f:
        success = np.asarray(f["eval_success_rate"][0], float)
        reward = np.asarray(f["eval_reward"][0], float)
    steps = study.env_steps(preset(method, **{**SCHEME_BASE, **overrides}))
    return steps, success, reward


def steps_to_row(steps: np.ndarray, success: np.ndarray) -> dict:
    """steps_to_50, steps_to_90: the seeds that reach the level, the median over all seeds of the
    environment steps to it and its 95% interval."""
    row = {}
    for level in (0.5, 0.9):
        hit = study.steps_to(steps, success, level, tol=1e-9)
        med, lo, hi = study.median_ci(hit)
        row[f"steps_to_{int(level * 100)}"] = dict(seeds=int(np.isfinite(hit).sum()), median=med,
                                                   ci=[lo, hi])
    return row


def action_length_scale(out: str, method: str, scheme: str) -> float | None:
    """Median over seeds of the fitted action length-scale (N m), if the run fitted a GP."""
    path = os.path.join(out, "heldout", method, scheme, f"kernels_{method}.npz")
    if not os.path.exists(path):
        return None
    with np.load(path) as f:
        return float(np.median(np.asarray(f["lengthscales"], float)[:, -1]))


def report(out: str) -> str:
    meta = study.read_json(os.path.join(out, "heldout.json"))
    chosen = {m: r["chosen"]["scheme"]
              for m, r in study.read_json(os.path.join(out, "tuning.json"))["methods"].items()}
    table = {"seeds": meta["seeds"], "rows": [], "guidance": []}
    # the run directories' curves (results.npz) are not kept in the repository: a run whose
    # curves are not on this machine keeps its row of the table file, and the figure is drawn
    # only when every run's curves are here
    table_path = os.path.join(out, "heldout_table.json")
    previous = study.read_json(table_path, {"rows": [], "guidance": []})
    kept = {f"{r['method']}/{r['scheme']}": r for r in previous["rows"]}
    have = {key: os.path.exists(os.path.join(out, "heldout", *key.split("/"), "results.npz"))
            for key in meta["runs"]}
    # the figure shows each method's chosen scheme; the guidance compares every scheme's runs
    draw = all(have[k] for k in meta["runs"] if k.split("/")[1] == chosen[k.split("/")[0]])
    guide = all(have.values())
    finals = {}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    order = [f"{m}/{x}" for m in METHODS for x in (*ABLATION[m], RETUNED)]
    for key in sorted(meta["runs"], key=order.index):
        run = meta["runs"][key]
        method, scheme = key.split("/")
        if not have[key]:
            table["rows"].append(kept[key])
            continue
        steps, success, reward = _curves(out, method, scheme, run["overrides"])
        smooth = study.smoothed(success)  # a trailing mean over 5 updates, as the swing-up study's
        is_chosen = scheme == chosen[method]
        table["rows"].append(dict(
            method=method, scheme=scheme, chosen=is_chosen, settings=run["overrides"],
            final_success=float(study.final(success).mean()),
            final_reward=float(study.final(reward).mean()),
            action_length_scale=action_length_scale(out, method, scheme), wall_s=run["wall_s"],
            **steps_to_row(steps, smooth)))
        finals[key] = study.final(reward)
        if is_chosen:
            for ax, y in zip(axes, (smooth, reward)):
                study.plot_band(ax, steps, y, label=f"{method} ({scheme})")
    bmeta = study.read_json(os.path.join(out, "baselines.json"))
    if bmeta is not None:  # brax PPO and SAC, re-tuned for this study (`baselines`)
        assert bmeta["seeds"] == meta["seeds"], "the baselines ran on other seeds"
        for name, run in bmeta["runs"].items():
            with np.load(os.path.join(out, "heldout", f"{name}.npz")) as f:
                steps, success, reward = (np.asarray(f[k], float)
                                          for k in ("steps", "success", "reward"))
            # each evaluation is 64 episodes: no trailing mean
            table["rows"].append(dict(
                method=name, scheme="its own", chosen=True, settings=run["settings"],
                final_success=float(study.final(success).mean()),
                final_reward=float(study.final(reward).mean()), action_length_scale=None,
                wall_s=run["wall_s"], **steps_to_row(steps, success)))
            for ax, y in zip(axes, (success, reward)):
                study.plot_band(ax, steps, y, alpha=0.15, ls="--", label=f"{name} (brax, re-tuned)")
    if not guide:
        table["guidance"] = previous["guidance"]
    for scheme in ("ou_0.5s", "coloured_2", "hold_0.5s") if guide else ():
        a, b = f"guided_variance/{scheme}", f"gp_pg/{scheme}"
        if a in finals and b in finals:
            p = stats_lib.probability_of_improvement(finals[a], finals[b])
            lo, hi = stats_lib.probability_of_improvement_ci(finals[a], finals[b])
            table["guidance"].append(dict(scheme=scheme, p=p, ci=[lo, hi]))
    axes[0].set_ylabel("success rate (methods: trailing mean over 5 updates)")
    axes[1].set_ylabel("reward per step")
    for ax in axes:
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Swing-up, each method's chosen exploration: mean and 95% t-band over "
                 f"{len(meta['seeds'])} held-out seeds")
    fig.tight_layout()
    if draw:
        fig.savefig(os.path.join(out, "exploration_swingup.png"), dpi=120)
    else:
        log("the curves of a chosen run are not here: the figure not redrawn")
    if not guide:
        log("the curves of some runs are not here: their rows and the guidance kept")
    plt.close(fig)
    study.write_json(os.path.join(out, "heldout_table.json"), table)
    study.critic_diagnostics({f"gp_critic ({scheme})": os.path.join(out, "heldout", "gp_critic",
                                                                   scheme, "results.npz")
                              for scheme in (*ABLATION["gp_critic"], RETUNED)},
                             os.path.join(out, "critic_diagnostics.json"))
    return json.dumps(table["rows"], indent=1)


# --------------------------------------------------------------------------------------- standard


def standard_tune(task: str, out: str, only=None) -> dict:
    """The scheme each method would choose on the tuning seeds: each scheme of
    `STANDARD_SCHEMES[task]` it can take at its tuned settings, on `TUNING_SEEDS`; score: the mean
    final return of the deterministic policy. Writes <out>/<task>/standard_tuning.json (a scheme
    tried there is not run again; each method's entry is written into the record as it is then,
    so that processes tuning other methods of the task at the same time keep theirs)."""
    base = os.path.join(out, task)
    path = os.path.join(base, "standard_tuning.json")
    header = {"task": task, "seeds": list(TUNING_SEEDS)}
    rec = study.read_json(path, {**header, "methods": {}})
    for method in only or METHODS:
        tried = rec["methods"].get(method, {}).get("tried", [])
        done = {t["scheme"] for t in tried}
        for name in schemes_of(method, STANDARD_SCHEMES[task]):
            if name in done:
                continue
            run = study.run_method(task, method, TUNING_SEEDS,
                                   os.path.join(base, "tuning", method, name),
                                   standard_overrides(task, name), dtype=STANDARD_DTYPE)
            tried.append(dict(scheme=name, **study.final_return(run.records)))
            log(f"[standard-tune {task}] {method}/{name}: {tried[-1]['score']:.1f}")
        rec = study.record_result(path, header, method, dict(
            tried=tried, chosen=max(tried, key=study.by_score)["scheme"]))
    return rec


def standard(task: str, out: str, only=None, chosen: bool = False) -> dict:
    """Each method at its tuned settings for `task` under each of `STANDARD_SCHEMES[task]`, one
    `gpguided_jax.reproduce` run per (method, scheme) under <out>/<task>/; writes
    <out>/<task>/standard.json with each run's summary row and, where its curves are on this
    machine (or no seed reaches the threshold), the steps at which each seed first reaches it
    (null: never; a run recorded there with the same settings is not run again). `chosen`: each
    method under the scheme its `standard-tune` record chose only."""
    base = os.path.join(out, task)
    path = os.path.join(base, "standard.json")

    def run(key, overrides):
        method, run_dir = key.split("/")[0], os.path.join(base, key)
        wall = study.run_method(task, method, STANDARD_SEEDS, run_dir, overrides,
                                dtype=STANDARD_DTYPE).wall_s
        with open(os.path.join(run_dir, "summary.csv")) as f:
            row = next(csv.DictReader(f))
        log(f"[standard {task}] {key}: return {float(row['final_return_iqm']):.1f}, "
            f"{row['seeds_reaching_threshold']} seeds reach the threshold")
        return {"wall_s": wall, "summary": row}

    choice = ({m: r["chosen"] for m, r in study.read_json(
        os.path.join(base, "standard_tuning.json"))["methods"].items()} if chosen else {})
    parts = {f"{m}/{name}": standard_overrides(task, name)
             for m in only or METHODS for name in schemes_of(m, STANDARD_SCHEMES[task])
             if not chosen or name == choice[m]}
    meta = study.run_parts(path, {"task": task, "seeds": list(STANDARD_SEEDS)}, parts, run,
                           log=lambda m: log(f"[standard {task}] {m}"))
    # the guidance against the same unguided noise: P(guided_variance > gp_pg), final return (the
    # run directories' curves are not kept in the repository: a scheme whose two runs' curves are
    # not on this machine keeps its earlier entry)
    finals = {}
    for key, rec in meta["runs"].items():
        results = os.path.join(base, key, "results.npz")
        if os.path.exists(results):
            with np.load(results) as f:
                finals[key] = study.final(f["eval_return"][0])
                cfg = config_lib.preset(task, method=key.split("/")[0], dtype=STANDARD_DTYPE,
                                        **rec["overrides"])
                reach = summaries.steps_to_threshold(f["eval_return"][0],
                                                     summaries.task_budget(cfg))
                rec["steps_to_threshold"] = [None if np.isnan(v) else float(v) for v in reach]
        elif int(rec["summary"]["seeds_reaching_threshold"]) == 0:
            rec["steps_to_threshold"] = [None] * len(STANDARD_SEEDS)
    earlier = {g["scheme"]: g for g in meta.get("guidance", [])}
    meta["guidance"] = []
    for name in STANDARD_SCHEMES[task]:
        a, b = f"guided_variance/{name}", f"gp_pg/{name}"
        if a in finals and b in finals:
            lo, hi = stats_lib.probability_of_improvement_ci(finals[a], finals[b])
            meta["guidance"].append(dict(
                scheme=name, p=stats_lib.probability_of_improvement(finals[a], finals[b]),
                ci=[lo, hi]))
        elif name in earlier:
            meta["guidance"].append(earlier[name])
    study.write_json(path, meta)
    return meta


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage", choices=("reach", "tune", "heldout", "retune", "baselines-tune",
                                      "baselines", "report", "standard-tune", "standard"))
    ap.add_argument("--task", default="mountaincar-continuous", choices=sorted(STANDARD_SCHEMES),
                    help="the standard task of the `standard` stage")
    ap.add_argument("--chosen", action="store_true",
                    help="standard: each method under the scheme its tuning chose only")
    ap.add_argument("--out", default="docs/results/exploration")
    ap.add_argument("--only", nargs="+", default=None, choices=(*METHODS, *baselines.NAMES),
                    help="these methods (or, for the baseline stages, baselines) only")
    ap.add_argument("--compile-cache", default=runtime.DEFAULT_COMPILE_CACHE)
    args = ap.parse_args(argv)
    if args.only:
        names = baselines.NAMES if args.stage.startswith("baselines") else METHODS
        if not set(args.only) <= set(names):
            ap.error(f"--only: the {args.stage} stage takes {', '.join(names)}")
    runtime.set_compile_cache(args.compile_cache)
    os.makedirs(args.out, exist_ok=True)
    if args.stage == "reach":
        reach(args.out)
    elif args.stage == "tune":
        tune(args.out, args.only)
    elif args.stage == "heldout":
        heldout(args.out, args.only)
    elif args.stage == "retune":
        retune(args.out)
    elif args.stage == "baselines-tune":
        baselines_tune(args.out, args.only)
    elif args.stage == "baselines":
        baselines_heldout(args.out, args.only)
    elif args.stage == "standard-tune":
        gpguided_jax.enable_x64()
        standard_tune(args.task, args.out, args.only)
    elif args.stage == "standard":
        gpguided_jax.enable_x64()
        standard(args.task, args.out, args.only, args.chosen)
    else:
        print(report(args.out))
    return 0


if __name__ == "__main__":
    gpguided_jax.enable_x64(False)
    sys.exit(main())
