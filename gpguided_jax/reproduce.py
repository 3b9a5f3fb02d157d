"""Chunked, resumable, device-sharded runs of every method over many seeds (Fig. 5), with their
summary, failure accounting, tables and plots. `gpguided reproduce` is a thin wrapper over
`reproduce`, which reads as one pass:

  configs -> config.json -> fitted GP priors (kernels.npz) -> each method, a chunk at a time
  (checkpoint_<method>.npz) -> results.npz -> summary.csv + comparisons.csv -> Fig. 5 PNGs.

Output directory layout (every file is written atomically: to a temporary name, then renamed):
  config.json              resolved config of every method (+ seeds, chunk size, devices, dtype)
  kernels.npz              fitted GP hyperparameters and prior mean per seed (shared by GP methods)
  checkpoint_<method>.npz  state after the last finished chunk and the records so far
  results.npz              methods, seeds, per-update records of shape (methods, seeds, updates)
  summary.csv              per method: final performance (mean and t-interval; IQM and stratified
                           bootstrap interval), updates to 90%, failing seeds by cause
  comparisons.csv          probability of improvement (rliable) of each GP method over REINFORCE
                           and of each guided method over gp_pg, with bootstrap intervals
  fig5_reward.png, fig5_exploration.png

A checkpoint or kernels file that cannot be read is renamed to `<name>.corrupt` (the log says so)
and that part of the run starts afresh.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import io
import json
import os
import sys
import time
import zipfile
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from gpguided_jax import config as config_lib
from gpguided_jax import distributed, pendulum
from gpguided_jax import kernels as kernels_lib
from gpguided_jax import stats as stats_lib
from gpguided_jax import train as train_lib

RECORD_FIELDS = train_lib.UpdateRecord._fields
CHECKPOINT_VERSION = 4  # bump when the state's pytree or the programs change; older ones are ignored
GP_PROGRAMS = ("shared", "per_method")
# Pairs (x, y) for which the probability that x beats y is reported (rliable).
COMPARISONS = (
    ("gp_pg", "reinforce"),
    ("guided_variance", "reinforce"),
    ("guided_direction", "reinforce"),
    ("guided_variance", "gp_pg"),
    ("guided_direction", "gp_pg"),
)
FAILURE_CAUSES = ("nonfinite_grad", "gp_guard", "std_at_bound", "below_zero_torque", "nan_record")


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _silent(msg: str) -> None:
    del msg


# ------------------------------------------------------------------------------------------------
# Files: atomic writes, tolerant reads.
# ------------------------------------------------------------------------------------------------


def _atomic_write_bytes(path: str, data: bytes) -> None:
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)  # atomic: a reader sees the old file or the new one, never half of one


def atomic_savez(path: str, **arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    _atomic_write_bytes(path, buf.getvalue())


def atomic_write_text(path: str, text: str) -> None:
    _atomic_write_bytes(path, text.encode())


def _set_aside(path: str, why: str, progress) -> None:
    bad = path + ".corrupt"
    os.replace(path, bad)
    progress(f"WARNING: {path} could not be read ({why}); moved to {bad}, starting that part afresh")


def _read_npz(path: str, progress) -> dict | None:
    """All arrays of an .npz file, or None if it is missing; a corrupt file is set aside."""
    if not os.path.exists(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        _set_aside(path, f"{type(e).__name__}: {e}", progress)
        return None


# ------------------------------------------------------------------------------------------------
# Seeds and devices.
# ------------------------------------------------------------------------------------------------


def seed_keys(seeds: Sequence[int]) -> jax.Array:
    """One raw uint32 PRNG key per seed (raw keys are plain arrays: easy to checkpoint)."""
    return jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])


def make_mesh(num_devices: int | None = None, num_seeds: int | None = None) -> Mesh:
    """A one-axis mesh ('seeds') over at most `num_devices` devices (default: all).

    Given `num_seeds` (one process), no more devices than the seeds need: the seeds per device,
    ceil(seeds / devices), stay the same and the padding (`pad_seeds`) is as small as possible
    (100 seeds on 64 devices: 50 devices with 2 seeds each rather than 64 with 28 padded seeds).
    """
    devices = jax.devices()
    n = len(devices) if num_devices is None else min(int(num_devices), len(devices))
    if n < 1:
        raise ValueError(f"--devices must be >= 1, got {num_devices}")
    if num_seeds is not None and distributed.process_count() == 1:
        n = devices_for_seeds(num_seeds, n)
    return Mesh(np.array(devices[:n]), ("seeds",))


def devices_for_seeds(num_seeds: int, available: int) -> int:
    """The fewest of `available` devices that keep ceil(seeds / available) seeds per device."""
    if num_seeds < 1 or available < 1:
        raise ValueError(f"need at least one seed and one device, got {num_seeds} and {available}")
    per_device = -(-int(num_seeds) // int(available))
    return -(-int(num_seeds) // per_device)


SEED_LOOPS = ("auto", "vmap", "map")


def resolve_seed_loop(seed_loop: str, mesh: Mesh) -> str:
    """'auto': 'map' on CPU devices, 'vmap' on accelerators."""
    if seed_loop not in SEED_LOOPS:
        raise ValueError(f"seed_loop must be one of {SEED_LOOPS}, got {seed_loop!r}")
    if seed_loop == "auto":
        return "map" if mesh.devices.flat[0].platform == "cpu" else "vmap"
    return seed_loop


def per_seed_program(fn: Callable, mesh: Mesh, seed_loop: str = "auto", donate: bool = False):
    """`fn` (one seed's arguments -> one seed's outputs) as one compiled program over all seeds.

    The leading axis of every argument and output is the seed axis, split over the mesh with
    `shard_map`: each device runs its own seeds with no communication between devices (a `jit`
    of a `vmap` over sharded inputs would partition the batch-wide `any` of the GP update into an
    all-reduce at every GP step). On each device the seeds run either as one batch (`vmap`: what
    an accelerator needs) or one after another (`lax.map`). On a CPU the second is faster for the
    GP methods (the GP update is a sequential scan of O(M^2) steps: batching seeds adds no
    parallelism, and a batch runs the insertion branch whenever any of its seeds needs it) and
    makes every seed's result independent of its batch-mates and of the device count, bit for bit.

    Args:
      fn: per-seed function of positional array arguments (pytrees allowed).
      mesh: the mesh from `make_mesh`.
      seed_loop: 'auto' (see `resolve_seed_loop`), 'vmap' or 'map'.
      donate: donate the first argument's buffers (a state that the program replaces).
    """
    loop = resolve_seed_loop(seed_loop, mesh)
    if loop == "map":
        def local(*args):
            return jax.lax.map(lambda a: fn(*a), args)
    else:
        local = jax.vmap(fn)
    spec = PartitionSpec(mesh.axis_names[0])
    # check_vma=False: the per-seed code never communicates, and the GP update's `lax.cond` on an
    # unbatched predicate (`sparse_gp._any_in_batch`) mixes device-varying and invariant branch
    # outputs, which the varying-axes type check would refuse.
    program = jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
    return jax.jit(program, donate_argnums=(0,) if donate else ())


def pad_seeds(seeds: Sequence[int], num_devices: int) -> list[int]:
    """The seeds followed by extra ones up to a multiple of `num_devices` (they only fill devices;
    their results are dropped)."""
    seeds = list(map(int, seeds))
    return seeds + [seeds[-1] + 1 + i for i in range((-len(seeds)) % num_devices)]


def _shard(tree, mesh: Mesh):
    """Places every leaf with its leading (seed) axis split over the mesh (over the devices of
    every process when there are several; each process places its own rows)."""
    return distributed.shard(tree, mesh)


def _digest(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------
# The GP priors (hyperparameter fit), shared by every GP method of a seed.
# ------------------------------------------------------------------------------------------------


def fit_priors(cfg: config_lib.TrainConfig, seeds, out_dir, mesh, progress,
               seed_loop: str = "auto") -> train_lib.GPPrior:
    """Loads `kernels.npz` if it was fitted for these seeds and this config, else fits and saves.

    The fit depends only on the seed and the initial policy's data (not on the method), so every
    GP method of a seed shares it.
    """
    path = os.path.join(out_dir, "kernels.npz")
    fit_cfg = {k: v for k, v in cfg.to_json_dict().items() if k != "method"}
    loop = resolve_seed_loop(seed_loop, mesh)
    digest = _digest(CHECKPOINT_VERSION, fit_cfg, list(map(int, seeds)), loop)
    fields = kernels_lib.KernelParams._fields
    saved = _read_npz(path, progress)
    if saved is not None and str(saved.get("digest", "")) == digest:
        return train_lib.GPPrior(kernels_lib.KernelParams(*(saved[k] for k in fields)),
                                 saved["prior_mean"])
    t0 = time.perf_counter()
    fit = _kept(_FIT_PROGRAMS, (json.dumps(fit_cfg, sort_keys=True), mesh, loop),
                lambda: per_seed_program(train_lib.make_train(cfg).fit_kernel_for_seed, mesh, loop))
    fitted = distributed.gather(fit(_shard(seed_keys(pad_seeds(seeds, mesh.devices.size)), mesh)))
    prior = jax.tree_util.tree_map(lambda x: np.asarray(x)[: len(seeds)], fitted)
    if distributed.is_main():
        atomic_savez(path, digest=digest, seeds=np.asarray(seeds), prior_mean=prior.mean,
                     **prior.kernel._asdict())
    progress(f"hyperparameter fit for {len(seeds)} seeds: {time.perf_counter() - t0:.1f}s")
    return prior


# ------------------------------------------------------------------------------------------------
# One method, a chunk of updates at a time.
# ------------------------------------------------------------------------------------------------


def checkpoint_path(out_dir: str, method: str) -> str:
    """This process's checkpoint: checkpoint_<method>.npz, or with several processes
    checkpoint_<method>.process<I>-of-<N>.npz (each holds its own seeds' state)."""
    n = distributed.process_count()
    tag = "" if n == 1 else f".process{jax.process_index()}-of-{n}"
    return os.path.join(out_dir, f"checkpoint_{method}{tag}.npz")


def _save_checkpoint(path, state, records, chunks_done, digest):
    """This process's rows of the state and all records, atomically; the previous checkpoint is
    kept as `<path>.prev` so that processes interrupted between their writes can still agree."""
    arrays = {}
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state)):
        rows, arrays[f"leaf_{i}"] = distributed.local_rows(leaf)
    arrays.update({f"rec_{k}": np.asarray(v) for k, v in records.items()})
    buf = io.BytesIO()
    np.savez(buf, chunks_done=chunks_done, digest=digest, rows=rows, **arrays)
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(buf.getvalue())
        f.flush()
        os.fsync(f.fileno())
    if os.path.exists(path):
        os.replace(path, path + ".prev")
    os.replace(tmp, path)


