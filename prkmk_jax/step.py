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
connected sets of slopes are solved by fixed-point iteration (or any
optimistix root finder) to `rtol`/`atol` within `max_iterations`, and the
others are evaluated directly. Non-convergence is returned as a
`diffrax.RESULTS` value.
"""

import functools
import math
from typing import Any, Literal

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, PyTree

from .bundles import AbstractBundle, AlgebraPair, BundleElement
from .coordinates import AbstractCoordinates, Exp
from .exact_sums import rounded_once_combination
from .method import RESULTS, AbstractFieldOnBundle, AbstractMethod, Step, Time, VectorField, first_failure, flag_nonfinite, varying_with
from .stage_plan import COUPLED, Explicit, StageDependence, plan_stages, stage_dependence
from .tableaus import PartitionedTableau, stormer_verlet

STAGE_SLOPES_NAME = "prkmk_stage_slopes"

STAGE_LOOP_BATCH = 16
"""From this many trajectories in the state on, `explicit_stages="auto"`
evaluates an explicit tableau's stages in a loop (`PRKMK`)."""


class PRKMK(AbstractMethod):
    """A partitioned Runge–Kutta–Munthe-Kaas method (Algorithm 4.2).

    **Arguments:**

    - `bundle`: the bundle group, e.g. `Cartesian(SO3)` or `Cotangent(SO3)`.
    - `coordinates`: `Exp()` or `Cayley()`, with their truncation.
    - `tableau`: a `PartitionedTableau`, e.g. `stormer_verlet`.
    - `form`: `"space"` for y' = (ξ, η)·y, `"body"` for y' = y·(ξ, η).
    - `rtol`, `atol`: tolerances of the implicit stages (on the slopes);
      default max(1e-12, 50·eps) of the state's dtype.
    - `iterate_until`: when the fixed-point iteration of the implicit stages
      stops. `"round-off"` (default): once within `rtol`/`atol`, it goes on
      while its increments still shrink, and stops when one is zero or no
      smaller than the last (Hairer, McLachlan & Razakarivony, BIT 48, 2008),
      then evaluates the stages once more outside its loop, in the same
      compiled program as the step's update (the loop body is compiled
      apart and may round the same formula differently, a difference that
      would bias every step the same way). The stages are then solved as
      exactly as rounding allows, so a symmetric or symplectic method is
      symmetric or symplectic to round-off, and its energy error grows
      about as the random walk of the rounding errors does (√N over N
      steps) instead of steadily with a bias set by the tolerance. The
      step's increment h·Σ bᵢKᵢ is then computed exactly and rounded once
      (`exact_sums`): rounded by the stages' own formula, of which they are
      a fixed point, its error would lean the same way at every step, a
      bias that overtakes the random walk over millions of steps. The
      rounding of the stage solve itself leans the way the iteration
      approaches its solution from, so each step's iteration starts on
      one side of its extrapolated guess or the other, as the state's
      last bits fall (`extrapolated_guesses`): the leans cancel, where a
      start on the same side at every step would make the energy drift
      (`benchmarks/energy_drift.py` measures the drift on the free body,
      `benchmarks/drift_emulation.py` traces it to the stage solve,
      `benchmarks/round_off.py` fits the growth).
      `"tolerance"`: it stops at `rtol`/`atol`, a few iterations a step
      sooner. `benchmarks/round_off.py` measures both: the growth exponent
      and the cost.
      An optimistix `root_finder` stops by its own tolerances.
    - `compensated_sum`: how the step's change is added to the state.
      True (default): computed with the state kept out of it, added, and
      what the sum loses to rounding handed on (`Step.rounding`), which the
      drivers carry into the next step's sum (`compensated`): a long run's
      rounding error then grows with that of the steps' changes, several
      times smaller than with the state rounded at each step. False: the
      product f(U)⊙y as it is, a little quicker a step
      (`benchmarks/against_revision.py` measures both), for runs too short
      to notice.
    - `start_either_side`: with `iterate_until="round-off"` and no
      `root_finder`, where each step's stage iteration starts. True
      (default): on the side of the extrapolated guess that the state's last
      bits pick, so that the leans of the round-off solve cancel. False: at
      the guess, about one iteration a step fewer, and the energy drifts
      with the lean; the reversible backward pass undoes steps so, since it
      needs each state rebuilt to round-off, not a drift without bias.
    - `max_iterations`: iteration cap of each implicit block's loop (with
      `iterate_until="round-off"` one more evaluation follows it).
    - `root_finder`: an optimistix fixed-point solver or root finder (e.g.
      `optx.Newton(rtol, atol)`); default fixed-point iteration, which
      converges when h times the field's Lipschitz constant is below 1 and
      slows down as it approaches 1 (symmetric rigid body at h = 0.1: ~94
      iterations a step, Newton: 4).
    - `coupling`: how the step decides which stage slopes it solves for
      together. `"traced"` (default) reads from the traced program of one
      stage which slopes each depends on (`stage_plan`): a field with η ≡ 0
      (the free rigid body) has L ≡ 0, so Störmer–Verlet's first stage is
      explicit; a separable field (4.15) on `DirectProduct` or `Cartesian`
      with df⁻¹ = I makes symplectic Euler and Störmer–Verlet explicit.
      `"tableau"` assumes every slope depends on the whole stage point, so
      the A matrices alone decide. Both give the same trajectory to the
      stage tolerance.
    - `explicit_stages`: how an explicit tableau (both A matrices strictly
      lower triangular, e.g. `dormand_prince_8`) is laid out in the
      program. `"unrolled"`: every stage written out, which runs fastest for
      one trajectory. `"loop"`: one stage in a `lax.fori_loop` over the
      stages, the slopes in one array: XLA fuses each slope's arithmetic
      into every later stage that reads it, so an unrolled many-stage step
      on a batch recomputes early stages many times over, and the loop
      computes each once. `"auto"` (default) takes the loop for a state
      carrying at least `STAGE_LOOP_BATCH` trajectories, the
      unrolled stages otherwise; under `jax.vmap` the step sees one
      trajectory and keeps them unrolled, which is also the faster layout
      there (a vmapped loop indexes its slope arrays per trajectory).
      `benchmarks/stage_layout.py` measures both. They give the same
      trajectory up to rounding.
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
        if not isinstance(self.bundle, AbstractBundle):
            raise TypeError(f"bundle must be a bundle group such as Cartesian(SO3), got {self.bundle!r}.")
        if not isinstance(self.coordinates, AbstractCoordinates):
            raise TypeError(f"coordinates must be an AbstractCoordinates such as Exp() or Cayley(), got {self.coordinates!r}.")
        if not isinstance(self.tableau, PartitionedTableau):
            raise TypeError(f"tableau must be a PartitionedTableau, got {type(self.tableau).__name__}.")
        if self.form not in ("space", "body"):
            raise ValueError(f"form must be 'space' (y' = X·y) or 'body' (y' = y·X), got {self.form!r}.")
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0):
                raise ValueError(f"{name} must be None (the default) or a number ≥ 0, got {value!r}.")
        if self.rtol == 0 and self.atol == 0:
            raise ValueError("rtol and atol cannot both be 0: the implicit stages could never stop.")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"max_iterations must be a positive int, got {self.max_iterations!r}.")
        if self.root_finder is not None and not isinstance(self.root_finder, (optx.AbstractFixedPointSolver, optx.AbstractRootFinder)):
            raise TypeError("root_finder must be an optimistix fixed-point solver or root finder.")
        if self.coupling not in ("traced", "tableau"):
            raise ValueError(f"coupling must be 'traced' (read from the field's program) or 'tableau', got {self.coupling!r}.")
        if self.explicit_stages not in ("auto", "unrolled", "loop"):
            raise ValueError(f"explicit_stages must be 'auto', 'unrolled' or 'loop', got {self.explicit_stages!r}.")
        if not isinstance(self.compensated_sum, bool):
            raise TypeError(f"compensated_sum must be True or False, got {self.compensated_sum!r}.")
        if not isinstance(self.start_either_side, bool):
            raise TypeError(f"start_either_side must be True or False, got {self.start_either_side!r}.")
        if self.iterate_until not in ("round-off", "tolerance"):
            raise ValueError(
                "iterate_until must be 'round-off' (until the increments stop shrinking) or 'tolerance' (rtol/atol), "
                f"got {self.iterate_until!r}."
            )
        if self.explicit_stages == "loop" and not self.tableau.is_explicit:
            raise ValueError(
                f"explicit_stages='loop' needs an explicit tableau (A strictly lower triangular in both parts); {self.tableau.name} is not."
            )
        self.coordinates.check_bundle(self.bundle)

    @property
    def order(self) -> int:
        return self.tableau.order

    @property
    def is_symmetric(self) -> bool:
        return False

    def start_field(self, carried):
        return carried[0]

    def check_fits(self, vector_field: VectorField) -> None:
        """Any field on the bundle (its shapes are checked by
        `check_vector_field`); a field that names its bundle and form (a
        scene, `AbstractFieldOnBundle`) must name this method's."""
        if not isinstance(vector_field, AbstractFieldOnBundle):
            return
        name = type(vector_field).__name__
        if eqx.tree_equal(vector_field.bundle, self.bundle) is not True:
            raise ValueError(
                f"{name} lives on {vector_field.bundle!r}, but this method was built for {self.bundle!r}: the same generator on "
                f"another bundle is another system. Build the method from the scene (scene.method(tableau)) or on its bundle."
            )
        if vector_field.form != self.form:
            raise ValueError(
                f"{name} is written in {vector_field.form} form, but this method steps in {self.form} form: "
                f"build it with form={vector_field.form!r} (scene.method(tableau) does)."
            )

    def initial_carried(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None):
        """(X(t, y), the same field as every stage slope): a first step starts
        its implicit stages from the field at y."""
        x = self.generator(vector_field, t, y, args)
        return x, tuple(x for _ in range(self.tableau.num_stages))

    def carried_step(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, carried) -> Step:
        """One step, the implicit stages started from the previous step's
        stage slopes, each moved as much as the field at the step's start
        moved over that step: Kᵢ ≈ Kᵢ_prev + X(tₙ, yₙ) − X(tₙ₋₁, yₙ₋₁), an O(h²)
        guess where X(tₙ, yₙ) alone is O(h); solved to round-off, the
        iteration starts at an O(h) offset to one side of that guess or the
        other (`extrapolated_guesses`). `carried` is (X(tₙ₋₁, yₙ₋₁),
        ((K₁, L₁), …, (K_s, L_s))) from the previous step (or
        `initial_carried`); the step hands on (X(tₙ, yₙ), its own slopes)."""
        self.check_vector_field(vector_field, t, y, args)
        zeros = self.bundle.algebra_zeros(y)
        if not (isinstance(carried, (tuple, list)) and len(carried) == 2):
            raise ValueError(f"carried must be (the field at the step's start, the stage slopes), got {jax.tree.structure(carried)}.")
        _check_pairs("carried's field", (carried[0],), zeros)
        _check_pairs("carried's stage slopes", carried[1], zeros, self.tableau.num_stages)
        field_now, guesses = self.extrapolated_guesses(vector_field, t, y, args, carried)
        y_next, rounding, increment, result, iterations, stages = self._solve_step(vector_field, t, y, dt, args, field_now, guesses)
        return Step(y_next, increment, result, iterations, rounding, (field_now, stages))

    def step_at_stages(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, stages) -> Step:
        """The step from (t, y) whose stage slopes ((K₁, L₁), …, (K_s, L_s))
        are known to solve its stage equations (to round-off; say, from the
        `Adjoint` step at −h that undid it, which solves the same equations):
        each implicit block is evaluated once at them instead of iterated,
        and differentiated as a solved block is (the implicit function
        theorem). With a `root_finder` the blocks are solved from these
        slopes as `carried_step` solves them. `ReversibleGradient` runs a
        step again this way for its VJP."""
        self.check_vector_field(vector_field, t, y, args)
        _check_pairs("stages", stages, self.bundle.algebra_zeros(y), self.tableau.num_stages)
        field_now = self.generator(vector_field, t, y, args)
        y_next, rounding, increment, result, iterations, solved = self._solve_step(vector_field, t, y, dt, args, field_now, stages, True)
        return Step(y_next, increment, result, iterations, rounding, (field_now, solved))

    def extrapolated_guesses(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree, carried):
        """(X(tₙ, yₙ), the stage guesses) from what the previous step carried
        (see `carried_step`): Gᵢ = Kᵢ_prev + X(tₙ, yₙ) − X(tₙ₋₁, yₙ₋₁).

        With the stages solved to round-off by fixed-point iteration (the
        default) and `start_either_side`, the iteration starts on one side
        of Gᵢ or the other, at Gᵢ ± Dᵢ with Dᵢ = Kᵢ_prev − X(tₙ₋₁, yₙ₋₁) (so
        that the − side is the field at the step's start), the side set by
        the parity of the lowest bits of yₙ's fiber (`_start_side`). At
        round-off, where the iteration settles depends on the direction it
        comes from, and a start on the same side at every step makes the
        energy error drift the same way at every step; starts on either side
        at random cancel that drift (`benchmarks/energy_drift.py`). The O(h)
        offset costs about one iteration a step more than starting at Gᵢ,
        the start otherwise."""
        previous_field, previous_stages = carried
        field_now = self.generator(vector_field, t, y, args)
        change = jax.tree.map(jnp.subtract, field_now, previous_field)
        guesses = tuple(jax.tree.map(jnp.add, stage, change) for stage in previous_stages)
        if self.iterate_until != "round-off" or self.root_finder is not None or not self.start_either_side:
            return field_now, guesses
        side = _start_side(y.fiber)
        offsets = tuple(jax.tree.map(jnp.subtract, stage, previous_field) for stage in previous_stages)
        return field_now, tuple(
            jax.tree.map(lambda g, d: g + side.astype(g.dtype) * d, guess, offset) for guess, offset in zip(guesses, offsets)
        )

    def _solve_step(
        self,
        vector_field: VectorField,
        t: Time,
        y: BundleElement,
        dt: Time,
        args: PyTree,
        field_at_start: AlgebraPair,
        stage_guesses: tuple[AlgebraPair, ...],
        stages_solved: bool = False,
    ):
        """One step from (t, y) to t + dt. Returns (y_next, its rounding
        (`advance`), increment, result, iterations, stage slopes ((K₁, L₁), …,
        (K_s, L_s))).

        `field_at_start` is `generator(vector_field, t, y, args)`, used where
        the step needs the field at (t, y) (explicit stages with U = 0 at
        c = 0); `stage_guesses` are the implicit stages' starting values, one
        (K_i, L_i) per stage, or with `stages_solved` their solution
        (`solve_implicit`)."""
        tab = self.tableau
        dtype = jnp.result_type(*jax.tree.leaves(y))
        dt = jnp.asarray(dt, dtype)
        t = jnp.asarray(t, dtype)
        zeros = self.bundle.algebra_zeros(y)
        field_at_yn = tuple(jnp.asarray(x, dtype) for x in field_at_start)

        def field(tt, Y):
            return self.generator(vector_field, tt, Y, args)

        def stage_slope(i, first, second):
            # U_i = h (Σ_j a¹_ij K_j, Σ_j a²_ij L_j), Y_i = f(U_i)⊙yₙ, slope_i = df⁻¹(X_i).
            # The sums run over the tableau's nonzero entries only (static
            # numbers), so XLA fuses them with the stage's arithmetic. A slope
            # still None is zero or, by the plan, one this stage's wanted
            # slopes do not depend on.
            u = static_combination(dt, tab.a_first[i], first, zeros[0])
            v = static_combination(dt, tab.a_second[i], second, zeros[1])
            tt = t + float(tab.c_first[i]) * dt
            if u is None and v is None:  # U_i = 0: Y_i = yₙ and df⁻¹_0 = I
                return field_at_yn if tab.c_first[i] == 0 else field(tt, y)
            # v None (no L enters this stage: L ≡ 0, or a zero row of A²) stays
            # None: the stage point then skips the fiber part of f(U).
            return self.slope_at(vector_field, tt, (zeros[0] if u is None else u, v), y, args)

        plan = self.stage_plan(vector_field, t, y, args)
        if self._stages_in_loop(zeros):
            first, second = self._explicit_slopes_in_loop(vector_field, stage_slope, plan, t, y, dt, args, zeros)
            return self._finish_step(dt, y, first, second, zeros, RESULTS.successful, jnp.array(0, jnp.int32))
        slopes: list[list] = [[None] * tab.num_stages, [None] * tab.num_stages]
        result = RESULTS.successful
        iterations = jnp.array(0, jnp.int32)
        for part in plan:
            if isinstance(part, Explicit):
                pair = stage_slope(part.stage, *slopes)
                for c in part.components:
                    slopes[c][part.stage] = pair[c]
                continue

            def block_slopes(block, part=part):
                trial = [list(slopes[0]), list(slopes[1])]
                for (i, c), value in zip(part.slopes, block):
                    trial[c][i] = value
                pairs = {i: stage_slope(i, *trial) for i in part.stages}
                return tuple(pairs[i][c] for i, c in part.slopes)

            guess = tuple(jnp.asarray(stage_guesses[i][c], dtype) for i, c in part.slopes)
            block, block_result, n = self.solve_implicit(block_slopes, guess, dtype, guess_solves=stages_solved)
            result = first_failure(result, block_result)
            iterations = iterations + n
            for (i, c), value in zip(part.slopes, block):
                slopes[c][i] = value
        return self._finish_step(dt, y, slopes[0], slopes[1], zeros, result, iterations)

    def _finish_step(self, dt, y, first, second, zeros, result, iterations):
        """y_{n+1} = f(h Σ bᵢ (Kᵢ, Lᵢ))⊙yₙ and what `_solve_step` returns;
        a slope None is one the plan never computed, identically zero (L when
        η ≡ 0), and is left out of the sums."""
        tab = self.tableau
        if tab.is_explicit or self.iterate_until != "round-off":
            u_next = static_combination(dt, tab.b_first, first, zeros[0])
        else:
            # Rounded once from its exact value, not by the formula of the
            # stages: stages solved to round-off are a fixed point of that
            # formula's rounding, whose error in h·Σ bᵢKᵢ would then lean the
            # same way at every step (see `exact_sums`).
            u_next = rounded_once_combination(dt, tab.b_first, first, zeros[0])
        v_next = static_combination(dt, tab.b_second, second, zeros[1])
        u_next = zeros[0] if u_next is None else u_next
        y_next, rounding = self.advance((u_next, v_next), y, self.compensated_sum)
        increment = (u_next, zeros[1] if v_next is None else v_next)
        stages = tuple(zip(*([z if k is None else k for k in slopes] for slopes, z in zip((first, second), zeros))))
        return y_next, rounding, increment, flag_nonfinite(result, y_next), iterations, stages

    def _stages_in_loop(self, zeros) -> bool:
        """Whether this step evaluates its (explicit) stages in a loop (see
        `explicit_stages`)."""
        if self.explicit_stages != "auto":
            return self.explicit_stages == "loop"
        batch_shape = zeros[0].shape[: zeros[0].ndim - self.bundle.base.algebra_ndim]
        return self.tableau.is_explicit and math.prod(batch_shape) >= STAGE_LOOP_BATCH

    def _explicit_slopes_in_loop(self, vector_field, stage_slope, plan, t, y, dt, args, zeros):
        """The slopes of an explicit tableau, stage after stage in a
        `lax.fori_loop`: stage i reads the rows A¹ᵢ, A²ᵢ and the slopes found
        so far (zeros in the later entries, which the strictly lower
        triangular rows do not reach). Returns the two lists of slopes,
        None for a component the plan never computes (L when η ≡ 0)."""
        tab = self.tableau
        dtype = zeros[0].dtype
        computed = {c for part in plan for c in part.components}
        first_slope = stage_slope(0, [None] * tab.num_stages, [None] * tab.num_stages)
        buffers = []
        for c, zero in enumerate(zeros):
            buffer = jnp.zeros((tab.num_stages, *zero.shape), dtype)
            buffers.append(buffer.at[0].set(first_slope[c]) if c in computed else buffer)
        a_first, a_second, c_first = (jnp.asarray(x, dtype) for x in (tab.a_first, tab.a_second, tab.c_first))

        def one_stage(i, buffers):
            first, second = buffers
            u = dt * jnp.tensordot(a_first[i], first, axes=1)
            v = dt * jnp.tensordot(a_second[i], second, axes=1) if 1 in computed else None
            pair = self.slope_at(vector_field, t + c_first[i] * dt, (u, v), y, args)
            return tuple(b.at[i].set(p) if c in computed else b for c, (b, p) in enumerate(zip(buffers, pair)))

        buffers = jax.lax.fori_loop(1, tab.num_stages, one_stage, tuple(buffers))
        return tuple(list(b) if c in computed else [None] * tab.num_stages for c, b in enumerate(buffers))

    def stage_plan(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None):
        """The order in which this step finds its stage slopes at (t, y)
        (`stage_plan.plan_stages`; trace-time, from the field's program
        when `coupling="traced"`)."""
        return plan_stages(self.tableau, self.stage_dependence(vector_field, t, y, args))

    def stage_dependence(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None) -> StageDependence:
        """What a stage's slopes depend on, and whether L ≡ 0
        (`stage_plan.stage_dependence`; trace-time): `COUPLED` when
        `coupling="tableau"`."""
        if self.coupling == "tableau":
            return COUPLED
        zeros = self.bundle.algebra_zeros(y)

        def stage(u, v):
            return self.slope_at(vector_field, t, (u, v), y, args)

        return stage_dependence(stage, lambda state: self.generator(vector_field, t, state, args), zeros, y)

    def solve_implicit(self, block_slopes, guess, dtype, guess_solves: bool = False):
        """Solve block_slopes(K) = K for the slopes K of an implicit block
        from `guess`, with this method's root finder and tolerances; returns
        (K, result, iterations). `guess_solves`: the guess is the solution
        (to round-off), evaluated once by the default iteration
        (`_fixed_point_iteration`); a root finder solves from it."""
        eps = float(jnp.finfo(dtype).eps)
        default_tol = max(1e-12, 50 * eps)
        rtol = default_tol if self.rtol is None else self.rtol
        atol = default_tol if self.atol is None else self.atol
        root_finder = self.root_finder
        if root_finder is None:
            return _fixed_point_iteration(
                block_slopes,
                guess,
                rtol,
                atol,
                self.max_iterations,
                dtype,
                until_round_off=self.iterate_until == "round-off",
                guess_solves=guess_solves,
            )
        fn = lambda z, _: block_slopes(z)  # noqa: E731
        if isinstance(root_finder, optx.AbstractFixedPointSolver):
            sol = optx.fixed_point(fn, root_finder, guess, max_steps=self.max_iterations, throw=False)
        else:
            sol = optx.root_find(
                lambda z, a: jax.tree.map(jnp.subtract, fn(z, a), z), root_finder, guess, max_steps=self.max_iterations, throw=False
            )
        return sol.value, RESULTS.promote(sol.result), sol.stats["num_steps"].astype(jnp.int32)


