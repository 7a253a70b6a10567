"""Reverse-mode gradients of a run without its stored trajectory.

A method's step can be undone: yₙ = Φ_h⁻¹(yₙ₊₁). For a symmetric method
Φ_h⁻¹ = Φ_{−h}; for any PRKMK method Φ_h⁻¹ = Φ*_{−h}, the adjoint method
(`Adjoint`, Φ*_h = Φ_{−h}⁻¹) at −h. Both hold to the stage solve and
round-off. So the backward pass of a run need not keep the states of the
forward pass: it walks back from the last state, reconstructing each state
by the undoing step and applying the step's VJP there (implicit stages are
differentiated as in the forward step). The forward pass keeps the saved
states and one state every `checkpoint_every` steps; each stretch between
two kept states is reconstructed from the later one, so the reconstruction
error cannot grow over more than that stretch, and the memory is that of
the kept states, whatever the number of steps. A `Splitting` in float64 is
undone and differentiated sub-flow by sub-flow instead
(`Splitting.reverse_step`), without running its step forward again.

`ReversibleGradient` does this for `integrate` and `resume`;
`ReversibleAdjoint` for `diffrax.diffeqsolve` with `PRKMKSolver`.
"""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .made_of_steps import AbstractMadeOfSteps, Adjoint
from .method import (
    LOW_PRECISION_EPS,
    RESULTS,
    AbstractMethod,
    counted_start,
    counted_step,
    first_failure,
    largest_entry_difference,
    varying_with,
)
from .solver import PRKMKSolver, _user_clock
from .splitting import Splitting
from .step import PRKMK


class ReversibleGradient(eqx.Module):
    """Gradients of `integrate` by reconstructing the states backwards
    (module docstring), for `integrate(..., gradient=ReversibleGradient())`.
    Reverse mode only (the run is a `custom_vjp`): forward mode (`jax.jvp`,
    `jax.jacfwd`) raises JAX's error there and takes `gradient=None`.

    - `checkpoint_every`: reconstruct at most this many steps from one kept
      state. The forward pass keeps the saved states and, between two of
      them, one state every K steps, K the largest divisor of `save_every`
      not above `checkpoint_every`: memory of N/K states for N steps. None
      keeps the saved states only (with `save_every=num_steps`, memory
      independent of N, and reconstruction over the whole run).
    - `max_reconstruction_error`: the backward pass compares each stretch's
      rebuilt first state with the kept one, max |Δ|/(1 + max |y|) over the
      state's entries, and raises where the difference exceeds this (a
      chaotic motion amplifies the rounding of the undoing steps
      exponentially over long stretches; keep more states then). None
      takes √ε of the state's dtype.
    """

    checkpoint_every: int | None = eqx.field(static=True, default=1000)
    max_reconstruction_error: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_checkpoint_every(self.checkpoint_every)
        _check_max_reconstruction_error(self.max_reconstruction_error)


def _check_checkpoint_every(k) -> None:
    if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
        raise ValueError(f"checkpoint_every must be None or an int ≥ 1, got {k!r}.")


def _check_max_reconstruction_error(tol) -> None:
    if tol is not None and not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and tol > 0):
        raise ValueError(f"max_reconstruction_error must be None or a number > 0, got {tol!r}.")


def undoing_method(method: AbstractMethod) -> AbstractMethod:
    """The method whose step of −h undoes a step of h of `method`: the method
    itself where it is symmetric by construction (`is_symmetric`), the
    adjoint of a PRKMK method, the PRKMK method of an `Adjoint`."""
    if method.is_symmetric:
        return method
    if isinstance(method, PRKMK):
        return Adjoint(method)  # pyright: ignore[reportCallIssue]  # equinox: AbstractVars implemented by properties are not __init__ fields
    if isinstance(method, Adjoint) and isinstance(method.method, PRKMK):
        return method.method
    raise TypeError(
        f"reversible gradients need a method whose step can be undone exactly: a PRKMK method or its Adjoint (undone by "
        f"each other), or a method symmetric by construction (Symmetrized, Splitting, a Composition of those or one with "
        f"assume_symmetric_base=True); got a {type(method).__name__} that is none of these (a Composition of a base that "
        "is not symmetric: compose Symmetrized(base) instead)."
    )


