"""The stage plan: which slopes a step solves for together and which it
evaluates directly. The dependence read from the traced program is checked
against autodiff, the plans against the paper's remarks, and every plan
against the tableau-coupled solve (same trajectory to the stage tolerance)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, TOP_ARGS, initial_state, rigid_body_field, scene_order, scene_reference
from prkmk_jax.methods.stage_plan import COUPLED, Explicit, Implicit, StageDependence, output_dependence, plan_stages
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, SphericalTop, SymmetricRigidBody, TopParameters, random_rotation

SPHERICAL_ARGS = TopParameters(jnp.array(0.7), jnp.array([0.1, 0.2, 0.9]))


# --- reading dependence from a program -----------------------------------------------------
def test_output_dependence_of_small_programs():
    closed_over = jnp.array([1.0, 2.0, 3.0])

    @jax.jit
    def nested(a, b):  # a nested jit is followed output by output
        return a + 1.0, 2.0 * b

    def fn(a, b):
        first, second = nested(a, b)
        return a * 2.0, jnp.zeros(3), jnp.cross(a, b), first, second, closed_over * 0.0, jnp.ones(3) - 1.0

    out = output_dependence(fn, jnp.ones(3), jnp.ones(3))
    assert [deps for deps, _ in out] == [{0}, set(), {0, 1}, {0}, {1}, set(), set()]
    values = [value for _, value in out]
    assert all(values[k] is None for k in (0, 2, 3, 4))
    np.testing.assert_array_equal(values[1], np.zeros(3))
    assert values[5] is None  # depends on a closed-over value: not a known constant
    np.testing.assert_array_equal(values[6], np.zeros(3))


def test_output_dependence_over_states_not_values():
    """Structural, so it can only over-state: x − x depends on x."""
    (deps, value), *_ = output_dependence(lambda x: (x - x,), jnp.ones(2))
    assert deps == {0} and value is None


SCENES = {
    "free body T*SO(3)": (FreeRigidBody(), jnp.asarray(INERTIA)),
    "free body G×g": (FreeRigidBody(pk.DirectProduct(pk.SO3)), jnp.asarray(INERTIA)),
    "heavy top": (HeavyTop(), TOP_ARGS),
    "spherical top": (SphericalTop(), SPHERICAL_ARGS),
    "symmetric body": (SymmetricRigidBody(), jnp.asarray(INERTIA)),
}


def _state(scene, seed=0):
    if isinstance(scene, SymmetricRigidBody):
        return initial_state(scene.bundle, seed)
    return pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(seed))), jnp.array([0.3, -0.4, 1.5]))


@pytest.mark.parametrize("coordinates", [pk.Exp(), pk.Exp(truncation=2), pk.Cayley()], ids=["exp", "exp q=2", "cayley"])
@pytest.mark.parametrize("name", list(SCENES))
def test_traced_dependence_agrees_with_autodiff(name, coordinates):
    """Where the plan says a slope does not depend on u or v, its Jacobian
    there is exactly zero at random stage points; where it says it does, the
    Jacobian is not (so the reading is neither too loose nor vacuous here)."""
    scene, args = SCENES[name]
    method = scene.method(pk.stormer_verlet, coordinates)
    y = _state(scene)
    zeros = method.bundle.algebra_zeros(y)

    def stage(u, v):
        U = (u, v)
        return method.slope(U, method.generator(scene, 0.0, method.apply_increment(U, y), args))

    deps = [d for d, _ in output_dependence(stage, *zeros)]
    rng = np.random.default_rng(1)
    for trial in range(3):
        point = tuple(jnp.asarray(0.1 * rng.normal(size=z.shape)) for z in zeros)
        jacobian = jax.jacfwd(stage, argnums=(0, 1))(*point)
        for c in (0, 1):
            for k in (0, 1):
                nonzero = bool(jnp.any(jacobian[c][k] != 0))
                if k not in deps[c]:
                    assert not nonzero, (name, c, k)
                elif trial == 0:
                    assert nonzero, (name, c, k, deps)


# --- plans ---------------------------------------------------------------------------------
def test_eta_zero_makes_the_first_verlet_stage_explicit():
    """The free body on T*SO(3) has η ≡ 0, so L ≡ 0 and only A¹ links the
    K's: SV's first stage is explicit (K₁ = ξ(yₙ)), Lobatto 4 iterates two
    stages instead of three, in exp (any truncation) and Cayley."""
    scene, args = SCENES["free body T*SO(3)"]
    y = _state(scene)
    for coordinates in (pk.Exp(), pk.Exp(truncation=None), pk.Cayley()):
        assert scene.method(pk.stormer_verlet, coordinates).stage_plan(scene, 0.0, y, args) == (
            Explicit(0, (0,)),
            Implicit(((1, 0),)),
        )
        assert scene.method(pk.lobatto_iiia_iiib4, coordinates).stage_plan(scene, 0.0, y, args) == (
            Explicit(0, (0,)),
            Implicit(((1, 0), (2, 0))),
        )


@pytest.mark.parametrize("coordinates", [pk.Exp(), pk.Cayley()], ids=["exp", "cayley"])
def test_separable_field_makes_euler_and_verlet_explicit(coordinates):
    """The paper's remark after (4.15): ξ(w), η(g) on G×g with the truncated
    equations (df⁻¹ = I) give explicit schemes; with the exact dexp⁻¹ they
    stay implicit (footnote 3)."""
    scene, args = SCENES["spherical top"]
    y = _state(scene)
    for tab in (pk.symplectic_euler, pk.stormer_verlet):
        plan = scene.method(tab, coordinates).stage_plan(scene, 0.0, y, args)
        assert all(isinstance(part, Explicit) for part in plan), plan
        assert sorted((p.stage, c) for p in plan for c in p.components) == [(i, c) for i in range(tab.num_stages) for c in (0, 1)]
    exact = scene.method(pk.stormer_verlet, pk.Exp(truncation=None)).stage_plan(scene, 0.0, y, args)
    assert any(isinstance(part, Implicit) for part in exact)


def test_plan_of_a_dependence_given_by_hand():
    """K depends on v only and L on u only (separable, decoupled): SV is the
    classical explicit leapfrog order L₁, K₁, K₂, L₂."""
    separable = StageDependence(frozenset({"v"}), frozenset({"u"}))
    assert plan_stages(pk.stormer_verlet, separable) == (Explicit(0, (1,)), Explicit(0, (0,)), Explicit(1, (0,)), Explicit(1, (1,)))
    assert plan_stages(pk.stormer_verlet, COUPLED) == (Implicit(((0, 0), (0, 1))), Implicit(((1, 0), (1, 1))))
    with pytest.raises(ValueError, match="depends on 'u' and/or 'v'"):
        StageDependence(frozenset({"w"}), frozenset())


def test_a_constant_nonzero_eta_is_not_taken_for_zero():
    """η = const ≠ 0 (a constant body torque) moves the fiber: L is a slope."""
    bundle = pk.Cotangent(pk.SO3)

    def field(t, y, inertia):
        return y.fiber / inertia, jnp.array([0.0, 0.1, 0.0])

    method = pk.PRKMK(bundle, pk.Exp(), pk.stormer_verlet, form="body")
    plan = method.stage_plan(field, 0.0, initial_state(bundle), jnp.asarray(INERTIA))
    assert any(c == 1 for part in plan for c in (part.components if isinstance(part, Explicit) else [c for _, c in part.slopes]))


# --- the same trajectories -----------------------------------------------------------------
TABLEAUS = {"SE": pk.symplectic_euler, "SV": pk.stormer_verlet, "L4": pk.lobatto_iiia_iiib4}


# Each scene and each tableau at least once; the heavy top, whose field
# couples most, with the tableau of most stages.
PLAN_CASES = [
    ("free body T*SO(3)", "SE"),
    ("free body G×g", "L4"),
    ("heavy top", "L4"),
    ("spherical top", "SV"),
    ("symmetric body", "SE"),
]


@pytest.mark.parametrize("name, tab", PLAN_CASES)
def test_traced_plan_gives_the_tableau_plan_trajectory(name, tab):
    """50 steps; states agree to 1e-12, and to the tolerance the traced plan
    never iterates more (past it, solving to round-off, the count of the
    last iterations is the rounding's). Explicit plans iterate not at all."""
    scene, args = SCENES[name]
    y0, h, steps = _state(scene), 0.05, 50
    runs = {}
    for until in ("round-off", "tolerance"):
        for coupling in ("traced", "tableau"):
            method = scene.method(TABLEAUS[tab], coupling=coupling, iterate_until=until)
            runs[until, coupling] = pk.integrate(method, scene, y0, 0.0, h, steps, args, save_every=10)
    for a, b in zip(jax.tree.leaves(runs["round-off", "traced"].ys), jax.tree.leaves(runs["round-off", "tableau"].ys)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    iterations = {key: int(run.stats["num_iterations"]) for key, run in runs.items()}
    assert iterations["tolerance", "traced"] <= iterations["tolerance", "tableau"]
    plan = scene.method(TABLEAUS[tab]).stage_plan(scene, 0.0, y0, args)
    if all(isinstance(part, Explicit) for part in plan):
        assert iterations["round-off", "traced"] == iterations["tolerance", "traced"] == 0


@pytest.mark.parametrize(
    "bundle, form",
    [
        (pk.Cotangent(pk.SO3), "space"),
        (pk.Semidirect(pk.SO3, "right"), "body"),
        (pk.Semidirect(pk.SO3, "left"), "space"),
        (pk.DirectProduct(pk.SO3), "body"),
    ],
    ids=str,
)
def test_both_forms_and_trivialisations_agree_with_the_tableau_plan(bundle, form):
    field = rigid_body_field(bundle, form)
    y0, args = initial_state(bundle), jnp.asarray(INERTIA)
    ends = []
    for coupling in ("traced", "tableau"):
        method = pk.PRKMK(bundle, pk.Exp(), pk.stormer_verlet, form=form, coupling=coupling)
        ends.append(pk.integrate(method, field, y0, 0.0, 0.05, 40, args, save_every=40).ys)
    for a, b in zip(jax.tree.leaves(ends[0]), jax.tree.leaves(ends[1])):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_explicit_verlet_keeps_its_order_and_the_spin_to_round_off():
    """On the spherical top the explicit SV is still order 2 (slope against
    DOP853 at 1e-13 on the embedding, which knows nothing of the plan), its
    invariants hold as the exact flow's do along that reference, and
    Π' = Γ × ℓ ⟂ ℓ makes the spin ℓ·Π exact per step."""
    scene, args = SCENES["spherical top"]
    y0, t_end = _state(scene), 2.0
    z_ref = scene_reference(scene, y0, t_end, args)
    reference = z_ref[-1]
    along = pk.BundleElement(pk.SO3(jnp.asarray(z_ref[:, :9].reshape(-1, 3, 3))), jnp.asarray(z_ref[:, 9:]))
    for name, values in scene.invariants(along, args).items():
        np.testing.assert_allclose(values, values[0], atol=1e-10, err_msg=name)
    method = scene.method(pk.stormer_verlet)
    slope, errors = scene_order(method, scene, y0, args, t_end, [20, 40, 80, 160], reference=reference)
    assert abs(slope - 2) < 0.2, (slope, errors)
    traj = pk.integrate(method, scene, y0, 0.0, 0.1, 2000, args, save_every=100)
    spin = scene.invariants(traj.ys, args)["spin"]
    np.testing.assert_allclose(spin, spin[0], rtol=0, atol=1e-13)


def test_spherical_top_refuses_principal_moments():
    scene = SphericalTop()
    with pytest.raises(ValueError, match="one number"):
        scene(0.0, _state(scene), TOP_ARGS)


def test_coupling_is_checked():
    with pytest.raises(ValueError, match="coupling must be"):
        pk.PRKMK(pk.Cotangent(pk.SO3), coupling="loose")
