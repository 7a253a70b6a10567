"""The satellite on T*(SO(3) × ℝ³), on (SO(3) × ℝ³) × ℝ⁶ and on SE(3) × ℝ⁶:
the torque and force derived from the potential against MacCullagh's
torque and differences of the potential, the scene's field against the
equations written out on every model, PRKMK methods and the splittings
reaching their orders against DOP853, the invariants a symplectic method
and the splitting keep, and a gradient through a run against central
differences (the splitting's parts: `test_splitting.py`; bad inputs:
`test_bad_inputs.py`)."""

import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import (
    SATELLITE_ARGS,
    assert_embedding_field_is,
    central_differences,
    gradient_and_central_differences,
    satellite_state,
    scene_order,
)
from prkmk_jax.scenes import Satellite, SatelliteParameters
from prkmk_jax.scenes.satellite import embedding_field, potential, torque_and_force

ARGS = SATELLITE_ARGS


def test_torque_and_force_are_the_potentials():
    y = satellite_state()
    rotation, position = y.base.rotation, y.base.translation
    torque, force = torque_and_force(rotation, position, ARGS)
    distance = jnp.linalg.norm(position)
    body = rotation.T @ position / distance
    np.testing.assert_allclose(torque, 3 * ARGS.mu / distance**3 * jnp.cross(body, ARGS.inertia * body), rtol=1e-12)
    differences = central_differences(lambda r: potential(rotation, r, ARGS), position, 1e-6)
    np.testing.assert_allclose(force, -differences, rtol=1e-8)
    turned = central_differences(lambda e: potential(rotation @ pk.SO3.exp(e).matrix, position, ARGS), jnp.zeros(3), 1e-6)
    np.testing.assert_allclose(torque, -turned, rtol=1e-7, atol=1e-12)


MODELS = [pk.Cotangent(pk.SO3xR3), pk.DirectProduct(pk.SO3xR3), pk.DirectProduct(pk.SE3)]


@pytest.mark.parametrize("bundle", MODELS, ids=["T*G", "G×g", "SE(3)×se(3)"])
def test_the_scene_is_its_equations(bundle):
    """On SE(3) the state holds the body-frame momentum P = Rᵀp and is
    embedded with p = RP: the same equations on the embedding, where R is a
    rotation (off the group, RRᵀp ≠ p and the models part)."""
    scene = Satellite(bundle)
    z = Satellite().to_embedding(satellite_state())
    y0 = scene.from_embedding(z)
    np.testing.assert_allclose(scene.to_embedding(y0), z, rtol=0, atol=1e-15)
    if bundle.base is pk.SE3:
        np.testing.assert_allclose(scene.embedding_field(0.0, z, ARGS), embedding_field(0.0, z, ARGS), rtol=0, atol=1e-13)
    else:
        assert_embedding_field_is(embedding_field, scene, 0.0, y0, ARGS)


@pytest.mark.parametrize(
    "bundle, tableau, coordinates, order",
    [
        (pk.Cotangent(pk.SO3xR3), pk.stormer_verlet, pk.Exp(), 2),
        (pk.Cotangent(pk.SO3xR3), pk.lobatto_iiia_iiib4, pk.Cayley(), 4),
        (pk.DirectProduct(pk.SO3xR3), pk.dormand_prince_8, pk.Cayley(), 8),
        (pk.DirectProduct(pk.SE3), pk.stormer_verlet, pk.Exp(), 2),
        (pk.DirectProduct(pk.SE3), pk.lobatto_iiia_iiib4, pk.Cayley(), 4),
    ],
    ids=["SV T*G", "Lobatto 4 Cayley T*G", "RKMK 8 Cayley G×g", "SV SE(3)", "Lobatto 4 Cayley SE(3)"],
)
def test_methods_reach_their_orders(bundle, tableau, coordinates, order):
    scene = Satellite(bundle)
    y0, t_end = scene.from_embedding(Satellite().to_embedding(satellite_state())), 1.0
    steps = (4, 5, 6, 8) if order == 8 else (10, 20, 40, 80)
    slope, errors = scene_order(scene.method(tableau, coordinates), scene, y0, ARGS, t_end, steps)
    assert abs(slope - order) < 0.2, (slope, errors)


@pytest.mark.parametrize(
    "options, order",
    [({}, 2), ({"free_part": "exact"}, 2), ({"coefficients": pk.kahan_li_6}, 6)],
    ids=["Strang axes", "Strang exact free part", "Kahan–Li 6 axes"],
)
def test_the_splittings_reach_their_orders(options, order):
    scene = Satellite()
    y0, t_end = satellite_state(), 1.0
    steps = (4, 6, 8, 12) if order == 6 else (10, 20, 40, 80)
    slope, errors = scene_order(scene.splitting(**options), scene, y0, ARGS, t_end, steps)
    assert abs(slope - order) < 0.2, (slope, errors)


def test_the_splitting_keeps_the_angular_momentum_to_round_off():
    """Each part of the splitting keeps RΠ + r × p (module docstring of the
    scene), so over 20 orbits (12,566 steps) its error stays at round-off
    (PRKMK's is the method's, `test_stormer_verlet_keeps_the_invariants_small_over_twenty_orbits`),
    and the energy's stays bounded."""
    scene = Satellite()
    ys = pk.integrate(scene.splitting(), scene, satellite_state(), 0.0, 0.01, 12566, ARGS, save_every=61).ys
    invariants = scene.invariants(ys, ARGS)
    momentum = np.asarray(invariants["angular momentum"])
    assert np.max(np.abs(momentum - momentum[0])) < 2e-13 * np.max(np.abs(momentum[0]))
    energy = np.abs(np.asarray(invariants["energy"] - invariants["energy"][0]))
    quarter = len(energy) // 4
    assert np.max(energy) < 1e-4
    assert np.max(energy[-quarter:]) < 2 * np.max(energy[:quarter])


def test_stormer_verlet_keeps_the_invariants_small_over_twenty_orbits():
    """Störmer–Verlet over 20 orbits (12,566 steps): the energy's and the
    total angular momentum's errors stay small, no larger in the last
    quarter of the run than twice the first. (PRKMK on T*(SO(3) × ℝ³) does
    not keep RΠ + r × p: over 10⁵ steps its error grows, slowly;
    `benchmarks/long_time.py --scene satellite`.)"""
    scene = Satellite()
    ys = pk.integrate(scene.method(pk.stormer_verlet), scene, satellite_state(), 0.0, 0.01, 12566, ARGS, save_every=61).ys
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
    y0 = satellite_state()
    method = scene.method(pk.stormer_verlet)

    def loss(parameters):
        args = SatelliteParameters(parameters[:3], parameters[3], parameters[4])
        y = pk.integrate(method, scene, y0, 0.0, 0.05, 40, args, save_every=40).ys
        return jnp.sum(y.base.translation[-1] ** 2) + jnp.sum(y.fiber[-1, :3] * jnp.asarray([0.3, -0.2, 0.9]))

    gradient, differences = gradient_and_central_differences(loss, jnp.asarray([3e-3, 2e-3, 1e-3, 1.0, 1.0]), step=1e-7)
    np.testing.assert_allclose(gradient, differences, rtol=1e-6)
