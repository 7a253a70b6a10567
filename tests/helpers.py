"""Shared test helpers: rigid-body vector fields on every representation and
an independent SciPy reference solution."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

import prkmk_jax as pk
from prkmk_jax.methods.base import as_traced
from prkmk_jax.scenes import ForcedParameters, FreeRigidBody, HarmonicTorque, SatelliteParameters, SymmetricRigidBody, TopParameters
from prkmk_jax.scenes.base import attitude_of
from prkmk_jax.scenes.rigid_body import random_rotation, symmetric_initial_state

INERTIA = np.array([7 / 8, 5 / 8, 1 / 4])
TOP_ARGS = TopParameters(jnp.array([1.0, 0.8, 0.4]), jnp.array([0.1, 0.2, 0.9]))
"""The heavy top of the tests: principal moments and lever ℓ = m g χ."""
FORCED_ARGS = ForcedParameters(
    jnp.asarray(INERTIA), HarmonicTorque(jnp.array([0.3, 0.2, 0.1]), jnp.array([1.0, 2.0, 3.0]), jnp.array([0.0, 0.5, 1.0]))
)
"""The forced body of the tests: the paper's inertia and a harmonic torque."""
SATELLITE_ARGS = SatelliteParameters(jnp.asarray([3e-3, 2e-3, 1e-3]), jnp.asarray(1.0), jnp.asarray(1.0))
"""The satellite of the tests: a body about a twentieth of its orbit's
radius across (nondimensional: μ = m = 1, |r| ≈ 1, an orbit of period 2π)."""


def satellite_state() -> pk.BundleElement:
    """A satellite on a slightly inclined, nearly circular orbit, turning slowly."""
    attitude = pk.SO3.exp(jnp.asarray([0.4, -0.3, 0.9])).matrix
    return pk.BundleElement(pk.SO3xR3(attitude, jnp.asarray([1.0, 0.1, -0.05])), jnp.asarray([5e-4, -1e-3, 2e-3, 0.05, 0.95, 0.1]))


M0 = np.array([0.250, 0.625, 0.875])


# --- free rigid body, (g, Π) with g' = gΩ, Π' = Π × Ω --------------------------------
def rigid_body_field(bundle, form: str):
    """Vector field f(t, y, args) on `bundle`, args = inertia (3,), so that the
    solution is the free rigid body g' = gΩ, Π' = Π×Ω, Ω = Π/I.

    For `Cartesian` the state is the symmetric rigid body (Q, P) of (3.3)."""
    if isinstance(bundle, pk.Cartesian):

        def field(t, y, inertia):
            m = pk.vee(y.base.matrix.T @ y.fiber.matrix - y.fiber.matrix.T @ y.base.matrix)
            omega = m / inertia
            if form == "body":
                return omega, omega
            return y.base.matrix @ omega, y.fiber.matrix @ omega

        return field

    def field(t, y, inertia):
        g, pi = y.base.matrix, y.fiber
        omega = pi / inertia
        pidot = jnp.cross(pi, omega)
        spatial = g @ omega
        if isinstance(bundle, pk.DirectProduct):
            return (omega, pidot) if form == "body" else (spatial, pidot)
        # semidirect (and cotangent) products
        left = bundle.trivialization == "left"
        if form == "body":
            # left: (g, Π)·(ξ, η) ≈ (g(1 + ξ), Π − ξ×Π + η); right: (g(1 + ξ), Π + g η)
            return (omega, jnp.zeros(3)) if left else (omega, g.T @ pidot)
        # space: (ξ, η)·(g, Π): left ≈ (g + ξ g, gᵀ η + Π); right ≈ (g + ξ g, η + ξ×Π)
        return (spatial, g @ pidot) if left else (spatial, pidot - jnp.cross(spatial, pi))

    return field


def initial_state(bundle, seed=0, m0=M0):
    q0 = random_rotation(seed)
    if isinstance(bundle, pk.Cartesian):
        return symmetric_initial_state(q0, m0)  # P₀ = Q₀ exp(sinh⁻¹(M₀/2))
    return pk.BundleElement(attitude_of(jnp.asarray(q0), bundle.base), jnp.asarray(m0))


