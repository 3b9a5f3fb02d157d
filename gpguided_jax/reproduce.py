"""The run driver: chunked, resumable, device-sharded runs of every method over many seeds
(Fig. 5). `gpguided reproduce` is a thin wrapper over `reproduce`, which reads as one pass:

  configs -> config.json -> fitted GP priors (kernels.npz) -> each method, a chunk at a time
  (checkpoint_<method>.npz) -> results.npz -> summary.csv + comparisons.csv -> Fig. 5 PNGs.

It leans on `sharding` (seeds over devices, per-seed programs), `checkpoints` (atomic files,
checkpoints), `summaries` (summary and comparison tables) and `plots` (Fig. 5). Here: the
compiled programs of a run, kept for the process (`fit_program`, `init_program`,
`chunk_program`, `gp_methods_program`), the GP priors (`fit_priors`), one method's run
(`run_method`) and the whole one (`reproduce`).

Output directory layout (every file is written atomically: to a temporary name, then renamed):
  config.json              resolved config of every method (+ seeds, chunk size, devices, dtype)
  kernels_<method>.npz     a method's fitted prior per seed (GP hyperparameters and prior mean;
                           fitted once for the methods whose fit inputs agree)
  checkpoint_<method>.npz  state after the last finished chunk and the records so far
  results.npz              methods, seeds, per-update records of shape (methods, seeds, updates)
                           (NaN past a method's last update, or for a record it does not keep),
                           num_updates (methods,) and env_steps (methods, updates), the
                           environment steps spent by the end of each update (the prior's
                           fit included), where the records of the update's own episodes
                           were taken (a record of the deterministic policy, eval_*, was
                           taken one update earlier: `summaries.env_steps_axis`)
  summary.csv              per method: final performance (mean and t-interval; IQM and stratified
                           bootstrap interval), updates to 90%, failing seeds by cause
  comparisons.csv          probability of improvement (rliable) of each GP method over REINFORCE
                           and of each guided method over gp_pg, with bootstrap intervals
  fig5_reward.png, fig5_exploration.png
  index.html               the run's report for a browser: the figures, the summary and
                           comparison tables and the config (`report`)

A checkpoint or kernels file that cannot be read is renamed to `<name>.corrupt` (the log says so)
and that part of the run starts afresh.
"""

from __future__ import annotations

import functools
import json
import os
import sys
import time
from typing import Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh

from gpguided_jax import checkpoints, distributed, plots, report, sharding, summaries
from gpguided_jax import config as config_lib
from gpguided_jax import kernels as kernels_lib
from gpguided_jax import methods as methods_lib
from gpguided_jax import train as train_lib

GP_PROGRAMS = ("shared", "per_method")


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _silent(msg: str) -> None:
    del msg


def _check_gp_program(gp_program: str) -> None:
    if gp_program not in GP_PROGRAMS:
        raise ValueError(f"gp_program must be one of {GP_PROGRAMS}, got {gp_program!r}")


# ------------------------------------------------------------------------------------------------
# The compiled programs of a run, kept for the process.
# ------------------------------------------------------------------------------------------------

_SHARED_PROGRAMS: dict = {}  # (static config, mesh, loop, updates, donate) -> jitted chunk program
_FIT_PROGRAMS: dict = {}  # (config but the method, mesh, loop) -> jitted hyperparameter fit
_OWN_PROGRAMS: dict = {}  # (kind, config, mesh, loop, ...) -> a method's own init or chunk program
_PROGRAMS_KEPT = 8  # per cache: the last few


def _kept(cache: dict, key, make: Callable):
    """`cache[key]`, made by `make()` if missing; the cache keeps the last `_PROGRAMS_KEPT`. A
    process that runs `reproduce` again (a notebook, the tests) then reuses the jitted programs
    (the fit, the initial states, the chunks): tracing and compiling them again would take most
    of a small run's time."""
    program = cache.get(key)
    if program is None:
        while len(cache) >= _PROGRAMS_KEPT:
            cache.pop(next(iter(cache)))
        program = cache[key] = make()
    return program


def _config_key(cfg: config_lib.TrainConfig) -> str:
    """A config's every field, as a cache key (the programs bake its values in)."""
    return json.dumps(cfg.to_json_dict(), sort_keys=True)


