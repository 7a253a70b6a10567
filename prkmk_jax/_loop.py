"""The core the drivers share: the start check, the forward loop of fixed
steps, and the reversible backward walk.

`integrate`/`resume` (through a gradient strategy, `_gradients`),
`PRKMKSolver` and `ReversibleAdjoint` all start a run with `checked_start`;
the fixed-step runs loop with `steps_forward`; both reversible gradients
walk back with `walk_back`. Everything here knows a method only through
`AbstractMethod`.
"""

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from ._bundles import BundleElement
from ._fields import VectorField, checked_field_args
from .methods.base import RESULTS, AbstractMethod, batched_like, compensated, first_failure, largest_entry_difference, no_compensation

Carry = tuple
"""The forward loop's carry: (state, its compensation, the first failure,
the total of the implicit iterations, the most in one step, what the last
step carried)."""


def checked_start(method: AbstractMethod, vector_field: VectorField, y: BundleElement, t, args: PyTree, called=None):
    """The checks every driver makes before a run: the method fits the
    field, the state (static and run-time checks), the field's parameters
    (`checked_field_args`), and the field's output at (t, y) (`called`, the
    field as the driver calls it, where that is not `vector_field`).
    Returns (y, t in the state's dtype, args), checked."""
    y = method.bundle.check(y)
    t = jnp.asarray(t, jnp.result_type(*jax.tree.leaves(y)))
    method.check_fits(vector_field)
    checked_args = checked_field_args(vector_field, args)
    method.check_vector_field(vector_field if called is None else called, t, y, args)
    return y, t, checked_args


def loop_body(method: AbstractMethod, vector_field: VectorField, t0, dt, args: PyTree):
    """The body of a fixed-step `lax.scan` over step numbers n: step n runs
    from t0 + n·dt, its sum compensated (`compensated`); the carry is a
    `Carry` (`loop_start`)."""

    def one_step(carry, n):
        y, compensation, result, total, worst, carried = carry
        step = method.carried_step(vector_field, t0 + n * dt, y, dt, args, carried)
        y_next, compensation = compensated(step.y, step.rounding, compensation)
        result = first_failure(result, step.result)
        return (y_next, compensation, result, total + step.iterations, jnp.maximum(worst, step.iterations), step.carried), None

    return one_step


def loop_start(y: BundleElement, carried: Any, compensation: BundleElement | None = None) -> Carry:
    """The `Carry` before the first step (no compensation yet, unless a
    continued run hands on its own), batched like `y` (`batched_like`)."""
    zero = jnp.array(0, jnp.int32)
    if compensation is None:
        compensation = no_compensation(y)
    return y, *batched_like((compensation, RESULTS.successful, zero, zero, carried), y)


def steps_forward(one_step, init: Carry, first_step, counts: tuple[int, ...]):
    """`one_step` over prod(counts) steps from step number `first_step`, as
    scans nested len(counts) deep (the outermost over counts[0]). Returns
    the last carry and the state after each innermost run of counts[-1]
    steps, with leading axes counts[:-1]."""

    def nested(depth):
        span = math.prod(counts[depth + 1 :])
        if depth == len(counts) - 1:

            def run_steps(carry, first):
                carry, _ = jax.lax.scan(one_step, carry, first + jnp.arange(counts[depth], dtype=jnp.int32))
                return carry, carry[0]

            return run_steps
        inner = nested(depth + 1)
        return lambda carry, first: jax.lax.scan(inner, carry, first + span * jnp.arange(counts[depth], dtype=jnp.int32))

    return nested(0)(init, first_step)


def step_back(
    method: AbstractMethod, undo: AbstractMethod, params_dynamic, params_static, t_start, t_end, dt, y_next, cotangent, undo_carried, result
):
    """The step of `method` from t_start to t_end = t_start + dt that ended at
    `y_next` undone, and `cotangent` pulled back through it: (the step's
    start, its cotangent, the parameters' cotangent, what the undoing step
    carries, the first failure). The parameters are (args, vector field),
    split into the arrays differentiated and the rest. A method that undoes
    and differentiates its own step does (`pulled_back_step`); otherwise
    `undo`'s step of −dt rebuilds the start, and the VJP of the method's
    step taken again there (`step_again`) pulls the cotangent back."""
    args, vector_field = eqx.combine(params_dynamic, params_static)
    method, undo = method.for_reconstruction(), undo.for_reconstruction()
    own = method.pulled_back_step(t_start, y_next, dt, args, cotangent)
    if own is not None:
        y_prev, cotangent_prev, args_step = own
        return y_prev, cotangent_prev, (args_step, jax.tree.map(jnp.zeros_like, params_dynamic[1])), undo_carried, result
    undone = undo.carried_step(vector_field, t_end, y_next, -dt, args, undo_carried)

    def forward(y, dynamic):
        a, f = eqx.combine(dynamic, params_static)
        again = method.step_again(f, t_start, y, dt, a, undone.carried)
        return again.y, again.result

    _, vjp, again_result = eqx.filter_vjp(forward, undone.y, params_dynamic, has_aux=True)
    cotangent_prev, params_step = vjp(cotangent)
    result = first_failure(first_failure(result, undone.result), again_result)
    return undone.y, cotangent_prev, params_step, undone.carried, result