def _read_checkpoint(path, template, digest, mesh, progress):
    """(chunks_done, state, records) from one checkpoint file, or None (missing, stale or corrupt;
    a corrupt file is set aside)."""
    saved = _read_npz(path, progress)
    if saved is None:
        return None
    if str(saved.get("digest", "")) != digest:
        progress(f"ignoring {path}: it was written by a different config or seed list")
        return None
    treedef = jax.tree_util.tree_structure(template)
    shapes = [t.shape for t in jax.tree_util.tree_leaves(template)]
    rows = distributed.expected_rows(shapes[0], mesh)
    leaves = [saved.get(f"leaf_{i}") for i in range(treedef.num_leaves)]
    records = {k[4:]: v for k, v in saved.items() if k.startswith("rec_")}
    ok = (
        "chunks_done" in saved and "rows" in saved and np.array_equal(saved["rows"], rows)
        and set(records) == set(RECORD_FIELDS)
        and all(leaf is not None and leaf.shape == (len(rows),) + shape[1:]
                for leaf, shape in zip(leaves, shapes))
    )
    if not ok:
        _set_aside(path, "missing or mis-shaped arrays", progress)
        return None
    state = jax.tree_util.tree_unflatten(
        treedef, [distributed.from_local_rows(shape, rows, leaf, mesh)
                  for shape, leaf in zip(shapes, leaves)])
    return int(saved["chunks_done"]), state, records


