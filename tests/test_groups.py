"""Group axioms, exp/log, brackets and gradients at the identity, for the base
groups and every bundle group, on hypothesis-sampled elements (near-identity
ones included)."""

import math
from fractions import Fraction
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from jax.scipy.linalg import expm

import prkmk_jax as pk
from helpers import algebra_vectors, assert_closed_forms_are_the_defaults, assert_jacobians_at_the_identity, bjorck_step, skew
from prkmk_jax.groups import AbstractRotationGroup

TOL = 1e-12


def _close(a, b, tol=TOL):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=tol)


def _so4(vec6):
    return jnp.asarray(skew(4, vec6))


BASES = {
    "SO3": (pk.SO3, lambda v: jnp.asarray(v[:3])),
    "SO4": (pk.SOn, lambda v: _so4(v[:6] / 2)),
    "R3": (pk.VectorSpace, lambda v: jnp.asarray(v[:3])),
    "SE3": (pk.SE3, jnp.asarray),
    "SO3xR3": (pk.SO3xR3, jnp.asarray),
    "SO3-pair": (pk.SO3Power, lambda v: jnp.asarray(v).reshape(2, 3)),
}

vectors6 = algebra_vectors(dim=6, max_norm=3.0)


@pytest.mark.parametrize("name", BASES)
@given(a=vectors6, b=vectors6, c=vectors6)
def test_base_group_axioms(name, a, b, c):
    group, alg = BASES[name]
    x, y, z = (group.exp(alg(v)) for v in (a, b, c))
    _close((x @ y) @ z, x @ (y @ z))
    _close(x @ x.identity_like(), x)
    _close(x.identity_like() @ x, x)
    _close(x @ x.inverse(), x.identity_like())
    _close(x.inverse() @ x, x.identity_like())


@given(u=algebra_vectors(dim=3, max_norm=3.1))
def test_so3_exp_matches_expm_and_log_inverts(u):
    u = jnp.asarray(u)
    r = pk.SO3.exp(u)
    _close(r.matrix, expm(pk.hat(u)))
    _close(r.log(), u)
    _close(pk.SO3.cayley(u).matrix, jnp.linalg.solve(jnp.eye(3) - pk.hat(u) / 2, jnp.eye(3) + pk.hat(u) / 2))


@given(v=vectors6)
def test_son_exp_matches_expm_and_log_inverts(v):
    u = _so4(v / 2)  # ‖u‖₂ < π keeps log principal
    r = pk.SOn.exp(u)
    _close(r.matrix, expm(u))
    _close(r.log(), u, tol=1e-10)


def test_so3_log_near_pi():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    for angle in (np.pi - 1e-6, np.pi - 1e-3, 3.0):
        np.testing.assert_allclose(pk.SO3.exp(jnp.asarray(axis * angle)).log(), axis * angle, atol=1e-9)


def test_batched_elements():
    u = jnp.asarray(np.random.default_rng(0).normal(size=(4, 5, 3)))
    r = pk.SO3.exp(u)
    assert r.matrix.shape == (4, 5, 3, 3)
    _close(r.log(), u)
    product = r @ pk.SO3.exp(u[1, 1])  # batch (4, 5) times an unbatched element
    _close(product.matrix[2, 3], (pk.SO3.exp(u[2, 3]) @ pk.SO3.exp(u[1, 1])).matrix)
    m = pk.SOn.exp(jax.vmap(jax.vmap(pk.hat))(u))
    assert m.matrix.shape == (4, 5, 3, 3)
    _close(m.matrix, r.matrix)


@pytest.mark.parametrize("fn", ["exp", "log", "dexp", "dexp_inv", "cayley", "dcayley", "dcayley_inv"])
def test_so3_gradients_finite_and_correct_at_identity(fn):
    v = jnp.array([0.3, -0.2, 0.5])
    funcs = {
        "exp": lambda u: pk.SO3.exp(u).matrix,
        "log": lambda u: pk.SO3.exp(u).log(),
        "dexp": lambda u: pk.SO3.dexp(u, v),
        "dexp_inv": lambda u: pk.SO3.dexp_inv(u, v),
        "cayley": lambda u: pk.SO3.cayley(u).matrix,
        "dcayley": lambda u: pk.SO3.dcayley(u, v),
        "dcayley_inv": lambda u: pk.SO3.dcayley_inv(u, v),
    }
    assert_jacobians_at_the_identity(funcs[fn], 3)