def state_vector(bundle, y) -> np.ndarray:
    """Flatten a (batch of) state(s) to what the reference solves."""
    if isinstance(bundle, pk.Cartesian):
        return np.concatenate(
            [
                np.asarray(y.base.matrix).reshape(*y.base.matrix.shape[:-2], 9),
                np.asarray(y.fiber.matrix).reshape(*y.fiber.matrix.shape[:-2], 9),
            ],
            axis=-1,
        )
    return np.concatenate([np.asarray(y.base.matrix).reshape(*y.base.matrix.shape[:-2], 9), np.asarray(y.fiber)], axis=-1)


def reference(bundle, y0, t_end, inertia=INERTIA, t_eval=None) -> np.ndarray:
    """The rigid body's reference solution on its embedding ℝ⁹×ℝ³ (ℝ⁹×ℝ⁹
    on `Cartesian`: the symmetric body), the scene's
    `reference_solution` (DOP853 at rtol = atol = 1e-13): the state at
    `t_end`, or at each of `t_eval` (one row per time). The free body's
    embedding is the same on every bundle of SO(3) and ℝ³."""
    scene = SymmetricRigidBody() if isinstance(bundle, pk.Cartesian) else FreeRigidBody()
    rows = scene.reference_solution(y0, [t_end] if t_eval is None else t_eval, jnp.asarray(inertia))
    return rows[-1] if t_eval is None else rows


def scene_reference(scene, y0, t_end, args, t_eval=None) -> np.ndarray:
    """`scene.reference_solution` at each time of `t_eval`, or on a grid of
    201 times from 0 to `t_end`: one row per time."""
    return scene.reference_solution(y0, np.linspace(0.0, t_end, 201) if t_eval is None else t_eval, args)


def final_state_by_steps(method: pk.AbstractMethod, field):
    """A jitted (y0, dt, n, args, t0=0) -> (y after n steps of `method.step`
    from (t0, y0), whether every step's implicit stages converged). dt, n and
    t0 are traced, and numbers are taken as the library's drivers take them
    (`as_traced`): one compiled program serves every step size and start
    time of a convergence test, whatever kind of number each is."""

    @jax.jit
    def run(y0, dt, n, args, t0):
        def one_step(i, carry):
            y, converged = carry
            step = method.step(field, t0 + i * dt, y, dt, args)
            y, result = step.y, step.result
            return y, converged & (result == pk.RESULTS.successful)

        return jax.lax.fori_loop(0, n, one_step, (y0, jnp.array(True)))

    return lambda y0, dt, n, args, t0=0.0: run(y0, as_traced(dt), n, args, as_traced(t0))


@functools.cache
def final_state_fn(method: pk.PRKMK, form_field_key):
    """`final_state_by_steps` on the rigid body's field in a form, one per
    (method, (bundle, form)) for the whole test run."""
    bundle, form = form_field_key
    return final_state_by_steps(method, rigid_body_field(bundle, form))


def empirical_order(method: pk.PRKMK, t_end=2.0, steps=(10, 20, 40, 80), seed=0, inertia=INERTIA):
    """Log–log slope of the final-time error vs h against the DOP853 reference."""
    bundle = method.bundle
    y0 = initial_state(bundle, seed)
    ref = reference(bundle, y0, t_end, inertia)
    run = final_state_fn(method, (bundle, method.form))
    errs = []
    for n in steps:
        yn, converged = run(y0, jnp.asarray(t_end / n), n, jnp.asarray(inertia))
        assert converged
        errs.append(np.max(np.abs(state_vector(bundle, yn) - ref)))
    hs = t_end / np.asarray(steps)
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    return slope, np.asarray(errs)


def scene_order(method: pk.AbstractMethod, scene, y0, args, t_end: float, steps, reference=None) -> tuple[float, list[float]]:
    """Log–log slope of the error at `t_end` (max over the embedding's
    entries) against h = t_end/n for n in `steps`, and the errors: the
    method's run of the scene against `reference` (default the scene's
    DOP853 reference solution)."""
    if reference is None:
        reference = scene_reference(scene, y0, t_end, args)[-1]
    final_state = final_state_by_steps(method, scene)
    errors = []
    for n in steps:
        y, converged = final_state(y0, t_end / n, n, args)
        assert converged
        errors.append(float(np.max(np.abs(np.asarray(scene.to_embedding(y)) - reference))))
    slope = float(np.polyfit(np.log(t_end / np.asarray(steps)), np.log(errors), 1)[0])
    return slope, errors


