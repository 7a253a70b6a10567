"""What a one-step method on a bundle group offers the drivers.

`integrate` and `PRKMKSolver` know a method only through `AbstractMethod`:
a step that carries its implicit stages' starting guesses from one step to
the next, the coordinate map its increments live in (for dense output), and
the pieces shared by every method (the generator in the state's dtype, the
vector-field check), and how a step is undone for the reversible
gradients. `PRKMK` (Algorithm 4.2, `prkmk.py`) is one, `Splitting`
another; the methods made of other methods' steps (`Adjoint`,
`Symmetrized`, `Composition`) are the others.
"""

import abc
import functools
from typing import Any, Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, PyTree

from .._bundles import AbstractBundle, AlgebraPair, BundleElement, Increment
from .._exact_sums import two_sum
from .._fields import AbstractFieldOnBundle, Iterations, Time, VectorField
from ..coordinates import AbstractCoordinates
from ..groups._util import is_low_precision
from ..groups.trig import computed_once

RESULTS = diffrax.RESULTS


def batched_like(tree: PyTree, reference: PyTree) -> PyTree:
    """`tree` as it is, traced as a function of `reference`'s arrays.

    For a loop's carry that starts as a constant (a zero, a counter, a
    result) and that the loop body makes depend on the state: under `vmap`,
    the batching rule of `lax.scan` and `lax.while_loop` finds such a carry
    batched only by batching the loop body again, once more for each carry
    it promotes, and each loop nested in that body again each time. Started
    as a function of the batched state, the carry is batched from the
    start, and the body is batched once: a saving in trace time that
    multiplies with the depth of the nesting (a reversible backward pass
    nests loops three deep). The dependence is a select on a predicate that
    is always false, which XLA folds away.
    """
    leaves = [leaf for leaf in jax.tree.leaves(reference) if jnp.size(leaf) > 0]
    if not leaves:
        return tree
    never = jnp.any(leaves[0] != leaves[0]) & False
    return jax.tree.map(lambda x: jnp.where(never, x, x) if eqx.is_array(x) else x, tree)


def check_parts(bundle, coordinates, form) -> None:
    """Trace-time checks of what a method on a bundle is built from: a
    bundle group, a coordinate map that exists on its base, and a form."""
    if not isinstance(bundle, AbstractBundle):
        raise TypeError(f"bundle must be a bundle group such as Cartesian(SO3), got {bundle!r}.")
    if not isinstance(coordinates, AbstractCoordinates):
        raise TypeError(f"coordinates must be an AbstractCoordinates such as Exp() or Cayley(), got {coordinates!r}.")
    if form not in ("space", "body"):
        raise ValueError(f"form must be 'space' (y' = X·y) or 'body' (y' = y·X), got {form!r}.")
    bundle.check_coordinates(coordinates)


def no_compensation(y: BundleElement) -> BundleElement:
    """The compensation of a state whose arrays are exact as they are: zeros."""
    return jax.tree.map(jnp.zeros_like, y)


def tree_two_sum(a: PyTree, b: PyTree) -> tuple[PyTree, PyTree]:
    """`two_sum` leaf by leaf: (a + b rounded, its rounding error)."""
    summed = jax.tree.map(two_sum, a, b)
    return jax.tree.map(lambda _, pair: pair[0], a, summed), jax.tree.map(lambda _, pair: pair[1], a, summed)


def compensated(y: BundleElement, rounding: BundleElement | None, compensation: BundleElement) -> tuple[BundleElement, BundleElement]:
    """One update of a run's compensated summation (Kahan): the state `y` a
    step returned, plus what its update lost to rounding (`Step.rounding`)
    and what the run's earlier updates lost (`compensation`), summed so that
    the part below y's last bit is carried on: (y', compensation') with
    y + rounding + compensation = y' + compensation' to within the rounding
    of the small sum. Then the roundings of the updates do not accumulate:
    the state's error grows with that of each step's change, far smaller
    than the state (Hairer, McLachlan & Razakarivony, BIT 48, 2008).

    The drivers call it after every step; a loop of `AbstractMethod.step`
    written by hand does the same, starting from zeros shaped as the state
    (`lost = jax.tree.map(jnp.zeros_like, y0)`):

        y, lost = compensated(step.y, step.rounding, lost)

    A step without a rounding (None) leaves y and the compensation as they
    are. The compensation is a correction below the state's rounding, zero
    in exact arithmetic: it is not differentiated."""
    if rounding is None:
        return y, compensation
    small = jax.lax.stop_gradient(jax.tree.map(jnp.add, rounding, compensation))
    y_next, lost = tree_two_sum(*computed_once((y, small)))
    return y_next, jax.lax.stop_gradient(lost)


