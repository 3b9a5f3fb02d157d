"""Chunked, resumable, device-sharded runs of every method over many seeds (Fig. 5), and their
summary, table and plots. The `gpguided reproduce` command is a thin wrapper over `reproduce`.

Output directory layout:
  config.json            resolved config of every method (+ seeds, chunk size, devices)
  checkpoint_<method>.npz  state after the last finished chunk and the records so far
  kernels.npz            fitted GP hyperparameters and prior mean per seed (shared by the GP methods)
  results.npz            methods (names), seeds, and per-update records of shape (methods, seeds, updates)
  summary.csv            final performance (mean, 95% CI over seeds) and updates to 90%
  fig5_reward.png, fig5_exploration.png
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import sys
import time
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from gpguided_jax import config as config_lib
from gpguided_jax import train as train_lib

RECORD_FIELDS = train_lib.UpdateRecord._fields
CHECKPOINT_VERSION = 2  # bump when the state's pytree changes; older checkpoints are ignored


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def seed_keys(seeds: Sequence[int]) -> jax.Array:
    """One raw uint32 PRNG key per seed (raw keys are plain arrays: easy to checkpoint)."""
    return jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])


def make_mesh(num_devices: int | None = None) -> Mesh:
    devices = jax.devices()
    n = len(devices) if num_devices is None else min(int(num_devices), len(devices))
    if n < 1:
        raise ValueError(f"--devices must be >= 1, got {num_devices}")
    return Mesh(np.array(devices[:n]), ("seeds",))


def pad_seeds(seeds: Sequence[int], num_devices: int) -> list[int]:
    """The seeds followed by extra ones up to a multiple of `num_devices` (they only fill devices;
    their results are dropped)."""
    seeds = list(map(int, seeds))
    return seeds + [seeds[-1] + 1 + i for i in range((-len(seeds)) % num_devices)]


def _shard(tree, mesh: Mesh):
    """Places every leaf with its leading (seed) axis split over the mesh."""
    sharding = NamedSharding(mesh, PartitionSpec("seeds"))
    return jax.device_put(tree, sharding)


def _config_hash(cfg: config_lib.TrainConfig, seeds, chunk_size) -> str:
    blob = json.dumps([CHECKPOINT_VERSION, cfg.to_json_dict(), list(map(int, seeds)), chunk_size],
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _save_checkpoint(path, state, records, chunks_done, digest):
    leaves = jax.tree_util.tree_leaves(jax.device_get(state))
    arrays = {f"leaf_{i}": np.asarray(x) for i, x in enumerate(leaves)}
    arrays.update({f"rec_{k}": np.asarray(v) for k, v in records.items()})
    tmp = path + ".tmp.npz"
    np.savez(tmp, chunks_done=chunks_done, digest=digest, **arrays)
    os.replace(tmp, path)  # atomic: an interrupted save never leaves a half-written checkpoint


def _load_checkpoint(path, template, digest):
    if not os.path.exists(path):
        return None
    with np.load(path) as f:
        if str(f["digest"]) != digest:
            _log(f"ignoring {path}: it was written by a different config or seed list")
            return None
        treedef = jax.tree_util.tree_structure(template)
        n = treedef.num_leaves
        state = jax.tree_util.tree_unflatten(treedef, [f[f"leaf_{i}"] for i in range(n)])
        records = {k[4:]: f[k] for k in f.files if k.startswith("rec_")}
        return state, records, int(f["chunks_done"])


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
) -> dict[str, np.ndarray]:
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

    Returns:
      dict field -> (seeds, updates_done) array of the per-update records.
    """
    mesh = mesh or make_mesh()
    n_dev = mesh.devices.size
    seeds = list(map(int, seeds))
    n_real = len(seeds)
    padded = pad_seeds(seeds, n_dev)
    pad = len(padded) - n_real
    train = train_lib.make_train(cfg)
    keys = _shard(seed_keys(padded), mesh)
    if kernels is not None and pad:
        kernels = jax.tree_util.tree_map(lambda x: np.concatenate([x, x[-pad:]]), kernels)

    init = jax.jit(jax.vmap(lambda k, kern: train.init(k, cfg, kern)) if kernels is not None
                   else jax.vmap(lambda k: train.init(k, cfg)))
    chunk_size = min(chunk_size, cfg.num_updates)
    n_chunks = -(-cfg.num_updates // chunk_size)
    run = {}

    def chunk_fn(n):
        if n not in run:
            run[n] = jax.jit(jax.vmap(lambda s: train.run_chunk(s, cfg, n)), donate_argnums=0)
        return run[n]

    ckpt = os.path.join(out_dir, f"checkpoint_{cfg.method}.npz")
    digest = _config_hash(cfg, padded, chunk_size)
    args = (keys,) if kernels is None else (keys, _shard(kernels, mesh))
    template = jax.eval_shape(init, *args)
    loaded = _load_checkpoint(ckpt, template, digest)
    if loaded is not None:
        state, records, done = loaded
        state = _shard(state, mesh)
        progress(f"[{cfg.method}] resuming from {ckpt}: {done}/{n_chunks} chunks done")
    else:
        t0 = time.perf_counter()
        state = init(*args)
        jax.block_until_ready(state)
        progress(f"[{cfg.method}] init (hyperparameter fit) {time.perf_counter() - t0:.1f}s")
        records, done = {k: np.zeros((len(padded), 0)) for k in RECORD_FIELDS}, 0

    t_start, chunks_this_call = time.perf_counter(), 0
    while done < n_chunks and (max_chunks is None or chunks_this_call < max_chunks):
        n = min(chunk_size, cfg.num_updates - done * chunk_size)
        state, rec = chunk_fn(n)(state)
        rec = jax.device_get(rec)
        bad = int(np.sum(rec.nonfinite_grad))
        records = {k: np.concatenate([records[k], np.asarray(getattr(rec, k))], axis=1)
                   for k in RECORD_FIELDS}
        done += 1
        chunks_this_call += 1
        _save_checkpoint(ckpt, state, records, done, digest)
        elapsed = time.perf_counter() - t_start
        updates_done = min(done * chunk_size, cfg.num_updates)
        rate = chunks_this_call * chunk_size / max(elapsed, 1e-9)
        eta = (cfg.num_updates - updates_done) / max(rate, 1e-9)
        msg = (f"[{cfg.method}] updates {updates_done}/{cfg.num_updates} | {rate:.1f} updates/s "
               f"x {n_real} seeds | ETA {eta:.0f}s | mean reward {np.mean(rec.mean_reward[:n_real, -1]):.3f}")
        if bad:
            msg += f" | WARNING: {bad} non-finite gradient estimates skipped"
        progress(msg)
    return {k: v[:n_real] for k, v in records.items()}, state


def summarise(mean_reward: np.ndarray, methods: Sequence[str]) -> list[dict]:
    """Per method: final performance (mean reward per step over the last 10% of updates), its mean
    and 95% t-interval over seeds, and the updates needed to reach 90% of the way from the initial
    to the final performance (per seed on a 10-update moving average; mean over seeds).

    Args:
      mean_reward: (methods, seeds, updates).
    """
    from scipy import stats

    rows = []
    n_updates = mean_reward.shape[-1]
    tail = max(1, int(round(0.1 * n_updates)))
    for m, curves in zip(methods, mean_reward):
        final = curves[:, -tail:].mean(axis=1)
        n = len(final)
        half = stats.t.ppf(0.975, n - 1) * final.std(ddof=1) / np.sqrt(n) if n > 1 else np.nan
        w = min(10, n_updates)
        smooth = np.stack([np.convolve(c, np.ones(w) / w, mode="valid") for c in curves])
        start = smooth[:, :1]
        target = start + 0.9 * (final[:, None] - start)
        improving = final[:, None] >= start
        reached = np.where(improving, smooth >= target, smooth <= target)
        first = np.where(reached.any(axis=1), reached.argmax(axis=1) + w, n_updates)
        rows.append(dict(
            method=m,
            final_mean=float(final.mean()),
            ci95_low=float(final.mean() - half),
            ci95_high=float(final.mean() + half),
            initial_mean=float(curves[:, :tail].mean()),
            updates_to_90pct=float(np.mean(first)),
            seeds=n,
        ))
    return rows


def write_summary_csv(rows: list[dict], path: str) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def summary_markdown(rows: list[dict]) -> str:
    lines = ["| method | initial | final (mean) | 95% CI | updates to 90% |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['initial_mean']:.3f} | {r['final_mean']:.3f} | "
                     f"[{r['ci95_low']:.3f}, {r['ci95_high']:.3f}] | {r['updates_to_90pct']:.0f} |")
    return "\n".join(lines)


def plot_fig5(results: dict[str, np.ndarray], out_dir: str) -> list[str]:
    """Fig. 5: (a) mean reward per step vs updates, (b) exploration std; mean and 95% band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

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
            half = (stats.t.ppf(0.975, n - 1) * curves.std(0, ddof=1) / np.sqrt(n)) if n > 1 else 0 * mean
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
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


def reproduce(
    preset: str = "paper",
    seeds: Sequence[int] = tuple(range(10)),
    methods: Sequence[str] = config_lib.METHODS,
    out_dir: str = "results/paper",
    *,
    chunk_size: int = 50,
    num_devices: int | None = None,
    max_chunks: int | None = None,
    overrides: dict | None = None,
    progress: Callable[[str], None] = _log,
) -> dict:
    """Runs every method for every seed and writes results.npz, config.json, summary.csv, Fig. 5.

    Returns a dict with the summary rows and the output paths; `complete` is False when
    `max_chunks` stopped a method early (then nothing but checkpoints is written).
    """
    os.makedirs(out_dir, exist_ok=True)
    mesh = make_mesh(num_devices)
    cfgs = {m: config_lib.preset(preset, method=m, **(overrides or {})) for m in methods}
    with open(os.path.join(out_dir, "config.json"), "w") as f:
        json.dump({"preset": preset, "seeds": list(map(int, seeds)), "chunk_size": chunk_size,
                   "devices": [str(d) for d in mesh.devices.flat],
                   "methods": {m: c.to_json_dict() for m, c in cfgs.items()}}, f, indent=2)

    # The GP hyperparameters depend only on the seed (initial policy and its data), so they are
    # fitted once per seed and shared by the GP methods.
    kernels = None
    gp_methods = [m for m in methods if cfgs[m].uses_gp]
    if gp_methods:
        kpath = os.path.join(out_dir, "kernels.npz")
        cfg0 = cfgs[gp_methods[0]]
        fit = jax.jit(jax.vmap(train_lib.make_train(cfg0).fit_kernel_for_seed))
        if os.path.exists(kpath):
            with np.load(kpath) as f:
                if list(f["seeds"]) == list(seeds) and "prior_mean" in f.files:
                    fields = train_lib.kernels.KernelParams._fields
                    kernels = train_lib.GPPrior(
                        train_lib.kernels.KernelParams(*(f[k] for k in fields)), f["prior_mean"])
        if kernels is None:
            t0 = time.perf_counter()
            fitted = fit(_shard(seed_keys(pad_seeds(seeds, mesh.devices.size)), mesh))
            kernels = jax.tree_util.tree_map(lambda x: np.asarray(x)[: len(seeds)], jax.device_get(fitted))
            np.savez(kpath, seeds=np.asarray(seeds), prior_mean=kernels.mean,
                     **kernels.kernel._asdict())
            progress(f"hyperparameter fit for {len(seeds)} seeds: {time.perf_counter() - t0:.1f}s")

    results = {k: [] for k in RECORD_FIELDS}
    complete = True
    for m in methods:
        recs, _ = run_method(cfgs[m], seeds, out_dir, chunk_size=chunk_size, mesh=mesh,
                             kernels=kernels if cfgs[m].uses_gp else None,
                             max_chunks=max_chunks, progress=progress)
        if recs["mean_reward"].shape[1] < cfgs[m].num_updates:
            complete = False
            continue
        for k in RECORD_FIELDS:
            results[k].append(recs[k])
    if not complete:
        return {"complete": False}
    arrays = {k: np.stack(v) for k, v in results.items()}
    np.savez(os.path.join(out_dir, "results.npz"), methods=np.asarray(methods),
             seeds=np.asarray(seeds), **arrays)
    rows = summarise(arrays["mean_reward"], methods)
    write_summary_csv(rows, os.path.join(out_dir, "summary.csv"))
    figs = plot_fig5({"methods": list(methods), **arrays}, out_dir)
    return {"complete": True, "summary": rows, "figures": figs, "markdown": summary_markdown(rows)}