def for_the_backward_pass(method: AbstractMethod) -> AbstractMethod:
    """`method` with each PRKMK method in it taking its step's product as it
    is (`compensated_sum=False`) and starting its stage iteration at the
    extrapolated guess (`start_either_side=False`). The backward pass undoes
    and differentiates steps with it: the compensation is carried by the
    forward pass only, the undone states are checked against the kept ones,
    and neither the step's derivative nor the rebuilt state's accuracy
    depends on how its change is added or where the iteration starts (the
    start cancels a drift over many steps forward, which the rebuilt states
    do not accumulate: each stretch starts again from a kept state)."""
    if isinstance(method, PRKMK):
        return dataclasses.replace(method, compensated_sum=False, start_either_side=False)
    if isinstance(method, AbstractMadeOfSteps):
        return eqx.tree_at(lambda m: m.method, method, for_the_backward_pass(method.method))
    return method


def _chunk_steps(gradient: ReversibleGradient, save_every: int) -> int:
    """The largest divisor of `save_every` not above `checkpoint_every`."""
    if gradient.checkpoint_every is None:
        return save_every
    return max(k for k in range(1, min(gradient.checkpoint_every, save_every) + 1) if save_every % k == 0)


def reversible_run(method, vector_field, y0, compensation0, carried0, t0, dt, steps_done, args, num_saves, save_every, gradient):
    """The forward pass of `integrate` under `ReversibleGradient`: (saved
    states, (last state, its compensation), result, iteration total and
    maximum, carried), differentiable in (y0, args, vector_field) by
    reconstruction. The steps are summed with compensation as `integrate`
    sums them; the reconstruction undoes the steps from the last state alone
    (the compensation is below its rounding)."""
    chunk = _chunk_steps(gradient, save_every)
    chunks_per_save = save_every // chunk
    undo = undoing_method(method)
    if not isinstance(vector_field, eqx.Module):
        # A plain function may close over arrays that are differentiated (a
        # parameter in the enclosing scope): made explicit, they are
        # differentiated as `args` are.
        vector_field = eqx.filter_closure_convert(vector_field, t0, y0, args)
    # The carried stage slopes only start the first step's stage iteration:
    # its solution, and so the gradient, does not depend on them.
    start = jax.lax.stop_gradient((carried0, compensation0))
    tolerance = _tolerance(gradient.max_reconstruction_error, y0)
    saved, y_last, *counts = _run_and_undo(
        (y0, args, vector_field), method, undo, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk, tolerance
    )
    # The result, the iteration counts, the carried slopes and the
    # compensation are not differentiated (the slopes only start the next
    # run's stages; the compensation is below the state's rounding).
    result, total, worst, carried, compensation = jax.lax.stop_gradient(counts)
    return saved, (y_last, compensation), result, total, worst, carried


def _forward(diff, method, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk):
    """Every step, keeping the state at the end of each chunk of `chunk`
    steps; `start` is (what the first step carries, the compensation)."""
    y0, args, vector_field = diff
    carried0, compensation0 = start
    one_step = counted_step(method, vector_field, t0, dt, args)

    def one_chunk(carry, first):
        carry, _ = jax.lax.scan(one_step, carry, first + jnp.arange(chunk, dtype=jnp.int32))
        return carry, carry[0]

    def one_save(carry, first):
        carry, kept = jax.lax.scan(one_chunk, carry, first + chunk * jnp.arange(chunks_per_save, dtype=jnp.int32))
        return carry, kept

    init = counted_start(y0, carried0, compensation0)
    save_starts = steps_done + chunks_per_save * chunk * jnp.arange(num_saves, dtype=jnp.int32)
    (y_last, compensation, result, total, worst, carried), kept = jax.lax.scan(one_save, init, save_starts)
    return kept, (y_last, result, total, worst, carried, compensation)


