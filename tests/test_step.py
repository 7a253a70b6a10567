"""The PRKMK step: the paper's §4.3 update formulas, equivalence with the
classical PRK method on ℝⁿ×ℝⁿ, and the empirical order of every tableau on
every representation with both coordinate maps."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import prkmk_jax as pk
from helpers import INERTIA, initial_state, max_leaf_difference, random_rotation, rigid_body_field
from prkmk_jax.methods.stage_plan import Implicit

H = 0.1


# --- §4.3: symplectic Euler in exp coordinates on the three representations ------------
def _xi(g, w):
    return jnp.array([0.3, -0.1, 0.2]) + 0.5 * w + g @ jnp.array([0.1, 0.4, -0.2])


def _eta(g, w):
    return jnp.cross(g @ jnp.array([0.2, 0.1, 0.3]), w) + jnp.array([0.05, 0.0, -0.1])


def _solve_4_7(g0, w0):
    """Solve (4.7) by plain fixed-point iteration: u₁ = hξ(exp(u₁)g₀, w₀),
    v₁ = hη(exp(u₁)g₀, w₀)."""
    u = jnp.zeros(3)
    for _ in range(200):
        u = H * _xi(pk.SO3.exp(u).matrix @ g0, w0)
    v = H * _eta(pk.SO3.exp(u).matrix @ g0, w0)
    return u, v


def _left_dexp_by_quadrature(u, v):
    """(exp(−ad_u) − I)/(−ad_u) v = ∫₀¹ Ad_{exp(−su)} v ds, by Gauss–Legendre."""
    nodes, weights = np.polynomial.legendre.leggauss(30)
    s = 0.5 * (nodes + 1)
    return sum(0.5 * wk * (pk.SO3.exp(-sk * u).matrix @ v) for sk, wk in zip(s, weights))


def _space_field(feature):
    """The field of §4.3 for a representation: ξ(g, w), η(g, w) written in its
    general form (2.2–2.3 / §2.2 left / §2.3), `feature` giving w from the fiber."""

    def field(t, y, args):
        return _xi(y.base.matrix, feature(y)), _eta(y.base.matrix, feature(y))

    return field


def test_section_4_3_update_formulas():
    g0 = jnp.asarray(random_rotation(4))
    w0 = jnp.array([0.4, -0.3, 0.7])
    p0 = pk.SO3.exp(w0)
    u1, v1 = _solve_4_7(g0, w0)
    g1 = pk.SO3.exp(u1).matrix @ g0

    def se(bundle):
        return pk.PRKMK(bundle, pk.Exp(), pk.symplectic_euler, form="space")

    # G×g, (4.8): g₁ = exp(u₁)g₀, w₁ = v₁ + w₀ — the field (2.2–2.3) is (ξ, η).
    direct = pk.DirectProduct(pk.SO3)
    y1 = se(direct).step(_space_field(lambda y: y.fiber), 0.0, pk.BundleElement(pk.SO3(g0), w0), H).y
    np.testing.assert_allclose(y1.base.matrix, g1, atol=1e-13)
    np.testing.assert_allclose(y1.fiber, v1 + w0, atol=1e-13)

    # G⋉g left, (4.11): w₁ = Ad_{g₀⁻¹}(dexp_{u₁}(v₁)) + w₀, for w' = Ad_{g⁻¹}η
    # i.e. the space-form generator (ξ, η).
    semi = pk.Semidirect(pk.SO3, "left")
    y1 = se(semi).step(_space_field(lambda y: y.fiber), 0.0, pk.BundleElement(pk.SO3(g0), w0), H).y
    np.testing.assert_allclose(y1.base.matrix, g1, atol=1e-13)
    np.testing.assert_allclose(y1.fiber, g0.T @ _left_dexp_by_quadrature(u1, v1) + w0, atol=1e-13)

    # G×G, (4.14): p₁ = exp(v₁)p₀, with w read from p as its logarithm.
    cart = pk.Cartesian(pk.SO3)
    y1 = se(cart).step(_space_field(lambda y: y.fiber.log()), 0.0, pk.BundleElement(pk.SO3(g0), p0), H).y
    np.testing.assert_allclose(y1.base.matrix, g1, atol=1e-13)
    np.testing.assert_allclose(y1.fiber.matrix, pk.SO3.exp(v1).matrix @ p0.matrix, atol=1e-13)


def test_rkmk8_with_cayley_on_the_cotangent_bundle_is_the_matrix_method():
    """T*SO(3) = SO(3)⋉ℝ³ as the 4×4 matrices [[g, 0], [Πᵀ, 1]] (their product
    is the left-trivialised bundle's), the free body's generator (Π/I, 0) as
    [[Ω̂, 0], [0, 0]]: RKMK 8 written on the matrices (cay(A) = (I − A/2)⁻¹(I + A/2),
    dcay⁻¹_A(B) = (I + A/2) B (I − A/2) for y = y₀·cay(A)) is the library's step."""
    scene, inertia = pk.scenes.FreeRigidBody(), jnp.asarray(INERTIA)
    tableau, eye, h = pk.dormand_prince_8, jnp.eye(4), 0.25

    def matrix(y):
        return jnp.block([[y.base.matrix, jnp.zeros((3, 1))], [y.fiber[None, :], jnp.ones((1, 1))]])

    def generator(y):
        return jnp.zeros((4, 4)).at[:3, :3].set(pk.hat(y[3, :3] / inertia))

    def cay(a):
        return jnp.linalg.solve(eye - a / 2, eye + a / 2)

    def step(y):
        slopes = []
        for row in tableau.a_first:
            a = h * sum((c * k for c, k in zip(row, slopes) if c != 0), jnp.zeros((4, 4)))
            slopes.append((eye + a / 2) @ generator(y @ cay(a)) @ (eye - a / 2))
        return y @ cay(h * sum(c * k for c, k in zip(tableau.b_first, slopes)))

    y = initial_state(pk.Cotangent(pk.SO3))
    by_hand, method = matrix(y), scene.method(tableau, pk.Cayley())
    for _ in range(8):
        by_hand, y = step(by_hand), method.step(scene, 0.0, y, h, inertia).y
    np.testing.assert_allclose(matrix(y), by_hand, rtol=0, atol=1e-13)


# --- classical PRK on ℝⁿ×ℝⁿ ------------------------------------------------------------
def _pendulum(t, y, args):
    q, p = y.base.value, y.fiber.value
    return p, -jnp.sin(q) + 0.1 * jnp.cos(t) * args  # (q' , p')


def _classical_prk(tab, q, p, t, h, args, iters=200):
    """Algorithm 4.1 written out (fixed-point iteration on all stage slopes)."""
    s = tab.num_stages
    k = np.zeros((s,) + q.shape)
    l_slopes = np.zeros((s,) + p.shape)
    for _ in range(iters):
        u = q + h * np.tensordot(tab.a_first, k, axes=1)
        v = p + h * np.tensordot(tab.a_second, l_slopes, axes=1)
        new = [_pendulum(t + tab.c_first[i] * h, pk.BundleElement(pk.VectorSpace(u[i]), pk.VectorSpace(v[i])), args) for i in range(s)]
        k = np.stack([np.asarray(n[0]) for n in new])
        l_slopes = np.stack([np.asarray(n[1]) for n in new])
    return q + h * tab.b_first @ k, p + h * tab.b_second @ l_slopes


LAYOUTS = [(tab, "auto") for tab in pk.tableaus.ALL_TABLEAUS] + [
    (tab, layout) for tab in pk.tableaus.EXPLICIT_TABLEAUS for layout in ("unrolled", "loop")
]


@pytest.mark.parametrize("tab,layout", LAYOUTS, ids=lambda x: getattr(x, "name", x))
@pytest.mark.parametrize("coords", [pk.Exp(), pk.Cayley()], ids=["exp", "cayley"])
def test_classical_prk_on_vector_space(tab, layout, coords):
    """On Cartesian(ℝ²) the PRKMK step is exactly Algorithm 4.1 (the
    explicit tableaus with their stages unrolled and in a loop)."""
    q0, p0 = np.array([1.2, -0.4]), np.array([0.3, 0.8])
    method = pk.PRKMK(pk.Cartesian(pk.VectorSpace), coords, tab, form="space", explicit_stages=layout)
    y = pk.BundleElement(pk.VectorSpace(jnp.asarray(q0)), pk.VectorSpace(jnp.asarray(p0)))
    step = method.step(_pendulum, 0.3, y, 0.2, 0.7)
    y1, result = step.y, step.result
    assert result == pk.RESULTS.successful
    q1, p1 = _classical_prk(tab, q0, p0, 0.3, 0.2, 0.7)
    np.testing.assert_allclose(y1.base.value, q1, atol=1e-13)
    np.testing.assert_allclose(y1.fiber.value, p1, atol=1e-13)


# --- starting guesses of the implicit stages -------------------------------------------
@pytest.mark.parametrize("tab", [pk.stormer_verlet, pk.lobatto_iiia_iiib4, pk.symplectic_euler], ids=lambda t: t.name)
def test_stage_guesses_change_the_iterations_not_the_step(tab):
    """Any starting guess converges to the same stage slopes (to the stage
    tolerance); the guess only changes how many iterations it takes."""
    bundle = pk.Cotangent(pk.SO3)
    method = pk.PRKMK(bundle, pk.Exp(), tab, form="body")
    field = rigid_body_field(bundle, "body")
    y0 = initial_state(bundle)
    args = jnp.asarray(INERTIA)
    default = method.step(field, 0.0, y0, H, args)
    y_default, n_default, stages = default.y, default.iterations, default.carried[1]
    assert default.result == pk.RESULTS.successful
    # Carried in with the field at y0 itself, the guesses are the stage
    # slopes (they move by the change of that field, here zero), or, solved
    # to round-off, the slopes moved to one side by their offset from it.
    x0 = method.generator(field, 0.0, y0, args)
    far = tuple((k_i + 0.3, l_i - 0.2) for k_i, l_i in stages)
    to_tolerance = dataclasses.replace(method, iterate_until="tolerance")
    from_far, from_exact, exact_to_tolerance = (
        m.step(field, 0.0, y0, H, args, (x0, guesses)) for m, guesses in ((method, far), (method, stages), (to_tolerance, stages))
    )
    for y in (from_far.y, from_exact.y, exact_to_tolerance.y):
        np.testing.assert_allclose(y.fiber, y_default.fiber, rtol=0, atol=1e-12)
        np.testing.assert_allclose(y.base.matrix, y_default.base.matrix, rtol=0, atol=1e-12)
    # From the solution itself each implicit block confirms it in one
    # iteration (stopped at the tolerance); to round-off, any of these starts
    # takes more than that and the evaluation after the loop.
    implicit_blocks = sum(isinstance(part, Implicit) for part in method.stage_plan(field, 0.0, y0, args))
    assert int(exact_to_tolerance.iterations) == implicit_blocks
    assert all(int(n) > 2 * implicit_blocks for n in (n_default, from_far.iterations, from_exact.iterations))


@pytest.mark.parametrize(
    "make",
    [
        lambda: pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.lobatto_iiia_iiib4, form="body"),
        lambda: pk.PRKMK(pk.Cartesian(pk.SO3), pk.Cayley(), pk.stormer_verlet, form="body"),
        lambda: pk.Adjoint(pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.lobatto_iiia_iiib4, form="body")),
        lambda: pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(None), pk.stormer_verlet, form="body", root_finder=optx.Newton(1e-13, 1e-13)),
    ],
    ids=["L4", "SV-cartesian-cayley", "adjoint-L4", "SV-exact-newton"],
)
def test_step_again_at_solved_stages_is_the_step_and_its_derivative(make):
    """From the slopes a step solved for (which the step that undoes it
    solves again), `step_again` evaluates each implicit block once and
    takes the same step; its derivative in the state and the parameters
    (through the implicit function theorem at those slopes) is the
    iterated step's."""
    method = make()
    bundle = method.bundle
    field, y0, args = rigid_body_field(bundle, "body"), initial_state(bundle), jnp.asarray(INERTIA)
    cotangent = jax.tree.map(lambda x: jnp.cos(jnp.arange(x.size, dtype=x.dtype).reshape(x.shape)), y0)

    @eqx.filter_jit
    def step_and_vjp(step_of, y, a):
        """The step and the VJP of its end state at `cotangent`, one program."""

        def end_and_step(y, a):
            step = step_of(y, a)
            return step.y, step

        _, vjp, step = eqx.filter_vjp(end_and_step, y, a, has_aux=True)
        return step, vjp(cotangent)

    solved, expected = step_and_vjp(lambda y, a: method.step(field, 0.0, y, H, a), y0, args)
    again, got = step_and_vjp(lambda y, a: method.step_again(field, 0.0, y, H, a, solved.carried), y0, args)
    assert again.result == pk.RESULTS.successful
    assert max_leaf_difference(again.y, solved.y) <= 1e-15
    if isinstance(method, pk.Adjoint):
        assert int(again.iterations) == 1  # one system for all stages, evaluated once
    elif method.root_finder is None:
        assert int(again.iterations) == sum(isinstance(part, Implicit) for part in method.stage_plan(field, 0.0, y0, args))
    assert max_leaf_difference(got, expected) <= 1e-12 * max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(expected))


