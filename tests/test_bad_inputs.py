"""Bad input through every entry point: each case raises an error whose
message names the problem (static misuse at trace time, bad data at run
time, under `jax.jit` too), and a few plausible inputs are accepted."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, TOP_ARGS, PositiveReals, initial_state, rigid_body_field
from prkmk_jax.scenes import (
    DoublePendulum,
    ForcedParameters,
    ForcedRigidBody,
    FreeRigidBody,
    HeavyTop,
    PendulumParameters,
    Satellite,
    SatelliteParameters,
    SphericalTop,
    SymmetricRigidBody,
    TopParameters,
)

COTANGENT = pk.Cotangent(pk.SO3)
FIELD = rigid_body_field(COTANGENT, "body")
METHOD = pk.PRKMK(COTANGENT, pk.Exp(), pk.stormer_verlet, form="body")
ARGS = jnp.asarray(INERTIA)
GOOD = initial_state(COTANGENT)


def _with_base(matrix):
    return pk.BundleElement(pk.SO3(jnp.asarray(matrix)), GOOD.fiber)


def _integrate(y0=GOOD, dt=0.1, num_steps=10, args=ARGS, field=FIELD, method=METHOD, **kw):
    return pk.integrate(method, field, y0, 0.0, dt, num_steps, args, **kw).ys


def _diffeqsolve(y0=GOOD, term=None, solver=None, args=ARGS, **kw):
    return diffrax.diffeqsolve(term or pk.PRKMKTerm(FIELD), solver or pk.PRKMKSolver(METHOD), 0.0, 1.0, 0.1, y0, args, **kw).ys


TOP = HeavyTop()
TOP_ON_G_X_G_METHOD = HeavyTop(pk.DirectProduct(pk.SO3)).method(pk.stormer_verlet)
FREE_BODY = FreeRigidBody()
SYMMETRIC_SO4 = SymmetricRigidBody(pk.Cartesian(pk.SOn))
SYMMETRIC = SymmetricRigidBody()
SYMMETRIC_STATE = pk.BundleElement(pk.SO3(jnp.eye(3)), pk.SO3(jnp.eye(3)))
SO4_STATE = pk.BundleElement(pk.SOn(jnp.eye(4)), pk.SOn(jnp.eye(4)))
QUATERNION_BODY = FreeRigidBody(pk.Cotangent(pk.UnitQuaternion))
SATELLITE_STATE = pk.BundleElement(pk.SO3xR3(jnp.eye(3), jnp.asarray([1.0, 0.0, 0.0])), jnp.asarray([0.0, 0.0, 1e-3, 0.0, 1.0, 0.0]))
SATELLITE_ARGS = SatelliteParameters(jnp.asarray([3e-3, 2e-3, 1e-3]), 1.0, 1.0)
SATELLITE = Satellite()
PENDULUM_ARGS = PendulumParameters(jnp.ones((2, 3)), jnp.ones(2), jnp.ones((2, 3)), jnp.ones(3), 9.81)
PENDULUM_STATE = pk.BundleElement(pk.SO3Power(jnp.stack([jnp.eye(3)] * 2)), jnp.zeros((2, 3)))


def _satellite(args):
    return _integrate(SATELLITE_STATE, method=SATELLITE.method(pk.stormer_verlet), field=SATELLITE, args=args)


QUATERNION_METHOD = QUATERNION_BODY.method(pk.stormer_verlet)
SPACE_FORM_METHOD = pk.PRKMK(COTANGENT, tableau=pk.stormer_verlet)  # form="space" by default


NOT_SYMMETRIC = pk.Composition(METHOD, pk.yoshida_triple_jump)  # SV∘triple jump: not undone exactly by its adjoint


def _reversible_adjoint_gradient(**options):
    options = dict(adjoint=pk.ReversibleAdjoint(), max_steps=100) | options
    return jax.grad(lambda a: jnp.sum(_diffeqsolve(args=a, **options).fiber))(ARGS)


def _wrong_shape_field(t, y, args):
    return jnp.zeros(4), jnp.zeros(3)


STATIC = {
    # groups
    "SO3 of integers": (lambda: pk.SO3(jnp.eye(3, dtype=jnp.int32)), TypeError, "floating-point"),
    "SO3 of a string": (lambda: pk.SO3("identity"), TypeError, "must be an array"),
    "SO3 of a 2x2 matrix": (lambda: pk.SO3(jnp.eye(2)), ValueError, r"\(\.\.\., 3, 3\)"),
    "SOn of integers": (lambda: pk.SOn(np.eye(4, dtype=int)), TypeError, "floating-point"),
    "SOn not square": (lambda: pk.SOn(jnp.zeros((3, 4))), ValueError, r"\(\.\.\., n, n\)"),
    "VectorSpace of integers": (lambda: pk.VectorSpace(jnp.arange(3)), TypeError, "floating-point"),
    # bundles
    "Cotangent of a string": (lambda: pk.Cotangent("SO3"), TypeError, "base group class"),
    "Semidirect of a string": (lambda: pk.Semidirect("SO3"), TypeError, "base group class"),
    "Semidirect trivialization": (lambda: pk.Semidirect(pk.SO3, "middle"), ValueError, "trivialization"),
    "float32 base, float64 fiber": (
        lambda: _integrate(pk.BundleElement(pk.SO3(jnp.eye(3, dtype=jnp.float32)), GOOD.fiber)),
        TypeError,
        "dtype",
    ),
    "fiber of the wrong shape": (lambda: _integrate(pk.BundleElement(GOOD.base, jnp.zeros(4))), ValueError, "fiber shape"),
    "group fiber on T*G": (lambda: _integrate(pk.BundleElement(GOOD.base, GOOD.base)), TypeError, "algebra-array fiber"),
    "y0 not a BundleElement": (lambda: _integrate((GOOD.base, GOOD.fiber)), TypeError, "BundleElement"),
    # coordinates
    "negative truncation": (lambda: pk.Exp(truncation=-1), ValueError, "int ≥ 0"),
    "huge truncation": (lambda: pk.Exp(truncation=10**6), ValueError, "truncation=None"),
    "Cayley truncation 1": (lambda: pk.Cayley(truncation=1), ValueError, "gains no order"),
    "Cayley on a non-quadratic group": (lambda: pk.PRKMK(pk.DirectProduct(PositiveReals), pk.Cayley()), TypeError, "quadratic"),
    # tableaus
    "tableau of scalars": (lambda: pk.PartitionedTableau("x", 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1), ValueError, "non-empty vector"),
    "tableau row sums": (lambda: pk.PartitionedTableau("x", [[0.5]], [1.0], [1.0], [[0.0]], [1.0], [0.0], 1), ValueError, "row sums"),
    "tableau order too high": (
        lambda: pk.PartitionedTableau("x", [[1.0]], [1.0], [1.0], [[0.0]], [1.0], [0.0], 2),
        ValueError,
        "order conditions",
    ),
    # the method
    "negative rtol": (lambda: pk.PRKMK(COTANGENT, rtol=-1.0), ValueError, "rtol must be"),
    "negative atol": (lambda: pk.PRKMK(COTANGENT, atol=-1e-3), ValueError, "atol must be"),
    "rtol and atol zero": (lambda: pk.PRKMK(COTANGENT, rtol=0.0, atol=0.0), ValueError, "both be 0"),
    "max_iterations 0": (lambda: pk.PRKMK(COTANGENT, max_iterations=0), ValueError, "max_iterations"),
    "form sideways": (lambda: pk.PRKMK(COTANGENT, form="sideways"), ValueError, "form must be"),
    "bundle not a bundle": (lambda: pk.PRKMK(pk.SO3), TypeError, "bundle must be"),
    "composition of the wrong order": (
        lambda: pk.Composition(pk.PRKMK(COTANGENT, tableau=pk.lobatto_iiia_iiib4), pk.kahan_li_6),
        ValueError,
        "order 2",
    ),
    "adjoint of a composition": (lambda: pk.Adjoint(pk.Composition(METHOD, pk.suzuki_5)), TypeError, "Adjoint takes a PRKMK"),
    # integrate
    "integrate with a solver that is not a method": (lambda: _integrate(method=diffrax.Tsit5()), TypeError, "PRKMK method"),
    "num_steps 0": (lambda: _integrate(num_steps=0), ValueError, "num_steps must be an int"),
    "num_steps traced": (lambda: jax.jit(lambda n: _integrate(num_steps=n))(10), ValueError, "static Python int"),
    "save_every not a divisor": (lambda: _integrate(num_steps=10, save_every=3), ValueError, "must divide"),
    "dt negative": (lambda: _integrate(dt=-0.1), ValueError, "dt must be > 0"),
    "vector field of the wrong shape": (lambda: _integrate(field=_wrong_shape_field), ValueError, "returned ξ with shape"),
    # a scene and a method that do not match
    "scene on another bundle": (lambda: _integrate(field=TOP, method=TOP_ON_G_X_G_METHOD, args=TOP_ARGS), ValueError, "lives on Cotangent"),
    "scene on another bundle, jitted": (
        lambda: jax.jit(lambda y: _integrate(y, field=TOP, method=TOP_ON_G_X_G_METHOD, args=TOP_ARGS))(GOOD),
        ValueError,
        "lives on Cotangent",
    ),
    "resume with a scene on another bundle": (
        lambda: pk.resume(
            TOP_ON_G_X_G_METHOD,
            TOP,
            pk.integrate(TOP_ON_G_X_G_METHOD, HeavyTop(pk.DirectProduct(pk.SO3)), GOOD, 0.0, 0.1, 2, TOP_ARGS).continuation,
            2,
            TOP_ARGS,
        ),
        ValueError,
        "lives on Cotangent",
    ),
    "scene in the other form": (lambda: _integrate(field=FREE_BODY, method=SPACE_FORM_METHOD), ValueError, "written in body form"),
    "scene in the other form, composed and jitted": (
        lambda: jax.jit(lambda y: _integrate(y, field=FREE_BODY, method=pk.Composition(SPACE_FORM_METHOD, pk.suzuki_5)))(GOOD),
        ValueError,
        "written in body form",
    ),
    "ForcedRigidBody given a bundle": (lambda: ForcedRigidBody(pk.DirectProduct(pk.SO3)), TypeError, "lives on Cotangent"),
    # scene parameters
    "heavy top lever of shape (2,)": (lambda: TopParameters(TOP_ARGS.inertia, jnp.array([0.1, 0.2])), ValueError, "TopParameters.lever"),
    "heavy top inertia of shape (4,)": (lambda: TopParameters(jnp.ones(4), TOP_ARGS.lever), ValueError, "TopParameters.inertia"),
    "free body inertia of shape (2,)": (
        lambda: _integrate(field=FREE_BODY, args=jnp.array([1.0, 2.0])),
        ValueError,
        r"FreeRigidBody: the inertia is principal moments \(3,\) or a tensor",
    ),
    "free body inertia of shape (2, 3)": (
        lambda: _integrate(field=FREE_BODY, args=jnp.ones((2, 3))),
        ValueError,
        "FreeRigidBody: the inertia is principal moments",
    ),
    "heavy top given an array as args": (
        lambda: _integrate(field=TOP, method=TOP.method(pk.stormer_verlet), args=TOP_ARGS.inertia),
        TypeError,
        r"HeavyTop takes its parameters as args=TopParameters",
    ),
    "heavy top given one moment": (
        lambda: _integrate(field=TOP, method=TOP.method(pk.stormer_verlet), args=TopParameters(1.0, TOP_ARGS.lever)),
        ValueError,
        "SphericalTop's",
    ),
    "diffeqsolve, heavy top given an array as args": (
        lambda: _diffeqsolve(term=pk.PRKMKTerm(TOP), solver=pk.PRKMKSolver(TOP.method(pk.stormer_verlet)), args=TOP_ARGS.inertia),
        TypeError,
        "HeavyTop takes its parameters",
    ),
    "forced body inertia of shape (2,)": (
        lambda: ForcedParameters(jnp.array([1.0, 2.0]), None),
        ValueError,
        "ForcedParameters.inertia",
    ),
    "ForcedRigidBody given a torque that is not a function": (lambda: ForcedRigidBody("harmonic"), TypeError, "torque_law must be"),
    "diffeqsolve, scene on another bundle": (
        lambda: _diffeqsolve(term=pk.PRKMKTerm(TOP), solver=pk.PRKMKSolver(TOP_ON_G_X_G_METHOD), args=TOP_ARGS),
        ValueError,
        "lives on Cotangent",
    ),
    # diffeqsolve
    # diffrax checks an ODETerm's output against y0 first and names ODETerm;
    # a field that does return a state is refused by PRKMKSolver.
    "ODETerm with PRKMKSolver": (lambda: _diffeqsolve(term=diffrax.ODETerm(FIELD)), ValueError, "inside `ODETerm`"),
    "ODETerm returning a state": (lambda: _diffeqsolve(term=diffrax.ODETerm(lambda t, y, a: y)), TypeError, r"PRKMKTerm\(f\)"),
    "gradient through BacksolveAdjoint": (
        lambda: jax.grad(lambda a: jnp.sum(_diffeqsolve(args=a, adjoint=diffrax.BacksolveAdjoint()).fiber))(ARGS),
        NotImplementedError,
        "BacksolveAdjoint",
    ),
    "diffeqsolve y0 not a BundleElement": (lambda: _diffeqsolve(y0=(GOOD.base, GOOD.fiber)), TypeError, "BundleElement"),
    "PRKMKSolver of Tsit5": (lambda: pk.PRKMKSolver(diffrax.Tsit5()), TypeError, "wraps a PRKMK"),
    "PRKMKTerm with Tsit5": (lambda: _diffeqsolve(solver=diffrax.Tsit5()), NotImplementedError, "Lie-algebra generator"),
    # splittings
    "splitting, an inertia tensor": (
        lambda: _integrate(method=FREE_BODY.splitting(), field=FREE_BODY, args=jnp.diag(ARGS)),
        ValueError,
        "principal moments",
    ),
    "splitting of another scene": (
        lambda: _integrate(method=FREE_BODY.splitting(), field=TOP, args=TOP_ARGS),
        ValueError,
        "integrates the scene it was built for",
    ),
    "splitting of another scene, diffeqsolve": (
        lambda: _diffeqsolve(term=pk.PRKMKTerm(TOP), solver=pk.PRKMKSolver(FREE_BODY.splitting()), args=TOP_ARGS),
        ValueError,
        "integrates the scene it was built for",
    ),
    "splitting of a scene that does not split": (lambda: SphericalTop().splitting(), TypeError, "splits into exactly solvable parts"),
    "splitting, compensated_sum not a bool": (lambda: pk.Splitting(FREE_BODY, compensated_sum=1), TypeError, "compensated_sum must be"),
    "splitting, an unknown free part": (lambda: pk.Splitting(FREE_BODY, free_part="whole"), ValueError, "free_part must be"),
    "splitting of the symmetric body, exact free part": (
        lambda: _integrate(method=SYMMETRIC.splitting(free_part="exact"), field=SYMMETRIC, args=ARGS, y0=SYMMETRIC_STATE),
        ValueError,
        "axis terms only",
    ),
    # exact flows
    "exact flow, an inertia tensor": (
        lambda: _integrate(method=FREE_BODY.exact_flow(), field=FREE_BODY, args=jnp.diag(ARGS)),
        ValueError,
        "closed-form flow needs the principal moments",
    ),
    "exact flow of another field": (lambda: _integrate(method=FREE_BODY.exact_flow()), ValueError, "integrates the scene it was built for"),
    "exact flow of a scene without one": (lambda: pk.ExactFlow(TOP), TypeError, "closed form"),  # pyright: ignore[reportCallIssue]
    # unit quaternions
    "UnitQuaternion of three numbers": (lambda: pk.UnitQuaternion(jnp.ones(3)), ValueError, r"\(\.\.\., 4\) array"),
    "UnitQuaternion of integers": (lambda: pk.UnitQuaternion(jnp.array([1, 0, 0, 0])), TypeError, "floating-point dtype"),
    "symmetric body on UnitQuaternion": (lambda: SymmetricRigidBody(pk.Cartesian(pk.UnitQuaternion)), TypeError, "SymmetricRigidBody"),
    # rotations with translations, the satellite
    "SE3, a translation of four numbers": (lambda: pk.SE3(jnp.eye(3), jnp.zeros(4)), ValueError, r"\(\.\.\., 3\) translation"),
    "Cotangent(SE3)": (lambda: pk.Cotangent(pk.SE3), TypeError, "bi-invariant pairing"),
    "satellite on T*SO(3)": (lambda: Satellite(pk.Cotangent(pk.SO3)), TypeError, "Satellite lives on"),
    "satellite, args not SatelliteParameters": (
        lambda: _satellite(jnp.ones(3)),
        TypeError,
        "SatelliteParameters",
    ),
    "satellite, a mass of two numbers": (lambda: SatelliteParameters(jnp.ones(3), jnp.ones(2), 1.0), ValueError, "mass is a scalar"),
    # the double pendulum
    "SO3Power of one matrix": (lambda: pk.SO3Power(jnp.eye(3)), ValueError, r"\(\.\.\., n, 3, 3\)"),
    "double pendulum on T*SO(3)": (lambda: DoublePendulum(pk.Cotangent(pk.SO3)), TypeError, "DoublePendulum lives on"),
    "double pendulum, a joint of two numbers": (
        lambda: PendulumParameters(jnp.ones((2, 3)), jnp.ones(2), jnp.ones((2, 3)), jnp.ones(2), 9.81),
        ValueError,
        r"joint must have shape \(3,\)",
    ),
    "double pendulum, a state of one body": (
        lambda: DoublePendulum()(0.0, pk.BundleElement(pk.SO3(jnp.eye(3)), jnp.zeros(3)), PENDULUM_ARGS),
        TypeError,
        "SO3Power with two bodies",
    ),
    "splitting of the satellite on SE(3)": (
        lambda: _integrate(
            pk.BundleElement(pk.SE3(jnp.eye(3), SATELLITE_STATE.base.translation), SATELLITE_STATE.fiber),
            method=Satellite(pk.DirectProduct(pk.SE3)).splitting(),
            field=Satellite(pk.DirectProduct(pk.SE3)),
            args=SATELLITE_ARGS,
        ),
        TypeError,
        r"Satellite splits on SO\(3\) × ℝ³",
    ),
    "splitting of the symmetric body on SO(4)": (
        lambda: _integrate(SO4_STATE, method=SYMMETRIC_SO4.splitting(), field=SYMMETRIC_SO4, args=jnp.ones(4)),
        ValueError,
        r"Cartesian\(SO3\) only",
    ),
    # reversible gradients
    "ReversibleGradient of a method not undone exactly": (
        lambda: jax.grad(lambda a: jnp.sum(_integrate(args=a, method=NOT_SYMMETRIC, gradient=pk.ReversibleGradient()).fiber))(ARGS),
        TypeError,
        "can be undone exactly",
    ),
    "ReversibleGradient, checkpoint_every 0": (lambda: pk.ReversibleGradient(checkpoint_every=0), ValueError, "checkpoint_every"),
    "ReversibleGradient, a negative tolerance": (
        lambda: pk.ReversibleGradient(max_reconstruction_error=-1.0),
        ValueError,
        "max_reconstruction_error",
    ),
    "gradient given as a string": (lambda: _integrate(gradient="reversible"), TypeError, "ReversibleGradient"),
    "ReversibleGradient in forward mode": (
        lambda: jax.jvp(lambda a: jnp.sum(_integrate(args=a, gradient=pk.ReversibleGradient()).fiber), (ARGS,), (jnp.ones(3),)),
        TypeError,
        "forward-mode",
    ),
    "ReversibleAdjoint with a PID controller": (
        lambda: _reversible_adjoint_gradient(stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6)),
        ValueError,
        "ConstantStepSize",
    ),
    "ReversibleAdjoint saving at times": (
        lambda: _reversible_adjoint_gradient(saveat=diffrax.SaveAt(ts=jnp.array([0.5, 1.0]))),
        ValueError,
        "SaveAt",
    ),
    "ReversibleAdjoint of a method not undone exactly": (
        lambda: _reversible_adjoint_gradient(solver=pk.PRKMKSolver(NOT_SYMMETRIC)),
        TypeError,
        "can be undone exactly",
    ),
    "ReversibleAdjoint without max_steps": (
        lambda: _reversible_adjoint_gradient(max_steps=None),
        ValueError,
        "needs diffeqsolve's max_steps",
    ),
    "ReversibleAdjoint, a zero tolerance": (
        lambda: pk.ReversibleAdjoint(max_reconstruction_error=0.0),
        ValueError,
        "max_reconstruction_error",
    ),
    "ReversibleAdjoint, checkpoint_every 0": (lambda: pk.ReversibleAdjoint(checkpoint_every=0), ValueError, "checkpoint_every"),
}


@pytest.mark.parametrize("case", STATIC, ids=list(STATIC))
def test_static_misuse_is_refused_by_name(case):
    fn, error, match = STATIC[case]
    with pytest.raises(error, match=match):
        jax.block_until_ready(fn())


NOT_ORTHOGONAL = 2 * np.eye(3)
REFLECTION = np.diag([1.0, 1.0, -1.0])
RUNTIME = {
    "integrate, y0 not orthogonal": (lambda y: _integrate(y), _with_base(NOT_ORTHOGONAL), "not orthogonal"),
    "integrate, y0 a reflection": (lambda y: _integrate(y), _with_base(REFLECTION), "det = −1"),
    "integrate, y0 not finite": (lambda y: _integrate(y), pk.BundleElement(GOOD.base, jnp.array([1.0, jnp.nan, 0.0])), "not finite"),
    "integrate, dt ≤ 0 as data": (lambda dt: _integrate(dt=dt), jnp.asarray(-0.1), "dt must be > 0"),
    "integrate, args not finite": (lambda a: _integrate(args=a), jnp.array([1.0, jnp.inf, 1.0]), "non-finite"),
    "heavy top, a negative moment": (
        lambda i: _integrate(field=TOP, method=TOP.method(pk.stormer_verlet), args=TopParameters(i, TOP_ARGS.lever)),
        jnp.array([1.0, -0.8, 0.4]),
        "TopParameters.inertia: every principal moment",
    ),
    "heavy top, a zero moment": (lambda i: TopParameters(i, TOP_ARGS.lever).inertia, jnp.array([1.0, 0.0, 0.4]), "must be > 0"),
    "forced body, a negative moment": (
        lambda i: ForcedParameters(i, None).inertia,
        jnp.array([-1.0, 0.8, 0.4]),
        "ForcedParameters.inertia: every principal moment",
    ),
    "free body, a negative moment": (
        lambda i: _integrate(field=FREE_BODY, args=i),
        jnp.array([1.0, -0.8, 0.4]),
        "FreeRigidBody: every principal",
    ),
    "free body, a zero moment": (
        lambda i: _integrate(field=FREE_BODY, args=i),
        jnp.array([1.0, 0.8, 0.0]),
        "moment of inertia must be > 0",
    ),
    "free body, a tensor not positive definite": (
        lambda i: _integrate(field=FREE_BODY, args=i),
        jnp.diag(jnp.array([1.0, -0.5, 0.4])),
        "FreeRigidBody: the inertia tensor must be symmetric and positive definite",
    ),
    "free body, a tensor not symmetric": (
        lambda i: _integrate(field=FREE_BODY, args=i),
        jnp.array([[1.0, 0.1, 0.0], [0.0, 0.8, 0.0], [0.0, 0.0, 0.4]]),
        "symmetric and positive definite",
    ),
    "diffeqsolve, free body, an infinite moment": (
        lambda i: _diffeqsolve(term=pk.PRKMKTerm(FREE_BODY), args=i),
        jnp.array([1.0, jnp.inf, 0.4]),
        "args contain a non-finite value",
    ),
    "diffeqsolve, args not finite": (lambda a: _diffeqsolve(args=a), jnp.array([1.0, jnp.nan, 1.0]), "args contain a non-finite value"),
    "diffeqsolve, free body, a negative moment": (
        lambda i: _diffeqsolve(term=pk.PRKMKTerm(FREE_BODY), args=i),
        jnp.array([-1.0, 0.8, 0.4]),
        "FreeRigidBody: every principal",
    ),
    "symmetric body on SO(4), masses with Jᵢ + Jⱼ ≤ 0": (
        lambda j: _integrate(SO4_STATE, field=SYMMETRIC_SO4, method=SYMMETRIC_SO4.method(pk.symplectic_euler), args=j),
        jnp.array([0.9, 0.7, -0.8, 0.3]),
        r"SymmetricRigidBody: every Jᵢ \+ Jⱼ",
    ),
    "integrate, a quaternion y0 not of norm 1": (
        lambda q: _integrate(pk.BundleElement(pk.UnitQuaternion(q), GOOD.fiber), field=QUATERNION_BODY, method=QUATERNION_METHOD),
        jnp.array([1.0, 0.1, 0.0, 0.0]),
        "not of norm 1",
    ),
    "integrate, a quaternion y0 not finite": (
        lambda q: _integrate(pk.BundleElement(pk.UnitQuaternion(q), GOOD.fiber), field=QUATERNION_BODY, method=QUATERNION_METHOD),
        jnp.array([1.0, jnp.nan, 0.0, 0.0]),
        "UnitQuaternion element is not finite",
    ),
    "SE3, a translation not finite": (
        lambda p: pk.SE3(jnp.eye(3), p).check().translation,
        jnp.array([0.0, jnp.nan, 0.0]),
        "SE3 translation is not finite",
    ),
    "double pendulum, a negative mass": (
        lambda m: DoublePendulum().invariants(PENDULUM_STATE, PendulumParameters(jnp.ones((2, 3)), m, jnp.ones((2, 3)), jnp.ones(3), 9.81))[
            "energy"
        ],
        jnp.array([1.0, -1.0]),
        "both masses must be > 0",
    ),
    "satellite, a negative mass": (
        lambda m: _satellite(SatelliteParameters(SATELLITE_ARGS.inertia, m, 1.0)),
        jnp.asarray(-1.0),
        "mass must be > 0",
    ),
    "diffeqsolve, y0 not orthogonal": (lambda y: _diffeqsolve(y), _with_base(NOT_ORTHOGONAL), "not orthogonal"),
    "diffeqsolve, y0 a reflection": (lambda y: _diffeqsolve(y), _with_base(REFLECTION), "det = −1"),
}


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
@pytest.mark.parametrize("case", RUNTIME, ids=list(RUNTIME))
def test_bad_data_raises_at_run_time_with_its_message(case, jit):
    """Under `jax.jit` the error is a JaxRuntimeError whose text carries the
    library's message (eqx.filter_jit shows it alone)."""
    fn, data, match = RUNTIME[case]
    run = jax.jit(fn) if jit else fn
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(run(data))