def largest_entry_difference(a: PyTree, b: PyTree) -> Array:
    """max |a − b| over the entries of two states (their matrices or vectors)."""
    return functools.reduce(jnp.maximum, [jnp.max(jnp.abs(x - y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))])


def tree_scale(alpha, tree):
    """alpha·tree, leaf by leaf."""
    return jax.tree.map(lambda x: alpha * x, tree)


def first_failure(result: RESULTS, new: RESULTS) -> RESULTS:
    """`result` if it already records a failure, else `new`."""
    return RESULTS.where(result == RESULTS.successful, new, result)


def flag_nonfinite(result: RESULTS, y) -> RESULTS:
    """`result`, or `RESULTS.nonfinite` if it was a success and `y` holds a NaN or inf."""
    finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(y)]))
    return first_failure(result, RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite))  # pyright: ignore[reportArgumentType]  # an Enumeration member is typed as its Literal


def fractions_and_starts(coefficients, dtype) -> tuple[Array, Array]:
    """A composition's step fractions γ₁…γ_m and where each of its steps
    starts, Σ_{j<k} γ_j, both in units of h, as arrays of `dtype` (the
    inputs of a `lax.scan` over the composed steps)."""
    fractions = jnp.asarray(coefficients.fractions, dtype)
    return fractions, jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(fractions)[:-1]])


def differentiated_as(value, differentiated):
    """`value()`, and where it is differentiated (forward or reverse mode),
    `differentiated()` with its derivative: two programs of one function (a
    pytree of arrays), the second one whose derivative XLA compiles small
    (stages or sub-steps in a loop rather than unrolled). Both are
    closure-converted, so that what they close over (the state, the field's
    parameters, `args`) enters the derivative as inputs; they must close
    over the same values."""
    return _differentiated_as(eqx.filter_closure_convert(value), eqx.filter_closure_convert(differentiated))


@eqx.filter_custom_jvp
def _differentiated_as(value, differentiated):
    del differentiated
    return value()


@_differentiated_as.def_jvp
def _differentiated_as_jvp(primals, tangents):
    _, differentiated = primals
    _, tangent = tangents
    return eqx.filter_jvp(lambda f: f(), (differentiated,), (tangent,))


class Step(eqx.Module):
    """One step of a method from (t, y) to t + dt (`AbstractMethod.step`)."""

    y: BundleElement
    """The state at t + dt."""
    increment: AlgebraPair
    """The step in the algebra: the U with `apply_increment(U, y_start) = y`
    (dense output interpolates along it)."""
    result: RESULTS
    """`RESULTS.successful`, or the step's failure (an implicit stage that did
    not converge, a non-finite state)."""
    iterations: Iterations
    """The implicit iterations the step took."""
    rounding: BundleElement | None
    """What the update lost to rounding, array by array: y_start + change =
    y + rounding exactly, for the change the step computed (`advance`; in
    low precision y is then renormalised onto the group where it drifted,
    a correction this leaves out). The drivers carry it on (`compensated`).
    None where the step has no such sum: a `Splitting`'s rotations in
    float64, or a PRKMK step with `compensated_sum=False`."""
    carried: Any
    """What the next step starts from: the field at this step's start and,
    for implicit stages, this step's stage slopes, the next step's starting
    guesses (`start_field` reads the field). Pass it to the next `step`."""


