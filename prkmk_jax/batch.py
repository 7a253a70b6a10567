"""Batches of initial conditions or parameters, on one device or sharded
across all of them (a 1-D `jax.sharding.Mesh` over the batch axis).

    ys0 = shard_batch(batch_of_y0)           # leading axis split over devices
    run = jax.jit(jax.vmap(lambda y0: pk.integrate(method, f, y0, 0.0, dt, n, args)))
    out = run(ys0)                           # computed and left where each shard lives

JAX's SPMD partitioner carries the input sharding through `jit(vmap(...))`,
so each device integrates its own slice; nothing is gathered until asked.
"""

from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PyTree

BATCH_AXIS = "batch"


def batch_sharding(devices: Sequence[jax.Device] | None = None) -> NamedSharding:  # pyright: ignore[reportInvalidTypeForm]  # jax.Device is an alias of the runtime's device class
    """Split the leading axis over `devices` (default: all of them)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("batch_sharding needs at least one device.")
    return NamedSharding(Mesh(np.asarray(devices), (BATCH_AXIS,)), PartitionSpec(BATCH_AXIS))


def shard_batch(batch: PyTree, devices: Sequence[jax.Device] | None = None) -> PyTree:  # pyright: ignore[reportInvalidTypeForm]  # as above
    """Place every array leaf of `batch` with its leading (batch) axis split
    evenly over `devices`; the batch size must be a multiple of their number."""
    sharding = batch_sharding(devices)
    n = sharding.mesh.size
    for leaf in jax.tree.leaves(batch):
        if np.ndim(leaf) == 0 or np.shape(leaf)[0] % n:
            raise ValueError(f"every leaf needs a leading batch axis divisible by {n} devices; got shape {np.shape(leaf)}.")
    return jax.device_put(batch, sharding)
