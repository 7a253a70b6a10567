"""The library accepts its own output: random valid states, run for 10⁵
steps in float32 and float64, end in states that pass the library's checks
(float32 states stay orthogonal to a few ulps: the step renormalises them);
`project()` restores drifted rotations exactly."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import prkmk_jax as pk
from helpers import INERTIA, algebra_vectors, rigid_body_field
from prkmk_jax.diagnostics import orthogonality_defect

COTANGENT = pk.Cotangent(pk.SO3)
FIELD = rigid_body_field(COTANGENT, "body")
NUM_STEPS, DT = 100_000, 0.01
COORDINATES = {"exp": pk.Exp(), "cayley": pk.Cayley()}


@functools.cache
def _long_run(coordinates: str, dtype):
    method = pk.PRKMK(COTANGENT, COORDINATES[coordinates], pk.stormer_verlet, form="body")

    @jax.jit
    def run(y0, inertia):
        traj = pk.integrate(method, FIELD, y0, 0.0, DT, NUM_STEPS, inertia, save_every=NUM_STEPS)
        return jax.tree.map(lambda a: a[-1], traj.ys)

    return run


@settings(max_examples=12)
@given(
    rotation=algebra_vectors(max_norm=3.1),
    momentum=algebra_vectors(max_norm=2.0),
    coordinates=st.sampled_from(sorted(COORDINATES)),
    dtype=st.sampled_from([jnp.float32, jnp.float64]),
)
def test_long_runs_end_in_states_the_library_accepts(rotation, momentum, coordinates, dtype):
    """10⁵ steps of h = 0.01 (h|Ω| up to 0.08) from a random state: the final
    state passes `Cotangent.check`, so a restart from it is accepted."""
    y0 = pk.BundleElement(pk.SO3.exp(jnp.asarray(rotation, dtype)), jnp.asarray(momentum, dtype))
    y0 = jax.block_until_ready(COTANGENT.check(y0))
    y_end = _long_run(coordinates, dtype)(y0, jnp.asarray(INERTIA, dtype))
    assert y_end.fiber.dtype == dtype
    jax.block_until_ready(COTANGENT.check(y_end))  # raises if the library refused it
    # float32 states are renormalised once they drift: QᵀQ = I to a few ulps. In
    # float64 the drift is rounding, ~1e-16 a step at most.
    bound = 20 * float(jnp.finfo(dtype).eps) if dtype == jnp.float32 else 1e-10
    assert float(orthogonality_defect(y_end.base.matrix)) < bound
    # |Π| is a Casimir of the free body: kept to rounding, which in float32 is
    # systematic too (3.3e-4 after 10⁵ steps of a spin about an axis).
    np.testing.assert_allclose(np.linalg.norm(y_end.fiber), np.linalg.norm(momentum), rtol=1e-3 if dtype == jnp.float32 else 1e-11)


@pytest.mark.parametrize("group", [pk.SO3, pk.SOn])
def test_project_returns_the_nearest_rotation(group):
    """Independent characterisation: Q is a rotation and QᵀM is symmetric
    positive definite (Q is the polar factor of M, the Frobenius-nearest
    orthogonal matrix); a rotation scaled by 1 + δ projects back onto itself."""
    rng = np.random.default_rng(3)
    rotation = np.asarray(pk.SO3.exp(jnp.asarray(rng.normal(size=3))).matrix)
    np.testing.assert_allclose(group(jnp.asarray(rotation * (1 + 3e-3))).project().matrix, rotation, atol=1e-15)
    matrices = rng.normal(size=(5, 3, 3))
    matrices *= np.sign(np.linalg.det(matrices))[:, None, None]  # det > 0: the polar factor is a rotation
    q = np.asarray(group(jnp.asarray(matrices)).project().matrix)
    np.testing.assert_allclose(np.swapaxes(q, -1, -2) @ q, np.broadcast_to(np.eye(3), q.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(q), 1.0, atol=1e-14)
    sym = np.swapaxes(q, -1, -2) @ matrices
    np.testing.assert_allclose(sym, np.swapaxes(sym, -1, -2), atol=1e-13)
    assert np.all(np.linalg.eigvalsh(sym) > 0)


def test_a_drifted_state_is_refused_with_a_pointer_to_project_and_accepted_after_it():
    rotation = np.asarray(pk.SO3.exp(jnp.array([0.3, -1.0, 2.0])).matrix)
    drifted = pk.BundleElement(pk.SO3(jnp.asarray(rotation * (1 + 2e-3))), jnp.array([0.25, 0.625, 0.875]))
    with pytest.raises(Exception, match=r"not orthogonal.*project\(\)"):
        jax.block_until_ready(COTANGENT.check(drifted))
    restored = COTANGENT.project(drifted)
    np.testing.assert_allclose(restored.base.matrix, rotation, atol=1e-15)
    np.testing.assert_array_equal(restored.fiber, drifted.fiber)
    jax.block_until_ready(pk.integrate(pk.PRKMK(COTANGENT), FIELD, restored, 0.0, DT, 3, jnp.asarray(INERTIA)).ys)