# --- bundle groups ----------------------------------------------------------------------
EXP = pk.Exp()
"""The bundle's exponential map, as the coordinate map lifts it."""
BUNDLES = {
    "direct": pk.DirectProduct(pk.SO3),
    "semidirect-left": pk.Semidirect(pk.SO3, "left"),
    "semidirect-right": pk.Semidirect(pk.SO3, "right"),
    "cotangent": pk.Cotangent(pk.SO3),
    "cartesian": pk.Cartesian(pk.SO3),
    "semidirect-left-SO4": pk.Semidirect(pk.SOn, "left"),
    "cartesian-SO4": pk.Cartesian(pk.SOn),
    "direct-SO4": pk.DirectProduct(pk.SOn),
    "semidirect-right-R3": pk.Semidirect(pk.VectorSpace, "right"),
    "semidirect-left-SE3": pk.Semidirect(pk.SE3, "left"),
    "cotangent-SO3xR3": pk.Cotangent(pk.SO3xR3),
    "cotangent-SO3-pair": pk.Cotangent(pk.SO3Power),
}


def bundle_algebra(bundle, a, b):
    if bundle.base is pk.SOn:
        return _so4(a / 2), _so4(b / 2)
    if bundle.base in (pk.SE3, pk.SO3xR3):
        return jnp.asarray(a), jnp.asarray(b)
    if bundle.base is pk.SO3Power:
        return jnp.asarray(a).reshape(2, 3), jnp.asarray(b).reshape(2, 3)
    return jnp.asarray(a[:3]), jnp.asarray(b[:3])


def tangent_to_algebra(bundle, tangent):
    """The algebra pair of a tangent vector at the identity of the bundle."""

    def base_part(t):
        if isinstance(t, (pk.SO3, pk.SO3Power)):
            return pk.vee(t.matrix)
        if isinstance(t, pk.SOn):
            return t.matrix
        if isinstance(t, (pk.SE3, pk.SO3xR3)):
            return jnp.concatenate([pk.vee(t.rotation), t.translation], axis=-1)
        return t.value

    second = base_part(tangent.fiber) if bundle.fiber_is_group else tangent.fiber
    return base_part(tangent.base), second


def element(bundle, a, b):
    return bundle.map(EXP, bundle_algebra(bundle, a, b))


@pytest.mark.parametrize("name", BUNDLES)
@given(a=vectors6, b=vectors6, c=vectors6, d=vectors6, e=vectors6, f=vectors6)
def test_bundle_group_axioms(name, a, b, c, d, e, f):
    bundle = BUNDLES[name]
    x, y, z = element(bundle, a, b), element(bundle, c, d), element(bundle, e, f)
    mul = bundle.multiply
    _close(mul(mul(x, y), z), mul(x, mul(y, z)))
    one = bundle.identity_like(x)
    _close(mul(x, one), x)
    _close(mul(one, x), x)
    _close(mul(x, bundle.inverse(x)), one)
    _close(mul(bundle.inverse(x), x), one)


@pytest.mark.parametrize("name", BUNDLES)
@given(a=algebra_vectors(dim=6, max_norm=1.5), b=vectors6)
def test_bundle_log_inverts_exp(name, a, b):
    bundle = BUNDLES[name]
    U = bundle_algebra(bundle, a, b)
    _close(bundle.inverse_map(EXP, bundle.map(EXP, U)), U, tol=1e-10)


@pytest.mark.parametrize("name", BUNDLES)
def test_bundle_bracket_is_the_group_commutator(name):
    """[X, Y] = ∂_t ∂_s exp(tX) exp(sY) exp(tX)⁻¹ at 0, by nested jvp."""
    bundle = BUNDLES[name]
    rng = np.random.default_rng(3)
    X = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))
    Y = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))

    def scaled(t, U):
        return jax.tree.map(lambda x: t * x, U)

    def adjoint_of_exp(t):
        g = bundle.map(EXP, scaled(t, X))

        def inner(s):
            return bundle.multiply(bundle.multiply(g, bundle.map(EXP, scaled(s, Y))), bundle.inverse(g))

        return tangent_to_algebra(bundle, jax.jvp(inner, (0.0,), (1.0,))[1])

    _, bracket = jax.jvp(adjoint_of_exp, (0.0,), (1.0,))
    _close(bracket, bundle.bracket(X, Y))


