"""Fixed-step integration of a PRKMK method with `lax.scan`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float, Int, PyTree, Real

from .bundles import BundleElement
from .method import RESULTS, AbstractMethod, Time, VectorField, checked_field_args, counted_start, counted_step, no_compensation
from .reversible import ReversibleGradient, reversible_run
from .step import STAGE_SLOPES_NAME


class Continuation(eqx.Module):
    """Where a fixed-step run stopped: all that `resume` needs to continue it
    exactly as the uninterrupted run would have gone on."""

    y: BundleElement
    """The last state."""
    t0: Real[Array, ""]
    """The start time of the first run; step n runs from t0 + n·dt."""
    dt: Real[Array, ""]
    """The step size."""
    steps_done: Int[Array, ""]
    """Steps taken since `t0` (int32)."""
    carried: PyTree
    """What the next step starts from (`Step.carried`: the field at the last
    step's start and its stage slopes, the next step's starting guesses)."""
    compensation: BundleElement
    """What the run's updates lost to rounding so far, below the last bit of
    `y` (compensated summation, `compensated`): y + compensation is
    the run's state to the rounding of each step's change."""


class Trajectory(eqx.Module):
    """Saved states of a fixed-step run."""

    ts: Float[Array, " num_saves"]
    """Save times, starting with `t0`."""
    ys: BundleElement
    """States with a leading time axis of length `num_saves`."""
    result: RESULTS
    """`RESULTS.successful`, or the first failure (an implicit stage that did
    not converge, a non-finite state)."""
    stats: dict[str, Int[Array, ""]]
    """`num_iterations`: total implicit iterations; `max_iterations_per_step`."""
    continuation: Continuation
    """Hand it to `resume` to continue the run: the continued run equals the
    uninterrupted one bit for bit."""


def _is_concrete(x) -> bool:
    try:
        float(x)
        return True
    except (TypeError, jax.errors.ConcretizationTypeError):
        return False


def _static_count(name, value) -> int:
    """A step count as a Python int (NumPy integers accepted): it sets the
    scan's length, so it cannot be traced."""
    if isinstance(value, Tracer):
        raise ValueError(
            f"{name} must be a static Python int, got a traced value; under jax.jit pass it as a static "
            f"argument (static_argnums / static_argnames, or eqx.filter_jit with a Python int)."
        )
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an int ≥ 1, got {value!r}.")
    return int(value)


def integrate(
    method: AbstractMethod,
    vector_field: VectorField,
    y0: BundleElement,
    t0: Time,
    dt: Time,
    num_steps: int,
    args: PyTree = None,
    *,
    save_every: int = 1,
    throw: bool = True,
    gradient: ReversibleGradient | None = None,
) -> Trajectory:
    """Integrate from `t0` with `num_steps` steps of size `dt`, saving `y0`
    and every `save_every`-th state.

    Pure and jittable (wrap it in `jax.jit`/`eqx.filter_jit` with the
    integers static), differentiable with respect to `y0` and `args`, and
    `vmap`-able over batches of `y0` and `args`. With `throw=True` a failed
    implicit stage or a non-finite state raises at run time; otherwise it is
    reported in `Trajectory.result`.

    `method` is any `AbstractMethod`: a `PRKMK` or a method built from
    them (`Composition`, `Symmetrized`, `Adjoint`). Implicit stages start
    from the previous step's stage slopes, moved by the change of the field
    at the step's start (an O(h²) guess; the field at yₙ alone is O(h);
    `PRKMK.carried_step`); they converge to the same tolerance either
    way. To continue the run later, pass `Trajectory.continuation` to
    `resume`.

    `gradient`: None differentiates through the stored steps (reverse mode
    keeps every step's state and stage slopes); `ReversibleGradient()`
    keeps only the saved states (and its checkpoints) and reconstructs the
    others backwards, for memory that does not grow with the number of
    steps (`reversible`).
    """
    _check_method(method)
    y0, t0, dt, args = _checked_start(method, vector_field, y0, t0, dt, args)
    carried = method.initial_carried(vector_field, t0, y0, args)
    start = Continuation(y0, t0, dt, jnp.array(0, jnp.int32), carried, no_compensation(y0))
    return _run(method, vector_field, start, num_steps, args, save_every, throw, gradient)