def assert_embedding_field_is(formula, scene, t, y, args, atol=1e-13):
    """The scene's embedding field equals `formula(t, z, args)` (its
    equations written out) at (t, y) and off the group (the embedded state
    scaled by 1.01), and so does the field derived from its generator
    (`derived_embedding_field`)."""
    for z in (scene.to_embedding(y), 1.01 * scene.to_embedding(y)):
        expected = formula(t, z, args)
        np.testing.assert_allclose(scene.embedding_field(t, z, args), expected, atol=atol)
        np.testing.assert_allclose(pk.scenes.derived_embedding_field(scene, t, z, args), expected, atol=atol)


def bjorck_step(matrix):
    """One step of Björck's orthogonalisation, Q(3I − QᵀQ)/2, written out:
    the correction a drifted rotation is expected to receive."""
    gram = jnp.swapaxes(matrix, -1, -2) @ matrix
    return matrix @ (3 * jnp.eye(matrix.shape[-1], dtype=matrix.dtype) - gram) / 2


@functools.cache
def compiled_value_and_grad(loss):
    """`jax.jit(jax.value_and_grad(loss))`, one for each `loss`."""
    return jax.jit(jax.value_and_grad(loss))


def central_differences(value, x, step):
    """(value(x + step·eₖ) − value(x − step·eₖ))/(2 step) for each entry k
    of x's last axis, stacked as the last axis (x a vector, or a batch of
    vectors that `value` maps row by row)."""
    return np.stack(
        [(np.asarray(value(x + step * e)) - np.asarray(value(x - step * e))) / (2 * step) for e in np.eye(x.shape[-1])], axis=-1
    )


def gradient_and_central_differences(loss, x, *rest, step=1e-5):
    """`jax.grad` of `loss(x, *rest)` in the vector x, and its central
    differences (loss(x + step·eₖ) − loss(x − step·eₖ))/(2 step), both from
    one compiled program, `jax.value_and_grad`: its values at x ± step·eₖ
    make the differences (no derivative enters them), its gradient at x is
    the one checked. The same `loss` reuses its program."""
    value_and_grad = compiled_value_and_grad(loss)
    gradient = value_and_grad(x, *rest)[1]
    return np.asarray(gradient), central_differences(lambda z: value_and_grad(z, *rest)[0], x, step)


def assert_jacobians_at_the_identity(f, dim: int, atol=1e-8):
    """`jax.jacfwd` and `jax.jacrev` of f at 0 ∈ ℝ^dim are finite and equal
    central differences of f (steps 1e-6): a map's Taylor branch at the
    identity differentiates as the map does."""
    f = jax.jit(f)
    forward, reverse = jax.jit(lambda u: (jax.jacfwd(f)(u), jax.jacrev(f)(u)))(jnp.zeros(dim))
    assert np.all(np.isfinite(forward)) and np.all(np.isfinite(reverse))
    eps = 1e-6
    differences = np.stack([(f(eps * e) - f(-eps * e)) / (2 * eps) for e in jnp.eye(dim)], axis=-1)
    np.testing.assert_allclose(forward, differences, atol=atol)
    np.testing.assert_allclose(reverse, differences, atol=atol)


def assert_closed_forms_are_the_defaults(group, plain, u, x):
    """What `group` writes in closed form (its differentials, actions, fiber
    solves and changes) equals, at algebra elements u and x, what `plain`
    (the same group with only the methods every group must write) gets from
    the defaults."""

    def close(a, b, tol):
        for p, q in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_allclose(np.asarray(p), np.asarray(q), rtol=0, atol=tol)

    for method in ["dexp", "dexp_inv", "exp_adjoint", "exp_adjoint_change", "dcayley", "cayley_adjoint", "cayley_adjoint_change"]:
        close(getattr(plain, method)(u, x), getattr(group, method)(u, x), 1e-13)
    close(plain.inverse_shifted_ad(u, x, 0.5), group.inverse_shifted_ad(u, x, 0.5), 1e-13)
    close(plain.shifted_cayley_adjoint_inverse(u, x), group.shifted_cayley_adjoint_inverse(u, x), 1e-13)
    for method in ["exp_change", "cayley_change"]:
        close(getattr(plain, method)(u), getattr(group, method)(u), 1e-15)


