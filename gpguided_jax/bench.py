"""`gpguided bench`: the project's benchmarks in one JSON report (medians of several runs).

Sections (each a dict of figures; times in seconds, medians with min and max over `repeats`):

* ``env``: pendulum steps per second, 1 / 10 / 1000 vmapped 2000-step episodes.
* ``gp``: sparse GP updates per second on a pendulum-like stream (M = 100, 10 seeds, as training
  runs them: one after another on each device)
  against the NumPy reference (`gp_reference.OnlineGP`, one seed at a time), and their ratio.
* ``hyperfit``: the GP hyperparameter fit of the paper preset for the seeds (compile and run);
  ``hyperfit_alternative``: the same with the other optimiser (Adam 100 steps / L-BFGS 15).
* ``train``: per method, compile and run time of all `num_updates` updates for the seeds as one
  vmapped program, and seed-steps per second.
* ``capacity``: the cost of one update at each GP budget M (100 and 400 on the paper preset), of
  gp_pg (one ascent step) and gp_critic (its K surrogate steps besides), each a compiled chunk of
  updates over the seeds, timed apart from compilation.
* ``numpy_gp_pg``: the per-seed NumPy loop doing gp_pg's work (pendulum RK4, linear policy and its
  score, the reference GP, the gradient step) over a few updates, extrapolated to the whole run,
  and the ratio to the JAX gp_pg run.
* ``paper_run``: wall time of the whole `gpguided reproduce --preset paper` command for the seeds
  (subprocess; hyperparameter fit, compilation, checkpoints, figures), with an empty persistent
  compilation cache ("cold") and again with the cache it filled ("warm").
* ``model``: where gp_model's update spends its time, at its preset on each task
  (`MODEL_TASKS`) in float64 and float32: each part of one update (`MODEL_PARTS`: the update's
  episodes, the take-in, the conditioning on the old data with the error record, the refit, the
  conditioning after the take-in, the controller's optimisation, the evaluation episodes) as its
  own compiled program over the seeds, and the whole update, each timed apart from its
  compilation on the state after a few real updates; and the whole update's time for 1 to 100
  seeds (``seed_scaling``).

`python -m gpguided_jax.cli bench --out docs/results/bench.json` writes the report that the
benchmark table of docs/benchmarks.md is generated from (`experiments/docs_tables.py`).
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import (
    checkpoints,
    gp_reference,
    kernels,
    pendulum,
    reproduce,
    rollouts,
    sharding,
    sparse_gp,
)
from gpguided_jax import config as config_lib
from gpguided_jax import model_based as mb
from gpguided_jax import train as train_lib


def _stats(times) -> dict:
    return {"median": statistics.median(times), "min": min(times), "max": max(times),
            "runs": len(times)}


def _timed(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return times


def timed_in_turn(programs: dict, args: dict, repeats: int) -> dict:
    """Wall seconds of each program over `repeats` rounds, the programs run in turn (A B A B ...)
    so that their ratios hold when the CPU's speed drifts. `args[name]` is the tuple of
    arguments of `programs[name]`. Returns {name: [seconds, ...]}."""
    times = {k: [] for k in programs}
    for _ in range(repeats):
        for k, run in programs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(run(*args[k]))
            times[k].append(time.perf_counter() - t0)
    return times


def trees_equal(a, b) -> bool:
    """Whether two pytrees of arrays are equal bit for bit (leaf by leaf)."""
    return all(bool(np.array_equal(np.asarray(x), np.asarray(y)))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def print_report(report: dict, out: str | None = None) -> None:
    """Prints a benchmark's JSON report and, given `out`, writes it there too (atomically, the
    directory created if needed)."""
    import json

    text = json.dumps(report, indent=2)
    if out:
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        checkpoints.atomic_write_text(out, text + "\n")
    print(text)


def bench_env(repeats: int, steps: int = 2000, batches=(1, 10, 1000)) -> dict:
    params = pendulum.make_params()

    def policy(key, s):
        return -2.0 * jnp.sin(s[0]) - 0.3 * s[1] + 0.5 * jax.random.normal(key, (), s.dtype)

    def one(b):
        run = jax.jit(lambda keys: pendulum.batch_rollout(keys, params, policy, steps).rewards.sum())
        keys = jax.random.split(jax.random.key(0), b)
        jax.block_until_ready(run(keys))
        t = _stats(_timed(lambda: run(keys), repeats))
        return {"run_s": t, "steps_per_s": b * steps / t["median"]}

    return {f"episodes_{b}": one(b) for b in batches}


def _pendulum_stream(n: int, seed: int):
    rng = np.random.default_rng(seed)
    phi = np.pi - 0.5 + np.cumsum(rng.normal(0, 0.01, n))
    omega = np.cumsum(rng.normal(0, 0.02, n)) % 4 - 2
    a = np.clip(rng.normal(2, 1.5, n), -6, 6)
    xs = np.stack([np.sin(phi), np.cos(phi), omega, a], 1)
    ys = -10 * (phi - np.pi) ** 2 - 10 * omega**2 / 16 - 0.1 * a**2 - 5 + rng.normal(0, 0.1, n)
    return xs, ys


GP_SETTINGS = dict(lengthscales=[0.3, 0.3, 1.0, 3.0], signal_variance=30.0, noise_variance=0.01,
                   novelty_tol=1e-4, age_penalty=100.0, age_scale=1.0)


PAIRS_PER_STAMP = 150  # the streams' timestamps advance every 150 pairs, as an update's episodes


def gp_streams(seeds: int, n: int, dtype=None):
    """`seeds` pendulum-like streams of n (x, y) pairs: xs (seeds, n, 4) and ys (seeds, n) as
    arrays, and the list of NumPy (x, y) streams they were made from."""
    streams = [_pendulum_stream(n, i) for i in range(seeds)]
    xs = jnp.asarray(np.stack([a for a, _ in streams]), dtype)
    ys = jnp.asarray(np.stack([b for _, b in streams]), dtype)
    return xs, ys, streams


def gp_stream_program(mesh, n: int, capacity: int, dtype=None):
    """The per-seed program (over `mesh`, `sharding.per_seed_program`) that takes one stream of n
    pairs into an empty GP of `capacity` with `GP_SETTINGS`: `gpguided bench`'s sparse-GP figure."""
    s = GP_SETTINGS
    hyper = kernels.make_kernel_params(s["lengthscales"], s["signal_variance"], s["noise_variance"],
                                       dtype=dtype)
    kw = dict(novelty_tol=s["novelty_tol"], age_penalty=s["age_penalty"], age_scale=s["age_scale"])
    ts = jnp.arange(n) // PAIRS_PER_STAMP
    return sharding.per_seed_program(lambda x, y: sparse_gp.update_batch(
        sparse_gp.init(capacity, 4, dtype), x, y, hyper, ts, **kw), mesh)