def _load_checkpoint(path, template, digest, mesh, progress):
    """The newest checkpoint that every process has (its latest or the one before): the processes
    exchange which chunk counts they hold and all resume from the same one, or all start afresh."""
    found = {}
    for candidate in (path, path + ".prev"):
        got = _read_checkpoint(candidate, template, digest, mesh, progress)
        if got is not None:
            found.setdefault(got[0], got)
    offered = sorted(found, reverse=True)[:2] + [-1, -1]
    held = distributed.agree(offered[:2])  # (processes, 2)
    common = set(held[0].tolist())
    for row in held[1:]:
        common &= set(row.tolist())
    common.discard(-1)
    if not common:
        return None
    done, state, records = found[max(common)]
    return state, records, done


def _check_gp_program(gp_program: str) -> None:
    if gp_program not in GP_PROGRAMS:
        raise ValueError(f"gp_program must be one of {GP_PROGRAMS}, got {gp_program!r}")


_SHARED_PROGRAMS: dict = {}  # (static config, mesh, loop, updates, donate) -> jitted chunk program
_FIT_PROGRAMS: dict = {}  # (config but the method, mesh, loop) -> jitted hyperparameter fit
_OWN_PROGRAMS: dict = {}  # (kind, config, mesh, loop, ...) -> a method's own init or chunk program
_PROGRAMS_KEPT = 8  # per cache: the last few


