"""df⁻¹ of both coordinate maps on every bundle, checked against autodiff:
with X = d/dt f(U + tV)·f(U)⁻¹ at t = 0 (jax.jvp), df⁻¹_U(X) must give back V."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_groups import BUNDLES, bundle_algebra, tangent_to_algebra

import prkmk_jax as pk
from helpers import PositiveReals, max_leaf_difference

COORDINATES = {"exp": pk.Exp(truncation=None), "cayley": pk.Cayley(truncation=None)}


def _differential(bundle, coords, U, V):
    """X = d/dt f(U + tV) f(U)⁻¹ |_{t=0}, by forward-mode autodiff."""
    f_inv = bundle.inverse(bundle.map(coords, U))

    def moved(W):
        return bundle.multiply(bundle.map(coords, W), f_inv)

    return tangent_to_algebra(bundle, jax.jvp(moved, (U,), (V,))[1])


@pytest.mark.parametrize("coords_name", COORDINATES)
@pytest.mark.parametrize("name", BUNDLES)
@pytest.mark.parametrize("scale", [1e-7, 0.3, 1.0])
def test_exact_inverse_differential_matches_autodiff(name, coords_name, scale):
    bundle, coords = BUNDLES[name], COORDINATES[coords_name]
    rng = np.random.default_rng(7)
    U = bundle_algebra(bundle, scale * rng.normal(size=6), scale * rng.normal(size=6))
    V = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))
    X = _differential(bundle, coords, U, V)
    back = bundle.inverse_differential(coords, U, X, method_order=4)
    assert max_leaf_difference(back, V) < 1e-12


def _next_nonzero_bernoulli(q):
    k = q + 1
    while k > 1 and k % 2 == 1:  # B_k = 0 for odd k ≥ 3
        k += 1
    return k


@pytest.mark.parametrize("name", BUNDLES)
@pytest.mark.parametrize("q", [0, 1, 2, 3, 4])
def test_truncated_series_error_rate(name, q):
    """‖series_q − exact‖ = O(|U|^{q+1}); precisely the first dropped nonzero
    Bernoulli term, so the slope is q+1 (or q+2 when B_{q+1} = 0)."""
    bundle = BUNDLES[name]
    rng = np.random.default_rng(11)
    U1 = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))
    X = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))
    scales = np.array([0.2, 0.1, 0.05, 0.025])
    errs = []
    for s in scales:
        U = jax.tree.map(lambda u: s * u, U1)
        exact = bundle.inverse_differential(pk.Exp(), U, X)
        errs.append(max_leaf_difference(bundle.inverse_differential(pk.Exp(truncation=q), U, X, 4), exact))
    errs = np.asarray(errs)
    if np.all(errs < 1e-14):  # abelian directions: the series is exact (e.g. over ℝ³)
        assert bundle.base is pk.VectorSpace
        return
    slope = np.polyfit(np.log(scales), np.log(errs), 1)[0]
    assert abs(slope - _next_nonzero_bernoulli(q)) < 0.1, (slope, errs)


def test_default_truncation_follows_method_order():
    assert [pk.Exp().resolve_truncation(p) for p in (1, 2, 3, 4, 6)] == [0, 0, 1, 2, 4]
    assert pk.Exp(truncation=5).resolve_truncation(2) == 5
    assert pk.Exp(truncation=None).resolve_truncation(2) is None
    assert [pk.Cayley().resolve_truncation(p) for p in (1, 2, 3, 4)] == [0, 0, None, None]


@pytest.mark.parametrize("bad", [-1, 1.5, "all", True])
def test_bad_truncation(bad):
    with pytest.raises(ValueError, match="truncation"):
        pk.Exp(truncation=bad)


def test_cayley_truncation_one_refused():
    with pytest.raises(ValueError, match="truncation 1"):
        pk.Cayley(truncation=1)


def test_cayley_needs_a_quadratic_group():
    with pytest.raises(TypeError, match="quadratic"):
        pk.PRKMK(pk.DirectProduct(PositiveReals), pk.Cayley(), pk.symplectic_euler)
    # exponential coordinates work on it
    pk.PRKMK(pk.DirectProduct(PositiveReals), pk.Exp(), pk.symplectic_euler)


def test_semidirect_cayley_is_the_section_4_4_map():
    """cay(u, v) = (cay(u), (I + ½ad_u)⁻¹ v) in left trivialisation (§4.4),
    written out for SO(3): (I + ½û)⁻¹ = (I − ½û + ¼uuᵀ)/(1 + |u|²/4)."""
    rng = np.random.default_rng(5)
    u, v = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))
    y = pk.Semidirect(pk.SO3, "left").map(pk.Cayley(), (u, v))
    inv = (jnp.eye(3) - pk.hat(u) / 2 + jnp.outer(u, u) / 4) / (1 + u @ u / 4)
    np.testing.assert_allclose(y.fiber, inv @ v, atol=1e-14)
    np.testing.assert_allclose(y.base.matrix, pk.SO3.cayley(u).matrix, atol=1e-14)
    # and (I − ½ad_u)⁻¹ v in right trivialisation
    yr = pk.Semidirect(pk.SO3, "right").map(pk.Cayley(), (u, v))
    np.testing.assert_allclose(jnp.linalg.solve(jnp.eye(3) - pk.hat(u) / 2, v), yr.fiber, atol=1e-14)


def test_dexp_series_inverts_dexp_inv_series():
    """dexp and dexp⁻¹ series are inverse power series: composing the two
    truncated at q leaves an O(|U|^{q+1}) residual."""
    rng = np.random.default_rng(2)
    u, x = 0.05 * jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))
    composed = pk.dexp_inv_series(pk.SO3.bracket, u, pk.dexp_series(pk.SO3.bracket, u, x, 12), 12)
    np.testing.assert_allclose(composed, x, atol=1e-15)
    np.testing.assert_allclose(pk.dexp_series(pk.SO3.bracket, u, x, 12), pk.SO3.dexp(u, x), atol=1e-15)
    # At |u| = 1.5 the Bernoulli numbers' terms matter to the twentieth power:
    # the series to 40 powers meets the closed form.
    u = 1.5 * u / jnp.linalg.norm(u)
    np.testing.assert_allclose(pk.dexp_inv_series(pk.SO3.bracket, u, x, 40), pk.SO3.dexp_inv(u, x), atol=1e-13)


@pytest.mark.parametrize("trivialization", ["left", "right"])
def test_paper_printed_semidirect_dcayley_inv_holds_on_so3_only(trivialization):
    """The §4.4 bracket-only dcay⁻¹ inverts the differential of the §4.4 map on
    so(3), but not on so(4): there the library uses its own derivation."""
    from prkmk_jax.coordinates import paper_semidirect_dcayley_inv

    coords = pk.Cayley(truncation=None)
    rng = np.random.default_rng(9)
    residuals = {}
    for base in (pk.SO3, pk.SOn):
        bundle = pk.Semidirect(base, trivialization)
        U = bundle_algebra(bundle, 0.6 * rng.normal(size=6), 0.6 * rng.normal(size=6))
        V = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))
        X = _differential(bundle, coords, U, V)
        residuals[base] = max_leaf_difference(paper_semidirect_dcayley_inv(base, U, X), V)
        assert max_leaf_difference(bundle.inverse_differential(coords, U, X), V) < 1e-12
    assert residuals[pk.SO3] < 1e-12
    assert residuals[pk.SOn] > 1e-4


@pytest.mark.parametrize("coords_name", COORDINATES)
@pytest.mark.parametrize("name", BUNDLES)
@pytest.mark.parametrize("scale", [1e-7, 0.3, 1.0])
def test_inverse_map_inverts_the_map(name, coords_name, scale):
    """f⁻¹(f(U)) = U, and a method's `increment_between` recovers the
    increment of y ↦ f(U)·y (space form) and y ↦ y·f(U) (body form)."""
    bundle, coords = BUNDLES[name], COORDINATES[coords_name]
    rng = np.random.default_rng(11)
    U = bundle_algebra(bundle, scale * rng.normal(size=6), scale * rng.normal(size=6))
    assert max_leaf_difference(bundle.inverse_map(coords, bundle.map(coords, U)), U) < 1e-12
    y = bundle.map(coords, bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6)))
    for form in ("space", "body"):
        method = pk.PRKMK(bundle, coords, form=form)
        moved = method.apply_increment(U, y)
        assert max_leaf_difference(method.increment_between(y, moved), U) < 1e-11


def test_so3_cayley_inverse_matches_the_matrix_formula():
    """cay⁻¹(R) = 2(R + I)⁻¹(R − I) for SO(3) in vector form and for SO(n)."""
    rng = np.random.default_rng(3)
    for u in rng.normal(size=(5, 3)):
        r = pk.SO3.cayley(jnp.asarray(u)).matrix
        matrix_form = 2 * np.linalg.solve(np.asarray(r) + np.eye(3), np.asarray(r) - np.eye(3))
        np.testing.assert_allclose(pk.hat(pk.SO3(r).cayley_inverse()), matrix_form, atol=1e-13)
        np.testing.assert_allclose(pk.SOn(r).cayley_inverse(), matrix_form, atol=1e-13)