def bench_gp(repeats: int, seeds: int = 10, n: int = 3000, capacity: int = 100,
             numpy_points: int = 1500) -> dict:
    s = GP_SETTINGS
    kw = dict(novelty_tol=s["novelty_tol"], age_penalty=s["age_penalty"], age_scale=s["age_scale"])
    xs, ys, streams = gp_streams(seeds, n)
    mesh = sharding.make_mesh(None, seeds)  # as training runs it: seeds over devices, per device
    if seeds % mesh.devices.size:            # one after another on a CPU (`per_seed_program`)
        mesh = sharding.make_mesh(1)
    xs, ys = sharding.shard((xs, ys), mesh)
    run = gp_stream_program(mesh, n, capacity)
    t0 = time.perf_counter()
    jax.block_until_ready(run(xs, ys))
    compile_s = time.perf_counter() - t0
    jax_t = _stats(_timed(lambda: run(xs, ys), repeats))
    x0, y0 = streams[0]
    np_times = []
    for _ in range(repeats):
        ref = gp_reference.OnlineGP(capacity, 4, s["lengthscales"], s["signal_variance"],
                                    s["noise_variance"], **kw)
        t0 = time.perf_counter()
        for i in range(numpy_points):
            ref.update(x0[i], y0[i], i // PAIRS_PER_STAMP)
        np_times.append(time.perf_counter() - t0)
    np_t = _stats(np_times)
    jax_rate = seeds * n / jax_t["median"]
    np_rate = numpy_points / np_t["median"]
    return {"capacity": capacity, "seeds": seeds, "points_per_seed": n, "compile_s": compile_s,
            "devices": int(mesh.devices.size),
            "jax_run_s": jax_t, "jax_updates_per_s": jax_rate, "numpy_run_s": np_t,
            "numpy_points": numpy_points, "numpy_updates_per_s": np_rate,
            "ratio": jax_rate / np_rate}


def numpy_gp_pg_seconds_per_update(cfg, prior, num_updates, rng) -> float:
    """Per-seed NumPy Algorithm 1 (gp_pg, linear controller): wall seconds per update."""
    kernel, m0 = prior.kernel, float(prior.mean)
    p = cfg.pendulum
    m, l, g, dt = float(p.mass), float(p.length), float(p.gravity), float(p.dt)
    b, umax, noise = float(p.friction), float(p.max_torque), float(p.reward_noise_std)
    gamma, lr = float(cfg.discount), float(cfg.learning_rate)
    w, log_std = np.zeros(4), float(cfg.init_log_std)
    gp = gp_reference.OnlineGP(
        cfg.gp_capacity, 4, np.asarray(kernel.lengthscales), float(kernel.signal_variance),
        float(kernel.noise_variance), novelty_tol=float(cfg.novelty_tol),
        age_penalty=float(cfg.age_penalty), age_scale=float(cfg.age_scale), age_fn=cfg.age_fn)

    def f(y, u):
        return np.array([y[1], (u - b * y[1] - m * g * l * math.sin(y[0])) / (m * l * l)])

    t0 = time.perf_counter()
    for t in range(num_updates):
        scores, feats = [], []
        for _ in range(cfg.episodes_per_update):
            s = np.asarray(p.start_mean, float) + np.asarray(p.start_std, float) * rng.normal(size=2)
            s[0] %= 2 * math.pi
            rewards = []
            for _ in range(cfg.episode_length):
                psi = np.array([math.sin(s[0]), math.cos(s[0]), s[1], 1.0])
                z = math.tanh(w @ psi)
                c = 5.0 * z
                sigma = math.exp(log_std)
                a = c + sigma * rng.normal()
                dc = 5.0 * (1 - z * z) * psi
                scores.append(np.append((a - c) / sigma**2 * dc, (a - c) ** 2 / sigma**2 - 1.0))
                feats.append(np.array([psi[0], psi[1], s[1], a]))
                u = min(max(a, -umax), umax)
                k1 = f(s, u)
                k2 = f(s + 0.5 * dt * k1, u)
                k3 = f(s + 0.5 * dt * k2, u)
                k4 = f(s + dt * k3, u)
                s = s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                s[0] %= 2 * math.pi
                rewards.append(-(s[0] - math.pi) ** 2 - (s[1] / 4) ** 2 + noise * rng.normal())
            ret, acc = np.zeros(len(rewards)), 0.0
            for i in reversed(range(len(rewards))):
                acc = rewards[i] + gamma * acc
                ret[i] = acc
            for x, y in zip(feats[-cfg.episode_length:], ret):
                gp.update(x, y - m0, t)
        q = m0 + np.array([gp.predict(x)[0] for x in feats])
        grad = (np.array(scores) * q[:, None]).sum(0) / cfg.episodes_per_update
        norm = np.linalg.norm(grad)
        if norm > float(cfg.max_grad_norm):
            grad = grad * float(cfg.max_grad_norm) / norm
        w = w + lr * grad[:4]
        log_std = float(np.clip(log_std + lr * grad[4], math.log(cfg.min_std), math.log(cfg.max_std)))
    return (time.perf_counter() - t0) / num_updates


def seed_mesh(seeds: int):
    """The mesh `gpguided reproduce` uses for seeds 0 .. seeds-1 in one process, and their keys
    (padded to the mesh) sharded over it: (mesh, keys)."""
    mesh = sharding.make_mesh(None, seeds)
    keys = sharding.seed_keys(sharding.pad_seeds(range(seeds), mesh.devices.size))
    return mesh, sharding.shard(keys, mesh)


def initial_states(cfg, mesh, keys, priors):
    """The seeds' initial `TrainState`s as `gpguided reproduce` makes them: a GP method starts from
    the fitted `priors` (shared by the GP methods), REINFORCE from none."""
    train = train_lib.make_train(cfg)
    if cfg.uses_gp:
        return sharding.per_seed_program(lambda k, p: train.init(k, cfg, p), mesh)(keys, priors)
    return sharding.per_seed_program(lambda k: train.init(k, cfg), mesh)(keys)


def compiled_gp_methods_program(preset: str, methods, mesh, seed_loop: str, keys, priors):
    """The GP methods' one program (`reproduce.gp_methods_program`, without donation: timed
    repeatedly on the same states) for `preset`'s whole run, compiled once. Returns (compiled,
    compile seconds, {method: (cfg, arguments)}), each method's arguments its initial states from
    `priors` and its `reproduce.gp_method_args`."""
    cfg0 = config_lib.preset(preset, method=methods[0])
    program = reproduce.gp_methods_program(cfg0, mesh, seed_loop, cfg0.num_updates, donate=False)
    runs = {}
    for method in methods:
        cfg = config_lib.preset(preset, method=method)
        runs[method] = cfg, (initial_states(cfg, mesh, keys, priors),
                             *reproduce.gp_method_args(cfg, len(keys), mesh))
    t0 = time.perf_counter()
    compiled = program.lower(*runs[methods[0]][1]).compile()
    return compiled, time.perf_counter() - t0, runs


def bench_train(repeats: int, seeds: int, numpy_updates: int, preset: str = "paper",
                methods=config_lib.PAPER_METHODS) -> dict:
    """The hyperparameter fit and the whole run of each of `methods` in its own program, and the
    three GP methods' shared program, compiled as `gpguided reproduce` compiles them
    (`sharding.per_seed_program` over the seed mesh), timed apart from compilation."""
    mesh, keys = seed_mesh(seeds)
    out: dict = {"seeds": seeds, "devices": [str(d) for d in mesh.devices.flat],
                 "seed_loop": sharding.resolve_seed_loop("auto", mesh), "methods": {}}
    cfg_gp = config_lib.preset(preset, method="gp_pg")

    def compiled_fit(cfg):
        fit = sharding.per_seed_program(train_lib.make_train(cfg).fit_kernel_for_seed, mesh)
        t0 = time.perf_counter()
        compiled = fit.lower(keys).compile()
        return compiled, time.perf_counter() - t0

    fit, fit_compile = compiled_fit(cfg_gp)
    fit_t = _stats(_timed(lambda: fit(keys), repeats))
    priors = fit(keys)
    out["hyperfit"] = {"compile_s": fit_compile, "run_s": fit_t,
                       "optimizer": cfg_gp.hyperfit_optimizer, "steps": cfg_gp.hyperfit_steps}
    # the other optimiser, for comparison (not used by the run)
    other = {"adam": ("lbfgs", 15), "lbfgs": ("adam", 100)}[cfg_gp.hyperfit_optimizer]
    alt, alt_compile = compiled_fit(cfg_gp.replace(hyperfit_optimizer=other[0],
                                                   hyperfit_steps=other[1]))
    out["hyperfit_alternative"] = {
        "compile_s": alt_compile, "run_s": _stats(_timed(lambda: alt(keys), repeats)),
        "optimizer": other[0], "steps": other[1]}

    def one(method):
        cfg = config_lib.preset(preset, method=method)
        train = train_lib.make_train(cfg)
        state = initial_states(cfg, mesh, keys, priors)
        run = sharding.per_seed_program(lambda s: train.run_chunk(s, cfg, cfg.num_updates), mesh)
        t0 = time.perf_counter()
        compiled = run.lower(state).compile()
        compile_s = time.perf_counter() - t0
        t = _stats(_timed(lambda: compiled(state), repeats))
        steps = seeds * cfg.num_updates * cfg.episodes_per_update * cfg.episode_length
        return {"compile_s": compile_s, "run_s": t, "seed_steps_per_s": steps / t["median"]}

    for method in methods:
        out["methods"][method] = one(method)

    # The GP methods as `gpguided reproduce` runs them by default: one program, compiled once.
    compiled, compile_s, runs = compiled_gp_methods_program(preset, train_lib.program_family(cfg_gp), mesh,
                                                            out["seed_loop"], keys, priors)
    out["gp_methods_program"] = {
        "compile_s": compile_s,
        "methods": {m: {"run_s": _stats(_timed(lambda a=a: compiled(*a), repeats))}
                    for m, (_, a) in runs.items()}}
    prior0 = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], jax.device_get(priors))
    # the same updates (same draws) `repeats` times: the median is the figure, as on the JAX side
    numpy_t = _stats([numpy_gp_pg_seconds_per_update(cfg_gp, prior0, numpy_updates,
                                                     np.random.default_rng(0))
                      for _ in range(repeats)])
    per_update = numpy_t["median"]
    numpy_run = per_update * cfg_gp.num_updates * seeds
    out["numpy_gp_pg"] = {"measured_updates": numpy_updates, "seconds_per_update": numpy_t,
                          "seconds_per_update_one_seed": per_update,
                          "extrapolated_run_s": numpy_run,
                          "ratio_jax_over_numpy": numpy_run / out["methods"]["gp_pg"]["run_s"]["median"]}
    own = out["methods"]
    shared = out["gp_methods_program"]
    out["in_process_total_per_method_s"] = (fit_compile + fit_t["median"] + sum(
        m["compile_s"] + m["run_s"]["median"] for m in own.values()))
    out["in_process_total_s"] = (  # as `gpguided reproduce` compiles: the GP methods share one
        fit_compile + fit_t["median"] + own["reinforce"]["compile_s"]
        + own["reinforce"]["run_s"]["median"] + shared["compile_s"]
        + sum(m["run_s"]["median"] for m in shared["methods"].values()))
    return out