def resume(
    method: AbstractMethod,
    vector_field: VectorField,
    continuation: Continuation,
    num_steps: int,
    args: PyTree = None,
    *,
    save_every: int = 1,
    throw: bool = True,
    gradient: ReversibleGradient | None = None,
) -> Trajectory:
    """Continue a run of `integrate` (or of `resume`) for `num_steps` more
    steps from its `Trajectory.continuation`.

    The continued run takes the same steps, at the same times
    t0 + n·dt, from the same starting guesses, as the uninterrupted run, so
    its states equal that run's bit for bit. Its `ts` and `ys` start with the
    continuation's time and state. The continuation is a pytree of arrays:
    keep it in memory, or save it with `eqx.tree_serialise_leaves` and load it
    with `eqx.tree_deserialise_leaves` (the template: `jax.eval_shape` of the
    run that produced it).

    Under `jax.jit`, give the first run its `t0` and `dt` as arguments rather
    than constants that the compiled function closes over: XLA may fold
    constants with another rounding (and fuse a multiply-add), and the two
    runs then differ in the last bit.

    `gradient`: as in `integrate`.
    """
    _check_method(method)
    if not isinstance(continuation, Continuation):
        raise TypeError(
            f"continuation must be a Trajectory's `continuation`, got {type(continuation).__name__}; to start from a state, use integrate."
        )
    c = continuation
    y, t, dt, args = _checked_start(method, vector_field, c.y, c.t0 + c.steps_done * c.dt, c.dt, args)
    expected = jax.tree.structure(eqx.filter_eval_shape(method.initial_carried, vector_field, t, y, args))
    if jax.tree.structure(continuation.carried) != expected:
        raise TypeError("the continuation comes from another method (what it carries has another structure).")
    start = eqx.tree_at(lambda c: (c.y, c.dt), continuation, (y, dt))
    return _run(method, vector_field, start, num_steps, args, save_every, throw, gradient)


def _check_method(method) -> None:
    if not isinstance(method, AbstractMethod):
        raise TypeError(
            f"method must be a PRKMK method, a Splitting, or one built from them (Composition, Adjoint, Symmetrized), "
            f"got {type(method).__name__}."
        )


def _checked_start(method, vector_field, y, t, dt, args):
    """The checks both entry points make before a run: the state (static and
    run-time), dt, args and the vector field's output at the start time t,
    with t and dt in the state's dtype. Returns (y, t, dt, args)."""
    y = method.bundle.check(y)
    dtype = jnp.result_type(*jax.tree.leaves(y))
    t = jnp.asarray(t, dtype)
    dt = _checked_dt(dt, dtype)
    method.check_fits(vector_field)
    args = checked_field_args(vector_field, args)
    method.check_vector_field(vector_field, t, y, args)
    return y, t, dt, args


def _checked_dt(dt, dtype) -> Array:
    if _is_concrete(dt):
        if not float(dt) > 0:
            raise ValueError(f"dt must be > 0 and finite, got {dt}.")
    dt = jnp.asarray(dt, dtype)
    return eqx.error_if(dt, ~(dt > 0), "dt must be > 0 and finite.")


def _run(method, vector_field, start: Continuation, num_steps, args, save_every, throw, gradient=None) -> Trajectory:
    num_steps, save_every = _static_count("num_steps", num_steps), _static_count("save_every", save_every)
    if num_steps % save_every:
        raise ValueError(f"save_every={save_every} must divide num_steps={num_steps}.")
    t0, dt = start.t0, start.dt
    if gradient is not None:
        if not isinstance(gradient, ReversibleGradient):
            raise TypeError(f"gradient must be None (through the stored steps) or ReversibleGradient(...), got {gradient!r}.")
        num_saves = num_steps // save_every
        y, compensation, carried = start.y, start.compensation, start.carried
        saved, last, result, total, worst, carried = reversible_run(
            method, vector_field, y, compensation, carried, t0, dt, start.steps_done, args, num_saves, save_every, gradient
        )
        return _trajectory(start, saved, last, result, total, worst, carried, num_saves, save_every, throw)

    # Under reverse mode a scanned step would store every intermediate of
    # every step (hundreds of per-trajectory scalars); rematerialised, it
    # stores the state and the implicit stages' solutions only, and the
    # backward pass re-runs the explicit arithmetic (`throughput.py`
    # measures the gradient's cost).
    saved = jax.checkpoint_policies.save_only_these_names(STAGE_SLOPES_NAME)
    step_fn = jax.checkpoint(counted_step(method, vector_field, t0, dt, args), prevent_cse=False, policy=saved)

    def one_save(carry, first):
        carry, _ = jax.lax.scan(step_fn, carry, first + jnp.arange(save_every, dtype=jnp.int32))
        return carry, carry[0]

    init = counted_start(start.y, start.carried, start.compensation)
    num_saves = num_steps // save_every
    save_steps = start.steps_done + save_every * jnp.arange(num_saves + 1, dtype=jnp.int32)
    (y_last, compensation, result, total, worst, carried), saved = jax.lax.scan(one_save, init, save_steps[:-1])
    return _trajectory(start, saved, (y_last, compensation), result, total, worst, carried, num_saves, save_every, throw)


def _trajectory(start: Continuation, saved, last, result, total, worst, carried, num_saves, save_every, throw) -> Trajectory:
    """The run's `Trajectory`; `last` is (the last state, its compensation)."""
    y_last, compensation = last
    save_steps = start.steps_done + save_every * jnp.arange(num_saves + 1, dtype=jnp.int32)
    ys = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), start.y, saved)
    ts = start.t0 + save_steps * start.dt
    if throw:
        ys = result.error_if(ys, result != RESULTS.successful)
    continuation = Continuation(y_last, start.t0, start.dt, save_steps[-1], carried, compensation)
    return Trajectory(ts, ys, result, {"num_iterations": total, "max_iterations_per_step": worst}, continuation)
