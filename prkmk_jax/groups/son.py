"""SO(n) for general n; so(n) is stored as skew-symmetric (n, n) matrices."""

import math
from typing import ClassVar, Self

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float

from ..series import dexp_inv_series
from ._util import as_array, bjorck_step, check_floating, checked_rotation, nearest_rotation
from .base import AbstractQuadraticGroup

EXACT_SERIES_TERMS = 40
"""Terms of the Bernoulli series used as the exact dexp⁻¹ on so(n) for small u.

The series Σ B_k/k! ad_u^k converges for ‖ad_u‖ < 2π; its terms decay like
(‖ad_u‖/2π)^k, so 40 terms are exact to float64 round-off for ‖ad_u‖ ≲ 2.5.
‖ad_u‖ ≤ 2‖u‖₂ ≤ √2‖u‖_F for skew u, so the series serves ‖u‖_F ≤
`SERIES_RADIUS`; beyond it `SOn.dexp_inv` diagonalises ad_u."""
SERIES_RADIUS = 1.75


NEAR_IDENTITY = 0.1
"""‖I − S‖_F below which `SOn.log` uses the power series of g(S)."""

# so(n) as skew-symmetric n×n matrices (and its dual, by the trace pairing),
# with any leading batch axes.
Skew = Float[Array, "*batch n n"]


def _log_series_factor(distance):
    """g(S) = Σ_k 2^k (k!)²/(2k+1)! Dᵏ with D = I − S, whose eigenvalues are
    1 − cos θ; 14 terms reach float64 round-off for ‖D‖ < 0.1 (ratio of
    successive terms ≤ ‖D‖/2)."""
    coefficients = [2**k * math.factorial(k) ** 2 / math.factorial(2 * k + 1) for k in range(14)]
    acc = coefficients[-1] * _eye_like(distance)
    for coefficient in reversed(coefficients[:-1]):
        acc = coefficient * _eye_like(distance) + distance @ acc
    return acc


def _dexp_inv_closed_form(u, v):
    complex_dtype = jnp.result_type(u.dtype, jnp.complex64)
    lam, vecs = jnp.linalg.eigh(1j * u.astype(complex_dtype))
    z = -1j * (lam[..., :, None] - lam[..., None, :])
    small = jnp.abs(z) < 1e-3
    safe = jnp.where(small, 1.0, z)
    # z/(eᶻ − 1) = 1 − z/2 + z²/12 − z⁴/720 + …
    factor = jnp.where(small, 1 - z / 2 + z**2 / 12, safe / jnp.expm1(safe))
    rotated = jnp.conj(_transpose(vecs)) @ v.astype(complex_dtype) @ vecs
    return jnp.real(vecs @ (factor * rotated) @ jnp.conj(_transpose(vecs))).astype(u.dtype)


def _transpose(m):
    return jnp.swapaxes(m, -1, -2)


def _commutator(u, v):
    return u @ v - v @ u


def _eye_like(m):
    return jnp.eye(m.shape[-1], dtype=m.dtype)


@jax.custom_jvp
def _log(r):
    """The principal logarithm's value (`SOn.log`)."""
    n = r.shape[-1]
    sym = 0.5 * (r + _transpose(r))
    skew = 0.5 * (r - _transpose(r))
    eye = _eye_like(r)
    distance = eye - sym
    near_identity = jnp.sum(distance**2, axis=(-2, -1)) < NEAR_IDENTITY**2
    c, w = jnp.linalg.eigh(sym)
    c = jnp.clip(c, -1.0, 1.0)
    one_minus = 1.0 - c
    small = one_minus < 1e-6
    safe = jnp.where(small, 0.5, c)
    # arccos(c)/sin(arccos c); near c = 1: 1 + (1 − c)/3 + 2(1 − c)²/15.
    # (Near c = −1 it grows without bound; the plane of such an angle is
    # handled below.)
    g = jnp.where(small, 1.0 + one_minus / 3 + 2 * one_minus**2 / 15, jnp.arccos(safe) / jnp.sqrt(jnp.maximum(1.0 - safe**2, 1e-300)))
    # The plane of the largest angle (eigenvalues 0 and 1, ascending).
    a, b = w[..., :, 0], w[..., :, 1]
    sin_ab = jnp.einsum("...i,...ij,...j->...", b, skew, a)
    sign = jnp.where(sin_ab >= 0, 1.0, -1.0).astype(r.dtype)
    cos_ab = 0.5 * (c[..., 0] + c[..., 1])
    theta = jnp.arctan2(jnp.abs(sin_ab), cos_ab)
    plane = (sign * theta)[..., None, None] * (b[..., :, None] * a[..., None, :] - a[..., :, None] * b[..., None, :])
    gap = c[..., 2] - c[..., 1] if n > 2 else jnp.ones_like(cos_ab)
    near_pi = (c[..., 0] < -0.9) & (gap > 1e-4)
    keep = jnp.where(near_pi[..., None] & (jnp.arange(n) < 2), 0.0, g)
    out = ((w * keep[..., None, :]) @ _transpose(w)) @ skew
    general = 0.5 * (out - _transpose(out)) + jnp.where(near_pi[..., None, None], plane, 0.0)
    series = _log_series_factor(distance) @ skew
    series = 0.5 * (series - _transpose(series))
    return jnp.where(near_identity[..., None, None], series, general)