def _outputs_and_kept(diff, method, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk):
    kept, (y_last, *counts) = _forward(diff, method, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk)
    saved = jax.tree.map(lambda x: x[:, -1], kept)  # each save interval's last chunk ends at the saved state
    return (saved, y_last, *counts), kept


@eqx.filter_custom_vjp
def _run_and_undo(diff, method, undo, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk, tolerance):
    return _outputs_and_kept(diff, method, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk)[0]


@_run_and_undo.def_fwd
def _run_and_undo_fwd(perturbed, diff, method, undo, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk, tolerance):
    del perturbed
    return _outputs_and_kept(diff, method, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk)


def _is_none(x) -> bool:
    return x is None


def _or_zeros(gradient, zeros):
    """A cotangent, zeros where autodiff gives None (an output not used)."""
    return zeros if gradient is None else gradient


def _step_back(method, undo, params_dynamic, params_static, t_start, t_end, dt, y_next, cotangent, undo_carried, result):
    """The step of `method` from t_start to t_end = t_start + dt that ended at
    `y_next` undone, and `cotangent` pulled back through it: (the step's start,
    its cotangent, the parameters' cotangent, what the undoing step carries,
    the first failure). The parameters are (args, vector field), split into
    the arrays differentiated and the rest."""
    args, vector_field = eqx.combine(params_dynamic, params_static)
    method, undo = for_the_backward_pass(method), for_the_backward_pass(undo)
    dtype = jnp.result_type(*jax.tree.leaves(y_next))
    if isinstance(method, Splitting) and jnp.finfo(dtype).eps <= LOW_PRECISION_EPS:
        # Undone and differentiated from its end, each sub-flow once.
        y_prev, cotangent_prev, args_step = method.reverse_step(t_start, y_next, dt, args, cotangent)
        return y_prev, cotangent_prev, (args_step, jax.tree.map(jnp.zeros_like, params_dynamic[1])), undo_carried, result
    undone = undo.carried_step(vector_field, t_end, y_next, -dt, args, undo_carried)

    def forward(y, dynamic):
        a, f = eqx.combine(dynamic, params_static)
        if isinstance(method, (PRKMK, Adjoint)) and _undo_each_other(method, undo):
            # A PRKMK step and its `Adjoint` at −h solve the same stage
            # equations, one for the step's end, the other for its start:
            # the undoing step's stage slopes are the step's own (to the
            # stage solve), evaluated once there instead of iterated to.
            again = method.step_at_stages(f, t_start, y, dt, a, jax.lax.stop_gradient(undone.carried[1]))
        else:
            # Other methods start from the field at the step's start. The
            # gradient does not depend on where the iteration starts.
            start = jax.lax.stop_gradient(method.initial_carried(f, t_start, y, a))
            again = method.carried_step(f, t_start, y, dt, a, start)
        return again.y, again.result

    _, vjp, again_result = eqx.filter_vjp(forward, undone.y, params_dynamic, has_aux=True)
    cotangent_prev, params_step = vjp(cotangent)
    result = first_failure(first_failure(result, undone.result), again_result)
    return undone.y, cotangent_prev, params_step, undone.carried, result


def _undo_each_other(method, undo) -> bool:
    """A PRKMK method and its `Adjoint`, in either order (`undoing_method`)."""
    return (isinstance(method, PRKMK) and isinstance(undo, Adjoint)) or (isinstance(undo, PRKMK) and isinstance(method, Adjoint))


