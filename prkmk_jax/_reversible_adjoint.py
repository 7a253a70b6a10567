"""Gradients of `diffrax.diffeqsolve` with `PRKMKSolver` without the stored
trajectory: `ReversibleAdjoint`, diffrax's counterpart of
`ReversibleGradient` (`_gradients`). The forward solve keeps its last state
and a checkpoint every K steps; the backward pass undoes the steps from
there (`_loop.walk_back`).

It runs diffrax's own loop (`AbstractAdjoint._loop`) with its loop hooks
and reads the loop's final state (`save_state`, `num_steps`): the diffrax
releases that `pyproject.toml` admits.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ._loop import check_reversible_options, checked_gradients, reconstruction_tolerance, walk_back
from ._solver import PRKMKSolver, _user_clock
from .methods.base import batched_like


def _is_none(x) -> bool:
    return x is None


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
    a method whose step can be undone (`AbstractMethod.undoing_method`), `ConstantStepSize` with `dt0`,
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
        check_reversible_options(self.checkpoint_every, self.max_reconstruction_error)

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
        undo = solver.method.undoing_method()
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
    ends up batched: each starts so (`batched_like`)."""
    return _while_loop(cond_fun, body_fun, batched_like(init_val, init_val.y), **kwargs)


def _keeping_every(every: int, kept: list):
    """diffrax's step loop as `_step_loop` does it, also keeping the state
    after steps K, 2K, … (K = `every`) in a buffer of max_steps // K states,
    which it appends to `kept` (the loop's caller reads it from there)."""

    def outer_while_loop(cond_fun, body_fun, init_val, *, max_steps, **kwargs):
        slots = max_steps // every
        if slots == 0:  # max_steps < K: nothing to keep; the backward pass starts from the last state
            return _step_loop(cond_fun, body_fun, init_val, max_steps=max_steps, **kwargs)
        del kwargs

        def body(carry):
            state, buffer = carry
            state = body_fun(state)
            k = state.num_steps
            # Steps that end off the grid of K write out of bounds: dropped.
            slot = jnp.where(k % every == 0, k // every - 1, slots)
            return state, jax.tree.map(lambda b, y: b.at[slot].set(y, mode="drop"), buffer, state.y)

        buffer = jax.tree.map(lambda y: jnp.zeros((slots,) + jnp.shape(y), jnp.result_type(y)), init_val.y)
        init = batched_like((init_val, buffer), init_val.y)
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
    """Walk back from the last state over every step the solve took
    (`walk_back`); with checkpoints, each stretch of K steps from the state
    kept at its end."""
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
    direction = field.direction
    end_of = _constant_step_ends(t0, t1, dt0)

    def step_times(k):
        start, end = end_of(k), end_of(k + 1)
        return direction * start, direction * end, direction * (end - start)

    cotangent, params_grad, result, worst = walk_back(method, undo, field, args, y0, y_last, cotangent, num_steps, step_times, every, kept)
    tolerance = reconstruction_tolerance(self.max_reconstruction_error, y0)
    if every is None:
        stretch, remedy = "the whole solve", "give ReversibleAdjoint a checkpoint_every"
    else:
        stretch, remedy = f"{every} steps", "give a smaller checkpoint_every"
    cotangent, (args_grad, field_grad) = checked_gradients((cotangent, params_grad), result, worst, tolerance, stretch, remedy)
    return cotangent, args_grad, None if field_grad is None else field_grad.terms