def test_bundle_element_checks():
    bundle = pk.Semidirect(pk.SO3)
    good = pk.BundleElement(pk.SO3.exp(jnp.ones(3)), jnp.zeros(3))
    bundle.check(good)
    with pytest.raises(TypeError, match="BundleElement"):
        bundle.check((good.base, good.fiber))
    with pytest.raises(TypeError, match="over SO3"):
        bundle.check(pk.BundleElement(pk.SOn(jnp.eye(3)), jnp.zeros(3)))
    with pytest.raises(ValueError, match="fiber shape"):
        bundle.check(pk.BundleElement(good.base, jnp.zeros(4)))
    with pytest.raises(TypeError, match="SO3 fiber"):
        pk.Cartesian(pk.SO3).check(good)
    with pytest.raises(ValueError, match="trivialization"):
        pk.Semidirect(pk.SO3, "middle")
    with pytest.raises(TypeError, match="base group class"):
        pk.DirectProduct("SO3")
    with pytest.raises(ValueError, match="3, 3"):
        pk.SO3(jnp.eye(4))


# --- the actions a PRKMK step uses instead of forming f(U) ------------------------------
@pytest.mark.parametrize("name", ["SO3", "SO4", "R3", "SO3xR3", "SO3-pair"])
@given(a=vectors6, b=vectors6)
def test_adjoint_of_exp_and_cayley_act_without_the_matrix(name, a, b):
    """exp_adjoint/cayley_adjoint agree with forming exp(u)/cay(u) and acting."""
    group, alg = BASES[name]
    u, x = alg(a), alg(b)
    _close(group.exp_adjoint(u, x), group.exp(u).adjoint(x))
    _close(group.cayley_adjoint(u, x), group.cayley(u).adjoint(x))


def _dexp_through_the_matrix(u, v):
    """dexp_u v = vee((d/ds exp(u + s v))|₀ exp(u)ᵀ), by autodiff of Rodrigues' matrix."""
    r, dr = jax.jvp(lambda w: pk.SO3.exp(w).matrix, (u,), (v,))
    return pk.vee(dr @ r.T)


_SO3_ACTIONS_AND_MATRIX_ROUTES = [
    (pk.SO3.exp_adjoint, lambda u, x: pk.SO3.exp(u).matrix @ x),
    (pk.SO3.dexp, _dexp_through_the_matrix),
]


@jax.jit
def _forward_and_reverse_derivatives(u, x, du, dx):
    """For each action and its matrix route: the JVP along (du, dx) and the
    VJP of a fixed cotangent, both ways. One compiled program for every
    example."""
    cotangent = jnp.asarray([0.3, -1.1, 0.7])
    return [
        tuple((jax.jvp(fn, (u, x), (du, dx)), jax.vjp(fn, u, x)[1](cotangent)) for fn in pair) for pair in _SO3_ACTIONS_AND_MATRIX_ROUTES
    ]


@given(a=vectors6, b=vectors6, c=vectors6)
def test_so3_actions_differentiate_as_the_matrix_route(a, b, c):
    """exp_adjoint and dexp have a hand-written derivative (a custom JVP in
    the dot form); its forward and reverse derivatives agree with autodiff
    of the matrix route, which forms exp(û) and multiplies."""
    u, x = jnp.asarray(a[:3]), jnp.asarray(b[:3])
    du, dx = jnp.asarray(c[:3]), jnp.asarray(c[3:])
    for action, matrix_route in _forward_and_reverse_derivatives(u, x, du, dx):
        _close(action, matrix_route, tol=1e-11)