@_run_and_undo.def_bwd
def _run_and_undo_bwd(
    kept, grad_out, perturbed, diff, method, undo, start, t0, dt, steps_done, num_saves, chunks_per_save, chunk, tolerance
):
    """Walk back chunk by chunk: reconstruct each state from the kept state at
    the chunk's end by `undo`'s step of −dt, and pull the cotangent back
    through the step's VJP there."""
    del perturbed, start
    y0, args, vector_field = diff
    grad_saved, grad_last = grad_out[0], grad_out[1]
    zeros_y = jax.tree.map(jnp.zeros_like, y0)
    saved_zeros = jax.tree.map(lambda x: jnp.zeros_like(x[:, -1]), kept)
    grad_saved = saved_zeros if grad_saved is None else jax.tree.map(_or_zeros, grad_saved, saved_zeros, is_leaf=_is_none)
    grad_last = zeros_y if grad_last is None else jax.tree.map(_or_zeros, grad_last, zeros_y, is_leaf=_is_none)
    params_dynamic, params_static = eqx.partition((args, vector_field), eqx.is_inexact_array)
    params_grad0 = jax.tree.map(jnp.zeros_like, params_dynamic)

    def back_one_step(carry, n):
        y_next, cotangent, params_grad, undo_carried, result = carry
        y_prev, cotangent_prev, params_step, undo_carried, result = _step_back(
            method, undo, params_dynamic, params_static, t0 + n * dt, t0 + (n + 1) * dt, dt, y_next, cotangent, undo_carried, result
        )
        params_grad = jax.tree.map(lambda a, b: a + b, params_grad, params_step)
        return (y_prev, cotangent_prev, params_grad, undo_carried, result), None

    def back_one_chunk(carry, inputs):
        cotangent, params_grad, result, worst = carry
        y_end, y_start, incoming, first = inputs
        cotangent = jax.tree.map(jnp.add, cotangent, incoming)
        undo_carried = undo.initial_carried(vector_field, t0 + (first + chunk) * dt, y_end, args)
        steps = first + jnp.arange(chunk, dtype=jnp.int32)[::-1]
        init = (y_end, cotangent, params_grad, undo_carried, result)
        (rebuilt, cotangent, params_grad, _, result), _ = jax.lax.scan(back_one_step, init, steps)
        # The stretch's first state is kept too: how far the rebuilt one is from it.
        return (cotangent, params_grad, result, jnp.maximum(worst, _reconstruction_gap(rebuilt, y_start))), None

    total_chunks = num_saves * chunks_per_save

    def by_chunk(x):
        return x.reshape((total_chunks,) + x.shape[2:])

    kept_flat = jax.tree.map(by_chunk, kept)
    # Each stretch starts where the one before ends, the first at y0.
    starts = jax.tree.map(lambda first, later: jnp.concatenate([first[None], later[:-1]]), y0, kept_flat)
    # The cotangent arriving at a stretch's end: the saved state's where the
    # stretch ends a save interval (the last of each), none otherwise.
    incoming = jax.tree.map(lambda g: by_chunk(jnp.zeros((num_saves, chunks_per_save) + g.shape[1:], g.dtype).at[:, -1].set(g)), grad_saved)
    firsts = steps_done + chunk * jnp.arange(total_chunks, dtype=jnp.int32)
    init = varying_with((grad_last, params_grad0, RESULTS.successful, jnp.zeros((), jnp.result_type(*jax.tree.leaves(y0)))), kept)
    (cotangent, params_grad, result, worst), _ = jax.lax.scan(back_one_chunk, init, (kept_flat, starts, incoming, firsts), reverse=True)
    remedy = "give a smaller checkpoint_every (or save more often)"
    cotangent, (args_grad, field_grad) = _checked((cotangent, params_grad), result, worst, tolerance, f"{chunk} steps", remedy)
    return cotangent, args_grad, field_grad


def _reconstruction_gap(rebuilt, kept):
    """max |rebuilt − kept| / (1 + max |kept|) over the state's entries."""
    size = jnp.max(jnp.stack([jnp.max(jnp.abs(b)) for b in jax.tree.leaves(kept)]))
    return largest_entry_difference(rebuilt, kept) / (1 + size)


def _checked(grads, result, worst, tolerance, stretch, remedy):
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


def _tolerance(max_reconstruction_error, y):
    """`max_reconstruction_error`, or √ε of the state's dtype for None."""
    if max_reconstruction_error is None:
        return float(np.sqrt(np.finfo(jnp.result_type(*jax.tree.leaves(y))).eps))
    return float(max_reconstruction_error)