def _kept(cache: dict, key, make: Callable):
    """`cache[key]`, made by `make()` if missing; the cache keeps the last `_PROGRAMS_KEPT`. A
    process that runs `reproduce` again (a notebook, the tests) then reuses the jitted programs
    (the fit, the initial states, the chunks) and does not trace and compile them again (a
    second tiny gp_pg run: 4.55 s when they were made anew, 0.47 s, on 2 cores)."""
    program = cache.get(key)
    if program is None:
        while len(cache) >= _PROGRAMS_KEPT:
            cache.pop(next(iter(cache)))
        program = cache[key] = make()
    return program


def _config_key(cfg: config_lib.TrainConfig) -> str:
    """A config's every field, as a cache key (the programs bake its values in)."""
    return json.dumps(cfg.to_json_dict(), sort_keys=True)


def init_program(cfg: config_lib.TrainConfig, mesh: Mesh, seed_loop: str, with_kernels: bool):
    """The jitted initial states over the sharded seed axis, `init(keys[, kernels])`, kept for
    the process (`_kept`)."""
    loop = resolve_seed_loop(seed_loop, mesh)

    def make():
        train = train_lib.make_train(cfg)
        return per_seed_program((lambda k, kern: train.init(k, cfg, kern)) if with_kernels
                                else (lambda k: train.init(k, cfg)), mesh, loop)

    return _kept(_OWN_PROGRAMS, ("init", _config_key(cfg), mesh, loop, with_kernels), make)


def chunk_program(cfg: config_lib.TrainConfig, mesh: Mesh, seed_loop: str, num_updates: int,
                  gp_program: str = "shared"):
    """The compiled chunk of `num_updates` updates that `run_method` runs for `cfg`, as
    `step(state) -> (state, records)` over the sharded seed axis (the state's buffers donated).

    With `gp_program='shared'` (the default) every GP method of one static configuration runs the
    same program (`train.make_gp_methods_train`, the method and the traced config its
    arguments): it is traced and compiled once per process for the three methods, and is the
    same program whichever of them a run asks for, so a method's records do not depend on the
    others. 'per_method' compiles `train.make_train(cfg).run_chunk` for each method (the records
    agree with the shared program's to rounding). REINFORCE always has its own program.
    """
    _check_gp_program(gp_program)
    loop = resolve_seed_loop(seed_loop, mesh)
    if not cfg.uses_gp or gp_program == "per_method":
        def make():
            train = train_lib.make_train(cfg)
            return per_seed_program(lambda s: train.run_chunk(s, cfg, num_updates), mesh, loop,
                                    donate=True)

        return _kept(_OWN_PROGRAMS, ("chunk", _config_key(cfg), mesh, loop, num_updates), make)
    program = gp_methods_program(cfg, mesh, loop, num_updates)
    args = {}  # the method index and the config, one row per seed, placed once

    def step(state):
        seeds = jax.tree_util.tree_leaves(state)[0].shape[0]
        if seeds not in args:
            args[seeds] = gp_method_args(cfg, seeds, mesh)
        return program(state, *args[seeds])

    return step