def _series_and_derivative(t2: float, first: int) -> tuple[float, float]:
    """Σₖ (−t2)ᵏ/(first + 2k)! and its derivative in t2, in exact rational
    arithmetic to 60 terms: sin θ/θ (first = 1) and (1 − cos θ)/θ² (first =
    2) as functions of t2 = θ², for θ ≤ π."""
    x = Fraction(t2)
    value = sum(Fraction((-1) ** k, math.factorial(first + 2 * k)) * x**k for k in range(60))
    slope = sum(Fraction(k * (-1) ** k, math.factorial(first + 2 * k)) * x ** (k - 1) for k in range(1, 60))
    return float(value), float(slope)


@pytest.mark.parametrize("theta", [1e-3, 0.0999, 0.1001, 0.5, 1.5, 3.1])
def test_so3_rotation_coefficients_differentiate_as_their_series(theta):
    """The coefficients of Rodrigues' formula and their derivatives in θ²,
    which a custom JVP computes together (either side of the Taylor branch
    at θ² = 1e-2), forward and reverse, against their series summed exactly.
    Just above the switch the exact forms' derivatives cancel to about
    ε/θ² relative; below it the Taylor polynomials are exact to rounding."""
    t2 = jnp.asarray(theta * theta)
    coefficients = jax.jit(pk.groups.so3._rotation_coefficients)
    (a, b), (da, db) = jax.jit(lambda s: jax.jvp(coefficients, (s,), (jnp.ones_like(s),)))(t2)
    reverse = jax.jit(jax.grad(lambda s: sum(w * c for w, c in zip((0.7, -1.3), coefficients(s)))))(t2)
    (a_exact, da_exact), (b_exact, db_exact) = (_series_and_derivative(float(t2), first) for first in (1, 2))
    np.testing.assert_allclose([a, b], [a_exact, b_exact], rtol=1e-14)
    np.testing.assert_allclose([da, db], [da_exact, db_exact], rtol=1e-12)
    np.testing.assert_allclose(reverse, 0.7 * da_exact - 1.3 * db_exact, rtol=1e-12)


@pytest.mark.parametrize("name", ["SO3", "SO4", "R3", "SE3", "SO3xR3", "SO3-pair"])
@pytest.mark.parametrize("alpha", [0.5, -0.5, 2.0])
@given(a=vectors6, b=vectors6)
def test_inverse_shifted_ad_solves_the_linear_system(name, alpha, a, b):
    """w = (I + α ad_u)⁻¹ v satisfies w + α[u, w] = v."""
    group, alg = BASES[name]
    u, v = alg(a), alg(b)
    w = group.inverse_shifted_ad(u, v, alpha)
    _close(w + alpha * group.bracket(u, w), v, tol=1e-11)


def _written_with_the_required_methods_only(group):
    """A rotation group that delegates the seven methods a quadratic rotation
    group must write to `group` and takes every other one from the defaults."""

    class Plain(AbstractRotationGroup):
        matrix: jax.Array
        algebra_ndim: ClassVar[int] = group.algebra_ndim
        bi_invariant_pairing: ClassVar[bool] = True

        @classmethod
        def exp(cls, u):
            return cls(group.exp(u).matrix)

        def log(self):
            return group(self.matrix).log()

        def adjoint(self, u):
            return group(self.matrix).adjoint(u)

        @classmethod
        def bracket(cls, u, v):
            return group.bracket(u, v)

        @classmethod
        def cayley(cls, u):
            return cls(group.cayley(u).matrix)

        def cayley_inverse(self):
            return group(self.matrix).cayley_inverse()

        @classmethod
        def dcayley_inv(cls, u, v):
            return group.dcayley_inv(u, v)

    return Plain


@pytest.mark.parametrize("name", ["SO3", "SO4", "SO3-pair"])
def test_the_defaults_agree_with_the_closed_forms(name):
    """What a group need not write (the differentials, the actions, the
    changes, the fiber solve) agrees, on a batch, with the closed forms SO(3)
    and SO(n) write for speed and rounding."""
    group, alg = BASES[name]
    plain = _written_with_the_required_methods_only(group)
    rng = np.random.default_rng(3)
    u = jnp.stack([alg(0.8 * rng.normal(size=6) / 3) for _ in range(2)])
    x = jnp.stack([alg(rng.normal(size=6)) for _ in range(2)])
    assert_closed_forms_are_the_defaults(group, plain, u, x)
    g = group.exp(x)
    change = group.exp_change(u)
    for side in ["right", "left"]:
        _close(plain(g.matrix).product_change(change, side).matrix, g.product_change(change, side).matrix, tol=1e-15)
    assert plain(g.matrix).algebra_zeros().shape == g.algebra_zeros().shape


