"""SO(n) for general n; so(n) is stored as skew-symmetric (n, n) matrices."""

from typing import ClassVar, Self

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float

from .base import AbstractQuadraticGroup
from ..series import dexp_inv_series
from ._util import as_array, check_floating, checked_rotation, nearest_rotation, bjorck_step

EXACT_SERIES_TERMS = 40
"""Terms of the Bernoulli series used as the 'exact' dexp⁻¹ on so(n).

The series Σ B_k/k! ad_u^k converges for ‖ad_u‖ < 2π; its terms decay like
(‖ad_u‖/2π)^k, so 40 terms are exact to float64 round-off for ‖ad_u‖ ≲ 2.5
(‖ad_u‖ ≤ 2‖u‖₂ for the spectral norm of skew u)."""


def _transpose(m):
    return jnp.swapaxes(m, -1, -2)


def _commutator(u, v):
    return u @ v - v @ u


def _eye_like(m):
    return jnp.eye(m.shape[-1], dtype=m.dtype)


class SOn(AbstractQuadraticGroup):
    """A rotation in SO(n); n is read off the matrix shape."""

    matrix: Float[Array, "*batch n n"] = eqx.field(converter=as_array)
    """Orthogonal matrix with det = 1."""

    algebra_ndim: ClassVar[int] = 2
    bi_invariant_pairing: ClassVar[bool] = True

    def __check_init__(self):
        check_floating(self.matrix, "an SOn matrix")
        if self.matrix.ndim < 2 or self.matrix.shape[-1] != self.matrix.shape[-2]:
            raise ValueError(f"SOn needs a (..., n, n) matrix, got shape {self.matrix.shape}.")

    @classmethod
    def exp(cls, u: Float[Array, "*batch n n"]) -> Self:
        expm = jsl.expm
        for _ in range(u.ndim - 2):
            expm = jax.vmap(expm)
        return cls(expm(u))

    def log(self) -> Float[Array, "*batch n n"]:
        """Principal logarithm (angles < π) from the polar split R = S + A.

        S = (R + Rᵀ)/2 and A = (R − Rᵀ)/2 commute and, in each invariant plane
        of rotation angle θ, equal cos θ·I and sin θ·J, so log R = g(S)·A with
        g(c) = arccos(c)/√(1 − c²) evaluated by a symmetric eigendecomposition.
        """
        r = self.matrix
        sym = 0.5 * (r + _transpose(r))
        skew = 0.5 * (r - _transpose(r))
        c, w = jnp.linalg.eigh(sym)
        c = jnp.clip(c, -1.0, 1.0)
        one_minus = 1.0 - c
        small = one_minus < 1e-6
        safe = jnp.where(small, 0.5, c)
        # arccos(c)/sin(arccos c); near c = 1: 1 + (1 − c)/3 + 2(1 − c)²/15.
        g = jnp.where(small, 1.0 + one_minus / 3 + 2 * one_minus**2 / 15, jnp.arccos(safe) / jnp.sqrt(1.0 - safe**2))
        g_matrix = (w * g[..., None, :]) @ _transpose(w)
        out = g_matrix @ skew
        return 0.5 * (out - _transpose(out))

    def multiply(self, other: Self) -> Self:
        return SOn(self.matrix @ other.matrix)

    def inverse(self) -> Self:
        return SOn(_transpose(self.matrix))

    def identity_like(self) -> Self:
        return SOn(jnp.broadcast_to(_eye_like(self.matrix), self.matrix.shape))

    def adjoint(self, u):
        return self.matrix @ u @ _transpose(self.matrix)

    def algebra_zeros(self):
        return jnp.zeros_like(self.matrix)

    def check(self) -> Self:
        return SOn(checked_rotation(self.matrix, "SOn"))

    def project(self) -> Self:
        return SOn(nearest_rotation(self.matrix))

    def renormalized(self) -> Self:
        return SOn(bjorck_step(self.matrix))

    @classmethod
    def bracket(cls, u, v):
        return _commutator(u, v)

    @classmethod
    def dexp(cls, u, v):
        """From the Fréchet derivative L(u, v) of expm: dexp_u v = L(u, v) e^{−u}."""
        frechet = jsl.expm_frechet
        for _ in range(u.ndim - 2):
            frechet = jax.vmap(frechet)
        expu, deriv = frechet(u, v)
        return deriv @ _transpose(expu)

    @classmethod
    def dexp_inv(cls, u, v):
        """Bernoulli series with `EXACT_SERIES_TERMS` terms (see there)."""
        return dexp_inv_series(cls.bracket, u, v, EXACT_SERIES_TERMS)

    @classmethod
    def exp_adjoint(cls, u, x):
        return cls.exp(u).adjoint(x)

    @classmethod
    def inverse_shifted_ad(cls, u, v, alpha):
        """Dense solve on the flattened algebra (ad_u as an n²×n² matrix)."""
        if u.ndim > 2:
            return jax.vmap(lambda uu, vv: cls.inverse_shifted_ad(uu, vv, alpha))(u, v)
        ad = jax.jacfwd(lambda w: _commutator(u, w))(v).reshape(v.size, v.size)
        eye = jnp.eye(v.size, dtype=v.dtype)
        return jnp.linalg.solve(eye + alpha * ad, v.reshape(-1)).reshape(v.shape)

    @classmethod
    def cayley(cls, u) -> Self:
        eye = _eye_like(u)
        return cls(jnp.linalg.solve(eye - 0.5 * u, eye + 0.5 * u))

    def cayley_inverse(self):
        r = self.matrix
        eye = _eye_like(r)
        # (R + 1)⁻¹ and R − 1 commute; the solve keeps the result skew up to round-off.
        return 2.0 * jnp.linalg.solve(r + eye, r - eye)

    @classmethod
    def dcayley(cls, u, v):
        eye = _eye_like(u)
        left = jnp.linalg.solve(eye - 0.5 * u, v)
        # X (1 + u/2)⁻¹ = ((1 + u/2)⁻ᵀ Xᵀ)ᵀ
        return _transpose(jnp.linalg.solve(_transpose(eye + 0.5 * u), _transpose(left)))

    @classmethod
    def dcayley_inv(cls, u, v):
        return v - 0.5 * _commutator(u, v) - 0.25 * u @ v @ u

    @classmethod
    def cayley_adjoint(cls, u, x):
        return cls.cayley(u).adjoint(x)
