"""The `gpguided` command line: parsing and the commands (demo, reproduce, baseline, sweep, bench,
race).
`gpguided --help` lists the commands; each has its own --help. The process's set-up before a
command runs (LAPACK threads, CPU devices, precision, compilation cache) is `runtime`'s."""

from __future__ import annotations

import argparse
import os
import sys

from gpguided_jax import runtime


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (refused with a one-line message otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _cmd_demo(args) -> int:
    runtime.set_precision("float64")
    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from gpguided_jax import pendulum

    params = pendulum.make_params(start_mean=(0.1, 0.0), start_std=(0.0, 0.0), reward_noise_std=0.0)

    def energy_pumping(key, s):
        # Swing-up heuristic: push along omega while below the upright energy, then a PD balance.
        del key
        e = pendulum.energy(s, params)
        e_top = params.mass * params.gravity * params.length
        near_top = jnp.cos(s[0] - jnp.pi) > 0.9
        balance = -20.0 * (s[0] - jnp.pi) - 4.0 * s[1]
        pump = 5.0 * jnp.sign(s[1] + 1e-3) * jnp.where(e < e_top, 1.0, -0.2)
        return jnp.where(near_top, balance, pump)

    steps = int(args.seconds / float(params.dt))
    traj = jax.jit(pendulum.rollout, static_argnums=(2, 3))(
        jax.random.key(args.seed), params, energy_pumping, steps
    )
    t = np.arange(steps) * float(params.dt)
    phi, omega = np.asarray(traj.states).T
    torque = np.clip(np.asarray(traj.actions), -5, 5)
    print(f"{'t [s]':>6} {'phi [rad]':>10} {'omega':>8} {'torque':>7} {'reward':>8}")
    for i in range(0, steps, max(1, steps // 20)):
        print(f"{t[i]:6.2f} {phi[i]:10.3f} {omega[i]:8.3f} {torque[i]:7.2f} {traj.rewards[i]:8.3f}")
    print(f"final |phi - pi| = {abs(float(traj.final_state[0]) - np.pi):.3f} rad")
    os.makedirs(args.out, exist_ok=True)
    fig, axes = plt.subplots(3, 1, figsize=(7, 6), sharex=True)
    axes[0].plot(t, phi)
    axes[0].axhline(np.pi, color="k", lw=0.5, ls="--")
    axes[0].set_ylabel("phi [rad]")
    axes[1].plot(t, omega)
    axes[1].set_ylabel("omega [rad/s]")
    axes[2].plot(t, torque)
    axes[2].set_ylabel("torque [N m]")
    axes[2].set_xlabel("time [s]")
    fig.suptitle("Energy-pumping swing-up on the 200 Hz, 5 N m pendulum")
    fig.tight_layout()
    path = os.path.join(args.out, "pendulum_demo.png")
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")
    return 0


def _start_processes(args) -> None:
    """`jax.distributed.initialize` from --coordinator/--num-processes/--process-id (all or none)."""
    given = [args.coordinator is not None, args.num_processes is not None, args.process_id is not None]
    if not any(given):
        return
    if not all(given):
        raise SystemExit("gpguided reproduce: error: --coordinator, --num-processes and --process-id "
                         "go together")
    if args.process_id >= args.num_processes:
        raise SystemExit(f"gpguided reproduce: error: --process-id must be < --num-processes "
                         f"({args.num_processes}), got {args.process_id}")
    from gpguided_jax import distributed

    distributed.initialize(args.coordinator, args.num_processes, args.process_id)


def _cmd_reproduce(args) -> int:
    from gpguided_jax.checkpoints import OutDirError

    try:
        return _reproduce(args)
    except OutDirError as e:
        raise SystemExit(f"gpguided reproduce: error: {e}") from None


def _reproduce(args) -> int:
    runtime.set_cpu_devices(args.cpu_devices)
    _start_processes(args)
    runtime.set_precision(args.dtype)
    runtime.set_compile_cache(args.compile_cache)
    from gpguided_jax import distributed, reproduce

    _import_modules(args.imports)
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    overrides = {}
    if args.env is not None:
        overrides["env"] = args.env
    if args.horizon is not None:
        overrides["discount_horizon"] = args.horizon
    for flag, field in (("exploration", "exploration"),
                        ("correlation_time", "noise_correlation_time"),
                        ("noise_exponent", "noise_exponent"),
                        ("resample_time", "noise_resample_time"), ("hold_time", "hold_time"),
                        ("optimism", "optimism"), ("episode_end", "episode_end")):
        if getattr(args, flag) is not None:
            overrides[field] = getattr(args, flag)
    fields = _parse_overrides(args.set)
    both = sorted(set(fields) & set(overrides) | set(fields) & {"method", "dtype"})
    if both:
        raise SystemExit(f"gpguided reproduce: error: --set {', '.join(both)}: given by its own "
                         "option too")
    overrides.update(fields)
    from gpguided_jax import config

    try:  # a config that makes no sense (an environment that is not supported) is one line
        for m in args.methods:
            config.preset(args.preset, method=m, dtype=args.dtype, **overrides)
    except (TypeError, ValueError) as e:
        raise SystemExit(f"gpguided reproduce: error: {e}") from None
    out = reproduce.reproduce(
        preset=args.preset,
        overrides=overrides,
        seeds=seeds,
        methods=args.methods,
        out_dir=args.out,
        dtype=args.dtype,
        chunk_size=args.chunk_size,
        num_devices=args.devices,
        max_chunks=args.max_chunks,
        seed_loop=args.seed_loop,
        gp_program=args.gp_program.replace("-", "_"),
        keep_checkpoints=args.keep_checkpoints,
    )
    runtime.report_compile_cache()
    if not out["complete"]:
        print(f"stopped early (--max-chunks); run the same command again to resume from {args.out}")
        return 0
    if not distributed.is_main():
        return 0
    print(out["markdown"])
    for path in out["figures"]:
        print(f"wrote {path}")
    print(f"wrote {args.out}/results.npz, summary.csv, comparisons.csv, config.json, index.html")
    return 0


def _import_modules(names: list[str] | None) -> None:
    """`--import`: each module imported, the working directory first on the path (as `python -m`
    has it); one line for a module that is not found or fails to import."""
    import importlib

    if not names:
        return
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    for name in names:
        try:
            importlib.import_module(name)
        except Exception as e:  # noqa: BLE001 (the user's module: any error, in one line)
            first = str(e).strip().splitlines()[0] if str(e).strip() else ""
            raise SystemExit(f"gpguided reproduce: error: --import {name}: "
                             f"{type(e).__name__}: {first}") from None


def _parse_overrides(items: list[str] | None) -> dict:
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"--set expects FIELD=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k] = int(v)
        except ValueError:
            try:
                out[k] = float(v)
            except ValueError:
                out[k] = {"true": True, "false": False}.get(v.lower(), v)
    return out


def _cmd_bench(args) -> int:
    runtime.set_cpu_devices(None)
    runtime.set_precision("float64")
    from gpguided_jax import bench

    if args.merge and not args.out:
        raise SystemExit("gpguided bench: error: --merge writes into the report at --out; give --out")
    report = bench.run(repeats=args.repeats, seeds=args.seeds, numpy_updates=args.numpy_updates,
                       quick=args.quick, paper_run=not args.no_paper_run, sections=args.sections,
                       model_tasks=args.model_tasks, model_seeds=args.model_seeds,
                       model_scaling_seeds=args.model_scaling_seeds)
    if args.merge and os.path.exists(args.out):
        import json

        with open(args.out) as f:
            report = bench.merge_reports(json.load(f), report, args.sections)
    bench.print_report(report, args.out)
    return 0


def _cmd_baseline(args) -> int:
    runtime.set_cpu_devices(None)
    import json

    import numpy as np

    from gpguided_jax import baselines, checkpoints

    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise SystemExit(f"gpguided baseline: error: --out {args.out} exists and is not a "
                         "directory")
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    run = dict(env=args.env, num_timesteps=args.steps, num_evals=args.evals,
               overrides=_parse_overrides(args.set))
    try:  # a run brax cannot do is refused in one line on stderr before anything compiles
        baselines.plan_preset(args.algorithm, args.preset, **run)
        runtime.set_compile_cache(args.compile_cache)
        res = baselines.run_preset(args.algorithm, args.preset, seeds, **run,
                                   hidden_layers=tuple(args.hidden),
                                   progress=lambda line: print(line, file=sys.stderr, flush=True))
    except baselines.BudgetError as e:
        print(f"gpguided baseline: error: {e} (--steps {e.smallest} or more)", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"gpguided baseline: error: {e}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"baseline_{args.algorithm}")
    np.savez(stem + ".npz", seeds=np.asarray(seeds), env_steps=res["env_steps"],
             returns=res["returns"])
    meta = {k: v for k, v in res.items() if k not in ("env_steps", "returns")}
    checkpoints.atomic_write_text(stem + ".json", json.dumps(meta, indent=2))
    s = res["summary"]
    seeds_word = "seed" if s["seeds"] == 1 else "seeds"
    budget = "" if res["steps_run"] == res["budget"] else f" for a budget of {res['budget']}"
    line = (f"{args.algorithm} on {res['env']} ({res['steps_run']} steps run{budget}, "
            f"{s['seeds']} {seeds_word}): "
            f"final return IQM {s['final_return_iqm']:.1f} [{s['ci95'][0]:.1f}, "
            f"{s['ci95'][1]:.1f}]")
    if s["threshold"] is not None:
        hits = [v for v in s["steps_to_threshold"] if v is not None]
        line += (f"; {len(hits)} of {s['seeds']} seeds reach {s['threshold']:g}"
                 + (f", median {float(np.median(hits)):.0f} steps" if hits else ""))
    print(line)
    print(f"wrote {stem}.npz and {stem}.json")
    return 0


def _cmd_race(args) -> int:
    from gpguided_jax import race

    if os.path.exists(args.out) and not os.path.isdir(args.out):
        print(f"gpguided race: error: --out {args.out} exists and is not a directory",
              file=sys.stderr)
        return 2
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    states = [c.strip() for c in args.cache.split(",") if c.strip()]
    try:  # everything a race cannot run is refused in one line before any process starts
        unknown = [c for c in states if c not in race.CACHE_STATES]
        if unknown or not states:
            raise race.RaceError(f"--cache {args.cache}: choose cold, warm or cold,warm")
        plan = race.plan(args.preset, seeds=seeds, sac_steps=args.sac_steps,
                         sac_evals=args.sac_evals, gp_overrides=_parse_overrides(args.gp_set),
                         sac_overrides=_parse_overrides(args.sac_set), threshold=args.threshold)
        say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
        say(f"[race] {plan['env']}: gp_model at its preset against SAC with {plan['sac_steps']} "
            f"steps ({plan['sac_steps_source']}), threshold {plan['threshold']:g}, "
            f"{len(seeds)} seed(s), {' and '.join(states)} compile cache")
        if plan["sac_note"]:
            say(f"[race] {plan['sac_note']}")
        report = race.race(plan, args.out, cache_states=states, progress=say)
    except race.RaceError as e:
        print(f"gpguided race: error: {e}", file=sys.stderr)
        return 2
    print(race.table(report))
    print(f"wrote {os.path.join(args.out, 'race.json')}")
    return 0


def _cmd_sweep(args) -> int:
    from gpguided_jax import sweep

    try:
        field = sweep.resolve_param(args.param)
    except ValueError as e:
        raise SystemExit(f"gpguided sweep: error: {e}") from None
    runtime.set_cpu_devices(args.cpu_devices)
    runtime.set_precision(args.dtype)
    runtime.set_compile_cache(args.compile_cache)
    overrides = _parse_overrides(args.set)
    overrides["dtype"] = args.dtype
    if args.num_updates is not None:
        overrides["num_updates"] = args.num_updates
    out_dir = args.out or os.path.join("results", f"sweep_{field}")
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    try:
        result = sweep.run_sweep(
            field, args.values, method=args.method, preset=args.preset, seeds=seeds,
            overrides=overrides, chunk_size=args.chunk_size, num_devices=args.devices,
            seed_loop=args.seed_loop,
        )
    except (ValueError, TypeError) as e:
        raise SystemExit(f"gpguided sweep: error: {e}") from None
    runtime.report_compile_cache()
    paths = sweep.write_sweep(result, out_dir, preset=args.preset)
    print(sweep.sweep_markdown(result))
    for p in paths.values():
        print(f"wrote {p}")
    return 0


REPORTED_SEED_START = 1000  # the reported results' seeds start here; tuning used seeds below


class _DefaultsHelp(argparse.ArgumentDefaultsHelpFormatter):
    """--help with each option's default, where it has one worth saying (not None, not off)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or not action.help:
            return action.help
        return super()._get_help_string(action)


def _add_device_options(parser: argparse.ArgumentParser, what: str) -> None:
    """--devices, --cpu-devices and --seed-loop (`sharding.per_seed_program`)."""
    parser.add_argument("--devices", type=positive_int, default=None,
                        help="use at most this many devices")
    parser.add_argument("--cpu-devices", type=positive_int, default=None,
                        help="JAX CPU devices to create (default: one per available core; ignored "
                        "when XLA_FLAGS sets xla_force_host_platform_device_count)")
    parser.add_argument("--seed-loop", default="auto", choices=["auto", "vmap", "map"],
                        help=f"how a device runs its {what}: one batch (vmap) or one after another "
                        "(map); auto: map on CPUs (faster there, and bit-for-bit independent of "
                        "batch and device count), vmap on accelerators")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="gpguided",
        description="Guided policy search with sparse online GPs (Jakab & Csato 2012) in JAX.",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    for add in (_add_demo, _add_reproduce, _add_baseline, _add_sweep, _add_bench, _add_race):
        add(sub)
    return ap


def _add_compile_cache(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--compile-cache", default=runtime.DEFAULT_COMPILE_CACHE, metavar="DIR",
                        help="JAX's persistent compilation cache, so that a repeated run does not "
                        "compile again (a subdirectory per CPU type; 'none' turns it off)")


def _add_demo(sub) -> None:
    demo = sub.add_parser("demo", help="simulate and plot one pendulum swing-up",
                          formatter_class=_DefaultsHelp)
    demo.add_argument("--seconds", type=float, default=8.0, help="simulated time [s]")
    demo.add_argument("--seed", type=int, default=0, help="random seed of the start state")
    demo.add_argument("--out", default="results/demo", help="output directory")
    demo.set_defaults(func=_cmd_demo)


def _add_reproduce(sub) -> None:
    rep = sub.add_parser(
        "reproduce",
        formatter_class=_DefaultsHelp,
        help="run every method for every seed (the paper's Fig. 5)",
        description="Runs Algorithm 1 for each method and seed (all seeds as one compiled, "
        "device-sharded program, a chunk of updates at a time), then writes results.npz, "
        "config.json, summary.csv and the two Fig. 5 panels to --out. An interrupted run resumes "
        "from the checkpoints in --out.",
    )
    _add_task_options(rep)
    _add_exploration_options(rep)
    _add_run_options(rep)
    _add_device_options(rep, "seeds")
    _add_compile_cache(rep)
    _add_process_options(rep)
    rep.set_defaults(func=_cmd_reproduce)


def _add_task_options(rep) -> None:
    """reproduce: the preset, the environment and the discount."""
    from gpguided_jax.config import PRESETS

    rep.add_argument("--preset", default="paper", choices=sorted(PRESETS),
                     help="budgets and settings (config.PRESETS); the standard tasks' presets "
                     "(pendulum-v1, mountaincar-continuous, inverted-pendulum, "
                     "inverted-double-pendulum) set their environment")
    rep.add_argument("--env", default=None, metavar="ENV",
                     help="the environment, replacing the preset's: pendulum, gymnax:<id> or "
                     "brax:<name> with one continuous action (e.g. gymnax:Pendulum-v1, "
                     "brax:inverted_double_pendulum); the preset's budget applies")
    rep.add_argument("--import", dest="imports", nargs="+", default=None, metavar="MODULE",
                     help="import these modules first (from the working directory or the path): "
                     "a module that registers a task of its own (tasks.register) makes its name "
                     "an --env")
    rep.add_argument("--horizon", type=float, default=None, metavar="SECONDS",
                     help="the discount as a horizon in seconds, gamma = exp(-dt / horizon) "
                     "(replaces the preset's discount)")


def _add_exploration_options(rep) -> None:
    """reproduce: the exploration scheme and its settings."""
    from gpguided_jax.exploration import NOISES

    rep.add_argument("--exploration", default=None, choices=list(NOISES),
                     help="exploration noise of the Gaussian policies (default: the preset's, "
                     "white for the paper): white (independent at each decision), ou "
                     "(Ornstein-Uhlenbeck), coloured (spectrum f^-beta) or parameter (the "
                     "controller's weights perturbed, for reinforce and gp_pg); guided_direction "
                     "takes white only")
    rep.add_argument("--correlation-time", type=float, default=None, metavar="SECONDS",
                     help="the OU noise's correlation time (default: the preset's, 0.5 s)")
    rep.add_argument("--noise-exponent", type=float, default=None, metavar="BETA",
                     help="the coloured noise's exponent beta in [0, 3] (default: the preset's, "
                     "1: pink)")
    rep.add_argument("--resample-time", type=float, default=None, metavar="SECONDS",
                     help="seconds between draws of the parameter noise (default: the "
                     "preset's, 0: one draw per episode)")
    rep.add_argument("--hold-time", type=float, default=None, metavar="SECONDS",
                     help="decide every SECONDS and hold the action in between (default: the "
                     "preset's, 0: every control step)")
    rep.add_argument("--optimism", type=float, default=None, metavar="KAPPA",
                     help="guided_direction scores its candidates by the GP's mean plus KAPPA "
                     "times its standard deviation (default: the preset's, 0: the mean, as the "
                     "paper)")
    rep.add_argument("--episode-end", default=None, choices=["mask", "restart"],
                     help="on a task whose episodes end early: mask the slots after the end "
                     "(default) or restart the environment in them, so that every slot is an "
                     "environment step")


def _add_run_options(rep) -> None:
    """reproduce: other config fields, the seeds, the methods and the output."""
    from gpguided_jax import methods, settings
    from gpguided_jax.config import FIELD_GROUPS, METHODS, PAPER_METHODS

    own = [f"{m}: " + ", ".join(f"{name} ({default})" for name, default, _ in
                                settings.describe(methods.get(m).settings))
           for m in METHODS if methods.get(m).settings is not None]
    rep.add_argument("--set", nargs="+", default=None, metavar="FIELD=VALUE",
                     help="any other TrainConfig field (or discount_horizon, in seconds) or "
                          "method setting, for every method, e.g. --set num_updates=100 "
                          "learning_rate=0.01; applied after the preset and the method's tuned "
                          "settings (a method ignores another method's settings). The fields: "
                          + "; ".join(f"{g}: {', '.join(fs)}" for g, fs in FIELD_GROUPS.items())
                          + ". Each method's own settings (default): " + "; ".join(own))
    rep.add_argument("--seeds", type=positive_int, default=10, help="number of seeds")
    rep.add_argument("--seed-start", type=non_negative_int, default=REPORTED_SEED_START,
                     help="first seed (the reported results use seeds from 1000 on; the presets "
                     "were tuned on seeds below)")
    rep.add_argument("--methods", nargs="+", default=list(PAPER_METHODS), choices=list(METHODS),
                     metavar="METHOD", help=f"methods to run, of {', '.join(METHODS)} (default: "
                                            "the paper's)")
    rep.add_argument("--out", default="results/paper", help="output directory")
    rep.add_argument("--dtype", default="float64", choices=["float64", "float32"],
                     help="computation dtype of every array")
    rep.add_argument("--chunk-size", type=positive_int, default=50,
                     help="updates per compiled chunk (a checkpoint and a progress line after each)")
    rep.add_argument("--keep-checkpoints", action="store_true",
                     help="keep the checkpoints once the results are written (they are deleted)")


def _add_process_options(rep) -> None:
    """reproduce: several processes, and how the GP methods are compiled."""
    rep.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                     help="several processes (jax.distributed): process 0's address, the same "
                     "for every process")
    rep.add_argument("--num-processes", type=positive_int, default=None,
                     help="several processes: how many in all")
    rep.add_argument("--process-id", type=non_negative_int, default=None,
                     help="several processes: this one's index, 0 .. N-1 (0 writes the results)")
    rep.add_argument("--gp-program", default="shared", choices=["shared", "per-method"],
                     help="shared: the three GP methods run one compiled program, the "
                     "method an argument (compiled once); per-method: one program each (the "
                     "records agree to rounding)")
    rep.add_argument("--max-chunks", type=int, default=None, help=argparse.SUPPRESS)


def _add_baseline(sub) -> None:
    from gpguided_jax.config import BASELINE_PRESETS, PRESETS

    bl = sub.add_parser(
        "baseline",
        formatter_class=_DefaultsHelp,
        help="run brax's PPO or SAC on a standard task with a preset's budget",
        description="Runs brax's PPO or SAC on a standard task (gymnax:<id> or brax:<name>), one "
        "run per seed, with the preset's episode length and budget of environment steps (the "
        "methods' budget) and, for "
        f"{', '.join(sorted(BASELINE_PRESETS))}, its tuned settings; the deterministic policy is "
        "evaluated --evals times. brax runs whole iterations between evaluations, so it may run "
        "more steps than the budget: the command says so and reports the steps run; a budget "
        "too small for brax (SAC's replay buffer prefill, min_replay_size steps, must leave "
        "steps to train on) is refused, naming the smallest. Writes baseline_<algorithm>.npz "
        "(returns per seed and evaluation) and .json (settings, budget, steps run, wall time, "
        "final return IQM and steps to the task's threshold) to --out.",
    )
    bl.add_argument("algorithm", choices=("ppo", "sac"))
    bl.add_argument("--preset", default="pendulum-v1", choices=sorted(PRESETS),
                    help="budget, episode length, environment and tuned settings")
    bl.add_argument("--env", default=None, metavar="ENV",
                    help="another environment than the preset's (gymnax:<id> or brax:<name>)")
    bl.add_argument("--seeds", type=positive_int, default=10, help="number of seeds")
    bl.add_argument("--seed-start", type=non_negative_int, default=REPORTED_SEED_START,
                    help="first seed (the presets were tuned on seeds below 1000)")
    bl.add_argument("--steps", type=positive_int, default=None,
                    help="budget of environment steps (default: the preset's, updates x "
                    "episodes x episode length); brax rounds it up to whole iterations")
    bl.add_argument("--evals", type=positive_int, default=26,
                    help="evaluations, the initial policy's included (at least 2)")
    bl.add_argument("--hidden", type=positive_int, nargs="+", default=[64, 64],
                    help="hidden sizes of every MLP")
    bl.add_argument("--set", nargs="+", default=None, metavar="KEY=VALUE",
                    help="further trainer arguments, e.g. --set num_envs=4 batch_size=32")
    bl.add_argument("--out", default="results/baseline", help="output directory")
    _add_compile_cache(bl)
    bl.set_defaults(func=_cmd_baseline)


def _add_sweep(sub) -> None:
    from gpguided_jax.config import METHODS, PRESETS
    from gpguided_jax.sweep import ALIASES, sweepable_fields

    sw = sub.add_parser(
        "sweep",
        formatter_class=_DefaultsHelp,
        help="sweep one traced config field x seeds as one compiled program",
        description="Trains one method for every (value, seed) pair of a grid over one traced "
        "TrainConfig field, all runs as one compiled program (a chunk of updates at a time; on "
        "a CPU one device per core, each taking its runs one after another), then writes "
        "results.npz, sweep.csv (final performance: mean reward per step over "
        "the last 10% of updates, mean and 95% CI over seeds), config.json and "
        "sweep_<field>.png to --out. Static fields (sizes, method, controller, ...) cannot be "
        "swept this way.",
        epilog="sweepable fields: " + ", ".join(sweepable_fields()) + "; aliases: "
        + ", ".join(f"{a}={f}" for a, f in ALIASES.items())
        + ". Example: gpguided sweep --param lambda --values 0 10 100 400 1000 --method gp_pg "
        "--preset paper --seeds 5",
    )
    sw.add_argument("--param", required=True, help="the traced field to sweep (or an alias)")
    sw.add_argument("--values", required=True, nargs="+", type=float, help="its values")
    sw.add_argument("--method", default="gp_pg", choices=list(METHODS), help="the method trained")
    sw.add_argument("--preset", default="paper", choices=sorted(PRESETS),
                    help="budgets and settings (config.PRESETS)")
    sw.add_argument("--seeds", type=positive_int, default=5, help="seeds per value")
    sw.add_argument("--seed-start", type=non_negative_int, default=REPORTED_SEED_START,
                    help="first seed")
    sw.add_argument("--out", default=None, help="output directory (default results/sweep_<field>)")
    sw.add_argument("--dtype", default="float64", choices=["float64", "float32"],
                    help="computation dtype of every array")
    sw.add_argument("--chunk-size", type=positive_int, default=50,
                    help="updates per compiled chunk")
    sw.add_argument("--num-updates", type=positive_int, default=None,
                    help="override num_updates (quick runs)")
    sw.add_argument("--set", nargs="*", metavar="FIELD=VALUE",
                    help="further config overrides, e.g. --set gp_capacity=50 optimizer=adam")
    _add_device_options(sw, "runs")
    _add_compile_cache(sw)
    sw.set_defaults(func=_cmd_sweep)


def _add_bench(sub) -> None:
    from gpguided_jax.bench import MODEL_PRESET_TASKS, MODEL_SCALING_SEEDS, MODEL_TASKS, SECTIONS

    be = sub.add_parser(
        "bench",
        formatter_class=_DefaultsHelp,
        help="run the benchmarks and print (and write) a JSON report",
        description="Environment, sparse GP (against the NumPy reference), hyperparameter fit, "
        "training per method (against a per-seed NumPy loop), the whole `gpguided reproduce` "
        "command cold and warm, and where gp_model's update spends its time; medians of "
        "--repeats runs. See gpguided_jax/bench.py.",
    )
    be.add_argument("--repeats", type=positive_int, default=3, help="runs per figure (median)")
    be.add_argument("--seeds", type=positive_int, default=10, help="seeds of the paper run")
    be.add_argument("--numpy-updates", type=positive_int, default=50,
                    help="updates of the per-seed NumPy loop per run (median of --repeats runs, "
                    "extrapolated to the whole run)")
    be.add_argument("--no-paper-run", action="store_true",
                    help="skip the whole-command timing (the slowest part)")
    be.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS,
                    metavar="SECTION", help="the sections to run, of: " + " ".join(SECTIONS))
    be.add_argument("--merge", action="store_true",
                    help="write the sections run into the report at --out, keeping its others")
    be.add_argument("--model-tasks", nargs="+", default=None, choices=MODEL_PRESET_TASKS,
                    metavar="TASK", help="the tasks of the gp_model section, of: "
                    + " ".join(MODEL_PRESET_TASKS) + " (default: " + " ".join(MODEL_TASKS)
                    + "; --quick: pendulum-v1)")
    be.add_argument("--model-seeds", type=positive_int, default=2,
                    help="seeds of the gp_model section's parts")
    be.add_argument("--model-scaling-seeds", nargs="+", type=positive_int, default=None,
                    metavar="N", help="seed counts of the gp_model section's whole update "
                    "(default: " + " ".join(map(str, MODEL_SCALING_SEEDS)) + "; --quick: 1 2)")
    be.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test)")
    be.add_argument("--out", default=None, help="also write the JSON here (default: stdout only)")
    be.set_defaults(func=_cmd_bench)


def _one_line_error(parser: argparse.ArgumentParser):
    """A parser's `error` that says the message in one line on stderr (no usage), exit status 2."""
    def error(message):
        print(f"{parser.prog}: error: {message}", file=sys.stderr)
        sys.exit(2)

    return error


def _add_race(sub) -> None:
    ra = sub.add_parser(
        "race",
        formatter_class=_DefaultsHelp,
        help="gp_model against brax's SAC: wall time to the task's threshold, compile included",
        description="Runs gp_model at its preset (as `gpguided reproduce --methods gp_model`) and "
        "brax's SAC (as `gpguided baseline sac`) on a standard task, each seed of each method in "
        "a fresh process of its own, one after another, and reports each one's wall time from "
        "the start of its process to its first evaluation of the deterministic policy at or "
        "above the task's threshold, compilation included: with a cold compile cache (an empty "
        "directory) and a warm one (the directory the cold run filled); the median over seeds "
        "counts a seed that never reaches it as never. Writes race.json to --out and prints a "
        "table. See gpguided_jax/race.py.",
    )
    ra.error = _one_line_error(ra)
    ra.add_argument("--preset", default="pendulum-v1",
                    help="a standard task's preset on which gp_model and SAC both run "
                    "(pendulum-v1, mountaincar-continuous, inverted-pendulum, "
                    "inverted-double-pendulum)")
    ra.add_argument("--seeds", type=positive_int, default=10, help="number of seeds")
    ra.add_argument("--seed-start", type=non_negative_int, default=REPORTED_SEED_START,
                    help="first seed (the reported results' held-out seeds start at 1000)")
    ra.add_argument("--sac-steps", type=positive_int, default=None,
                    help="SAC's budget of environment steps (default: SAC's median steps to the "
                    "threshold in docs/results/standard/<preset>/heldout_table.json, else the "
                    "preset's budget)")
    ra.add_argument("--sac-evals", type=positive_int, default=26,
                    help="SAC's evaluations, the initial policy's included (at least 2)")
    ra.add_argument("--cache", default="cold,warm", metavar="STATES",
                    help="the compile cache states to race in: cold, warm or cold,warm (a warm "
                    "run needs the cold run before it, which then runs unreported)")
    ra.add_argument("--threshold", type=float, default=None,
                    help="another level than the task's threshold")
    ra.add_argument("--gp-set", nargs="+", default=None, metavar="FIELD=VALUE",
                    help="config fields over gp_model's preset, as `gpguided reproduce --set`")
    ra.add_argument("--sac-set", nargs="+", default=None, metavar="KEY=VALUE",
                    help="trainer arguments over SAC's tuned settings, as `gpguided baseline "
                    "--set`")
    ra.add_argument("--out", default="results/race", help="output directory")
    ra.set_defaults(func=_cmd_race)


def main(argv: list[str] | None = None) -> int:
    """Runs a command. A bad argument, an unusable output directory, a system error or an
    interrupt ends it with one line on stderr, not a traceback (exit status 2 for a bad argument,
    1 for the others, 130 for Ctrl-C)."""
    runtime.single_threaded_lapack()  # first: building the parser may import modules that load LAPACK
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        resume = (f"; run the same command again to resume from the checkpoints in {args.out}"
                  if args.command == "reproduce" else "")
        print(f"\ngpguided {args.command}: interrupted{resume}", file=sys.stderr)
        return 130
    except OSError as e:
        print(f"gpguided {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
