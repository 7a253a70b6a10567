"""SE(3), the rigid motions x ↦ Rx + p, with closed forms.

An element holds its rotation R and translation p (the 4×4 matrix
[[R, p], [0, 1]]); se(3) is stored as 6-vectors u = (ω, v), the twist whose
matrix is [[ω̂, v], [0, 0]]. Then

    exp(ω, v) = (exp(ω̂), dexp_ω v),   [(ω, v), (x, y)] = (ω × x, ω × y − x × v),

with dexp_ω SO(3)'s right-trivialised differential (Σ ω̂ᵏ/(k+1)!).

The bracket makes ad_u = [[ω̂, 0], [v̂, ω̂]] block lower-triangular: the
matrix of the dual number ω̂ + εv̂ (ε² = 0). A function of ad_u is then
[[f(ω̂), 0], [Df(ω̂)[v̂], f(ω̂)]], Df(ω̂)[v̂] the derivative of f at ω̂
along v̂, so dexp_u and dexp⁻¹_u are SO(3)'s closed forms and their
derivatives in ω along v (forward-mode autodiff of the closed forms:
exact, not a series). The Cayley map of the 4×4 matrices stays in SE(3),
cay(ω, v) = (cay(ω̂), (I − ω̂/2)⁻¹v), and its inverse differential is the
matrix formula x − [u, x]/2 − u x u/4 written on the blocks.

SE(3)'s algebra has no bi-invariant pairing (`bi_invariant_pairing` is
False): it is the base of `DirectProduct`, `Semidirect` and `Cartesian`
bundles, not of `Cotangent`.
"""

from collections.abc import Callable
from typing import ClassVar, Literal, Self

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .pose import AbstractRotationAndTranslation, Twist, parts, rotate, twist
from .so3 import SO3


def _of_ad(so3_function: Callable[[Array, Array], Array], u: Twist, x: Twist) -> Twist:
    """f(ad_u) x for the function of ad that `so3_function(ω, a)` = f(ω̂) a
    is on so(3): (f(ω̂) a, f(ω̂) b + Df(ω̂)[v̂] a) for u = (ω, v), x = (a, b)
    (module docstring)."""
    omega, v = parts(u)
    a, b = parts(x)
    omega, v, a, b = jnp.broadcast_arrays(omega, v, a, b)
    f_a, derivative = jax.jvp(lambda w: so3_function(w, a), (omega,), (v,))
    return twist(f_a, so3_function(omega, b) + derivative)