def test_inverse_shifted_ad_and_exp_adjoint_broadcast_batches():
    u = jnp.asarray(np.random.default_rng(1).normal(size=(4, 5, 3)))
    v = jnp.asarray(np.random.default_rng(2).normal(size=(4, 5, 3)))
    w = pk.SO3.inverse_shifted_ad(u, v, 0.5)
    _close(w[2, 3], pk.SO3.inverse_shifted_ad(u[2, 3], v[2, 3], 0.5))
    _close(pk.SO3.exp_adjoint(u, v)[1, 4], pk.SO3.exp(u[1, 4]).adjoint(v[1, 4]))


@pytest.mark.parametrize("name", BUNDLES)
@pytest.mark.parametrize("form", ["space", "body"])
@pytest.mark.parametrize("coordinates", ["exp", "cayley"])
def test_apply_increment_equals_the_group_product(name, form, coordinates):
    """bundle.apply(coordinates, U, y, form) is y·f(U) (body) or f(U)·y (space)."""
    bundle = BUNDLES[name]
    rng = np.random.default_rng(4)
    y = element(bundle, rng.normal(size=6), rng.normal(size=6))
    U = bundle_algebra(bundle, 0.7 * rng.normal(size=6), rng.normal(size=6))
    coords = pk.Exp() if coordinates == "exp" else pk.Cayley()
    increment = bundle.map(coords, U)
    expected = bundle.multiply(y, increment) if form == "body" else bundle.multiply(increment, y)
    _close(bundle.apply(coords, U, y, form), expected, tol=1e-11)
    # A fiber component None is a zero known at trace time (what a PRKMK
    # stage passes when no L enters it): the product with f(u, 0).
    increment = bundle.map(coords, (U[0], jnp.zeros_like(U[1])))
    expected = bundle.multiply(y, increment) if form == "body" else bundle.multiply(increment, y)
    _close(bundle.apply(coords, (U[0], None), y, form), expected, tol=1e-11)


@pytest.mark.parametrize("group", [pk.SO3, pk.SOn])
def test_renormalized_corrects_only_a_rotation_that_drifted(group):
    """`renormalized` leaves a rotation within a few ulps of the group as it
    is, bit for bit, and takes Björck's step on one that drifted further,
    each matrix of a batch on its own; its derivative is the Björck step's."""
    eps = float(jnp.finfo(jnp.float32).eps)
    rotation = np.asarray(pk.SO3.exp(jnp.asarray([0.3, -1.2, 0.7])).matrix)
    # A rotation rounded to float32 is within a few ulps; one scaled by
    # 1 + 1000 eps has drifted well past them.
    batch = jnp.asarray(np.stack([rotation, rotation * (1 + 1000 * eps)]), jnp.float32)
    before = np.asarray(pk.diagnostics.orthogonality_defect(batch))
    assert before[0] <= 4 * eps and before[1] > 1000 * eps
    after = group(batch).renormalized().matrix
    np.testing.assert_array_equal(after[0], batch[0])
    np.testing.assert_allclose(after[1], bjorck_step(batch[1]), rtol=0, atol=4 * eps)
    assert float(pk.diagnostics.orthogonality_defect(after[1])) < before[1] / 10
    # The derivative is the Björck step's either way (that of the projection
    # onto the group), so a gradient does not depend on where rounding crossed.
    direction = jnp.asarray(np.random.default_rng(0).normal(size=(2, 3, 3)), jnp.float32)
    _, derivative = jax.jvp(lambda m: group(m).renormalized().matrix, (batch,), (direction,))
    _, expected = jax.jvp(bjorck_step, (batch,), (direction,))
    np.testing.assert_allclose(derivative, expected, rtol=0, atol=1e-6)
