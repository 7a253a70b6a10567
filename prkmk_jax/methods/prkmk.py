"""The PRKMK step: Algorithm 4.2 of the paper, generic over bundle group,
coordinate map and partitioned tableau.

Two forms of the vector field `f(t, y, args) -> (ξ, η)` are supported:

* `form="space"` (the paper's, Algorithm 4.2): y' = (ξ, η)·y. With
  y = f(U)·yₙ the algebra ODE is U' = df⁻¹_U(ξ, η) and yₙ₊₁ = f(Uₙ₊₁)·yₙ.
* `form="body"`: y' = y·(ξ, η), e.g. Q' = QΩ of (3.3). With y = yₙ·f(U),
  y⁻¹ = f(−U)·yₙ⁻¹ solves (y⁻¹)' = −(ξ, η)·y⁻¹ (both coordinate maps satisfy
  f(−U) = f(U)⁻¹), so the space form applied to −U gives
  U' = df⁻¹_{−U}(ξ, η) and yₙ₊₁ = yₙ·f(Uₙ₊₁). For exp this is the series
  Σ B_k/k! (−ad_U)^k, the left-trivialised dexp⁻¹ of Table 2.2.

Stage slopes (K, L) are found in the order `stage_plan.plan_stages` gives:
from the tableau's two A matrices and what each slope depends on (read from
the traced program of a stage, `stage_plan.stage_dependence`), strongly
connected sets of slopes are solved together (`stage_solve`), and the
others are evaluated directly. Non-convergence is returned as a
`diffrax.RESULTS` value. The adjoint step (`Adjoint`) centres the same
stages at the step's end.
"""

import dataclasses
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from .._bundles import AbstractBundle, BundleElement
from .._exact_sums import rounded_once_combination
from .._fields import Time, VectorField
from ..coordinates import AbstractCoordinates, Exp
from ..tableaus import PartitionedTableau, stormer_verlet
from .adjoint import Adjoint
from .base import RESULTS, AbstractMethod, Step, check_parts, flag_nonfinite
from .stage_plan import COUPLED, StageDependence, plan_stages, stage_dependence
from .stage_solve import StageSolve
from .stages import (
    check_stage_pairs,
    explicit_slopes,
    extrapolated_guesses,
    slopes_by_plan,
    start_side,
    static_combination,
)