def max_leaf_difference(a, b) -> float:
    """max |a − b| over the entries of two pytrees of the same structure, in
    NumPy (float64): no program compiled for each new shape."""
    return max(
        float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))
    )


# --- hypothesis strategies -----------------------------------------------------------
from hypothesis import strategies as st  # noqa: E402


def algebra_vectors(dim=3, max_norm=3.0):
    """Vectors of norm in {0} ∪ [1e-9, max_norm], log-uniformly, so near-identity
    elements are sampled as often as large ones."""
    direction = st.lists(st.floats(-1, 1), min_size=dim, max_size=dim).filter(lambda v: sum(x * x for x in v) > 1e-4)
    log_norm = st.one_of(st.just(None), st.floats(np.log(1e-9), np.log(max_norm)))

    def build(d, ln):
        d = np.asarray(d)
        if ln is None:
            return np.zeros(dim)
        return d / np.linalg.norm(d) * np.exp(ln)

    return st.builds(build, direction, log_norm)


def skew(n, vec):
    """so(n) element from n(n−1)/2 numbers."""
    m = np.zeros((n, n))
    m[np.triu_indices(n, 1)] = vec
    return m - m.T


# --- a group that is not quadratic, to exercise the Cayley refusal and the
# extension API ------------------------------------------------------------------------
from typing import ClassVar  # noqa: E402

import equinox as eqx  # noqa: E402


class PositiveReals(pk.groups.AbstractLieGroup):
    """(ℝ₊, ×) with algebra ℝ and exp = e^u: abelian, not quadratic."""

    value: jax.Array
    algebra_ndim: ClassVar[int] = 1
    bi_invariant_pairing: ClassVar[bool] = True

    @classmethod
    def exp(cls, u):
        return cls(jnp.exp(u))

    def log(self):
        return jnp.log(self.value)

    def multiply(self, other):
        return PositiveReals(self.value * other.value)

    def inverse(self):
        return PositiveReals(1 / self.value)

    def identity_like(self):
        return PositiveReals(jnp.ones_like(self.value))

    def adjoint(self, u):
        return u

    def algebra_zeros(self):
        return jnp.zeros_like(self.value)

    def project(self):
        return self

    def renormalized(self):
        return self

    def check(self):
        return PositiveReals(eqx.error_if(self.value, jnp.any(self.value <= 0), "not positive"))

    @classmethod
    def bracket(cls, u, v):
        return jnp.zeros_like(u)

    @classmethod
    def dexp(cls, u, v):
        return v

    @classmethod
    def dexp_inv(cls, u, v):
        return v

    @classmethod
    def exp_change(cls, u):
        return jnp.expm1(u)

    @classmethod
    def exp_adjoint_change(cls, u, x):
        return jnp.zeros_like(x)

    def product_change(self, change, side):
        return PositiveReals(self.value * change)


# --- the users' scripts, run in this process ---------------------------------------
def run_as_script(code: str, name: str) -> dict:
    """Run `code` as a user's script (`__name__ == "__main__"`) in a fresh
    namespace of this process, and return the namespace. In-process, it
    shares the test process's four host devices and float64 setting (every
    page and notebook enables float64 itself); figures are closed after."""
    import matplotlib.pyplot as plt

    plt.switch_backend("Agg")
    namespace = {"__name__": "__main__"}
    try:
        exec(compile(code, name, "exec"), namespace)
    finally:
        plt.close("all")
    return namespace


def benchmark_script(path):
    """A `benchmarks/` script imported as a module (its `main(argv)` is the command line)."""
    import importlib.util
    import sys

    folder = str(path.parent)
    sys.path.insert(0, folder)  # the scripts import `_common`
    try:
        spec = importlib.util.spec_from_file_location(f"benchmark_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(folder)
    return module
