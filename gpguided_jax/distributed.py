"""Seeds across processes and hosts: `jax.distributed` helpers for `gpguided reproduce`.

JAX's multi-controller model: the same program runs in every process; `initialize` connects them,
after which `jax.devices()` lists the devices of all processes and a `jit` over a mesh of them is
one SPMD program. Each process holds the rows (seeds) of the arrays that live on its own devices:

* `shard(tree, mesh)` builds global arrays, sharded over the mesh's first axis, from host arrays
  that every process computes in full (seed keys, fitted priors);
* `gather(tree)` brings a sharded result (records, priors) to every process;
* `local_rows(array)` / `from_local_rows(...)` take a process's own rows out of a global array and
  put them back (per-process checkpoints);
* `agree(values)` collects one small integer vector from every process (to agree on a checkpoint).

With one process all of these reduce to the single-process operations.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Connects this process to the others (before any other JAX call). On CPUs, the
    cross-process collectives (gathering results, agreeing on a checkpoint; the compiled training
    loop itself needs none, `sharding.per_seed_program`) run over gloo."""
    if not 0 <= process_id < num_processes:
        raise ValueError(f"process id {process_id} must be in [0, {num_processes})")
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except (AttributeError, ValueError, KeyError):  # newer JAX: gloo is the default, no flag
        pass
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id)


def process_count() -> int:
    return jax.process_count()


def is_main() -> bool:
    """Whether this is process 0 (the one that writes results and reports progress)."""
    return jax.process_index() == 0


def shard(tree, mesh: Mesh):
    """Global arrays from host arrays (the same full array in every process), leading axis split
    over the mesh; each process places only the rows of its own devices."""
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))

    def put(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(put, tree)


def gather(tree):
    """Every leaf in full, as NumPy, in every process."""
    if process_count() == 1:
        return jax.device_get(tree)
    return jax.tree_util.tree_map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def _row_slices(array: jax.Array) -> list[tuple[int, int, jax.Array]]:
    out = {}
    for s in array.addressable_shards:
        rows = s.index[0]
        start = 0 if rows.start is None else rows.start
        stop = array.shape[0] if rows.stop is None else rows.stop
        out[(start, stop)] = s.data  # replicas of the same rows appear once
    return [(a, b, d) for (a, b), d in sorted(out.items())]


def local_rows(array: jax.Array) -> tuple[np.ndarray, np.ndarray]:
    """(row indices, rows) of a global array that live on this process's devices."""
    parts = _row_slices(array)
    rows = np.concatenate([np.arange(a, b) for a, b, _ in parts])
    return rows, np.concatenate([np.asarray(d) for _, _, d in parts])


def expected_rows(shape, mesh: Mesh) -> np.ndarray:
    """The row indices this process holds of an array of `shape` sharded by `shard`."""
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    spans = set()
    for index in sharding.addressable_devices_indices_map(tuple(shape)).values():
        rows = index[0]
        spans.add((rows.start or 0, shape[0] if rows.stop is None else rows.stop))
    return np.concatenate([np.arange(a, b) for a, b in sorted(spans)])


def from_local_rows(shape, rows: np.ndarray, data: np.ndarray, mesh: Mesh) -> jax.Array:
    """A global array of `shape` from this process's rows (the inverse of `local_rows`)."""
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    position = {int(r): i for i, r in enumerate(rows)}

    def fetch(index):
        wanted = np.arange(shape[0])[index[0]]
        return data[[position[int(r)] for r in wanted]]

    return jax.make_array_from_callback(tuple(shape), sharding, fetch)


def agree(values) -> np.ndarray:
    """(processes, len(values)) int array: `values` of every process, in process order."""
    values = np.asarray(values, np.int64)
    if process_count() == 1:
        return values[None]
    return np.asarray(multihost_utils.process_allgather(values))
