"""Compensated summation of the steps' updates: each step's change of the
state is computed with the state kept out of it (`apply_change`), added to
the state, and what the sum loses to rounding is carried on by the drivers
(`compensated`), so that the state's rounding error grows with that of the
changes, not with that of the state."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_groups import BUNDLES, bundle_algebra

import prkmk_jax as pk
from helpers import max_leaf_difference
from prkmk_jax._exact_sums import two_sum
from prkmk_jax.methods.base import compensated
from prkmk_jax.scenes import FreeRigidBody
from prkmk_jax.scenes.rigid_body import PAPER_INERTIA, random_rotation

COORDINATES = {"exp": pk.Exp(truncation=None), "cayley": pk.Cayley(truncation=None)}
EPS32 = float(jnp.finfo(jnp.float32).eps)


def _cast(tree, dtype):
    return jax.tree.map(lambda a: jnp.asarray(a, dtype), tree)


def _element_and_increment(bundle, coords, seed, scale):
    rng = np.random.default_rng(seed)
    y = bundle.map(coords, bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6)))
    U = bundle_algebra(bundle, scale * rng.normal(size=6), scale * rng.normal(size=6))
    return y, U


@pytest.mark.parametrize("fiber_increment", [True, False], ids=["with-fiber", "fiber-None"])
@pytest.mark.parametrize("form", ["body", "space"])
@pytest.mark.parametrize("coords_name", COORDINATES)
@pytest.mark.parametrize("name", BUNDLES)
def test_change_is_rounded_relative_to_the_change(name, coords_name, form, fiber_increment):
    """In float32, against the float64 product minus the state: the change
    is accurate to a few float32 ulps of the change itself. The product
    computed first and the state subtracted after is off by ulps of the
    state, 10–160 times more for a step of 1e-2."""
    bundle, coords = BUNDLES[name], COORDINATES[coords_name]
    for seed in range(3):
        y, U = _element_and_increment(bundle, coords, seed, 1e-2)
        if not fiber_increment:
            U = (U[0], None)
        y32, U32 = _cast(y, jnp.float32), _cast(U, jnp.float32)
        y64, U64 = _cast(y32, jnp.float64), _cast(U32, jnp.float64)
        change = bundle.apply_change(coords, U32, y32, form)
        exact = jax.tree.map(jnp.subtract, bundle.apply(coords, U64, y64, form), y64)
        scale = max(float(jnp.max(jnp.abs(leaf))) for leaf in jax.tree.leaves(exact))
        assert jax.tree.structure(change) == jax.tree.structure(y32)
        assert max_leaf_difference(_cast(change, jnp.float64), exact) <= 6 * EPS32 * scale


@pytest.mark.parametrize("scale", [1e-9, 0.3, 1.5])
@pytest.mark.parametrize("form", ["body", "space"])
@pytest.mark.parametrize("coords_name", COORDINATES)
@pytest.mark.parametrize("name", BUNDLES)
def test_change_is_the_product_minus_the_state(name, coords_name, form, scale):
    """y + change = f(U)⊙y to float64 rounding of the state, for small and
    large increments (SO(n)'s series and closed branch of exp(u) − I)."""
    bundle, coords = BUNDLES[name], COORDINATES[coords_name]
    y, U = _element_and_increment(bundle, coords, 4, scale)
    moved = jax.tree.map(jnp.add, y, bundle.apply_change(coords, U, y, form))
    assert max_leaf_difference(moved, bundle.apply(coords, U, y, form)) < 1e-14


def _exact(x) -> list[Fraction]:
    return [Fraction(float(v)) for v in np.ravel(np.asarray(x, np.float64))]


def test_two_sum_is_exact_whatever_the_magnitudes():
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.normal(size=200) * 10.0 ** rng.integers(-20, 20, 200))
    b = jnp.asarray(rng.normal(size=200) * 10.0 ** rng.integers(-20, 20, 200))
    s, e = jax.jit(two_sum)(a, b)
    for ai, bi, si, ei in zip(_exact(a), _exact(b), _exact(s), _exact(e)):
        assert ai + bi == si + ei
    assert np.all(np.asarray(s) == np.asarray(a + b))


def test_compensated_keeps_what_the_sum_loses():
    """y' + c' = y + fl(rounding + compensation) exactly, and y' is the
    rounded sum."""
    rng = np.random.default_rng(1)
    y = pk.BundleElement(pk.SO3(jnp.asarray(rng.normal(size=(3, 3)))), jnp.asarray(rng.normal(size=3)))
    small = [jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape) * 1e-16), y) for _ in range(2)]
    y_next, lost = jax.jit(compensated)(y, *small)
    total = jax.tree.map(jnp.add, *small)
    for leaf_y, leaf_total, leaf_next, leaf_lost in zip(*(jax.tree.leaves(t) for t in (y, total, y_next, lost))):
        for a, b, c, d in zip(_exact(leaf_y), _exact(leaf_total), _exact(leaf_next), _exact(leaf_lost)):
            assert a + b == c + d
        assert np.all(np.asarray(leaf_next) == np.asarray(leaf_y + leaf_total))


