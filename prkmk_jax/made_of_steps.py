"""Methods made of other methods' steps: the adjoint Φ*, the symmetrised
Φ*_{h/2} ∘ Φ_{h/2}, and symmetric compositions Φ_{γ_m h} ∘ … ∘ Φ_{γ₁ h}.

Compositions raise the order of a *symmetric* base (Φ_{−h} ∘ Φ_h = id) and
keep what every sub-step keeps: the state stays on the group, Casimirs and
momentum maps conserved by the base stay conserved, a symplectic base gives
a symplectic method. Whether a PRKMK method is symmetric depends on the
tableau, the coordinate map, its truncation and the field (the centre of the
coordinates is the step's start, which the reversed step does not share):
`symmetry_defect` measures it on the user's problem. Measured on the free
rigid body (tests/test_composed.py): Störmer–Verlet with `Exp()` or
`Cayley()` at their default truncation (df⁻¹ ≈ I) is symmetric to round-off
on `Cotangent(SO3)` (η ≡ 0: both stage points are the step's end points);
with the exact df⁻¹, on `Cartesian(SO3)`, or for Lobatto IIIA–IIIB 4, it is
not. `Symmetrized(method)` is symmetric whatever the method, at the cost of
a second, fully implicit half step.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from .bundles import BundleElement
from .compositions import CompositionCoefficients
from .exact_sums import rounded_once_combination
from .method import (
    RESULTS,
    AbstractMethod,
    Step,
    VectorField,
    compensated,
    first_failure,
    flag_nonfinite,
    largest_entry_difference,
    no_compensation,
    varying_with,
)
from .splitting import Splitting
from .step import PRKMK, static_combination


class AbstractMadeOfSteps(AbstractMethod):
    """A method built from the steps of `method`: on its bundle, in its
    coordinates and form."""

    method: eqx.AbstractVar[AbstractMethod]

    @property
    def bundle(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.method.bundle

    @property
    def coordinates(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.method.coordinates

    @property
    def form(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.method.form

    def check_fits(self, vector_field):
        self.method.check_fits(vector_field)


class Adjoint(AbstractMadeOfSteps):
    """The adjoint Φ*_h = (Φ_{−h})⁻¹ of a PRKMK method Φ, or of a `Splitting`
    (symmetric: its adjoint is itself, and its steps are taken as they are).

    Φ*_h(yₙ) is the y with Φ_{−h}(y) = yₙ: the method's stages centred at
    the step's end. With U_i = −h(Σⱼ a¹ᵢⱼKⱼ, Σⱼ a²ᵢⱼLⱼ), W = h(Σⱼ b¹ⱼKⱼ, Σⱼ b²ⱼLⱼ),
    yₙ₊₁ = f(W)·yₙ (space form; yₙ·f(W) in body form) and stage points
    Y_i = f(U_i)·yₙ₊₁, the slopes solve (K_i, L_i) = df⁻¹_{U_i}(X(tₙ₊₁ − c_i h,
    Y_i)) — one implicit system for all stages (yₙ₊₁ depends on every slope),
    solved by the method's root finder. Then f(−W)·yₙ₊₁ = yₙ is the reversed
    step, since f(−W) = f(W)⁻¹ for both coordinate maps. In a vector space
    this is the PRK method of the adjoint tableau.

    The system is as small as the method's own stage plan allows: where the
    field has η ≡ 0 (`stage_plan`; not with `coupling="tableau"`) the K's
    alone are unknowns, and a stage whose rows of A are the weights (the
    last of Lobatto IIIA) has U_i = −W, so Y_i = yₙ, where the field is
    known: only df⁻¹_{−W} changes with the iterate. An adjoint step of
    Störmer–Verlet on the free body then costs what the method's step does.
    """

    method: PRKMK | Splitting  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a field narrows an AbstractVar's type

    def __check_init__(self):
        if not isinstance(self.method, (PRKMK, Splitting)):
            raise TypeError(f"Adjoint takes a PRKMK method (its stages are re-centred) or a Splitting, got {type(self.method).__name__}.")

    @property
    def order(self) -> int:
        return self.method.order

    @property
    def is_symmetric(self) -> bool:
        return self.method.is_symmetric

    def initial_carried(self, vector_field, t, y, args=None):
        return self.method.initial_carried(vector_field, t, y, args)

    def start_field(self, carried):
        return self.method.start_field(carried)

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        if isinstance(self.method, Splitting):  # symmetric: Φ* = Φ
            return self.method.carried_step(vector_field, t, y, dt, args, carried)
        field_now, guesses = self.method.extrapolated_guesses(vector_field, t, y, args, carried)
        return _adjoint_step(self.method, vector_field, t, y, dt, args, field_now, guesses, stages_solved=False)

    def step_at_stages(self, vector_field, t, y, dt, args, stages) -> Step:
        """The adjoint step whose stage slopes are known to solve its stage
        equations, evaluated once there (`PRKMK.step_at_stages`)."""
        if not isinstance(self.method, PRKMK):
            raise TypeError(f"step_at_stages needs the adjoint of a PRKMK method, got the adjoint of a {type(self.method).__name__}.")
        field_now = self.method.generator(vector_field, t, y, args)
        return _adjoint_step(self.method, vector_field, t, y, dt, args, field_now, stages, stages_solved=True)


def _adjoint_step(method: PRKMK, vector_field, t, y, dt, args, field_now, guesses, stages_solved: bool) -> Step:
    """A step of `Adjoint(method)`, its stages started from `guesses` (or,
    `stages_solved`, evaluated once there: `PRKMK.step_at_stages`)."""
    tab = method.tableau
    dtype = jnp.result_type(*jax.tree.leaves(y))
    dt = jnp.asarray(dt, dtype)
    t = jnp.asarray(t, dtype)
    zeros = method.bundle.algebra_zeros(y)
    # η ≡ 0 makes L ≡ 0 (`stage_plan`): the K's alone are unknowns, and
    # no stage point moves the fiber by an increment.
    fiber_free = method.stage_dependence(vector_field, t, y, args).second_zero

    def combination(scale, coefficients, slopes, zero):
        out = static_combination(scale, coefficients, slopes, zero)
        return zero if out is None else out

    def increment(first, second):
        v = None if fiber_free else combination(dt, tab.b_second, second, zeros[1])
        return combination(dt, tab.b_first, first, zeros[0]), v

    def all_slopes(unknowns):
        first, second = (list(unknowns), None) if fiber_free else ([k for k, _ in unknowns], [l_i for _, l_i in unknowns])
        y_end = method.apply_increment(increment(first, second), y)
        out = []
        for i in range(tab.num_stages):
            tt = t + (1.0 - float(tab.c_first[i])) * dt
            if not (tab.a_first[i].any() or (not fiber_free and tab.a_second[i].any())):  # U_i = 0: Y_i = yₙ₊₁, df⁻¹_0 = I
                slope = method.generator(vector_field, tt, y_end, args)
            else:
                u = combination(-dt, tab.a_first[i], first, zeros[0])
                v = None if fiber_free else combination(-dt, tab.a_second[i], second, zeros[1])
                if _reaches_start(tab, i, fiber_free):
                    # U_i = −W: Y_i = f(−W)·f(W)·yₙ = yₙ, where the field is
                    # known; only df⁻¹ moves with the slopes.
                    slope = method.slope(method.bundle.zero_filled((u, v), y), field_now)
                else:
                    slope = method.slope_at(vector_field, tt, (u, v), y_end, args)
            out.append(slope[0] if fiber_free else slope)
        return tuple(out)

    start = tuple(k for k, _ in guesses) if fiber_free else guesses
    solved, result, iterations = method.solve_implicit(all_slopes, start, dtype, guess_solves=stages_solved)
    stages = tuple((k, zeros[1]) for k in solved) if fiber_free else solved
    first, second = [k for k, _ in stages], [l_i for _, l_i in stages]
    u_next, v_next = increment(first, second)
    if method.iterate_until == "round-off":
        # As PRKMK's step: u rounded once from the solved slopes, not by
        # the formula of which they are a fixed point (`exact_sums`).
        u_rounded_once = rounded_once_combination(dt, tab.b_first, first, zeros[0])
        u_next = zeros[0] if u_rounded_once is None else u_rounded_once
    y_next, rounding = method.advance((u_next, v_next), y, method.compensated_sum)
    increment_made = (u_next, zeros[1] if v_next is None else v_next)
    return Step(y_next, increment_made, flag_nonfinite(result, y_next), iterations, rounding, (field_now, stages))


def _reaches_start(tab, i: int, fiber_free: bool) -> bool:
    """Whether stage i of the adjoint step sits at the step's start: its rows
    of A equal the weights (stiffly accurate stages, the last of Lobatto
    IIIA; the second part does not count where L ≡ 0), so U_i = −W, and its
    time is the start's (c_i = 1)."""
    rows_are_weights = np.array_equal(tab.a_first[i], tab.b_first) and (fiber_free or np.array_equal(tab.a_second[i], tab.b_second))
    return rows_are_weights and float(tab.c_first[i]) == 1.0


