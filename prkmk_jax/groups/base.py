"""Abstract base groups: the small API every base group G implements.

Conventions used throughout the package (they fix every sign):

* An element is an equinox Module holding arrays; leading batch axes are
  allowed wherever the shapes in the field docstrings say `*batch`.
* Algebra elements are plain arrays of shape `(*batch, *algebra_shape)`.
* `bracket(u, v)` is the matrix commutator uv − vu carried to the array
  representation, and `ad_u = bracket(u, ·)`.
* `dexp(u, v)` is the *right-trivialised* differential
  d/dt exp(u + tv)·exp(u)⁻¹ = Σ_k ad_u^k v/(k+1)!, and `dexp_inv` its inverse
  Σ_k B_k/k! ad_u^k with B_1 = −1/2 (the RKMK convention). The
  left-trivialised differential is the right one at −u:
  exp(u)⁻¹·d/dt exp(u + tv) = dexp(−u, v). The same holds for `dcayley`.
"""

import abc
import math
from collections.abc import Callable
from typing import Any, Literal, Self

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array

from .._series import dexp_inv_series, dexp_series

CONVERGED_SERIES_TERMS = 40
"""Powers of ad_u kept where a series stands in for an exact map (the
default `dexp` and `dexp_inv`, and so(n)'s small-u branch). The Bernoulli
series Σ B_k/k! ad_u^k converges for ‖ad_u‖ < 2π with terms decaying like
(‖ad_u‖/2π)^k, so 40 terms are exact to float64 round-off for
‖ad_u‖ ≲ 2.5, which a step's u is far inside."""


def solve_in_algebra(linear_map: Callable[[Array, Array], Array], u: Array, rhs: Array, algebra_ndim: int) -> Array:
    """w with `linear_map(u, w) = rhs`, for a map linear in w (an
    ad-polynomial at u, an inverse differential at u), solved for each element
    of a batch of (u, rhs) alone: one dense LU solve (`lineax`) of the map's
    matrix per element. The differentials without a closed form use it."""
    u, rhs = jnp.broadcast_arrays(u, rhs)
    algebra_shape = rhs.shape[rhs.ndim - algebra_ndim :]
    size = math.prod(algebra_shape)

    def solve_one(u_one, rhs_one):
        # The map's matrix by forward-mode autodiff; the solve sees arrays
        # only, so lineax's compiled solve is reused whatever the map.
        matrix = jax.jacfwd(lambda w: linear_map(u_one, w))(rhs_one).reshape(size, size)
        solution = lx.linear_solve(lx.MatrixLinearOperator(matrix), rhs_one.reshape(size), lx.LU())
        return solution.value.reshape(algebra_shape)

    solved = jax.vmap(solve_one)(u.reshape((-1, *algebra_shape)), rhs.reshape((-1, *algebra_shape)))
    return solved.reshape(rhs.shape)


def _difference(a: Any, b: Any) -> Any:
    return jax.tree.map(jnp.subtract, a, b)


