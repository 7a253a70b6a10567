"""The forced rigid body: a non-autonomous field whose energy follows the
work done by the torque. Checked against the bundle's own flow, a DOP853
reference that integrates the work alongside, and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import prkmk_jax as pk
from helpers import assert_embedding_field_is, final_state_by_steps
from prkmk_jax.scenes import ForcedParameters, ForcedRigidBody, HarmonicTorque, random_rotation

BODY = ForcedRigidBody()
ARGS = ForcedParameters(
    jnp.array([0.875, 0.625, 0.25]),
    HarmonicTorque(jnp.array([0.3, -0.2, 0.1]), jnp.array([1.0, 2.0, 0.5]), jnp.array([0.0, 0.5, 1.0])),
)
Y0 = pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(3))), jnp.array([0.25, 0.625, 0.875]))
T_END = 3.0


def _reference_with_work():
    """(Q, Π) at T and the work W(T) = ∫ Ω·τ dt, by DOP853 at 1e-13 on the
    embedding with W as a 13th component."""
    field = jax.jit(BODY.embedding_field)
    power = jax.jit(lambda t, z: BODY.power(t, pk.BundleElement(pk.SO3(z[:9].reshape(3, 3)), z[9:12]), ARGS))

    def rhs(t, z):
        z = jnp.asarray(z)
        return np.append(np.asarray(field(t, z[:12], ARGS)), float(power(t, z)))

    z0 = np.append(np.asarray(BODY.to_embedding(Y0)), 0.0)
    return solve_ivp(rhs, (0.0, T_END), z0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]


REFERENCE = _reference_with_work()


def _energy(z):
    return 0.5 * float(np.sum(z[9:12] ** 2 / np.asarray(ARGS.inertia)))


def test_the_embedding_field_derived_from_the_generator_is_the_equations():
    """Q' = QΩ̂, Π' = Π × Ω + τ(t)."""

    def written_out(t, z, args):
        q, pi = z[:9].reshape(3, 3), z[9:]
        omega = pi / args.inertia
        return jnp.concatenate([(q @ pk.hat(omega)).ravel(), jnp.cross(pi, omega) + BODY.torque_law(t, args.torque)])

    assert_embedding_field_is(written_out, BODY, 0.7, Y0, ARGS)


def test_the_reference_obeys_the_energy_balance():
    """H(T) − H(0) = W(T) along the exact flow: the balance the scene states."""
    assert abs(_energy(REFERENCE) - _energy(np.asarray(BODY.to_embedding(Y0))) - REFERENCE[12]) < 1e-11


@pytest.mark.parametrize(
    "tableau, order", [(pk.symplectic_euler, 1), (pk.stormer_verlet, 2), (pk.lobatto_iiia_iiib4, 4)], ids=["SE", "SV", "Lobatto4"]
)
def test_energy_balance_and_state_at_the_method_order(tableau, order):
    """The state error falls at the method's order, and so does the
    energy-balance error |H(T) − H(0) − W(T)| (at least)."""
    method = BODY.method(tableau)
    steps = np.array([30, 60, 120, 240])
    state_errors, balance_errors = [], []
    h0 = _energy(np.asarray(BODY.to_embedding(Y0)))
    final_state = final_state_by_steps(method, BODY)
    for n in steps:
        y, converged = final_state(Y0, T_END / n, n, ARGS)
        assert converged
        z = np.asarray(BODY.to_embedding(y))
        state_errors.append(np.max(np.abs(z - REFERENCE[:12])))
        balance_errors.append(abs(_energy(z) - h0 - REFERENCE[12]))
    hs = T_END / steps
    state_slope = np.polyfit(np.log(hs), np.log(state_errors), 1)[0]
    balance_slope = np.polyfit(np.log(hs), np.log(balance_errors), 1)[0]
    assert abs(state_slope - order) < 0.3, (state_slope, state_errors)
    # The balance error may fall faster before it settles (Lobatto 4: local
    # slopes 4.7, 4.5, 4.4 on this grid); it must not fall slower.
    assert order - 0.3 < balance_slope < order + 0.8, (balance_slope, balance_errors)


def test_gradient_in_the_torque_law_parameters():
    method = BODY.method(pk.stormer_verlet)

    @jax.jit
    def final_energy(amplitude):
        args = ForcedParameters(ARGS.inertia, HarmonicTorque(amplitude, ARGS.torque.frequency, ARGS.torque.phase))
        ys = pk.integrate(method, BODY, Y0, 0.0, 0.05, 40, args, save_every=40).ys
        return BODY.invariants(jax.tree.map(lambda a: a[-1], ys), args)["energy"]

    amplitude = ARGS.torque.amplitude
    grad = jax.grad(final_energy)(amplitude)
    step = 1e-6
    fd = np.array([(final_energy(amplitude + step * e) - final_energy(amplitude - step * e)) / (2 * step) for e in np.eye(3)])
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-10)
