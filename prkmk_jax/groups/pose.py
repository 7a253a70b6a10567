"""What SE(3) and SO(3) × ℝ³ share: an element is a rotation R and a
translation p, its algebra the 6-vectors (ω, v), angular part first. The
two groups differ in the product: SE(3)'s turns the second translation,
(R₁R₂, R₁p₂ + p₁); the direct product's adds it, (R₁R₂, p₁ + p₂)."""

from typing import Self

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._util import as_array, check_floating
from .base import AbstractQuadraticGroup
from .so3 import SO3

Twist = Float[Array, "*batch 6"]
"""An algebra element (ω, v): angular part first."""


def parts(u: Twist) -> tuple[Array, Array]:
    """(ω, v) of a twist."""
    return u[..., :3], u[..., 3:]


def twist(omega: Array, v: Array) -> Twist:
    """The twist (ω, v)."""
    omega, v = jnp.broadcast_arrays(omega, v)
    return jnp.concatenate([omega, v], axis=-1)


def rotate(rotation: Array, x: Array) -> Array:
    """R x for matrices and vectors with leading batch axes."""
    return jnp.einsum("...ij,...j->...i", rotation, x)


class AbstractRotationAndTranslation(AbstractQuadraticGroup):
    """An element (R, p): a rotation and a translation (module docstring)."""

    rotation: Float[Array, "*batch 3 3"] = eqx.field(converter=as_array)
    """R, with RᵀR = I and det R = 1."""
    translation: Float[Array, "*batch 3"] = eqx.field(converter=as_array)
    """p."""

    def __check_init__(self):
        name = type(self).__name__
        check_floating(self.rotation, f"a {name} rotation")
        check_floating(self.translation, f"a {name} translation")
        if self.rotation.shape[-2:] != (3, 3) or self.translation.shape[-1:] != (3,):
            shapes = f"{self.rotation.shape} and {self.translation.shape}"
            raise ValueError(f"{name} needs a (..., 3, 3) rotation and a (..., 3) translation, got shapes {shapes}.")

    def _with(self, rotation: Array, translation: Array) -> Self:
        # The concrete class's two fields; pyright counts the abstract class
        # variables as __init__ parameters too.
        return type(self)(rotation, translation)  # pyright: ignore[reportCallIssue]

    def identity_like(self) -> Self:
        rotation = jnp.broadcast_to(jnp.eye(3, dtype=self.rotation.dtype), self.rotation.shape)
        return self._with(rotation, jnp.zeros(rotation.shape[:-1], self.translation.dtype))

    def check(self) -> Self:
        """A rotation within the rotations' tolerance, and a finite translation."""
        rotation = SO3(self.rotation).check().matrix
        finite = jnp.all(jnp.isfinite(self.translation))
        translation = eqx.error_if(self.translation, ~finite, f"{type(self).__name__} translation is not finite (NaN or inf).")
        return self._with(rotation, translation)

    def project(self) -> Self:
        """The nearest rotation (`SO3.project`), the translation as it is."""
        return self._with(SO3(self.rotation).project().matrix, self.translation)

    def renormalized(self) -> Self:
        return self._with(SO3(self.rotation).renormalized().matrix, self.translation)
