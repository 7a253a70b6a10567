"""Run-time checks applied together (`prkmk_jax.checks`): the first failing
message wins, eagerly, under jit and under vmap, and the start of a run
compiles to one error branch."""

import diffrax
import jax
import jax.extend
import jax.numpy as jnp
import pytest

import prkmk_jax as pk
from prkmk_jax.checks import checked, collected_checks
from prkmk_jax.scenes import FreeRigidBody


def _three_checks(x):
    with collected_checks() as checks:
        a = checked(x, x[0] < 0, "first entry negative")
        b = checked(x, x[1] < 0, "second entry negative")
        c = checked(x, x[2] < 0, "third entry negative")
    return checks.applied_to((a, b, c))[0]


@pytest.mark.parametrize("transform", [lambda f: f, jax.jit], ids=["eager", "jit"])
def test_collected_checks_raise_the_first_failing_message(transform):
    run = transform(_three_checks)
    assert jnp.array_equal(run(jnp.array([1.0, 2.0, 3.0])), jnp.array([1.0, 2.0, 3.0]))
    with pytest.raises(Exception, match="second entry negative"):
        jax.block_until_ready(run(jnp.array([1.0, -2.0, -3.0])))
    with pytest.raises(Exception, match="third entry negative"):
        jax.block_until_ready(run(jnp.array([1.0, 2.0, -3.0])))


def test_collected_checks_under_vmap_raise_for_any_member():
    run = jax.jit(jax.vmap(_three_checks))
    good = jnp.ones((4, 3))
    assert jnp.array_equal(run(good), good)
    with pytest.raises(Exception, match="first entry negative"):
        jax.block_until_ready(run(good.at[2, 0].set(-1.0)))


def test_checked_outside_a_collection_is_error_if():
    with pytest.raises(Exception, match="alone"):
        checked(jnp.array(1.0), jnp.array(True), "alone")
    assert checked(jnp.array(1.0), jnp.array(False), "alone") == 1.0


def _error_branches(fn, *args) -> int:
    """Calls to equinox's error branch anywhere in `fn`'s program."""

    def count(jaxpr) -> int:
        here = sum("error_if" in str(eqn.params.get("name", "")) for eqn in jaxpr.eqns)
        return here + sum(count(inner) for inner in jax.extend.core.subjaxprs(jaxpr))

    return count(jax.make_jaxpr(fn)(*args).jaxpr)


def test_the_start_of_a_run_is_one_error_branch():
    """The state (finite, orthogonal, det +1, finite momentum), dt, args and
    the scene's moments are checked in one branch, where each check would be
    a branch of its own; the run's result in one more (`integrate`). A bad
    moment still names itself."""
    scene = FreeRigidBody()
    method = scene.method(pk.stormer_verlet)
    y0 = pk.BundleElement(pk.SO3(jnp.eye(3)), jnp.array([0.2, 0.5, 0.9]))
    inertia = jnp.array([1.0, 2.0, 3.0])

    def run(y0, inertia):
        return pk.integrate(method, scene, y0, 0.0, 0.01, 10, inertia).ys

    def solve(y0, inertia):
        return diffrax.diffeqsolve(pk.PRKMKTerm(scene), pk.PRKMKSolver(method), 0.0, 0.1, 0.01, y0, inertia, throw=False).ys

    assert _error_branches(run, y0, inertia) == 2
    assert _error_branches(solve, y0, inertia) <= 2  # the start's, and one of diffrax's
    with pytest.raises(Exception, match="moment of inertia must be > 0"):
        jax.block_until_ready(jax.jit(run)(y0, inertia.at[1].set(-1.0)))
    with pytest.raises(Exception, match="moment of inertia must be > 0"):
        jax.block_until_ready(jax.jit(solve)(y0, inertia.at[1].set(-1.0)))
    with pytest.raises(Exception, match="not orthogonal"):
        jax.block_until_ready(jax.jit(run)(pk.BundleElement(pk.SO3(2 * jnp.eye(3)), y0.fiber), inertia))
