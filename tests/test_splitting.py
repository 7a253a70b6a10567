"""Exact-flow splitting methods: the parts against the fields and the bundle
group's own exponential, empirical orders against DOP853, symmetry, what
they keep over long runs, gradients and batches (float32: test_float32.py; refusals: test_bad_inputs.py)."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import (
    FORCED_ARGS,
    SATELLITE_ARGS,
    TOP_ARGS,
    bjorck_step,
    compiled_value_and_grad,
    gradient_and_central_differences,
    max_leaf_difference,
    satellite_state,
)
from prkmk_jax.exact_flows import rotated_array, rotated_rows, turn_of, turned_rows
from prkmk_jax.groups import sincos
from prkmk_jax.scenes import (
    ForcedRigidBody,
    FreeRigidBody,
    HeavyTop,
    Satellite,
    SymmetricRigidBody,
    TopParameters,
    random_rotation,
    symmetric_initial_state,
)

INERTIA = jnp.array([7 / 8, 5 / 8, 1 / 4])
MOMENTUM = jnp.array([0.25, 0.625, 0.875])
FREE = FreeRigidBody()
TOP = HeavyTop()
FORCED = ForcedRigidBody()
SYMMETRIC = SymmetricRigidBody()


def _state(seed, momentum=MOMENTUM):
    return pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(seed))), jnp.asarray(momentum))


CASES = {  # name: (scene, y0, args)
    "free body": (FREE, _state(0), INERTIA),
    "heavy top": (TOP, _state(5, [0.3, -0.4, 1.5]), TOP_ARGS),
    "forced body": (FORCED, _state(1), FORCED_ARGS),
    "symmetric body": (SYMMETRIC, symmetric_initial_state(random_rotation(0), np.asarray(MOMENTUM)), INERTIA),
    "free body on G×g": (FreeRigidBody(pk.DirectProduct(pk.SO3)), _state(2), INERTIA),
    "satellite": (Satellite(), satellite_state(), SATELLITE_ARGS),
}


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_sincos_against_numpy_and_its_derivative(dtype):
    eps = float(jnp.finfo(dtype).eps)
    limit = 1e5 if dtype == jnp.float64 else 1e3
    rng = np.random.default_rng(0)
    angles = np.concatenate([rng.uniform(-1, 1, 2000), rng.uniform(-limit, limit, 2000), [0.0, np.pi / 4, -np.pi / 2, np.pi]]).astype(dtype)
    sine, cosine = jax.jit(sincos)(jnp.asarray(angles))
    exact = angles.astype(np.float64)
    np.testing.assert_allclose(np.asarray(sine, np.float64), np.sin(exact), rtol=0, atol=4 * eps)
    np.testing.assert_allclose(np.asarray(cosine, np.float64), np.cos(exact), rtol=0, atol=4 * eps)
    derivative = jax.vmap(jax.grad(lambda a: 2 * sincos(a)[0] + sincos(a)[1]))(jnp.asarray(angles[:50]))
    np.testing.assert_allclose(derivative, 2 * np.cos(angles[:50]) - np.sin(angles[:50]), rtol=0, atol=8 * eps)
    # One angle at a time (the library call), and many under vmap (the
    # polynomials): the same values to the same accuracy.
    one = jax.jit(sincos)
    for angle in angles[::400]:
        value = np.asarray(one(jnp.asarray(angle)), np.float64)
        np.testing.assert_allclose(value, (np.sin(float(angle)), np.cos(float(angle))), rtol=0, atol=4 * eps)
    vmapped = np.asarray(jax.vmap(sincos)(jnp.asarray(angles)), np.float64)
    np.testing.assert_allclose(vmapped, (np.sin(exact), np.cos(exact)), rtol=0, atol=4 * eps)


@pytest.mark.parametrize(
    "name, free_part",
    [(name, "axes") for name in ("free body", "heavy top", "forced body", "symmetric body", "satellite")]
    + [("heavy top", "exact"), ("satellite", "exact")],
)
def test_the_parts_add_up_to_the_field(name, free_part):
    """Σ_parts d/dh φ_part(h)(z) at h = 0, through each part's flow, equals
    the scene's embedding field: the split is of the scene's own equations
    (with the kinetic energy in axis terms, or whole)."""
    scene, y0, args = CASES[name]
    z = scene.pack(y0, args)
    t = jnp.asarray(0.7)
    total = jnp.zeros_like(scene.to_embedding(y0))

    def moved(part, h):
        return scene.to_embedding(scene.unpack(part.flow(pk.Exp(), t, z, h, args), y0, args))

    for part in scene.exact_flows(args, free_part=free_part):
        _, velocity = jax.jvp(lambda h, part=part: moved(part, h), (jnp.asarray(0.0),), (jnp.asarray(1.0),))
        total = total + velocity
    np.testing.assert_allclose(total, scene.embedding_field(t, scene.to_embedding(y0), args), atol=1e-14)


@pytest.mark.parametrize("name", ["free body", "heavy top", "symmetric body", "satellite"])
def test_packing_round_trips(name):
    scene, y0, args = CASES[name]
    assert max_leaf_difference(scene.unpack(scene.pack(y0, args), y0, args), y0) == 0


@pytest.mark.parametrize("name", ["free body", "heavy top", "symmetric body", "satellite"])
def test_each_part_is_an_exact_flow(name):
    """φ(a + b) = φ(b)∘φ(a): what the exact flow of an autonomous part does,
    and what merging adjacent sub-steps relies on."""
    scene, y0, args = CASES[name]
    z, t = scene.pack(y0, args), jnp.asarray(0.0)
    for part in scene.exact_flows(args):
        once = part.flow(pk.Exp(), t, z, jnp.asarray(0.7), args)
        twice = part.flow(pk.Exp(), t, part.flow(pk.Exp(), t, z, jnp.asarray(0.3), args), jnp.asarray(0.4), args)
        np.testing.assert_allclose(once, twice, atol=1e-14)


@pytest.mark.parametrize("coordinates", [pk.Exp(), pk.Cayley()], ids=["exp", "cayley"])
def test_an_axis_rotation_is_the_bundle_group_action(coordinates):
    """On T*SO(3) the i-th axis flow is y·f(h(ωᵢeᵢ, 0)) with the bundle's own
    exp or Cayley map (`AbstractCoordinates.apply`). The
    parts turn about the body axes by increasing inertia."""
    y0 = _state(3, [0.4, -1.1, 0.8])
    h = jnp.asarray(0.9)
    by_inertia = np.argsort(np.asarray(INERTIA))
    for part in FREE.exact_flows(INERTIA):
        moved = FREE.unpack(part.flow(coordinates, jnp.asarray(0.0), FREE.pack(y0, INERTIA), h, INERTIA), y0, INERTIA)
        axis = by_inertia[part.axis]
        u = h * y0.fiber[axis] / INERTIA[axis] * jnp.eye(3)[axis]
        expected = FREE.bundle.apply(coordinates, (u, None), y0, "body")
        assert max_leaf_difference(moved, expected) < 1e-15


@pytest.mark.parametrize("angle", [0.3, -1.2, 2.5, -3.1, 40.0])
def test_a_turn_by_shears_is_the_rotation(angle):
    """The three shears and the sign of a turn (`turn_of`, `turned_rows`)
    against the rotation matrix [[c, s], [−s, c]] on the free body's row
    pairs, at angles on both sides of ±π/2 (where the sign flips) and past
    2π; the rows a turn does not move stay as they are."""
    rng = np.random.default_rng(3)
    z = jnp.asarray(rng.normal(size=(12, 5)))
    sine, cosine = jnp.sin(jnp.full(5, angle)), jnp.cos(jnp.full(5, angle))
    for rotation in FREE.exact_flows(INERTIA):
        turned = np.asarray(turned_rows(z, rotation.pairs, turn_of(sine, cosine)))
        expected = np.asarray(rotated_rows(z, rotation.pairs, sine, cosine))
        np.testing.assert_allclose(turned, expected, rtol=0, atol=8 * np.finfo(float).eps * float(jnp.max(jnp.abs(z))))
        unmoved = [r for r in range(12) if r not in {i for pair in rotation.pairs for i in pair}]
        assert np.array_equal(turned[unmoved], np.asarray(z)[unmoved])


SYMMETRY_CASES = {  # the Strang splitting of each scene; the coordinates and the composition do not depend on the scene: one each
    **{f"{name}, Strang": (name, None, pk.Exp()) for name in CASES},
    "heavy top, Strang, Cayley": ("heavy top", None, pk.Cayley()),
    "forced body, Kahan–Li 6": ("forced body", pk.kahan_li_6, pk.Exp()),
}


@pytest.mark.parametrize("case", SYMMETRY_CASES)
def test_symmetric_to_round_off(case):
    name, coefficients, coordinates = SYMMETRY_CASES[case]
    scene, y0, args = CASES[name]
    defect = pk.symmetry_defect(scene.splitting(coefficients, coordinates), scene, y0, 0.2, args, t=0.3)
    assert defect <= 1e-13, defect


def test_free_body_invariants_over_a_long_run():
    """T = 1000: |Π|, the spatial momentum QΠ and QᵀQ to round-off (each
    part keeps them exactly); the energy error stays bounded."""
    for method, h in ((FREE.splitting(), 0.05), (FREE.splitting(pk.kahan_li_6), 0.25)):
        n = int(round(1000 / h))
        ys = pk.integrate(method, FREE, _state(0), 0.0, h, n, INERTIA, save_every=n // 200).ys
        values = FREE.invariants(ys, INERTIA)
        assert np.max(np.abs(values["momentum norm"] - values["momentum norm"][0])) < 1e-13
        assert np.max(np.abs(values["spatial momentum"] - values["spatial momentum"][0])) < 1e-13
        assert np.max(values["orthogonality"]) < 1e-13
        energy_error = np.abs(values["energy"] - values["energy"][0])
        assert energy_error[-50:].max() < 1.5 * energy_error[:50].max() + 1e-14


def test_heavy_top_casimir_over_a_long_run():
    """T = 1000: Γ·Π and QᵀQ to round-off; the energy error bounded."""
    method, h = TOP.splitting(pk.suzuki_5), 0.1
    ys = pk.integrate(method, TOP, CASES["heavy top"][1], 0.0, h, 10000, TOP_ARGS, save_every=50).ys
    values = TOP.invariants(ys, TOP_ARGS)
    assert np.max(np.abs(values["vertical momentum"] - values["vertical momentum"][0])) < 1e-13
    assert np.max(values["orthogonality"]) < 1e-13
    energy_error = np.abs(values["energy"] - values["energy"][0])
    assert energy_error[-50:].max() < 1.5 * energy_error[:50].max() + 1e-14


def _lever_loss(solve):
    def loss(lever):
        args = TopParameters(TOP_ARGS.inertia, lever)
        return jnp.sum(solve(args) * jnp.array([0.2, -0.5, 1.0]))

    return loss


def test_gradients_through_integrate_and_diffeqsolve_match_finite_differences():
    # Strang: a composition's gradient is its Strang steps' (`jax.vjp` of a
    # composed step is checked against the reverse step's VJP below).
    method = TOP.splitting()
    y0 = CASES["heavy top"][1]
    through_integrate = _lever_loss(lambda args: pk.integrate(method, TOP, y0, 0.0, 0.1, 20, args, save_every=20).ys.fiber[-1])
    through_diffeqsolve = _lever_loss(
        lambda args: diffrax.diffeqsolve(pk.PRKMKTerm(TOP), pk.PRKMKSolver(method), 0.0, 2.0, 0.1, y0, args).ys.fiber[-1]
    )
    lever = TOP_ARGS.lever
    for loss in (through_integrate, through_diffeqsolve):
        grad, fd = gradient_and_central_differences(loss, lever, step=1e-6)
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9)
    values = [compiled_value_and_grad(loss)(lever)[0] for loss in (through_integrate, through_diffeqsolve)]
    np.testing.assert_allclose(*values, rtol=1e-14)


def _batch_of(y0, batch, seed):
    """`batch` copies of y0 in the state's leading axis, differing by their
    initial attitude (turned by random rotations from `seed` on)."""
    turns = jnp.asarray(np.stack([random_rotation(seed + k) for k in range(batch)]))
    ys = jax.tree.map(lambda a: jnp.broadcast_to(a, (batch, *a.shape)), y0)
    if isinstance(y0.base, pk.SO3xR3):
        return pk.BundleElement(pk.SO3xR3(turns @ ys.base.rotation, ys.base.translation), ys.fiber)
    return pk.BundleElement(type(y0.base)(turns @ ys.base.matrix), ys.fiber)


@pytest.mark.parametrize("name", ["heavy top", "symmetric body", "free body on G×g"])
def test_a_batch_in_the_state_and_vmap_give_the_single_runs(name):
    """A batch in the state and under vmap: each trajectory as its own run,
    for each way a scene packs its state (a kick, two rotations, the fiber
    of G×g)."""
    batch = 3
    scene, y0, args = CASES[name]
    method = scene.splitting()
    ys = _batch_of(y0, batch, seed=10)

    def final(y):
        return pk.integrate(method, scene, y, 0.0, 0.1, 20, args, save_every=20).ys

    batched = jax.jit(final)(ys)
    mapped = jax.jit(jax.vmap(final))(ys)
    for k in (0, batch - 1):
        single = final(jax.tree.map(lambda a: a[k], ys))
        assert max_leaf_difference(jax.tree.map(lambda a: a[:, k], batched), single) < 1e-13
        assert max_leaf_difference(jax.tree.map(lambda a: a[k], mapped), single) < 1e-13


@pytest.mark.parametrize("name", ["free body", "satellite"])
def test_a_composed_splitting_differentiates_through_a_vmapped_batch(name):
    """A loss summed over a batch mapped with `vmap`, through a composed
    splitting (its step differentiated as its Strang steps in a loop,
    `differentiated_as`) and the driver's stored steps, differentiated in
    reverse mode and in forward mode: the gradient's product with a
    direction is the directional derivative. (The two scenes pack their
    states differently.)"""
    scene, y0, args = CASES[name]
    method = scene.splitting(pk.yoshida_triple_jump)
    ys = _batch_of(y0, 2, seed=10)
    direction = jax.tree.map(lambda a: jnp.cos(jnp.arange(a.size).reshape(a.shape)), ys)

    def loss(ys):
        def one(y):
            y = pk.integrate(method, scene, y, 0.0, 0.05, 3, args, save_every=3).ys
            return sum(jnp.sum(jnp.sin(leaf[-1])) for leaf in jax.tree.leaves(y))

        return jnp.sum(jax.vmap(one)(ys))

    gradient = jax.jit(jax.grad(loss))(ys)
    directional = jax.jit(lambda ys: jax.jvp(loss, (ys,), (direction,))[1])(ys)
    along = sum(jnp.sum(g * d) for g, d in zip(jax.tree.leaves(gradient), jax.tree.leaves(direction)))
    np.testing.assert_allclose(along, directional, rtol=1e-12)


REVERSE_VARIANTS = {  # name: (coefficients, coordinates, free part)
    "Strang": (None, pk.Exp(), "axes"),
    "Cayley": (None, pk.Cayley(), "axes"),
    "triple jump": (pk.yoshida_triple_jump, pk.Exp(), "axes"),
    "triple jump, Cayley": (pk.yoshida_triple_jump, pk.Cayley(), "axes"),  # Cayley's half steps do not merge
    "exact free part": (None, pk.Exp(), "exact"),
}


@pytest.mark.parametrize(
    "name, variant, batch",
    [(name, "Strang", 3) for name in CASES]
    # The coordinates and the composition do not depend on the scene: one each.
    + [("heavy top", "Cayley", 3), ("free body", "triple jump", 1), ("heavy top", "triple jump, Cayley", 1)]
    + [("forced body", "exact free part", 3)],
)
def test_reverse_step_undoes_the_step_and_gives_its_vjp(name, variant, batch):
    """`Splitting.reverse_step` from a step's end: the step's start (to
    round-off) and `jax.vjp` of the step there, for a random cotangent."""
    scene, y0, args = CASES[name]
    coefficients, coordinates, free_part = REVERSE_VARIANTS[variant]
    method = pk.Splitting(scene, coefficients, coordinates, free_part=free_part)
    ys = _batch_of(y0, batch, seed=20)
    t, dt = 0.3, 0.05

    def step(y, a):
        return method.step(scene, t, y, dt, a).y

    leaves, structure = jax.tree.flatten(ys)  # the end state has the start's shapes
    keys = jax.random.split(jax.random.key(0), len(leaves))
    cotangent = jax.tree.unflatten(structure, [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])

    @eqx.filter_jit
    def step_and_vjp(y, a):  # one program
        y1, vjp = eqx.filter_vjp(step, y, a)
        return y1, vjp(cotangent)

    y1, (expected_y, expected_args) = step_and_vjp(ys, args)
    start, cotangent_y, cotangent_args = jax.jit(method.reverse_step)(t, y1, dt, args, cotangent)
    assert max_leaf_difference(start, ys) < 1e-14
    scale = max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves((expected_y, expected_args)))
    assert max_leaf_difference(cotangent_y, expected_y) < 1e-13 * scale
    assert max_leaf_difference(cotangent_args, expected_args) < 1e-13 * scale


@pytest.mark.parametrize("shape", [(12,), (12, 5)], ids=["one", "batch"])
def test_rotated_array_turns_the_rows_as_rotated_rows_does(shape):
    """The reverse step's whole-array rotation against the row-by-row one of
    the forward step, for the free body's rotations about each axis: the
    same values to an ulp."""
    rng = np.random.default_rng(3)
    z = jnp.asarray(rng.normal(size=shape))
    angle = jnp.asarray(rng.normal(size=shape[1:]))
    for rotation in FREE.exact_flows(INERTIA):
        for sine, cosine in ((jnp.sin(angle), jnp.cos(angle)), (-jnp.sin(angle), jnp.cos(angle))):
            by_rows = np.asarray(rotated_rows(z, rotation.pairs, sine, cosine))
            whole = np.asarray(rotated_array(z, rotation.pairs, sine, cosine))
            np.testing.assert_allclose(whole, by_rows, rtol=0, atol=2 * np.finfo(float).eps * float(jnp.max(jnp.abs(z))))
            unmoved = [r for r in range(12) if r not in {i for pair in rotation.pairs for i in pair}]
            assert np.array_equal(whole[unmoved], np.asarray(z)[unmoved])


@pytest.mark.parametrize("name", ["free body", "heavy top", "forced body", "symmetric body", "satellite"])
def test_each_part_declares_whether_it_reads_the_rows_it_moves(name):
    """`reads_unmoved_rows_only` against the rows each flow moves and the rows
    its coefficients depend on (their Jacobian), both ways: a part that
    claims it is right, and one that does not claim it needs not to."""
    scene, y0, args = CASES[name]
    z, t = scene.pack(y0, args), jnp.asarray(0.7)
    for part in scene.exact_flows(args):

        def coefficients(z, part=part):
            return part.coefficients(pk.Exp(), t, z, jnp.asarray(0.3), args)

        moved_rows = np.any(np.asarray(part.moved(z, coefficients(z))) != np.asarray(z), axis=tuple(range(1, z.ndim)))
        jacobians = jax.tree.leaves(jax.jacobian(coefficients)(z))
        read_rows = np.any(np.stack([np.any(np.asarray(j) != 0, axis=tuple(range(j.ndim - z.ndim))) for j in jacobians]), axis=0)
        assert moved_rows.any()
        assert part.reads_unmoved_rows_only == (not np.any(moved_rows & read_rows)), type(part).__name__


def test_reverse_step_refuses_low_precision():
    y32 = jax.tree.map(lambda a: a.astype(jnp.float32), _state(0))
    with pytest.raises(ValueError, match="machine epsilon"):
        FREE.splitting().reverse_step(0.0, y32, 0.1, INERTIA.astype(jnp.float32), y32)


def test_renormalized_rotations_is_a_bjorck_step_on_each_matrix():
    """The row-wise renormalisation against the matrix form (3×3 products),
    on two perturbed rotations per trajectory, and rotations within a few
    ulps of the group left as they are; it commutes with relabelling the
    columns, as the packed states of the splittings have them."""
    from prkmk_jax.exact_flows import renormalized_rotations

    rng = np.random.default_rng(3)
    matrices = np.stack([[random_rotation(7 * b + k) for k in range(2)] for b in range(5)]) + 1e-3 * rng.standard_normal((5, 2, 3, 3))
    packed = jnp.asarray(np.moveaxis(matrices.reshape(5, 18), -1, 0))
    moved = np.moveaxis(np.asarray(renormalized_rotations(packed, (0, 9))), 0, -1).reshape(5, 2, 3, 3)
    expected = np.asarray(bjorck_step(jnp.asarray(matrices)))
    np.testing.assert_allclose(moved, expected, rtol=0, atol=1e-15)
    defect = lambda m: np.max(np.abs(np.swapaxes(m, -1, -2) @ m - np.eye(3)))  # noqa: E731
    assert defect(moved) < 1e-4 < 1e-3 < defect(matrices)
    rotations = np.stack([[random_rotation(7 * b + k) for k in range(2)] for b in range(5)])
    on_the_group = jnp.asarray(np.moveaxis(rotations.reshape(5, 18), -1, 0))
    np.testing.assert_array_equal(renormalized_rotations(on_the_group, (0, 9)), on_the_group)  # within a few ulps: left as it is
    permuted = packed.reshape(2, 3, 3, 5)[:, :, [2, 0, 1]].reshape(18, 5)
    again = np.asarray(renormalized_rotations(permuted, (0, 9))).reshape(2, 3, 3, 5)[:, :, [1, 2, 0]].reshape(18, 5)
    np.testing.assert_allclose(again, np.asarray(renormalized_rotations(packed, (0, 9))), rtol=0, atol=1e-15)


def test_the_wrappers_take_a_splitting():
    """Adjoint of a symmetric method is itself, Symmetrized is two half
    steps, and Composition composes it like any symmetric base."""
    t, h = 0.0, 0.3
    strang = FREE.splitting()

    @jax.jit  # one program for the eight steps
    def steps(y0):
        step = strang.step(FREE, t, y0, h, INERTIA).y
        adjoint = pk.Adjoint(strang).step(FREE, t, y0, h, INERTIA).y
        half = strang.step(FREE, t, strang.step(FREE, t, y0, h / 2, INERTIA).y, h / 2, INERTIA).y
        symmetrized = pk.Symmetrized(strang).step(FREE, t, y0, h, INERTIA).y
        composed = pk.Composition(strang, pk.suzuki_5).step(FREE, t, y0, h, INERTIA).y
        fused = FREE.splitting(pk.suzuki_5).step(FREE, t, y0, h, INERTIA).y
        return step, adjoint, half, symmetrized, composed, fused

    step, adjoint, half, symmetrized, composed, fused = steps(_state(0))
    assert max_leaf_difference(adjoint, step) == 0
    assert max_leaf_difference(symmetrized, half) < 1e-15
    assert max_leaf_difference(composed, fused) < 1e-14


@pytest.mark.parametrize("layout", ["in the state", "vmapped"])
def test_each_rotation_evaluates_its_sine_once(layout):
    """XLA fuses arithmetic into every consumer that reads it, so a sine read
    by the eight rows a rotation turns could be evaluated eight times;
    `computed_once` keeps it to one evaluation per rotation. Counted in the
    compiled step and reverse step of the Strang free body (five rotations)
    by the angle's rounding to a quadrant, which `sincos` does once."""
    method, batch = FREE.splitting(), 64
    ys = _batch_of(_state(0), batch, seed=3)

    def step(y):
        return method.carried_step(FREE, 0.0, y, 0.1, INERTIA, None).y

    def reverse(y):
        return method.reverse_step(0.0, y, 0.1, INERTIA, y)[:2]

    for fn in (step, reverse):
        program = jax.jit(fn if layout == "in the state" else jax.vmap(fn))
        text = program.lower(ys).compile().as_text()
        assert 1 <= text.count("round-nearest-even(") <= 5, fn.__name__