def _check_pairs(name, pairs, zeros, count=None):
    """Trace-time check that `pairs` is None or a sequence of `count` algebra
    pairs (ξ, η) with the shapes of `zeros`."""
    if pairs is None:
        return
    if not isinstance(pairs, (tuple, list)) or (count is not None and len(pairs) != count):
        raise ValueError(f"{name} must be a tuple of {count or 1} algebra pairs (ξ, η), got {jax.tree.structure(pairs)}.")
    for pair in pairs:
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2) or any(
            tuple(jnp.shape(x)) != tuple(z.shape) for x, z in zip(pair, zeros)
        ):
            raise ValueError(
                f"{name}: every entry must be a pair (ξ, η) of shapes {tuple(z.shape for z in zeros)}, got {jax.tree.map(jnp.shape, pair)}."
            )


def static_combination(dt, coefficients, slopes, zero):
    """dt·Σ_j coefficients[j]·slopes[j] over the nonzero (static) coefficients
    and the slopes that are not None (zero, or not needed: see `stage_plan`),
    or None when no term is left.

    Three terms or more are summed as one contraction of the stacked slopes:
    XLA then computes each slope once, where a chain of multiply-adds lets it
    fuse (and so recompute) each slope's whole arithmetic into every stage
    that sums it (`benchmarks/against_revision.py`, `benchmarks/stage_layout.py`)."""
    terms = [(c, slope) for c, slope in zip(coefficients, slopes) if c != 0 and slope is not None]
    if not terms:
        return None
    if len(terms) >= 3:
        weights = jnp.asarray([c for c, _ in terms], zero.dtype)
        return dt * jnp.tensordot(weights, jnp.stack([slope for _, slope in terms]), axes=1)
    acc = None
    for c, slope in terms:
        term = slope if c == 1 else jnp.asarray(c, zero.dtype) * slope
        acc = term if acc is None else acc + term
    return dt * acc


