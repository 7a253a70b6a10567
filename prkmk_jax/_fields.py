"""Vector fields on a bundle group, as the methods and drivers take them.

A vector field is any callable `f(t, y, args) -> (ξ, η)`, the generator of
y' = (ξ, η)·y (space form) or y' = y·(ξ, η) (body form). A field that also
says which bundle and form it is written for (the scenes) is an
`AbstractFieldOnBundle`, and checks its own parameters.
"""

import abc
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Int, PyTree, Real

from ._bundles import AbstractBundle, AlgebraPair, BundleElement

Time = float | Real[Array, ""]
"""A time or a step size: a Python number or a real scalar array."""
Iterations = Int[Array, ""]
"""A count of implicit iterations (an integer scalar)."""
VectorField = Callable[[Time, BundleElement, PyTree], AlgebraPair]
"""`f(t, y, args) -> (ξ, η)`: the generator of y' = (ξ, η)·y (space form) or
y' = y·(ξ, η) (body form)."""


class AbstractFieldOnBundle(eqx.Module):
    """A vector field that says which bundle it lives on and in which form
    (the scenes): a PRKMK method refuses it unless they are the method's own,
    since the same generator read on another bundle or from the other side is
    another system."""

    bundle: eqx.AbstractVar[AbstractBundle]
    """The bundle group the state lives on."""
    form: eqx.AbstractVar[Literal["space", "body"]]
    """Whether the generator acts from the left (space) or right (body)."""

    @abc.abstractmethod
    def checked_args(self, args: PyTree, /) -> PyTree:
        """`args` after this field's checks of its parameters: a type or shape
        that does not fit raises `TypeError`/`ValueError` at trace time, a
        value out of range (a moment of inertia that is not > 0) raises at
        run time through `eqx.error_if`, whose output this returns. The
        drivers (`integrate`, `resume`, `PRKMKSolver`) call it once a run,
        through `checked_field_args`."""


def checked_field_args(vector_field: VectorField, args: PyTree) -> PyTree:
    """`args` checked as both drivers (`integrate`, `PRKMKSolver`) check them
    before a run: every floating leaf finite (a run-time check), then the
    field's own checks where the field is a scene (an `AbstractFieldOnBundle`)."""

    def finite(leaf):
        if eqx.is_inexact_array(leaf):
            return eqx.error_if(leaf, ~jnp.all(jnp.isfinite(leaf)), "args contain a non-finite value (NaN or inf).")
        return leaf

    args = jax.tree.map(finite, args)
    if isinstance(vector_field, AbstractFieldOnBundle):
        return vector_field.checked_args(args)
    return args
