"""Unit quaternions S³ = SU(2): attitude in four numbers, the double cover of
SO(3) with the same Lie algebra so(3) ≅ ℝ³.

An element holds q = (w, x, y, z), scalar first, |q| = 1; it acts on ℝ³ as
the rotation v ↦ q v q̄, and q and −q are the same attitude. The algebra and
its conventions are `SO3`'s: u ∈ ℝ³ is the rotation vector, exp(u) =
(cos(θ/2), sin(θ/2) u/θ) turns by θ = |u| about u, and every algebra map
(bracket, dexp⁻¹, dcay⁻¹, the action Ad_{exp(u)} on the algebra) is SO(3)'s,
so a method run on quaternions computes the same attitudes as on rotation
matrices, with a quaternion's product and rounding.

The Cayley map is SO(3)'s lifted: cay(u) = (2, u)/√(4 + θ²), whose rotation
matrix is (I − û/2)⁻¹(I + û/2), a turn by φ with tan(φ/2) = |u|/2. (The
quaternion algebra's own Cayley transform (1 − ũ/2)⁻¹(1 + ũ/2) of the pure
quaternion ũ = (0, u/2) is another map, a turn with tan(φ/4) = |u|/4; SO(3)'s
is the one whose inverse differential `dcayley_inv` the methods use.)

A run's quaternion moves continuously, q_{n+1} = q_n·exp(·) or q_n·cay(·):
it never jumps to −q, so dense output and gradients along a run are smooth;
`log` alone chooses a representative (w ≥ 0, an angle in [0, π]).
"""

from typing import ClassVar, Literal, Self

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._util import ORTHOGONALITY_TOLERANCE, as_array, check_floating, drifted
from .base import AbstractQuadraticGroup
from .so3 import SO3

Vector3 = Float[Array, "*batch 3"]
Quaternion = Float[Array, "*batch 4"]

# Below this θ² the half-angle coefficients are their Taylor series (double
# `where`), whose terms through θ⁸ are exact to float64 round-off there.
_SMALL = 1e-2


def _half_angle_coefficients(t2: Array) -> tuple[Array, Array]:
    """(cos(θ/2) − 1, sin(θ/2)/θ) of θ² = t2; the first as −2 sin²(θ/4), which
    does not cancel."""
    small = t2 < _SMALL
    theta = jnp.sqrt(jnp.where(small, _SMALL, t2))
    cos_minus_one = -2 * jnp.sin(theta / 4) ** 2
    sinc = jnp.sin(theta / 2) / theta
    # cos(θ/2) − 1 = Σ_{k≥1} (−1)^k (θ²/4)^k/(2k)!, sin(θ/2)/θ = ½ Σ (−1)^k (θ²/4)^k/(2k + 1)!
    x = t2 / 4
    cos_series = x * (-1 / 2 + x * (1 / 24 + x * (-1 / 720 + x * (1 / 40320 - x / 3628800))))
    sinc_series = 0.5 * (1 + x * (-1 / 6 + x * (1 / 120 + x * (-1 / 5040 + x / 362880))))
    return jnp.where(small, cos_series, cos_minus_one), jnp.where(small, sinc_series, sinc)


def _product(p: Quaternion, q: Quaternion) -> Quaternion:
    """The Hamilton product pq, component by component (XLA fuses it)."""
    pw, px, py, pz = (p[..., i] for i in range(4))
    qw, qx, qy, qz = (q[..., i] for i in range(4))
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def _norm_defect(q: Quaternion) -> Array:
    """| |q|² − 1 |."""
    return jnp.abs(jnp.sum(q * q, axis=-1) - 1)


def _newton_normalization(q: Quaternion) -> Quaternion:
    """q (3 − |q|²)/2: for |q| = 1 + ε the result has norm 1 + O(ε²)."""
    return q * (1.5 - 0.5 * jnp.sum(q * q, axis=-1, keepdims=True))


@jax.custom_jvp
def _normalized_where_drifted(q: Quaternion) -> Quaternion:
    """`_newton_normalization` where |q|² − 1 is past a few ulps, q elsewhere
    (the rule and its reason are the rotation matrices' Björck step's,
    `groups._util.bjorck_step_where_drifted`); its derivative is always the
    normalization's, so a gradient does not depend on where rounding crossed
    the threshold."""
    return jnp.where(drifted(_norm_defect(q))[..., None], _newton_normalization(q), q)