_UNSIGNED_OF_WIDTH = {2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint64}


def _start_side(fiber: PyTree) -> Array:
    """+1 or −1: the parity of the sum of the lowest bits of the fiber's
    entries (their binary representation). A deterministic choice that
    the rounding of each step changes at random, with no state to carry;
    with a batch in the state, one choice for the whole batch."""
    parity = 0
    for leaf in jax.tree.leaves(fiber):
        bits = jax.lax.bitcast_convert_type(leaf, _UNSIGNED_OF_WIDTH[jnp.dtype(leaf.dtype).itemsize])
        parity = parity + jnp.sum(bits & 1)
    return jnp.where(parity % 2 == 0, 1, -1)


def _fixed_point_iteration(fn, guess, rtol, atol, max_iterations, dtype, until_round_off=True, guess_solves=False):
    """z ← fn(z) from `guess` until the scaled increment
    eₖ = max|zₖ₊₁ − zₖ|/(atol + rtol|zₖ₊₁|) is below 1 (the criterion of
    `optx.FixedPointIteration` with `optx.max_norm`) and, when
    `until_round_off`, further until eₖ is 0 or no smaller than eₖ₋₁ (the
    stopping rule of Hairer, McLachlan & Razakarivony, BIT 48, 2008, which
    leaves z where rounding alone moves it), and once more outside the
    loop. At most `max_iterations` times in the loop; a success when the
    last eₖ < 1. Returns (z, result, iterations). With `guess_solves` the
    guess is taken as the solution: z = fn(guess), one evaluation, a
    success where it moved the guess by less than the tolerance (e < 1).

    A bare `lax.while_loop` carrying only the iterate, its error, the
    previous error and a counter: under `vmap` every carried value costs a
    select per iteration, so this carries no more. Derivatives come from the implicit function theorem, as
    a `jax.custom_jvp` whose rule is traced only when the step is
    differentiated: the tangent system (I − ∂fn/∂z)ż = ∂fn/∂θ·θ̇, and in
    reverse mode its transpose, are solved by the same fixed-point iteration
    on the linearised map (`jax.lax.custom_linear_solve`): a few
    Jacobian-vector (or vector-Jacobian) products a step, no dense Jacobian.
    """
    # The stage inputs fn closes over (yₙ, h, args, earlier slopes; floats and
    # integers alike) become explicit leaves of `closed_fn`, so the JVP rule can
    # differentiate with respect to them and no tracer is captured.
    closed_fn = eqx.filter_closure_convert(fn, guess)
    settings = _IterationSettings(
        float(rtol), float(atol), int(max_iterations), jnp.dtype(dtype), bool(until_round_off), bool(guess_solves)
    )
    dynamic, static = eqx.partition(closed_fn, eqx.is_array)
    z, error, n = _solve_fixed_point(settings, static, guess, dynamic)
    result = RESULTS.where(error < 1, RESULTS.successful, RESULTS.nonlinear_max_steps_reached)  # pyright: ignore[reportArgumentType]  # an Enumeration member is typed as its Literal
    return z, result, n