def gp_methods_program(cfg: config_lib.TrainConfig, mesh: Mesh, seed_loop: str, num_updates: int,
                       donate: bool = True):
    """The jitted `program(state, method_index, cfg) -> (state, records)` of
    `train.make_gp_methods_train` for `cfg`'s static fields, over the sharded seed axis (the
    state's buffers donated unless `donate=False`; `gp_method_args` gives the other two
    arguments). One per static config, mesh, seed loop, chunk length and donation, kept for the
    process (the last few), so every GP method that asks for it gets the same compiled program."""
    loop = resolve_seed_loop(seed_loop, mesh)
    key_cfg = train_lib.gp_methods_key(cfg)
    cache_key = (tuple(sorted(key_cfg.static_dict().items())), mesh, loop, num_updates, donate)

    def make():
        run_chunk = train_lib.make_gp_methods_train(key_cfg)
        return per_seed_program(lambda s, i, c: run_chunk(s, i, c, num_updates), mesh, loop,
                                donate=donate)

    return _kept(_SHARED_PROGRAMS, cache_key, make)


def gp_method_args(cfg: config_lib.TrainConfig, seeds: int, mesh: Mesh):
    """`gp_methods_program`'s method index and config for `cfg`'s method, one row per seed of a
    batch of `seeds` (padded to the mesh), sharded over `mesh`."""
    def per_seed(x):
        return _shard(np.broadcast_to(np.asarray(x), (seeds,) + np.shape(x)), mesh)

    return (per_seed(np.int32(train_lib.GP_METHODS.index(cfg.method))),
            jax.tree_util.tree_map(per_seed, train_lib.gp_methods_key(cfg)))


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
      max_chunks: stop after this many chunks in this call (to test resumption); None: run to the end.
      seed_loop: how each device runs its seeds, 'auto', 'vmap' or 'map' (`per_seed_program`).
      gp_program: 'shared' (one program for every GP method) or 'per_method' (`chunk_program`).

    Returns:
      (records, state): dict field -> (seeds, updates_done) records, and the final `TrainState`.
    """
    _check_gp_program(gp_program)
    mesh = mesh or make_mesh()
    n_dev = mesh.devices.size
    seeds = list(map(int, seeds))
    n_real = len(seeds)
    padded = pad_seeds(seeds, n_dev)
    pad = len(padded) - n_real
    keys = _shard(seed_keys(padded), mesh)
    if kernels is not None and pad:
        kernels = jax.tree_util.tree_map(lambda x: np.concatenate([x, x[-pad:]]), kernels)

    loop = resolve_seed_loop(seed_loop, mesh)
    init = init_program(cfg, mesh, loop, kernels is not None)
    chunk_size = min(chunk_size, cfg.num_updates)
    n_chunks = -(-cfg.num_updates // chunk_size)
    compiled = {}

    def chunk_fn(n):
        if n not in compiled:
            compiled[n] = chunk_program(cfg, mesh, loop, n, gp_program)
        return compiled[n]

    ckpt = checkpoint_path(out_dir, cfg.method)
    digest = _digest(CHECKPOINT_VERSION, cfg.to_json_dict(), padded, chunk_size,
                     [str(d) for d in mesh.devices.flat], loop,
                     gp_program if cfg.uses_gp else "per_method")
    args = (keys,) if kernels is None else (keys, _shard(kernels, mesh))
    state, records, done = _resume_or_init(cfg, init, args, len(padded), ckpt, digest, mesh,
                                           n_chunks, progress)

    t_start, chunks_this_call = time.perf_counter(), 0
    while done < n_chunks and (max_chunks is None or chunks_this_call < max_chunks):
        n = min(chunk_size, cfg.num_updates - done * chunk_size)
        state, rec = chunk_fn(n)(state)
        rec, records = append_records(records, rec)
        done += 1
        chunks_this_call += 1
        _save_checkpoint(ckpt, state, records, done, digest)
        rate = chunks_this_call * chunk_size / max(time.perf_counter() - t_start, 1e-9)
        progress(_chunk_progress(cfg, rec, n_real, min(done * chunk_size, cfg.num_updates), rate))
    return {k: v[:n_real] for k, v in records.items()}, state


def _resume_or_init(cfg, init, args, num_seeds, ckpt, digest, mesh, n_chunks, progress):
    """(state, records, chunks done): from the checkpoint if it matches `digest`, else the initial
    states `init(*args)` of the `num_seeds` (padded) seeds with no records."""
    loaded = _load_checkpoint(ckpt, jax.eval_shape(init, *args), digest, mesh, progress)
    if loaded is not None:
        progress(f"[{cfg.method}] resuming from {ckpt}: {loaded[2]}/{n_chunks} chunks done")
        return loaded
    t0 = time.perf_counter()
    state = jax.block_until_ready(init(*args))
    progress(f"[{cfg.method}] init {time.perf_counter() - t0:.1f}s")
    return state, {k: np.zeros((num_seeds, 0)) for k in RECORD_FIELDS}, 0


def append_records(records: dict, rec) -> tuple:
    """A chunk's records (all processes' seeds) on the host, and the run's `records` with them
    appended: (the chunk's records, the run's)."""
    rec = distributed.gather(rec)
    return rec, {k: np.concatenate([records[k], np.asarray(getattr(rec, k))], axis=1)
                 for k in RECORD_FIELDS}


def _chunk_progress(cfg: config_lib.TrainConfig, rec, n_real: int, updates_done: int,
                    rate: float) -> str:
    """The progress line after a chunk: updates done, rate, ETA, the latest mean reward of the
    real (unpadded) seeds, and a warning for skipped gradients or rejected GP updates."""
    eta = (cfg.num_updates - updates_done) / max(rate, 1e-9)
    msg = (f"[{cfg.method}] updates {updates_done}/{cfg.num_updates} | {rate:.1f} updates/s "
           f"x {n_real} seeds | ETA {eta:.0f}s | mean reward {np.mean(rec.mean_reward[:n_real, -1]):.3f}")
    for field, what in (("nonfinite_grad", "non-finite gradient estimates skipped"),
                        ("gp_guard", "GP updates rejected by the health check")):
        bad = int(np.sum(np.asarray(getattr(rec, field))[:n_real]))
        if bad:
            msg += f" | WARNING: {bad} {what}"
    return msg


# ------------------------------------------------------------------------------------------------
# Summary: final performance, failing seeds, probability of improvement.
# ------------------------------------------------------------------------------------------------


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


def final_performance(mean_reward: np.ndarray) -> np.ndarray:
    """Per seed: the mean reward per step over the last 10% of updates. (..., updates) -> (...)."""
    tail = max(1, int(round(0.1 * mean_reward.shape[-1])))
    return mean_reward[..., -tail:].mean(axis=-1)


def failing_seeds(records: dict, zero_torque: float) -> dict[str, np.ndarray]:
    """Per cause, a (seeds,) bool array of the seeds that failed (records of one method):

    * nonfinite_grad: any gradient estimate was not finite;
    * gp_guard: the GP health check rejected any episode's update;
    * std_at_bound: the learnable sigma was at min_std or max_std after any update;
    * below_zero_torque: the final performance is below the zero-torque policy's;
    * nan_record: any record is NaN;
    * any: any of these.
    """
    out = {
        "nonfinite_grad": np.any(records["nonfinite_grad"] > 0, axis=-1),
        "gp_guard": np.any(records["gp_guard"] > 0, axis=-1),
        "std_at_bound": np.any(records["std_at_bound"] > 0, axis=-1),
        "below_zero_torque": final_performance(records["mean_reward"]) < zero_torque,
        "nan_record": np.any(np.stack([np.isnan(np.asarray(records[k], float)).any(-1)
                                       for k in RECORD_FIELDS]), axis=0),
    }
    out["any"] = np.any(np.stack(list(out.values())), axis=0)
    return out


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


def summarise(records_by_method: dict[str, dict], zero_torque: float | None = None,
              reps: int = stats_lib.DEFAULT_REPS, success: bool = False) -> list[dict]:
    """One row per method: initial and final performance (mean reward per step over the first and
    last 10% of updates), the final's mean with its 95% t-interval and its IQM with the 95%
    stratified-bootstrap interval over seeds, the mean updates to 90%, and the failing seeds.

    Args:
      records_by_method: method -> dict field -> (seeds, updates); at least mean_reward (the
        failure counts need the other `UpdateRecord` fields too).
      zero_torque: the zero-torque policy's reward per step (for `below_zero_torque`); None skips
        the failure counts.
      success: add the swing-up columns (records success_rate and eval_success_rate): the final
        success rate (last 10% of updates) of the exploring episodes and of the deterministic
        controller c(s), mean over seeds, and the seeds whose final deterministic success rate is
        at least 0.9.
    """
    rows = []
    for method, rec in records_by_method.items():
        curves = np.asarray(rec["mean_reward"], float)
        final = final_performance(curves)
        n = len(final)
        half = stats_lib.t_half_width(final) if n > 1 else np.nan
        lo, hi = stats_lib.bootstrap_ci(final, reps=reps) if n > 1 else (np.nan, np.nan)
        tail = max(1, int(round(0.1 * curves.shape[-1])))
        row = dict(
            method=method,
            seeds=n,
            initial_mean=float(curves[:, :tail].mean()),
            final_mean=float(final.mean()),
            ci95_low=float(final.mean() - half),
            ci95_high=float(final.mean() + half),
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
        if zero_torque is not None:
            fails = failing_seeds(rec, zero_torque)
            row["failing_seeds"] = int(fails["any"].sum())
            row.update({f"fail_{c}": int(fails[c].sum()) for c in FAILURE_CAUSES})
            row["zero_torque_reward"] = zero_torque
        rows.append(row)
    return rows


def compare(records_by_method: dict[str, dict], pairs=COMPARISONS,
            reps: int = stats_lib.DEFAULT_REPS) -> list[dict]:
    """Probability of improvement P(X > Y) of final performance, with its 95% bootstrap interval,
    for the pairs whose methods were both run."""
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
    atomic_write_text(path, buf.getvalue())


def summary_markdown(rows: list[dict]) -> str:
    succ = bool(rows) and "final_success_rate" in rows[0]
    head = ("| method | initial | final (mean) | 95% CI | final (IQM) | 95% CI (bootstrap) | "
            "updates to 90% | failing seeds |")
    rule = "|---|---|---|---|---|---|---|---|"
    if succ:
        head += " success (exploring) | success (c(s)) | seeds >= 90% |"
        rule += "---|---|---|"
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
        lines.append(line)
    return "\n".join(lines)


def comparisons_markdown(rows: list[dict]) -> str:
    lines = ["| X | Y | P(X > Y) | 95% CI (bootstrap) |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['x']} | {r['y']} | {r['p_improvement']:.2f} | "
                     f"[{r['ci95_low']:.2f}, {r['ci95_high']:.2f}] |")
    return "\n".join(lines)


def plot_fig5(results: dict[str, np.ndarray], out_dir: str) -> list[str]:
    """Fig. 5: (a) mean reward per step vs updates, (b) exploration std; mean and 95% band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for field, ylabel, name in [
        ("mean_reward", "average reward per step of an episode", "fig5_reward.png"),
        ("exploration_std", "exploration std (mean over visited states) [N m]", "fig5_exploration.png"),
    ]:
        fig, ax = plt.subplots(figsize=(7, 4.2))
        data = results[field]
        for m, curves in zip(results["methods"], data):
            n = curves.shape[0]
            mean = curves.mean(0)
            half = stats_lib.t_half_width(curves) if n > 1 else 0 * mean
            x = np.arange(1, curves.shape[1] + 1)
            ax.plot(x, mean, label=str(m))
            ax.fill_between(x, mean - half, mean + half, alpha=0.25)
        ax.set_xlabel("gradient updates performed")
        ax.set_ylabel(ylabel)
        ax.legend()
        ax.grid(alpha=0.3)
        panel = "(a)" if field == "mean_reward" else "(b)"
        ax.set_title(f"{panel} mean and 95% CI over {data.shape[1]} seeds")
        fig.tight_layout()
        path = os.path.join(out_dir, name)
        buf = io.BytesIO()
        fig.savefig(buf, dpi=120, format="png")
        plt.close(fig)
        _atomic_write_bytes(path, buf.getvalue())
        paths.append(path)
    return paths


