"""PRKMK as a diffrax solver: `diffrax.diffeqsolve(PRKMKTerm(f), PRKMKSolver(method), ...)`.

The state is a `BundleElement` and the vector field returns the generator
(ξ, η), an algebra pair of another shape than the state, which diffrax's
`ODETerm` (dy/dt) cannot express; `PRKMKTerm` carries it instead.
"""

from collections.abc import Callable
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._bundles import AlgebraPair, BundleElement
from ._interpolation import OnGroupInterpolation
from ._loop import checked_start
from .methods.base import AbstractMethod, compensated, first_failure, no_compensation, tree_scale

DENSE_OUTPUT_TRUNCATION_ORDER = 4
"""Dense output evaluates df⁻¹ at the step's end truncated as for a method of
at least this order, whatever the method's own: the cubic Hermite
interpolant (`OnGroupInterpolation`) needs its end slope to O(h³)."""


class PRKMKTerm(diffrax.AbstractTerm):
    """A vector field `f(t, y, args) -> (ξ, η)` on a bundle group, the
    generator of y' = (ξ, η)·y or y' = y·(ξ, η) (the solver's `form`)."""

    vector_field: Callable[..., AlgebraPair]

    def vf(self, t, y, args):
        if not isinstance(y, BundleElement):
            raise TypeError(f"a PRKMKTerm's state is a BundleElement(base, fiber), got {type(y).__name__}.")
        return self.vector_field(t, y, args)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        # Only a Euclidean solver (Tsit5, …, or BacksolveAdjoint's adjoint term)
        # forms f·dt, reading it as an increment of y; for a generator that is
        # meaningless, and PRKMKSolver never calls it.
        raise NotImplementedError(_EUCLIDEAN_USE)

    def vf_prod(self, t, y, args, control):
        raise NotImplementedError(_EUCLIDEAN_USE)


_EUCLIDEAN_USE = (
    "PRKMKTerm's vector field is a Lie-algebra generator (ξ, η), not dy/dt, so it cannot be used by a Euclidean "
    "solver or by BacksolveAdjoint, which solves the continuous adjoint equations as if the state were Euclidean. "
    "Use PRKMKSolver with RecursiveCheckpointAdjoint (the default), DirectAdjoint, ForwardMode or ReversibleAdjoint."
)


class _UserClock(eqx.Module):
    """The user's vector field, in the user's clock, from the terms
    diffeqsolve hands a solver.

    diffeqsolve runs a backward solve (t1 < t0) in the clock −t and wraps
    the term so that `terms.vf(τ, y, args)` is f(±τ, y, args); the control
    of the unit interval, `terms.contr(0, 1)`, is that sign (a
    `PRKMKTerm`'s control is t1 − t0). The step then runs in the user's
    clock, from s₀ = ±t₀ with step ±(t₁ − t₀)."""

    terms: diffrax.AbstractTerm
    direction: Array

    def __call__(self, s, y, args):
        return self.terms.vf(self.direction * s, y, args)


def _user_clock(terms) -> _UserClock:
    return _UserClock(terms, jnp.asarray(terms.contr(0, 1)))


def _check_terms(terms, y0) -> PRKMKTerm:
    """Refuse, by name, terms and states that only a Euclidean solve
    produces; return the user's `PRKMKTerm`."""
    if isinstance(y0, tuple) and len(y0) == 4 and isinstance(y0[0], BundleElement):
        # BacksolveAdjoint's backward solve: state (y, a_y, a_args, a_terms).
        raise NotImplementedError(_EUCLIDEAN_USE)
    # diffeqsolve may wrap the user's term (a backward-in-time solve), so look
    # for a PRKMKTerm anywhere in the terms' tree.
    found = [node for node in jax.tree.leaves(terms, is_leaf=lambda node: isinstance(node, PRKMKTerm)) if isinstance(node, PRKMKTerm)]
    if not found:
        raise TypeError(
            f"PRKMKSolver needs its vector field as a PRKMKTerm(f) with f(t, y, args) -> (ξ, η), "
            f"got {type(terms).__name__}; an ODETerm's dy/dt has no meaning on the group."
        )
    return found[0]


