"""Every method's declared order, measured in one place: the log–log slope of
the largest error at the given times against h, over step sizes in the
method's asymptotic range, against a DOP853 reference (SciPy, rtol = atol =
1e-13) of the same equations on a Euclidean embedding, which knows nothing of
the methods. One parametrised test over the families: PRKMK on every bundle
and in both forms, with the exact dexp⁻¹ and with too short a truncation;
the explicit RKMK tableaus; compositions and symmetrised methods; the
splittings; the heavy top; SO(4); a time-dependent field on ℝ×ℝ."""

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

import prkmk_jax as pk
from helpers import (
    FORCED_ARGS,
    INERTIA,
    TOP_ARGS,
    final_state_by_steps,
    initial_state,
    reference,
    rigid_body_field,
    scene_reference,
    state_vector,
)
from prkmk_jax.scenes import (
    ForcedRigidBody,
    FreeRigidBody,
    HeavyTop,
    SymmetricRigidBody,
    random_rotation,
    symmetric_initial_state,
)


class Problem(NamedTuple):
    field: Callable
    y0: pk.BundleElement
    args: Any
    embed: Callable[[pk.BundleElement], np.ndarray]
    reference: Callable[[np.ndarray], np.ndarray]
    """The embedded exact solution at each of the given times, one row each."""
    t0: float = 0.0


class Case(NamedTuple):
    method: pk.AbstractMethod
    problem: Problem
    times: tuple[float, ...]
    """Equally spaced, t0 + Δ, t0 + 2Δ, …: the error is the largest over them."""
    steps: tuple[int, ...]
    """Steps per Δ."""
    order: float
    below: float = 0.15
    above: float = 0.15


def _rigid_body(bundle, form="body") -> Problem:
    """The rigid body (free on SO(3)×ℝ³, symmetric on SO(3)×SO(3)) from a random state."""
    y0 = initial_state(bundle)
    return Problem(
        rigid_body_field(bundle, form),
        y0,
        jnp.asarray(INERTIA),
        lambda y: state_vector(bundle, y),
        lambda times: reference(bundle, y0, times[-1], t_eval=times),
    )


def _scene(scene, y0, args) -> Problem:
    return Problem(
        scene,
        y0,
        args,
        lambda y: np.asarray(scene.to_embedding(y)),
        lambda times: scene_reference(scene, y0, times[-1], args, t_eval=times),
    )


def _state(seed, momentum=(0.25, 0.625, 0.875)):
    return pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(seed))), jnp.asarray(momentum))


TOP, TOP_ON_G_X_G = HeavyTop(), HeavyTop(pk.DirectProduct(pk.SO3))
SCENES = {  # name: (scene, y0, args)
    "free body": (FreeRigidBody(), _state(0), jnp.asarray(INERTIA)),
    "heavy top": (TOP, _state(5, (0.3, -0.4, 1.5)), TOP_ARGS),
    "forced body": (ForcedRigidBody(), _state(1), FORCED_ARGS),
    "symmetric body": (
        SymmetricRigidBody(),
        symmetric_initial_state(random_rotation(0), np.array([0.25, 0.625, 0.875])),
        jnp.asarray(INERTIA),
    ),
    "free body on G×g": (FreeRigidBody(pk.DirectProduct(pk.SO3)), _state(2), jnp.asarray(INERTIA)),
}
CASES: dict[str, Case] = {}

# --- PRKMK on every bundle ----------------------------------------------------------------
BUNDLES = {
    "direct": pk.DirectProduct(pk.SO3),
    "semidirect-left": pk.Semidirect(pk.SO3, "left"),
    "semidirect-right": pk.Semidirect(pk.SO3, "right"),
    "cotangent": pk.Cotangent(pk.SO3),
    "cartesian": pk.Cartesian(pk.SO3),  # the symmetric rigid body (3.3)
}
# (t_end, step counts) per order, chosen in the asymptotic range: order-1
# methods have large error constants. The symmetric rigid body (G×G) at order
# 4 needs finer steps: with Cayley its local slopes over h = 1/10 … 1/80 are
# 3.46, 3.71, 3.85 (pre-asymptotic), over h = 1/40 … 1/320 they are ≥ 3.85.
GRIDS = {1: (0.5, (200, 400, 800, 1600)), 2: (1.0, (40, 80, 160, 320)), 4: (1.0, (10, 20, 40, 80)), 6: (1.0, (8, 16, 32))}
CARTESIAN_GRIDS = {4: (1.0, (40, 80, 160, 320))}
COORDINATES = (pk.Exp(), pk.Cayley())