class _IterationSettings(eqx.Module):
    """The static settings of one fixed-point solve (hashable, for custom_jvp)."""

    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    dtype: Any = eqx.field(static=True)
    until_round_off: bool = eqx.field(static=True)
    guess_solves: bool = eqx.field(static=True)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _solve_fixed_point(settings, static, guess, dynamic):
    closed_fn = eqx.combine(dynamic, static)
    rtol, atol, dtype = settings.rtol, settings.atol, settings.dtype

    def relative_change(new, old):
        ratios = [jnp.max(jnp.abs(o - n) / (atol + rtol * jnp.abs(n))) for n, o in zip(jax.tree.leaves(new), jax.tree.leaves(old))]
        return functools.reduce(jnp.maximum, ratios)

    def keep_going(carry):
        _, error, previous, n = carry
        unfinished = error >= 1
        if settings.until_round_off:
            # Within tolerance, go on while the increments still shrink: they
            # stop shrinking where rounding, not the iteration, sets them.
            unfinished = unfinished | ((error > 0) & (error < previous))
        return unfinished & (n < settings.max_iterations)

    def iterate(carry):
        z, error, _, n = carry
        new = closed_fn(z)
        return new, relative_change(new, z), error, n + 1

    if settings.guess_solves:
        # Checked, not trusted: a guess that fn moves by more than the
        # tolerance is not a solution, and the result says so.
        z = closed_fn(guess)
        return z, relative_change(z, guess), jnp.array(1, jnp.int32)
    # NaN never compares below 1, so a non-finite iterate ends the loop too.
    inf = jnp.asarray(jnp.inf, dtype)
    z, error, _, n = jax.lax.while_loop(keep_going, iterate, (guess, *varying_with((inf, inf, jnp.array(0, jnp.int32)), guess)))
    if settings.until_round_off:
        # One more evaluation, outside the loop: XLA compiles the loop body
        # apart from the rest of the step and may round the same formula
        # differently there (fusion, contraction). The step's update rounds
        # as this evaluation does, so the slopes are closer to a fixed point
        # of the arithmetic that makes the new state, and less of a rounding
        # difference between the two biases every step the same way
        # (`benchmarks/round_off.py` fits how a long run's energy error grows).
        z = closed_fn(z)
        n = n + 1
    return z, error, n


