"""The free rigid body's exact flow (`FreeRigidBody().exact_flow()`,
`scenes.free_flow`): against SciPy's DOP853 on the embedding, against the
equations themselves (its derivative in h is the field at every h) and the
group law in h; its invariants; as a method in every driver, with gradients
against finite differences."""

from fractions import Fraction as F

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import prkmk_jax as pk
from helpers import INERTIA, central_differences, max_leaf_difference
from prkmk_jax.scenes import FreeRigidBody, random_rotation
from prkmk_jax.scenes.free_flow import _separatrix_distance, free_body_flow

SCENE = FreeRigidBody()
METHOD = SCENE.exact_flow()


def _state(seed, momentum):
    return pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(seed))), jnp.asarray(momentum, float))


def _separatrix_momentum(inertia, offset):
    """A momentum with |Π|² = 2H·I_mid·(1 + offset): Π_hi² follows from Π_lo = 0.3, Π_mid = 0.9."""
    lo, mid, hi = np.sort(inertia)
    p_lo, p_mid = 0.3, 0.9
    p_hi = np.sqrt(p_lo**2 * (mid / lo - 1) / (1 - mid / hi) * (1 + offset))
    return np.array([p_lo, p_mid, p_hi])[np.argsort(np.argsort(inertia))]


_RNG = np.random.default_rng(62)
CASES = {  # name: (inertia, momentum)
    **{f"random {k}": (_RNG.uniform(0.2, 2.0, 3), _RNG.normal(size=3)) for k in range(4)},
    "two equal moments (1 = 2)": (np.array([1.0, 1.0, 0.5]), np.array([0.3, 0.4, 0.9])),
    "two equal moments (2 = 3)": (np.array([0.5, 1.0, 1.0]), np.array([0.3, 0.4, 0.9])),
    "a sphere": (np.array([0.7, 0.7, 0.7]), np.array([0.3, 0.4, 0.9])),
    "near-symmetric (1e-7)": (np.array([0.5, 1.0, 1.0 + 1e-7]), np.array([0.3, 0.4, 0.9])),
    "steady about the largest axis": (np.array([0.5, 0.75, 1.0]), np.array([0.0, 0.0, -0.9])),
    "steady about the middle axis": (np.array([0.5, 0.75, 1.0]), np.array([0.0, 0.9, 0.0])),
    "a zero component": (np.array([0.5, 0.75, 1.0]), np.array([0.0, 0.5, 0.9])),
    "near the separatrix, inside": (np.array([0.5, 0.75, 1.0]), _separatrix_momentum(np.array([0.5, 0.75, 1.0]), 1e-6)),
    "near the separatrix, outside": (np.array([1.0, 0.75, 0.5]), _separatrix_momentum(np.array([1.0, 0.75, 0.5]), -1e-6)),
    # Π stays near the middle axis for T = 10 while its amplitude sits near a
    # quarter turn with 1 − k² ≈ 1e-12 and 1e-18: the attitude's integrals
    # are evaluated where an amplitude's rounding would be magnified by 1/k′.
    "near the middle axis (1e-6)": (np.array([0.5, 0.75, 1.0]), np.array([1e-6, 0.9, 0.7e-6])),
    "near the middle axis (1e-9)": (np.array([1.0, 0.75, 0.5]), np.array([-0.7e-9, 0.9, 1e-9])),
    # Two moments 5e-11 apart and Π near their plane: Π precesses slowly, so
    # a step's increments of the attitude's integrals are small against
    # their values at its ends, and g/λ multiplies their rounding by 200.
    "slow precession": (np.array([2.0, 2.1, 2.0 * (1 + 5e-11)]), np.array([-2.25, -0.02, 0.08])),
}


@jax.jit
def _flows(q, pi, inertia, h):
    return jax.vmap(free_body_flow, (0, 0, 0, None))(q, pi, inertia, h)


def _batch():
    q = np.stack([random_rotation(k) for k in range(len(CASES))])
    inertia, pi = (np.stack(x) for x in zip(*CASES.values()))
    return q, pi, inertia