def _prkmk_case(tab, rep, coords, form):
    t_end, steps = CARTESIAN_GRIDS[tab.order] if (rep == "cartesian" and tab.order in CARTESIAN_GRIDS) else GRIDS[tab.order]
    method = pk.PRKMK(BUNDLES[rep], coords, tab, form=form)
    return Case(method, _rigid_body(BUNDLES[rep], form), (t_end,), steps, tab.order)


# Each tableau on two bundles and each bundle with two or three tableaus, the
# coordinates alternating so that each tableau and each bundle meets both
# maps; the space form once on each bundle, the two symmetric pairs and the
# two maps alternating.
for i, tab in enumerate(pk.tableaus.ALL_TABLEAUS):
    for k, rep in enumerate((list(BUNDLES)[i % 5], list(BUNDLES)[(i + 2) % 5])):
        coords = COORDINATES[(i + k) % 2]
        CASES[f"PRKMK {tab.name}, {rep}, {type(coords).__name__}"] = _prkmk_case(tab, rep, coords, "body")
for j, rep in enumerate(BUNDLES):
    tab, coords = (pk.stormer_verlet, pk.lobatto_iiia_iiib4)[j % 2], COORDINATES[(j // 2) % 2]
    CASES[f"PRKMK {tab.name}, {rep}, {type(coords).__name__}, space form"] = _prkmk_case(tab, rep, coords, "space")
for tab in (pk.lobatto_iiia_iiib4, pk.lobatto_iiia_iiib6):  # the exact dexp⁻¹ gives the order the truncated default does
    t_end, steps = GRIDS[tab.order]
    method = pk.PRKMK(BUNDLES["semidirect-right"], pk.Exp(truncation=None), tab, form="body")
    CASES[f"PRKMK {tab.name}, exact dexp⁻¹"] = Case(method, _rigid_body(BUNDLES["semidirect-right"]), (t_end,), steps, tab.order)
# Order 4 needs ad² in dexp⁻¹ (auto truncation q = 2); with q = 0 the Lobatto
# pair drops to order 2: the truncation rule is not vacuous.
CASES["PRKMK Lobatto 4 truncated too short"] = Case(
    pk.PRKMK(BUNDLES["direct"], pk.Exp(truncation=0), pk.lobatto_iiia_iiib4, form="body"),
    _rigid_body(BUNDLES["direct"]),
    (1.0,),
    (10, 20, 40, 80),
    2,
    below=0.3,
    above=0.3,
)

# --- the explicit RKMK tableaus -------------------------------------------------------------
# (t_end, step counts) where the errors run from ~1e-4 (RK 4) or ~1e-7 (DP 8)
# down to ~1e-12. Dormand–Prince 8 reaches its order from above: at errors the
# float64 references resolve, its h⁹ term still dominates with Cayley (local
# slopes 9.7 → 8.9 on the free body, 9.4 → 8.7 on the heavy top on T*SO(3),
# before round-off), so its fitted slope may lie up to 1.5 above 8.
EXPLICIT_GRIDS = {4: (2.0, (20, 40, 80, 160)), 8: (1.0, (4, 6, 8, 12))}
ABOVE = {4: 0.2, 8: 1.5}
# Each tableau with both maps, each problem at least once.
EXPLICIT = (
    (pk.tableaus.classical_rk4, pk.Exp(), "heavy top on T*SO(3)"),
    (pk.tableaus.classical_rk4, pk.Cayley(), "free body"),
    (pk.tableaus.dormand_prince_8, pk.Cayley(), "heavy top on T*SO(3)"),
    (pk.tableaus.dormand_prince_8, pk.Exp(), "heavy top on G×g"),
)
for tab, coords, problem_name in EXPLICIT:
    t_end, steps = EXPLICIT_GRIDS[tab.order]
    if problem_name == "free body":
        method, problem = pk.PRKMK(BUNDLES["cotangent"], coords, tab, form="body"), _rigid_body(BUNDLES["cotangent"])
    else:
        top = TOP if problem_name.endswith("T*SO(3)") else TOP_ON_G_X_G
        method, problem = top.method(tab, coords), _scene(top, *SCENES["heavy top"][1:])
    CASES[f"RKMK {tab.name}, {type(coords).__name__}, {problem_name}"] = Case(
        method, problem, (t_end,), steps, tab.order, below=0.2, above=ABOVE[tab.order]
    )

# --- compositions and symmetrised methods -------------------------------------------------------
SV_COT = pk.PRKMK(BUNDLES["cotangent"], pk.Exp(), pk.stormer_verlet, form="body")
SYM_SV_CART = pk.Symmetrized(pk.PRKMK(BUNDLES["cartesian"], pk.Exp(), pk.stormer_verlet, form="body"))
# Each composition on the symmetric SV (the triple jump on the heavy top
# below), and once on a symmetrised method.
COMPOSED = {  # name: (method, steps over T = 2)
    "SV ∘ Suzuki 5": (pk.Composition(SV_COT, pk.suzuki_5, assume_symmetric_base=True), (10, 20, 40)),
    "SV ∘ Kahan–Li 6": (pk.Composition(SV_COT, pk.kahan_li_6, assume_symmetric_base=True), (8, 16, 32)),
    "SV ∘ McLachlan 8": (pk.Composition(SV_COT, pk.mclachlan_8, assume_symmetric_base=True), (6, 12, 24)),
    "SV ∘ Kahan–Li 8": (pk.Composition(SV_COT, pk.kahan_li_8, assume_symmetric_base=True), (6, 12, 24)),
    "Symmetrized SE, SO(3)×SO(3)": (
        pk.Symmetrized(pk.PRKMK(BUNDLES["cartesian"], pk.Exp(), pk.symplectic_euler, form="body")),
        (40, 80, 160),
    ),
    "Symmetrized SV ∘ Kahan–Li 6, SO(3)×SO(3)": (pk.Composition(SYM_SV_CART, pk.kahan_li_6), (16, 32, 64)),
}
for name, (method, steps) in COMPOSED.items():
    CASES[name] = Case(method, _rigid_body(method.bundle), (2.0,), steps, method.order, below=0.2, above=0.2)

# --- splittings ----------------------------------------------------------------------------
# The largest error at t = 1, 2, …, 6: a high-order composition's error at one
# time rises and falls with the phase, its envelope over several times falls
# as h^p. Steps per unit of time, where the error is asymptotic and above round-off.
SPLITTINGS = {
    "Strang": (None, {"free body": (10, 20, 40, 80), "heavy top": (10, 20, 40, 80)}),
    "Suzuki 5": (pk.suzuki_5, {"free body": (5, 10, 20, 40)}),
    "Kahan–Li 6": (pk.kahan_li_6, {"heavy top": (4, 6, 8, 12)}),
    "Kahan–Li 8": (pk.kahan_li_8, {"free body": (4, 5, 6, 8)}),
}
for split_name, (coefficients, steps) in SPLITTINGS.items():
    for scene_name in steps:
        scene, y0, args = SCENES[scene_name]
        method = scene.splitting(coefficients)
        CASES[f"splitting {split_name}, {scene_name}"] = Case(
            method, _scene(scene, y0, args), tuple(np.arange(1.0, 7.0)), steps[scene_name], method.order, below=0.2, above=0.2
        )
# The other scenes, each with one order and one map: both orders and both maps among them.
for scene_name, coefficients, coords in (
    ("forced body", pk.suzuki_5, pk.Exp()),
    ("symmetric body", None, pk.Cayley()),
    ("free body on G×g", pk.suzuki_5, pk.Cayley()),
):
    scene, y0, args = SCENES[scene_name]
    method = scene.splitting(coefficients, coords)
    name = f"splitting {'Strang' if coefficients is None else 'Suzuki 5'}, {scene_name}, {type(coords).__name__}"
    CASES[name] = Case(method, _scene(scene, y0, args), (2.0,), (20, 40, 80), method.order, below=0.2, above=0.2)

# The kinetic energy taken whole (the free body's flow in closed form), one order on each scene with a potential or torque.
for scene_name, coefficients, steps in (("heavy top", None, (10, 20, 40)), ("forced body", pk.kahan_li_6, (10, 20, 40))):
    scene, y0, args = SCENES[scene_name]
    method = scene.splitting(coefficients, free_part="exact")
    name = f"splitting {'Strang' if coefficients is None else 'Kahan–Li 6'}, {scene_name}, exact free part"
    CASES[name] = Case(method, _scene(scene, y0, args), (2.0,), steps, method.order, below=0.2, above=0.2)

# --- the heavy top ---------------------------------------------------------------------------
HEAVY_TOP = {  # name: (scene, method)
    "SE": (TOP, TOP.method(pk.symplectic_euler)),
    "SV Cayley": (TOP, TOP.method(pk.stormer_verlet, pk.Cayley())),
    "Symmetrized SV ∘ triple jump": (TOP, pk.Composition(pk.Symmetrized(TOP.method(pk.stormer_verlet)), pk.yoshida_triple_jump)),
    "Lobatto 4 on G×g": (TOP_ON_G_X_G, TOP_ON_G_X_G.method(pk.lobatto_iiia_iiib4)),
}
for name, (scene, method) in HEAVY_TOP.items():
    CASES[f"heavy top, {name}"] = Case(method, _scene(scene, *SCENES["heavy top"][1:]), (2.0,), (20, 40, 80, 160), method.order, 0.2, 0.2)

# --- SO(4): the generalised rigid body M = JΩ + ΩJ, Ω_ij = M_ij/(J_i + J_j) ---------------------
J = np.array([0.9, 0.7, 0.5, 0.3])
_rng = np.random.default_rng(21)
G0 = expm((lambda a: a - a.T)(_rng.normal(size=(4, 4))))
M0 = (lambda a: 0.5 * (a - a.T))(_rng.normal(size=(4, 4)))


def _so4_reference(times):
    def rhs(t, z):
        g, m = z[:16].reshape(4, 4), z[16:].reshape(4, 4)
        w = m / (J[:, None] + J[None, :])
        return np.concatenate([(g @ w).ravel(), (m @ w - w @ m).ravel()])

    z0 = np.concatenate([G0.ravel(), M0.ravel()])
    return solve_ivp(rhs, (0, times[-1]), z0, method="DOP853", rtol=1e-13, atol=1e-13, t_eval=times).y.T


def _so4_field(bundle):
    """g' = gΩ, M' = [M, Ω] in body form."""

    def field(t, y, args):
        m = y.fiber
        w = m / jnp.asarray(J[:, None] + J[None, :])
        if isinstance(bundle, pk.Semidirect):  # left: the product supplies M' = −[Ω, M]
            return w, jnp.zeros_like(m)
        return w, m @ w - w @ m  # direct product: η = M'

    return field


for bundle_name, bundle in (("semidirect", pk.Semidirect(pk.SOn, "left")), ("direct", pk.DirectProduct(pk.SOn))):
    problem = Problem(
        _so4_field(bundle),
        pk.BundleElement(pk.SOn(jnp.asarray(G0)), jnp.asarray(M0)),
        None,
        lambda y: np.concatenate([np.ravel(y.base.matrix), np.ravel(y.fiber)]),
        _so4_reference,
    )
    # One tableau and one map on each bundle: both tableaus and both maps over the two.
    tab, coords = (pk.stormer_verlet, pk.Cayley()) if bundle_name == "direct" else (pk.lobatto_iiia_iiib4, pk.Exp())
    steps = (10, 20, 40, 80) if tab.order == 4 else (40, 80, 160, 320)
    name = f"SO(4), {bundle_name}, {tab.name}, {type(coords).__name__}"
    CASES[name] = Case(pk.PRKMK(bundle, coords, tab, form="body"), problem, (1.0,), steps, tab.order)


# --- a time-dependent field: the forced pendulum q' = p, p' = −sin q + 0.3 cos(2t) on ℝ×ℝ ---------
def _pendulum(t, y, args):
    return y.fiber.value, -jnp.sin(y.base.value) + 0.3 * jnp.cos(2 * t)


def _pendulum_reference(times):
    def rhs(t, z):
        return [z[1], -np.sin(z[0]) + 0.3 * np.cos(2 * t)]

    return solve_ivp(rhs, (0.4, times[-1]), [1.0, 0.2], method="DOP853", rtol=1e-13, atol=1e-13, t_eval=times).y.T


PENDULUM = Problem(
    _pendulum,
    pk.BundleElement(pk.VectorSpace(jnp.array([1.0])), pk.VectorSpace(jnp.array([0.2]))),
    None,
    lambda y: np.concatenate([np.asarray(y.base.value), np.asarray(y.fiber.value)]),
    _pendulum_reference,
    t0=0.4,
)
for tab in pk.tableaus.ALL_TABLEAUS:  # time enters through c_first
    steps = {1: (100, 200, 400, 800), 6: (4, 8, 16, 32)}.get(tab.order, (10, 20, 40, 80))
    CASES[f"time-dependent, {tab.name}"] = Case(pk.PRKMK(pk.Cartesian(pk.VectorSpace), pk.Exp(), tab), PENDULUM, (1.4,), steps, tab.order)


@pytest.mark.parametrize("name", CASES)
def test_declared_order(name):
    method, problem, times, steps, order, below, above = CASES[name]
    times = np.asarray(times)
    interval = times[0] - problem.t0
    expected = problem.reference(times)
    run = final_state_by_steps(method, problem.field)
    errors = []
    for n in steps:
        y, t, worst = problem.y0, problem.t0, 0.0
        for row, end in zip(expected, times):
            y, converged = run(y, interval / n, n, problem.args, t)
            assert converged
            worst, t = max(worst, float(np.max(np.abs(problem.embed(y) - row)))), end
        errors.append(worst)
    slope = np.polyfit(np.log(interval / np.asarray(steps)), np.log(errors), 1)[0]
    assert order - below <= slope <= order + above, (slope, errors)