class AbstractLieGroup(eqx.Module):
    """An element of a (matrix) Lie group G, with the algebra operations of g.

    A group implements the nine abstract methods (`exp`, `log`, `multiply`,
    `inverse`, `identity_like`, `adjoint`, `bracket`, `check`, `project`).
    The others have general defaults built from those: override them where a
    closed form is faster or rounds better (SO(3)'s Rodrigues formulas)."""

    algebra_ndim: eqx.AbstractClassVar[int]
    """Number of trailing axes of an algebra element (1: vectors, 2: matrices)."""
    bi_invariant_pairing: eqx.AbstractClassVar[bool]
    """Whether g ≅ g* through a pairing for which every ad_u is skew-adjoint.

    Then Ad*_g = Ad_{g⁻¹} and ad*_u = −ad_u under the identification, which is
    what the cotangent bundle G⋉_{Ad*}g* uses (true for compact groups)."""

    # --- what every group says ----------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def exp(cls, u: Array) -> Self:
        """The exponential map g → G."""

    @abc.abstractmethod
    def log(self) -> Array:
        """Inverse of `exp` on its principal domain."""

    @abc.abstractmethod
    def multiply(self, other: Self) -> Self:
        """The group product self·other."""

    @abc.abstractmethod
    def inverse(self) -> Self:
        """The group inverse."""

    @abc.abstractmethod
    def identity_like(self) -> Self:
        """The identity, with the batch shape and dtype of `self`."""

    @abc.abstractmethod
    def adjoint(self, u: Array) -> Array:
        """Ad_g u = g u g⁻¹."""

    @classmethod
    @abc.abstractmethod
    def bracket(cls, u: Array, v: Array) -> Array:
        """The Lie bracket [u, v]."""

    @abc.abstractmethod
    def check(self) -> Self:
        """Return `self`, raising at run time (`eqx.error_if`) if it is not
        a valid element (e.g. not orthogonal, or not finite)."""

    @abc.abstractmethod
    def project(self) -> Self:
        """The nearest valid element: for rotations the nearest rotation matrix
        (Frobenius norm); `self` for a group every array of its shape belongs
        to. Rounding drift of a very long run (float32 keeps
        max|RᵀR − I| ≈ 2e-4 over 10⁶ steps) stays far inside what `check`
        accepts; this restores such a state exactly, on request. It also
        turns data that is no rotation at all into one, so it is never
        applied silently."""

    # --- defaults, built from the above ---------------------------------------------------
    def algebra_zeros(self) -> Array:
        """A zero algebra element with the batch shape and dtype of `self`."""
        shape = jax.eval_shape(self.log)
        return jnp.zeros(shape.shape, shape.dtype)

    def renormalized(self) -> Self:
        """One cheap correction toward the group that removes rounding drift to
        first order, applied by the PRKMK step to every new state in low
        precision; `self` by default (a group whose arrays cannot leave it).
        For rotations Björck's step Q + ½Q(I − QᵀQ), which squares the
        defect, taken once max|QᵀQ − I| is past a few ulps
        (`AbstractRotationGroup`): in float32 the rounding of exp(u) and of
        the product is systematic for steady rotations, and the state would
        otherwise leave the group steadily."""
        return self

    @classmethod
    def dexp(cls, u: Array, v: Array) -> Array:
        """Right-trivialised differential of exp: Σ ad_u^k v/(k+1)!
        (by default the series to `CONVERGED_SERIES_TERMS` powers)."""
        return dexp_series(cls.bracket, u, v, CONVERGED_SERIES_TERMS)

    @classmethod
    def dexp_inv(cls, u: Array, v: Array) -> Array:
        """Inverse of `dexp` in its exact (or converged-series) form: by
        default the Bernoulli series to `CONVERGED_SERIES_TERMS` powers,
        exact to round-off for the u of a step (‖ad_u‖ ≲ 2.5)."""
        return dexp_inv_series(cls.bracket, u, v, CONVERGED_SERIES_TERMS)

    @classmethod
    def exp_adjoint(cls, u: Array, x: Array) -> Array:
        """Ad_{exp(u)} x, the same as `exp(u).adjoint(x)`. Groups with a closed
        form act on x directly, without forming exp(u) (Rodrigues on SO(3)):
        the fiber update of a PRKMK step on G⋉g is this action."""
        return cls.exp(u).adjoint(x)

    # --- changes: the difference of two nearby elements, the identity kept out ----
    # A step's update is summed from these (compensated summation,
    # `AbstractMethod.advance`). The defaults subtract the identity after the
    # fact, so they round relative to e rather than to the change; a group
    # whose steps should keep the last digits overrides them.
    def change_from_identity(self) -> Any:
        """self − e in the arrays an element holds (the container a `*_change`
        method returns, which `product_change` reads)."""
        return _difference(self, self.identity_like())

    @classmethod
    def exp_change(cls, u: Array) -> Any:
        """exp(u) − e in the arrays an element holds (the matrix of a
        rotation), ideally computed without adding the identity in, so that
        its rounding is relative to the change, not to e."""
        return cls.exp(u).change_from_identity()

    @classmethod
    def exp_adjoint_change(cls, u: Array, x: Array) -> Array:
        """Ad_{exp(u)} x − x, ideally computed without adding x in (see `exp_change`)."""
        return cls.exp_adjoint(u, x) - x

    def product_change(self, change: Any, side: Literal["right", "left"]) -> Self:
        """self·g − self (`side="right"`) or g·self − self (`"left"`) for the g
        with g − e = `change` (`exp_change`): a container with an element's
        shape holding the difference of the two elements' arrays, not a
        group element."""
        g = jax.tree.map(jnp.add, self.identity_like(), change)
        return _difference(self.multiply(g) if side == "right" else g.multiply(self), self)

    def __matmul__(self, other: Self) -> Self:
        return self.multiply(other)


