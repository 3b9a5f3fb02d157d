"""Files of a run: atomic writes, tolerant reads, and the per-method checkpoints of `reproduce`.

* `atomic_write_bytes` / `atomic_write_text` / `atomic_savez`: a file is written to a temporary
  name and renamed, so that a reader sees the old file or the new one, never half of one.
* `read_npz`: every array of an .npz file; one that cannot be read is renamed to
  `<name>.corrupt` (the log says so) and read as missing, so that part of the run starts afresh.
* `digest`: a short hash of what a file was computed from (config, seeds, ...); a file whose
  digest differs was written by another run and is ignored.
* `checkpoint_path`, `save_checkpoint`, `load_checkpoint`: a method's state after its last
  finished chunk of updates and its records so far, one file per process (each holds the rows of
  its own seeds), the previous one kept beside it, so that processes interrupted between their
  writes still resume from a chunk they all hold; `remove_checkpoints` once the run is written.
* `open_out_dir`: the output directory, created and locked for this run, so that two runs never
  write the same files.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import zipfile

import jax
import numpy as np

from gpguided_jax import distributed

try:
    import fcntl
except ImportError:  # not POSIX: output directories are not locked
    fcntl = None

# Part of every digest: bump it when the state's pytree or the compiled programs change, and the
# checkpoints and fitted priors written before are ignored.
CHECKPOINT_VERSION = 4


def atomic_write_bytes(path: str, data: bytes, keep_previous: bool = False) -> None:
    """Writes `data` to `path` through a temporary file and a rename; with `keep_previous` an
    existing file is first renamed to `<path>.prev`."""
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    if keep_previous and os.path.exists(path):
        os.replace(path, path + ".prev")
    os.replace(tmp, path)  # atomic: a reader sees the old file or the new one, never half of one


def atomic_savez(path: str, **arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def atomic_write_text(path: str, text: str) -> None:
    atomic_write_bytes(path, text.encode())


class OutDirError(RuntimeError):
    """The output directory cannot be used: not a directory, not writable, or another run's."""


@contextlib.contextmanager
def open_out_dir(out_dir: str):
    """Creates `out_dir` if needed and holds an exclusive lock on it (`.gpguided.lock`, one per
    process of a multi-process run) while the body runs. Raises `OutDirError`, in one line, when
    `out_dir` is a file, cannot be written, or is locked by another run."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise OutDirError(f"{out_dir} exists and is not a directory")
    try:
        os.makedirs(out_dir, exist_ok=True)
        n = distributed.process_count()
        name = ".gpguided.lock" if n == 1 else f".gpguided.process{jax.process_index()}-of-{n}.lock"
        lock = open(os.path.join(out_dir, name), "a")
    except OSError as e:
        raise OutDirError(f"cannot write to {out_dir}: {e.strerror or e}") from None
    with lock:
        if fcntl is not None:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                raise OutDirError(f"another run is writing to {out_dir} (it holds {lock.name}); "
                                  "wait for it to finish or choose another output directory") from None
        yield out_dir


def remove_checkpoints(out_dir: str, method: str) -> None:
    """Deletes `method`'s checkpoint files of this process (and the previous ones kept beside
    them): what a finished run no longer needs."""
    base = checkpoint_path(out_dir, method)
    for path in (base, base + ".prev"):
        if os.path.exists(path):
            os.remove(path)


def _set_aside(path: str, why: str, progress) -> None:
    bad = path + ".corrupt"
    os.replace(path, bad)
    progress(f"WARNING: {path} could not be read ({why}); moved to {bad}, starting that part afresh")


def read_npz(path: str, progress) -> dict | None:
    """All arrays of an .npz file, or None if it is missing; a corrupt file is set aside (renamed
    to `<path>.corrupt`, with a warning to `progress`)."""
    if not os.path.exists(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        _set_aside(path, f"{type(e).__name__}: {e}", progress)
        return None


def digest(*parts) -> str:
    """A short hash of `CHECKPOINT_VERSION` and `parts` (JSON-serialisable)."""
    text = json.dumps((CHECKPOINT_VERSION, *parts), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def checkpoint_path(out_dir: str, method: str) -> str:
    """This process's checkpoint: checkpoint_<method>.npz, or with several processes
    checkpoint_<method>.process<I>-of-<N>.npz (each holds its own seeds' state)."""
    n = distributed.process_count()
    tag = "" if n == 1 else f".process{jax.process_index()}-of-{n}"
    return os.path.join(out_dir, f"checkpoint_{method}{tag}.npz")


def save_checkpoint(path: str, state, records: dict, chunks_done: int, run_digest: str) -> None:
    """This process's rows of the state and all records, atomically; the previous checkpoint is
    kept as `<path>.prev` so that processes interrupted between their writes can still agree."""
    arrays = {}
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state)):
        rows, arrays[f"leaf_{i}"] = distributed.local_rows(leaf)
    arrays.update({f"rec_{k}": np.asarray(v) for k, v in records.items()})
    buf = io.BytesIO()
    np.savez(buf, chunks_done=chunks_done, digest=run_digest, rows=rows, **arrays)
    atomic_write_bytes(path, buf.getvalue(), keep_previous=True)


def read_checkpoint(path: str, template, record_fields, run_digest: str, mesh, progress):
    """(chunks_done, state, records) from one checkpoint file, or None (missing, stale or corrupt;
    a corrupt file is set aside).

    Args:
      template: the state's shapes (`jax.eval_shape` of the initial states).
      record_fields: the names of the records it must hold.
      run_digest: the `digest` of the run; a file with another is ignored.
    """
    saved = read_npz(path, progress)
    if saved is None:
        return None
    if str(saved.get("digest", "")) != run_digest:
        progress(f"ignoring {path}: it was written by a different config or seed list")
        return None
    treedef = jax.tree_util.tree_structure(template)
    shapes = [t.shape for t in jax.tree_util.tree_leaves(template)]
    rows = distributed.expected_rows(shapes[0], mesh)
    leaves = [saved.get(f"leaf_{i}") for i in range(treedef.num_leaves)]
    records = {k[4:]: v for k, v in saved.items() if k.startswith("rec_")}
    ok = (
        "chunks_done" in saved and "rows" in saved and np.array_equal(saved["rows"], rows)
        and set(records) == set(record_fields)
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


def load_checkpoint(path: str, template, record_fields, run_digest: str, mesh, progress):
    """(state, records, chunks_done) of the newest checkpoint that every process has (its latest
    or the one before), or None: the processes exchange which chunk counts they hold and all
    resume from the same one, or all start afresh. Arguments as `read_checkpoint`'s."""
    found = {}
    for candidate in (path, path + ".prev"):
        got = read_checkpoint(candidate, template, record_fields, run_digest, mesh, progress)
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
