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
from typing import Literal, Self

import equinox as eqx
from jaxtyping import Array


class AbstractLieGroup(eqx.Module):
    """An element of a (matrix) Lie group G, with the algebra operations of g."""

    algebra_ndim: eqx.AbstractClassVar[int]
    """Number of trailing axes of an algebra element (1: vectors, 2: matrices)."""
    bi_invariant_pairing: eqx.AbstractClassVar[bool]
    """Whether g ≅ g* through a pairing for which every ad_u is skew-adjoint.

    Then Ad*_g = Ad_{g⁻¹} and ad*_u = −ad_u under the identification, which is
    what the cotangent bundle G⋉_{Ad*}g* uses (true for compact groups)."""

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

    @abc.abstractmethod
    def algebra_zeros(self) -> Array:
        """A zero algebra element with the batch shape and dtype of `self`."""

    @abc.abstractmethod
    def check(self) -> Self:
        """Return `self`, raising at run time (`eqx.error_if`) if it is not
        a valid element (e.g. not orthogonal, or not finite)."""

    @abc.abstractmethod
    def renormalized(self) -> Self:
        """One cheap correction toward the group that removes rounding drift to
        first order (for rotations Björck's step Q + ½Q(I − QᵀQ), which
        squares the defect, taken once max|QᵀQ − I| is past a few ulps:
        `groups._util.bjorck_step_where_drifted`). The PRKMK step applies it
        to every new state in low precision: in float32 the rounding of
        exp(u) and of the product is systematic for steady rotations, and
        the state would otherwise leave the group steadily."""

    @abc.abstractmethod
    def project(self) -> Self:
        """The nearest valid element: for rotations the nearest rotation matrix
        (Frobenius norm). Rounding drift of a very long run (float32 keeps
        max|RᵀR − I| ≈ 2e-4 over 10⁶ steps) stays far inside what `check`
        accepts; this restores such a state exactly, on request. It also
        turns data that is no rotation at all into one, so it is never
        applied silently."""

    @classmethod
    @abc.abstractmethod
    def bracket(cls, u: Array, v: Array) -> Array:
        """The Lie bracket [u, v]."""

    @classmethod
    @abc.abstractmethod
    def dexp(cls, u: Array, v: Array) -> Array:
        """Right-trivialised differential of exp: Σ ad_u^k v/(k+1)!."""

    @classmethod
    @abc.abstractmethod
    def dexp_inv(cls, u: Array, v: Array) -> Array:
        """Inverse of `dexp` in its exact (or converged-series) form."""

    @classmethod
    @abc.abstractmethod
    def exp_adjoint(cls, u: Array, x: Array) -> Array:
        """Ad_{exp(u)} x, the same as `exp(u).adjoint(x)`. Groups with a closed
        form act on x directly, without forming exp(u) (Rodrigues on SO(3)):
        the fiber update of a PRKMK step on G⋉g is this action."""

    # --- changes: the difference of two nearby elements, the identity kept out ----
    @classmethod
    @abc.abstractmethod
    def exp_change(cls, u: Array) -> Array:
        """exp(u) − e in the array an element holds (the matrix of a rotation),
        computed without adding the identity in: its rounding is relative to
        the change, not to e. A step's update is summed from it (compensated
        summation, `AbstractMethod.advance`)."""

    @classmethod
    @abc.abstractmethod
    def exp_adjoint_change(cls, u: Array, x: Array) -> Array:
        """Ad_{exp(u)} x − x, computed without adding x in (see `exp_change`)."""

    @abc.abstractmethod
    def product_change(self, change: Array, side: Literal["right", "left"]) -> Self:
        """self·g − self (`side="right"`) or g·self − self (`"left"`) for the g
        with g − e = `change` (`exp_change`): a container with an element's
        shape holding the difference of the two elements' arrays, not a
        group element."""

    def __matmul__(self, other: Self) -> Self:
        return self.multiply(other)


class AbstractQuadraticGroup(AbstractLieGroup):
    """A group on which the Cayley map cay(u) = (1 − u/2)⁻¹(1 + u/2) is a
    local diffeomorphism g → G: the quadratic groups {X : XᵀJX = J} (paper §4.4)
    and the additive group ℝⁿ (whose unipotent matrix representation makes
    cay(u) = exp(u) = translation by u)."""

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
    def dcayley(cls, u: Array, v: Array) -> Array:
        """Right-trivialised differential (1 − u/2)⁻¹ v (1 + u/2)⁻¹."""

    @classmethod
    @abc.abstractmethod
    def dcayley_inv(cls, u: Array, v: Array) -> Array:
        """Inverse differential (1 − u/2) v (1 + u/2) = v − [u,v]/2 − uvu/4."""

    @classmethod
    @abc.abstractmethod
    def cayley_adjoint(cls, u: Array, x: Array) -> Array:
        """Ad_{cay(u)} x, the same as `cayley(u).adjoint(x)` (see `exp_adjoint`)."""

    @classmethod
    @abc.abstractmethod
    def cayley_change(cls, u: Array) -> Array:
        """cay(u) − e, the identity kept out (see `exp_change`)."""

    @classmethod
    @abc.abstractmethod
    def cayley_adjoint_change(cls, u: Array, x: Array) -> Array:
        """Ad_{cay(u)} x − x, x kept out (see `exp_change`)."""

    @classmethod
    @abc.abstractmethod
    def inverse_shifted_ad(cls, u: Array, v: Array, alpha: float) -> Array:
        """(I + α ad_u)⁻¹ v, the fiber factor of the semidirect Cayley map (§4.4)."""