@_solve_fixed_point.defjvp
def _solve_fixed_point_jvp(settings, static, primals, tangents):
    guess, dynamic = primals
    _, dynamic_dot = tangents  # the solution does not depend on the guess
    z, error, n = _solve_fixed_point(settings, static, guess, dynamic)
    closed_fn = eqx.combine(dynamic, static)
    # Named, so that a rematerialised step (`integrate` under reverse mode)
    # keeps the solution instead of iterating to it again.
    z = checkpoint_name(z, STAGE_SLOPES_NAME)
    # ż = ∂fn/∂z·ż + ∂fn/∂θ·θ̇, i.e. (I − ∂fn/∂z)ż = rhs.
    _, rhs = jax.jvp(lambda d: eqx.combine(d, static)(z), (dynamic,), (dynamic_dot,))
    _, linearised = jax.linearize(closed_fn, z)
    # One flat vector: custom_linear_solve's transpose needs every part of
    # the right-hand side to be linear in the tangents, and some parts of
    # a stage block (say L when η does not depend on the parameters) are
    # constant zeros.
    flat_rhs, unflatten = jax.flatten_util.ravel_pytree(rhs)

    def identity_minus_jacobian(x):
        return x - jax.flatten_util.ravel_pytree(linearised(unflatten(x)))[0]

    def iterate_linear(matvec, b):
        # (I − J)x = b with J a contraction wherever the nonlinear iteration
        # converged: x ← x − matvec(x) + b = Jx + b converges as fast. The same
        # loop solves the transposed system in reverse mode, with Jᵀ.
        def keep_going(carry):
            _, change, k = carry
            return (change > 0) & (k < settings.max_iterations)

        def step(carry):
            x, _, k = carry
            new = x - matvec(x) + b
            size = jnp.max(jnp.abs(new - x)) - settings.rtol * jnp.max(jnp.abs(new))
            return new, size, k + 1

        x, _, _ = jax.lax.while_loop(keep_going, step, (b, *varying_with((jnp.asarray(jnp.inf, b.dtype), jnp.array(0, jnp.int32)), b)))
        return x

    z_dot = unflatten(jax.lax.custom_linear_solve(identity_minus_jacobian, flat_rhs, iterate_linear, iterate_linear))
    # The error and the count are not differentiable (the count's tangent is float0).
    zero_aux = (jnp.zeros_like(error), np.zeros(np.shape(n), jax.dtypes.float0))
    return (z, error, n), (z_dot, *zero_aux)
