"""Implicit stages solved to round-off (`PRKMK(iterate_until="round-off")`,
the default): the iteration stops where its increments stop shrinking, so
the stage equations hold as exactly as rounding allows, and a long run's
energy error is rounding, not the stage tolerance."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from prkmk_jax.methods.stage_solve import _fixed_point_iteration
from prkmk_jax.scenes import FreeRigidBody
from prkmk_jax.scenes.rigid_body import PAPER_INERTIA, random_rotation

DOTTIE = 0.739085133215160641655312087673873404013411758900757464965680635773
"""The fixed point of cos (the Dottie number), to 66 digits."""


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_round_off_iteration_reaches_the_fixed_point_to_rounding(dtype):
    """z ← cos z contracts by |sin z*| ≈ 0.67 an iteration. Stopped at the
    tolerance it is off by about the tolerance; iterated to round-off it is
    within a few ulps of the fixed point."""
    eps = float(jnp.finfo(dtype).eps)
    tolerance = 1e-3 if dtype == jnp.float32 else 1e-9

    def solve(until_round_off):
        z, result, n = _fixed_point_iteration(jnp.cos, jnp.asarray(0.0, dtype), tolerance, tolerance, 500, dtype, until_round_off)
        assert result == pk.RESULTS.successful
        return float(z), int(n)

    (z_tol, n_tol), (z_round, n_round) = solve(False), solve(True)
    assert abs(z_tol - DOTTIE) > 10 * eps
    assert abs(z_round - DOTTIE) <= 4 * eps
    assert n_round > n_tol


def test_round_off_iteration_still_reports_a_failure():
    """A map without a contraction (z ← 2z + 1) never meets the tolerance:
    the round-off rule does not turn that into a success. (The count is the
    30 iterations of the loop and the one evaluation after it.)"""
    z, result, n = _fixed_point_iteration(lambda z: 2 * z + 1, jnp.asarray(0.5), 1e-12, 1e-12, 30, jnp.float64, True)
    assert result == pk.RESULTS.nonlinear_max_steps_reached
    assert int(n) == 31


def test_iterate_until_and_the_start_are_checked():
    with pytest.raises(ValueError, match="iterate_until must be 'round-off'"):
        pk.PRKMK(pk.Cotangent(pk.SO3), iterate_until="exact")  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="start_either_side must be True or False"):
        pk.PRKMK(pk.Cotangent(pk.SO3), start_either_side="yes")  # pyright: ignore[reportArgumentType]


def _energy_errors(iterate_until, num_steps, batch=8, h=0.1, coordinates=pk.Exp()):
    """The largest relative energy error over `num_steps` steps of SV on the
    free body, for `batch` random initial states (unit |Π|)."""
    scene = FreeRigidBody()
    method = pk.PRKMK(scene.bundle, coordinates, pk.stormer_verlet, form="body", iterate_until=iterate_until)
    rng = np.random.default_rng(5)
    momenta = rng.normal(size=(batch, 3))
    momenta /= np.linalg.norm(momenta, axis=1, keepdims=True)
    y0 = pk.BundleElement(pk.SO3(jnp.asarray(np.stack([random_rotation(s) for s in range(batch)]))), jnp.asarray(momenta))
    inertia = jnp.asarray(PAPER_INERTIA)
    every = num_steps // 20
    run = jax.jit(jax.vmap(lambda y: pk.integrate(method, scene, y, 0.0, h, num_steps, inertia, save_every=every)))
    trajectory = run(y0)
    assert bool(jnp.all(trajectory.result == pk.RESULTS.successful))
    energy = np.asarray(scene.invariants(trajectory.ys, inertia)["energy"])
    errors = energy / energy[:, :1] - 1
    return np.max(np.abs(errors), axis=1)


def test_energy_error_over_a_long_run_is_rounding_not_the_tolerance():
    """Störmer–Verlet keeps the free body's energy exactly in exact
    arithmetic (its error is rounding alone, whatever h). Over 10⁵ steps
    from 8 random states, with the stages stopped at the default tolerance
    1e-12 the energy drifts by about 1e-10, a bias of the tolerance; solved
    to round-off it stays within 5e-13, with exp and with Cayley coordinates:
    a random walk of 10⁵ roundings of ~1e-16 is ~3e-14, and a bias of one
    ulp a step would reach 2e-11. (How the error grows with N, fitted up to
    10⁷ steps, is `benchmarks/round_off.py`'s table.)"""
    by_tolerance = _energy_errors("tolerance", 100_000)
    assert np.median(by_tolerance) > 1e-11
    for coordinates in (pk.Exp(), pk.Cayley()):
        assert np.max(_energy_errors("round-off", 100_000, coordinates=coordinates)) < 5e-13