def test_plausible_inputs_are_accepted():
    """A rotation as nested lists or a NumPy array, NumPy integer step counts."""
    from_lists = pk.SO3([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    assert isinstance(from_lists.matrix, jax.Array) and from_lists.matrix.dtype == jnp.float64
    assert pk.SO3(np.eye(3)).matrix.shape == (3, 3)
    ys = _integrate(num_steps=np.int64(10), save_every=np.int32(5))
    assert ys.fiber.shape == (3, 3)


def test_rounding_drift_is_accepted_and_a_scaled_matrix_is_not():
    """The orthogonality policy: a defect of 5e-4 (float32 data promoted to
    float64 has ~1e-7) restarts, in float32 and float64; 2e-3 is refused."""
    rotation = np.asarray(GOOD.base.matrix)
    for dtype in (jnp.float32, jnp.float64):
        drifted = pk.BundleElement(pk.SO3(jnp.asarray(rotation * (1 + 2.5e-4), dtype)), GOOD.fiber.astype(dtype))
        ys = _integrate(drifted, args=ARGS.astype(dtype))
        assert ys.fiber.dtype == dtype and np.all(np.isfinite(ys.fiber))
    with pytest.raises(Exception, match="not orthogonal"):
        _integrate(_with_base(rotation * (1 + 1e-3)))