@pytest.mark.parametrize("adjoint", [False, True], ids=["PRKMK", "adjoint"])
def test_step_again_flags_slopes_that_do_not_solve(adjoint):
    """Slopes off the solution by far more than the stage tolerance are
    evaluated once, as asked, and the step's result says they were no
    solution."""
    bundle = pk.Cotangent(pk.SO3)
    method = pk.PRKMK(bundle, pk.Exp(), pk.lobatto_iiia_iiib4, form="body")
    method = pk.Adjoint(method) if adjoint else method
    field, y0, args = rigid_body_field(bundle, "body"), initial_state(bundle), jnp.asarray(INERTIA)
    carried = method.step(field, 0.0, y0, H, args).carried
    off = (carried[0], tuple((k_i + 1e-6, l_i) for k_i, l_i in carried[1]))
    assert method.step_again(field, 0.0, y0, H, args, carried).result == pk.RESULTS.successful
    assert method.step_again(field, 0.0, y0, H, args, off).result == pk.RESULTS.nonlinear_max_steps_reached


def test_integrate_extrapolated_guesses_save_iterations():
    """integrate starts each implicit stage from the previous step's slope
    moved by the change of the field (O(h²)); the plain start is the field at
    yₙ (O(h)). Same trajectory to the stage tolerance, fewer iterations to
    reach the tolerance (the iterations past it, to round-off, are about as
    many from either start)."""
    bundle = pk.Cotangent(pk.SO3)
    method = pk.PRKMK(bundle, pk.Exp(), pk.lobatto_iiia_iiib4, form="body", iterate_until="tolerance")
    field = rigid_body_field(bundle, "body")
    y, args, h, steps = initial_state(bundle), jnp.asarray(INERTIA), 0.02, 50
    traj = pk.integrate(method, field, y, 0.0, h, steps, args, save_every=steps)
    plain_iterations = 0
    step = eqx.filter_jit(method.step)  # one compilation for the 50 steps
    for n in range(steps):
        taken = step(field, jnp.asarray(n * h), y, h, args)
        assert taken.result == pk.RESULTS.successful
        y = taken.y
        plain_iterations += int(taken.iterations)
    np.testing.assert_allclose(traj.ys.fiber[-1], y.fiber, rtol=0, atol=1e-12)
    assert int(traj.stats["num_iterations"]) < 0.9 * plain_iterations, (int(traj.stats["num_iterations"]), plain_iterations)


def test_carried_of_the_wrong_structure_is_refused():
    bundle = pk.Cotangent(pk.SO3)
    method = pk.PRKMK(bundle, pk.Exp(), pk.lobatto_iiia_iiib4, form="body")
    field = rigid_body_field(bundle, "body")
    y0, args, zero = initial_state(bundle), jnp.asarray(INERTIA), jnp.zeros(3)
    with pytest.raises(ValueError, match="tuple of 3 algebra pairs"):
        method.step(field, 0.0, y0, H, args, ((zero, zero), ((zero, zero),) * 2))
    with pytest.raises(ValueError, match="every entry must be a pair"):
        method.step(field, 0.0, y0, H, args, ((zero, zero), ((zero, jnp.zeros(4)),) * 3))
    with pytest.raises(ValueError, match="carried's field"):
        method.step(field, 0.0, y0, H, args, ((zero,), ((zero, zero),) * 3))
    with pytest.raises(ValueError, match="carried must be"):
        method.step(field, 0.0, y0, H, args, ((zero, zero),))
