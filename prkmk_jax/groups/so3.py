"""SO(3) with closed forms; so(3) is stored as 3-vectors (hat map u ↦ û)."""

import math
from typing import ClassVar, Self

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._util import as_array, check_floating, is_low_precision, taylor_or_exact
from .rotation import AbstractRotationGroup
from .trig import computed_once

# Below this θ² the Taylor branches are used; the exact forms that cancel
# (θ − sin θ)/θ³ and the dexp⁻¹ coefficient lose ~eps/θ² relative accuracy.
_SMALL = 1e-2
# In low precision the rotation coefficients' series runs further, up to θ² = 1.
_SMALL_LOW_PRECISION = 1.0

# so(3) ≅ ℝ³ (u ↦ û) and its dual, with any leading batch axes.
Vector3 = Float[Array, "*batch 3"]


def hat(u: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The skew matrix û with û v = u × v."""
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def vee(m: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Inverse of `hat` (reads the skew part of `m`)."""
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


def _theta_sq(u):
    return jnp.sum(u * u, axis=-1)


def _dot(u, v):
    return jnp.sum(u * v, axis=-1)


def _dot_fused(u, v):
    """u·v as `_dot`, written as the sum of its three products, which XLA
    fuses with the arithmetic around it, where `_dot`'s reduction over the
    length-3 axis is a kernel of its own on the CPU. dcay⁻¹ uses it: it is
    evaluated at every stage, and with the reduction a batched RKMK step
    with Cayley coordinates on T*SO(3) ran at a fraction of this speed
    (measured against it; the step's time: `benchmarks/throughput.py`, the
    stage layouts). Elsewhere the reduction stays: written out, θ² and what
    is computed from it (the exponential's sines, the Cayley factor) are
    evaluated again in every kernel that reads them, and the steps
    measured slower."""
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def _cross_twice(u, v):
    """û² v = u × (u × v) = (u·v) u − θ² v."""
    return _dot(u, v)[..., None] * u - _theta_sq(u)[..., None] * v


@jax.custom_jvp
def _rotation_terms(u, x):
    """(u × x, u × (u × x)) by two cross products.

    The actions exp(û)x and dexp_u v use this form, not (u·x)u − θ²x: a dot
    product is a reduction over the length-3 axis, which XLA's CPU backend
    runs as separate kernels at large batches, and the step on T*SO(3) is
    markedly faster this way. dexp⁻¹
    keeps the dot form: there two cross products measured slower.

    The derivative is that of the dot form (`_cross_twice`): the transpose
    of a cross product is a handful of slices and pads, and a gradient with
    cross products in the derivative as well measured slower.
    """
    ux = jnp.cross(u, x)
    return ux, jnp.cross(u, ux)


@_rotation_terms.defjvp
def _rotation_terms_jvp(primals, tangents):
    # The tangent of the same pair written with the dot form, `_cross_twice`.
    _, tangent_out = jax.jvp(lambda u, x: (jnp.cross(u, x), _cross_twice(u, x)), primals, tangents)
    return _rotation_terms(*primals), tangent_out


def _eye_plus(alpha, beta, gamma, u):
    """αI + β û + γ uuᵀ, entrywise."""
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    rows = [
        [alpha + gamma * x * x, gamma * x * y - beta * z, gamma * x * z + beta * y],
        [gamma * y * x + beta * z, alpha + gamma * y * y, gamma * y * z - beta * x],
        [gamma * z * x - beta * y, gamma * z * y + beta * x, alpha + gamma * z * z],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def _rodrigues_terms(u, x):
    """((sin θ/θ) u×x, ((1 − cos θ)/θ²) u×(u×x)): exp(û) x − x as two terms,
    added to x in that order by `SO3.exp_adjoint`."""
    a, b = _rotation_coefficients(_theta_sq(u))
    ux, uux = _rotation_terms(u, x)
    return a[..., None] * ux, b[..., None] * uux


@jax.custom_jvp
def _rotation_coefficients(t2):
    """(sin θ/θ, (1 − cos θ)/θ²) of θ² = t2 (`_rotation_coefficients_of`).

    Differentiated, the coefficients and their derivatives in t2 are
    computed together behind one optimisation barrier (`computed_once`).
    Without it XLA fuses the sines, and the cosines of their derivatives,
    into every kernel of a step's VJP that reads them, and evaluates them
    again for each component of the vectors there."""
    return _rotation_coefficients_of(t2)


@_rotation_coefficients.defjvp
def _rotation_coefficients_jvp(primals, tangents):
    (t2,), (t2_dot,) = primals, tangents
    (a, b), (da, db) = jax.jvp(_rotation_coefficients_of, (t2,), (jnp.ones_like(t2),))
    (a, b), (da, db) = computed_once(jnp.stack([a, b]), jnp.stack([da, db]))
    return (a, b), (da * t2_dot, db * t2_dot)


def _rotation_coefficients_of(t2):
    """(sin θ/θ, (1 − cos θ)/θ²), the second as ½(sin(θ/2)/(θ/2))², which
    does not cancel. Taylor branches below `_SMALL` (in low precision
    `_SMALL_LOW_PRECISION`; double where).

    Two sines rather than one sine and cosine of θ/2: XLA's CPU fusion
    recomputes a cosine in every fusion that consumes it (it treats it as
    cheap) but materialises a sine once; with the cosine, a Lobatto 4 step
    on T*SO(3) ran markedly slower. Both share one
    square root and one double `where` here instead of two `taylor_or_exact`
    calls, which written separately also measured slower.
    """
    # In low precision the series runs up to θ = 1 (eight terms): the
    # sines' rounding, divided by θ, keeps its sign over long stretches of
    # a motion and a long float32 run's |Π| drifted with it; the series'
    # rounding changes sign far more often (`round_off.py`'s float32 rows).
    low = is_low_precision(t2.dtype)
    below, terms = (_SMALL_LOW_PRECISION, 8) if low else (_SMALL, 5)
    small = t2 < below
    theta = jnp.sqrt(jnp.where(small, below, t2))
    half = 0.5 * theta
    sinc_half = jnp.sin(half) / half
    a_exact = jnp.sin(theta) / theta
    b_exact = 0.5 * sinc_half * sinc_half
    a_taylor = _poly(t2, [(-1) ** k / math.factorial(2 * k + 1) for k in range(terms)])
    b_taylor = _poly(t2, [(-1) ** k / math.factorial(2 * k + 2) for k in range(terms)])
    return jnp.where(small, a_taylor, a_exact), jnp.where(small, b_taylor, b_exact)


def _poly(x, coefficients):
    acc = jnp.zeros_like(x)
    for c in reversed(coefficients):
        acc = acc * x + c
    return acc


class SO3(AbstractRotationGroup):
    """A rotation in SO(3)."""

    matrix: Float[Array, "*batch 3 3"] = eqx.field(converter=as_array)
    """Rotation matrix R with RᵀR = I, det R = 1."""

    algebra_ndim: ClassVar[int] = 1  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        check_floating(self.matrix, "an SO3 matrix")
        if self.matrix.shape[-2:] != (3, 3):
            raise ValueError(f"SO3 needs a (..., 3, 3) matrix, got shape {self.matrix.shape}.")

    # --- group -----------------------------------------------------------------
    @classmethod
    def exp(cls, u: Vector3) -> Self:
        """Rodrigues' formula R = I + (sin θ/θ) û + ((1 − cos θ)/θ²) û²."""
        t2 = _theta_sq(u)
        a, b = _rotation_coefficients(t2)
        # û² = uuᵀ − θ² I
        return cls(_eye_plus(1.0 - b * t2, a, b, u))

    @classmethod
    def exp_change(cls, u: Vector3) -> Float[Array, "*batch 3 3"]:
        """exp(û) − I = (sin θ/θ) û + ((1 − cos θ)/θ²) û², the identity kept out."""
        t2 = _theta_sq(u)
        a, b = _rotation_coefficients(t2)
        return _eye_plus(-b * t2, a, b, u)

    def log(self) -> Vector3:
        """Rotation vector with angle in [0, π], through the unit quaternion
        (Shepperd's branch choice, robust near θ = π)."""
        r = self.matrix
        r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
        trace = r00 + r11 + r22
        # 4q_k² for the four candidate pivots; they sum to 4, so the largest is ≥ 1.
        pivots = jnp.stack([1 + trace, 1 + 2 * r00 - trace, 1 + 2 * r11 - trace, 1 + 2 * r22 - trace], axis=-1)
        best = jnp.argmax(pivots, axis=-1)
        d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
        s01, s02, s12 = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
        candidates = []
        for k, (num_w, num_x, num_y, num_z) in enumerate(
            [
                (None, d21, d02, d10),
                (d21, None, s01, s02),
                (d02, s01, None, s12),
                (d10, s02, s12, None),
            ]
        ):
            # Double where: the unselected pivots may be ≤ 0.
            p = jnp.where(best == k, pivots[..., k], 1.0)
            half = 0.5 * jnp.sqrt(p)
            denom = 4 * half
            comps = [half if n is None else n / denom for n in (num_w, num_x, num_y, num_z)]
            candidates.append(jnp.stack(comps, axis=-1))
        q = candidates[0]
        for k in range(1, 4):
            q = jnp.where((best == k)[..., None], candidates[k], q)
        q = jnp.where(q[..., :1] < 0, -q, q)  # w ≥ 0 → angle ≤ π
        w, v = q[..., 0], q[..., 1:]
        n2 = jnp.sum(v * v, axis=-1)
        # θ/|v| with θ = 2 atan2(|v|, w); Taylor in |v|² about 0 for w ≈ 1.
        small = n2 < 1e-10
        n_safe = jnp.sqrt(jnp.where(small, 1.0, n2))
        w_safe = jnp.where(small, w, 1.0)
        factor = jnp.where(
            small,
            2.0 / w_safe - (2.0 / 3.0) * n2 / w_safe**3,
            2.0 * jnp.arctan2(n_safe, w) / n_safe,
        )
        return factor[..., None] * v

    def adjoint(self, u: Vector3) -> Vector3:
        """Ad_R u = R u."""
        return jnp.einsum("...ij,...j->...i", self.matrix, u)

    def algebra_zeros(self) -> Vector3:
        return jnp.zeros(self.matrix.shape[:-1], self.matrix.dtype)

    # --- algebra ---------------------------------------------------------------
    @classmethod
    def bracket(cls, u: Vector3, v: Vector3) -> Vector3:
        """[û, v̂] = (u × v)^."""
        return jnp.cross(u, v)

    @classmethod
    def dexp(cls, u: Vector3, v: Vector3) -> Vector3:
        """dexp_u v = v + ((1 − cos θ)/θ²) u×v + ((θ − sin θ)/θ³) u×(u×v)."""
        t2 = _theta_sq(u)
        a, b = _rotation_coefficients(t2)
        # (θ − sin θ)/θ³ = (1 − a)/θ², Taylor below _SMALL where it cancels.
        small = t2 < _SMALL
        c = jnp.where(small, _poly(t2, [1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800]), (1.0 - a) / jnp.where(small, 1.0, t2))
        uv, uuv = _rotation_terms(u, v)
        return v + b[..., None] * uv + c[..., None] * uuv

    @classmethod
    def dexp_inv(cls, u: Vector3, v: Vector3) -> Vector3:
        """dexp_u⁻¹ v = v − ½ u×v + ((1 − (θ/2)cot(θ/2))/θ²) u×(u×v), |θ| < 2π."""
        t2 = _theta_sq(u)

        def exact(s):
            th = jnp.sqrt(s)
            return (1.0 - 0.5 * th / jnp.tan(0.5 * th)) / s

        c = taylor_or_exact(t2, [1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160], exact, _SMALL)
        return v - 0.5 * jnp.cross(u, v) + c[..., None] * _cross_twice(u, v)

    @classmethod
    def exp_adjoint(cls, u: Vector3, x: Vector3) -> Vector3:
        """exp(û) x = x + (sin θ/θ) u×x + ((1 − cos θ)/θ²) u×(u×x) (Rodrigues).

        The change is summed before it is added to x: added one term at a
        time, x is rounded twice at its own scale, and for a slow turn the
        second term, a few ulps of x, is rounded much the same way step
        after step (in float32 a momentum's norm then drifted in proportion
        to the steps)."""
        return x + cls.exp_adjoint_change(u, x)

    @classmethod
    def exp_adjoint_change(cls, u: Vector3, x: Vector3) -> Vector3:
        """exp(û) x − x = (sin θ/θ) u×x + ((1 − cos θ)/θ²) u×(u×x)."""
        first, second = _rodrigues_terms(u, x)
        return first + second

    @classmethod
    def inverse_shifted_ad(cls, u: Vector3, v: Vector3, alpha: float) -> Vector3:
        """(I + αû)⁻¹ v = (v − α u×v + α²(u·v) u)/(1 + α²θ²)."""
        alpha2 = alpha * alpha
        return (v - alpha * jnp.cross(u, v) + alpha2 * _dot(u, v)[..., None] * u) / (1.0 + alpha2 * _theta_sq(u))[..., None]

    @classmethod
    def cayley(cls, u: Vector3) -> Self:
        """cay(u) = I + 4/(4 + θ²) (û + û²/2)."""
        t2 = _theta_sq(u)
        k = 4.0 / (4.0 + t2)
        # û + û²/2 = û + (uuᵀ − θ² I)/2
        return cls(_eye_plus(1.0 - 0.5 * k * t2, k, 0.5 * k, u))

    @classmethod
    def cayley_change(cls, u: Vector3) -> Float[Array, "*batch 3 3"]:
        """cay(û) − I = 4/(4 + θ²) (û + û²/2), the identity kept out."""
        t2 = _theta_sq(u)
        k = 4.0 / (4.0 + t2)
        return _eye_plus(-0.5 * k * t2, k, 0.5 * k, u)

    def cayley_inverse(self) -> Vector3:
        """cay⁻¹(R) = 2 vee(R − Rᵀ)/(1 + tr R): for R = cay(u), R − Rᵀ = 2kû and
        1 + tr R = 4k with k = 4/(4 + θ²)."""
        r = self.matrix
        trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
        return 2.0 * vee(r - jnp.swapaxes(r, -1, -2)) / (1.0 + trace)[..., None]

    @classmethod
    def dcayley(cls, u: Vector3, v: Vector3) -> Vector3:
        """dcay_u v = 4/(4 + θ²) (v + ½ u×v)."""
        k = 4.0 / (4.0 + _theta_sq(u))
        return k[..., None] * (v + 0.5 * jnp.cross(u, v))

    @classmethod
    def dcayley_inv(cls, u: Vector3, v: Vector3) -> Vector3:
        """dcay_u⁻¹ v = v − ½ u×v + ¼ (u·v) u  (since ûv̂û = −(u·v)û)."""
        return v - 0.5 * jnp.cross(u, v) + 0.25 * _dot_fused(u, v)[..., None] * u

    @classmethod
    def cayley_adjoint(cls, u: Vector3, x: Vector3) -> Vector3:
        """cay(û) x = x + 4/(4 + θ²) (u×x + ½ u×(u×x)), by two cross
        products (`_rotation_terms`). Not by (u·x)u − θ²x: along a free
        rigid body's motion u·x is the same every step (u = hΩ, x = Π:
        2hH), so its rounding is too, and |x| drifted by it steadily
        (`benchmarks/round_off.py`)."""
        return x + cls.cayley_adjoint_change(u, x)

    @classmethod
    def shifted_cayley_adjoint_inverse(cls, u: Vector3, x: Vector3) -> Vector3:
        """(I + ½û) cay(−û) x = x − ½ u×x: on so(3) Ad_{cay(−u)} is the
        matrix cay(−û) = (I + ½û)⁻¹(I − ½û), and the factors commute (one
        cross product where the default takes three and a division)."""
        return x - 0.5 * jnp.cross(u, x)

    @classmethod
    def cayley_adjoint_change(cls, u: Vector3, x: Vector3) -> Vector3:
        """cay(û) x − x = 4/(4 + θ²) (u×x + ½ u×(u×x))."""
        k = 4.0 / (4.0 + _theta_sq(u))
        ux, uux = _rotation_terms(u, x)
        return k[..., None] * (ux + 0.5 * uux)
