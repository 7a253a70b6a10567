"""How `integrate` and `resume` are differentiated: a gradient strategy runs
the forward loop and says what reverse mode keeps.

- `StoredSteps()` (the default): JAX differentiates the loop, keeping every
  step's state and implicit stage slopes; the explicit arithmetic of a step
  is recomputed in the backward pass.
- `ReversibleGradient()`: the loop's VJP walks back from the last state,
  rebuilding each state by the step that undoes it
  (`AbstractMethod.undoing_method`: for a symmetric method Φ_h⁻¹ = Φ_{−h};
  for a PRKMK method Φ_h⁻¹ = Φ*_{−h}, its adjoint at −h; both to the stage
  solve and round-off) and applying the step's VJP there. The forward pass
  keeps the saved states and one state every `checkpoint_every` steps; each
  stretch between two kept states is rebuilt from the later one, so the
  reconstruction error cannot grow over more than that stretch, and the
  memory is that of the kept states, whatever the number of steps.

`ReversibleAdjoint` (`_reversible_adjoint`) does the same for
`diffrax.diffeqsolve` with `PRKMKSolver`.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

from ._loop import (
    check_reversible_options,
    checked_gradients,
    loop_body,
    loop_start,
    reconstruction_tolerance,
    steps_forward,
    walk_back,
)
from .methods.base import AbstractMethod
from .methods.stage_solve import STAGE_SLOPES_NAME


class AbstractGradient(eqx.Module):
    """How a fixed-step run is differentiated (`integrate(..., gradient=...)`)."""

    @abc.abstractmethod
    def run(
        self, method: AbstractMethod, vector_field, y, compensation, carried, t0, dt, steps_done, args, num_saves: int, save_every: int
    ) -> tuple:
        """`num_saves·save_every` steps from `y` (step n from t0 + n·dt, the
        first numbered `steps_done`): (the state after every `save_every`
        steps, (the last state, its compensation), the first failure, the
        total of the implicit iterations, the most in one step, what the
        last step carried)."""


class StoredSteps(AbstractGradient):
    """Reverse mode through the stored steps: every step's state and the
    solutions of its implicit stages are kept; the rest of a step (hundreds
    of per-trajectory intermediates) is recomputed in the backward pass
    (a rematerialised step). Memory grows with the number of steps.
    Forward mode (`jax.jvp`, `jax.jacfwd`) works too."""

    def run(self, method, vector_field, y, compensation, carried, t0, dt, steps_done, args, num_saves, save_every) -> tuple:
        policy = jax.checkpoint_policies.save_only_these_names(STAGE_SLOPES_NAME)
        one_step = jax.checkpoint(loop_body(method, vector_field, t0, dt, args), prevent_cse=False, policy=policy)
        init = loop_start(y, carried, compensation)
        (y_last, compensation, result, total, worst, carried), saved = steps_forward(one_step, init, steps_done, (num_saves, save_every))
        return saved, (y_last, compensation), result, total, worst, carried


class ReversibleGradient(AbstractGradient):
    """Gradients of `integrate` by rebuilding the states backwards (module
    docstring), for `integrate(..., gradient=ReversibleGradient())`.
    Reverse mode only (the run is a `custom_vjp`): forward mode (`jax.jvp`,
    `jax.jacfwd`) raises JAX's error there and takes `StoredSteps()`.

    - `checkpoint_every`: rebuild at most this many steps from one kept
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
        check_reversible_options(self.checkpoint_every, self.max_reconstruction_error)

    def chunk_steps(self, save_every: int) -> int:
        """The largest divisor of `save_every` not above `checkpoint_every`."""
        if self.checkpoint_every is None:
            return save_every
        return max(k for k in range(1, min(self.checkpoint_every, save_every) + 1) if save_every % k == 0)

    def run(self, method, vector_field, y, compensation, carried, t0, dt, steps_done, args, num_saves, save_every) -> tuple:
        chunk = self.chunk_steps(save_every)
        undo = method.undoing_method()
        if not isinstance(vector_field, eqx.Module):
            # A plain function may close over arrays that are differentiated (a
            # parameter in the enclosing scope): made explicit, they are
            # differentiated as `args` are.
            vector_field = eqx.filter_closure_convert(vector_field, t0, y, args)
        # The carried stage slopes only start the first step's stage iteration:
        # its solution, and so the gradient, does not depend on them.
        start = jax.lax.stop_gradient((carried, compensation))
        tolerance = reconstruction_tolerance(self.max_reconstruction_error, y)
        counts = (num_saves, save_every // chunk, chunk)
        saved, y_last, *counts_out = _run_and_undo((y, args, vector_field), method, undo, start, t0, dt, steps_done, counts, tolerance)
        # The result, the iteration counts, the carried slopes and the
        # compensation are not differentiated (the slopes only start the next
        # run's stages; the compensation is below the state's rounding).
        result, total, worst, carried, compensation = jax.lax.stop_gradient(counts_out)
        return saved, (y_last, compensation), result, total, worst, carried


def _outputs_and_kept(diff, method, start, t0, dt, steps_done, counts):
    """Every step, keeping the state at the end of each stretch; the steps
    are summed with compensation as `StoredSteps` sums them (the backward
    pass undoes them from the last state alone: the compensation is below
    its rounding)."""
    y0, args, vector_field = diff
    carried0, compensation0 = start
    init = loop_start(y0, carried0, compensation0)
    (y_last, compensation, result, total, worst, carried), kept = steps_forward(
        loop_body(method, vector_field, t0, dt, args), init, steps_done, counts
    )
    saved = jax.tree.map(lambda x: x[:, -1], kept)  # each save interval's last stretch ends at the saved state
    return (saved, y_last, result, total, worst, carried, compensation), kept


@eqx.filter_custom_vjp
def _run_and_undo(diff, method, undo, start, t0, dt, steps_done, counts, tolerance):
    return _outputs_and_kept(diff, method, start, t0, dt, steps_done, counts)[0]


@_run_and_undo.def_fwd
def _run_and_undo_fwd(perturbed, diff, method, undo, start, t0, dt, steps_done, counts, tolerance):
    del perturbed
    return _outputs_and_kept(diff, method, start, t0, dt, steps_done, counts)


def _is_none(x) -> bool:
    return x is None


def _or_zeros(gradient, zeros):
    """A cotangent, zeros where autodiff gives None (an output not used)."""
    return zeros if gradient is None else gradient


@_run_and_undo.def_bwd
def _run_and_undo_bwd(kept, grad_out, perturbed, diff, method, undo, start, t0, dt, steps_done, counts, tolerance):
    """Walk back stretch by stretch (`walk_back`): each rebuilt from the kept
    state at its end by `undo`'s step of −dt, the cotangent pulled back
    through each step's VJP, a saved state's cotangent added where it was
    saved."""
    del perturbed, start
    num_saves, chunks_per_save, chunk = counts
    y0, args, vector_field = diff
    grad_saved, grad_last = grad_out[0], grad_out[1]
    zeros_y = jax.tree.map(jnp.zeros_like, y0)
    saved_zeros = jax.tree.map(lambda x: jnp.zeros_like(x[:, -1]), kept)
    grad_saved = saved_zeros if grad_saved is None else jax.tree.map(_or_zeros, grad_saved, saved_zeros, is_leaf=_is_none)
    grad_last = zeros_y if grad_last is None else jax.tree.map(_or_zeros, grad_last, zeros_y, is_leaf=_is_none)
    save_every = chunks_per_save * chunk
    num_steps = num_saves * save_every
    kept_flat = jax.tree.map(lambda x: x.reshape((num_saves * chunks_per_save,) + x.shape[2:]), kept)
    y_last = jax.tree.map(lambda x: x[-1], kept_flat)

    def step_times(k):
        n = steps_done + k
        return t0 + n * dt, t0 + (n + 1) * dt, dt

    def incoming(step):
        # The saved state after `step` (a multiple of save_every) takes its cotangent; the others none.
        saved = jax.tree.map(lambda g: g[jnp.clip(step // save_every - 1, 0, num_saves - 1)], grad_saved)
        return jax.tree.map(lambda g: jnp.where(step % save_every == 0, g, jnp.zeros_like(g)), saved)

    # The last state is the last saved one: its cotangent is both.
    cotangent = jax.tree.map(lambda g, last: g[-1] + last, grad_saved, grad_last)
    cotangent, params_grad, result, worst = walk_back(
        method, undo, vector_field, args, y0, y_last, cotangent, num_steps, step_times, chunk, kept_flat, incoming
    )
    remedy = "give a smaller checkpoint_every (or save more often)"
    cotangent, (args_grad, field_grad) = checked_gradients((cotangent, params_grad), result, worst, tolerance, f"{chunk} steps", remedy)
    return cotangent, args_grad, field_grad
