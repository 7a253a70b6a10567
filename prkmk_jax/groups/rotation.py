"""Rotations as orthogonal matrices: what SO(3) and SO(n) share."""

from typing import Literal, Self

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._util import bjorck_step_where_drifted, checked_rotation, nearest_rotation
from .base import AbstractQuadraticGroup


class AbstractRotationGroup(AbstractQuadraticGroup):
    """A rotation group SO(n) whose elements hold an orthogonal matrix with
    determinant 1: the product, inverse, identity and the checks and
    corrections of such matrices (`SO3`, `SOn` add their algebra)."""

    matrix: eqx.AbstractVar[Float[Array, "*batch n n"]]
    """The rotation matrix R, RᵀR = I, det R = 1."""

    def _with_matrix(self, matrix: Array) -> Self:
        # The concrete class's one field; pyright counts the abstract class
        # variables as __init__ parameters too.
        return type(self)(matrix)  # pyright: ignore[reportCallIssue]

    def multiply(self, other: Self) -> Self:  # pyright: ignore[reportIncompatibleMethodOverride]  # pyright binds the base's Self in a parameter to the base class
        return self._with_matrix(self.matrix @ other.matrix)

    def inverse(self) -> Self:
        return self._with_matrix(jnp.swapaxes(self.matrix, -1, -2))

    def identity_like(self) -> Self:
        return self._with_matrix(jnp.broadcast_to(jnp.eye(self.matrix.shape[-1], dtype=self.matrix.dtype), self.matrix.shape))

    def check(self) -> Self:
        return self._with_matrix(checked_rotation(self.matrix, type(self).__name__))

    def project(self) -> Self:
        return self._with_matrix(nearest_rotation(self.matrix))

    def renormalized(self) -> Self:
        return self._with_matrix(bjorck_step_where_drifted(self.matrix))

    def change_from_identity(self) -> Array:
        return self.matrix - jnp.eye(self.matrix.shape[-1], dtype=self.matrix.dtype)

    def product_change(self, change: Array, side: Literal["right", "left"]) -> Self:
        return self._with_matrix(self.matrix @ change if side == "right" else change @ self.matrix)
