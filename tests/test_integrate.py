"""The lax.scan integrator: saving, jit/vmap/grad, long runs, bad input, float32."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, central_differences, gradient_and_central_differences, initial_state, max_leaf_difference, rigid_body_field

COTANGENT = pk.Cotangent(pk.SO3)
FIELD = rigid_body_field(COTANGENT, "body")


def _method(tab=pk.stormer_verlet, coords=pk.Exp(), bundle=COTANGENT, **kw):
    return pk.PRKMK(bundle, coords, tab, form="body", **kw)


def test_saving_and_times():
    y0 = initial_state(COTANGENT)
    traj = pk.integrate(_method(), FIELD, y0, 1.0, 0.01, 300, jnp.asarray(INERTIA), save_every=50)
    assert traj.ts.shape == (7,) and traj.ys.base.matrix.shape == (7, 3, 3) and traj.ys.fiber.shape == (7, 3)
    np.testing.assert_allclose(traj.ts, 1.0 + 0.5 * np.arange(7), atol=1e-14)
    np.testing.assert_array_equal(traj.ys.fiber[0], y0.fiber)
    every = pk.integrate(_method(), FIELD, y0, 1.0, 0.01, 300, jnp.asarray(INERTIA))
    np.testing.assert_allclose(every.ys.fiber[::50], traj.ys.fiber, atol=0)
    assert traj.result == pk.RESULTS.successful
    assert int(traj.stats["num_iterations"]) > 0


@pytest.mark.parametrize("coords", [pk.Exp(), pk.Cayley()], ids=["exp", "cayley"])
def test_stays_on_group_for_1e5_steps(coords):
    bundle = pk.Cartesian(pk.SO3)
    y0 = initial_state(bundle)
    traj = jax.jit(
        lambda y: pk.integrate(
            pk.PRKMK(bundle, coords, pk.symplectic_euler_adjoint, form="body"),
            rigid_body_field(bundle, "body"),
            y,
            0.0,
            0.01,
            100_000,
            jnp.asarray(INERTIA),
            save_every=10_000,
        )
    )(y0)
    for q in (traj.ys.base.matrix, traj.ys.fiber.matrix):
        defect = np.abs(np.einsum("tji,tjk->tik", q, q) - np.eye(3)).max()
        assert defect <= 1e-12, defect


def test_jit_vmap_over_initial_conditions_and_args():
    ys = [initial_state(COTANGENT, seed=s) for s in range(4)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *ys)
    inertias = jnp.asarray(INERTIA) * jnp.array([1.0, 1.1, 0.9, 1.2])[:, None]
    method = _method(pk.lobatto_iiia_iiib4)

    @jax.jit
    def run(y0, inertia):
        return pk.integrate(method, FIELD, y0, 0.0, 0.05, 40, inertia, save_every=10)

    batched = jax.vmap(run)(batch, inertias)
    assert batched.ys.fiber.shape == (4, 5, 3)
    for i in range(4):
        single = run(ys[i], inertias[i])
        np.testing.assert_allclose(batched.ys.fiber[i], single.ys.fiber, atol=1e-14)
        np.testing.assert_allclose(batched.ys.base.matrix[i], single.ys.base.matrix, atol=1e-14)


def test_no_retrace_for_new_data():
    method = _method()

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(y0, inertia, dt):
        return pk.integrate(method, FIELD, y0, 0.0, dt, 20, inertia)

    for seed in range(3):
        run(initial_state(COTANGENT, seed), jnp.asarray(INERTIA) * (1 + seed), jnp.asarray(0.01 * (seed + 1)))


def test_a_plain_call_compiles_once_per_shape():
    """`integrate` called as it is, twice with new values of the same shapes
    (state, parameters, t0, dt), traces the run once: the field is traced
    during the first call only, whether the times are Python floats, ints or
    NumPy scalars. A new number of steps compiles again."""
    method, traces = _method(), []

    def field(t, y, inertia):
        traces.append(None)
        return FIELD(t, y, inertia)

    pk.integrate(method, field, initial_state(COTANGENT, 0), 0.0, 0.01, 20, jnp.asarray(INERTIA))
    first = len(traces)
    assert first > 0
    pk.integrate(method, field, initial_state(COTANGENT, 1), 0.5, 0.02, 20, 2 * jnp.asarray(INERTIA))
    pk.integrate(method, field, initial_state(COTANGENT, 1), 1, np.float64(0.02), 20, jnp.asarray(INERTIA))
    assert len(traces) == first
    pk.integrate(method, field, initial_state(COTANGENT, 1), 0.0, 0.01, 40, jnp.asarray(INERTIA))
    assert len(traces) > first


def test_a_plain_step_compiles_once_per_shape_and_is_the_traced_step():
    """`method.step` and `symmetry_defect` called as they are trace once for
    new values of the same shapes (t and dt as Python numbers too); inside
    `jit` the step is traced into the caller's program and takes the same
    step."""
    method, traces = _method(pk.lobatto_iiia_iiib4), []

    def field(t, y, inertia):
        traces.append(None)
        return FIELD(t, y, inertia)

    first = method.step(field, 0.0, initial_state(COTANGENT, 0), 0.05, jnp.asarray(INERTIA))
    once = len(traces)
    second = method.step(field, 0.3, initial_state(COTANGENT, 1), 0.02, 2 * jnp.asarray(INERTIA))
    assert len(traces) == once and not np.array_equal(first.y.fiber, second.y.fiber)
    inside = jax.jit(lambda y, a: method.step(field, 0.3, y, 0.02, a))(initial_state(COTANGENT, 1), 2 * jnp.asarray(INERTIA))
    assert max_leaf_difference(inside.y, second.y) <= 1e-15
    pk.symmetry_defect(method, field, initial_state(COTANGENT, 0), 0.1, jnp.asarray(INERTIA))
    after_defect = len(traces)
    defect = pk.symmetry_defect(method, field, initial_state(COTANGENT, 1), 0.05, 2 * jnp.asarray(INERTIA))
    assert len(traces) == after_defect and float(defect) > 0


def _loss_fn(method, bundle, field):
    def loss(inertia, y0):
        traj = pk.integrate(method, field, y0, 0.0, 0.05, 40, inertia, save_every=10)
        target = jnp.array([0.3, -0.2, 0.9])
        return jnp.sum((traj.ys.base.matrix[:, :, 2] - target) ** 2)

    return loss


@pytest.mark.parametrize(
    "bundle,tab,coords",
    [
        (pk.Cotangent(pk.SO3), pk.stormer_verlet, pk.Exp()),
        (pk.DirectProduct(pk.SO3), pk.lobatto_iiia_iiib4, pk.Cayley()),
        (pk.Cartesian(pk.SO3), pk.symplectic_euler, pk.Exp(truncation=None)),
    ],
    ids=["cotangent-SV-exp", "direct-lobatto-cayley", "cartesian-SE-exact"],
)
def test_gradient_wrt_args_matches_finite_differences(bundle, tab, coords):
    method = pk.PRKMK(bundle, coords, tab, form="body")
    loss = _loss_fn(method, bundle, rigid_body_field(bundle, "body"))
    y0 = initial_state(bundle)
    grad, fd = gradient_and_central_differences(loss, jnp.asarray(INERTIA), y0)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_gradient_wrt_initial_momentum_under_vmap():
    method = _method(pk.lobatto_iiia_iiib4)
    loss = _loss_fn(method, COTANGENT, FIELD)
    y0 = initial_state(COTANGENT)

    def loss_of_pi(pi, inertia):
        return loss(inertia, pk.BundleElement(y0.base, pi))

    pis = jnp.asarray(y0.fiber) * jnp.array([[1.0], [0.8], [1.3]])
    inertia = jnp.asarray(INERTIA)
    # One program: the gradients of the batch, and its values at the
    # momenta moved along each axis for the central differences.
    values_and_grads = jax.jit(jax.vmap(jax.value_and_grad(loss_of_pi), in_axes=(0, None)))
    grads = values_and_grads(pis, inertia)[1]
    eps = 1e-5
    fd = central_differences(lambda p: values_and_grads(p, inertia)[0], pis, eps)
    for b in range(3):
        np.testing.assert_allclose(grads[b], fd[b], rtol=1e-6, atol=1e-9 * np.abs(fd[b]).max())


@pytest.mark.parametrize(
    # The closed forms divide by |U|; Exp()'s default dexp⁻¹ is a polynomial in U, and its exp is this one's.
    "coords",
    [pk.Exp(truncation=None), pk.Cayley(truncation=None)],
    ids=["exp-exact", "cayley"],
)
def test_gradients_finite_through_the_identity(coords):
    """Every step evaluates f and df⁻¹ at U = 0; starting at g = I and Π = 0
    the state itself sits at the identity too."""
    bundle = pk.Semidirect(pk.SO3, "left")
    method = pk.PRKMK(bundle, coords, pk.lobatto_iiia_iiib4, form="body")

    def loss(pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(jnp.eye(3)), pi0)
        traj = pk.integrate(method, rigid_body_field(bundle, "body"), y0, 0.0, 0.1, 10, inertia)
        return jnp.sum(traj.ys.base.log() ** 2) + jnp.sum(traj.ys.base.matrix)

    g_pi, g_i = jax.jit(jax.grad(loss, argnums=(0, 1)))(jnp.zeros(3), jnp.asarray(INERTIA))
    assert np.all(np.isfinite(g_pi)) and np.all(np.isfinite(g_i))


# --- bad input ---------------------------------------------------------------------------
def test_non_orthogonal_initial_rotation():
    y0 = initial_state(COTANGENT)
    bad = pk.BundleElement(pk.SO3(y0.base.matrix * 1.001), y0.fiber)
    with pytest.raises(Exception, match="not orthogonal"):
        pk.integrate(_method(), FIELD, bad, 0.0, 0.01, 10, jnp.asarray(INERTIA))
    reflection = pk.BundleElement(pk.SO3(-y0.base.matrix), y0.fiber)
    with pytest.raises(Exception, match="reflection"):
        jax.jit(lambda y: pk.integrate(_method(), FIELD, y, 0.0, 0.01, 10, jnp.asarray(INERTIA)))(reflection)


def test_nan_input():
    y0 = initial_state(COTANGENT)
    with pytest.raises(Exception, match="not finite"):
        pk.integrate(_method(), FIELD, pk.BundleElement(y0.base, y0.fiber.at[1].set(jnp.nan)), 0.0, 0.01, 10, jnp.asarray(INERTIA))
    with pytest.raises(Exception, match="non-finite"):
        pk.integrate(_method(), FIELD, y0, 0.0, 0.01, 10, jnp.asarray(INERTIA).at[0].set(jnp.nan))


def test_mismatched_shapes():
    y0 = initial_state(COTANGENT)
    with pytest.raises(ValueError, match="shape"):
        pk.integrate(_method(), lambda t, y, a: (jnp.zeros(4), jnp.zeros(3)), y0, 0.0, 0.01, 10)
    with pytest.raises(ValueError, match="pair"):
        pk.integrate(_method(), lambda t, y, a: jnp.zeros(3), y0, 0.0, 0.01, 10)
    with pytest.raises(ValueError, match="fiber shape"):
        pk.integrate(_method(), FIELD, pk.BundleElement(y0.base, jnp.zeros(2)), 0.0, 0.01, 10, jnp.asarray(INERTIA))
    with pytest.raises(TypeError, match="SO3 fiber"):
        pk.integrate(_method(bundle=pk.Cartesian(pk.SO3)), FIELD, y0, 0.0, 0.01, 10, jnp.asarray(INERTIA))


@pytest.mark.parametrize("dt", [0.0, -0.1, float("nan")])
def test_bad_dt(dt):
    y0 = initial_state(COTANGENT)
    with pytest.raises(ValueError, match="dt must be > 0"):
        pk.integrate(_method(), FIELD, y0, 0.0, dt, 10, jnp.asarray(INERTIA))
    with pytest.raises(Exception, match="dt must be > 0"):
        jax.jit(lambda d: pk.integrate(_method(), FIELD, y0, 0.0, d, 10, jnp.asarray(INERTIA)))(jnp.asarray(dt))


def test_bad_step_counts():
    y0 = initial_state(COTANGENT)
    with pytest.raises(ValueError, match="divide"):
        pk.integrate(_method(), FIELD, y0, 0.0, 0.01, 10, jnp.asarray(INERTIA), save_every=3)
    with pytest.raises(ValueError, match="num_steps"):
        pk.integrate(_method(), FIELD, y0, 0.0, 0.01, 0, jnp.asarray(INERTIA))
    with pytest.raises(TypeError, match="PRKMK"):
        pk.integrate("SV", FIELD, y0, 0.0, 0.01, 10, jnp.asarray(INERTIA))


def test_bad_solver_options():
    with pytest.raises(ValueError, match="form"):
        pk.PRKMK(COTANGENT, form="sideways")
    with pytest.raises(ValueError, match="max_iterations"):
        pk.PRKMK(COTANGENT, max_iterations=0)
    with pytest.raises(TypeError, match="tableau"):
        pk.PRKMK(COTANGENT, tableau="verlet")


def test_non_converging_implicit_stage():
    """Symplectic Euler on the symmetric rigid body with h = 1: the fixed-point
    map is not a contraction (the field's Lipschitz constant is ≈ 8)."""
    bundle = pk.Cartesian(pk.SO3)
    method = pk.PRKMK(bundle, pk.Exp(), pk.symplectic_euler, form="body", max_iterations=30)
    field = rigid_body_field(bundle, "body")
    y0 = initial_state(bundle)
    with pytest.raises(Exception, match="maximum number of steps was reached in the nonlinear solver"):
        pk.integrate(method, field, y0, 0.0, 1.0, 5, jnp.asarray(INERTIA))
    traj = pk.integrate(method, field, y0, 0.0, 1.0, 5, jnp.asarray(INERTIA), throw=False)
    assert traj.result == pk.RESULTS.nonlinear_max_steps_reached
    # the same step size converges with Newton's method
    import optimistix as optx

    newton = pk.PRKMK(bundle, pk.Exp(), pk.symplectic_euler, form="body", root_finder=optx.Newton(rtol=1e-10, atol=1e-10))
    assert pk.integrate(newton, field, y0, 0.0, 1.0, 5, jnp.asarray(INERTIA), throw=False).result == pk.RESULTS.successful