class SE3(AbstractRotationAndTranslation):
    """A rigid motion x ↦ Rx + p (module docstring); leading batch axes allowed."""

    algebra_ndim: ClassVar[int] = 1  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = False  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def as_matrix(self) -> Float[Array, "*batch 4 4"]:
        """The homogeneous matrix [[R, p], [0, 1]]."""
        rotation, translation = self.rotation, jnp.broadcast_to(self.translation, self.rotation.shape[:-1])
        top = jnp.concatenate([rotation, translation[..., None]], axis=-1)
        bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], top.dtype), top.shape[:-2] + (1, 4))
        return jnp.concatenate([top, bottom], axis=-2)

    # --- group -----------------------------------------------------------------
    @classmethod
    def exp(cls, u: Twist) -> Self:
        """(exp(ω̂), dexp_ω v)."""
        omega, v = parts(u)
        return cls(SO3.exp(omega).matrix, SO3.dexp(omega, v))

    def log(self) -> Twist:
        """(ω, dexp⁻¹_ω p), ω = log R (`SO3.log`: rotation angles below π)."""
        omega = SO3(self.rotation).log()
        return twist(omega, SO3.dexp_inv(omega, self.translation))

    def multiply(self, other: Self) -> Self:  # pyright: ignore[reportIncompatibleMethodOverride]  # pyright binds the base's Self in a parameter to the base class
        return self._with(self.rotation @ other.rotation, rotate(self.rotation, other.translation) + self.translation)

    def inverse(self) -> Self:
        transposed = jnp.swapaxes(self.rotation, -1, -2)
        return self._with(transposed, -rotate(transposed, self.translation))

    def adjoint(self, u: Twist) -> Twist:
        """Ad_g (ω, v) = (Rω, Rv + p × Rω)."""
        omega, v = parts(u)
        turned = rotate(self.rotation, omega)
        return twist(turned, rotate(self.rotation, v) + jnp.cross(self.translation, turned))

    @classmethod
    def bracket(cls, u: Twist, v: Twist) -> Twist:
        """[(ω, v), (x, y)] = (ω × x, ω × y − x × v): the 4×4 matrices' commutator."""
        (omega, a), (x, b) = parts(u), parts(v)
        return twist(jnp.cross(omega, x), jnp.cross(omega, b) - jnp.cross(x, a))

    # --- differentials: SO(3)'s closed forms on the dual numbers ---------------
    @classmethod
    def dexp(cls, u: Twist, v: Twist) -> Twist:
        return _of_ad(SO3.dexp, u, v)

    @classmethod
    def dexp_inv(cls, u: Twist, v: Twist) -> Twist:
        return _of_ad(SO3.dexp_inv, u, v)

    @classmethod
    def inverse_shifted_ad(cls, u: Twist, v: Twist, alpha: float) -> Twist:
        """(I + α ad_u)⁻¹ (a, b) = (w, S(b − α v × w)), w = S a, S = (I + α ω̂)⁻¹."""
        (omega, shift), (a, b) = parts(u), parts(v)
        w = SO3.inverse_shifted_ad(omega, a, alpha)
        return twist(w, SO3.inverse_shifted_ad(omega, b - alpha * jnp.cross(shift, w), alpha))

    # --- the actions of exp(u) and cay(u), without forming them ---------------------
    @classmethod
    def exp_adjoint(cls, u: Twist, x: Twist) -> Twist:
        omega, v = parts(u)
        return _turned_and_shifted(SO3.exp_adjoint, SO3.dexp(omega, v), omega, x)

    @classmethod
    def exp_adjoint_change(cls, u: Twist, x: Twist) -> Twist:
        omega, v = parts(u)
        return _turned_and_shifted(SO3.exp_adjoint_change, SO3.dexp(omega, v), omega, x, change=True)

    @classmethod
    def cayley_adjoint(cls, u: Twist, x: Twist) -> Twist:
        omega, v = parts(u)
        return _turned_and_shifted(SO3.cayley_adjoint, SO3.inverse_shifted_ad(omega, v, -0.5), omega, x)

    @classmethod
    def cayley_adjoint_change(cls, u: Twist, x: Twist) -> Twist:
        omega, v = parts(u)
        return _turned_and_shifted(SO3.cayley_adjoint_change, SO3.inverse_shifted_ad(omega, v, -0.5), omega, x, change=True)

    # --- changes: the identity kept out ------------------------------------------
    @classmethod
    def exp_change(cls, u: Twist) -> "SE3":
        """(exp(ω̂) − I, dexp_ω v): the translation is its own change."""
        omega, v = parts(u)
        return cls(SO3.exp_change(omega), SO3.dexp(omega, v))

    def product_change(self, change: "SE3", side: Literal["right", "left"]) -> Self:
        """g·(e + c) − g = (R c_R, R c_p), or (e + c)·g − g = (c_R R, c_R p + c_p)."""
        if side == "right":
            return self._with(self.rotation @ change.rotation, rotate(self.rotation, change.translation))
        return self._with(change.rotation @ self.rotation, rotate(change.rotation, self.translation) + change.translation)

    # --- Cayley ------------------------------------------------------------------
    @classmethod
    def cayley(cls, u: Twist) -> Self:
        """(cay(ω̂), (I − ω̂/2)⁻¹ v)."""
        omega, v = parts(u)
        return cls(SO3.cayley(omega).matrix, SO3.inverse_shifted_ad(omega, v, -0.5))

    @classmethod
    def cayley_change(cls, u: Twist) -> "SE3":
        omega, v = parts(u)
        return cls(SO3.cayley_change(omega), SO3.inverse_shifted_ad(omega, v, -0.5))

    def cayley_inverse(self) -> Twist:
        """(cay⁻¹ R, (I − ω̂/2) p)."""
        omega = SO3(self.rotation).cayley_inverse()
        return twist(omega, self.translation - 0.5 * jnp.cross(omega, self.translation))

    @classmethod
    def dcayley_inv(cls, u: Twist, v: Twist) -> Twist:
        """x − [u, x]/2 − u x u/4 on the blocks: (dcay⁻¹_ω a, b − (ω × b − a × v)/2 − ω × (a × v)/4)."""
        (omega, shift), (a, b) = parts(u), parts(v)
        a_shift = jnp.cross(a, shift)
        return twist(SO3.dcayley_inv(omega, a), b - 0.5 * (jnp.cross(omega, b) - a_shift) - 0.25 * jnp.cross(omega, a_shift))


def _turned_and_shifted(turn, translation: Array, omega: Array, x: Twist, change: bool = False) -> Twist:
    """Ad_g (a, b) = (Ra, Rb + p × Ra) for g = (R, p), R applied as
    `turn(ω, ·)` (`SO3.exp_adjoint` or `SO3.cayley_adjoint`) and p =
    `translation`; with `change`, `turn` gives Ra − a and this Ad_g x − x,
    both parts rounded relative to the change (p × Ra is of its size)."""
    a, b = parts(x)
    turned_a = turn(omega, a)
    rotated_a = a + turned_a if change else turned_a
    return twist(turned_a, turn(omega, b) + jnp.cross(translation, rotated_a))