@_normalized_where_drifted.defjvp
def _normalized_where_drifted_jvp(primals, tangents):
    (q,), (q_dot,) = primals, tangents
    _, out_dot = jax.jvp(_newton_normalization, (q,), (q_dot,))
    return _normalized_where_drifted(q), out_dot


class UnitQuaternion(AbstractQuadraticGroup):
    """An attitude as a unit quaternion (w, x, y, z), scalar first (module
    docstring); leading batch axes allowed."""

    wxyz: Float[Array, "*batch 4"] = eqx.field(converter=as_array)
    """The quaternion q = w + xi + yj + zk, |q| = 1."""

    algebra_ndim: ClassVar[int] = 1  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        check_floating(self.wxyz, "a UnitQuaternion")
        if self.wxyz.shape[-1:] != (4,):
            raise ValueError(f"UnitQuaternion needs a (..., 4) array (w, x, y, z), got shape {self.wxyz.shape}.")

    # --- conversions -------------------------------------------------------------
    @classmethod
    def from_matrix(cls, matrix: Float[Array, "*batch 3 3"]) -> Self:
        """The quaternion with w ≥ 0 of a rotation matrix (through `SO3.log`'s
        Shepperd pivoting, accurate at every angle)."""
        return cls.exp(SO3(jnp.asarray(matrix)).log())

    def as_matrix(self) -> Float[Array, "*batch 3 3"]:
        """The rotation matrix R(q), R v = q v q̄: I + 2w v̂ + 2v̂², v = (x, y, z)."""
        w, x, y, z = (self.wxyz[..., i] for i in range(4))
        rows = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
        return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)

    # --- group -------------------------------------------------------------------
    @classmethod
    def exp(cls, u: Vector3) -> Self:
        """(cos(θ/2), sin(θ/2) u/θ), θ = |u|."""
        cos_minus_one, sinc = _half_angle_coefficients(jnp.sum(u * u, axis=-1))
        return cls(jnp.concatenate([(1 + cos_minus_one)[..., None], sinc[..., None] * u], axis=-1))

    @classmethod
    def exp_change(cls, u: Vector3) -> Quaternion:
        """exp(u) − 1 = (−2 sin²(θ/4), sin(θ/2) u/θ), the identity kept out."""
        cos_minus_one, sinc = _half_angle_coefficients(jnp.sum(u * u, axis=-1))
        return jnp.concatenate([cos_minus_one[..., None], sinc[..., None] * u], axis=-1)

    def log(self) -> Vector3:
        """The rotation vector of angle θ ∈ [0, π]: of the representative with
        w ≥ 0, θ = 2 atan2(|v|, w) along v."""
        q = jnp.where(self.wxyz[..., :1] < 0, -self.wxyz, self.wxyz)
        w, v = q[..., 0], q[..., 1:]
        n2 = jnp.sum(v * v, axis=-1)
        # θ/|v|, its Taylor series in |v|² about 0 where w ≈ 1 (double where).
        small = n2 < 1e-10
        n_safe = jnp.sqrt(jnp.where(small, 1.0, n2))
        w_safe = jnp.where(small, w, 1.0)
        factor = jnp.where(small, 2.0 / w_safe - (2.0 / 3.0) * n2 / w_safe**3, 2.0 * jnp.arctan2(n_safe, w) / n_safe)
        return factor[..., None] * v

    def multiply(self, other: Self) -> Self:  # pyright: ignore[reportIncompatibleMethodOverride]  # pyright binds the base's Self in a parameter to the base class
        return type(self)(_product(self.wxyz, other.wxyz))

    def inverse(self) -> Self:
        """The conjugate (w, −v), the inverse of a unit quaternion."""
        return type(self)(self.wxyz * jnp.asarray([1, -1, -1, -1], self.wxyz.dtype))

    def identity_like(self) -> Self:
        return type(self)(jnp.broadcast_to(jnp.asarray([1, 0, 0, 0], self.wxyz.dtype), self.wxyz.shape))

    def adjoint(self, u: Vector3) -> Vector3:
        """q u q̄ = u + 2w (v × u) + 2 v × (v × u)."""
        w, v = self.wxyz[..., :1], self.wxyz[..., 1:]
        vu = jnp.cross(v, u)
        return u + 2 * (w * vu + jnp.cross(v, vu))

    def algebra_zeros(self) -> Vector3:
        return jnp.zeros(self.wxyz.shape[:-1] + (3,), self.wxyz.dtype)

    def check(self) -> Self:
        """Finite and of norm 1 within `ORTHOGONALITY_TOLERANCE` (the rotation
        matrices' tolerance on max|RᵀR − I|, which is about | |q|² − 1 |)."""
        q = self.wxyz
        tol = max(float(np.sqrt(np.finfo(q.dtype).eps)), ORTHOGONALITY_TOLERANCE)
        q = eqx.error_if(q, ~jnp.all(jnp.isfinite(q)), "UnitQuaternion element is not finite (NaN or inf).")
        q = eqx.error_if(
            q,
            jnp.any(_norm_defect(q) > tol),
            f"UnitQuaternion element is not of norm 1: | |q|² − 1 | exceeds {tol:.0e} "
            "(if this is rounding drift, `project()` returns the nearest unit quaternion).",
        )
        return type(self)(q)

    def project(self) -> Self:
        """q/|q|."""
        return type(self)(self.wxyz / jnp.linalg.norm(self.wxyz, axis=-1, keepdims=True))

    def renormalized(self) -> Self:
        """q (3 − |q|²)/2 where | |q|² − 1 | is past a few ulps."""
        return type(self)(_normalized_where_drifted(self.wxyz))

    def change_from_identity(self) -> Quaternion:
        return self.wxyz - jnp.asarray([1, 0, 0, 0], self.wxyz.dtype)

    def product_change(self, change: Quaternion, side: Literal["right", "left"]) -> Self:
        """q(1 + c) − q = qc (or cq): the product is bilinear."""
        return type(self)(_product(self.wxyz, change) if side == "right" else _product(change, self.wxyz))

    # --- the algebra: SO(3)'s -----------------------------------------------------
    @classmethod
    def bracket(cls, u: Vector3, v: Vector3) -> Vector3:
        return SO3.bracket(u, v)

    @classmethod
    def dexp(cls, u: Vector3, v: Vector3) -> Vector3:
        return SO3.dexp(u, v)

    @classmethod
    def dexp_inv(cls, u: Vector3, v: Vector3) -> Vector3:
        return SO3.dexp_inv(u, v)

    @classmethod
    def exp_adjoint(cls, u: Vector3, x: Vector3) -> Vector3:
        return SO3.exp_adjoint(u, x)

    @classmethod
    def exp_adjoint_change(cls, u: Vector3, x: Vector3) -> Vector3:
        return SO3.exp_adjoint_change(u, x)

    @classmethod
    def inverse_shifted_ad(cls, u: Vector3, v: Vector3, alpha: float) -> Vector3:
        return SO3.inverse_shifted_ad(u, v, alpha)

    # --- the Cayley map: SO(3)'s, lifted -------------------------------------------
    @classmethod
    def cayley(cls, u: Vector3) -> Self:
        """(2, u)/√(4 + θ²): the rotation cay(û) = (I − û/2)⁻¹(I + û/2)."""
        r = jnp.sqrt(4 + jnp.sum(u * u, axis=-1))[..., None]
        return cls(jnp.concatenate([2 / r, u / r], axis=-1))

    @classmethod
    def cayley_change(cls, u: Vector3) -> Quaternion:
        """cay(u) − 1 = (−θ²/(r(2 + r)), u/r), r = √(4 + θ²): the identity kept out."""
        t2 = jnp.sum(u * u, axis=-1)[..., None]
        r = jnp.sqrt(4 + t2)
        return jnp.concatenate([-t2 / (r * (2 + r)), u / r], axis=-1)

    def cayley_inverse(self) -> Vector3:
        """cay⁻¹(q) = 2v/w (the same for −q), defined for angles below π (w ≠ 0)."""
        return 2 * self.wxyz[..., 1:] / self.wxyz[..., :1]

    @classmethod
    def dcayley(cls, u: Vector3, v: Vector3) -> Vector3:
        return SO3.dcayley(u, v)

    @classmethod
    def dcayley_inv(cls, u: Vector3, v: Vector3) -> Vector3:
        return SO3.dcayley_inv(u, v)

    @classmethod
    def cayley_adjoint(cls, u: Vector3, x: Vector3) -> Vector3:
        return SO3.cayley_adjoint(u, x)

    @classmethod
    def shifted_cayley_adjoint_inverse(cls, u: Vector3, x: Vector3) -> Vector3:
        return SO3.shifted_cayley_adjoint_inverse(u, x)

    @classmethod
    def cayley_adjoint_change(cls, u: Vector3, x: Vector3) -> Vector3:
        return SO3.cayley_adjoint_change(u, x)
