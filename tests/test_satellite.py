"""The satellite on T*(SO(3) × ℝ³): the torque and force derived from the
potential against MacCullagh's torque and differences of the potential, the
scene's field against the equations written out, PRKMK methods reaching
their orders against DOP853, the invariants a symplectic method keeps, and
a gradient through a run against central differences (bad inputs:
`test_bad_inputs.py`)."""

import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import assert_embedding_field_is, central_differences, final_state_by_steps, gradient_and_central_differences
from prkmk_jax.scenes import Satellite, SatelliteParameters
from prkmk_jax.scenes.satellite import embedding_field, potential, torque_and_force

ARGS = SatelliteParameters(jnp.asarray([3e-3, 2e-3, 1e-3]), jnp.asarray(1.0), jnp.asarray(1.0))
"""A body about a twentieth of its orbit's radius across (nondimensional:
μ = m = 1, |r| ≈ 1, an orbit of period 2π)."""


def _state(bundle_base=pk.SO3xR3):
    attitude = pk.SO3.exp(jnp.asarray([0.4, -0.3, 0.9])).matrix
    base = bundle_base(attitude, jnp.asarray([1.0, 0.1, -0.05]))
    return pk.BundleElement(base, jnp.asarray([5e-4, -1e-3, 2e-3, 0.05, 0.95, 0.1]))


def test_torque_and_force_are_the_potentials():
    y = _state()
    rotation, position = y.base.rotation, y.base.translation
    torque, force = torque_and_force(rotation, position, ARGS)
    distance = jnp.linalg.norm(position)
    body = rotation.T @ position / distance
    np.testing.assert_allclose(torque, 3 * ARGS.mu / distance**3 * jnp.cross(body, ARGS.inertia * body), rtol=1e-12)
    differences = central_differences(lambda r: potential(rotation, r, ARGS), position, 1e-6)
    np.testing.assert_allclose(force, -differences, rtol=1e-8)
    turned = central_differences(lambda e: potential(rotation @ pk.SO3.exp(e).matrix, position, ARGS), jnp.zeros(3), 1e-6)
    np.testing.assert_allclose(torque, -turned, rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize("bundle", [pk.Cotangent(pk.SO3xR3), pk.DirectProduct(pk.SO3xR3)], ids=["T*G", "G×g"])
def test_the_scene_is_its_equations(bundle):
    assert_embedding_field_is(embedding_field, Satellite(bundle), 0.0, _state(), ARGS)


@pytest.mark.parametrize(
    "bundle, tableau, coordinates, order",
    [
        (pk.Cotangent(pk.SO3xR3), pk.stormer_verlet, pk.Exp(), 2),
        (pk.Cotangent(pk.SO3xR3), pk.lobatto_iiia_iiib4, pk.Cayley(), 4),
        (pk.DirectProduct(pk.SO3xR3), pk.dormand_prince_8, pk.Cayley(), 8),
    ],
    ids=["SV T*G", "Lobatto 4 Cayley T*G", "RKMK 8 Cayley G×g"],
)
def test_methods_reach_their_orders(bundle, tableau, coordinates, order):
    scene = Satellite(bundle)
    y0, t_end = _state(), 1.0
    steps = (4, 5, 6, 8) if order == 8 else (10, 20, 40, 80)
    reference = scene.reference_solution(y0, [t_end], ARGS)[-1]
    run = final_state_by_steps(scene.method(tableau, coordinates), scene)
    errors = []
    for n in steps:
        y, converged = run(y0, t_end / n, n, ARGS)
        assert converged
        errors.append(float(np.max(np.abs(np.asarray(scene.to_embedding(y)) - reference))))
    slope = np.polyfit(np.log(t_end / np.asarray(steps)), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.2, (slope, errors)


def test_a_symplectic_method_keeps_the_invariants_bounded():
    """Störmer–Verlet over 20 orbits (12,566 steps): the energy's and the
    total angular momentum's errors stay bounded, no larger in the last
    quarter of the run than in the first. (PRKMK on T*(SO(3) × ℝ³) does
    not keep RΠ + r × p exactly: its error is the method's, bounded.)"""
    scene = Satellite()
    ys = pk.integrate(scene.method(pk.stormer_verlet), scene, _state(), 0.0, 0.01, 12566, ARGS, save_every=61).ys
    invariants = scene.invariants(ys, ARGS)
    energy = np.abs(np.asarray(invariants["energy"] - invariants["energy"][0]))
    momentum = np.asarray(invariants["angular momentum"])
    momentum = np.max(np.abs(momentum - momentum[0]), axis=-1)
    quarter = len(energy) // 4
    for error, bound in ((energy, 1e-4), (momentum, 1e-5)):
        assert np.max(error) < bound
        assert np.max(error[-quarter:]) < 2 * np.max(error[:quarter])


def test_gradient_in_the_parameters_matches_finite_differences():
    scene = Satellite()
    y0 = _state()
    method = scene.method(pk.stormer_verlet)

    def loss(parameters):
        args = SatelliteParameters(parameters[:3], parameters[3], parameters[4])
        y = pk.integrate(method, scene, y0, 0.0, 0.05, 40, args, save_every=40).ys
        return jnp.sum(y.base.translation[-1] ** 2) + jnp.sum(y.fiber[-1, :3] * jnp.asarray([0.3, -0.2, 0.9]))

    gradient, differences = gradient_and_central_differences(loss, jnp.asarray([3e-3, 2e-3, 1e-3, 1.0, 1.0]), step=1e-7)
    np.testing.assert_allclose(gradient, differences, rtol=1e-6)