class Symmetrized(AbstractMadeOfSteps):
    """Φ̂_h = Φ*_{h/2} ∘ Φ_{h/2}: half a step of a PRKMK method Φ, then half a
    step of its adjoint (`Adjoint`). Φ̂ is symmetric for any Φ, of order p
    (p even) or p + 1 (p odd: symplectic Euler gives order 2), and a
    symmetric base for `Composition` where Φ itself is not symmetric. Of a
    `Splitting` (already symmetric) it is two half steps."""

    method: PRKMK | Splitting  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a field narrows an AbstractVar's type

    def __check_init__(self):
        if not isinstance(self.method, (PRKMK, Splitting)):
            raise TypeError(f"Symmetrized takes a PRKMK method or a Splitting, got {type(self.method).__name__}.")

    @property
    def adjoint(self) -> Adjoint:
        return Adjoint(self.method)  # pyright: ignore[reportCallIssue]  # equinox: AbstractVars implemented by properties are not __init__ fields

    @property
    def order(self) -> int:
        p = self.method.order
        return p + p % 2

    @property
    def is_symmetric(self) -> bool:
        return True

    def initial_carried(self, vector_field, t, y, args=None):
        carried = self.method.initial_carried(vector_field, t, y, args)
        return carried, carried

    def start_field(self, carried):
        return self.method.start_field(carried[0])

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        dtype = jnp.result_type(*jax.tree.leaves(y))
        half = jnp.asarray(dt, dtype) / 2
        t = jnp.asarray(t, dtype)
        first = self.method.step(vector_field, t, y, half, args, carried[0])
        # The half steps' roundings summed as the drivers sum steps'
        # (`compensated`): the step hands on what both lost.
        y_half, lost = compensated(first.y, first.rounding, no_compensation(y))
        second = self.adjoint.step(vector_field, t + half, y_half, half, args, carried[1])
        y_next, lost = compensated(second.y, second.rounding, lost)
        result = first_failure(first.result, second.result)
        increment = self.increment_between(y, y_next)
        rounding = None if first.rounding is None and second.rounding is None else lost
        return Step(y_next, increment, result, first.iterations + second.iterations, rounding, (first.carried, second.carried))


