"""The double pendulum of two rigid bodies on T*SO(3)²: its mass matrix
against the blocks written out, its motion in a plane against the planar
compound double pendulum's Euler–Lagrange equations in angles (written by
hand, solved by DOP853), the implicit PRKMK methods reaching their orders
against DOP853 on the embedding, what a symmetric method keeps over a long
run, and a gradient against central differences (bad inputs:
`test_bad_inputs.py`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import prkmk_jax as pk
from helpers import final_state_by_steps, gradient_and_central_differences, scene_order
from prkmk_jax.scenes import DoublePendulum, PendulumParameters
from prkmk_jax.scenes.double_pendulum import body_momenta, kinetic_energy, mass_matrix

ARGS = PendulumParameters(
    inertia=jnp.array([[0.02, 0.03, 0.01], [0.015, 0.01, 0.02]]),
    mass=jnp.array([1.0, 0.8]),
    centre=jnp.array([[0.05, 0.0, -0.5], [0.0, 0.03, -0.4]]),
    joint=jnp.array([0.02, 0.0, -1.0]),
    gravity=jnp.asarray(9.81),
)
"""Two links about a metre long, their centres of mass a little off the
line of the joints (so that no motion is planar)."""
ON_T_STAR_G = DoublePendulum()
ON_G_TIMES_G = DoublePendulum(pk.DirectProduct(pk.SO3Power))


def _state(angles=((0.6, -0.2, 0.3), (-0.3, 0.7, 0.1)), velocities=((0.5, 1.0, -0.3), (0.2, -1.5, 2.0))):
    rotations = jnp.stack([pk.SO3.exp(jnp.asarray(a)).matrix for a in angles])
    return pk.BundleElement(pk.SO3Power(rotations), body_momenta(rotations, jnp.asarray(velocities), ARGS))


def _about_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_the_mass_matrix_is_the_kinetic_energys_hessian():
    """M, written out as blocks, against the Hessian in Ω of the kinetic
    energy ½Σ(Ω·IΩ + m|ẋ|²) (autodiff of `kinetic_energy`), on a batch."""
    rotations = jnp.stack([_state().base.matrix, _state(((1.0, 0.2, -0.4), (0.3, -0.8, 2.0))).base.matrix])
    hessian = jax.vmap(lambda r: jax.hessian(lambda w: kinetic_energy(r, w.reshape(2, 3), ARGS))(jnp.zeros(6)))(rotations)
    np.testing.assert_allclose(mass_matrix(rotations, ARGS), hessian, rtol=0, atol=1e-14)


def test_a_planar_motion_is_the_compound_double_pendulum():
    """Both bodies turning about the horizontal y axis, the centres of mass
    on the bodies' z axes: the chain is the planar compound double pendulum,
    whose Lagrangian in the angles θₖ (written here from the textbook, not
    from the scene) gives θ(T) through Euler–Lagrange and DOP853. The
    attitudes R_y(θₖ(T)) against RKMK 8 (Cayley) on G×g."""
    args = PendulumParameters(
        ARGS.inertia, ARGS.mass, jnp.array([[0.0, 0.0, -0.5], [0.0, 0.0, -0.4]]), jnp.array([0.0, 0.0, -1.0]), ARGS.gravity
    )
    (i1, i2), (m1, m2), (a1, l1, a2), g = ARGS.inertia[:, 1], ARGS.mass, (0.5, 1.0, 0.4), 9.81

    def lagrangian(q, qd):
        kinetic = 0.5 * (i1 + m1 * a1**2 + m2 * l1**2) * qd[0] ** 2 + 0.5 * (i2 + m2 * a2**2) * qd[1] ** 2
        kinetic = kinetic + m2 * l1 * a2 * jnp.cos(q[0] - q[1]) * qd[0] * qd[1]
        return kinetic + g * (m1 * a1 * jnp.cos(q[0]) + m2 * (l1 * jnp.cos(q[0]) + a2 * jnp.cos(q[1])))

    @jax.jit
    def euler_lagrange(t, s):
        q, qd = s[:2], s[2:]
        force = jax.grad(lagrangian, 0)(q, qd) - jax.jacfwd(jax.grad(lagrangian, 1), 0)(q, qd) @ qd
        return jnp.concatenate([qd, jnp.linalg.solve(jax.hessian(lagrangian, 1)(q, qd), force)])

    angles, rates, t_end = np.array([0.8, -0.5]), np.array([0.3, 1.1]), 2.0
    solution = solve_ivp(
        lambda t, s: np.asarray(euler_lagrange(t, s)), (0, t_end), np.concatenate([angles, rates]), "DOP853", rtol=1e-13, atol=1e-13
    )
    rotations = jnp.asarray(np.stack([_about_y(a) for a in angles]))
    y0 = pk.BundleElement(pk.SO3Power(rotations), body_momenta(rotations, jnp.asarray([[0.0, w, 0.0] for w in rates]), args))
    y, converged = final_state_by_steps(ON_G_TIMES_G.method(pk.dormand_prince_8, pk.Cayley()), ON_G_TIMES_G)(y0, t_end / 400, 400, args)
    assert converged
    np.testing.assert_allclose(y.base.matrix, np.stack([_about_y(a) for a in solution.y[:2, -1]]), rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "scene, method, steps, order",
    [
        (ON_T_STAR_G, ON_T_STAR_G.method(pk.stormer_verlet), (50, 100, 200, 400), 2),
        (ON_T_STAR_G, ON_T_STAR_G.method(pk.lobatto_iiia_iiib4, pk.Cayley()), (25, 50, 100, 200), 4),
        (ON_T_STAR_G, ON_T_STAR_G.method(pk.lobatto_iiia_iiib6), (40, 60, 80, 120), 6),
    ],
    ids=["SV", "Lobatto 4 Cayley", "Lobatto 6"],
)
def test_methods_reach_their_orders(scene, method, steps, order):
    """The implicit methods, over T = 0.5 (the links swing and spin at a few
    radians a second), every stage converging. (RKMK 8, explicit, is checked
    at 1e-10 by the planar motion above.)"""
    slope, errors = scene_order(method, scene, _state(), ARGS, 0.5, steps)
    assert abs(slope - order) < 0.2, (slope, errors)


def test_a_symmetric_method_keeps_the_energy_bounded():
    """Symmetrized Störmer–Verlet on T*SO(3)² over 10,000 steps of 0.02, the
    links swinging by a few tenths of a radian: the energy's error stays
    bounded, no larger in the last quarter of the run than 1.5 times the
    first (plain SV on T*G, not symmetric where the fiber moves on its own,
    grows about fourfold here: `docs/concepts/choosing.md`), and the
    vertical momentum's stays small."""
    y0 = _state(((0.1, -0.05, 0.2), (-0.1, 0.1, 0.05)), ((0.1, 0.2, -0.3), (0.1, -0.2, 0.5)))
    method = pk.Symmetrized(ON_T_STAR_G.method(pk.stormer_verlet))
    trajectory = pk.integrate(method, ON_T_STAR_G, y0, 0.0, 0.02, 10_000, ARGS, save_every=50)
    invariants = ON_T_STAR_G.invariants(trajectory.ys, ARGS)
    energy = np.abs(np.asarray(invariants["energy"] - invariants["energy"][0]))[1:].reshape(4, -1)
    assert np.max(energy) < 1e-3
    assert np.max(energy[-1]) < 1.5 * np.max(energy[0]), np.max(energy, axis=1)
    assert np.max(np.abs(np.asarray(invariants["vertical momentum"] - invariants["vertical momentum"][0]))) < 1e-5
    assert np.max(np.asarray(invariants["orthogonality"])) < 1e-13


def test_gradient_in_the_parameters_matches_finite_differences():
    """Through the implicit stages' solves (their implicit-function derivative)."""
    method = ON_T_STAR_G.method(pk.stormer_verlet)

    def loss(parameters):
        args = PendulumParameters(ARGS.inertia, parameters[:2], ARGS.centre, parameters[2:], ARGS.gravity)
        y = pk.integrate(method, ON_T_STAR_G, _state(), 0.0, 0.02, 20, args, save_every=20).ys
        return jnp.sum(y.base.matrix[-1, 1, :, 2] * jnp.asarray([0.3, -0.2, 0.9])) + jnp.sum(y.fiber[-1] ** 2)

    gradient, differences = gradient_and_central_differences(loss, jnp.asarray([1.0, 0.8, 0.02, 0.0, -1.0]), step=1e-6)
    np.testing.assert_allclose(gradient, differences, rtol=1e-6, atol=1e-9)
