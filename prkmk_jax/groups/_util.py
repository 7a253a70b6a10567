"""Small numerical helpers shared by the closed-form group maps."""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax.numpy as jnp
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


def orthogonality_defect(matrix: Array) -> Array:
    """max |XᵀX − I| over the last two axes."""
    n = matrix.shape[-1]
    gram = jnp.swapaxes(matrix, -1, -2) @ matrix
    return jnp.max(jnp.abs(gram - jnp.eye(n, dtype=matrix.dtype)), axis=(-2, -1))


def checked_rotation(matrix: Array, group_name: str) -> Array:
    """`matrix`, with run-time errors (`eqx.error_if`) unless it is finite,
    orthogonal to sqrt(eps) and of determinant +1."""
    tol = jnp.sqrt(jnp.finfo(matrix.dtype).eps)
    matrix = eqx.error_if(matrix, ~jnp.all(jnp.isfinite(matrix)), f"{group_name} element is not finite (NaN or inf).")
    matrix = eqx.error_if(matrix, jnp.any(orthogonality_defect(matrix) > tol), f"{group_name} element is not orthogonal: max|RᵀR − I| exceeds sqrt(eps).")
    return eqx.error_if(matrix, jnp.any(jnp.linalg.det(matrix) < 0), f"{group_name} element has det = −1: a reflection, not a rotation.")