class AbstractQuadraticGroup(AbstractLieGroup):
    """A group on which the Cayley map cay(u) = (1 − u/2)⁻¹(1 + u/2) is a
    local diffeomorphism g → G: the quadratic groups {X : XᵀJX = J} (paper §4.4),
    the additive group ℝⁿ (whose unipotent matrix representation makes
    cay(u) = exp(u) = translation by u) and SE(3) (its 4×4 matrices). Such a
    group adds three methods (`cayley`, `cayley_inverse`, `dcayley_inv`); the
    rest default."""

    @classmethod
    @abc.abstractmethod
    def cayley(cls, u: Array) -> Self:
        """cay(u) = (1 − u/2)⁻¹(1 + u/2)."""

    @abc.abstractmethod
    def cayley_inverse(self) -> Array:
        """cay⁻¹(g) = 2(g + 1)⁻¹(g − 1), the inverse of `cayley` (defined where
        g + 1 is invertible: rotation angles < π)."""

    @classmethod
    @abc.abstractmethod
    def dcayley_inv(cls, u: Array, v: Array) -> Array:
        """Inverse differential (1 − u/2) v (1 + u/2) = v − [u,v]/2 − uvu/4."""

    @classmethod
    def dcayley(cls, u: Array, v: Array) -> Array:
        """Right-trivialised differential (1 − u/2)⁻¹ v (1 + u/2)⁻¹ (by
        default `dcayley_inv` solved for v, `solve_in_algebra`)."""
        return solve_in_algebra(cls.dcayley_inv, u, v, cls.algebra_ndim)

    @classmethod
    def cayley_adjoint(cls, u: Array, x: Array) -> Array:
        """Ad_{cay(u)} x, the same as `cayley(u).adjoint(x)` (see `exp_adjoint`)."""
        return cls.cayley(u).adjoint(x)

    @classmethod
    def cayley_change(cls, u: Array) -> Any:
        """cay(u) − e, ideally with the identity kept out (see `exp_change`)."""
        return cls.cayley(u).change_from_identity()

    @classmethod
    def cayley_adjoint_change(cls, u: Array, x: Array) -> Array:
        """Ad_{cay(u)} x − x, ideally with x kept out (see `exp_change`)."""
        return cls.cayley_adjoint(u, x) - x

    @classmethod
    def shifted_cayley_adjoint_inverse(cls, u: Array, x: Array) -> Array:
        """(I + ½ ad_u) Ad_{cay(u)⁻¹} x: how the left-trivialised semidirect
        Cayley map's inverse differential moves the fiber
        (`Cayley.semidirect_inverse_differential`); by default its two
        factors (cay(u)⁻¹ = cay(−u))."""
        z = cls.cayley_adjoint(-u, x)
        return z + 0.5 * cls.bracket(u, z)

    @classmethod
    def inverse_shifted_ad(cls, u: Array, v: Array, alpha: float) -> Array:
        """(I + α ad_u)⁻¹ v, the fiber factor of the semidirect Cayley map
        (§4.4); by default a dense solve per element (`solve_in_algebra`)."""
        return solve_in_algebra(lambda uu, w: w + alpha * cls.bracket(uu, w), u, v, cls.algebra_ndim)
