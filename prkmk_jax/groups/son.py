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
    denominator = jnp.expm1(safe)
    # At z = 2πik the entry belongs to a pair of conjugate eigenvectors
    # (λⱼ = −λₖ = iθ, θ = π), whose direction wⱼwⱼᵀ is symmetric: a skew v
    # has no component there, only rounding. Zero it instead of dividing by 0.
    singular = jnp.abs(denominator) == 0
    # z/(eᶻ − 1) = 1 − z/2 + z²/12 − z⁴/720 + …
    factor = jnp.where(small, 1 - z / 2 + z**2 / 12, jnp.where(singular, 0.0, safe / jnp.where(singular, 1.0, denominator)))
    rotated = jnp.conj(_transpose(vecs)) @ v.astype(complex_dtype) @ vecs
    out = jnp.real(vecs @ (factor * rotated) @ jnp.conj(_transpose(vecs))).astype(u.dtype)
    # The rounding of those symmetric directions, multiplied by the large
    # z/(eᶻ − 1) near z = 2πi (an angle near π), lands in the symmetric part:
    # the skew part is the result.
    return 0.5 * (out - _transpose(out))


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
    distance = _eye_like(r) - sym
    near_identity = jnp.sum(distance**2, axis=(-2, -1)) < NEAR_IDENTITY**2
    # S = W diag(c) Wᵀ; in that basis A is block diagonal (a block per
    # eigenvalue cluster of S, sin θ·J on a plane of angle θ).
    c, w = jnp.linalg.eigh(sym)
    c = jnp.clip(c, -1.0, 1.0)
    rotated = _transpose(w) @ skew @ w
    # General formula: θ_k J = (θ_k / sin θ_k) A on each eigenvector w_k, with
    # sin θ_k = |A w_k| (accurate to round-off in absolute terms, unlike
    # √(1 − c²) near c = −1) and θ_k = atan2(sin θ_k, c_k).
    sine = jnp.sqrt(jnp.sum(rotated**2, axis=-2))
    positive = sine > 0
    ratio = jnp.where(positive, jnp.arctan2(sine, c) / jnp.where(positive, sine, 1.0), 1.0)
    general = 0.5 * (ratio[..., :, None] * rotated + rotated * ratio[..., None, :])
    # Planes near π: there A ≈ 0 carries J with a relative error eps/sin θ, and
    # the plane itself (eigenvectors 2p, 2p+1 of S, whose eigenvalues come in
    # equal pairs, ascending) gives θJ to eps/gap instead: J = ±(b aᵀ − a bᵀ),
    # the sign of bᵀAa, θ = atan2(|bᵀAa|, c). Taken where the pair stands
    # apart from its neighbours by more than sin θ.
    log_rotated = general
    pair_sine = [jnp.abs(rotated[..., 2 * p + 1, 2 * p]) for p in range(n // 2)]
    for p in range(n // 2):
        i, j = 2 * p, 2 * p + 1
        sin_ab = rotated[..., j, i]
        cos_ab = 0.5 * (c[..., i] + c[..., j])
        gap = jnp.full_like(cos_ab, jnp.inf)
        if i > 0:
            gap = jnp.minimum(gap, c[..., i] - c[..., i - 1])
        if j + 1 < n:
            gap = jnp.minimum(gap, c[..., j + 1] - c[..., j])
        theta = jnp.arctan2(jnp.abs(sin_ab), cos_ab)
        # The plane's error is eps/gap. The general formula's is eps/sin θ
        # within a cluster of equal angles, but eps/gap times the ratio of
        # the sines where the next plane's angle differs: take the plane
        # where it stands apart (gap > sin θ) or its neighbours' sines differ
        # from its own by more than a quarter.
        neighbours = [pair_sine[k] for k in (p - 1, p + 1) if 0 <= k < n // 2]
        distinct = jnp.ones_like(cos_ab, dtype=bool)
        for other in neighbours:
            distinct = distinct & (jnp.abs(other - jnp.abs(sin_ab)) > 0.25 * jnp.maximum(other, jnp.abs(sin_ab)))
        use_plane = (cos_ab < 0) & ((gap > jnp.abs(sin_ab)) | distinct)
        sign = jnp.where(sin_ab >= 0, 1.0, -1.0).astype(r.dtype)
        in_plane = (jnp.arange(n) == i) | (jnp.arange(n) == j)
        touches = in_plane[:, None] | in_plane[None, :]
        block = jnp.zeros((n, n), r.dtype).at[j, i].set(1.0).at[i, j].set(-1.0)
        plane = (sign * theta)[..., None, None] * block
        log_rotated = jnp.where(use_plane[..., None, None] & touches, plane, log_rotated)
    log_rotated = 0.5 * (log_rotated - _transpose(log_rotated))
    general = w @ log_rotated @ _transpose(w)
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
        of rotation angle θ, equal cos θ·I and sin θ·J, so log R = θJ there:

        * near the identity (‖I − S‖_F < 0.1) log R = g(S)·A with
          g(c) = arccos(c)/√(1 − c²) as a power series in I − S, without an
          eigendecomposition, so that gradients are finite at R = I;
        * elsewhere, in the eigenbasis of S: on each eigenvector w,
          θ = atan2(|Aw|, c) and θJ = (θ/|Aw|)·A;
        * on a plane whose angle is near π (c < 0), where A ≈ 0 carries J
          with a relative error eps/sin θ, and whose pair of eigenvalues
          stands apart from the others by more than sin θ, θJ is built from
          the plane itself (its eigenvectors a, b: J = ±(baᵀ − abᵀ), the sign
          of bᵀAa, θ = atan2(|bᵀAa|, c)), accurate to eps/gap. At θ = π
          exactly either sign is a logarithm.

        Its error is of the order of eps times the condition number of log
        at R (the norm of dexp⁻¹ at log R, which grows like 1/(2π − θᵢ − θⱼ)
        as two angles approach π together; at −I in SO(4) log is not unique),
        except for two *distinct* angles π − δᵢ, π − δⱼ both so close to π
        that their cosines (−1 + δ²/2) are closer than the eigensolver of S
        resolves: the error is then about eps/|δᵢ² − δⱼ²|.

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
        by z/(eᶻ − 1) at that z; the result's skew part is kept, which drops
        the rounding that entries of Ṽ outside so(n) (pairs of conjugate
        eigenvectors, z = 2iθ, large as θ → π) would add. Accurate to eps
        times the condition number (the largest |z/(eᶻ − 1)| over ad_u's
        eigenvalues on so(n), ±i(θⱼ ± θₖ), ±iθⱼ) up to angles of π. (Its
        gradient needs distinct eigenvalues of iu, as any
        eigendecomposition's does.)"""
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
