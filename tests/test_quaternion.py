"""Unit quaternions: the group is SO(3) through the rotation matrix (every
map checked against `SO3`'s on sampled vectors, near-identity ones
included), the changes round relative to the change, the double cover is
handled, and every family of method on the free body and the heavy top
computes on quaternions what it computes on rotation matrices, the
splittings included."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given

import prkmk_jax as pk
from helpers import INERTIA, TOP_ARGS, algebra_vectors, central_differences
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, random_rotation
from prkmk_jax.scenes.base import rotation_matrix

Q, S = pk.UnitQuaternion, pk.SO3
IDENTITY = jnp.asarray([1.0, 0.0, 0.0, 0.0])


def _close(a, b, tol=1e-14):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=tol)


@given(a=algebra_vectors(max_norm=3.1), b=algebra_vectors(max_norm=3.1), c=algebra_vectors(max_norm=3.1))
def test_every_map_is_so3_through_the_matrix(a, b, c):
    u, v, x = jnp.asarray(a), jnp.asarray(b), jnp.asarray(c)
    p, q = Q.exp(u), Q.exp(v)
    _close(p.as_matrix(), S.exp(u).matrix)
    _close(Q.cayley(u).as_matrix(), S.cayley(u).matrix)
    _close((p @ q).as_matrix(), S.exp(u).matrix @ S.exp(v).matrix)
    _close(p.inverse().as_matrix(), S.exp(u).matrix.T)
    _close(p.adjoint(x), S.exp(u).matrix @ x)
    _close(p.log(), S.exp(u).log(), 1e-12)
    _close(Q.cayley(u).cayley_inverse(), u, 1e-12)
    _close(Q.from_matrix(S.exp(u).matrix).as_matrix(), S.exp(u).matrix)
    # The group laws, on the quaternions themselves.
    r = Q.exp(x)
    _close(((p @ q) @ r).wxyz, (p @ (q @ r)).wxyz)
    _close((p @ p.inverse()).wxyz, IDENTITY)
    _close((p.identity_like() @ p).wxyz, p.wxyz)
    # The actions on the algebra are Ad of the quaternions the maps give.
    _close(Q.exp_adjoint(u, x), p.adjoint(x))
    _close(Q.cayley_adjoint(u, x), Q.cayley(u).adjoint(x))


def _right_trivialized(chart, u, v):
    """2·vec(d/dt chart(u + tv) · chart(u)⁻¹): the differential the methods
    read as dexp_u v (or dcay_u v), from autodiff of the quaternion map."""
    q, dq = jax.jvp(lambda w: chart(w).wxyz, (u,), (v,))
    return 2 * (Q(dq) @ Q(q).inverse()).wxyz[1:]


@given(a=algebra_vectors(max_norm=3.1), b=algebra_vectors(max_norm=3.1))
def test_the_differentials_are_those_of_the_quaternion_maps(a, b):
    """SO(3)'s dexp and dcay (which the group lends) are the differentials of
    the quaternion exp and Cayley maps themselves, and dexp⁻¹, dcay⁻¹ invert
    them: the lifted Cayley map is the one whose dcay⁻¹ the methods use."""
    u, v = jnp.asarray(a), jnp.asarray(b)
    _close(_right_trivialized(Q.exp, u, v), Q.dexp(u, v), 1e-12)
    _close(_right_trivialized(Q.cayley, u, v), Q.dcayley(u, v), 1e-12)
    _close(Q.dexp_inv(u, Q.dexp(u, v)), v, 1e-11)
    _close(Q.dcayley_inv(u, Q.dcayley(u, v)), v, 1e-11)


@given(a=algebra_vectors(max_norm=3.1), b=algebra_vectors(max_norm=3.1))
def test_changes_round_relative_to_the_change(a, b):
    """exp(u) − 1 and cay(u) − 1 without the identity added in: where u is
    small (and the difference of the elements has lost its digits) each
    component to 1e-13 relative against the maps' series to θ⁴, whose next
    terms are below 1e-16 relative there; elsewhere against the difference.
    The product change is q·(g − 1)."""
    u = jnp.asarray(a)
    t2 = float(np.sum(np.square(a)))
    series = {  # (cos(θ/2) − 1, sin(θ/2)/θ · u) and (2/r − 1, u/r), r = √(4 + θ²)
        "exp": np.concatenate([[-t2 / 8 + t2 * t2 / 384], a / 2 * (1 - t2 / 24)]),
        "cayley": np.concatenate([[-t2 / 8 + 3 * t2 * t2 / 128], a / 2 * (1 - t2 / 8)]),
    }
    for name, change, element in (("exp", Q.exp_change(u), Q.exp(u)), ("cayley", Q.cayley_change(u), Q.cayley(u))):
        if t2 < 1e-8:
            np.testing.assert_allclose(np.asarray(change), series[name], rtol=1e-13, atol=0)
        else:
            _close(change, element.wxyz - IDENTITY, 1e-15)
    g = Q.exp(jnp.asarray(b))
    for side, product in (("right", g @ Q.exp(u)), ("left", Q.exp(u) @ g)):
        _close(g.product_change(Q.exp_change(u), side).wxyz, product.wxyz - g.wxyz)


@pytest.mark.parametrize("fn", ["exp", "log", "cayley", "cayley_inverse", "as_matrix"])
def test_gradients_are_finite_and_right_at_the_identity(fn):
    """At u = 0 (q = 1) and nearby, each map's derivative equals central
    differences and is finite (the double-`where` branches)."""
    maps = {
        "exp": lambda u: Q.exp(u).wxyz,
        "log": lambda u: Q(jnp.concatenate([jnp.sqrt(1 - jnp.sum(u * u, keepdims=True)), u])).log(),
        "cayley": lambda u: Q.cayley(u).wxyz,
        "cayley_inverse": lambda u: Q(jnp.concatenate([jnp.sqrt(1 - jnp.sum(u * u, keepdims=True)), u])).cayley_inverse(),
        "as_matrix": lambda u: Q.exp(u).as_matrix(),
    }
    f = maps[fn]
    for point in (jnp.zeros(3), jnp.asarray([1e-6, -2e-6, 3e-7]), jnp.asarray([0.3, -0.2, 0.1])):
        jacobian = jax.jacfwd(f)(point)
        assert np.all(np.isfinite(jacobian))
        _close(jacobian, central_differences(f, point, 1e-5), 1e-9)


def test_the_double_cover():
    """q and −q: the same rotation, the same log and Cayley coordinates; log
    picks the representative with w ≥ 0, an angle in [0, π]."""
    u = jnp.asarray([[0.3, -1.2, 2.9], [0.0, 0.0, 0.0], [1e-9, 0.0, 0.0]])
    q = Q.exp(u)
    minus = Q(-q.wxyz)
    _close(minus.as_matrix(), q.as_matrix())
    _close(minus.log(), q.log())
    _close(minus.cayley_inverse(), q.cayley_inverse(), 1e-13)
    _close(Q.exp(jnp.asarray([0.0, 0.0, 3.5])).log(), [0.0, 0.0, 3.5 - 2 * np.pi], 1e-14)  # turned past π: the shorter way round


def test_renormalized_corrects_only_a_quaternion_that_drifted():
    eps = float(jnp.finfo(jnp.float32).eps)
    q = np.asarray(Q.exp(jnp.asarray([0.3, -1.2, 0.7])).wxyz)
    batch = jnp.asarray(np.stack([q, q * (1 + 1000 * eps)]), jnp.float32)
    after = Q(batch).renormalized().wxyz
    np.testing.assert_array_equal(after[0], batch[0])
    assert abs(float(jnp.sum(after[1] ** 2)) - 1) < 10 * eps
    # The derivative is the normalization's either way.
    direction = jnp.asarray(np.random.default_rng(0).normal(size=(2, 4)), jnp.float32)
    _, derivative = jax.jvp(lambda x: Q(x).renormalized().wxyz, (batch,), (direction,))
    _, expected = jax.jvp(lambda x: x * (1.5 - 0.5 * jnp.sum(x * x, -1, keepdims=True)), (batch,), (direction,))
    _close(derivative, expected, 1e-6)


# --- methods on quaternions compute what they compute on matrices ---------------------------
FREE, TOP = FreeRigidBody, HeavyTop
# One case for each family (implicit PRKMK, explicit RKMK, composition,
# symmetrised, adjoint, exact flow), each bundle and each chart at least
# once; the families reach the group only through the bundle.
CASES = {  # name: (scene class, bundle, method of the scene, dt, steps)
    "free body, Lobatto 4, G×g, Cayley": (FREE, pk.DirectProduct, lambda s: s.method(pk.lobatto_iiia_iiib4, pk.Cayley()), 0.1, 40),
    "free body, RKMK 8, G⋉g left, Cayley": (
        FREE,
        lambda g: pk.Semidirect(g, "left"),
        lambda s: s.method(pk.dormand_prince_8, pk.Cayley()),
        0.2,
        20,
    ),
    "free body, SV ∘ Kahan–Li 6": (
        FREE,
        pk.Cotangent,
        lambda s: pk.Composition(s.method(pk.stormer_verlet), pk.kahan_li_6, assume_symmetric_base=True),
        0.2,
        20,
    ),
    "free body, exact flow": (FREE, pk.Cotangent, lambda s: s.exact_flow(), 0.5, 20),
    "heavy top, symmetrised SE, T*G, Cayley": (
        TOP,
        pk.Cotangent,
        lambda s: pk.Symmetrized(s.method(pk.symplectic_euler, pk.Cayley())),
        0.05,
        40,
    ),
    "heavy top, adjoint of Lobatto 4, T*G": (TOP, pk.Cotangent, lambda s: pk.Adjoint(s.method(pk.lobatto_iiia_iiib4)), 0.05, 40),
    # The splittings: the axes ordered by an even permutation here (a
    # right-handed frame), by an odd one for TOP_ARGS and INERTIA.
    "free body, Kahan–Li 6 splitting, Cayley": (FREE, pk.Cotangent, lambda s: s.splitting(pk.kahan_li_6, pk.Cayley()), 0.2, 20),
    "heavy top, Strang splitting with the exact free part, G×g": (
        TOP,
        pk.DirectProduct,
        lambda s: s.splitting(free_part="exact"),
        0.05,
        40,
    ),
    "heavy top, Strang splitting, T*G": (TOP, pk.Cotangent, lambda s: s.splitting(), 0.05, 40),
}
ARGS = {"free body, Kahan–Li 6 splitting, Cayley": jnp.asarray([5 / 8, 7 / 8, 1 / 4])}


@pytest.mark.parametrize("name", CASES)
def test_a_run_on_quaternions_is_the_run_on_matrices(name):
    """The same attitudes (as matrices) and momenta to ≤ 1e-13; the
    quaternion moves continuously (never to −q) and stays of norm 1."""
    scene_class, bundle, make_method, dt, steps = CASES[name]
    args = ARGS.get(name, jnp.asarray(INERTIA) if scene_class is FREE else TOP_ARGS)
    rotation = jnp.asarray(random_rotation(4))
    runs = {}
    for group, base in ((S, S(rotation)), (Q, Q.from_matrix(rotation))):
        scene = scene_class(bundle(group))
        y0 = pk.BundleElement(base, jnp.asarray([0.3, -0.4, 1.5]))
        runs[group] = pk.integrate(make_method(scene), scene, y0, 0.0, dt, steps, args).ys
    on_matrices, on_quaternions = runs[S], runs[Q]
    _close(on_quaternions.base.as_matrix(), on_matrices.base.matrix, 1e-13)
    _close(on_quaternions.fiber, on_matrices.fiber, 1e-13)
    q = np.asarray(on_quaternions.base.wxyz)
    assert np.all(np.sum(q[1:] * q[:-1], axis=-1) > 0)
    _close(np.sum(q * q, axis=-1), 1.0, 1e-14)


def test_dense_output_on_quaternions_is_the_matrix_runs():
    """diffeqsolve's on-group interpolation between steps: the same attitudes
    as on matrices, and the quaternions continuous (never −q)."""
    rotation = jnp.asarray(random_rotation(6))
    ts = jnp.linspace(0.0, 3.0, 41)  # four values inside each step of 0.3
    runs = {}
    for group, base in ((S, S(rotation)), (Q, Q.from_matrix(rotation))):
        scene = FreeRigidBody(pk.Cotangent(group))
        y0 = pk.BundleElement(base, jnp.asarray([0.3, -0.4, 1.5]))
        solver = pk.PRKMKSolver(scene.method(pk.lobatto_iiia_iiib4))
        args = jnp.asarray(INERTIA)
        runs[group] = diffrax.diffeqsolve(pk.PRKMKTerm(scene), solver, 0.0, 3.0, 0.3, y0, args, saveat=diffrax.SaveAt(ts=ts)).ys
    _close(runs[Q].base.as_matrix(), runs[S].base.matrix, 1e-13)
    q = np.asarray(runs[Q].base.wxyz)
    assert np.all(np.sum(q[1:] * q[:-1], axis=-1) > 0.9)


def test_a_gradient_through_a_quaternion_run_is_the_matrix_runs():
    """d/dΠ₀ and d/dI of a loss on the final attitude and momentum: the
    quaternion run's, rebuilt backwards (`ReversibleGradient`), equals the
    matrix run's from stored steps."""
    rotation = jnp.asarray(random_rotation(5))

    def loss(group, gradient):
        scene = FreeRigidBody(pk.Cotangent(group))
        base = S(rotation) if group is S else Q.from_matrix(rotation)

        def of(momentum, inertia):
            y0 = pk.BundleElement(base, momentum)
            y = pk.integrate(scene.method(pk.stormer_verlet), scene, y0, 0.0, 0.1, 30, inertia, gradient=gradient)
            final = jax.tree.map(lambda a: a[-1], y.ys)
            return jnp.sum(rotation_matrix(final.base)[:, 0] * jnp.asarray([0.2, -0.5, 0.9])) + jnp.sum(final.fiber**2)

        return jax.grad(of, argnums=(0, 1))(jnp.asarray([0.3, -0.4, 1.5]), jnp.asarray(INERTIA))

    for a, b in zip(loss(Q, pk.ReversibleGradient()), loss(S, pk.StoredSteps())):
        _close(a, b, 1e-12)
