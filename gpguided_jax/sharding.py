"""Seeds over devices: one PRNG key per seed, a one-axis mesh, and per-seed programs over it.

Every multi-seed run of the project (`reproduce`, `sweep`, `bench`, the experiment scripts) runs
its seeds this way: the seeds' keys (`seed_keys`), padded to a multiple of the device count
(`pad_seeds`), are placed with their leading axis split over a mesh (`make_mesh`, `shard`), and a
function of one seed becomes one compiled program over all of them (`per_seed_program`), each
device running its own seeds one after another or as one batch (`resolve_seed_loop`).
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from gpguided_jax import distributed

SEED_LOOPS = ("auto", "vmap", "map")


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


def shard(tree, mesh: Mesh):
    """Places every leaf with its leading (seed) axis split over the mesh (over the devices of
    every process when there are several; each process places its own rows): the inputs of a
    `per_seed_program`."""
    return distributed.shard(tree, mesh)
