"""Reversible gradients (`ReversibleGradient`): equal to the gradient through
the stored steps and to finite differences, for every family of methods
that can be undone; closures and vmap (float32: test_float32.py; refusals:
test_bad_inputs.py; the memory against the number of steps:
benchmarks/gradients.py)."""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import FORCED_ARGS, TOP_ARGS, gradient_and_central_differences
from prkmk_jax.methods.adjoint import AbstractMadeOfSteps
from prkmk_jax.scenes import ForcedRigidBody, FreeRigidBody, HeavyTop, random_rotation

FREE, TOP = FreeRigidBody(), HeavyTop()
INERTIA = jnp.array([7 / 8, 5 / 8, 1 / 4])
Y0 = pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(5))), jnp.array([0.25, 0.625, 0.875]))
H = 0.05

METHODS = {  # one of each way a step is undone
    "PRKMK symplectic Euler (undone by its adjoint)": (FREE, FREE.method(pk.symplectic_euler), INERTIA),
    "Adjoint of PRKMK SV (undone by PRKMK)": (FREE, pk.Adjoint(FREE.method(pk.stormer_verlet)), INERTIA),
    "Composition of Symmetrized symplectic Euler": (
        FREE,
        pk.Composition(pk.Symmetrized(FREE.method(pk.symplectic_euler)), pk.yoshida_triple_jump),
        INERTIA,
    ),
    "splitting": (FREE, FREE.splitting(), INERTIA),
    "heavy top, PRKMK SV Cayley": (TOP, TOP.method(pk.stormer_verlet, pk.Cayley()), TOP_ARGS),
}


def _loss(method, field, num_steps, save_every, gradient):
    """A loss of every saved state, differentiable in y0 and the parameters."""

    def loss(y0, args):
        ys = pk.integrate(method, field, y0, 0.0, H, num_steps, args, save_every=save_every, gradient=gradient).ys
        return jnp.sum(ys.fiber**2 * jnp.arange(1.0, 4.0)) + jnp.sum(ys.base.matrix[..., 0, :] * jnp.arange(1.0, 4.0))

    return loss


def _gradients(method, field, args, num_steps=60, save_every=20, gradient=pk.StoredSteps(), y0=Y0):
    return jax.jit(jax.grad(_loss(method, field, num_steps, save_every, gradient), argnums=(0, 1)))(y0, args)


def _relative_gap(a, b) -> float:
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    scale = max(float(jnp.max(jnp.abs(x))) for x in leaves_a)
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(leaves_a, leaves_b)) / scale


@pytest.mark.parametrize("name", METHODS)
def test_reversible_gradient_equals_the_stored_one(name):
    """Reconstructed from each saved state (20 steps back), or for the first
    from checkpoints every 5 steps; checkpoint_every = 7 with save_every = 20
    keeps a state every 5 steps (the largest divisor of save_every below
    it): the same gradient, bit for bit."""
    field, method, args = METHODS[name]
    stored = _gradients(method, field, args)
    reversible = {}
    for checkpoint_every in (5, 7) if name == list(METHODS)[0] else (None,):
        reversible[checkpoint_every] = _gradients(method, field, args, gradient=pk.ReversibleGradient(checkpoint_every))
        assert _relative_gap(stored, reversible[checkpoint_every]) <= 1e-10, (
            checkpoint_every,
            _relative_gap(stored, reversible[checkpoint_every]),
        )
    if 7 in reversible:
        assert _relative_gap(reversible[5], reversible[7]) == 0.0


@pytest.mark.parametrize("name", METHODS)
def test_the_backward_pass_sums_every_prkmk_step_plainly_from_the_guess(name):
    """The methods the backward pass undoes and differentiates with: the
    same, every PRKMK method in them (however nested) with
    compensated_sum=False and start_either_side=False."""
    _, method, _ = METHODS[name]
    plain = method.for_reconstruction()

    def prkmk_parts(m):
        return [m] if isinstance(m, pk.PRKMK) else prkmk_parts(m.method) if isinstance(m, AbstractMadeOfSteps) else []

    originals, plains = prkmk_parts(method), prkmk_parts(plain)
    assert len(plains) == len(originals)
    assert all(p.compensated_sum is False and p.start_either_side is False for p in plains)
    assert all(
        eqx.tree_equal(dataclasses.replace(o, compensated_sum=False, start_either_side=False), p) is True for o, p in zip(originals, plains)
    )
    assert type(plain) is type(method)
    if not originals:
        assert plain is method


