"""The rigid-body scenes: the embedding field against the group flow, and the
scene objects of the free rigid body on every bundle it lives on, against
the closed-form (elliptic) body momentum, a full inertia tensor against the
principal problem it rotates into, and misuse."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import assert_embedding_field_is
from prkmk_jax.scenes import PAPER_INERTIA, PAPER_MOMENTUM, FreeRigidBody, elliptic_momentum, random_rotation
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
    fwd = method.step(field, 0.0, y0, h, inertia).y
    bwd = method.step(field, 0.0, y0, -h, inertia).y
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


BUNDLES = {
    "cotangent": pk.Cotangent(pk.SO3),
    "semidirect-left": pk.Semidirect(pk.SO3, "left"),
    "direct": pk.DirectProduct(pk.SO3),
}
Y0 = pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(1))), jnp.asarray(PAPER_MOMENTUM))
INERTIA = jnp.asarray(PAPER_INERTIA)


@pytest.mark.parametrize("name", BUNDLES, ids=list(BUNDLES))
def test_free_body_follows_the_elliptic_solution_at_second_order(name):
    body = FreeRigidBody(BUNDLES[name])
    method = body.method(pk.stormer_verlet)
    # One program (1000 steps, a state every 100) for both steps: h = 0.01
    # saves at t = 0, 1, …, 10, h = 0.02 at t = 0, 2, …, 20; compared at t = 0, 2, …, 10.
    errors, even_times = [], np.arange(0.0, 10.5, 2.0)
    exact = elliptic_momentum(PAPER_MOMENTUM, PAPER_INERTIA, even_times)
    for h, at_even_times in ((0.02, slice(0, 6)), (0.01, slice(0, 11, 2))):
        ys = pk.integrate(method, body, Y0, 0.0, h, 1000, INERTIA, save_every=100).ys
        errors.append(np.abs(np.asarray(ys.fiber)[at_even_times] - exact).max())
    assert errors[1] < 2e-3 and 3.6 < errors[0] / errors[1] < 4.4, errors
    invariants = body.invariants(ys, INERTIA)
    kept = ("energy", "momentum norm", "orthogonality") + (() if name == "direct" else ("spatial momentum",))
    for key in kept:
        assert float(jnp.max(jnp.abs(invariants[key] - invariants[key][0]))) < 1e-12, key


def test_a_full_inertia_tensor_is_the_principal_body_rotated():
    """Body with tensor I = R diag(I_p) Rᵀ from (Q, Π) is the principal body
    from (QR, RᵀΠ): its trajectory maps onto that one."""
    r = jnp.asarray(random_rotation(3))
    tensor = r @ jnp.diag(INERTIA) @ r.T
    body = FreeRigidBody()
    method = body.method(pk.lobatto_iiia_iiib4)
    full = pk.integrate(method, body, Y0, 0.0, 0.05, 40, tensor).ys
    principal_y0 = pk.BundleElement(pk.SO3(Y0.base.matrix @ r), r.T @ Y0.fiber)
    principal = pk.integrate(method, body, principal_y0, 0.0, 0.05, 40, INERTIA).ys
    np.testing.assert_allclose(full.base.matrix @ r, principal.base.matrix, atol=1e-12)
    np.testing.assert_allclose(jnp.einsum("ji,tj->ti", r, full.fiber), principal.fiber, atol=1e-12)


@pytest.mark.parametrize("bundle", [pk.Cotangent(pk.SO3), pk.DirectProduct(pk.SO3)], ids=["cotangent", "direct product"])
def test_the_embedding_field_is_the_generator_pushed_forward(bundle):
    assert_embedding_field_is(rb.embedding_field, FreeRigidBody(bundle), 0.0, Y0, INERTIA)


def test_misuse_is_refused():
    with pytest.raises(TypeError, match="FreeRigidBody lives on"):
        FreeRigidBody(pk.Cartesian(pk.SO3))
    with pytest.raises(TypeError, match="FreeRigidBody lives on"):
        FreeRigidBody(pk.Semidirect(pk.SO3, "right"))
    with pytest.raises(ValueError, match="three distinct"):
        elliptic_momentum(PAPER_MOMENTUM, np.array([1.0, 1.0, 2.0]), np.zeros(2))


SO4_MASSES = jnp.array([0.9, 0.7, 0.5, 0.3])


def _symmetric_cases():
    from prkmk_jax.scenes import SymmetricRigidBody, symmetric_initial_state

    a = np.random.default_rng(2004).normal(size=(4, 4))
    return {
        "SO3": (SymmetricRigidBody(), symmetric_initial_state(random_rotation(2), PAPER_MOMENTUM), INERTIA),
        "SO4": (
            SymmetricRigidBody(pk.Cartesian(pk.SOn)),
            symmetric_initial_state(random_rotation(1, 4), 0.2 * (a - a.T)),
            SO4_MASSES,
        ),
    }


@pytest.mark.parametrize("n", ["SO3", "SO4"])
def test_symmetric_body_field_and_invariants(n):
    body, y0, args = _symmetric_cases()[n]

    def written_out(t, z, inertia):  # Q' = QΩ, P' = PΩ, Ω = I⁻¹(QᵀP − PᵀQ)
        size = int(round((z.shape[-1] // 2) ** 0.5))
        q, p = z[: size * size].reshape(size, size), z[size * size :].reshape(size, size)
        m = q.T @ p - p.T @ q
        omega = pk.hat(rb.angular_velocity(pk.vee(m), inertia, False)) if size == 3 else rb.angular_velocity(m, inertia, True)
        return jnp.concatenate([(q @ omega).ravel(), (p @ omega).ravel()])

    assert_embedding_field_is(written_out, body, 0.0, y0, args)
    ys = pk.integrate(body.method(pk.stormer_verlet), body, y0, 0.0, 0.1, 200, args, save_every=10).ys
    invariants = body.invariants(ys, args)
    for key in ("momentum norm", "spatial momentum", "orthogonality"):
        assert float(jnp.max(jnp.abs(invariants[key] - invariants[key][0]))) < 1e-13, key
    # The energy is not kept: on SO(3)×SO(3) it drifts (the paper's Fig 5.2,
    # tests/test_reproduce.py).


def test_symmetric_body_refuses_other_bundles():
    from prkmk_jax.scenes import SymmetricRigidBody

    with pytest.raises(TypeError, match="SymmetricRigidBody lives on"):
        SymmetricRigidBody(pk.Cotangent(pk.SO3))


@pytest.mark.parametrize("bundle", [pk.Cotangent(pk.SO3), pk.DirectProduct(pk.SO3)], ids=["cotangent", "direct product"])
def test_three_so3_momenta_are_three_vectors_not_a_matrix(bundle):
    """A batch of exactly three SO(3) states: the fields and the symmetric
    body's invariants treat the momenta (3, 3) as three vectors, as they do
    one at a time."""
    inertia = jnp.asarray(PAPER_INERTIA)
    qs = jnp.asarray(np.stack([random_rotation(k) for k in range(3)]))
    momenta = jnp.asarray(PAPER_MOMENTUM) * jnp.array([[1.0], [-0.5], [2.0]])
    field = rb.unreduced_rigid_body(bundle)
    together = field(0.0, pk.BundleElement(pk.SO3(qs), momenta), inertia)
    for k in range(3):
        alone = field(0.0, pk.BundleElement(pk.SO3(qs[k]), momenta[k]), inertia)
        np.testing.assert_allclose(together[0][k], momenta[k] / inertia, rtol=1e-15)
        np.testing.assert_allclose(together[1][k], alone[1], rtol=1e-14, atol=1e-15)

    symmetric = rb.SymmetricRigidBody()
    states = pk.BundleElement(pk.SO3(qs), pk.SO3(jnp.asarray(np.stack([random_rotation(10 + k) for k in range(3)]))))
    both = symmetric.invariants(states, inertia)["energy"]
    generator = symmetric(0.0, states, inertia)
    for k in range(3):
        state = jax.tree.map(lambda a: a[k], states)
        np.testing.assert_allclose(both[k], symmetric.invariants(state, inertia)["energy"], rtol=1e-14)
        np.testing.assert_allclose(generator[0][k], symmetric(0.0, state, inertia)[0], rtol=1e-14, atol=1e-15)


def test_reference_solution_follows_the_closed_form():
    """The scene's reference (DOP853 on the embedding) against the free body's
    elliptic-function solution, and the attitude kept on the group along it."""
    q0, pi0 = _state(3)
    ts = np.linspace(0.0, 10.0, 11)
    rows = FreeRigidBody().reference_solution(pk.BundleElement(pk.SO3(q0), pi0), ts, jnp.asarray(PAPER_INERTIA))
    assert rows.shape == (11, 12)
    np.testing.assert_allclose(rows[:, 9:], elliptic_momentum(np.asarray(pi0), PAPER_INERTIA, ts), rtol=0, atol=1e-11)
    q = rows[:, :9].reshape(-1, 3, 3)
    np.testing.assert_allclose(np.swapaxes(q, -1, -2) @ q, np.broadcast_to(np.eye(3), q.shape), atol=1e-11)


def test_reference_solution_refuses_a_batch_and_unordered_times():
    q0, pi0 = _state(0)
    body, inertia = FreeRigidBody(), jnp.asarray(PAPER_INERTIA)
    batch = pk.BundleElement(pk.SO3(jnp.stack([q0, q0])), jnp.stack([pi0, pi0]))
    with pytest.raises(ValueError, match="one trajectory"):
        body.reference_solution(batch, [1.0], inertia)
    with pytest.raises(ValueError, match="increasing times"):
        body.reference_solution(pk.BundleElement(pk.SO3(q0), pi0), [2.0, 1.0], inertia)
