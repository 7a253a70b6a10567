"""SO(3) × ℝ³, the direct product of the rotations and the translations: a
body's attitude and its position, each moving on its own.

An element holds (R, p) as `SE3` does, its algebra the 6-vectors (ω, v),
but the product adds the translations, (R₁R₂, p₁ + p₂): the position is not
turned with the body. So the bracket is ((ω × x), 0), Ad_g(ω, v) = (Rω, v),
and every map is SO(3)'s on ω and the identity on v (exp, dexp and Cayley
alike: ℝ³'s maps are translations). The Euclidean pairing is
Ad-invariant on both factors, so T*(SO(3) × ℝ³) is a `Cotangent` bundle:
body angular momentum and the (inertial) linear momentum, the model of a
body whose translation and rotation couple only through a potential.
"""

from typing import ClassVar, Literal, Self

import jax.numpy as jnp

from .pose import AbstractRotationAndTranslation, Twist, parts, rotate, twist
from .so3 import SO3


class SO3xR3(AbstractRotationAndTranslation):
    """An attitude R and a position p, multiplied factor by factor (module
    docstring); leading batch axes allowed."""

    algebra_ndim: ClassVar[int] = 1  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    # --- group -----------------------------------------------------------------
    @classmethod
    def exp(cls, u: Twist) -> Self:
        omega, v = parts(u)
        return cls(SO3.exp(omega).matrix, jnp.broadcast_to(v, omega.shape))

    def log(self) -> Twist:
        return twist(SO3(self.rotation).log(), self.translation)

    def multiply(self, other: Self) -> Self:  # pyright: ignore[reportIncompatibleMethodOverride]  # pyright binds the base's Self in a parameter to the base class
        return self._with(self.rotation @ other.rotation, self.translation + other.translation)

    def inverse(self) -> Self:
        return self._with(jnp.swapaxes(self.rotation, -1, -2), -self.translation)

    def adjoint(self, u: Twist) -> Twist:
        omega, v = parts(u)
        return twist(rotate(self.rotation, omega), v)

    @classmethod
    def bracket(cls, u: Twist, v: Twist) -> Twist:
        (omega, _), (x, _) = parts(u), parts(v)
        return twist(jnp.cross(omega, x), jnp.zeros_like(omega))

    # --- differentials and actions: SO(3)'s on ω, the identity on v ---------------
    @classmethod
    def dexp(cls, u: Twist, v: Twist) -> Twist:
        return _on_rotations(SO3.dexp, u, v)

    @classmethod
    def dexp_inv(cls, u: Twist, v: Twist) -> Twist:
        return _on_rotations(SO3.dexp_inv, u, v)

    @classmethod
    def exp_adjoint(cls, u: Twist, x: Twist) -> Twist:
        return _on_rotations(SO3.exp_adjoint, u, x)

    @classmethod
    def inverse_shifted_ad(cls, u: Twist, v: Twist, alpha: float) -> Twist:
        return _on_rotations(lambda omega, a: SO3.inverse_shifted_ad(omega, a, alpha), u, v)

    @classmethod
    def dcayley(cls, u: Twist, v: Twist) -> Twist:
        return _on_rotations(SO3.dcayley, u, v)

    @classmethod
    def dcayley_inv(cls, u: Twist, v: Twist) -> Twist:
        return _on_rotations(SO3.dcayley_inv, u, v)

    @classmethod
    def cayley_adjoint(cls, u: Twist, x: Twist) -> Twist:
        return _on_rotations(SO3.cayley_adjoint, u, x)

    # --- changes: the identity kept out ------------------------------------------
    @classmethod
    def exp_change(cls, u: Twist) -> "SO3xR3":
        omega, v = parts(u)
        return cls(SO3.exp_change(omega), jnp.broadcast_to(v, omega.shape))

    @classmethod
    def exp_adjoint_change(cls, u: Twist, x: Twist) -> Twist:
        return _on_rotations(SO3.exp_adjoint_change, u, x, translations=False)

    def product_change(self, change: "SO3xR3", side: Literal["right", "left"]) -> Self:
        """g·(e + c) − g = (R c_R, c_p), or (e + c)·g − g = (c_R R, c_p)."""
        rotation = self.rotation @ change.rotation if side == "right" else change.rotation @ self.rotation
        return self._with(rotation, jnp.broadcast_to(change.translation, rotation.shape[:-1]))

    # --- Cayley ------------------------------------------------------------------
    @classmethod
    def cayley(cls, u: Twist) -> Self:
        omega, v = parts(u)
        return cls(SO3.cayley(omega).matrix, jnp.broadcast_to(v, omega.shape))

    @classmethod
    def cayley_change(cls, u: Twist) -> "SO3xR3":
        omega, v = parts(u)
        return cls(SO3.cayley_change(omega), jnp.broadcast_to(v, omega.shape))

    def cayley_inverse(self) -> Twist:
        return twist(SO3(self.rotation).cayley_inverse(), self.translation)

    @classmethod
    def cayley_adjoint_change(cls, u: Twist, x: Twist) -> Twist:
        return _on_rotations(SO3.cayley_adjoint_change, u, x, translations=False)


def _on_rotations(so3_map, u: Twist, x: Twist, translations: bool = True) -> Twist:
    """(so3_map(ω, a), b) for u = (ω, v), x = (a, b): a linear map that is
    SO(3)'s on the rotations and the identity on the translations; with
    `translations` False, (so3_map(ω, a), 0) (a change, which the identity
    leaves at 0)."""
    omega, _ = parts(u)
    a, b = parts(x)
    turned = so3_map(omega, a)
    return twist(turned, jnp.broadcast_to(b, turned.shape) if translations else jnp.zeros_like(turned))
