"""Adjoint, symmetrised and composed methods: coefficient sets checked on a
matrix splitting, adjointness and symmetry, empirical orders on two bundles,
invariants, and the same methods through diffeqsolve."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import prkmk_jax as pk
from helpers import (
    INERTIA,
    compiled_value_and_grad,
    empirical_order,
    gradient_and_central_differences,
    initial_state,
    max_leaf_difference,
    reference,
    rigid_body_field,
    state_vector,
)

COTANGENT = pk.Cotangent(pk.SO3)
CARTESIAN = pk.Cartesian(pk.SO3)
ARGS = jnp.asarray(INERTIA)


def _prkmk(bundle, tab=pk.stormer_verlet, coordinates=None, form="body"):
    return pk.PRKMK(bundle, coordinates or pk.Exp(), tab, form=form)


# --- coefficient sets ---------------------------------------------------------------
def _strang_global_error(coefficients, steps, base_order=2):
    """Global error at T = 1 of the composition of a symmetric splitting of
    exp(A + B) for non-commuting 4×4 matrices: Strang (order 2), or for base
    order 4 Strang raised by the triple jump. Independent of the package's
    step: plain matrix exponentials."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(2, 4, 4)) * 0.8
    exact = scipy.linalg.expm(a + b)

    def strang(h):
        half = scipy.linalg.expm(0.5 * h * a)
        return half @ scipy.linalg.expm(h * b) @ half

    def base(h):
        if base_order == 2:
            return strang(h)
        g = pk.triple_jump(2).fractions
        return strang(g[2] * h) @ strang(g[1] * h) @ strang(g[0] * h)

    errors = []
    for n in steps:
        h = 1.0 / n
        step = np.eye(4)
        for gamma in coefficients.fractions:
            step = base(gamma * h) @ step
        errors.append(np.abs(np.linalg.matrix_power(step, n) - exact).max())
    return np.polyfit(np.log(1.0 / np.asarray(steps)), np.log(errors), 1)[0], errors


@pytest.mark.parametrize(
    "coefficients,steps,base_order",
    [
        (pk.yoshida_triple_jump, (8, 16, 32, 64), 2),
        (pk.suzuki_5, (8, 16, 32, 64), 2),
        (pk.kahan_li_6, (4, 8, 16, 32), 2),
        (pk.mclachlan_8, (4, 6, 8, 12), 2),
        (pk.kahan_li_8, (4, 6, 8, 12), 2),
        (pk.triple_jump(4), (4, 8, 16, 32), 4),
        (pk.suzuki_fractal(4), (4, 8, 16, 32), 4),
    ],
    ids=lambda c: getattr(c, "name", None),
)
def test_coefficients_raise_the_order_of_a_matrix_splitting(coefficients, steps, base_order):
    slope, errors = _strang_global_error(coefficients, steps, base_order)
    assert abs(slope - coefficients.order) <= 0.25, (slope, errors)
    assert coefficients.base_order == base_order


def test_coefficient_sets_validate_themselves():
    with pytest.raises(ValueError, match="sum to"):
        pk.CompositionCoefficients("bad", (0.5, 0.6, 0.5), 4, 2, "test")
    with pytest.raises(ValueError, match="palindrome"):
        pk.CompositionCoefficients("bad", (0.3, 0.3, 0.4), 2, 2, "test")
    with pytest.raises(ValueError, match="Σγ\\^3"):
        pk.CompositionCoefficients("bad", (0.25, 0.5, 0.25), 4, 2, "test")
    with pytest.raises(ValueError, match="even order"):
        pk.CompositionCoefficients("bad", (1.0,), 3, 2, "test")
    with pytest.raises(ValueError, match="Σγ\\^5"):  # the triple jump is of order 4, not 6
        pk.CompositionCoefficients("bad", pk.yoshida_triple_jump.fractions, 6, 2, "test")
    for coefficients in pk.compositions.ALL_COMPOSITIONS:
        assert coefficients.source and coefficients.num_steps == len(coefficients.fractions)