class Composition(AbstractMadeOfSteps):
    """Ψ_h = Φ_{γ_m h} ∘ … ∘ Φ_{γ₁ h}: m steps of `method` with the step
    fractions of `coefficients` (e.g. `kahan_li_6`, `triple_jump(4)`).

    The coefficients raise the order of a *symmetric* base of order
    `coefficients.base_order` (checked: the orders must match) to
    `coefficients.order`; of a base that is not symmetric, the composition
    keeps the base's order (Störmer–Verlet with the exact dexp⁻¹ composed by
    `kahan_li_6` measures order 3, not 6). So `order` is
    `coefficients.order` when the base is symmetric by construction
    (`method.is_symmetric`: `Symmetrized`, `Splitting`) or when
    `assume_symmetric_base=True` says it is on the user's problem (a PRKMK
    method's symmetry depends on the field: check it with
    `symmetry_defect`), and the base's order otherwise. The step is the same
    either way; `order` is what `PRKMKSolver` reports to diffrax (step-size
    control) and what the method promises.

    The sub-steps run in a `lax.scan`, so compile time does not grow with m;
    each sub-step's implicit stages start from the same sub-step of the
    previous step (`Step.carried`). Negative fractions step backwards
    in time, which every PRKMK method allows.
    """

    method: AbstractMethod
    coefficients: CompositionCoefficients = eqx.field(static=True)
    assume_symmetric_base: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if not isinstance(self.method, AbstractMethod):
            raise TypeError(f"Composition composes a PRKMK method (or another composition), got {type(self.method).__name__}.")
        if not isinstance(self.coefficients, CompositionCoefficients):
            raise TypeError(f"coefficients must be CompositionCoefficients, got {type(self.coefficients).__name__}.")
        if self.method.order != self.coefficients.base_order:
            raise ValueError(
                f"{self.coefficients.name} raises a symmetric base of order {self.coefficients.base_order}, but the method "
                f"has order {self.method.order}; use coefficients for that order (e.g. triple_jump({self.method.order}))."
            )
        if not isinstance(self.assume_symmetric_base, bool):
            raise TypeError(f"assume_symmetric_base must be True or False, got {self.assume_symmetric_base!r}.")

    @property
    def order(self) -> int:
        if self.method.is_symmetric or self.assume_symmetric_base:
            return self.coefficients.order
        return self.method.order

    @property
    def is_symmetric(self) -> bool:
        # A palindrome of symmetric steps is symmetric.
        return self.method.is_symmetric or self.assume_symmetric_base

    def initial_carried(self, vector_field, t, y, args=None):
        m = self.coefficients.num_steps
        carried = self.method.initial_carried(vector_field, t, y, args)
        return jax.tree.map(lambda x: jnp.broadcast_to(x, (m,) + jnp.shape(x)), carried)

    def start_field(self, carried):
        return self.method.start_field(jax.tree.map(lambda x: x[0], carried))

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        dtype = jnp.result_type(*jax.tree.leaves(y))
        dt = jnp.asarray(dt, dtype)
        t = jnp.asarray(t, dtype)
        fractions = jnp.asarray(self.coefficients.fractions, dtype)
        starts = jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(fractions)[:-1]])

        sums = []  # whether the sub-step hands on a rounding, seen as the scan traces it

        def substep(state, inputs):
            y_k, lost, result, iterations = state
            fraction, start, carried_k = inputs
            sub = self.method.step(vector_field, t + start * dt, y_k, fraction * dt, args, carried_k)
            # The sub-steps' roundings summed as the drivers sum steps' (`compensated`).
            sums.append(sub.rounding is not None)
            y_k, lost = compensated(sub.y, sub.rounding, lost)
            return (y_k, lost, first_failure(result, sub.result), iterations + sub.iterations), sub.carried

        init = (y, *varying_with((no_compensation(y), RESULTS.successful, jnp.array(0, jnp.int32)), y))
        (y_next, lost, result, iterations), carried = jax.lax.scan(substep, init, (fractions, starts, carried))
        return Step(y_next, self.increment_between(y, y_next), result, iterations, lost if any(sums) else None, carried)


def symmetry_defect(
    method: AbstractMethod, vector_field: VectorField, y: BundleElement, dt: float | Array, args: PyTree = None, t: float | Array = 0.0
) -> Array:
    """max |Φ_{−h}(Φ_h(y)) − y| over the entries of the state (in its matrix
    or vector embedding): zero up to round-off and the stage tolerance for a
    symmetric method, O(h^{p+1}) for a non-symmetric one of order p."""
    t, dt = jnp.asarray(t), jnp.asarray(dt)
    y_forward = method.step(vector_field, t, y, dt, args).y
    y_back = method.step(vector_field, t + dt, y_forward, -dt, args).y
    return largest_entry_difference(y_back, y)