# ------------------------------------------------------------------------------------------------
# The whole reproduction, in one pass.
# ------------------------------------------------------------------------------------------------


def reproduce(
    preset: str = "paper",
    seeds: Sequence[int] = tuple(range(10)),
    methods: Sequence[str] = config_lib.METHODS,
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
) -> dict:
    """Runs every method for every seed and writes results.npz, config.json, summary.csv,
    comparisons.csv and Fig. 5 to `out_dir`.

    Returns a dict with the summary and comparison rows, their markdown tables and the output
    paths; `complete` is False when `max_chunks` stopped a method early (then nothing but
    checkpoints is written). With several processes (`distributed.initialize`) the seeds are
    sharded over the devices of all of them; each keeps its own checkpoint, and process 0 reports
    progress and writes config.json, results.npz, the CSV files and the figures. The GP methods
    share one compiled program (`gp_program='shared'`; 'per_method' compiles one each, see
    `chunk_program`).
    """
    _check_gp_program(gp_program)
    seeds = list(map(int, seeds))
    main = distributed.is_main()
    if not main:  # one voice: process 0 reports progress and writes the results
        progress = _silent
    os.makedirs(out_dir, exist_ok=True)
    mesh = make_mesh(num_devices, len(seeds))
    loop = resolve_seed_loop(seed_loop, mesh)
    cfgs = {m: config_lib.preset(preset, method=m, dtype=dtype, **(overrides or {})) for m in methods}
    if main:
        atomic_write_text(os.path.join(out_dir, "config.json"), json.dumps(
            {"preset": preset, "seeds": seeds, "chunk_size": chunk_size, "dtype": dtype,
             "processes": distributed.process_count(),
             "devices": [str(d) for d in mesh.devices.flat], "seed_loop": loop,
             "gp_program": gp_program, "methods": {m: c.to_json_dict() for m, c in cfgs.items()}}, indent=2))

    gp_methods = [m for m in methods if cfgs[m].uses_gp]
    priors = (fit_priors(cfgs[gp_methods[0]], seeds, out_dir, mesh, progress, loop)
              if gp_methods else None)

    records = {}
    for m in methods:
        rec, _ = run_method(cfgs[m], seeds, out_dir, chunk_size=chunk_size, mesh=mesh,
                            kernels=priors if cfgs[m].uses_gp else None,
                            max_chunks=max_chunks, progress=progress, seed_loop=loop,
                            gp_program=gp_program)
        if rec["mean_reward"].shape[1] < cfgs[m].num_updates:
            return {"complete": False}
        records[m] = rec

    c0 = cfgs[methods[0]]
    swingup_task = c0.episode_length * float(np.asarray(c0.pendulum.dt)) >= c0.success_hold_time
    rows = summarise(records, zero_torque_reward(c0), success=swingup_task)
    comparisons = compare(records)
    out = {"complete": True, "summary": rows, "comparisons": comparisons, "figures": [],
           "markdown": summary_markdown(rows)
           + ("\n\n" + comparisons_markdown(comparisons) if comparisons else "")}
    if main:
        arrays = {k: np.stack([records[m][k] for m in methods]) for k in RECORD_FIELDS}
        atomic_savez(os.path.join(out_dir, "results.npz"), methods=np.asarray(methods),
                     seeds=np.asarray(seeds), **arrays)
        write_csv(rows, os.path.join(out_dir, "summary.csv"))
        if comparisons:
            write_csv(comparisons, os.path.join(out_dir, "comparisons.csv"))
        out["figures"] = plot_fig5({"methods": list(methods), **arrays}, out_dir)
    return out