# --- adjoint and symmetry ----------------------------------------------------------------
@pytest.mark.parametrize("bundle", [COTANGENT, CARTESIAN], ids=["cotangent", "cartesian"])
@pytest.mark.parametrize(
    "tab,coordinates,form",
    [
        (pk.symplectic_euler, pk.Exp(), "body"),
        (pk.stormer_verlet, pk.Exp(None), "body"),
        (pk.lobatto_iiia_iiib4, pk.Cayley(), "body"),
        (pk.stormer_verlet, pk.Cayley(None), "space"),
    ],
    ids=["SE-exp", "SV-exp-exact", "L4-cayley", "SV-cayley-space"],
)
def test_adjoint_undoes_the_reversed_step(bundle, tab, coordinates, form):
    """Φ*_h = (Φ_{−h})⁻¹: a step of the adjoint, then a step of −h of the
    method itself, returns to the start; so does the reverse order."""
    field = rigid_body_field(bundle, form)
    y0 = initial_state(bundle)
    method = _prkmk(bundle, tab, coordinates, form)
    adjoint = pk.Adjoint(method)
    h = 0.1
    forward = adjoint.step(field, 0.0, y0, h, ARGS)
    y1, result = forward.y, forward.result
    back = method.step(field, h, y1, -h, ARGS).y
    assert result == pk.RESULTS.successful
    assert max_leaf_difference(back, y0) <= 1e-12
    y1 = method.step(field, 0.0, y0, -h, ARGS).y
    back = adjoint.step(field, -h, y1, h, ARGS).y
    assert max_leaf_difference(back, y0) <= 1e-12
    assert max_leaf_difference(adjoint.step(field, 0.0, y0, h, ARGS).y, method.step(field, 0.0, y0, h, ARGS).y) > 1e-8


@pytest.mark.parametrize("tab", [pk.stormer_verlet, pk.lobatto_iiia_iiib4, pk.lobatto_iiia_iiib6], ids=["SV", "L4", "L6"])
def test_adjoint_step_takes_the_same_step_whatever_the_stage_plan(tab):
    """With η ≡ 0 the adjoint iterates the K's alone and evaluates a stage
    whose rows are the weights at the step's start; with
    `coupling="tableau"` it iterates every (K, L) and moves every stage
    point from the step's end. Both solve the same equations."""
    field = rigid_body_field(COTANGENT, "body")
    y0 = initial_state(COTANGENT)
    methods = [pk.PRKMK(COTANGENT, pk.Exp(None), tab, form="body", coupling=c) for c in ("traced", "tableau")]
    steps = [pk.Adjoint(method).step(field, 0.0, y0, 0.1, ARGS) for method in methods]
    assert all(s.result == pk.RESULTS.successful for s in steps)
    assert max_leaf_difference(steps[0].y, steps[1].y) <= 1e-13
    assert max_leaf_difference(steps[0].carried[1], steps[1].carried[1]) <= 1e-12
    # and each undoes the method's step of −h
    assert max_leaf_difference(methods[0].step(field, 0.1, steps[0].y, -0.1, ARGS).y, y0) <= 1e-13


def _adjoint_tableau(tab):
    """The classical adjoint of an RK pair: a*ᵢⱼ = b_{s+1−j} − a_{s+1−i,s+1−j}, b* = b reversed."""

    def adjoint(a, b):
        return b[::-1][None, :] - a[::-1, ::-1], b[::-1]

    a1, b1 = adjoint(tab.a_first, tab.b_first)
    a2, b2 = adjoint(tab.a_second, tab.b_second)
    return pk.PartitionedTableau(f"{tab.name} adjoint", a1, b1, a1.sum(1), a2, b2, a2.sum(1), tab.order)


@pytest.mark.parametrize("tab", [pk.symplectic_euler, pk.lobatto_iiia_iiib4], ids=["SE", "L4"])
def test_adjoint_in_a_vector_space_is_the_adjoint_tableau(tab):
    """On ℝⁿ×ℝⁿ the re-centred stages are the classical adjoint RK pair."""
    bundle = pk.Cartesian(pk.VectorSpace)

    def pendulum(t, y, args):
        return y.fiber.value, -args * jnp.sin(y.base.value)

    y0 = pk.BundleElement(pk.VectorSpace(jnp.array([0.9, -0.3])), pk.VectorSpace(jnp.array([0.2, 0.5])))
    ours = pk.Adjoint(_prkmk(bundle, tab, form="space")).step(pendulum, 0.0, y0, 0.2, 1.3).y
    classical = _prkmk(bundle, _adjoint_tableau(tab), form="space").step(pendulum, 0.0, y0, 0.2, 1.3).y
    assert max_leaf_difference(ours, classical) <= 1e-13
    if tab is pk.symplectic_euler:
        assert np.array_equal(_adjoint_tableau(tab).a_first, pk.symplectic_euler_adjoint.a_first)


