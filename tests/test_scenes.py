"""The rigid-body scene's embedding field, checked against the group flow."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from prkmk_jax.scenes import rigid_body as rb


def _state(seed):
    q = rb.random_rotation(seed)
    pi = np.random.default_rng(seed).normal(size=3)
    return jnp.asarray(q), jnp.asarray(pi)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_embedding_field_is_the_derivative_of_the_group_flow(seed):
    # Central difference of one order-4 PRKMK step on T*SO(3), forward and
    # backward: an independent route to (Q', Π') at t = 0.
    q, pi = _state(seed)
    inertia = jnp.asarray(rb.PAPER_INERTIA)
    method = pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.lobatto_iiia_iiib4, form="body")
    field = rb.unreduced_rigid_body(pk.Cotangent(pk.SO3))
    y0 = pk.BundleElement(pk.SO3(q), pi)
    h = 1e-4  # truncation error ~h²|y‴| ≈ 1e-7
    fwd, _, _ = method.step(field, 0.0, y0, h, inertia)
    bwd, _, _ = method.step(field, 0.0, y0, -h, inertia)
    dq = (fwd.base.matrix - bwd.base.matrix) / (2 * h)
    dpi = (fwd.fiber - bwd.fiber) / (2 * h)
    z = rb.embedding_field(0.0, jnp.concatenate([q.ravel(), pi]), inertia)
    np.testing.assert_allclose(z[:9].reshape(3, 3), dq, atol=1e-6)
    np.testing.assert_allclose(z[9:], dpi, atol=1e-6)


def test_embedding_field_with_a_tensor_is_the_diagonal_body_in_principal_axes():
    # I = R D Rᵀ: in the body frame turned by R (Q ↦ QR, Π ↦ RᵀΠ) the body has
    # the diagonal inertia D, so the two fields are related by the same turn.
    q, pi = _state(3)
    r = jnp.asarray(rb.random_rotation(4))
    d = jnp.array([0.8, 0.6, 0.3])
    tensor = rb.embedding_field(0.0, jnp.concatenate([q.ravel(), pi]), r @ jnp.diag(d) @ r.T)
    diagonal = rb.embedding_field(0.0, jnp.concatenate([(q @ r).ravel(), r.T @ pi]), d)
    np.testing.assert_allclose(tensor[:9].reshape(3, 3) @ r, diagonal[:9].reshape(3, 3), atol=1e-14)
    np.testing.assert_allclose(r.T @ tensor[9:], diagonal[9:], atol=1e-14)


def test_embedding_field_refuses_bad_shapes():
    z = jnp.zeros(12)
    with pytest.raises(ValueError, match="inertia must have shape"):
        rb.embedding_field(0.0, z, jnp.ones(4))
    with pytest.raises(ValueError, match="embedded state"):
        rb.embedding_field(0.0, jnp.zeros(9), jnp.ones(3))


def test_embedding_field_works_under_jit_and_vmap():
    zs = jnp.stack([jnp.concatenate([q.ravel(), p]) for q, p in map(_state, range(4))])
    out = jax.jit(jax.vmap(rb.embedding_field, in_axes=(None, 0, None)))(0.0, zs, jnp.asarray(rb.PAPER_INERTIA))
    assert out.shape == (4, 12) and bool(jnp.all(jnp.isfinite(out)))