class PRKMK(AbstractMethod):
    """A partitioned Runge–Kutta–Munthe-Kaas method (Algorithm 4.2).

    **Arguments:**

    - `bundle`: the bundle group, e.g. `Cartesian(SO3)` or `Cotangent(SO3)`.
    - `coordinates`: `Exp()` or `Cayley()`, with their truncation.
    - `tableau`: a `PartitionedTableau`, e.g. `stormer_verlet`.
    - `form`: `"space"` for y' = (ξ, η)·y, `"body"` for y' = y·(ξ, η).
    - `rtol`, `atol`, `max_iterations`, `root_finder`, `iterate_until`: how
      the implicit stages are solved (`StageSolve`). By default fixed-point
      iteration to round-off (`iterate_until="round-off"`), so that a
      symmetric or symplectic method is so to round-off; `"tolerance"`
      stops at `rtol`/`atol` (default max(1e-12, 50·eps)); an optimistix
      `root_finder` (e.g. `optx.Newton(rtol, atol)`) converges where h times
      the field's Lipschitz constant is not small.
    - `compensated_sum`: True (default) adds each step's change to the state
      and carries what the sum loses to rounding into the next step
      (`compensated`); False takes the product f(U)⊙y as it is.
    - `start_either_side`: solving to round-off, start each step's iteration
      on the side of its guess that the state's last bits pick, so that the
      solve's leans cancel (default; `stages.extrapolated_guesses`).
    - `coupling`: `"traced"` (default) reads what each slope depends on
      from the field's program (`stage_plan`); `"tableau"` from A alone.
    - `explicit_stages`: an explicit tableau's stages `"unrolled"`, in a
      `"loop"`, or `"auto"` (default): the loop from `STAGE_LOOP_BATCH`
      trajectories in the state on (docs: *Tableaus, order and compositions*);
      differentiated, the loop at every batch.
    """

    bundle: AbstractBundle
    coordinates: AbstractCoordinates = Exp()
    tableau: PartitionedTableau = eqx.field(static=True, default=stormer_verlet)
    form: Literal["space", "body"] = eqx.field(static=True, default="space")
    rtol: float | None = eqx.field(static=True, default=None)
    atol: float | None = eqx.field(static=True, default=None)
    max_iterations: int = eqx.field(static=True, default=100)
    root_finder: Any = eqx.field(static=True, default=None)
    coupling: Literal["traced", "tableau"] = eqx.field(static=True, default="traced")
    explicit_stages: Literal["auto", "unrolled", "loop"] = eqx.field(static=True, default="auto")
    iterate_until: Literal["round-off", "tolerance"] = eqx.field(static=True, default="round-off")
    compensated_sum: bool = eqx.field(static=True, default=True)
    start_either_side: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        check_parts(self.bundle, self.coordinates, self.form)
        if not isinstance(self.tableau, PartitionedTableau):
            raise TypeError(f"tableau must be a PartitionedTableau, got {type(self.tableau).__name__}.")
        self.stage_solve  # checks the solve's options  # noqa: B018
        if self.coupling not in ("traced", "tableau"):
            raise ValueError(f"coupling must be 'traced' (read from the field's program) or 'tableau', got {self.coupling!r}.")
        if self.explicit_stages not in ("auto", "unrolled", "loop"):
            raise ValueError(f"explicit_stages must be 'auto', 'unrolled' or 'loop', got {self.explicit_stages!r}.")
        for name in ("compensated_sum", "start_either_side"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be True or False, got {getattr(self, name)!r}.")
        if self.explicit_stages == "loop" and not self.tableau.is_explicit:
            raise ValueError(
                f"explicit_stages='loop' needs an explicit tableau (A strictly lower triangular in both parts); {self.tableau.name} is not."
            )

    @property
    def stage_solve(self) -> StageSolve:
        """How this method solves a block of implicit stage slopes."""
        return StageSolve(self.rtol, self.atol, self.max_iterations, self.root_finder, self.iterate_until)

    @property
    def order(self) -> int:
        return self.tableau.order

    @property
    def is_symmetric(self) -> bool:
        return False

    @property
    def has_adjoint_step(self) -> bool:
        return True

    def start_field(self, carried):
        return carried[0]

    def initial_carried(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None):
        """(X(t, y), the same field as every stage slope): a first step starts
        its implicit stages from the field at y."""
        x = self.generator(vector_field, t, y, args)
        return x, tuple(x for _ in range(self.tableau.num_stages))

    def carried_step(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, carried) -> Step:
        """One step, its implicit stages started from the previous step's
        (`carried`), extrapolated (`stages.extrapolated_guesses`)."""
        field_now, guesses = self._warm_start(vector_field, t, y, args, carried)
        return self._step(vector_field, t, y, dt, args, field_now, guesses, stages_solved=False)

    def step_at_stages(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, stages) -> Step:
        """The step from (t, y) whose stage slopes ((K₁, L₁), …, (K_s, L_s))
        solve its stage equations (to round-off): each implicit block is
        evaluated once there (a `root_finder` solves from there)."""
        self.check_vector_field(vector_field, t, y, args)
        check_stage_pairs("stages", stages, self.bundle.algebra_zeros(y), self.tableau.num_stages)
        return self._step(vector_field, t, y, dt, args, self.generator(vector_field, t, y, args), stages, stages_solved=True)

    def adjoint_carried_step(self, vector_field, t, y, dt, args, carried, stages_solved: bool = False) -> Step:
        """A step of the adjoint Φ*_h = (Φ_{−h})⁻¹ (`Adjoint`): the same
        stages centred at the step's end (`_adjoint_step`)."""
        if stages_solved:
            field_now, guesses = self.generator(vector_field, t, y, args), carried[1]
        else:
            field_now, guesses = self._warm_start(vector_field, t, y, args, carried)
        return _adjoint_step(self, vector_field, t, y, dt, args, field_now, guesses, stages_solved)

    def undoing_method(self) -> AbstractMethod:
        """Its adjoint at −h undoes a step: Φ_h⁻¹ = Φ*_{−h}."""
        return Adjoint(self)  # pyright: ignore[reportCallIssue]  # equinox: AbstractVars implemented by properties are not __init__ fields

    def for_reconstruction(self) -> "PRKMK":
        """The product as it is and the iteration from the guess: a state
        rebuilt from a kept one needs round-off, not a long run's refinements."""
        return dataclasses.replace(self, compensated_sum=False, start_either_side=False)

    def step_again(self, vector_field, t, y, dt, args, undone_carried) -> Step:
        """Its adjoint's step at −h solved the same stage equations: their
        slopes are evaluated once (`step_at_stages`)."""
        return self.step_at_stages(vector_field, t, y, dt, args, jax.lax.stop_gradient(undone_carried[1]))

    def stage_plan(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None):
        """The order in which this step finds its stage slopes at (t, y)
        (`stage_plan.plan_stages`; trace-time)."""
        return plan_stages(self.tableau, self.stage_dependence(vector_field, t, y, args))

    def stage_dependence(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None) -> StageDependence:
        """What a stage's slopes depend on, and whether L ≡ 0
        (`stage_plan.stage_dependence`): `COUPLED` when `coupling="tableau"`."""
        if self.coupling == "tableau":
            return COUPLED
        zeros = self.bundle.algebra_zeros(y)
        stage = lambda u, v: self.slope_at(vector_field, t, (u, v), y, args)  # noqa: E731
        return stage_dependence(stage, lambda state: self.generator(vector_field, t, state, args), zeros, y)

    def _warm_start(self, vector_field, t, y, args, carried):
        """(X(tₙ, yₙ), the implicit stages' starting guesses) from `carried`."""
        self.check_vector_field(vector_field, t, y, args)
        zeros = self.bundle.algebra_zeros(y)
        if not (isinstance(carried, (tuple, list)) and len(carried) == 2):
            raise ValueError(f"carried must be (the field at the step's start, the stage slopes), got {jax.tree.structure(carried)}.")
        check_stage_pairs("carried's field", (carried[0],), zeros)
        check_stage_pairs("carried's stage slopes", carried[1], zeros, self.tableau.num_stages)
        field_now = self.generator(vector_field, t, y, args)
        side = start_side(y.fiber) if self.stage_solve.to_round_off and self.start_either_side else None
        return field_now, extrapolated_guesses(field_now, carried, side)

    def _step(self, vector_field, t, y, dt, args, field_now, guesses, stages_solved) -> Step:
        """Algorithm 4.2 from (t, y): the stage slopes (from `guesses`, or
        evaluated once there if `stages_solved`), then
        yₙ₊₁ = f(h Σ bᵢ (Kᵢ, Lᵢ))⊙yₙ."""
        tab = self.tableau
        dtype = jnp.result_type(*jax.tree.leaves(y))
        dt, t = jnp.asarray(dt, dtype), jnp.asarray(t, dtype)
        zeros = self.bundle.algebra_zeros(y)
        field_at_yn = tuple(jnp.asarray(x, dtype) for x in field_now)

        def stage_slope(i, first, second):
            # U_i = h (Σ_j a¹_ij K_j, Σ_j a²_ij L_j), Y_i = f(U_i)⊙yₙ, slope_i = df⁻¹(X_i),
            # summed over the tableau's nonzero entries; a slope still None is
            # zero or, by the plan, one this stage's wanted slopes do not read.
            u = static_combination(dt, tab.a_first[i], first, zeros[0])
            v = static_combination(dt, tab.a_second[i], second, zeros[1])
            tt = t + float(tab.c_first[i]) * dt
            if u is None and v is None:  # U_i = 0: Y_i = yₙ and df⁻¹_0 = I
                return field_at_yn if tab.c_first[i] == 0 else self.generator(vector_field, tt, y, args)
            # v None (no L enters this stage) skips the fiber part of f(U).
            return self.slope_at(vector_field, tt, (zeros[0] if u is None else u, v), y, args)

        plan = self.stage_plan(vector_field, t, y, args)
        if tab.is_explicit:
            slope_at = lambda tt, U: self.slope_at(vector_field, tt, U, y, args)  # noqa: E731
            slopes = explicit_slopes(self.explicit_stages, tab, plan, stage_slope, slope_at, t, dt, zeros, self.bundle.base.algebra_ndim)
            result, iterations = RESULTS.successful, jnp.array(0, jnp.int32)
        else:
            solve = lambda block_slopes, guess: self.stage_solve(block_slopes, guess, dtype, guess_solves=stages_solved)  # noqa: E731
            slopes, result, iterations = slopes_by_plan(plan, tab.num_stages, stage_slope, guesses, solve, dtype)
        return self._push_forward(dt, y, slopes, zeros, result, iterations, field_now)

    def _push_forward(self, dt, y, slopes, zeros, result, iterations, field_now) -> Step:
        """yₙ₊₁ = f(h Σ bᵢ (Kᵢ, Lᵢ))⊙yₙ, a slope None (never computed: L when
        η ≡ 0) left out of the sums. Stages solved to round-off are a fixed
        point of their own formula's rounding, so h·Σ bᵢKᵢ is rounded once
        from its exact value (`_exact_sums`), not by that formula, whose error
        would lean the same way at every step."""
        tab, (first, second) = self.tableau, slopes
        if tab.is_explicit or self.iterate_until != "round-off":
            u_next = static_combination(dt, tab.b_first, first, zeros[0])
        else:
            u_next = rounded_once_combination(dt, tab.b_first, first, zeros[0])
        v_next = static_combination(dt, tab.b_second, second, zeros[1])
        u_next = zeros[0] if u_next is None else u_next
        y_next, rounding = self.advance((u_next, v_next), y, self.compensated_sum)
        increment = (u_next, zeros[1] if v_next is None else v_next)
        stages = tuple(zip(*([z if k is None else k for k in part] for part, z in zip(slopes, zeros))))
        return Step(y_next, increment, flag_nonfinite(result, y_next), iterations, rounding, (field_now, stages))


def _adjoint_step(method: PRKMK, vector_field, t, y, dt, args, field_now, guesses, stages_solved: bool) -> Step:
    """A step of `Adjoint(method)`, its stages started from `guesses` (or,
    `stages_solved`, evaluated once there, as `PRKMK.step_at_stages` does)."""
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
    solved, result, iterations = method.stage_solve(all_slopes, start, dtype, guess_solves=stages_solved)
    stages = tuple((k, zeros[1]) for k in solved) if fiber_free else solved
    first, second = [k for k, _ in stages], [l_i for _, l_i in stages]
    u_next, v_next = increment(first, second)
    if method.iterate_until == "round-off":
        # As PRKMK's step: u rounded once from the solved slopes, not by
        # the formula of which they are a fixed point (`_exact_sums`).
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
