"""The additive group ℝⁿ (any trailing shape): product is +, exp is the identity."""

from typing import ClassVar, Literal, Self

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._util import as_array, check_floating
from .base import AbstractQuadraticGroup

# ℝⁿ is its own algebra (and dual); `n` stands for any trailing shape.
Vector = Float[Array, "*batch n"]


class VectorSpace(AbstractQuadraticGroup):
    """An element of the abelian group (ℝⁿ, +).

    With it, `Cartesian(VectorSpace)` is the classical phase space ℝⁿ×ℝⁿ and a
    PRKMK step there is exactly the classical partitioned RK step.
    """

    value: Float[Array, "*batch n"] = eqx.field(converter=as_array)
    """The vector."""

    def __check_init__(self):
        check_floating(self.value, "a VectorSpace value")

    algebra_ndim: ClassVar[int] = 1  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    @classmethod
    def exp(cls, u: Vector) -> Self:
        return cls(u)

    def log(self) -> Vector:
        return self.value

    def multiply(self, other: Self) -> Self:  # pyright: ignore[reportIncompatibleMethodOverride]  # pyright binds the base's Self in a parameter to the base class
        return type(self)(self.value + other.value)

    def inverse(self) -> Self:
        return type(self)(-self.value)

    def identity_like(self) -> Self:
        return type(self)(jnp.zeros_like(self.value))

    def adjoint(self, u: Vector) -> Vector:
        return u

    def algebra_zeros(self) -> Vector:
        return jnp.zeros_like(self.value)

    def project(self) -> Self:
        return self

    def check(self) -> Self:
        return type(self)(eqx.error_if(self.value, ~jnp.all(jnp.isfinite(self.value)), "VectorSpace element is not finite (NaN or inf)."))

    @classmethod
    def bracket(cls, u: Vector, v: Vector) -> Vector:
        return jnp.zeros_like(u)

    @classmethod
    def dexp(cls, u: Vector, v: Vector) -> Vector:
        return v

    @classmethod
    def dexp_inv(cls, u: Vector, v: Vector) -> Vector:
        return v

    @classmethod
    def exp_adjoint(cls, u: Vector, x: Vector) -> Vector:
        return x

    @classmethod
    def inverse_shifted_ad(cls, u: Vector, v: Vector, alpha: float) -> Vector:
        return v

    @classmethod
    def cayley(cls, u: Vector) -> Self:
        return cls(u)

    def cayley_inverse(self) -> Vector:
        return self.value

    @classmethod
    def dcayley(cls, u: Vector, v: Vector) -> Vector:
        return v

    @classmethod
    def dcayley_inv(cls, u: Vector, v: Vector) -> Vector:
        return v

    @classmethod
    def cayley_adjoint(cls, u: Vector, x: Vector) -> Vector:
        return x

    @classmethod
    def exp_change(cls, u: Vector) -> Vector:
        return u

    @classmethod
    def exp_adjoint_change(cls, u: Vector, x: Vector) -> Vector:
        return jnp.zeros_like(x)

    def product_change(self, change: Vector, side: Literal["right", "left"]) -> Self:
        # The product is +: self + change − self.
        return type(self)(change)

    @classmethod
    def cayley_change(cls, u: Vector) -> Vector:
        return cls.exp_change(u)  # cay = exp: translation by u

    @classmethod
    def cayley_adjoint_change(cls, u: Vector, x: Vector) -> Vector:
        return cls.exp_adjoint_change(u, x)