def fit_program(train, mesh: Mesh, seed_loop: str):
    """The jitted hyperparameter fit `fit(keys) -> GPPrior` of `train` (from `train.make_train`)
    over the sharded seed axis, kept for the process: one for every GP method of a config."""
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    key = (json.dumps(methods_lib.fit_inputs(train.config), sort_keys=True), mesh, loop)
    return _kept(_FIT_PROGRAMS, key,
                 lambda: sharding.per_seed_program(train.fit_kernel_for_seed, mesh, loop))


def init_program(train, mesh: Mesh, seed_loop: str, with_kernels: bool):
    """The jitted initial states of `train` (from `train.make_train`) over the sharded seed axis,
    `init(keys[, kernels])`, kept for the process (`_kept`)."""
    cfg = train.config
    loop = sharding.resolve_seed_loop(seed_loop, mesh)

    def make():
        return sharding.per_seed_program((lambda k, kern: train.init(k, cfg, kern)) if with_kernels
                                         else (lambda k: train.init(k, cfg)), mesh, loop)

    return _kept(_OWN_PROGRAMS, ("init", _config_key(cfg), mesh, loop, with_kernels), make)


def chunk_program(train, mesh: Mesh, seed_loop: str, num_updates: int, gp_program: str = "shared"):
    """The compiled chunk of `num_updates` updates that `run_method` runs for `train`'s config
    (`train` from `train.make_train`), as `step(state) -> (state, records)` over the sharded seed
    axis (the state's buffers donated).

    With `gp_program='shared'` (the default) every method of `train.program_family(cfg)` (the
    methods that share a prior and an improvement step and accept the config: the three GP
    methods of the paper) runs the same program (`train.make_methods_train`, the method and the
    traced config its arguments): it is traced and compiled once per process for all of them,
    and is the same program whichever of them a run asks for, so a method's records do not
    depend on the others. 'per_method' compiles `train.run_chunk` for each method (the records
    agree with the shared program's to rounding). A method alone in its family (REINFORCE) always
    has its own program.
    """
    _check_gp_program(gp_program)
    cfg = train.config
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    if _program_kind(cfg, gp_program) == "per_method":
        def make():
            return sharding.per_seed_program(lambda s: train.run_chunk(s, cfg, num_updates), mesh,
                                             loop, donate=True)

        return _kept(_OWN_PROGRAMS, ("chunk", _config_key(cfg), mesh, loop, num_updates), make)
    program = gp_methods_program(cfg, mesh, loop, num_updates)
    args = {}  # the method index and the config, one row per seed, placed once

    def step(state):
        seeds = jax.tree_util.tree_leaves(state)[0].shape[0]
        if seeds not in args:
            args[seeds] = gp_method_args(cfg, seeds, mesh)
        return program(state, *args[seeds])

    return step


def _program_kind(cfg: config_lib.TrainConfig, gp_program: str) -> str:
    """'shared' if `cfg`'s method runs in its family's one program, else 'per_method'."""
    shared = gp_program == "shared" and len(train_lib.program_family(cfg)) > 1
    return "shared" if shared else "per_method"


def gp_methods_program(cfg: config_lib.TrainConfig, mesh: Mesh, seed_loop: str, num_updates: int,
                       donate: bool = True):
    """The jitted `program(state, method_index, cfg) -> (state, records)` of
    `train.make_methods_train` for `cfg`'s static fields, over the sharded seed axis (the
    state's buffers donated unless `donate=False`; `gp_method_args` gives the other two
    arguments). One per static config, mesh, seed loop, chunk length and donation, kept for the
    process (the last few), so every method of the family that asks for it gets the same
    compiled program."""
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    key_cfg = train_lib.methods_key(cfg)
    cache_key = (tuple(sorted(key_cfg.static_dict().items())), mesh, loop, num_updates, donate)

    def make():
        run_chunk = train_lib.make_methods_train(key_cfg)
        return sharding.per_seed_program(lambda s, i, c: run_chunk(s, i, c, num_updates), mesh,
                                         loop, donate=donate)

    return _kept(_SHARED_PROGRAMS, cache_key, make)


def gp_method_args(cfg: config_lib.TrainConfig, seeds: int, mesh: Mesh):
    """`gp_methods_program`'s method index and config for `cfg`'s method, one row per seed of a
    batch of `seeds` (padded to the mesh), sharded over `mesh`."""
    def per_seed(x):
        return sharding.shard(np.broadcast_to(np.asarray(x), (seeds,) + np.shape(x)), mesh)

    return (per_seed(np.int32(train_lib.method_index(cfg))),
            jax.tree_util.tree_map(per_seed, train_lib.methods_key(cfg)))