def test_a_reconstruction_off_the_kept_state_raises():
    """The backward pass compares each rebuilt stretch start with the kept
    state. A chaotic heavy top (h = 0.05) rebuilt over 8000 steps is off by
    far more than √ε; over 100 steps it is not. Asked for a gradient of the
    parameters only (the check must not be dropped with the unused y0
    gradient)."""
    method = TOP.splitting()

    def parameter_gradient(checkpoint_every):
        def loss(args):
            y = pk.integrate(method, TOP, Y0, 0.0, 0.05, 8000, args, save_every=8000, gradient=pk.ReversibleGradient(checkpoint_every)).ys
            return jnp.sum(y.fiber[-1] * jnp.arange(1.0, 4.0))

        return jax.block_until_ready(jax.jit(jax.grad(loss))(TOP_ARGS))

    with pytest.raises(Exception, match="max_reconstruction_error"):
        parameter_gradient(None)
    assert np.all(np.isfinite(parameter_gradient(100).inertia))


def test_reversible_gradient_agrees_with_finite_differences():
    """The gradient in the inertia against central differences of the
    forward run (the values of the same program; no derivative enters them)."""
    method = FREE.method(pk.stormer_verlet)
    loss = _loss(method, FREE, 200, 200, pk.ReversibleGradient())
    gradient, finite_differences = gradient_and_central_differences(lambda inertia: loss(Y0, inertia), INERTIA, step=1e-6)
    np.testing.assert_allclose(gradient, finite_differences, rtol=1e-6)


def test_a_closure_over_a_differentiated_parameter_is_differentiated():
    method = pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.stormer_verlet, form="body")

    def loss(inertia, gradient):
        def field(t, y, args):
            return y.fiber / inertia, jnp.zeros(3)

        final = pk.integrate(method, field, Y0, 0.0, H, 60, None, save_every=60, gradient=gradient).ys.fiber[-1]
        return jnp.sum(final**2 * jnp.arange(1.0, 4.0))  # not the Casimir |Π|², whose gradient is 0

    gradient = eqx.filter_jit(jax.grad(loss))
    np.testing.assert_allclose(gradient(INERTIA, pk.ReversibleGradient()), gradient(INERTIA, pk.StoredSteps()), rtol=1e-11)


def test_a_field_module_is_differentiated():
    class Body(eqx.Module):
        inertia: jax.Array

        def __call__(self, t, y, args):
            return y.fiber / self.inertia, jnp.zeros(3)

    method = pk.PRKMK(pk.Cotangent(pk.SO3), pk.Exp(), pk.stormer_verlet, form="body")

    def loss(body, gradient):
        final = pk.integrate(method, body, Y0, 0.0, H, 60, None, save_every=60, gradient=gradient).ys.fiber[-1]
        return jnp.sum(final**2 * jnp.arange(1.0, 4.0))

    gradient = eqx.filter_jit(eqx.filter_grad(loss))
    stored = gradient(Body(INERTIA), pk.StoredSteps()).inertia
    np.testing.assert_allclose(gradient(Body(INERTIA), pk.ReversibleGradient()).inertia, stored, rtol=1e-11)


def test_vmapped_over_initial_states():
    rotations = jnp.asarray(np.stack([random_rotation(k) for k in range(4)]))
    momenta = jnp.array([0.25, 0.625, 0.875]) * (1 + 0.1 * jnp.arange(4.0))[:, None]
    method = FREE.method(pk.stormer_verlet)

    def batch_loss(inertia, gradient):
        def one(q, p):
            return _loss(method, FREE, 60, 30, gradient)(pk.BundleElement(pk.SO3(q), p), inertia)

        return jnp.sum(jax.vmap(one)(rotations, momenta))

    gradient = eqx.filter_jit(jax.grad(batch_loss))
    np.testing.assert_allclose(gradient(INERTIA, pk.ReversibleGradient()), gradient(INERTIA, pk.StoredSteps()), rtol=1e-10)


# --- diffeqsolve: ReversibleAdjoint ------------------------------------------------


def _final_loss(y):
    return jnp.sum(y.fiber**2 * jnp.arange(1.0, 4.0)) + jnp.sum(y.base.matrix[0, :] * jnp.arange(1.0, 4.0))


def _solve_loss(method, field, t1, dt0, adjoint):
    def loss(y0, args):
        sol = diffrax.diffeqsolve(pk.PRKMKTerm(field), pk.PRKMKSolver(method), 0.0, t1, dt0, y0, args, adjoint=adjoint, max_steps=10_000)
        return _final_loss(jax.tree.map(lambda a: a[-1], sol.ys))

    return loss


