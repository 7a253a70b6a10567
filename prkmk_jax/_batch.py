"""Batches of initial conditions or parameters, split over every device of
every process (a 1-D `jax.sharding.Mesh` over the batch axis).

    ys0 = shard_batch(rows)                  # this process's rows, placed on the mesh
    run = jax.jit(vmap_over_devices(lambda y0, i: pk.integrate(method, f, y0, 0.0, dt, n, i).ys, in_axes=(0, None)))
    out = run(ys0, inertia)                  # each device integrates its rows; out stays where it was computed
    mine = local_rows(out)                   # this process's rows, no communication
    every = gather(out)                      # the whole batch on every process, when asked

The same code runs in one process (its rows are the whole batch) and in
many, after `jax.distributed.initialize`: each process passes the rows it
holds, and the global batch is their concatenation in process order. JAX's
runtime does the communication; nothing here sends data itself.

`vmap_over_devices` runs `jax.vmap` of the function inside `jax.shard_map`,
so each device iterates its own implicit stages to its own stop. Under
`jit(vmap(...))` of a sharded batch instead, every stage loop's stopping
test is one program over the whole batch, an all-reduce across devices at
every iteration of every step.
"""

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PyTree

BATCH_AXIS = "batch"


def batch_sharding(devices: Sequence[jax.Device] | None = None) -> NamedSharding:  # pyright: ignore[reportInvalidTypeForm]  # jax.Device is an alias of the runtime's device class
    """Split the leading axis over `devices` (default: every device of every
    process), ordered by process and then by device id, so that each
    process's devices hold one contiguous block of rows, in process order."""
    devices = sorted(jax.devices() if devices is None else devices, key=lambda d: (d.process_index, d.id))
    if not devices:
        raise ValueError("batch_sharding needs at least one device.")
    return NamedSharding(Mesh(np.asarray(devices), (BATCH_AXIS,)), PartitionSpec(BATCH_AXIS))


def shard_batch(batch: PyTree, devices: Sequence[jax.Device] | None = None) -> PyTree:  # pyright: ignore[reportInvalidTypeForm]  # as above
    """Place every array leaf of `batch` with its leading (batch) axis split
    over `devices` (default: every device of every process).

    In one process `batch` is the whole batch, of a size divisible by the
    number of devices. In several processes each passes the rows it holds:
    the same number in every process, divisible by its number of devices in
    the mesh; the global batch is their concatenation in process order. A
    process with another number of rows than the others is a `ValueError`
    in every process (found by one all-gather of the row counts, so every
    process must call this, as every process calls any computation on the
    global batch)."""
    sharding = batch_sharding(devices)
    local_devices = len(sharding.addressable_devices)
    rows = _leading_size(batch, "shard_batch")
    if jax.process_count() > 1:
        counts = np.asarray(multihost_utils.process_allgather(np.int64(rows))).reshape(-1)
        if np.any(counts != counts[0]):
            held = ", ".join(f"process {p}: {int(c)}" for p, c in enumerate(counts))
            raise ValueError(f"every process must pass the same number of rows to shard_batch; they hold {held}.")
    if local_devices == 0 or rows % local_devices:
        raise ValueError(f"this process's batch of {rows} rows does not split evenly over its {local_devices} device(s) in the mesh.")

    def placed(leaf):
        # A JAX array goes as it is: no trip through the host where it is on a device already.
        return jax.make_array_from_process_local_data(sharding, leaf if isinstance(leaf, jax.Array) else np.asarray(leaf))

    return jax.tree.map(placed, batch)


def vmap_over_devices(
    fn: Callable[..., Any],
    in_axes: int | None | Sequence[int | None] = 0,
    devices: Sequence[jax.Device] | None = None,  # pyright: ignore[reportInvalidTypeForm]  # as above
) -> Callable[..., Any]:
    """`jax.vmap(fn, in_axes)` with each device running its own rows: a
    `jax.shard_map` over the batch mesh of `batch_sharding(devices)`, with no
    communication between devices inside `fn`.

    `in_axes` as in `jax.vmap` but only 0 (batched, split over the devices:
    pass a batch from `shard_batch`) or None (the same on every device) per
    positional argument. Every output leaf is batched along its leading
    axis. Call it under `jax.jit`; a loss over its outputs (a mean over the
    batch) is one reduction across devices at the end, and its gradient
    with respect to an unbatched argument is summed across devices."""
    if not callable(fn):
        raise TypeError(f"vmap_over_devices needs a function, got {type(fn).__name__}.")
    sharding = batch_sharding(devices)
    mesh = sharding.mesh

    def mapped(*args):
        axes = (in_axes,) * len(args) if in_axes is None or isinstance(in_axes, int) else tuple(in_axes)
        if len(axes) != len(args):
            raise ValueError(f"in_axes has {len(axes)} entries for {len(args)} arguments.")
        for axis, arg in zip(axes, args):
            if axis not in (0, None):
                raise ValueError(f"vmap_over_devices maps over the leading axis only: in_axes entries are 0 or None, got {axis!r}.")
            if axis == 0:
                rows = _leading_size(arg, "vmap_over_devices")
                if rows % mesh.size:
                    raise ValueError(f"a batched argument's {rows} rows do not split evenly over {mesh.size} devices.")
        specs = tuple(sharding.spec if axis == 0 else PartitionSpec() for axis in axes)
        # check_vma=False: equinox's runtime checks (eqx.error_if) branch
        # between a device-varying value and an unvarying one, which the
        # varying-axis type check refuses; every output is per device.
        per_device = jax.shard_map(jax.vmap(fn, in_axes=axes), mesh=mesh, in_specs=specs, out_specs=sharding.spec, check_vma=False)
        return per_device(*args)

    return mapped


def gather(tree: PyTree) -> PyTree:
    """Every array leaf whole, as NumPy, on every process: a collective, so
    every process calls it; with one process, `jax.device_get`."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    return multihost_utils.process_allgather(tree, tiled=True)


def local_rows(tree: PyTree) -> PyTree:
    """This process's part of every array leaf, as NumPy, without
    communication: the block of the global array its devices hold (for a
    batch placed by `shard_batch`, the rows this process passed, or what was
    computed from them), a replicated leaf whole."""

    def part(leaf):
        if not isinstance(leaf, jax.Array):
            return np.asarray(leaf)
        if leaf.is_fully_replicated:
            return np.asarray(leaf.addressable_shards[0].data)
        blocks = [[s.index[k].indices(n)[:2] for k, n in enumerate(leaf.shape)] for s in leaf.addressable_shards]
        lo = [min(block[k][0] for block in blocks) for k in range(leaf.ndim)]
        hi = [max(block[k][1] for block in blocks) for k in range(leaf.ndim)]
        out = np.empty([high - low for low, high in zip(lo, hi)], leaf.dtype)
        covered = np.zeros(out.shape, bool)
        for shard, block in zip(leaf.addressable_shards, blocks):
            region = tuple(slice(start - low, stop - low) for (start, stop), low in zip(block, lo))
            out[region] = np.asarray(shard.data)
            covered[region] = True
        if not covered.all():
            raise ValueError(f"this process's shards of an array of shape {leaf.shape} are not one block; use gather instead.")
        return out

    return jax.tree.map(part, tree)


def _leading_size(tree: PyTree, caller: str) -> int:
    shapes = [np.shape(leaf) for leaf in jax.tree.leaves(tree)]
    sizes = {shape[0] for shape in shapes if shape}
    if len(sizes) != 1 or any(not shape for shape in shapes):
        raise ValueError(f"{caller} needs array leaves with one common leading batch axis; got shapes {shapes}.")
    return sizes.pop()
