"""float32, the one home for the dtype: every kind of method and every
driver runs a float32 state in float32, keeps it on the group to a few
ulps (the step renormalises a rotation that has drifted) and stays within
float32's accuracy of the same run in float64."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, TOP_ARGS, initial_state, max_leaf_difference
from prkmk_jax.diagnostics import orthogonality_defect
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, SymmetricRigidBody
from prkmk_jax.scenes.rigid_body import symmetric_initial_state

COTANGENT, CARTESIAN = pk.Cotangent(pk.SO3), pk.Cartesian(pk.SO3)
FREE, TOP, SYMMETRIC = FreeRigidBody(), HeavyTop(), SymmetricRigidBody()
QUATERNION_BODY = FreeRigidBody(pk.Cotangent(pk.UnitQuaternion))
SV = pk.PRKMK(COTANGENT, pk.Exp(), pk.stormer_verlet, form="body")
STEPS, H = 400, 0.01
EPS32 = float(jnp.finfo(jnp.float32).eps)


def _f32(tree):
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), tree)


def _steady_spin(bundle):
    """A spin about the axis of smallest inertia: without the renormalisation
    its rotation drifts off the group by ~5e-8 a step in float32."""
    if bundle == CARTESIAN:
        return symmetric_initial_state(np.eye(3), np.array([0.0, 0.0, 1.0]))
    if bundle.base is pk.UnitQuaternion:
        return pk.BundleElement(pk.UnitQuaternion(jnp.array([1.0, 0.0, 0.0, 0.0])), jnp.array([0.0, 0.0, 1.0]))
    return pk.BundleElement(pk.SO3(jnp.eye(3)), jnp.array([0.0, 0.0, 1.0]))


# name: (field, method, args)
KINDS = {
    "PRKMK SV, exp": (FREE, SV, INERTIA),
    "PRKMK SV, Cayley": (FREE, pk.PRKMK(COTANGENT, pk.Cayley(), pk.stormer_verlet, form="body"), INERTIA),
    "PRKMK Lobatto 4": (FREE, pk.PRKMK(COTANGENT, pk.Exp(), pk.lobatto_iiia_iiib4, form="body"), INERTIA),
    "RKMK 8, stages unrolled": (TOP, TOP.method(pk.dormand_prince_8, pk.Cayley()), TOP_ARGS),
    "RKMK 4, stages in a loop": (
        TOP,
        pk.PRKMK(TOP.bundle, pk.Cayley(), pk.tableaus.classical_rk4, form="body", explicit_stages="loop"),
        TOP_ARGS,
    ),
    "Composition of SV": (FREE, pk.Composition(SV, pk.kahan_li_6), INERTIA),
    "Adjoint of Lobatto 4": (
        FREE,
        pk.Adjoint(pk.PRKMK(COTANGENT, pk.Exp(), pk.lobatto_iiia_iiib4, form="body")),
        INERTIA,
    ),
    "Symmetrized SE on SO(3)×SO(3)": (
        SYMMETRIC,
        pk.Symmetrized(pk.PRKMK(CARTESIAN, pk.Exp(), pk.symplectic_euler, form="body")),
        INERTIA,
    ),
    "PRKMK SV on unit quaternions": (QUATERNION_BODY, QUATERNION_BODY.method(pk.stormer_verlet), INERTIA),
    "Splitting, free body": (FREE, FREE.splitting(pk.suzuki_5), INERTIA),
    "Splitting on unit quaternions": (QUATERNION_BODY, QUATERNION_BODY.splitting(), INERTIA),
    "Splitting, symmetric body": (SYMMETRIC, SYMMETRIC.splitting(), INERTIA),
}


def _two_states(bundle):
    """A random state and a steady spin, stacked (the run is vmapped)."""
    states = [initial_state(bundle), _steady_spin(bundle)]
    return jax.tree.map(lambda *a: jnp.stack(a), *states)


def _groups(y):
    """The rotation matrices of a state (a quaternion's: its defect is about
    2·| |q|² − 1 |)."""
    return [
        g.as_matrix() if isinstance(g, pk.UnitQuaternion) else g.matrix
        for g in (y.base, y.fiber)
        if isinstance(g, (pk.SO3, pk.UnitQuaternion))
    ]


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_of_method_runs_float32_on_the_group_near_float64(kind):
    field, method, args = KINDS[kind]
    y0 = _two_states(method.bundle)

    def final(y0, args):
        run = jax.vmap(lambda y: pk.integrate(method, field, y, 0.0, H, STEPS, args, save_every=STEPS).ys)
        return jax.tree.map(lambda a: a[:, -1], run(y0))

    y32 = final(_f32(y0), _f32(args))
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(y32))
    for matrix in _groups(y32):
        assert float(jnp.max(orthogonality_defect(matrix))) < 20 * EPS32
    y64 = final(y0, args)
    assert max_leaf_difference(jax.tree.map(lambda a: a.astype(jnp.float64), y32), y64) < 1e-4


# name: (method, h, steps, the bound on |Π|²'s relative error in ulps)
NORM_KEEPERS = {
    "Strang splitting": (FREE.splitting(), 0.001, 8000, 400),
    "PRKMK SV, exp": (SV, 0.002, 4000, 100),
}


@pytest.mark.parametrize("name", NORM_KEEPERS)
def test_the_momentum_norm_stays_at_round_off_over_many_small_steps(name):
    """The free body in float32 on T*SO(3), eight tumbles: every step turns
    Π (the splitting's rotations, the action of exp(hΩ) that pushes PRKMK's
    step forward), which keeps |Π|², so its error is rounding alone. A
    rounded turn that scales Π by much the same factor at every step (the
    rotation matrix's √(c² + s²) ≠ 1; x rounded twice in x + a u×x + b u×(u×x))
    grows it in proportion to the steps, to several times these bounds; the
    library's turns keep it a random walk."""
    method, h, steps, bound = NORM_KEEPERS[name]
    y0 = jax.tree.map(lambda *a: jnp.stack(a), *[initial_state(COTANGENT, seed) for seed in range(8)])
    y0 = _f32(pk.BundleElement(y0.base, y0.fiber * jnp.asarray([1.0, -0.7, 1.3])))
    ys = pk.integrate(method, FREE, y0, 0.0, h, steps, jnp.asarray(INERTIA, jnp.float32), save_every=steps // 8).ys
    norms = np.sum(np.asarray(ys.fiber, np.float64) ** 2, axis=-1)
    start = np.sum(np.asarray(y0.fiber, np.float64) ** 2, axis=-1)
    assert np.max(np.abs(norms - start) / start) < bound * EPS32


def _loss_through_diffeqsolve(adjoint, method=SV, field=FREE):
    """max_steps = 32, fewer than ReversibleAdjoint's default checkpoint_every:
    no state is kept but the last."""

    def loss(y0, inertia):
        t1, dt = jnp.asarray(1.0, inertia.dtype), jnp.asarray(0.05, inertia.dtype)
        sol = diffrax.diffeqsolve(pk.PRKMKTerm(field), pk.PRKMKSolver(method), 0.0 * t1, t1, dt, y0, inertia, adjoint=adjoint, max_steps=32)
        return jnp.sum(sol.ys.fiber[-1] ** 2 * jnp.arange(1.0, 4.0)) + jnp.sum(sol.ys.base.matrix[-1, 0, :] * jnp.arange(1.0, 4.0))

    return loss


def _loss_through_integrate(gradient, method=SV):
    """The same loss as `_loss_through_diffeqsolve` (20 steps of 0.05)."""

    def loss(y0, inertia):
        y = pk.integrate(method, FREE, y0, 0.0, 0.05, 20, inertia, save_every=20, gradient=gradient).ys
        return jnp.sum(y.fiber[-1] ** 2 * jnp.arange(1.0, 4.0)) + jnp.sum(y.base.matrix[-1, 0, :] * jnp.arange(1.0, 4.0))

    return loss


# name: (a loss of (y0, inertia) with a reversible gradient, the same loss through the stored steps)
GRADIENTS = {
    "integrate, ReversibleGradient": (_loss_through_integrate(pk.ReversibleGradient()), _loss_through_integrate(pk.StoredSteps())),
    "diffeqsolve, ReversibleAdjoint of a splitting": (
        _loss_through_diffeqsolve(pk.ReversibleAdjoint(), FREE.splitting()),
        _loss_through_integrate(pk.StoredSteps(), FREE.splitting()),
    ),
}


@pytest.mark.parametrize("driver", GRADIENTS)
def test_every_driver_differentiates_float32_in_float32(driver):
    """Two initial states under vmap: the float32 gradient stays float32 and
    equals the gradient through the stored steps of the same run in float32
    to float32's accuracy."""
    loss, reference = GRADIENTS[driver]
    y0 = _two_states(COTANGENT)

    def gradient(loss, y0, inertia):
        return jax.jit(jax.grad(lambda inertia: jnp.sum(jax.vmap(loss, in_axes=(0, None))(y0, inertia))))(inertia)

    g32 = gradient(loss, _f32(y0), jnp.asarray(INERTIA, jnp.float32))
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(g32, gradient(reference, _f32(y0), jnp.asarray(INERTIA, jnp.float32)), rtol=1e-4)


def test_diffeqsolve_runs_in_the_dtype_of_its_times():
    """diffeqsolve promotes y0 to the dtype of t0, t1 and dt0 (README: give
    float32 times for a float32 solve); with them the solve stays float32
    and equals the float32 scan integrator."""
    y32, inertia = _f32(initial_state(COTANGENT)), jnp.asarray(INERTIA, jnp.float32)
    t0, t1, dt = jnp.float32(0.0), jnp.float32(1.0), jnp.float32(0.05)
    sol = diffrax.diffeqsolve(pk.PRKMKTerm(FREE), pk.PRKMKSolver(SV), t0, t1, dt, y32, inertia)
    assert sol.ys.fiber.dtype == jnp.float32 and sol.ys.base.matrix.dtype == jnp.float32
    traj = pk.integrate(SV, FREE, y32, 0.0, 0.05, 20, inertia, save_every=20)
    np.testing.assert_allclose(sol.ys.fiber[-1], traj.ys.fiber[-1], rtol=0, atol=1e-5)
    promoted = diffrax.diffeqsolve(pk.PRKMKTerm(FREE), pk.PRKMKSolver(SV), 0.0, 1.0, 0.05, y32, inertia)
    assert promoted.ys.fiber.dtype == jnp.float64


def test_a_long_float32_run_stays_near_the_same_run_in_float64():
    """Sixteen free bodies, 16000 steps from the same float32 start: SV and
    the Strang splitting round their sums with compensation in float32
    (`AbstractMethod.advance`, `exact_flows.AbstractExactFlow.moved_change`)
    and stay within a hundred ulps of the same runs in float64; with the
    state rounded as it is at every step (`compensated_sum=False`) the
    difference grows with the number of steps, past this bound."""
    steps = 16_000
    start = _f32(jax.tree.map(lambda *a: jnp.stack(a), *[initial_state(COTANGENT, seed) for seed in range(16)]))
    inertia = jnp.asarray(INERTIA, jnp.float32)

    def final(method, y0, inertia):
        return pk.integrate(method, FREE, y0, 0.0, 10.0 / steps, steps, inertia, save_every=steps).ys

    splitting = FREE.splitting()
    start64, inertia64 = jax.tree.map(lambda a: a.astype(jnp.float64), (start, inertia))
    twins = {"SV": final(SV, start64, inertia64), "splitting": final(splitting, start64, inertia64)}
    plain_sv = pk.PRKMK(COTANGENT, pk.Exp(), pk.stormer_verlet, form="body", compensated_sum=False)
    plain_splitting = pk.Splitting(FREE, compensated_sum=False)
    cases = ((SV, "SV", True), (splitting, "splitting", True), (plain_sv, "SV", False), (plain_splitting, "splitting", False))
    for method, twin, within in cases:
        y32 = jax.tree.map(lambda a: a.astype(jnp.float64), final(method, start, inertia))
        assert (max_leaf_difference(y32, twins[twin]) < 100 * EPS32) == within, method