class PRKMKSolver(diffrax.AbstractSolver):
    """Runs a `PRKMK` method inside `diffrax.diffeqsolve`.

    Fixed steps (`ConstantStepSize`, `StepTo`) give the same values as
    `integrate`; dense output (`SaveAt(ts=...)`, `SaveAt(dense=True)`,
    `Solution.evaluate`) is `OnGroupInterpolation`, of order min(p, 3).
    Gradients: `RecursiveCheckpointAdjoint` (default), `DirectAdjoint`,
    `ForwardMode`, and `ReversibleAdjoint` for fixed steps (the states
    rebuilt backwards, `reversible_adjoint`). `BacksolveAdjoint` is refused, with this library's message,
    when its backward solve starts: that solve hands the solver diffrax's
    adjoint term and an augmented Euclidean state (its continuous adjoint
    treats the state as Euclidean). Its forward solve is the plain solve.
    For a known number of fixed steps, `RecursiveCheckpointAdjoint(
    checkpoints=num_steps)` recomputes each step once in the backward pass;
    diffrax's default keeps fewer checkpoints and recomputes more.

    The solver state carries the previous step's field at its start and its
    stage slopes (the implicit stages start from them as `integrate` does),
    and what the steps' sums lost to rounding, carried on as `integrate`
    carries it (`compensated`).

    Batches: `jax.vmap` over `diffeqsolve` keeps each trajectory's own stage
    iterations and result. diffrax's step loop stops on the result, so under
    `vmap` its stop condition is per trajectory and it selects its whole
    state every step. A state with a leading batch axis (where the field
    broadcasts over it, as the scenes' fields do) runs as one solve instead:
    its stages iterate until every trajectory has converged, and its result
    is one value for the batch, so one trajectory's failed stage fails the
    solve. For fixed steps that route costs about what `integrate` does
    (`docs/design-notes.md`). With an optimistix root finder that forms a
    Jacobian (`root_finder=optx.Newton(...)`), the Jacobian would then span
    the whole batch: keep `vmap` there.
    """

    method: AbstractMethod
    adaptive: bool = eqx.field(static=True, default=False)
    """Estimate the local error by step doubling (one step of h against two of
    h/2), for `PIDController`, and carry the two-half-step state on (as
    `diffrax.HalfSolver` does). Costs three steps' work per step. Dense output
    still interpolates the full step, so between steps it may differ from the
    carried state by up to the local error estimate (it stays on the group).
    Adaptive steps forfeit the exact symplecticity of a fixed-step method."""
    # Any term passes diffrax's own check, so that `init` can refuse what is
    # not a PRKMKTerm (an ODETerm, BacksolveAdjoint's adjoint term) with this
    # library's explanation rather than diffrax's generic mismatch.
    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar = OnGroupInterpolation

    def __check_init__(self):
        if not isinstance(self.method, AbstractMethod):
            raise TypeError(
                f"PRKMKSolver wraps a PRKMK method, a Splitting, or a method built from them, got {type(self.method).__name__}."
            )

    def order(self, terms):
        return self.method.order

    def error_order(self, terms):
        # Both estimates have order p: their difference is O(h^{p+1}).
        return self.method.order + 1 if self.adaptive else None

    def init(self, terms, t0, t1, y0, args):
        term = _check_terms(terms, y0)
        method, field = self.method, _user_clock(terms)
        # Static type/shape errors now; the run-time checks of the data (a
        # finite, orthogonal, det +1 base; a scene's parameters) act through
        # the checked values, kept alive below: an invalid y0 raises.
        y0, _, checked_args = checked_start(method, term.vector_field, y0, field.direction * t0, args, called=field)
        # The solver state is what a step carries (`Step.carried`): the
        # previous step's field at its start and its stage slopes, the implicit
        # stages' starting guesses (as in `integrate`).
        carried = method.initial_carried(field, field.direction * t0, y0, args)
        # The field may not read every part of y0 (the free body ignores the
        # attitude), and XLA would then drop those checks as dead code. A zero
        # that depends on every checked entry keeps them alive (XLA does not fold
        # 0·x for floats; the `where` keeps an infinite parameter from making it NaN).
        checked = [leaf for leaf in jax.tree.leaves((y0, checked_args)) if eqx.is_inexact_array(leaf)]
        zero = jnp.asarray(sum(jnp.sum(jnp.where(jnp.isfinite(leaf), leaf, 0) * 0) for leaf in checked))
        # With it, what the steps' sums lost to rounding (`compensated`), as
        # `integrate` carries it: nothing yet.
        return jax.tree.map(lambda x: x + zero.astype(x.dtype), carried), no_compensation(y0)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump  # the carried slopes are only a starting guess
        method, field = self.method, _user_clock(terms)
        direction = field.direction
        s0, s1 = direction * t0, direction * t1
        h = s1 - s0
        carried, compensation = solver_state
        step = method.carried_step(field, s0, y0, h, args, carried)
        increment, result, carried = step.increment, step.result, step.carried
        y1, compensation_next = compensated(step.y, step.rounding, compensation)
        x0 = method.start_field(carried)  # the field at (s0, y0)
        y_next, y_error = y1, None
        if self.adaptive:
            # Two half steps: carried on, and their difference from the full
            # step (entrywise in the embedding) is the error estimate.
            first = method.step(field, s0, y0, h / 2, args)
            y_half, lost = compensated(first.y, first.rounding, compensation)
            second = method.step(field, s0 + h / 2, y_half, h / 2, args)
            y_next, compensation_next = compensated(second.y, second.rounding, lost)
            y_error = jax.tree.map(jnp.subtract, y_next, y1)
            for r in (first.result, second.result):
                result = first_failure(result, r)
        # Dense output interpolates the full step y0 → y1; slopes are per unit
        # of diffrax's clock, in which the interpolation runs.
        x1 = method.generator(field, s1, y1, args)
        slope0 = tree_scale(direction, x0)  # df⁻¹_0 = I
        slope1 = tree_scale(direction, method.slope(increment, x1, order=max(method.order, DENSE_OUTPUT_TRUNCATION_ORDER)))
        dense_info = dict(y0=y0, increment=increment, slope0=slope0, slope1=slope1, method=method)
        return y_next, y_error, dense_info, (carried, compensation_next), result

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