@_log.defjvp
def _log_jvp(primals, tangents):
    """R = exp(u) gives dR Rᵀ = dexp_u(du) (right-trivialised), so
    du = dexp⁻¹_u(dR Rᵀ): finite wherever log is differentiable (angles < π),
    including the repeated eigenvalues of S that every rotation has."""
    (r,), (dr,) = primals, tangents
    u = _log(r)
    right = dr @ _transpose(r)
    return u, SOn.dexp_inv(u, 0.5 * (right - _transpose(right)))


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
    def exp(cls, u: Skew) -> Self:
        expm = jsl.expm
        for _ in range(u.ndim - 2):
            expm = jax.vmap(expm)
        return cls(expm(u))

    def log(self) -> Skew:
        """Principal logarithm (angles ≤ π) from the split R = S + A.

        S = (R + Rᵀ)/2 and A = (R − Rᵀ)/2 commute and, in each invariant plane
        of rotation angle θ, equal cos θ·I and sin θ·J, so log R = g(S)·A with
        g(c) = arccos(c)/√(1 − c²):

        * near the identity (‖I − S‖_F < 0.1) g(S) is its power series in
          I − S, without an eigendecomposition, so that gradients are finite
          at R = I;
        * elsewhere g comes from the eigendecomposition of S;
        * when the largest angle is near π (cos θ < −0.9) A ≈ 0 carries too
          little of J, and that plane's term θJ is built from the plane itself
          (the eigenvectors a, b of S: J = ±(baᵀ − abᵀ), the sign of bᵀAa,
          θ = atan2(|bᵀAa|, cos θ)). At θ = π exactly either sign is a
          logarithm. Two angles that are both near π and nearly equal make
          log ill-conditioned (at −I in SO(4) it is not unique); the general
          formula is used then.

        Its derivative is not that of these formulas (the eigendecomposition
        of S, whose eigenvalues come in equal pairs, has none) but
        d log R = dexp⁻¹_u(dR Rᵀ), u = log R, from R = exp(u).
        """
        return _log(self.matrix)

    def multiply(self, other: Self) -> Self:  # pyright: ignore[reportIncompatibleMethodOverride]  # pyright binds the base's Self in a parameter to the base class
        return type(self)(self.matrix @ other.matrix)

    def inverse(self) -> Self:
        return type(self)(_transpose(self.matrix))

    def identity_like(self) -> Self:
        return type(self)(jnp.broadcast_to(_eye_like(self.matrix), self.matrix.shape))

    def adjoint(self, u: Skew) -> Skew:
        return self.matrix @ u @ _transpose(self.matrix)

    def algebra_zeros(self) -> Skew:
        return jnp.zeros_like(self.matrix)

    def check(self) -> Self:
        return type(self)(checked_rotation(self.matrix, "SOn"))

    def project(self) -> Self:
        return type(self)(nearest_rotation(self.matrix))

    def renormalized(self) -> Self:
        return type(self)(bjorck_step(self.matrix))

    @classmethod
    def bracket(cls, u: Skew, v: Skew) -> Skew:
        return _commutator(u, v)

    @classmethod
    def dexp(cls, u: Skew, v: Skew) -> Skew:
        """From the Fréchet derivative L(u, v) of expm: dexp_u v = L(u, v) e^{−u}."""
        u, v = jnp.broadcast_arrays(u, v)
        frechet = jsl.expm_frechet
        for _ in range(u.ndim - 2):
            frechet = jax.vmap(frechet)
        expu, deriv = frechet(u, v)
        return deriv @ _transpose(expu)

    @classmethod
    def dexp_inv(cls, u: Skew, v: Skew) -> Skew:
        """dexp_u⁻¹ v = Σ B_k/k! ad_uᵏ v, exact for every u where dexp_u is
        invertible (no eigenvalue difference of u a nonzero multiple of 2πi).

        For ‖u‖_F ≤ `SERIES_RADIUS` the Bernoulli series with
        `EXACT_SERIES_TERMS` terms (round-off accurate there, and smooth to
        differentiate at u = 0). Beyond, where the series converges slowly or
        not at all, the closed form: iu = VΛV* is Hermitian, ad_u acts on
        Ṽ = V*vV entrywise as −i(λ_j − λ_k), and dexp⁻¹ multiplies each entry
        by z/(eᶻ − 1) at that z. (Its gradient needs distinct eigenvalues of
        iu, as any eigendecomposition's does.)"""
        u, v = jnp.broadcast_arrays(u, v)
        large = jnp.sum(u**2, axis=(-2, -1)) > SERIES_RADIUS**2
        series_u = jnp.where(large[..., None, None], 0.0, u)
        series = dexp_inv_series(cls.bracket, series_u, v, EXACT_SERIES_TERMS)
        # Double where: the closed form sees a harmless generator (distinct
        # eigenvalues) where the series is used.
        n = u.shape[-1]
        harmless = jnp.zeros((n, n), u.dtype).at[jnp.triu_indices(n, 1)].set(jnp.arange(1, n * (n - 1) // 2 + 1, dtype=u.dtype))
        harmless = harmless - harmless.T
        closed = _dexp_inv_closed_form(jnp.where(large[..., None, None], u, harmless), v)
        return jnp.where(large[..., None, None], closed, series)

    @classmethod
    def exp_adjoint(cls, u: Skew, x: Skew) -> Skew:
        return cls.exp(u).adjoint(x)

    @classmethod
    def inverse_shifted_ad(cls, u: Skew, v: Skew, alpha: float) -> Skew:
        """Dense solve on the flattened algebra (ad_u as an n²×n² matrix)."""
        if u.ndim > 2:
            return jax.vmap(lambda uu, vv: cls.inverse_shifted_ad(uu, vv, alpha))(u, v)
        ad = jax.jacfwd(lambda w: _commutator(u, w))(v).reshape(v.size, v.size)
        eye = jnp.eye(v.size, dtype=v.dtype)
        return jnp.linalg.solve(eye + alpha * ad, v.reshape(-1)).reshape(v.shape)

    @classmethod
    def cayley(cls, u: Skew) -> Self:
        eye = _eye_like(u)
        return cls(jnp.linalg.solve(eye - 0.5 * u, eye + 0.5 * u))

    def cayley_inverse(self) -> Skew:
        r = self.matrix
        eye = _eye_like(r)
        # (R + 1)⁻¹ and R − 1 commute; the solve keeps the result skew up to round-off.
        return 2.0 * jnp.linalg.solve(r + eye, r - eye)

    @classmethod
    def dcayley(cls, u: Skew, v: Skew) -> Skew:
        eye = _eye_like(u)
        left = jnp.linalg.solve(eye - 0.5 * u, v)
        # X (1 + u/2)⁻¹ = ((1 + u/2)⁻ᵀ Xᵀ)ᵀ
        return _transpose(jnp.linalg.solve(_transpose(eye + 0.5 * u), _transpose(left)))

    @classmethod
    def dcayley_inv(cls, u: Skew, v: Skew) -> Skew:
        return v - 0.5 * _commutator(u, v) - 0.25 * u @ v @ u

    @classmethod
    def cayley_adjoint(cls, u: Skew, x: Skew) -> Skew:
        return cls.cayley(u).adjoint(x)