class ReversibleAdjoint(diffrax.AbstractAdjoint):
    """Gradients of `diffrax.diffeqsolve` with `PRKMKSolver` by reconstructing
    the states backwards (module docstring): `diffeqsolve(...,
    adjoint=ReversibleAdjoint())`. The forward solve keeps its last state
    and the checkpoints below; the backward pass undoes its steps from there
    to y0 (which it compares the rebuilt y0 with, as `ReversibleGradient`
    compares each kept state).

    - `checkpoint_every`: the forward solve also keeps the state after every
      K-th step, in a buffer of `max_steps // K` states (so `diffeqsolve`
      needs `max_steps`), and the backward pass rebuilds each stretch of K
      steps from the kept state at its end, comparing its rebuilt start
      with the kept one: the reconstruction error cannot grow over more
      than K steps. None keeps the last state only: memory independent of
      `max_steps`, and the reconstruction runs over the whole solve.

    It takes what a fixed-step solve to t1 is: `PRKMKSolver` (not adaptive) of
    a method that `undoing_method` accepts, `ConstantStepSize` with `dt0`,
    `SaveAt(t1=True)`, no event and no solver or controller state passed in.
    Anything else raises `ValueError` (`TypeError` for a method that cannot
    be undone) when the solve is traced.

    The backward pass takes each step's times from diffrax's rule for
    `ConstantStepSize` (a first step of dt0, then t0 + (t1 − t0)·k/n), and the
    number of steps from the solve.

    - `max_reconstruction_error`: as in `ReversibleGradient`; None takes √ε
      of the state's dtype.
    """

    checkpoint_every: int | None = eqx.field(static=True, default=1000)
    max_reconstruction_error: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_checkpoint_every(self.checkpoint_every)
        _check_max_reconstruction_error(self.max_reconstruction_error)

    def loop(
        self,
        *,
        args,
        terms,
        solver,
        stepsize_controller,
        event,
        saveat,
        t0,
        t1,
        dt0,
        max_steps,
        throw,
        init_state,
        passed_solver_state,
        passed_controller_state,
        progress_meter,
    ):
        del throw
        if not isinstance(solver, PRKMKSolver) or solver.adaptive:
            raise ValueError(f"ReversibleAdjoint needs PRKMKSolver(method) with fixed steps, got {solver!r}.")
        undo = undoing_method(solver.method)
        if not isinstance(stepsize_controller, diffrax.ConstantStepSize) or dt0 is None:
            raise ValueError("ReversibleAdjoint needs stepsize_controller=ConstantStepSize() (the default) and a dt0.")
        if eqx.tree_equal(saveat, diffrax.SaveAt(t1=True)) is not True:
            raise ValueError("ReversibleAdjoint needs saveat=SaveAt(t1=True) (the default): the last state is the one it keeps.")
        if event is not None:
            raise ValueError("ReversibleAdjoint does not take an event.")
        if passed_solver_state or passed_controller_state:
            raise ValueError("ReversibleAdjoint does not take a solver_state or controller_state: the solve starts afresh.")
        if self.checkpoint_every is not None and max_steps is None:
            raise ValueError(
                "ReversibleAdjoint(checkpoint_every=K) keeps max_steps // K states and needs diffeqsolve's max_steps; "
                "give max_steps, or checkpoint_every=None to keep the last state only."
            )
        y0 = init_state.y
        init_state = eqx.tree_at(lambda s: s.y, init_state, object())
        # The stage slopes carried in the solver state only start the stages.
        init_state = eqx.tree_at(lambda s: s.solver_state, init_state, replace_fn=jax.lax.stop_gradient)
        loop = dict(
            self=self,
            undo=undo,
            solver=solver,
            stepsize_controller=stepsize_controller,
            saveat=saveat,
            t0=t0,
            t1=t1,
            dt0=dt0,
            max_steps=max_steps,
            init_state=init_state,
            progress_meter=progress_meter,
        )
        final_state, aux_stats = _diffrax_loop((y0, args, terms), **loop)
        # Only the saved states are differentiated (the rest of the final
        # state is the solve's bookkeeping, or the same state again).
        ys = final_state.save_state.ys
        final_state = jax.lax.stop_gradient(eqx.tree_at(lambda s: s.save_state.ys, final_state, None, is_leaf=_is_none))
        return eqx.tree_at(lambda s: s.save_state.ys, final_state, ys, is_leaf=_is_none), aux_stats