@pytest.mark.parametrize(
    "bundle,method,symmetric",
    [
        (COTANGENT, _prkmk(COTANGENT), True),  # η ≡ 0 and df⁻¹ ≈ I: both stage points are end points
        (COTANGENT, _prkmk(COTANGENT, coordinates=pk.Cayley()), True),
        (COTANGENT, _prkmk(COTANGENT, coordinates=pk.Exp(None)), False),
        (COTANGENT, _prkmk(COTANGENT, pk.lobatto_iiia_iiib4), False),
        (CARTESIAN, _prkmk(CARTESIAN), False),
        # Symmetrized makes symmetric what is not: SE on G×G, Lobatto 4 on T*SO(3).
        # (A composition of a symmetric base is symmetric: the splittings' test.)
        (CARTESIAN, pk.Symmetrized(_prkmk(CARTESIAN, pk.symplectic_euler)), True),
        (COTANGENT, pk.Symmetrized(_prkmk(COTANGENT, pk.lobatto_iiia_iiib4, pk.Cayley(None))), True),
    ],
    ids=["SV-cot", "SV-cot-cayley", "SV-cot-exact", "L4-cot", "SV-cart", "sym-SE-cart", "sym-L4-cot"],
)
def test_symmetry_defect(bundle, method, symmetric):
    field = rigid_body_field(bundle, "body")
    y0 = initial_state(bundle)
    defects = [float(pk.symmetry_defect(method, field, y0, h, ARGS)) for h in (0.2, 0.1)]
    if symmetric:
        assert max(defects) <= 1e-12, defects
    else:
        assert min(defects) >= 1e-9, defects
        assert defects[0] > defects[1]  # O(h^{p+1}) → 0 with h


# --- orders ---------------------------------------------------------------------------------
# Störmer–Verlet at Exp()'s default truncation is symmetric on T*SO(3) for the
# free body (`test_symmetry_defect`), so its compositions may claim the
# coefficients' order there.
_SV_COT = _prkmk(COTANGENT)
_SYM_SV_CART = pk.Symmetrized(_prkmk(CARTESIAN))


def test_a_composition_of_a_base_not_symmetric_claims_no_more_than_it_shows():
    """Störmer–Verlet with the exact dexp⁻¹ is not symmetric on T*SO(3)
    (its coordinates are centred at the step's start): composed by
    `kahan_li_6` it measures order 3, not 6. The composition declares the
    base's order, 2, which the slope does not contradict; a symmetrised base
    earns the coefficients' order."""
    base = _prkmk(COTANGENT, pk.stormer_verlet, pk.Exp(None))
    composed = pk.Composition(base, pk.kahan_li_6)
    assert not base.is_symmetric and not composed.is_symmetric
    assert composed.order == 2
    slope, errors = empirical_order(composed, steps=(8, 16, 32))
    assert composed.order - 0.2 <= slope < 4.0, (slope, errors)
    symmetrized = pk.Composition(pk.Symmetrized(base), pk.kahan_li_6)
    assert symmetrized.is_symmetric and symmetrized.order == 6
    assert pk.Composition(symmetrized, pk.triple_jump(6)).order == 8
    with pytest.raises(TypeError, match="assume_symmetric_base must be True or False"):
        pk.Composition(base, pk.kahan_li_6, assume_symmetric_base=1)  # pyright: ignore[reportArgumentType]


def test_composition_needs_a_base_of_its_order():
    with pytest.raises(ValueError, match="order 2.*order 4"):
        pk.Composition(_prkmk(COTANGENT, pk.lobatto_iiia_iiib4), pk.kahan_li_6)
    # Lobatto IIIA–IIIB 4 is not symmetric on T*SO(3) in exp coordinates:
    # the composition claims the base's order unless told otherwise.
    assert pk.Composition(_prkmk(COTANGENT, pk.lobatto_iiia_iiib4), pk.triple_jump(4)).order == 4
    assert pk.Composition(_prkmk(COTANGENT, pk.lobatto_iiia_iiib4), pk.triple_jump(4), assume_symmetric_base=True).order == 6
    with pytest.raises(TypeError, match="CompositionCoefficients"):
        pk.Composition(_SV_COT, (0.5, 0.5))
    with pytest.raises(TypeError, match="composes a PRKMK method"):
        pk.Composition(pk.stormer_verlet, pk.kahan_li_6)
    with pytest.raises(TypeError, match="Adjoint takes a PRKMK"):
        pk.Adjoint(pk.Composition(_SV_COT, pk.kahan_li_6))
    assert pk.Symmetrized(_prkmk(CARTESIAN, pk.symplectic_euler)).order == 2


