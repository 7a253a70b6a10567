"""The solve of a PRKMK step's implicit stages: K = F(K) for a block of
stage slopes (`PRKMK`, `Adjoint`).

The default is fixed-point iteration with the round-off stopping rule
(`iterate_until="round-off"`: past the tolerance, on while the increments
shrink; Hairer, McLachlan & Razakarivony, BIT 48, 2008), differentiated by
the implicit function theorem with the same iteration on the linearised
map; an optimistix fixed-point solver or root finder may take its place.
"""

import functools
from typing import Any, Literal

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.ad_checkpoint import checkpoint_name

from .base import RESULTS, batched_like

STAGE_SLOPES_NAME = "prkmk_stage_slopes"
"""The name the solved stage slopes carry in a traced program
(`jax.ad_checkpoint.checkpoint_name`): a rematerialised step keeps them
instead of iterating to them again."""


class StageSolve(eqx.Module):
    """How a block of implicit stage slopes is solved: tolerances on the
    slopes, an iteration cap, the stopping rule, and an optional optimistix
    solver in place of the fixed-point iteration (`PRKMK`'s options)."""

    rtol: float | None = eqx.field(static=True, default=None)
    atol: float | None = eqx.field(static=True, default=None)
    max_iterations: int = eqx.field(static=True, default=100)
    root_finder: Any = eqx.field(static=True, default=None)
    iterate_until: Literal["round-off", "tolerance"] = eqx.field(static=True, default="round-off")

    def __check_init__(self):
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
        if self.iterate_until not in ("round-off", "tolerance"):
            raise ValueError(
                "iterate_until must be 'round-off' (until the increments stop shrinking) or 'tolerance' (rtol/atol), "
                f"got {self.iterate_until!r}."
            )

    @property
    def to_round_off(self) -> bool:
        """Whether the default iteration solves to round-off (no optimistix
        solver, `iterate_until="round-off"`)."""
        return self.iterate_until == "round-off" and self.root_finder is None

    def __call__(self, block_slopes, guess, dtype, guess_solves: bool = False):
        """Solve block_slopes(K) = K for the slopes K of an implicit block
        from `guess`; returns (K, result, iterations). `guess_solves`: the
        guess is the solution (to round-off), evaluated once by the default
        iteration (`_fixed_point_iteration`); a root finder solves from it.
        The tolerances default to max(1e-12, 50·eps) of `dtype`."""
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
    z, error, _, n = jax.lax.while_loop(keep_going, iterate, (guess, *batched_like((inf, inf, jnp.array(0, jnp.int32)), guess)))
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

        x, _, _ = jax.lax.while_loop(keep_going, step, (b, *batched_like((jnp.asarray(jnp.inf, b.dtype), jnp.array(0, jnp.int32)), b)))
        return x

    z_dot = unflatten(jax.lax.custom_linear_solve(identity_minus_jacobian, flat_rhs, iterate_linear, iterate_linear))
    # The error and the count are not differentiable (the count's tangent is float0).
    zero_aux = (jnp.zeros_like(error), np.zeros(np.shape(n), jax.dtypes.float0))
    return (z, error, n), (z_dot, *zero_aux)
