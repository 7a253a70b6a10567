"""Explicit tableaus (RKMK): classical RK 4 and Dormand–Prince 8 on the
bundle groups. Their order on the free body and the heavy top against DOP853
references, the same step with the stages unrolled and in a loop, what the
step keeps (the group, the coadjoint orbit), gradients against finite
differences, vmap, diffeqsolve and float32."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import (
    INERTIA,
    TOP_ARGS,
    central_differences,
    gradient_and_central_differences,
    initial_state,
    max_leaf_difference,
    rigid_body_field,
)
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, TopParameters, random_rotation

TOP_Y0 = pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(5))), jnp.array([0.3, -0.4, 1.5]))
TOPS = {"cotangent": HeavyTop(), "direct product": HeavyTop(pk.DirectProduct(pk.SO3))}
COORDINATES = {"cayley": pk.Cayley(), "exp": pk.Exp()}


def _batch_state(size, seed=3):
    rng = np.random.default_rng(seed)
    qs = np.stack([random_rotation(seed * 1000 + k) for k in range(size)])
    return pk.BundleElement(pk.SO3(jnp.asarray(qs)), jnp.asarray(np.array([0.3, -0.4, 1.5]) * (1 + 0.1 * rng.normal(size=(size, 3)))))


def test_the_tableaus():
    for tab in pk.tableaus.EXPLICIT_TABLEAUS:
        assert tab.is_explicit and not tab.is_partitioned and not tab.is_symplectic()
        assert tab.violated_conditions(tab.order) == [] and tab.violated_conditions(tab.order + 1) != []
    assert pk.dormand_prince_8.num_stages == 13  # diffrax's 14th (FSAL) stage carries no weight
    assert not pk.lobatto_iiia_iiib6.is_explicit and pk.lobatto_iiia_iiib6.is_partitioned


def test_a_tableau_with_a_diagonal_does_not_convert():
    with pytest.raises(ValueError, match="only explicit"):
        pk.PartitionedTableau.from_butcher("Kvaerno 3", diffrax.Kvaerno3.tableau, order=3)


def _program_has_a_loop(method, field, y, args):
    jaxpr = str(jax.make_jaxpr(lambda y: method.step(field, 0.0, y, 0.1, args).y)(y))
    return "while" in jaxpr or "scan" in jaxpr


@pytest.mark.parametrize(
    "top, coords",
    [(TOPS["cotangent"], COORDINATES["cayley"]), (TOPS["direct product"], COORDINATES["exp"])],
    ids=["cotangent-cayley", "direct product-exp"],
)
def test_stages_in_a_loop_give_the_unrolled_step(top, coords):
    y0 = _batch_state(20)
    runs = {}
    for layout in ("unrolled", "loop"):
        method = pk.PRKMK(top.bundle, coords, pk.dormand_prince_8, form="body", explicit_stages=layout)
        runs[layout] = jax.jit(lambda y, m=method: pk.integrate(m, top, y, 0.0, 0.1, 30, TOP_ARGS, save_every=30).ys)(y0)
    assert max_leaf_difference(runs["loop"], runs["unrolled"]) < 1e-13
    # 20 trajectories: "auto" takes the loop, one trajectory the unrolled stages.
    auto = pk.PRKMK(top.bundle, coords, pk.dormand_prince_8, form="body")
    assert _program_has_a_loop(auto, top, y0, TOP_ARGS) and not _program_has_a_loop(auto, top, TOP_Y0, TOP_ARGS)


def test_layout_errors():
    with pytest.raises(ValueError, match="explicit_stages must be"):
        pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.dormand_prince_8, explicit_stages="scan")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="needs an explicit tableau"):
        pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.lobatto_iiia_iiib6, explicit_stages="loop")


@pytest.mark.parametrize("layout", ["unrolled", "loop"])
def test_the_free_body_stays_on_the_group_and_its_coadjoint_orbit(layout):
    """Not symplectic: the energy drifts. On T*SO(3) the fiber moves by Ad*
    alone (η ≡ 0), so |Π| is kept to round-off, and Q stays orthogonal, over
    T = 1000 (10⁴ steps)."""
    scene = FreeRigidBody()
    method = pk.PRKMK(scene.bundle, pk.Cayley(), pk.dormand_prince_8, form="body", explicit_stages=layout)
    y0 = initial_state(scene.bundle)
    ys = pk.integrate(method, scene, y0, 0.0, 0.1, 10_000, jnp.asarray(INERTIA), save_every=100).ys
    norms = jnp.linalg.norm(ys.fiber, axis=-1)
    assert float(jnp.max(jnp.abs(norms - norms[0]))) < 1e-13 * float(norms[0]) * 50
    assert float(jnp.max(pk.diagnostics.orthogonality_defect(ys.base.matrix))) < 1e-13


def _final_momentum_projection(method, field, y0, args):
    fiber = pk.integrate(method, field, y0, 0.0, 0.1, 20, args, save_every=20).ys.fiber[-1]
    return jnp.sum(fiber * jnp.array([0.2, -0.5, 1.0]))


@pytest.mark.parametrize(
    "batch, tableau",
    # RK 4 at one trajectory (plain runs unrolled, the gradient through the
    # loop: finite differences of the one against the other) and a batch of
    # 16 (the loop throughout). Through integrate: diffeqsolve's stages are
    # integrate's (`test_vmap_of_diffeqsolve_equals_the_batch_in_the_state`),
    # and its gradients are checked in test_solver.py and test_splitting.py.
    [(None, pk.classical_rk4), (16, pk.classical_rk4)],
    ids=["one (unrolled), RK 4", "batch 16 (loop), RK 4"],
)
def test_gradient_in_the_lever_matches_finite_differences(batch, tableau):
    top = TOPS["cotangent"]
    method = top.method(tableau, pk.Cayley())
    y0 = TOP_Y0 if batch is None else _batch_state(batch)

    def loss(lever):
        return _final_momentum_projection(method, top, y0, TopParameters(TOP_ARGS.inertia, lever))

    grad, fd = gradient_and_central_differences(loss, TOP_ARGS.lever, step=1e-6)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)


def test_a_vmapped_gradient_of_thirteen_stages_matches_finite_differences():
    """Under vmap a step sees one trajectory and runs Dormand–Prince 8's
    stages unrolled; its gradient (which takes them in a loop) in the
    inertia, for each trajectory, equals central differences."""
    scene = FreeRigidBody()
    method = scene.method(pk.dormand_prince_8, pk.Cayley())
    y0 = _batch_state(3)

    def projection(y, inertia):
        final = pk.integrate(method, scene, y, 0.0, 0.1, 20, inertia, save_every=20).ys.fiber[-1]
        return jnp.sum(final * jnp.array([0.2, -0.5, 1.0]))

    inertia = jnp.asarray(INERTIA)
    # One program: the gradients, and the values for the central differences.
    values_and_grads = jax.jit(jax.vmap(jax.value_and_grad(projection, argnums=1), in_axes=(0, None)))
    grads = values_and_grads(y0, inertia)[1]
    step = 1e-6
    fd = central_differences(lambda i: values_and_grads(y0, i)[0], inertia, step)
    np.testing.assert_allclose(grads, fd, rtol=1e-6, atol=1e-8)


def test_vmap_of_diffeqsolve_equals_the_batch_in_the_state():
    top = TOPS["direct product"]
    y0 = _batch_state(8)

    def solve(method, y):
        return diffrax.diffeqsolve(pk.PRKMKTerm(top), pk.PRKMKSolver(method), 0.0, 2.0, 0.1, y, TOP_ARGS).ys

    loop = pk.PRKMK(top.bundle, pk.Cayley(), pk.dormand_prince_8, form="body", explicit_stages="loop")
    vmapped = jax.jit(jax.vmap(lambda y: solve(top.method(pk.dormand_prince_8, pk.Cayley()), y)))(y0)
    in_state = jax.jit(lambda y: solve(loop, y))(y0)
    assert max_leaf_difference(jax.tree.map(lambda a: a[:, -1], vmapped), jax.tree.map(lambda a: a[-1], in_state)) < 1e-13


@pytest.mark.parametrize("tab", pk.tableaus.EXPLICIT_TABLEAUS, ids=lambda t: t.name)
def test_explicit_tableaus_need_no_iteration(tab):
    field = rigid_body_field(pk.Cotangent(pk.SO3), "body")
    method = pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), tab, form="body")
    step = method.step(field, 0.0, initial_state(pk.Cotangent(pk.SO3)), 0.1, jnp.asarray(INERTIA))
    result, iterations = step.result, step.iterations
    assert result == pk.RESULTS.successful and int(iterations) == 0