class AbstractMethod(eqx.Module):
    """A one-step method on a bundle group, as the drivers use it.

    A step is `step(vector_field, t, y, dt, args, carried)`, which returns a
    `Step`: the new state, the step's increment, its result and iterations,
    and what it hands on to the next step (`Step.carried`; before the first
    step, `initial_carried`). The drivers and the methods made of other
    methods' steps use this one entry point.
    """

    bundle: eqx.AbstractVar[AbstractBundle]
    coordinates: eqx.AbstractVar[AbstractCoordinates]
    form: eqx.AbstractVar[Literal["space", "body"]]

    @property
    @abc.abstractmethod
    def order(self) -> int:
        """The method's order: what its construction guarantees on every
        smooth problem (a composition claims the order its coefficients
        give only of a base known to be symmetric, see `Composition`)."""

    @property
    @abc.abstractmethod
    def is_symmetric(self) -> bool:
        """Whether the method is symmetric (Φ_{−h} ∘ Φ_h = id) by its
        construction, whatever the problem: `Symmetrized`, a `Splitting`, and
        compositions and adjoints of these (or a composition whose base the
        user declares symmetric, `Composition(assume_symmetric_base=True)`).
        False for a PRKMK method, whose symmetry depends on the tableau, the
        coordinate map and the field (`symmetry_defect` measures it on a
        problem)."""

    @abc.abstractmethod
    def initial_carried(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None) -> Any:
        """What a step from (t, y) starts from when no step came before it:
        what `Step.carried` holds, with the field at (t, y) in place of a
        previous step's (for implicit stages, as every stage slope)."""

    @abc.abstractmethod
    def carried_step(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, carried: Any) -> Step:
        """`step` with `carried` given: what each method implements."""

    def check_fits(self, vector_field: VectorField) -> None:
        """Trace-time check that this method can integrate `vector_field`
        (`ValueError` if not); the drivers call it with the user's field.
        By default any field on the bundle (its shapes are checked by
        `check_vector_field`), but a field that names its bundle and form (a
        scene, `AbstractFieldOnBundle`) must name this method's: the same
        generator read on another bundle or from the other side is another
        system. A `Splitting` takes only the scene it was built for."""
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

    @abc.abstractmethod
    def start_field(self, carried: Any) -> AlgebraPair:
        """The generator X(tₙ, yₙ) at the start of the step that returned
        `carried` (it is part of what a step carries)."""

    # --- how a step is undone (the reversible gradients) -----------------------------
    def undoing_method(self) -> "AbstractMethod":
        """The method whose step of −h undoes this method's step of h, to the
        stage solve and round-off: yₙ = Ψ_{−h}(Φ_h(yₙ)). The default is the
        method itself where it is symmetric by construction (`is_symmetric`:
        Φ_{−h} = Φ_h⁻¹); a method that is not symmetric says which method
        undoes it (a PRKMK method its `Adjoint`, the adjoint the PRKMK
        method), and one that cannot say raises `TypeError`."""
        if self.is_symmetric:
            return self
        raise TypeError(
            f"reversible gradients need a method whose step can be undone exactly: a PRKMK method or its Adjoint (undone by "
            f"each other), or a method symmetric by construction (Symmetrized, Splitting, a Composition of those or one with "
            f"assume_symmetric_base=True); got a {type(self).__name__} that is none of these (a Composition of a base that "
            "is not symmetric: compose Symmetrized(base) instead)."
        )

    @property
    def has_adjoint_step(self) -> bool:
        """Whether `adjoint_carried_step` takes a step of the adjoint
        Φ*_h = (Φ_{−h})⁻¹ (`Adjoint`): by default where the method is
        symmetric, Φ* = Φ."""
        return self.is_symmetric

    def adjoint_carried_step(
        self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, carried: Any, stages_solved: bool = False
    ) -> Step:
        """A step of the adjoint Φ*_h = (Φ_{−h})⁻¹, for `Adjoint`: by default
        the method's own step, where it is symmetric. `stages_solved` (a
        method with implicit stages): `carried` holds slopes that solve the
        adjoint step's stages, to evaluate once (`step_again`)."""
        del stages_solved
        if not self.is_symmetric:
            raise TypeError(f"a {type(self).__name__} that is not symmetric has no adjoint step of its own.")
        return self.carried_step(vector_field, t, y, dt, args, carried)

    def for_reconstruction(self) -> "AbstractMethod":
        """This method as the reversible backward pass steps it, undoing and
        differentiating steps between kept states: the same steps, without
        what serves a long forward run only (a PRKMK method's compensated
        sum and either-side start). Default: the method itself."""
        return self

    def step_again(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree, undone_carried: Any) -> Step:
        """This method's step from (t, y), taken again to differentiate it,
        where `undoing_method()`'s step from its end carried `undone_carried`.
        Default: the stage iteration started from the field at y (the step's
        derivative does not depend on where its iteration starts); a PRKMK
        method and its adjoint evaluate their stages once at the slopes the
        undoing step solved for, which solve the same equations."""
        start = jax.lax.stop_gradient(self.initial_carried(vector_field, t, y, args))
        return self.carried_step(vector_field, t, y, dt, args, start)

    def pulled_back_step(self, t: Time, y_next: BundleElement, dt: Time, args: PyTree, cotangent: BundleElement) -> Any:
        """None (the default): the backward pass undoes a step with
        `undoing_method()` and differentiates it by `step_again`. A method
        that undoes and differentiates its own step returns (the step's
        start, the cotangent there, the cotangent of `args`) instead
        (`Splitting`, sub-flow by sub-flow)."""
        del t, y_next, dt, args, cotangent
        return None

    # --- shared by every method -----------------------------------------------------
    def apply_increment(self, U: Increment, y: BundleElement) -> BundleElement:
        """f(U)·y (space form) or y·f(U) (body form), f the coordinate map.
        U's fiber component may be None, a zero known at trace time
        (`AbstractBundle.apply`)."""
        return self.bundle.apply(self.coordinates, U, y, self.form)

    def advance(self, U: Increment, y: BundleElement, compensate: bool = True) -> tuple[BundleElement, BundleElement | None]:
        """The step's new state `apply_increment(U, y)` and what its sum lost
        to rounding (`Step.rounding`).

        With `compensate`, the state is summed as y + (f(U)⊙y − y), the
        change computed with y kept out of it
        (`AbstractBundle.apply_change`), so it is rounded relative to
        the change; the sum's rounding is returned exactly (`two_sum`), for
        the driver to carry on (`compensated`). Without, the product as it
        is, and no rounding (None).

        In low precision (machine epsilon above `LOW_PRECISION_EPS`) the new
        state is also corrected back onto the group where it has drifted off
        by more than a few ulps (`AbstractBundle.renormalized`): there the
        rounding of f(U) is systematic for steady motions and would pull the
        state off the group a little every step. The sum is compensated all
        the same: the correction moves the state by a few ulps now and then,
        but the sum rounds at every step, and with its rounding carried on a
        long float32 run stays near the same run in float64, where without it
        their difference grows with the number of steps
        (`tests/test_float32.py`)."""
        if compensate:
            change = computed_once(self.bundle.apply_change(self.coordinates, U, y, self.form))
            y_next, rounding = tree_two_sum(y, change)
            rounding = jax.lax.stop_gradient(rounding)
        else:
            y_next, rounding = self.apply_increment(U, y), None
        if is_low_precision(jnp.result_type(*jax.tree.leaves(y))):
            y_next = self.bundle.renormalized(y_next)
        return y_next, rounding

    def increment_between(self, y: BundleElement, y_next: BundleElement) -> AlgebraPair:
        """The U near 0 with `apply_increment(U, y) = y_next`: f⁻¹(y_next·y⁻¹)
        (space form) or f⁻¹(y⁻¹·y_next) (body form)."""
        bundle = self.bundle
        if self.form == "body":
            relative = bundle.multiply(bundle.inverse(y), y_next)
        else:
            relative = bundle.multiply(y_next, bundle.inverse(y))
        return bundle.inverse_map(self.coordinates, relative)

    def slope(self, U: AlgebraPair, X: AlgebraPair, order: int | None = None) -> AlgebraPair:
        """U' for the generator X at the point reached by the increment U:
        df⁻¹_U(X) (space form) or df⁻¹_{−U}(X) (body form), truncated as the
        coordinates say for a method of order `order` (default this
        method's)."""
        if self.form == "body":
            U = tree_scale(-1.0, U)
        return self.bundle.inverse_differential(self.coordinates, U, X, self.order if order is None else order)

    def slope_at(self, vector_field: VectorField, t: Time, U: Increment, y: BundleElement, args: PyTree) -> AlgebraPair:
        """The slope of a stage: df⁻¹_U(X(t, f(U)⊙y)), the field at the point
        the increment U reaches from y, pulled back to the algebra. U's fiber
        component may be None, a zero known at trace time."""
        point = self.apply_increment(U, y)
        return self.slope(self.bundle.zero_filled(U, y), self.generator(vector_field, t, point, args))

    def generator(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree) -> AlgebraPair:
        """(ξ, η) = vector_field(t, y, args) in the state's dtype, whatever
        precision the user's field returns."""
        zeros = self.bundle.algebra_zeros(y)
        xi, eta = vector_field(t, y, args)
        return jnp.asarray(xi, zeros[0].dtype), jnp.asarray(eta, zeros[1].dtype)

    def check_vector_field(self, vector_field: VectorField, t, y: BundleElement, args) -> None:
        """Trace-time check that `vector_field(t, y, args)` returns a pair
        (ξ, η) of algebra arrays of the right shapes."""
        out = jax.eval_shape(vector_field, t, y, args)
        zeros = self.bundle.algebra_zeros(y)
        if not (isinstance(out, (tuple, list)) and len(out) == 2):
            raise ValueError(f"the vector field must return a pair (ξ, η) of algebra elements, got {jax.tree.structure(out)}.")
        for name, got, want in zip(("ξ", "η"), out, zeros):
            if not hasattr(got, "shape") or tuple(got.shape) != tuple(want.shape):
                raise ValueError(
                    f"the vector field returned {name} with shape {getattr(got, 'shape', type(got))}, "
                    f"but the algebra of {type(self.bundle).__name__}({self.bundle.base.__name__}) at this state has shape {want.shape}."
                )

    def step(self, vector_field: VectorField, t: Time, y: BundleElement, dt: Time, args: PyTree = None, carried: Any = None) -> Step:
        """One step from (t, y) to t + dt. `carried` is the previous step's
        `Step.carried`, whose stage slopes start this step's implicit stages
        (an O(h²) guess); None starts them from the field at y, as
        `initial_carried` says. Both converge to the same stage solution.

        Called on concrete values (not inside `jit`, `vmap` or a
        derivative), the step runs compiled, once for each shape of its
        inputs, as `integrate` does; run operation by operation, a fresh
        process would compile each of its hundreds of operations on its own.
        The field and the method are part of the compiled program: a new
        field function (a lambda made at each call) compiles again. Inside a
        traced function the step is traced there."""
        if not any(isinstance(leaf, Tracer) for leaf in jax.tree.leaves((vector_field, t, y, dt, args, carried))):
            return _compiled_step(self, vector_field, as_traced(t), y, as_traced(dt), args, carried)
        return _step(self, vector_field, t, y, dt, args, carried)