# --- drivers, invariants, gradients ------------------------------------------------------------
def test_composition_keeps_the_invariants_over_a_long_run():
    """T*SO(3) over 2000 steps: QᵀQ = I and |Π| to round-off, energy bounded."""
    field = rigid_body_field(COTANGENT, "body")
    y0 = initial_state(COTANGENT)
    method = pk.Composition(_SV_COT, pk.kahan_li_6)
    traj = jax.jit(lambda y: pk.integrate(method, field, y, 0.0, 0.05, 2000, ARGS, save_every=50))(y0)
    q, pi = np.asarray(traj.ys.base.matrix), np.asarray(traj.ys.fiber)
    assert np.abs(np.einsum("tji,tjk->tik", q, q) - np.eye(3)).max() <= 1e-13
    assert np.abs(np.linalg.norm(pi, axis=1) - np.linalg.norm(pi[0])).max() <= 1e-13
    energy = 0.5 * np.sum(pi**2 / INERTIA, axis=1)
    assert np.abs(energy - energy[0]).max() <= 1e-6


def test_composition_through_diffeqsolve_interpolates_on_the_group():
    """Dense output between the composed steps (its steps are integrate's:
    `tests/test_drivers.py`)."""
    field = rigid_body_field(COTANGENT, "body")
    y0 = initial_state(COTANGENT)
    method = pk.Composition(_SV_COT, pk.kahan_li_6)
    ts = jnp.array([0.25, 0.55, 0.95])
    sol = diffrax.diffeqsolve(pk.PRKMKTerm(field), pk.PRKMKSolver(method), 0.0, 1.0, 0.1, y0, ARGS, saveat=diffrax.SaveAt(ts=ts))
    dense = sol.ys
    q = np.asarray(dense.base.matrix)
    assert np.abs(np.einsum("tji,tjk->tik", q, q) - np.eye(3)).max() <= 1e-13
    ref = reference(COTANGENT, y0, 0.95, t_eval=np.asarray(ts))
    assert np.abs(state_vector(COTANGENT, dense) - ref).max() <= 1e-4  # cubic Hermite, h = 0.1


def test_symmetrized_step_doubling_reaches_the_tolerance():
    field = rigid_body_field(CARTESIAN, "body")
    y0 = initial_state(CARTESIAN)
    ref = reference(CARTESIAN, y0, 2.0)
    solver = pk.PRKMKSolver(pk.Composition(_SYM_SV_CART, pk.yoshida_triple_jump), adaptive=True)
    sol = diffrax.diffeqsolve(
        pk.PRKMKTerm(field),
        solver,
        0.0,
        2.0,
        0.05,
        y0,
        ARGS,
        stepsize_controller=diffrax.PIDController(rtol=1e-7, atol=1e-7),
        max_steps=1000,
    )
    err = np.abs(state_vector(CARTESIAN, jax.tree.map(lambda a: a[-1], sol.ys)) - ref).max()
    assert err <= 1e-6, err


def test_composition_gradient_matches_finite_differences_and_vmaps():
    field = rigid_body_field(COTANGENT, "body")
    y0 = initial_state(COTANGENT)
    method = pk.Composition(_SV_COT, pk.yoshida_triple_jump)

    def loss(inertia, pi0):
        traj = pk.integrate(method, field, pk.BundleElement(y0.base, pi0), 0.0, 0.1, 10, inertia, save_every=10)
        return jnp.sum(traj.ys.base.matrix[-1, :, 2] * jnp.array([0.3, -0.5, 0.8]))

    grad, fd = gradient_and_central_differences(loss, ARGS, y0.fiber)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())
    batch = jnp.asarray(y0.fiber) * jnp.array([[1.0], [0.9], [1.1]])
    values = jax.jit(jax.vmap(loss, in_axes=(None, 0)))(ARGS, batch)
    np.testing.assert_allclose(values, [compiled_value_and_grad(loss)(ARGS, p)[0] for p in batch], rtol=0, atol=1e-13)
