"""Sharding a batch over devices: the four CPU devices of the test run."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, initial_state, rigid_body_field


def test_sharded_batch_equals_unsharded_on_four_devices():
    """A batch placed on the four CPU devices (conftest.py) runs as the
    unsharded batch does, through both drivers (by `jit(vmap)` of the sharded
    batch and by `vmap_over_devices`), with a gradient and with its run-time
    checks."""
    assert len(jax.devices()) == 4, jax.devices()
    bundle = pk.Cotangent(pk.SO3)
    field = rigid_body_field(bundle, "body")
    method = pk.PRKMK(bundle, pk.Exp(), pk.stormer_verlet, form="body")
    y0s = jax.tree.map(lambda *a: jnp.stack(a), *[initial_state(bundle, seed=s) for s in range(8)])
    inertias = jnp.asarray(INERTIA) * (1 + 0.05 * jnp.arange(8.0))[:, None]

    def scan_run(y0, inertia):
        return pk.integrate(method, field, y0, 0.0, 0.01, 100, inertia, save_every=50).ys

    def diffrax_run(y0, inertia):
        return diffrax.diffeqsolve(pk.PRKMKTerm(field), pk.PRKMKSolver(method), 0.0, 1.0, 0.01, y0, inertia).ys

    scan_over_devices = jax.jit(pk.vmap_over_devices(scan_run))  # run again below on a broken batch
    for run, routes in (
        (scan_run, (jax.jit(jax.vmap(scan_run)), scan_over_devices)),
        (diffrax_run, (jax.jit(pk.vmap_over_devices(diffrax_run)),)),
    ):
        plain = jax.jit(jax.vmap(run))(y0s, inertias)
        for batched in routes:
            sharded = batched(pk.shard_batch(y0s), pk.shard_batch(inertias))
            out = sharded.fiber
            assert len(out.sharding.device_set) == 4, out.sharding
            assert sorted(s.data.shape[0] for s in out.addressable_shards) == [2, 2, 2, 2]
            for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(sharded)):
                assert np.abs(np.asarray(a) - np.asarray(b)).max() <= 1e-14
            # One process: its rows are the whole batch.
            for a, b, c in zip(jax.tree.leaves(pk.local_rows(sharded)), jax.tree.leaves(pk.gather(sharded)), jax.tree.leaves(sharded)):
                assert isinstance(a, np.ndarray) and np.array_equal(a, b) and np.array_equal(a, np.asarray(c))

    # A shared argument and a gradient summed over the devices.
    def loss(inertia, y0s, map_over_batch, gradient):
        def final_moment(y0, inertia):
            return pk.integrate(method, field, y0, 0.0, 0.01, 100, inertia, gradient=gradient).ys.fiber[-1]

        return jnp.mean(map_over_batch(final_moment, in_axes=(0, None))(y0s, inertia)[:, 0] * jnp.arange(1.0, 9.0))

    shared = jnp.asarray(INERTIA)
    value_and_grad = jax.jit(jax.value_and_grad(loss), static_argnums=(2, 3))
    plain = value_and_grad(shared, y0s, jax.vmap, pk.StoredSteps())
    sharded = value_and_grad(shared, pk.shard_batch(y0s), pk.vmap_over_devices, pk.StoredSteps())
    for a, b in zip(plain, sharded):
        assert np.abs(np.asarray(a) - np.asarray(b)).max() <= 1e-12 * np.abs(np.asarray(a)).max(), (plain, sharded)

    # The run-time checks still raise on each device's rows.
    broken = pk.shard_batch(eqx.tree_at(lambda y: y.fiber, y0s, y0s.fiber.at[5, 0].set(jnp.nan)))
    try:
        jax.block_until_ready(scan_over_devices(broken, inertias))
    except Exception as error:
        assert "not finite" in str(error), error
    else:
        raise AssertionError("a NaN row ran")
    # A batch that does not split over the four devices.
    six = jax.tree.map(lambda a: a[:6], y0s)
    for split in (pk.shard_batch, lambda y: pk.vmap_over_devices(scan_run, in_axes=(0, None))(y, inertias[0])):
        try:
            split(six)
        except ValueError as error:
            assert "6 rows" in str(error) and "4 device" in str(error), error
        else:
            raise AssertionError("6 rows split over 4 devices")


def test_shard_batch_checks_the_batch_axis():
    with pytest.raises(ValueError, match="leading batch axis"):
        pk.shard_batch(jnp.float64(1.0))
    sharded = pk.shard_batch({"a": jnp.ones((8, 2))})
    assert sharded["a"].shape == (8, 2) and len(sharded["a"].sharding.device_set) == len(jax.devices())


def test_vmap_over_devices_refuses_what_it_cannot_split():
    double = pk.vmap_over_devices(lambda x, c: 2 * x + c, in_axes=(0, None))
    assert jnp.array_equal(double(jnp.arange(8.0), 1.0), 2 * jnp.arange(8.0) + 1)
    with pytest.raises(ValueError, match="in_axes entries are 0 or None"):
        pk.vmap_over_devices(lambda x: x, in_axes=1)(jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="in_axes has 1 entries for 2 arguments"):
        pk.vmap_over_devices(lambda x, c: x, in_axes=(0,))(jnp.ones(2), 1.0)
    with pytest.raises(ValueError, match="leading batch axis"):
        pk.vmap_over_devices(lambda x: x)({"a": jnp.ones(2), "b": jnp.ones(3)})
    with pytest.raises(TypeError, match="needs a function"):
        pk.vmap_over_devices(3)