# ------------------------------------------------------------------------------------------------
# The GP priors (hyperparameter fit), shared by every GP method of a seed.
# ------------------------------------------------------------------------------------------------


def fit_priors(cfgs: dict[str, config_lib.TrainConfig], seeds, out_dir, mesh, progress,
               seed_loop: str = "auto", seconds: dict | None = None) -> dict[str, train_lib.GPPrior]:
    """The fitted prior of each method of `cfgs` (method -> config) that declares one.

    A method's prior is read from `kernels_<method>.npz` if it was fitted for these seeds and the
    method's fit inputs (`methods.fit_inputs`: the config fields its fit reads), else fitted and
    saved. Methods whose fit inputs agree share one fit; a method whose tuned settings change
    the fit's data (its discount, initial noise, hold, ...) gets its own. `seconds`, if given,
    receives each method's fit time (0 for a prior read from its file or shared).
    """
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    fitted: dict[str, train_lib.GPPrior] = {}  # fit digest -> prior
    priors = {}
    for m, cfg in cfgs.items():
        inputs = methods_lib.fit_inputs(cfg)
        if inputs is None:
            continue
        digest = checkpoints.digest(inputs, list(map(int, seeds)), loop)
        path = os.path.join(out_dir, f"kernels_{m}.npz")
        saved = checkpoints.read_npz(path, progress)
        if saved is not None and str(saved.get("digest", "")) == digest:
            kernel = kernels_lib.KernelParams(*(saved[k] for k in kernels_lib.KernelParams._fields))
            priors[m] = fitted.setdefault(digest, train_lib.GPPrior(kernel, saved["prior_mean"]))
            continue
        t0 = time.perf_counter()
        if digest not in fitted:
            fitted[digest] = _fit(cfg, seeds, mesh, loop, progress)
        if seconds is not None:
            seconds[m] = time.perf_counter() - t0
        priors[m] = prior = fitted[digest]
        if distributed.is_main():
            checkpoints.atomic_savez(path, digest=digest, seeds=np.asarray(seeds),
                                     prior_mean=prior.mean, **prior.kernel._asdict())
    return priors


def _fit(cfg, seeds, mesh, loop, progress) -> train_lib.GPPrior:
    """The prior of `cfg`'s method fitted for `seeds` (on the host, the padding seeds dropped)."""
    t0 = time.perf_counter()
    fit = fit_program(train_lib.make_train(cfg), mesh, loop)
    keys = sharding.seed_keys(sharding.pad_seeds(seeds, mesh.devices.size))
    fitted = distributed.gather(fit(sharding.shard(keys, mesh)))
    prior = jax.tree_util.tree_map(lambda x: np.asarray(x)[: len(seeds)], fitted)
    progress(f"[{cfg.method}] hyperparameter fit for {len(seeds)} seeds: "
             f"{time.perf_counter() - t0:.1f}s")
    return prior


# ------------------------------------------------------------------------------------------------
# One method, a chunk of updates at a time.
# ------------------------------------------------------------------------------------------------


