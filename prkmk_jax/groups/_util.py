"""Small numerical helpers shared by the closed-form group maps."""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array


def taylor_or_exact(
    theta_sq: Array,
    taylor: Sequence[float],
    exact: Callable[[Array], Array],
    threshold: float,
) -> Array:
    """`exact(theta_sq)` away from 0, its Taylor polynomial in `theta_sq` near 0.

    Uses the double-`where` trick: the exact branch is evaluated at a safe
    argument where the Taylor branch is selected, so both the value *and the
    gradient* are finite at `theta_sq = 0`.
    """
    small = theta_sq < threshold
    safe = jnp.where(small, threshold, theta_sq)
    poly = jnp.zeros_like(theta_sq)
    for coeff in reversed(taylor):
        poly = poly * theta_sq + coeff
    return jnp.where(small, poly, exact(safe))


def as_array(value):
    """Field converter: nested lists, tuples and NumPy arrays become JAX arrays
    (so `SO3([[1, 0, 0], …])` works); anything else (arrays, tracers, the
    placeholders of pytree manipulations) is left as it is."""
    if isinstance(value, (list, tuple)) or type(value).__module__ == "numpy":
        return jnp.asarray(value)
    return value


def check_floating(value, what: str) -> None:
    """Trace-time check that `value` is a floating-point array: a TypeError
    naming `what` and the dtype otherwise (integer matrices would silently
    truncate every product)."""
    dtype = getattr(value, "dtype", None)
    if dtype is None:
        raise TypeError(f"{what} must be an array, got {type(value).__name__}.")
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"{what} must have a floating-point dtype, got {dtype}; convert it with .astype(float).")


def orthogonality_defect(matrix: Array) -> Array:
    """max |XᵀX − I| over the last two axes."""
    n = matrix.shape[-1]
    gram = jnp.swapaxes(matrix, -1, -2) @ matrix
    return jnp.max(jnp.abs(gram - jnp.eye(n, dtype=matrix.dtype)), axis=(-2, -1))


ORTHOGONALITY_TOLERANCE = 1e-3
"""The largest max|RᵀR − I| a rotation may have (or √eps of its dtype, if
larger). It refuses data that is not a rotation (scaled, sheared, NaN) and
accepts rounding: float32 data promoted to float64, or rotations computed
elsewhere in float32. The library's own states stay far inside it (float32
runs are renormalised once their defect passes a few ulps,
`RENORMALIZATION_DEFECT`)."""


def bjorck_step(matrix: Array) -> Array:
    """Q + ½Q(I − QᵀQ): for Q = R(I + E) with R orthogonal and E small and
    symmetric, the result is R(I + O(E²))."""
    gram = jnp.swapaxes(matrix, -1, -2) @ matrix
    return 1.5 * matrix - 0.5 * (matrix @ gram)


LOW_PRECISION_EPS = 1e-10
"""States of a dtype whose machine epsilon is above this (float32, bfloat16,
float16) are renormalised after each step where they have drifted off the
group by more than a few ulps (`AbstractMethod.advance`), and a splitting
turns their rows by shears (`exact_flows.PlanarTurn`). In float64 the drift
stays below 1e-7 over 10⁹ steps and the state is left exactly as the
coordinate map gives it."""


def is_low_precision(dtype) -> bool:
    """Whether `dtype`'s machine epsilon is above `LOW_PRECISION_EPS`."""
    return float(jnp.finfo(dtype).eps) > LOW_PRECISION_EPS


RENORMALIZATION_DEFECT = 4.0
"""A rotation is renormalised (`AbstractRotationGroup.renormalized`) once its
max|QᵀQ − I| exceeds this many machine epsilons of its dtype."""


def drifted(defect: Array) -> Array:
    """Whether an orthogonality defect (max|QᵀQ − I|, any batch shape) is past
    `RENORMALIZATION_DEFECT` machine epsilons of its dtype."""
    return defect > RENORMALIZATION_DEFECT * float(jnp.finfo(defect.dtype).eps)


@jax.custom_jvp
def bjorck_step_where_drifted(matrix: Array) -> Array:
    """`bjorck_step` on each matrix whose orthogonality defect has `drifted`,
    the others as they are. A correction at every step acts on the last
    product's rounding alone, which follows the motion and so is much the
    same step after step: in float32 the corrections then moved the spatial
    momentum of a free body steadily. Past a few ulps the defect is rounding
    accumulated over many steps, and its correction is not biased
    (`benchmarks/round_off.py` fits how the errors grow).

    Its derivative is `bjorck_step`'s wherever the correction is taken or
    not: that of the projection onto the group, the identity along the
    group, so a gradient does not depend on the steps at which rounding
    crossed the threshold (a run rebuilt backwards crosses it elsewhere)."""
    return jnp.where(drifted(orthogonality_defect(matrix))[..., None, None], bjorck_step(matrix), matrix)


@bjorck_step_where_drifted.defjvp
def _bjorck_step_where_drifted_jvp(primals, tangents):
    (matrix,), (matrix_dot,) = primals, tangents
    _, out_dot = jax.jvp(bjorck_step, (matrix,), (matrix_dot,))
    return bjorck_step_where_drifted(matrix), out_dot


def nearest_rotation(matrix: Array) -> Array:
    """The rotation closest to `matrix` in the Frobenius norm: U diag(1, …, 1,
    det UVᵀ) Vᵀ from the SVD M = U Σ Vᵀ (batch axes allowed)."""
    u, _, vt = jnp.linalg.svd(matrix)
    sign = jnp.sign(jnp.linalg.det(u @ vt))
    u = u.at[..., :, -1].multiply(sign[..., None])
    return u @ vt


def checked_rotation(matrix: Array, group_name: str) -> Array:
    """`matrix`, with run-time errors (`eqx.error_if`) unless it is finite,
    orthogonal to `ORTHOGONALITY_TOLERANCE` and of determinant +1."""
    tol = max(float(np.sqrt(np.finfo(matrix.dtype).eps)), ORTHOGONALITY_TOLERANCE)
    matrix = eqx.error_if(matrix, ~jnp.all(jnp.isfinite(matrix)), f"{group_name} element is not finite (NaN or inf).")
    matrix = eqx.error_if(
        matrix,
        jnp.any(orthogonality_defect(matrix) > tol),
        f"{group_name} element is not orthogonal: max|RᵀR − I| exceeds {tol:.0e} "
        "(if this is rounding drift, `project()` returns the nearest rotation).",
    )
    return eqx.error_if(matrix, jnp.any(jnp.linalg.det(matrix) < 0), f"{group_name} element has det = −1: a reflection, not a rotation.")
