"""Small numerical helpers shared by the closed-form group maps."""

from collections.abc import Callable, Sequence

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