def run_method(
    cfg: config_lib.TrainConfig,
    seeds: Sequence[int],
    out_dir: str,
    *,
    chunk_size: int = 50,
    mesh: Mesh | None = None,
    kernels=None,
    max_chunks: int | None = None,
    progress: Callable[[str], None] = _log,
    seed_loop: str = "auto",
    gp_program: str = "shared",
    on_chunk: Callable[[str, int, dict], None] | None = None,
):
    """Runs one method for all seeds, a compiled chunk of updates at a time, resuming from
    `out_dir/checkpoint_<method>.npz` when present.

    Args:
      cfg: the method's config.
      seeds: integer seeds (the seed axis is sharded over `mesh`; padded to a multiple of its size).
      out_dir: where the checkpoint goes.
      chunk_size: updates per compiled chunk (progress is reported and a checkpoint written after each).
      mesh: device mesh with axis 'seeds' (default: all devices).
      kernels: optional fitted `train.GPPrior` with a leading seed axis (skips the hyperfit).
      max_chunks: run at most this many chunks in this call (to test resumption); None: to the end.
      seed_loop: how each device runs its seeds, 'auto', 'vmap' or 'map' (`per_seed_program`).
      gp_program: 'shared' (one program for every GP method) or 'per_method' (`chunk_program`).
      on_chunk: called after each chunk, once its records are on the host, with the method, the
        updates done and the chunk's records (field -> (seeds, updates of the chunk)).

    Returns:
      (records, state): dict field -> (seeds, updates_done) records, and the final `TrainState`.
    """
    _check_gp_program(gp_program)
    mesh = mesh or sharding.make_mesh()
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    seeds = list(map(int, seeds))
    padded = sharding.pad_seeds(seeds, mesh.devices.size)
    chunk_size = min(chunk_size, cfg.num_updates)
    n_chunks = -(-cfg.num_updates // chunk_size)
    train = train_lib.make_train(cfg)  # the method's program, for every builder below
    ckpt = checkpoints.checkpoint_path(out_dir, cfg.method)
    digest = checkpoints.digest(cfg.to_json_dict(), padded, chunk_size,
                                [str(d) for d in mesh.devices.flat], loop,
                                _program_kind(cfg, gp_program))
    init = init_program(train, mesh, loop, kernels is not None)
    state, records, done = _resume_or_init(cfg, init, _init_args(padded, len(seeds), kernels, mesh),
                                           ckpt, digest, mesh, n_chunks, progress)
    chunk = functools.cache(lambda n: chunk_program(train, mesh, loop, n, gp_program))

    # The first chunk of a call includes compiling the program: the rate (and the ETA) is
    # measured over the chunks after it.
    t_first, chunks_this_call = None, 0
    while done < n_chunks and (max_chunks is None or chunks_this_call < max_chunks):
        t0 = time.perf_counter()
        n = min(chunk_size, cfg.num_updates - done * chunk_size)
        state, rec = chunk(n)(state)
        rec, records = append_records(records, rec)
        done += 1
        chunks_this_call += 1
        checkpoints.save_checkpoint(ckpt, state, records, done, digest)
        updates_done = min(done * chunk_size, cfg.num_updates)
        if t_first is None:
            t_first, rate = time.perf_counter(), None
            first_s = t_first - t0
        else:
            rate = (chunks_this_call - 1) * chunk_size / max(time.perf_counter() - t_first, 1e-9)
        progress(_chunk_progress(cfg, rec, len(seeds), updates_done, rate, first_s))
        if on_chunk is not None:
            on_chunk(cfg.method, updates_done,
                     {k: np.asarray(getattr(rec, k))[:len(seeds)] for k in rec._fields})
    return {k: v[:len(seeds)] for k, v in records.items()}, state


def _init_args(padded: list[int], n_real: int, kernels, mesh: Mesh) -> tuple:
    """The initial states' arguments, sharded over `mesh`: the padded seeds' keys and, given
    fitted `kernels` of the `n_real` seeds, those too (the padding seeds take copies of the last
    seeds' kernels)."""
    keys = sharding.shard(sharding.seed_keys(padded), mesh)
    if kernels is None:
        return (keys,)
    pad = len(padded) - n_real
    if pad:
        kernels = jax.tree_util.tree_map(lambda x: np.concatenate([x, x[-pad:]]), kernels)
    return keys, sharding.shard(kernels, mesh)


def _resume_or_init(cfg, init, args, ckpt, digest, mesh, n_chunks, progress):
    """(state, records, chunks done): from the checkpoint if it matches `digest`, else the initial
    states `init(*args)` of the (padded) seeds with no records."""
    fields = train_lib.record_fields(cfg.method)
    loaded = checkpoints.load_checkpoint(ckpt, jax.eval_shape(init, *args), fields, digest, mesh,
                                         progress)
    if loaded is not None:
        progress(f"[{cfg.method}] resuming from {ckpt}: {loaded[2]}/{n_chunks} chunks done")
        return loaded
    t0 = time.perf_counter()
    state = jax.block_until_ready(init(*args))
    progress(f"[{cfg.method}] init {time.perf_counter() - t0:.1f}s")
    num_seeds = args[0].shape[0]
    return state, {k: np.zeros((num_seeds, 0)) for k in fields}, 0


def append_records(records: dict, rec) -> tuple:
    """A chunk's records (all processes' seeds) on the host, and the run's `records` with them
    appended: (the chunk's records, the run's)."""
    rec = distributed.gather(rec)
    return rec, {k: np.concatenate([records[k], np.asarray(getattr(rec, k))], axis=1)
                 for k in rec._fields}


def _chunk_progress(cfg: config_lib.TrainConfig, rec, n_real: int, updates_done: int,
                    rate: float | None, first_s: float) -> str:
    """The progress line after a chunk: updates done, rate and ETA (`rate` None: the first chunk
    of the call, which took `first_s` and compiled the program if it was not yet), the latest
    mean reward of the real (unpadded) seeds, and a warning for skipped gradients or rejected GP
    updates."""
    left = cfg.num_updates - updates_done
    if rate is None:
        timing = f"first chunk in {first_s:.1f}s, compiling included" + (
            " | ETA after the next chunk" if left else "")
    else:
        timing = f"{rate:.1f} updates/s x {n_real} seeds | ETA {left / max(rate, 1e-9):.0f}s"
    msg = (f"[{cfg.method}] updates {updates_done}/{cfg.num_updates} | {timing} | "
           f"mean reward {np.mean(rec.mean_reward[:n_real, -1]):.3f}")
    for field, what in (("nonfinite_grad", "non-finite gradient estimates skipped"),
                        ("gp_guard", "GP updates rejected by the health check")):
        if field not in rec._fields:
            continue
        bad = int(np.sum(np.asarray(getattr(rec, field))[:n_real]))
        if bad:
            msg += f" | WARNING: {bad} {what}"
    return msg


# ------------------------------------------------------------------------------------------------
# The whole reproduction, in one pass.
# ------------------------------------------------------------------------------------------------


def reproduce(
    preset: str = "paper",
    seeds: Sequence[int] = tuple(range(10)),
    methods: Sequence[str] | None = None,
    out_dir: str = "results/paper",
    *,
    dtype: str = "float64",
    chunk_size: int = 50,
    num_devices: int | None = None,
    max_chunks: int | None = None,
    overrides: dict | None = None,
    progress: Callable[[str], None] = _log,
    seed_loop: str = "auto",
    gp_program: str = "shared",
    keep_checkpoints: bool = False,
    on_chunk: Callable[[str, int, dict], None] | None = None,
) -> dict:
    """Runs every method (default: the paper's) for every seed and writes results.npz,
    config.json, summary.csv, comparisons.csv and Fig. 5 to `out_dir`.

    `out_dir` is locked for the run (`checkpoints.open_out_dir`: a second run writing to it is
    refused with `checkpoints.OutDirError`). Each method's checkpoints are kept while the run is
    unfinished, so that the same call resumes it, and deleted once the results are written
    (unless `keep_checkpoints`).

    Returns a dict with the summary and comparison rows, their markdown tables, the output paths
    and `wall_s`, method -> seconds of its fit (when it made one) and its run in this call,
    compilation included; `complete` is False when `max_chunks` ended a method early (then nothing but
    checkpoints is written). With several processes (`distributed.initialize`) the seeds are
    sharded over the devices of all of them; each keeps its own checkpoint, and process 0 reports
    progress and writes config.json, results.npz, the CSV files and the figures. The GP methods
    share one compiled program (`gp_program='shared'`; 'per_method' compiles one each, see
    `chunk_program`). `on_chunk`: `run_method`'s, for every method.
    """
    _check_gp_program(gp_program)
    methods = list(methods_lib.paper() if methods is None else methods)
    with checkpoints.open_out_dir(out_dir):
        out = _reproduce(preset, list(map(int, seeds)), list(methods), out_dir, dtype, chunk_size,
                         num_devices, max_chunks, overrides, progress, seed_loop, gp_program,
                         on_chunk)
        if out["complete"] and not keep_checkpoints:
            for m in methods:
                checkpoints.remove_checkpoints(out_dir, m)
    return out


def _reproduce(preset, seeds, methods, out_dir, dtype, chunk_size, num_devices, max_chunks,
               overrides, progress, seed_loop, gp_program, on_chunk=None) -> dict:
    """`reproduce` in the locked `out_dir`."""
    main = distributed.is_main()
    if not main:  # one voice: process 0 reports progress and writes the results
        progress = _silent
    mesh = sharding.make_mesh(num_devices, len(seeds))
    loop = sharding.resolve_seed_loop(seed_loop, mesh)
    cfgs = {m: config_lib.preset(preset, method=m, dtype=dtype, **(overrides or {})) for m in methods}
    if main:
        checkpoints.atomic_write_text(os.path.join(out_dir, "config.json"), json.dumps(
            {"preset": preset, "seeds": seeds, "chunk_size": chunk_size, "dtype": dtype,
             "processes": distributed.process_count(),
             "devices": [str(d) for d in mesh.devices.flat], "seed_loop": loop,
             "gp_program": gp_program, "methods": {m: c.to_json_dict() for m, c in cfgs.items()}}, indent=2))

    wall = {m: 0.0 for m in methods}
    priors = fit_priors(cfgs, seeds, out_dir, mesh, progress, loop, seconds=wall)
    records = {}
    for m in methods:
        t0 = time.perf_counter()
        rec, _ = run_method(cfgs[m], seeds, out_dir, chunk_size=chunk_size, mesh=mesh,
                            kernels=priors.get(m),
                            max_chunks=max_chunks, progress=progress, seed_loop=loop,
                            gp_program=gp_program, on_chunk=on_chunk)
        if rec["mean_reward"].shape[1] < cfgs[m].num_updates:
            return {"complete": False}
        records[m] = rec
        wall[m] += time.perf_counter() - t0

    out = _summary(cfgs, records)
    out["wall_s"] = wall
    if main:
        out["figures"] = _write_results(out_dir, cfgs, seeds, records, out)
    return out


def _summary(cfgs: dict[str, config_lib.TrainConfig], records: dict) -> dict:
    """The run's summary and comparison rows and their Markdown (`summaries`), for the task of
    the configs (the level of doing nothing, and the swing-up columns if its episodes can hold
    one)."""
    cfg = next(iter(cfgs.values()))
    pendulum = cfg.env == "pendulum"
    budgets = None if pendulum else {m: summaries.task_budget(cfgs[m]) for m in records}
    rows = summaries.summarise(records, summaries.zero_torque_reward(cfg) if pendulum else "no-level",
                               success=summaries.holds_swing_up(cfg), budgets=budgets)
    comparisons = summaries.compare(records)
    return {"complete": True, "summary": rows, "comparisons": comparisons, "figures": [],
            "markdown": summaries.summary_markdown(rows)
            + ("\n\n" + summaries.comparisons_markdown(comparisons) if comparisons else "")}


def stack_records(records: dict[str, dict]) -> dict[str, np.ndarray]:
    """Per-method records as arrays (methods, seeds, updates) of every field any method keeps,
    NaN past a method's last update or where it does not keep the field."""
    names = list(records)
    fields = list(dict.fromkeys(k for m in names for k in records[m]))
    seeds = max(np.shape(records[m]["mean_reward"])[0] for m in names)
    updates = max(np.shape(records[m]["mean_reward"])[1] for m in names)
    out = {}
    for k in fields:
        shapes = {np.shape(records[m].get(k)) for m in names}
        if len(shapes) == 1 and all(k in records[m] for m in names):  # nothing to pad
            out[k] = np.stack([np.asarray(records[m][k]) for m in names])
            continue
        arr = np.full((len(names), seeds, updates), np.nan)
        for i, m in enumerate(names):
            if k in records[m]:
                v = np.asarray(records[m][k], float)
                arr[i, : v.shape[0], : v.shape[1]] = v
        out[k] = arr
    return out


def _write_results(out_dir: str, cfgs: dict, seeds: list[int], records: dict,
                   out: dict) -> list[str]:
    """results.npz, summary.csv, comparisons.csv (if any), Fig. 5 and index.html (`report`);
    returns the figures' paths."""
    methods_run = list(records)
    arrays = stack_records(records)
    updates = arrays["mean_reward"].shape[-1]
    num_updates = np.asarray([records[m]["mean_reward"].shape[1] for m in methods_run])
    env_steps = np.full((len(methods_run), updates), np.nan)
    for i, m in enumerate(methods_run):
        # the steps by the end of each update: where its own episodes' records were taken
        own = summaries.task_budget(cfgs[m])._replace(return_record="mean_return")
        env_steps[i, : num_updates[i]] = summaries.env_steps_axis(own, int(num_updates[i]))
    checkpoints.atomic_savez(os.path.join(out_dir, "results.npz"), methods=np.asarray(methods_run),
                             seeds=np.asarray(seeds), num_updates=num_updates, env_steps=env_steps,
                             **arrays)
    summaries.write_csv(out["summary"], os.path.join(out_dir, "summary.csv"))
    if out["comparisons"]:
        summaries.write_csv(out["comparisons"], os.path.join(out_dir, "comparisons.csv"))
    figures = plots.plot_fig5({"methods": methods_run, "env_steps": env_steps, **arrays}, out_dir)
    report.write_report(out_dir)  # after every file it shows
    return figures