def _constant_step_ends(t0, t1, dt0):
    """k ↦ where step k of diffrax's `ConstantStepSize` ends (t0 for k = 0):
    the first step is dt0 and step k ≥ 2 ends at t0 + (t1 − t0)·k/n, n the
    number of steps (diffrax's own formula, without accumulated rounding); an
    end within 100 ulp of t1 is t1, as in diffrax's loop. n and that bound
    are computed once, outside the loop that asks for each end.
    `test_reversible.py` checks these against diffrax's steps."""
    dtype = jnp.result_type(t0, t1, dt0)
    n = jnp.ceil((t1 - t0) / jnp.nextafter(dt0, jnp.inf)).astype(jnp.int32)
    t1_clip_floor = t1
    for _ in range(100):
        t1_clip_floor = jnp.nextafter(t1_clip_floor, -jnp.inf)

    def end_of(k):
        end = t0 + (t1 - t0) * (jnp.asarray(k, dtype) / n.astype(dtype))
        end = jnp.where(k == n, t1, end)
        end = jnp.where(k == 1, t0 + dt0, end)
        end = jnp.where(end > t1_clip_floor, t1, end)
        return jnp.where(k == 0, t0, end)

    return end_of


def _while_loop(cond_fun, body_fun, init_val, **kwargs):
    """A diffrax loop hook as a plain `lax.while_loop` (not differentiated:
    the backward pass is `_diffrax_loop`'s own)."""
    del kwargs
    return jax.lax.while_loop(cond_fun, body_fun, init_val)


def _step_loop(cond_fun, body_fun, init_val, **kwargs):
    """diffrax's step loop as `_while_loop` runs it. The loop stops on the
    solve's result, which the state sets, so under `vmap` every carry of it
    ends up batched: each starts so (`varying_with`)."""
    return _while_loop(cond_fun, body_fun, varying_with(init_val, init_val.y), **kwargs)


