"""Sharding a batch over devices: 4 CPU devices forced in a subprocess."""

import subprocess
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import pytest

import prkmk_jax as pk

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent(
    """
    import os
    # The test run's XLA flags (conftest.py), with 4 host devices added.
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    import sys
    sys.path.insert(0, "tests")
    import diffrax, jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import prkmk_jax as pk
    from helpers import INERTIA, initial_state, rigid_body_field

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

    for run in (scan_run, diffrax_run):
        batched = jax.jit(jax.vmap(run))
        plain = batched(y0s, inertias)
        sharded = batched(pk.shard_batch(y0s), pk.shard_batch(inertias))
        out = sharded.fiber
        assert len(out.sharding.device_set) == 4, out.sharding
        assert sorted(s.data.shape[0] for s in out.addressable_shards) == [2, 2, 2, 2]
        for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(sharded)):
            assert np.abs(np.asarray(a) - np.asarray(b)).max() <= 1e-14
    print("sharded ok")
    """
)


def test_sharded_batch_equals_unsharded_on_four_devices():
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "sharded ok" in out.stdout


def test_shard_batch_checks_the_batch_axis():
    with pytest.raises(ValueError, match="leading batch axis"):
        pk.shard_batch(jnp.float64(1.0))
    sharded = pk.shard_batch({"a": jnp.ones((3, 2))})  # one device here: any size divides
    assert sharded["a"].shape == (3, 2)