def test_against_dop853():
    """T = 10 for every case (T = 100 for the first), relative to |Π|."""
    q, pi, inertia = _batch()
    q_end, pi_end = _flows(q, pi, inertia, 10.0)
    q_far, pi_far = _flows(q, pi, inertia, 100.0)
    for k, name in enumerate(CASES):
        y0 = pk.BundleElement(pk.SO3(jnp.asarray(q[k])), jnp.asarray(pi[k]))
        times = [10.0, 100.0] if k == 0 else [10.0]
        reference = SCENE.reference_solution(y0, times, jnp.asarray(inertia[k]))
        scale = np.linalg.norm(pi[k])
        np.testing.assert_allclose(q_end[k].ravel(), reference[0, :9], rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(pi_end[k], reference[0, 9:], rtol=0, atol=1e-12 * scale, err_msg=name)
        if k == 0:
            np.testing.assert_allclose(q_far[k].ravel(), reference[1, :9], rtol=0, atol=1e-11, err_msg=name)
            np.testing.assert_allclose(pi_far[k], reference[1, 9:], rtol=0, atol=1e-11 * scale, err_msg=name)


def test_solves_the_equations_and_composes():
    """d/dh of the flow at h is (QΩ̂, Π × Ω) at the state it reached, and
    φ_a ∘ φ_b = φ_{a+b} (a, b of both signs); |Π|, the energy, QΠ and QᵀQ
    stay to round-off."""
    q, pi, inertia = _batch()

    @jax.jit
    def residuals(h):
        (q_h, pi_h), (dq, dpi) = jax.jvp(lambda h: _flows(q, pi, inertia, h), (h,), (jnp.ones_like(h),))
        omega = pi_h / inertia
        field_q = q_h @ pk.hat(omega)
        field_pi = jnp.cross(pi_h, omega)
        return jnp.max(jnp.abs(dq - field_q)), jnp.max(jnp.abs(dpi - field_pi)), q_h, pi_h

    for h in (0.3, 7.0, -4.0):
        dq_error, dpi_error, q_h, pi_h = residuals(jnp.asarray(h))
        assert dq_error < 1e-12 and dpi_error < 1e-12, (h, dq_error, dpi_error)
        np.testing.assert_allclose(np.linalg.norm(pi_h, axis=-1), np.linalg.norm(pi, axis=-1), rtol=1e-14)
        np.testing.assert_allclose(np.sum(pi_h**2 / inertia, -1), np.sum(pi**2 / inertia, -1), rtol=1e-14)
        np.testing.assert_allclose(np.einsum("bij,bj->bi", q_h, pi_h), np.einsum("bij,bj->bi", q, pi), atol=1e-14)
        np.testing.assert_allclose(np.swapaxes(q_h, -1, -2) @ q_h, np.broadcast_to(np.eye(3), q.shape), atol=1e-14)
    for a, b in ((2.5, 4.0), (6.0, -9.0)):
        q_a, pi_a = _flows(q, pi, inertia, a)
        q_ab, pi_ab = _flows(q_a, pi_a, inertia, b)
        q_sum, pi_sum = _flows(q, pi, inertia, a + b)
        np.testing.assert_allclose(q_ab, q_sum, atol=2e-14)
        np.testing.assert_allclose(pi_ab, pi_sum, atol=2e-14)


def test_many_short_steps_are_one_long_step():
    """100 steps of 1 end where one step of 100 does, to the rounding of a
    hundred states (the flow is exact, so only rounding can part them);
    not near the separatrix or the middle axis, where the motion itself
    multiplies an ulp by 1e5 over T = 100."""
    q, pi, inertia = _batch()

    @jax.jit
    def hundred_steps(q, pi):
        return jax.lax.scan(lambda state, _: (_flows(*state, inertia, 1.0), None), (q, pi), None, length=100)[0]

    q_many, pi_many = hundred_steps(q, pi)
    q_one, pi_one = _flows(q, pi, inertia, 100.0)
    scale = np.linalg.norm(pi, axis=-1)
    for k, name in enumerate(CASES):
        if not name.startswith("near the"):
            assert np.max(np.abs(q_many[k] - q_one[k])) < 5e-13, name
            assert np.max(np.abs(pi_many[k] - pi_one[k])) < 5e-13 * scale[k], name


def test_a_method_in_every_driver():
    """One step of 10 equals 100 steps of 0.1 and diffeqsolve's steps; a step
    back undoes a step; the method is symmetric and undoes itself."""
    y0, inertia = _state(0, [0.25, 0.625, 0.875]), jnp.asarray(INERTIA)
    one = pk.integrate(METHOD, SCENE, y0, 0.0, 10.0, 1, inertia).ys
    many = pk.integrate(METHOD, SCENE, y0, 0.0, 0.1, 100, inertia).ys
    assert max_leaf_difference(jax.tree.map(lambda a: a[-1], one), jax.tree.map(lambda a: a[-1], many)) < 2e-14
    sol = diffrax.diffeqsolve(pk.PRKMKTerm(SCENE), pk.PRKMKSolver(METHOD), t0=0.0, t1=10.0, dt0=2.5, y0=y0, args=inertia)
    assert max_leaf_difference(jax.tree.map(lambda a: a[-1], sol.ys), jax.tree.map(lambda a: a[-1], one)) < 2e-14
    assert METHOD.is_symmetric and METHOD.undoing_method() is METHOD
    assert pk.symmetry_defect(METHOD, SCENE, y0, 3.0, inertia) < 1e-14


def test_flow_gradients_everywhere():
    """The derivatives of one flow step with respect to the momentum and the
    inertia, for every case (steady turns and the sphere included, where the
    elliptic formulas are 0/0), against central differences."""
    q, pi, inertia = _batch()
    weights = jnp.arange(12.0)

    def loss(params, q):
        q_end, pi_end = free_body_flow(q, params[:3], params[3:], 1.7)
        return jnp.concatenate([q_end.ravel(), pi_end]) @ weights

    params = jnp.concatenate([pi, inertia], -1)
    gradients = jax.jit(jax.vmap(jax.grad(loss)))(params, q)
    differences = central_differences(jax.jit(lambda params: jax.vmap(loss)(params, jnp.asarray(q))), params, 1e-6)
    assert np.all(np.isfinite(gradients))
    for k, name in enumerate(CASES):
        if name == "steady about the middle axis":
            # The states a difference steps to lie a hair from the separatrix,
            # where the attitude's closed form loses digits (module docstring
            # of scenes.free_flow): differences of it are no reference.
            continue
        np.testing.assert_allclose(gradients[k], differences[k], rtol=1e-6, atol=1e-7 * np.max(np.abs(differences[k])), err_msg=name)


def test_gradients_against_finite_differences():
    """With respect to the initial momentum and the inertia, through
    ReversibleGradient (the step undone by itself, then differentiated)."""
    q0 = jnp.asarray(random_rotation(1))
    weights = jnp.arange(12.0)

    def loss(params, gradient=pk.ReversibleGradient()):
        momentum, inertia = params[:3], params[3:]
        ys = pk.integrate(METHOD, SCENE, pk.BundleElement(pk.SO3(q0), momentum), 0.0, 0.5, 20, inertia, gradient=gradient).ys
        return jnp.concatenate([ys.base.matrix[-1].ravel(), ys.fiber[-1]]) @ weights

    params = jnp.array([0.3, -0.5, 0.8, 0.9, 0.6, 0.3])
    gradient = jax.jit(jax.grad(loss))(params)
    assert np.all(np.isfinite(gradient))
    np.testing.assert_allclose(gradient, central_differences(jax.jit(loss), params, 1e-6), rtol=1e-6)


def test_float32():
    """A float32 step stays in float32, near the float64 one."""
    y0 = _state(0, [0.25, 0.625, 0.875])
    low = jax.tree.map(lambda a: a.astype(jnp.float32), y0)
    step64 = METHOD.step(SCENE, 0.0, y0, 3.0, jnp.asarray(INERTIA)).y
    step32 = METHOD.step(SCENE, jnp.float32(0.0), low, jnp.float32(3.0), jnp.asarray(INERTIA, jnp.float32)).y
    assert step32.fiber.dtype == jnp.float32 and step32.base.matrix.dtype == jnp.float32
    assert max_leaf_difference(step32, step64) < 2e-6


def test_the_separatrix_distance_to_its_own_accuracy():
    """|Π|² − 2H·I_mid, which sets 1 − k² and the side of the separatrix,
    against exact rational arithmetic on states from 1e-14 to 1 of the
    separatrix (relative to |Π|²): within 4 ulps of itself and of the right
    sign, where the two terms rounded as they stand err by up to 2e-2."""
    rng = np.random.default_rng(59)
    inertia = np.sort(rng.uniform(0.5, 3.0, (400, 3)), axis=-1)
    lo, mid, hi = inertia.T
    p_lo = rng.uniform(0.1, 1.0, 400)
    offset = rng.choice([-1.0, 1.0], 400) * 10.0 ** -rng.uniform(0, 14, 400)
    p_hi = np.sqrt(p_lo**2 * (mid / lo - 1) / (1 - mid / hi) * (1 + offset))
    exact = np.array(
        [float(F(b) ** 2 * (F(h) - F(m)) / F(h) - F(a) ** 2 * (F(m) - F(c)) / F(c)) for a, b, c, m, h in zip(p_lo, p_hi, lo, mid, hi)]
    )
    computed = np.asarray(jax.jit(_separatrix_distance)(p_lo, p_hi, lo, mid, hi))
    assert np.all(np.sign(computed) == np.sign(exact))
    assert np.max(np.abs(computed - exact) / np.abs(exact)) < 4 * np.finfo(float).eps