def _stored_steps_loss(method, field, t1, dt0):
    """`_solve_loss` through `integrate`'s stored steps, on the steps of
    diffrax's `ConstantStepSize`: the first of dt0, the others ending at
    t1·k/n for n = ⌈t1/dt0⌉ (`test_reversible_adjoint_steps_at_diffrax_times`)."""
    n = int(np.ceil(t1 / np.nextafter(dt0, np.inf)))

    def loss(y0, args):
        y = method.step(field, 0.0, y0, dt0, args).y
        y = method.step(field, dt0, y, 2 * t1 / n - dt0, args).y
        ys = pk.integrate(method, field, y, 2 * t1 / n, t1 / n, n - 2, args, save_every=n - 2).ys
        return _final_loss(jax.tree.map(lambda a: a[-1], ys))

    return loss


FORCED = ForcedRigidBody()
SOLVE_CASES = {  # a PRKMK method and a splitting; the methods' own undoing is tested above
    "heavy top, splitting": (TOP, TOP.splitting(), TOP_ARGS),
    "forced body (time-dependent), PRKMK SV": (FORCED, FORCED.method(pk.stormer_verlet), FORCED_ARGS),
}


@pytest.mark.parametrize("name", SOLVE_CASES)
def test_reversible_adjoint_equals_recursive_checkpointing(name):
    """t1 = 1.23 with dt0 = 0.05: diffrax takes 25 steps, the first of 0.05,
    the second shorter, the others of 1.23/25; rebuilt from the last state
    (the splitting) or in stretches of 5 steps (PRKMK): the gradient of the
    same steps stored."""
    field, method, args = SOLVE_CASES[name]
    reference = jax.jit(jax.grad(_stored_steps_loss(method, field, 1.23, 0.05), argnums=(0, 1)))(Y0, args)
    checkpoint_every = None if name == "heavy top, splitting" else 5
    loss = _solve_loss(method, field, 1.23, 0.05, pk.ReversibleAdjoint(checkpoint_every=checkpoint_every))
    assert _relative_gap(reference, jax.jit(jax.grad(loss, argnums=(0, 1)))(Y0, args)) <= 1e-10


def test_reversible_adjoint_checks_the_rebuilt_states():
    """The chaotic heavy top over 8000 steps of 0.05 cannot be rebuilt to √ε
    from its last state, and the error says what to give; over stretches of
    100 steps it can (that the stretches give the stored steps' gradient:
    `test_reversible_adjoint_equals_recursive_checkpointing`)."""
    method = TOP.splitting()

    def gradient(adjoint):
        return jax.block_until_ready(jax.jit(jax.grad(_solve_loss(method, TOP, 400.0, 0.05, adjoint), argnums=1))(Y0, TOP_ARGS))

    with pytest.raises(Exception, match="max_reconstruction_error.*the whole solve.*checkpoint_every"):
        gradient(pk.ReversibleAdjoint(checkpoint_every=None))
    assert np.all(np.isfinite(gradient(pk.ReversibleAdjoint(checkpoint_every=100)).inertia))


@pytest.mark.parametrize("t1, dt0", [(1.23, 0.05), (1.0, 0.1), (0.3, 0.5), (7.0, 0.013)])
def test_reversible_adjoint_steps_at_diffrax_times(t1, dt0):
    """The times the backward pass undoes the steps at are those of diffrax's
    steps (`SaveAt(steps=True)`), to the last bit (the same formula, whose
    product XLA may round either way)."""
    from prkmk_jax._reversible_adjoint import _constant_step_ends

    solver, steps = pk.PRKMKSolver(FREE.splitting()), diffrax.SaveAt(steps=True)
    sol = diffrax.diffeqsolve(pk.PRKMKTerm(FREE), solver, 0.0, t1, dt0, Y0, INERTIA, saveat=steps, max_steps=1000)
    n = int(sol.stats["num_steps"])
    ends = jax.vmap(_constant_step_ends(jnp.asarray(0.0), jnp.asarray(t1), jnp.asarray(dt0)))(jnp.arange(1, n + 1))
    np.testing.assert_allclose(ends, sol.ts[:n], rtol=2.3e-16, atol=0)


def test_forward_mode_runs_through_the_stored_steps():
    """`ReversibleGradient` refuses forward mode (`tests/test_bad_inputs.py`);
    the stored steps give it."""
    loss = _loss(FREE.splitting(), FREE, 10, 10, pk.StoredSteps())
    assert np.isfinite(jax.jvp(lambda a: loss(Y0, a), (INERTIA,), (jnp.ones(3),))[1])