def _free_body_runs(num_steps=20_000, batch=16, h=0.1, every=1000):
    """SV exp on the free body from `batch` random initial states (unit |Π|)."""
    scene = FreeRigidBody()
    rng = np.random.default_rng(3)
    momenta = rng.normal(size=(batch, 3))
    momenta /= np.linalg.norm(momenta, axis=1, keepdims=True)
    y0 = pk.BundleElement(pk.SO3(jnp.asarray(np.stack([random_rotation(s) for s in range(batch)]))), jnp.asarray(momenta))
    inertia = jnp.asarray(PAPER_INERTIA)

    def run(method):
        return jax.jit(jax.vmap(lambda y: pk.integrate(method, scene, y, 0.0, h, num_steps, inertia, save_every=every)))(y0)

    return scene, inertia, y0, run


def test_compensation_shrinks_a_long_runs_rounding_error():
    """SV keeps the free body's energy exactly in exact arithmetic, so its
    energy error is rounding alone. Over 2·10⁴ steps from 16 random states,
    with the updates' roundings carried on the median of the largest errors
    is several times smaller than with the product taken as it is
    (`compensated_sum=False`)."""
    scene, inertia, _, run = _free_body_runs()

    def median_error(compensated_sum):
        trajectory = run(scene.method(pk.stormer_verlet, compensated_sum=compensated_sum))
        energy = np.asarray(scene.invariants(trajectory.ys, inertia)["energy"])
        return np.median(np.max(np.abs(energy / energy[:, :1] - 1), axis=1))

    with_compensation, without = median_error(True), median_error(False)
    assert with_compensation * 4 < without
    assert with_compensation < 1e-14


def test_a_loop_of_steps_summed_with_compensated_is_integrate():
    """`compensated` as its docstring shows, in a loop of `step`: the same
    states as `integrate`, bit for bit, and the same compensation as the
    continuation's."""
    scene, inertia, y0, run = _free_body_runs(num_steps=300, batch=4, every=300)
    method = scene.method(pk.stormer_verlet)
    trajectory = run(method)

    def by_hand(y):
        def one_step(carry, n):
            y, lost, carried = carry
            step = method.step(scene, n * 0.1, y, 0.1, inertia, carried)
            y, lost = pk.compensated(step.y, step.rounding, lost)
            return (y, lost, step.carried), None

        start = (y, jax.tree.map(jnp.zeros_like, y), method.initial_carried(scene, 0.0, y, inertia))
        (y, lost, _), _ = jax.lax.scan(one_step, start, jnp.arange(300))
        return y, lost

    y_last, lost = jax.jit(jax.vmap(by_hand))(y0)
    assert max_leaf_difference(y_last, trajectory.continuation.y) == 0.0
    assert max_leaf_difference(lost, trajectory.continuation.compensation) == 0.0
    assert max(float(jnp.max(jnp.abs(leaf))) for leaf in jax.tree.leaves(lost)) > 0.0


def test_without_compensation_a_step_hands_on_no_rounding():
    scene = FreeRigidBody()
    y = pk.BundleElement(pk.SO3(jnp.eye(3)), jnp.array([0.3, -0.2, 0.9]))
    step = scene.method(pk.stormer_verlet, compensated_sum=False).step(scene, 0.0, y, 0.1, jnp.asarray(PAPER_INERTIA))
    assert step.rounding is None
    assert scene.splitting().step(scene, 0.0, y, 0.1, jnp.asarray(PAPER_INERTIA)).rounding is None
    plain = scene.method(pk.stormer_verlet, compensated_sum=False)
    for made_of_steps in (pk.Symmetrized(plain), pk.Composition(pk.Symmetrized(plain), pk.triple_jump(2))):
        assert made_of_steps.step(scene, 0.0, y, 0.1, jnp.asarray(PAPER_INERTIA)).rounding is None
    summed = pk.Composition(pk.Symmetrized(scene.method(pk.stormer_verlet)), pk.triple_jump(2))
    assert summed.step(scene, 0.0, y, 0.1, jnp.asarray(PAPER_INERTIA)).rounding is not None
    with pytest.raises(TypeError, match="compensated_sum must be True or False"):
        pk.PRKMK(pk.Cotangent(pk.SO3), compensated_sum=1)  # pyright: ignore[reportArgumentType]