def walk_back(method, undo, vector_field, args, y0, y_last, cotangent, num_steps, step_times, every=None, kept=None, incoming=None):
    """The reversible backward pass of a run of `num_steps` fixed steps that
    started at `y0` and ended at `y_last`, with `cotangent` arriving there:
    stretch by stretch from the end, each step undone and differentiated
    (`step_back`). Both reversible gradients walk back with it.

    - `step_times(k)`: (start, end, step) of the run's step k (0 the first).
    - `every`, `kept`: the run kept the state after steps every, 2·every, …
      in `kept` (slot j after step (j + 1)·every); each stretch between
      kept states is rebuilt from the kept state at its end, the undoing
      method's carried slopes started afresh there. None: one stretch.
    - `incoming(step)`: the cotangent arriving at the kept state after that
      step (a saved state's), or None for none.

    Each stretch's rebuilt start is compared with the kept one (y0 for the
    first). Returns (the cotangent at y0, the parameters' cotangents as
    (args, vector field), the first failure, the largest `reconstruction_gap`).
    """
    params_dynamic, params_static = eqx.partition((args, vector_field), eqx.is_inexact_array)

    def back_one_step(carry):
        k, y_next, cotangent, params_grad, undo_carried, result = carry
        t_start, t_end, dt = step_times(k)
        y_prev, cotangent, params_step, undo_carried, result = step_back(
            method, undo, params_dynamic, params_static, t_start, t_end, dt, y_next, cotangent, undo_carried, result
        )
        return k - 1, y_prev, cotangent, jax.tree.map(jnp.add, params_grad, params_step), undo_carried, result

    def kept_after(step):
        if every is None:
            return y0
        slot = jnp.clip(step // every - 1, 0, jax.tree.leaves(kept)[0].shape[0] - 1)
        state = jax.tree.map(lambda b: b[slot], kept)
        return jax.tree.map(lambda first, later: jnp.where(step == 0, first, later), y0, state)

    def back_one_stretch(carry):
        end, y_end, cotangent, params_grad, result, worst = carry
        first = jnp.zeros_like(end) if every is None else ((end - 1) // every) * every
        undo_carried = undo.initial_carried(vector_field, step_times(end - 1)[1], y_end, args)
        init = (end - 1, y_end, cotangent, params_grad, *batched_like((undo_carried,), y_end), result)
        _, rebuilt, cotangent, params_grad, _, result = jax.lax.while_loop(lambda c: c[0] >= first, back_one_step, init)
        start = kept_after(first)
        worst = jnp.maximum(worst, reconstruction_gap(rebuilt, start))
        if incoming is not None:
            arriving = incoming(first)
            cotangent = jax.tree.map(lambda c, a: c + jnp.where(first > 0, a, jnp.zeros_like(a)), cotangent, arriving)
        return first, start, cotangent, params_grad, result, worst

    params_grad = jax.tree.map(jnp.zeros_like, params_dynamic)
    worst = jnp.zeros((), jnp.result_type(*jax.tree.leaves(y0)))
    init = (jnp.asarray(num_steps, jnp.int32), y_last, *batched_like((cotangent, params_grad, RESULTS.successful, worst), y_last))
    _, _, cotangent, params_grad, result, worst = jax.lax.while_loop(lambda c: c[0] > 0, back_one_stretch, init)
    return cotangent, params_grad, result, worst


def reconstruction_gap(rebuilt, kept):
    """max |rebuilt − kept| / (1 + max |kept|) over the state's entries."""
    size = jnp.max(jnp.stack([jnp.max(jnp.abs(b)) for b in jax.tree.leaves(kept)]))
    return largest_entry_difference(rebuilt, kept) / (1 + size)


def checked_gradients(grads, result, worst, tolerance, stretch, remedy):
    """`grads`, raising where an undoing step failed or a rebuilt state is
    off its kept one by more than `tolerance`. The checks act through every
    gradient returned: those not asked for are dropped, with whatever they
    pass through."""
    grads = result.error_if(grads, result != RESULTS.successful)
    return eqx.error_if(
        grads,
        ~(worst <= tolerance),
        f"reversible gradient: a state rebuilt by undoing steps is off the kept one by more than max_reconstruction_error = "
        f"{tolerance:.1e} (relative); the motion amplifies the rounding over a stretch of {stretch}: {remedy}.",
    )


def reconstruction_tolerance(max_reconstruction_error, y) -> float:
    """`max_reconstruction_error`, or √ε of the state's dtype for None."""
    if max_reconstruction_error is None:
        return float(np.sqrt(np.finfo(jnp.result_type(*jax.tree.leaves(y))).eps))
    return float(max_reconstruction_error)


def check_reversible_options(checkpoint_every, max_reconstruction_error) -> None:
    """The options both reversible gradients take, checked at construction."""
    k = checkpoint_every
    if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
        raise ValueError(f"checkpoint_every must be None or an int ≥ 1, got {k!r}.")
    tol = max_reconstruction_error
    if tol is not None and not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and tol > 0):
        raise ValueError(f"max_reconstruction_error must be None or a number > 0, got {tol!r}.")
