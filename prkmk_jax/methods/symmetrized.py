"""Φ̂_h = Φ*_{h/2} ∘ Φ_{h/2}: a symmetric method from any method with an
adjoint step, and `symmetry_defect`, which measures how far a method is
from symmetric on a problem.

Whether a PRKMK method is symmetric depends on the tableau, the coordinate
map, its truncation and the field (the centre of the coordinates is the
step's start, which the reversed step does not share). Measured on the free
rigid body (tests/test_composed.py): Störmer–Verlet with `Exp()` or
`Cayley()` at their default truncation (df⁻¹ ≈ I) is symmetric to round-off
on `Cotangent(SO3)` (η ≡ 0: both stage points are the step's end points);
with the exact df⁻¹, on `Cartesian(SO3)`, or for Lobatto IIIA–IIIB 4, it is
not. `Symmetrized(method)` is symmetric whatever the method, at the cost of
a second, fully implicit half step.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .._bundles import BundleElement
from .._fields import VectorField
from .adjoint import AbstractMadeOfSteps, Adjoint
from .base import AbstractMethod, Step, compensated, first_failure, largest_entry_difference, no_compensation


class Symmetrized(AbstractMadeOfSteps):
    """Φ̂_h = Φ*_{h/2} ∘ Φ_{h/2}: half a step of a PRKMK method Φ, then half a
    step of its adjoint (`Adjoint`). Φ̂ is symmetric for any Φ, of order p
    (p even) or p + 1 (p odd: symplectic Euler gives order 2), and a
    symmetric base for `Composition` where Φ itself is not symmetric. Of a
    `Splitting` (already symmetric) it is two half steps."""

    method: AbstractMethod

    def __check_init__(self):
        if not isinstance(self.method, AbstractMethod) or not self.method.has_adjoint_step:
            raise TypeError(f"Symmetrized takes a PRKMK method or a Splitting (with an adjoint step), got {type(self.method).__name__}.")

    @property
    def adjoint(self) -> Adjoint:
        return Adjoint(self.method)  # pyright: ignore[reportCallIssue]  # equinox: AbstractVars implemented by properties are not __init__ fields

    @property
    def order(self) -> int:
        p = self.method.order
        return p + p % 2

    @property
    def is_symmetric(self) -> bool:
        return True

    def initial_carried(self, vector_field, t, y, args=None):
        carried = self.method.initial_carried(vector_field, t, y, args)
        return carried, carried

    def start_field(self, carried):
        return self.method.start_field(carried[0])

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        dtype = jnp.result_type(*jax.tree.leaves(y))
        half = jnp.asarray(dt, dtype) / 2
        t = jnp.asarray(t, dtype)
        first = self.method.step(vector_field, t, y, half, args, carried[0])
        # The half steps' roundings summed as the drivers sum steps'
        # (`compensated`): the step hands on what both lost.
        y_half, lost = compensated(first.y, first.rounding, no_compensation(y))
        second = self.adjoint.step(vector_field, t + half, y_half, half, args, carried[1])
        y_next, lost = compensated(second.y, second.rounding, lost)
        result = first_failure(first.result, second.result)
        increment = self.increment_between(y, y_next)
        rounding = None if first.rounding is None and second.rounding is None else lost
        return Step(y_next, increment, result, first.iterations + second.iterations, rounding, (first.carried, second.carried))


def symmetry_defect(
    method: AbstractMethod, vector_field: VectorField, y: BundleElement, dt: float | Array, args: PyTree = None, t: float | Array = 0.0
) -> Array:
    """max |Φ_{−h}(Φ_h(y)) − y| over the entries of the state (in its matrix
    or vector embedding): zero up to round-off and the stage tolerance for a
    symmetric method, O(h^{p+1}) for a non-symmetric one of order p.
    Compiled once for each shape of its inputs."""
    return _symmetry_defect(method, vector_field, y, jnp.asarray(dt), args, jnp.asarray(t))


@eqx.filter_jit
def _symmetry_defect(method, vector_field, y, dt, args, t):
    y_forward = method.step(vector_field, t, y, dt, args).y
    y_back = method.step(vector_field, t + dt, y_forward, -dt, args).y
    return largest_entry_difference(y_back, y)
