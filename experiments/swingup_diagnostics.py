"""What limits the methods on the swing-up task: two diagnostics outside the tuning budget (seeds
100-104, never reported as results; nothing is chosen from them).

1. ``warm``: each of the four methods, with its white-noise swing-up settings
   (`swingup_study.study_config`; or `--warm-lr`), starts from the RBF
   controller fitted to the energy-pumping controller (`swingup.fit_controller`; it swings up from
   ~99% of start states when run deterministically) instead of from theta_c = 0. If the policy
   gradient keeps (or improves) a swing-up once it has one, what the methods lack is a way to find
   one: exploration. The GP hyperparameters are fitted, as always, on data of the initial
   fixed-noise policy with theta_c = 0.
2. ``sac``: brax SAC with the tuned settings but a discount of 0.999 (0.99 at 200 Hz is a 0.5 s
   horizon) and 8 gradient steps per environment step of the 16 environments (the tuned runs made
   one per 16 environment steps), at the same 270,000-step budget.

Writes diagnostics.json under --out (default docs/results/swingup) and prints it.

Usage:
  python experiments/swingup_diagnostics.py [warm] [sac]
  python experiments/swingup_diagnostics.py warm --warm-lr 0.003
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import numpy as np

from gpguided_jax import checkpoints, sharding, study, summaries, swingup
from gpguided_jax import config as config_lib
from gpguided_jax import train as train_lib

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from swingup_study import METHODS, study_config  # noqa: E402

SEEDS = (100, 101, 102, 103, 104)
log = study.log


def warm_start(seeds, tuning: dict, learning_rate=None) -> dict:
    out = {}
    cfg0 = study_config(tuning, "gp_pg", dtype="float32")
    controller = train_lib.make_controller(cfg0)
    theta_fit, mse = swingup.fit_controller(
        controller, cfg0.pendulum, swingup.energy_pumping_policy(cfg0.pendulum),
        jax.random.PRNGKey(7), episode_length=cfg0.episode_length, num_episodes=100)
    keys = sharding.seed_keys(seeds)
    priors = jax.jit(jax.vmap(train_lib.make_train(cfg0).fit_kernel_for_seed))(keys)
    for m in METHODS:
        lr = {} if learning_rate is None else {"learning_rate": learning_rate}
        cfg = study_config(tuning, m, dtype="float32", **lr)
        train = train_lib.make_train(cfg)
        if cfg.uses_gp:
            state = jax.jit(jax.vmap(lambda k, p, t=train, c=cfg: t.init(k, c, p)))(keys, priors)
        else:
            state = jax.jit(jax.vmap(lambda k, t=train, c=cfg: t.init(k, c)))(keys)
        warm = jax.tree_util.tree_map(lambda x: np.broadcast_to(x, (len(seeds), *x.shape)),
                                      theta_fit)
        state = state._replace(theta=state.theta._replace(controller=warm))
        _, rec = jax.jit(jax.vmap(lambda s, t=train, c=cfg: t.run_chunk(s, c, c.num_updates)))(state)
        succ = np.asarray(rec.eval_success_rate)
        rew = np.asarray(rec.eval_reward)
        out[m] = {"first_10_updates_success": float(succ[:, :10].mean()),
                  "final_success": float(summaries.final_performance(succ).mean()),
                  "final_success_per_seed": summaries.final_performance(succ).tolist(),
                  "first_10_updates_reward": float(rew[:, :10].mean()),
                  "final_reward": float(summaries.final_performance(rew).mean())}
        log(f"[warm {m} lr {float(cfg.learning_rate):g}] success first 10 updates "
            f"{out[m]['first_10_updates_success']:.2f} -> "
            f"final {out[m]['final_success']:.2f}; reward {out[m]['first_10_updates_reward']:.3f} "
            f"-> {out[m]['final_reward']:.3f}")
    out["fitted_controller_mse"] = mse
    return out


def sac_long_horizon(seeds) -> dict:
    with open(os.path.join("docs", "results", "swingup", "tuning.json")) as f:
        tuned = json.load(f)["methods"]["sac"]["chosen"]
    cfg = config_lib.preset("swingup", method="reinforce", dtype="float32")
    settings = {**tuned, "discounting": 0.999, "grad_updates_per_step": 8,
                "deterministic_eval": True}
    run = study.run_baseline("sac", cfg, seeds[:2], settings, num_evals=11,
                             progress=lambda m: log(f"[gamma 0.999, 8 updates/step] {m}"))
    runs = [dict(seed=s, success=run.records["eval_success_rate"][i].tolist(),
                 reward=run.records["eval_reward"][i].tolist(), env_steps=run.env_steps.tolist(),
                 wall_s=run.seed_wall_s[i]) for i, s in enumerate(seeds[:2])]
    return {"settings": settings, "runs": runs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("parts", nargs="*", default=["warm", "sac"])
    ap.add_argument("--out", default="docs/results/swingup")
    ap.add_argument("--warm-lr", type=float, default=None,
                    help="warm start with this learning rate instead of the tuned one")
    args = ap.parse_args(argv)
    path = os.path.join(args.out, "diagnostics.json")
    report = {}
    if os.path.exists(path):
        with open(path) as f:
            report = json.load(f)
    report["seeds"] = list(SEEDS)
    with open(os.path.join(args.out, "tuning.json")) as f:  # the white-noise study's
        tuning = json.load(f)
    if "warm" in args.parts:
        key = "warm_start" if args.warm_lr is None else f"warm_start_lr_{args.warm_lr:g}"
        report[key] = warm_start(SEEDS, tuning, args.warm_lr)
    if "sac" in args.parts:
        report["sac_long_horizon"] = sac_long_horizon(SEEDS)
    checkpoints.atomic_write_text(path, json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
