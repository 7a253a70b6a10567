"""SO(n) for general n; so(n) is stored as skew-symmetric (n, n) matrices."""

import math
from typing import ClassVar, Self

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float

from .._series import dexp_inv_series
from ._util import as_array, check_floating
from .base import CONVERGED_SERIES_TERMS
from .rotation import AbstractRotationGroup

SERIES_RADIUS = 1.75
"""‖u‖_F up to which `SOn.dexp_inv` sums the Bernoulli series
(`CONVERGED_SERIES_TERMS` powers, exact to round-off for ‖ad_u‖ ≲ 2.5, and
‖ad_u‖ ≤ 2‖u‖₂ ≤ √2‖u‖_F for skew u); beyond it the closed form
diagonalises ad_u."""


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


def _singular_dexp(lam, dtype):
    """Whether dexp_u is not invertible on so(n), from the eigenvalues λ of
    iu (±θⱼ, and 0 for odd n): an eigenvalue of ad_u on so(n), ±iθⱼ or
    ±i(θⱼ ± θₖ) for j ≠ k, is a nonzero multiple of 2πi, to within the
    rounding of the angles (then z/(eᶻ − 1) has no digit left)."""
    n = lam.shape[-1]
    thetas = jnp.abs(lam[..., n - n // 2 :])  # the ⌊n/2⌋ largest, one per plane
    alphas = [thetas[..., j] for j in range(n // 2)]
    for j in range(n // 2):
        for k in range(j + 1, n // 2):
            alphas += [thetas[..., j] + thetas[..., k], jnp.abs(thetas[..., j] - thetas[..., k])]
    eps = float(jnp.finfo(dtype).eps)
    singular = jnp.zeros(lam.shape[:-1], bool)
    for alpha in alphas:
        turns = jnp.round(alpha / (2 * math.pi))
        singular = singular | ((turns >= 1) & (jnp.abs(alpha - 2 * math.pi * turns) <= 64 * eps * jnp.maximum(alpha, 1.0)))
    return singular


def _dexp_inv_closed_form(u, v, check=None):
    """dexp⁻¹_u v through the eigendecomposition of iu (`SOn.dexp_inv`).
    Where `check` (a boolean per matrix; default everywhere) is set, a u at
    which dexp_u is not invertible raises (`eqx.error_if`)."""
    complex_dtype = jnp.result_type(u.dtype, jnp.complex64)
    lam, vecs = jnp.linalg.eigh(1j * u.astype(complex_dtype))
    singular = _singular_dexp(lam, u.dtype)
    if check is not None:
        singular = singular & check
    vecs = eqx.error_if(
        vecs,
        singular,
        "SOn.dexp_inv: dexp_u is not invertible at this u: an eigenvalue of ad_u (±iθⱼ or ±i(θⱼ ± θₖ) for its rotation "
        "angles θ) is a nonzero multiple of 2πi. As an increment, u is too large a step.",
    )
    z = -1j * (lam[..., :, None] - lam[..., None, :])
    small = jnp.abs(z) < 1e-3
    safe = jnp.where(small, 1.0, z)
    denominator = jnp.expm1(safe)
    # At z = 2πik the entry belongs to a pair of conjugate eigenvectors
    # (λⱼ = −λₖ = iθ, θ = π), whose direction wⱼwⱼᵀ is symmetric: a skew v
    # has no component there, only rounding. Zero it instead of dividing by 0.
    vanishing = jnp.abs(denominator) == 0
    # z/(eᶻ − 1) = 1 − z/2 + z²/12 − z⁴/720 + …
    factor = jnp.where(small, 1 - z / 2 + z**2 / 12, jnp.where(vanishing, 0.0, safe / jnp.where(vanishing, 1.0, denominator)))
    rotated = jnp.conj(_transpose(vecs)) @ v.astype(complex_dtype) @ vecs
    out = jnp.real(vecs @ (factor * rotated) @ jnp.conj(_transpose(vecs))).astype(u.dtype)
    # The rounding of those symmetric directions, multiplied by the large
    # z/(eᶻ − 1) near z = 2πi (an angle near π), lands in the symmetric part:
    # the skew part is the result.
    return 0.5 * (out - _transpose(out))


_CHANGE_SERIES_TERMS = 18
"""Powers of u in `SOn.exp_change`'s series: for ‖u‖ < 1 the rest is below
1/19! < eps(float64)/20 of the change."""


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
    dtype = r.dtype
    eps = float(jnp.finfo(dtype).eps)
    sym = 0.5 * (r + _transpose(r))
    skew = 0.5 * (r - _transpose(r))
    distance = _eye_like(r) - sym
    near_identity = jnp.sum(distance**2, axis=(-2, -1)) < NEAR_IDENTITY**2
    # S = W diag(c) Wᵀ; in that basis A is block diagonal (a block per
    # eigenvalue of S, sin θ·J on each plane of angle θ).
    c, w = jnp.linalg.eigh(sym)
    c = jnp.clip(c, -1.0, 1.0)
    rotated = _transpose(w) @ skew @ w
    sine = jnp.sqrt(jnp.sum(rotated**2, axis=-2))
    # Near π, cos θ = −1 + δ²/2 separates planes by δ² only, and S's
    # eigenvectors mix planes whose δ differ by eps/Δc: in clusters of such
    # eigenvalues the planes come from A instead, the eigenvectors of −A²
    # (eigenvalues sin²θ, apart to first order in δ) restricted to the
    # cluster. Taking two eigenvalues Δc apart as one moves the angle
    # atan2(s, c) by about Δc·s; neighbours join where that is below the
    # eps/Δc the eigenvectors of S would cost, Δc²·s < eps. A shift by 4 per
    # cluster keeps the clusters' spectra apart.
    near_pi = c < -0.5
    difference = c[..., 1:] - c[..., :-1]
    join = near_pi[..., 1:] & near_pi[..., :-1] & (difference**2 * jnp.maximum(sine[..., 1:], sine[..., :-1]) < eps)
    label = jnp.concatenate([jnp.zeros_like(c[..., :1]), jnp.cumsum(jnp.where(join, 0.0, 1.0), axis=-1)], axis=-1)
    same = label[..., :, None] == label[..., None, :]
    size = jnp.sum(same, axis=-1)
    refined = near_pi & (size >= 4)  # two planes or more; a single plane is handled below
    in_cluster = same & refined[..., :, None] & refined[..., None, :]
    masked = jnp.where(in_cluster, rotated, 0.0)
    shifted = -(masked @ masked) + 4.0 * jnp.eye(n, dtype=dtype) * label[..., None, :]
    _, x = jnp.linalg.eigh(shifted)
    w = w @ x
    rotated = _transpose(x) @ rotated @ x
    c = jnp.clip(jnp.einsum("...ki,...k,...ki->...i", x, c, x), -1.0, 1.0)
    refined = jnp.einsum("...ki,...k->...i", x**2, refined.astype(dtype)) > 0.5
    label = jnp.einsum("...ki,...k->...i", x**2, label)
    in_cluster = jnp.abs(label[..., :, None] - label[..., None, :]) < 0.5
    # General formula: θ_k J = (θ_k / sin θ_k) A on each eigenvector w_k, with
    # sin θ_k = |A w_k| (accurate to round-off in absolute terms, unlike
    # √(1 − c²) near c = −1) and θ_k = atan2(sin θ_k, c_k). Entries between a
    # refined cluster and the rest are rounding (A keeps the cluster's space)
    # and are dropped.
    sine = jnp.sqrt(jnp.sum(rotated**2, axis=-2))
    positive = sine > 0
    ratio = jnp.where(positive, jnp.arctan2(sine, c) / jnp.where(positive, sine, 1.0), 1.0)
    general = 0.5 * (ratio[..., :, None] * rotated + rotated * ratio[..., None, :])
    crossing = (refined[..., :, None] | refined[..., None, :]) & ~in_cluster
    log_rotated = jnp.where(crossing, 0.0, general)
    # A single plane near π: there A ≈ 0 carries J with a relative error
    # eps/sin θ, and the plane itself (eigenvectors 2p, 2p+1 of S, whose
    # eigenvalues come in equal pairs, ascending) gives θJ to eps/gap instead:
    # J = ±(b aᵀ − a bᵀ), the sign of bᵀAa, θ = atan2(|bᵀAa|, c).
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
        use_plane = (cos_ab < 0) & ((gap > jnp.abs(sin_ab)) | distinct) & ~refined[..., i] & ~refined[..., j]
        sign = jnp.where(sin_ab >= 0, 1.0, -1.0).astype(dtype)
        in_plane = (jnp.arange(n) == i) | (jnp.arange(n) == j)
        touches = in_plane[:, None] | in_plane[None, :]
        block = jnp.zeros((n, n), dtype).at[j, i].set(1.0).at[i, j].set(-1.0)
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


class SOn(AbstractRotationGroup):
    """A rotation in SO(n); n is read off the matrix shape."""

    matrix: Float[Array, "*batch n n"] = eqx.field(converter=as_array)
    """Orthogonal matrix with det = 1."""

    algebra_ndim: ClassVar[int] = 2  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

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

    @classmethod
    def exp_change(cls, u: Skew) -> Skew:
        """exp(u) − I, the identity kept out: for ‖u‖_F < 1 the series
        u(I + u/2(I + u/3(…))) to the term u^`_CHANGE_SERIES_TERMS` (its
        remainder below eps relative to the change), beyond it expm(u) − I,
        which then cancels little. Double where: each branch sees an argument
        it handles."""
        small = jnp.sum(u**2, axis=(-2, -1)) < 1.0
        series_u = jnp.where(small[..., None, None], u, 0.0)
        eye = _eye_like(u)
        acc = eye
        for k in range(_CHANGE_SERIES_TERMS, 1, -1):
            acc = eye + (series_u @ acc) / k
        series = series_u @ acc
        closed = cls.exp(jnp.where(small[..., None, None], 0.0, u)).matrix - eye
        return jnp.where(small[..., None, None], series, closed)

    def log(self) -> Skew:
        """Principal logarithm (angles ≤ π) from the split R = S + A.

        S = (R + Rᵀ)/2 and A = (R − Rᵀ)/2 commute and, in each invariant plane
        of rotation angle θ, equal cos θ·I and sin θ·J, so log R = θJ there:

        * near the identity (‖I − S‖_F < 0.1) log R = g(S)·A with
          g(c) = arccos(c)/√(1 − c²) as a power series in I − S, without an
          eigendecomposition, so that gradients are finite at R = I;
        * elsewhere, in the eigenbasis of S: on each eigenvector w,
          θ = atan2(|Aw|, c) and θJ = (θ/|Aw|)·A;
        * on a single plane whose angle is near π (c < 0), where A ≈ 0
          carries J with a relative error eps/sin θ, and whose pair of
          eigenvalues stands apart from the others, θJ is built from the
          plane itself (its eigenvectors a, b: J = ±(baᵀ − abᵀ), the sign of
          bᵀAa, θ = atan2(|bᵀAa|, c)), accurate to eps/gap. At θ = π exactly
          either sign is a logarithm;
        * two or more planes near π whose cosines (−1 + δ²/2) are too close
          for S's eigenvectors to tell them apart are separated by the
          eigenvectors of −A² (eigenvalues sin²θ ≈ δ²) within their cluster.

        Its error is of the order of eps times the condition number of log
        at R: the norm of dexp⁻¹ at log R, which grows like
        1/(2π − θᵢ − θⱼ) as two angles approach π together (at −I in SO(4)
        log is not unique). `tests/test_son_accuracy.py` checks this against
        SciPy's `logm` for one or two angles within 1e-9 … 1e-2 of π.

        Its derivative is not that of these formulas (the eigendecomposition
        of S, whose eigenvalues come in equal pairs, has none) but
        d log R = dexp⁻¹_u(dR Rᵀ), u = log R, from R = exp(u).
        """
        return _log(self.matrix)

    def adjoint(self, u: Skew) -> Skew:
        return self.matrix @ u @ _transpose(self.matrix)

    def algebra_zeros(self) -> Skew:
        return jnp.zeros_like(self.matrix)

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
        `CONVERGED_SERIES_TERMS` terms (round-off accurate there, and smooth to
        differentiate at u = 0). Beyond, where the series converges slowly or
        not at all, the closed form: iu = VΛV* is Hermitian, ad_u acts on
        Ṽ = V*vV entrywise as −i(λ_j − λ_k), and dexp⁻¹ multiplies each entry
        by z/(eᶻ − 1) at that z; the result's skew part is kept, which drops
        the rounding that entries of Ṽ outside so(n) (pairs of conjugate
        eigenvectors, z = 2iθ, large as θ → π) would add. Accurate to eps
        times the condition number (the largest |z/(eᶻ − 1)| over ad_u's
        eigenvalues on so(n), ±i(θⱼ ± θₖ), ±iθⱼ) up to angles of π. Where one
        of those eigenvalues is a nonzero multiple of 2πi, dexp_u is not
        invertible and it raises (`eqx.error_if`). (Its gradient needs
        distinct eigenvalues of iu, as any eigendecomposition's does.)"""
        u, v = jnp.broadcast_arrays(u, v)
        large = jnp.sum(u**2, axis=(-2, -1)) > SERIES_RADIUS**2
        series_u = jnp.where(large[..., None, None], 0.0, u)
        series = dexp_inv_series(cls.bracket, series_u, v, CONVERGED_SERIES_TERMS)
        # Double where: the closed form sees a harmless generator (distinct
        # eigenvalues) where the series is used.
        n = u.shape[-1]
        harmless = jnp.zeros((n, n), u.dtype).at[jnp.triu_indices(n, 1)].set(jnp.arange(1, n * (n - 1) // 2 + 1, dtype=u.dtype))
        harmless = harmless - harmless.T
        closed = _dexp_inv_closed_form(jnp.where(large[..., None, None], u, harmless), v, check=large)
        return jnp.where(large[..., None, None], closed, series)

    @classmethod
    def exp_adjoint_change(cls, u: Skew, x: Skew) -> Skew:
        """g x gᵀ − x = E x + x Eᵀ + E x Eᵀ with E = g − I (`exp_change`)."""
        return _adjoint_change(cls.exp_change(u), x)

    @classmethod
    def cayley(cls, u: Skew) -> Self:
        eye = _eye_like(u)
        return cls(jnp.linalg.solve(eye - 0.5 * u, eye + 0.5 * u))

    @classmethod
    def cayley_change(cls, u: Skew) -> Skew:
        """cay(u) − I = (I − u/2)⁻¹ u, the identity kept out."""
        return jnp.linalg.solve(_eye_like(u) - 0.5 * u, u)

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
    def cayley_adjoint_change(cls, u: Skew, x: Skew) -> Skew:
        """g x gᵀ − x for g = cay(u) (see `exp_adjoint_change`)."""
        return _adjoint_change(cls.cayley_change(u), x)


def _adjoint_change(change: Array, x: Array) -> Array:
    """g x gᵀ − x for the rotation g = I + `change`, x kept out."""
    moved = change @ x
    return moved + x @ _transpose(change) + moved @ _transpose(change)