class AbstractOfOneScene(AbstractMethod):
    """A method built from one scene's own solution (its parts' exact flows,
    or its whole flow): it lives on the scene's bundle and form, integrates
    that scene only, and carries the field at a step's start (for dense
    output) and nothing else."""

    scene: eqx.AbstractVar[AbstractFieldOnBundle]
    built_by: eqx.AbstractClassVar[str]
    """How the scene builds this method, for the message of `check_fits`."""

    @property
    def bundle(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.scene.bundle

    @property
    def form(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.scene.form

    def check_fits(self, vector_field) -> None:
        if not (vector_field is self.scene or eqx.tree_equal(vector_field, self.scene) is True):
            raise ValueError(
                f"this {type(self).__name__} integrates the scene it was built for ({type(self.scene).__name__}), but was given the "
                f"vector field {type(vector_field).__name__}; build it from that scene ({self.built_by})."
            )

    def initial_carried(self, vector_field: VectorField, t: Time, y: BundleElement, args: PyTree = None):
        """The field at (t, y): all a step carries (for dense output)."""
        return self.generator(vector_field, t, y, args)

    def start_field(self, carried):
        return carried


def as_traced(x):
    """A Python or NumPy number as a weakly typed float array, so that a
    compiled function takes it as an argument: one compilation for every
    value and every kind of number (a Python float, an int and a NumPy
    scalar trace alike), no constant that XLA folds with another rounding
    than the caller's, and no promotion of a float32 state (a weak type
    takes the state's)."""
    return jnp.asarray(float(x)) if isinstance(x, (int, float, np.number)) and not isinstance(x, bool) else x


def _step(method: AbstractMethod, vector_field, t, y, dt, args, carried) -> Step:
    if carried is None:
        carried = method.initial_carried(vector_field, t, y, args)
    return method.carried_step(vector_field, t, y, dt, args, carried)


_compiled_step = eqx.filter_jit(_step)