def _keeping_every(every: int, kept: list):
    """diffrax's step loop as `_step_loop` does it, also keeping the state
    after steps K, 2K, … (K = `every`) in a buffer of max_steps // K states,
    which it appends to `kept` (the loop's caller reads it from there)."""

    def outer_while_loop(cond_fun, body_fun, init_val, *, max_steps, **kwargs):
        del kwargs
        slots = max_steps // every

        def body(carry):
            state, buffer = carry
            state = body_fun(state)
            k = state.num_steps
            # Steps that end off the grid of K write out of bounds: dropped.
            slot = jnp.where(k % every == 0, k // every - 1, slots)
            return state, jax.tree.map(lambda b, y: b.at[slot].set(y, mode="drop"), buffer, state.y)

        buffer = jax.tree.map(lambda y: jnp.zeros((slots,) + jnp.shape(y), jnp.result_type(y)), init_val.y)
        init = varying_with((init_val, buffer), init_val.y)
        final_state, buffer = jax.lax.while_loop(lambda carry: cond_fun(carry[0]), body, init)
        kept.append(buffer)
        return final_state

    return outer_while_loop


def _run_diffrax_loop(y_args_terms, outer_while_loop, *, self, undo, init_state, **kwargs):
    del undo
    y0, args, terms = y_args_terms
    init_state = eqx.tree_at(lambda s: s.y, init_state, y0)
    loops = dict(inner_while_loop=_while_loop, outer_while_loop=outer_while_loop)
    return self._loop(args=args, terms=terms, init_state=init_state, event=None, **loops, **kwargs)


@eqx.filter_custom_vjp
def _diffrax_loop(y_args_terms, **kwargs):
    return _run_diffrax_loop(y_args_terms, _step_loop, **kwargs)


@_diffrax_loop.def_fwd
def _diffrax_loop_fwd(perturbed, y_args_terms, **kwargs):
    del perturbed
    every, kept = kwargs["self"].checkpoint_every, []
    final_state, aux_stats = _run_diffrax_loop(y_args_terms, _step_loop if every is None else _keeping_every(every, kept), **kwargs)
    return (final_state, aux_stats), (final_state.y, final_state.num_steps, kept[0] if kept else None)


@_diffrax_loop.def_bwd
def _diffrax_loop_bwd(residuals, grad_out, perturbed, y_args_terms, *, self, undo, solver, t0, t1, dt0, **kwargs):
    """Walk back from the last state over every step the solve took; with
    checkpoints, each stretch of K steps from the state kept at its end."""
    del perturbed, kwargs
    y_last, num_steps, kept = residuals
    # No state kept (max_steps < K) is no checkpoint.
    every = self.checkpoint_every if kept is not None and jax.tree.leaves(kept)[0].shape[0] > 0 else None
    y0, args, terms = y_args_terms
    grad_ys = None if grad_out[0] is None else grad_out[0].save_state.ys
    if grad_ys is None:
        cotangent = jax.tree.map(jnp.zeros_like, y_last)
    else:
        cotangent = jax.tree.map(lambda y, g: jnp.zeros_like(y) if g is None else g[0], y_last, grad_ys, is_leaf=_is_none)
    method, field = solver.method, _user_clock(terms)
    params_dynamic, params_static = eqx.partition((args, field), eqx.is_inexact_array)
    direction = field.direction
    end_of = _constant_step_ends(t0, t1, dt0)

    def step_times(k):
        start, end = end_of(k), end_of(k + 1)
        return direction * start, direction * end, direction * (end - start)

    def back_one_step(carry):
        k, y_next, cotangent, params_grad, undo_carried, result, worst = carry
        if every is not None:
            # A step that ends at a kept state (not the last) starts its
            # stretch's reconstruction there, once its rebuilt value is checked.
            end = k + 1
            at_kept = (end % every == 0) & (end < num_steps)
            kept_state = jax.tree.map(lambda b: b[jnp.clip(end // every - 1, 0, b.shape[0] - 1)], kept)  # any slot where not at_kept
            worst = jnp.where(at_kept, jnp.maximum(worst, _reconstruction_gap(y_next, kept_state)), worst)
            y_next = jax.tree.map(lambda a, b: jnp.where(at_kept, b, a), y_next, kept_state)
        s_start, s_end, h = step_times(k)
        y_prev, cotangent, params_step, undo_carried, result = _step_back(
            method, undo, params_dynamic, params_static, s_start, s_end, h, y_next, cotangent, undo_carried, result
        )
        return k - 1, y_prev, cotangent, jax.tree.map(jnp.add, params_grad, params_step), undo_carried, result, worst

    undo_carried = undo.initial_carried(field, direction * t1, y_last, args)
    params_grad0 = jax.tree.map(jnp.zeros_like, params_dynamic)
    worst0 = jnp.zeros((), jnp.result_type(*jax.tree.leaves(y0)))
    init = (num_steps - 1, y_last, *varying_with((cotangent, params_grad0, undo_carried, RESULTS.successful, worst0), y_last))
    _, rebuilt, cotangent, params_grad, _, result, worst = jax.lax.while_loop(lambda carry: carry[0] >= 0, back_one_step, init)
    worst = jnp.maximum(worst, _reconstruction_gap(rebuilt, y0))
    tolerance = _tolerance(self.max_reconstruction_error, y0)
    if every is None:
        stretch, remedy = "the whole solve", "give ReversibleAdjoint a checkpoint_every"
    else:
        stretch, remedy = f"{every} steps", "give a smaller checkpoint_every"
    cotangent, (args_grad, field_grad) = _checked((cotangent, params_grad), result, worst, tolerance, stretch, remedy)
    return cotangent, args_grad, None if field_grad is None else field_grad.terms
