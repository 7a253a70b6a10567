"""Fixed-step runs of any method: `integrate` from a state, `resume` from
where a run stopped. Each is compiled once per shape of its inputs
(`eqx.filter_jit`, as `diffrax.diffeqsolve` is); the loop and what reverse
mode keeps are the gradient strategy's (`_gradients`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float, Int, PyTree, Real

from ._bundles import BundleElement
from ._fields import Time, VectorField
from ._gradients import AbstractGradient, StoredSteps
from ._loop import checked_start
from .methods.base import RESULTS, AbstractMethod, as_traced, no_compensation


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
    gradient: AbstractGradient = StoredSteps(),
) -> Trajectory:
    """Integrate from `t0` with `num_steps` steps of size `dt`, saving `y0`
    and every `save_every`-th state.

    Compiled once per shape of its inputs (`eqx.filter_jit`: arrays, `t0`
    and `dt` are traced; the method and the counts are static),
    differentiable with respect to `y0` and `args`, and
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

    `gradient`: `StoredSteps()` (the default) differentiates through the
    stored steps (reverse mode keeps every step's state and stage slopes);
    `ReversibleGradient()` keeps only the saved states (and its
    checkpoints) and rebuilds the others backwards, for memory that does
    not grow with the number of steps (`_gradients`).
    """
    _check_method(method)
    _check_dt_value(dt)
    num_steps, save_every = _checked_counts(num_steps, save_every)
    return _integrate(method, vector_field, y0, as_traced(t0), as_traced(dt), num_steps, args, save_every, throw, gradient)


@eqx.filter_jit
def _integrate(method, vector_field, y0, t0, dt, num_steps, args, save_every, throw, gradient) -> Trajectory:
    y0, t0, args = checked_start(method, vector_field, y0, t0, args)
    dt = _checked_dt(dt, t0.dtype)
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
    gradient: AbstractGradient = StoredSteps(),
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
    num_steps, save_every = _checked_counts(num_steps, save_every)
    return _resume(method, vector_field, continuation, num_steps, args, save_every, throw, gradient)


@eqx.filter_jit
def _resume(method, vector_field, continuation: Continuation, num_steps, args, save_every, throw, gradient) -> Trajectory:
    c = continuation
    y, t, args = checked_start(method, vector_field, c.y, c.t0 + c.steps_done * c.dt, args)
    dt = _checked_dt(c.dt, t.dtype)
    expected = jax.tree.structure(eqx.filter_eval_shape(method.initial_carried, vector_field, t, y, args))
    if jax.tree.structure(continuation.carried) != expected:
        raise TypeError("the continuation comes from another method (what it carries has another structure).")
    start = eqx.tree_at(lambda c: (c.y, c.dt), continuation, (y, dt))
    return _run(method, vector_field, start, num_steps, args, save_every, throw, gradient)


def _checked_counts(num_steps, save_every) -> tuple[int, int]:
    """The step and save counts as Python ints, static to the compiled run."""
    num_steps, save_every = _static_count("num_steps", num_steps), _static_count("save_every", save_every)
    if num_steps % save_every:
        raise ValueError(f"save_every={save_every} must divide num_steps={num_steps}.")
    return num_steps, save_every


def _check_method(method) -> None:
    if not isinstance(method, AbstractMethod):
        raise TypeError(
            f"method must be a PRKMK method, a Splitting, or one built from them (Composition, Adjoint, Symmetrized), "
            f"got {type(method).__name__}."
        )


def _check_dt_value(dt) -> None:
    """A dt known before the run (not traced) must be > 0: said at once."""
    if _is_concrete(dt) and not float(dt) > 0:
        raise ValueError(f"dt must be > 0 and finite, got {dt}.")


def _checked_dt(dt, dtype) -> Array:
    dt = jnp.asarray(dt, dtype)
    return eqx.error_if(dt, ~(dt > 0), "dt must be > 0 and finite.")


def _run(method, vector_field, start: Continuation, num_steps, args, save_every, throw, gradient) -> Trajectory:
    if not isinstance(gradient, AbstractGradient):
        raise TypeError(f"gradient must be StoredSteps() (the default) or ReversibleGradient(...), got {gradient!r}.")
    num_saves = num_steps // save_every
    saved, last, result, total, worst, carried = gradient.run(
        method, vector_field, start.y, start.compensation, start.carried, start.t0, start.dt, start.steps_done, args, num_saves, save_every
    )
    return _trajectory(start, saved, last, result, total, worst, carried, num_saves, save_every, throw)


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