def bench_capacity(repeats: int, seeds: int, preset: str = "paper", capacities=(100, 400),
                   methods=("gp_pg", "gp_critic"), updates: int = 10) -> dict:
    """Seconds per update of each of `methods` at each GP budget M in `capacities`: a compiled
    chunk of `updates` updates for the seeds (each from the state after the fit; the buffers are
    of fixed size, so an update costs the same however full the GP is), its median run over
    `repeats` divided by `updates`."""
    mesh, keys = seed_mesh(seeds)
    out: dict = {"preset": preset, "seeds": seeds, "updates": updates, "capacities": {}}
    for m in capacities:
        row = {}
        for method in methods:
            cfg = config_lib.preset(preset, method=method, gp_capacity=m, num_updates=updates)
            train = train_lib.make_train(cfg)
            state = jax.block_until_ready(
                sharding.per_seed_program(lambda k, c=cfg, t=train: t.init(k, c), mesh)(keys))
            run = sharding.per_seed_program(lambda s, c=cfg, t=train: t.run_chunk(s, c, updates),
                                            mesh)
            t0 = time.perf_counter()
            compiled = run.lower(state).compile()
            compile_s = time.perf_counter() - t0
            t = _stats([x / updates for x in _timed(lambda f=compiled, s=state: f(s), repeats)])
            row[method] = {"compile_s": compile_s, "per_update_s": t}
        out["capacities"][str(m)] = row
    return out


