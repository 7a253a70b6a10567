"""PRKMK inside diffrax.diffeqsolve: on-group dense output and its order,
adjoints, batches and errors (its steps are integrate's: test_drivers.py)."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, gradient_and_central_differences, initial_state, max_leaf_difference, reference, rigid_body_field, state_vector

COTANGENT = pk.Cotangent(pk.SO3)
FIELD = rigid_body_field(COTANGENT, "body")
TERM = pk.PRKMKTerm(FIELD)


def _method(tab=pk.stormer_verlet, **kw):
    return pk.PRKMK(COTANGENT, pk.Exp(), tab, form="body", **kw)


def _solve(method, t1, dt, y0, args=jnp.asarray(INERTIA), **kw):
    return diffrax.diffeqsolve(TERM, pk.PRKMKSolver(method), 0.0, t1, dt, y0, args, **kw)


def test_non_autonomous_field_and_step_to():
    def forced(t, y, args):
        return y.fiber.value, -jnp.sin(y.base.value) + args * jnp.cos(2 * t)

    method = pk.PRKMK(pk.Cartesian(pk.VectorSpace), pk.Exp(), pk.lobatto_iiia_iiib4)
    y0 = pk.BundleElement(pk.VectorSpace(jnp.array([1.0])), pk.VectorSpace(jnp.array([0.2])))
    ts = jnp.linspace(0.4, 1.4, 11)
    sol = diffrax.diffeqsolve(pk.PRKMKTerm(forced), pk.PRKMKSolver(method), 0.4, 1.4, None, y0, 0.3, stepsize_controller=diffrax.StepTo(ts))
    traj = pk.integrate(method, forced, y0, 0.4, 0.1, 10, 0.3)
    np.testing.assert_allclose(sol.ys.base.value[-1], traj.ys.base.value[-1], atol=1e-13)


@pytest.mark.parametrize("tab,dense_order", [(pk.stormer_verlet, 2), (pk.lobatto_iiia_iiib4, 3)], ids=["SV", "lobatto"])
def test_dense_output_is_on_the_group_and_converges(tab, dense_order):
    y0 = initial_state(COTANGENT)
    ts = jnp.array([0.37, 0.61, 0.83, 0.97])  # never step points below
    ref = reference(COTANGENT, y0, float(ts[-1]), t_eval=np.asarray(ts))
    method = _method(tab)
    run = jax.jit(lambda dt: _solve(method, 1.0, dt, y0, saveat=diffrax.SaveAt(ts=ts), max_steps=4096))
    hs = np.array([0.1, 0.05, 0.025, 0.0125])
    errs = []
    for h in hs:
        sol = run(h)
        q = np.asarray(sol.ys.base.matrix)
        assert np.abs(np.einsum("tji,tjk->tik", q, q) - np.eye(3)).max() <= 1e-13
        errs.append(np.abs(state_vector(COTANGENT, sol.ys) - ref).max())
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    assert slope >= dense_order - 0.15, (slope, errs)


def test_dense_solution_evaluate_and_backward_solve():
    y0 = initial_state(COTANGENT)
    method = _method(pk.lobatto_iiia_iiib4)
    sol = _solve(method, 1.0, 0.05, y0, saveat=diffrax.SaveAt(dense=True, t1=True))
    mid = sol.evaluate(0.4321)
    assert isinstance(mid, pk.BundleElement)
    q = np.asarray(mid.base.matrix)
    assert np.abs(q.T @ q - np.eye(3)).max() <= 1e-13
    with pytest.raises(TypeError, match="BundleElement"):  # y(t1) − y(t0) has no meaning on a group
        sol.evaluate(0.1, 0.2)
    # backward in time from y(1) returns to y(0)
    y1 = jax.tree.map(lambda a: a[-1], sol.ys)
    back = diffrax.diffeqsolve(
        TERM, pk.PRKMKSolver(method), 1.0, 0.0, -0.05, y1, jnp.asarray(INERTIA), saveat=diffrax.SaveAt(ts=jnp.array([0.5, 0.0]))
    )
    np.testing.assert_allclose(back.ys.fiber[-1], y0.fiber, atol=1e-7)
    np.testing.assert_allclose(back.ys.base.matrix[-1], y0.base.matrix, atol=1e-7)
    np.testing.assert_allclose(back.ys.fiber[0], sol.evaluate(0.5).fiber, atol=1e-6)


def test_gradients_of_each_adjoint_match_finite_differences():
    """diffrax's RecursiveCheckpointAdjoint, DirectAdjoint and ForwardMode,
    against central differences of the solve (through dense output)."""
    y0 = initial_state(COTANGENT)
    method = _method(pk.stormer_verlet)
    target = jnp.array([0.3, -0.2, 0.9])

    def loss(inertia, adjoint=diffrax.RecursiveCheckpointAdjoint()):
        sol = _solve(method, 1.0, 0.05, y0, inertia, saveat=diffrax.SaveAt(ts=jnp.array([0.33, 0.75, 1.0])), adjoint=adjoint, max_steps=32)
        return jnp.sum((sol.ys.base.matrix[:, :, 2] - target) ** 2)

    inertia = jnp.asarray(INERTIA)
    checkpointed, fd = gradient_and_central_differences(loss, inertia)
    direct = jax.jit(jax.grad(lambda i: loss(i, diffrax.DirectAdjoint())))(inertia)
    forward = jax.jit(jax.jacfwd(lambda i: loss(i, diffrax.ForwardMode())))(inertia)
    for grad in (checkpointed, direct, forward):
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_gradient_with_integer_args_and_backward_in_time():
    """The implicit stages close over `args`; an integer array among them
    (here an exponent) must be carried through the stages' derivative rule
    like any other input, forwards and backwards in time."""
    y0 = initial_state(COTANGENT)
    method = _method(pk.stormer_verlet)

    def field(t, y, args):
        inertia, power = args
        return (y.fiber / inertia**power, jnp.zeros(3))

    def loss(inertia, t1):
        sol = diffrax.diffeqsolve(
            pk.PRKMKTerm(field), pk.PRKMKSolver(method), 0.0, t1, 0.05 * jnp.sign(t1), y0, (inertia, jnp.array(1)), max_steps=16
        )
        return jnp.sum(sol.ys.fiber[-1] * jnp.array([0.3, -0.2, 0.9]))

    for t1 in (jnp.asarray(0.5), jnp.asarray(-0.5)):  # traced: one program both ways
        grad, fd = gradient_and_central_differences(loss, jnp.asarray(INERTIA), t1, step=1e-6)
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-10)


def test_backsolve_adjoint_refused():
    y0 = initial_state(COTANGENT)

    def loss(inertia):
        return jnp.sum(_solve(_method(), 0.2, 0.05, y0, inertia, adjoint=diffrax.BacksolveAdjoint(), max_steps=8).ys.fiber)

    # The forward solve is the plain solve; the gradient is refused by name.
    np.testing.assert_allclose(loss(jnp.asarray(INERTIA)), jnp.sum(_solve(_method(), 0.2, 0.05, y0, jnp.asarray(INERTIA)).ys.fiber))
    with pytest.raises(NotImplementedError, match="BacksolveAdjoint"):
        jax.grad(loss)(jnp.asarray(INERTIA))


def test_vmap_over_initial_conditions():
    ys = [initial_state(COTANGENT, seed=s) for s in range(3)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *ys)
    method = _method()
    run = jax.jit(jax.vmap(lambda y: _solve(method, 0.5, 0.05, y).ys))
    out = run(batch)
    for i, y in enumerate(ys):
        np.testing.assert_allclose(out.fiber[i], _solve(method, 0.5, 0.05, y).ys.fiber, atol=1e-14)


def test_a_batch_in_the_state_is_one_solve():
    """A state with a leading batch axis runs as one solve (the faster route
    for fixed steps through diffeqsolve, see PRKMKSolver), when the field
    broadcasts over that axis as the free-body scene does: each trajectory
    agrees with its own solve to the stage tolerance, the stages iterate
    until every trajectory has converged, and a stage that fails for one
    trajectory fails the solve, where under vmap only that trajectory fails."""
    scene = pk.scenes.FreeRigidBody()
    method = scene.method(pk.stormer_verlet, max_iterations=20)
    inertia = jnp.asarray(INERTIA)
    ys = [initial_state(COTANGENT, seed=s) for s in range(4)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *ys)

    def solve(y0, **kw):
        return diffrax.diffeqsolve(pk.PRKMKTerm(scene), pk.PRKMKSolver(method), 0.0, 0.5, 0.05, y0, inertia, **kw)

    def run(y0):
        return pk.integrate(method, scene, y0, 0.0, 0.05, 10, inertia)

    def batch_first(ys):
        return jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), ys)

    together = solve(batch)
    assert together.ys.fiber.shape == (1, 4, 3)
    assert max_leaf_difference(together.ys, batch_first(jax.vmap(solve)(batch).ys)) <= 1e-12
    one, each = run(batch), jax.vmap(run)(batch)
    assert max_leaf_difference(one.ys, batch_first(each.ys)) <= 1e-12
    assert int(one.stats["num_iterations"]) >= int(jnp.max(each.stats["num_iterations"]))

    # A spin 2000× faster: h|Ω| ≈ 100, where the fixed-point stage cannot converge.
    spun = eqx.tree_at(lambda y: y.fiber, batch, batch.fiber.at[3].multiply(2000.0))
    assert solve(spun, throw=False).result == diffrax.RESULTS.nonlinear_max_steps_reached
    apart = jax.vmap(lambda y: solve(y, throw=False).result)(spun)
    assert np.asarray(apart == diffrax.RESULTS.successful).tolist() == [True, True, True, False]


def test_errors():
    y0 = initial_state(COTANGENT)
    method = _method()
    with pytest.raises(TypeError, match="PRKMKTerm"):
        diffrax.diffeqsolve(diffrax.ODETerm(lambda t, y, args: y), pk.PRKMKSolver(method), 0.0, 1.0, 0.1, y0, jnp.asarray(INERTIA))
    with pytest.raises(TypeError, match="SO3 fiber"):
        diffrax.diffeqsolve(TERM, pk.PRKMKSolver(pk.PRKMK(pk.Cartesian(pk.SO3))), 0.0, 1.0, 0.1, y0, jnp.asarray(INERTIA))
    with pytest.raises(TypeError, match="BundleElement"):
        diffrax.diffeqsolve(TERM, pk.PRKMKSolver(method), 0.0, 1.0, 0.1, (y0.base, y0.fiber), jnp.asarray(INERTIA))
    with pytest.raises(TypeError, match="wraps a PRKMK"):
        pk.PRKMKSolver(diffrax.Tsit5())


def test_failed_implicit_stage_is_a_result():
    bundle = pk.Cartesian(pk.SO3)
    method = pk.PRKMK(bundle, pk.Exp(), pk.symplectic_euler, form="body", max_iterations=20)
    y0 = initial_state(bundle)
    term = pk.PRKMKTerm(rigid_body_field(bundle, "body"))
    sol = diffrax.diffeqsolve(term, pk.PRKMKSolver(method), 0.0, 3.0, 1.0, y0, jnp.asarray(INERTIA), throw=False)
    assert sol.result == diffrax.RESULTS.nonlinear_max_steps_reached
    with pytest.raises(Exception, match="nonlinear solver"):
        diffrax.diffeqsolve(term, pk.PRKMKSolver(method), 0.0, 3.0, 1.0, y0, jnp.asarray(INERTIA))


def test_progress_meter(capsys):
    y0 = initial_state(COTANGENT)
    sol = _solve(_method(), 1.0, 0.1, y0, progress_meter=diffrax.TextProgressMeter(minimum_increase=0.5))
    assert sol.result == diffrax.RESULTS.successful
    assert "100.00%" in capsys.readouterr().out


def test_pid_controller_reaches_the_tolerance():
    """Step-doubling estimate with the order-4 Lobatto pair: the global error
    at T = 10 stays within 10× rtol (measured 6.7×, 8.4×, 3.5×)."""
    y0 = initial_state(COTANGENT)
    ref = reference(COTANGENT, y0, 10.0)
    solver = pk.PRKMKSolver(_method(pk.lobatto_iiia_iiib4), adaptive=True)
    run = jax.jit(
        lambda rtol: diffrax.diffeqsolve(
            TERM,
            solver,
            0.0,
            10.0,
            0.01,
            y0,
            jnp.asarray(INERTIA),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            max_steps=4096,
        )
    )
    steps = []
    for rtol in (1e-4, 1e-6, 1e-8):
        sol = run(rtol)
        err = np.abs(state_vector(COTANGENT, jax.tree.map(lambda a: a[-1], sol.ys)) - ref).max()
        assert err <= 10 * rtol, (rtol, err)
        q = np.asarray(sol.ys.base.matrix[-1])
        assert np.abs(q.T @ q - np.eye(3)).max() <= 1e-13
        steps.append(int(sol.stats["num_accepted_steps"]))
    assert steps[0] < steps[1] < steps[2]
    assert solver.error_order(TERM) == 5 and pk.PRKMKSolver(_method()).error_order(TERM) is None