def bench_paper_run(repeats: int, seeds: int, preset: str = "paper",
                    methods: tuple[str, ...] = config_lib.PAPER_METHODS) -> dict:
    """`gpguided reproduce` as a user runs it, cold (empty compilation cache) and warm."""
    cold, warm = [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d:
            cache = os.path.join(d, "cache")
            for times in (cold, warm):
                out = os.path.join(d, f"out{len(times)}-{times is warm}")
                cmd = [sys.executable, "-m", "gpguided_jax.cli", "reproduce", "--preset", preset,
                       "--seeds", str(seeds), "--methods", *methods, "--out", out,
                       "--compile-cache", cache]
                t0 = time.perf_counter()
                proc = subprocess.run(cmd, capture_output=True, text=True)
                times.append(time.perf_counter() - t0)
                if proc.returncode != 0:
                    raise RuntimeError(proc.stderr[-2000:])
    return {"seeds": seeds, "methods": list(methods), "cold_s": _stats(cold),
            "warm_s": _stats(warm)}


# gp_model's tasks whose preset is cheap enough for every `gpguided bench`; the others
# (`MODEL_PRESET_TASKS`) on request (`--model-tasks`)
MODEL_TASKS = ("pendulum-v1", "mountaincar-continuous", "inverted-pendulum")
MODEL_PRESET_TASKS = tuple(mb.method.PRESETS)
# the parts of one gp_model update, in the order it runs them (the evaluation episodes last)
MODEL_PARTS = ("episodes", "take_in", "condition_before", "refit", "condition_after", "optimise",
               "evaluation")
MODEL_SCALING_SEEDS = (1, 10, 30, 100)
# `--quick`: sizes at which every part compiles and runs in moments (the section's shape, not
# its figures)
QUICK_MODEL = dict(episode_length=50, num_updates=3, eval_episodes=2, model_inducing=16,
                   model_particles=4, model_steps=30, model_fit_steps=20, model_fit_subset=32,
                   model_horizon=0.5)


def model_parts(cfg) -> dict:
    """gp_model's update (`train.one_update` with `model_based.update`) of `cfg` in parts, each a
    function of one seed: name -> (function, names of its arguments). Their arguments are the
    update's state (``state``) and the parts' outputs before them (``episodes``, ``take_in``,
    ``refit``, ``condition_after``), so that each part runs on what the update hands it; their
    draws are the update's (`train.update_keys`, `model_based.model_keys`). ``update`` is the
    whole update (`make_train(cfg).run_chunk` for one update)."""
    train = train_lib.make_train(cfg)
    prog, own = train.program, cfg.settings

    def episodes(state):
        _, keys, _ = train_lib.update_keys(prog, state)
        return train_lib.roll_out_and_take_in(prog, cfg, state, keys)[1]

    def take_in(state, eps):
        tr = mb.transitions(prog, cfg, eps)
        return mb.take_in(state.method_state, tr.inputs, tr.targets, tr.valid), tr

    def condition_before(state, taken):
        return mb.model_errors(prog, cfg, state.method_state, taken[1])

    def refit(state, taken):
        k_fit, _ = mb.model_keys(state)
        return mb.refit(k_fit, taken[0], subset_size=own.fit_subset, num_steps=own.fit_steps,
                        first=state.method_state.count == 0)

    def condition_after(taken, log_kernels):
        return mb.build(taken[0]._replace(log_kernels=log_kernels), own.inducing)

    def optimise(state, taken, conditioned):
        _, k_plan = mb.model_keys(state)
        model, target_mean = conditioned
        return mb.improve(prog, cfg, model, target_mean, k_plan, state.theta.controller,
                          taken[0].hallucination)

    def evaluation(state):
        _, _, key_eval = train_lib.update_keys(prog, state)
        return rollouts.evaluate(prog, key_eval, state.theta, cfg)

    def update(state):
        return train.run_chunk(state, cfg, 1)

    return {"episodes": (episodes, ("state",)), "take_in": (take_in, ("state", "episodes")),
            "condition_before": (condition_before, ("state", "take_in")),
            "refit": (refit, ("state", "take_in")),
            "condition_after": (condition_after, ("take_in", "refit")),
            "optimise": (optimise, ("state", "take_in", "condition_after")),
            "evaluation": (evaluation, ("state",)), "update": (update, ("state",))}


def _compiled(fn, mesh, args):
    """`fn` as a per-seed program over `mesh`, compiled for `args`: (compiled, seconds)."""
    t0 = time.perf_counter()
    compiled = sharding.per_seed_program(fn, mesh).lower(*args).compile()
    return compiled, time.perf_counter() - t0


def model_config(task: str, dtype: str, quick: bool = False, **overrides):
    """gp_model's config at its preset on `task` in `dtype` (`QUICK_MODEL`'s sizes if `quick`)."""
    return config_lib.preset(task, method="gp_model", dtype=dtype,
                             **{**(QUICK_MODEL if quick else {}), **overrides})


def bench_model_parts(repeats: int, cfg, seeds: int, warm_updates: int,
                      progress=lambda m: None) -> dict:
    """The parts of one update of `cfg` (`model_parts`) and the whole update, each compiled apart,
    on the seeds' state after `warm_updates` real updates (the whole update's program run that
    many times from the initial state), timed in turn (`timed_in_turn`) over `repeats` rounds.
    Per part: compile seconds, the program's run seconds for all seeds (median, min, max) and
    that median over the seeds (`per_seed_s`); the parts' sum and its ratio to the whole."""
    mesh, keys = seed_mesh(seeds)
    train = train_lib.make_train(cfg)
    state = jax.block_until_ready(
        sharding.per_seed_program(lambda k: train.init(k, cfg), mesh)(keys))
    parts = model_parts(cfg)
    compiled, compile_s = {}, {}
    compiled["update"], compile_s["update"] = _compiled(parts["update"][0], mesh, (state,))
    for _ in range(warm_updates):
        state = jax.block_until_ready(compiled["update"](state)[0])
    outputs, args = {"state": state}, {"update": (state,)}
    for name in MODEL_PARTS:
        progress(f"bench: gp_model on {cfg.env}, {cfg.dtype}: {name}")
        fn, takes = parts[name]
        args[name] = tuple(outputs[t] for t in takes)
        compiled[name], compile_s[name] = _compiled(fn, mesh, args[name])
        outputs[name] = jax.block_until_ready(compiled[name](*args[name]))
    times = timed_in_turn({k: compiled[k] for k in (*MODEL_PARTS, "update")}, args, repeats)
    n = len(keys)
    out = {k: {"compile_s": compile_s[k], "run_s": _stats(v), "per_seed_s": _stats(v)["median"] / n}
           for k, v in times.items()}
    parts_sum = sum(out[k]["run_s"]["median"] for k in MODEL_PARTS)
    own = cfg.settings
    data = state.method_state
    return {
        "env": cfg.env, "dtype": cfg.dtype, "seeds": n, "devices": int(mesh.devices.size),
        "warm_updates": warm_updates,
        "settings": {"episode_length": cfg.episode_length, "episodes": cfg.episodes_per_update,
                     "eval_episodes": cfg.eval_episodes, "hold": train.program.hold,
                     "capacity": int(data.valid.shape[1]), "inducing": own.inducing,
                     "fit_subset": own.fit_subset, "fit_steps": own.fit_steps,
                     "particles": own.particles, "steps": own.steps,
                     "plan_steps": mb.plan_steps(train.program, cfg),
                     "exploration": own.exploration,
                     "outputs": int(data.targets.shape[-1])},
        "buffer_transitions": float(jnp.mean(jnp.sum(data.valid, axis=1))),
        "parts": {k: out[k] for k in MODEL_PARTS}, "update": out["update"],
        "parts_sum_s": parts_sum, "parts_over_update": parts_sum / out["update"]["run_s"]["median"],
        "parts_compile_sum_s": sum(out[k]["compile_s"] for k in MODEL_PARTS),
    }


def bench_model_scaling(repeats: int, cfg, seed_counts, progress=lambda m: None) -> dict:
    """The whole update of `cfg` (`make_train(cfg).run_chunk`, one update) for each number of
    seeds in `seed_counts`, compiled apart, then run once from the initial state (the first run
    warms the caches; its state is the one timed) and `repeats` times more."""
    rows = []
    train = train_lib.make_train(cfg)
    for seeds in seed_counts:
        progress(f"bench: gp_model on {cfg.env}, {cfg.dtype}: the whole update, {seeds} seeds")
        mesh, keys = seed_mesh(seeds)
        state = jax.block_until_ready(
            sharding.per_seed_program(lambda k: train.init(k, cfg), mesh)(keys))
        run, compile_s = _compiled(lambda s: train.run_chunk(s, cfg, 1), mesh, (state,))
        state = jax.block_until_ready(run(state)[0])
        t = _stats(_timed(lambda r=run, s=state: r(s), repeats))
        rows.append({"seeds": len(keys), "devices": int(mesh.devices.size), "compile_s": compile_s,
                     "run_s": t, "per_seed_s": t["median"] / len(keys)})
    return {"env": cfg.env, "dtype": cfg.dtype, "rows": rows}


def bench_model(repeats: int, *, tasks=MODEL_TASKS, dtypes=("float64", "float32"), seeds: int = 2,
                warm_updates: int = 3, scaling_seeds=MODEL_SCALING_SEEDS,
                scaling_task: str = "pendulum-v1", quick: bool = False,
                progress=lambda m: None) -> dict:
    """gp_model's update in parts on each of `tasks` in each of `dtypes` (`bench_model_parts`),
    and its whole update over `scaling_seeds` seeds on `scaling_task` in the first of `dtypes`
    (`bench_model_scaling`). float64 needs JAX's x64 mode (`gpguided bench` turns it on). The
    section names its own repeats, date and load, so that it can be merged into a report whose
    other sections were run at another time (`merge_reports`)."""
    out: dict = {"repeats": repeats, "quick": quick, "date": time.strftime("%Y-%m-%d"),
                 "jax": jax.__version__, "cpu_count": os.cpu_count(), "tasks": {}}
    for task in tasks:
        out["tasks"][task] = {
            dtype: bench_model_parts(repeats, model_config(task, dtype, quick), seeds,
                                     warm_updates, progress)
            for dtype in dtypes}
    out["seed_scaling"] = {"task": scaling_task, **bench_model_scaling(
        repeats, model_config(scaling_task, dtypes[0], quick), scaling_seeds, progress)}
    out["load_average_after"] = list(os.getloadavg())
    return out


SECTIONS = ("env", "gp", "train", "capacity", "paper_run", "model")


def merge_reports(old: dict, new: dict, sections) -> dict:
    """`old` (a report) with the `sections` of `new` in place of its own: a section run alone,
    written into a report whose other sections (and their metadata) stay as they were."""
    return {**old, **{k: new[k] for k in sections if k in new}}


def run(*, repeats: int = 3, seeds: int = 10, numpy_updates: int = 50, quick: bool = False,
        paper_run: bool = True, sections=SECTIONS, model_tasks=None, model_seeds: int = 2,
        model_scaling_seeds=None,
        progress=lambda m: print(m, file=sys.stderr, flush=True)) -> dict:
    """The `sections` (`SECTIONS`; ``paper_run`` only if `paper_run` too); `quick` shrinks every
    size (for the tests). `model_tasks` and `model_scaling_seeds` default to `MODEL_TASKS` and
    `MODEL_SCALING_SEEDS` (quick: Pendulum-v1 alone, 1 and 2 seeds)."""
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        raise ValueError(f"unknown bench sections {sorted(unknown)}; choose from {SECTIONS}")
    report = {
        "jax": jax.__version__, "numpy": np.__version__, "python": platform.python_version(),
        "devices": [str(d) for d in jax.devices()], "cpu_count": os.cpu_count(),
        "platform": platform.platform(), "dtype": str(jnp.result_type(float)),
        "date": time.strftime("%Y-%m-%d"), "repeats": repeats, "quick": quick,
    }
    if "env" in sections:
        progress("bench: environment")
        report["env"] = bench_env(repeats, steps=200 if quick else 2000,
                                  batches=(1, 10) if quick else (1, 10, 1000))
    if "gp" in sections:
        progress("bench: sparse GP")
        report["gp"] = bench_gp(repeats, seeds=2 if quick else 10, n=300 if quick else 3000,
                                capacity=20 if quick else 100, numpy_points=100 if quick else 1500)
    preset = "tiny" if quick else "paper"
    if "train" in sections:
        progress("bench: training")
        # quick: each method's own program for REINFORCE and gp_pg alone (the ratio's two sides)
        report["train"] = bench_train(repeats, 2 if quick else seeds, 1 if quick else numpy_updates,
                                      preset, ("reinforce", "gp_pg") if quick
                                      else config_lib.PAPER_METHODS)
    if "capacity" in sections:
        progress("bench: cost per update at each GP budget")
        # quick: gp_critic at one small budget (the section's shape, not its figures)
        report["capacity"] = bench_capacity(
            repeats, 2 if quick else seeds, preset, (16,) if quick else (100, 400),
            ("gp_critic",) if quick else ("gp_pg", "gp_critic"), 2 if quick else 10)
    if paper_run and "paper_run" in sections:
        progress("bench: the whole reproduce command, cold and warm")
        # quick (the tests): the command timed once, with REINFORCE alone, whose compile is the
        # shortest (with the four methods the cold and warm runs would take most of the time)
        report["paper_run"] = bench_paper_run(
            1 if quick else repeats, 2 if quick else seeds, preset,
            ("reinforce",) if quick else config_lib.PAPER_METHODS)
    if "model" in sections:
        progress("bench: where gp_model's update spends its time")
        if model_tasks is None:
            model_tasks = ("pendulum-v1",) if quick else MODEL_TASKS
        if model_scaling_seeds is None:
            model_scaling_seeds = (1, 2) if quick else MODEL_SCALING_SEEDS
        report["model"] = bench_model(repeats, tasks=tuple(model_tasks), seeds=model_seeds,
                                      warm_updates=1 if quick else 3,
                                      scaling_seeds=tuple(model_scaling_seeds), quick=quick,
                                      progress=progress)
    report["load_average_after"] = list(os.getloadavg())
    return report
