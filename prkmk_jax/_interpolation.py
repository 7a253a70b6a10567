"""Dense output that stays on the group.

Within a step yₙ → yₙ₊₁ = f(U)·yₙ (space form; yₙ·f(U) in body form) the
algebra curve U(t), U(tₙ) = 0, U(tₙ₊₁) = U, is interpolated by the cubic
Hermite polynomial matching its end slopes U'(tₙ) = df⁻¹_0(X(tₙ, yₙ)) and
U'(tₙ₊₁) = df⁻¹_U(X(tₙ₊₁, yₙ₊₁)), and pushed forward by the same coordinate
map, so every interpolated value is a group element (up to round-off) and
equals yₙ₊₁ at the step's end. Its local error is O(h^{min(p+1, 4)}): dense
output of order min(p, 3) for a method of order p.
"""

import diffrax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from ._bundles import AlgebraPair, BundleElement
from .methods.base import AbstractMethod


class OnGroupInterpolation(diffrax.AbstractLocalInterpolation):
    """Cubic Hermite interpolation in the algebra, mapped to the group."""

    t0: Array  # pyright: ignore[reportIncompatibleVariableOverride]  # diffrax declares t0, t1 abstract; fields implement them
    t1: Array  # pyright: ignore[reportIncompatibleVariableOverride]
    y0: BundleElement
    increment: AlgebraPair
    slope0: AlgebraPair
    slope1: AlgebraPair
    method: AbstractMethod

    def evaluate(self, t0, t1=None, left: bool = True) -> PyTree[Array]:
        del left
        if t1 is not None:
            raise NotImplementedError(
                "an increment y(t1) − y(t0) is not defined for group-valued solutions; evaluate y(t0) and y(t1) separately."
            )
        h = self.t1 - self.t0
        theta = (t0 - self.t0) / jnp.where(h == 0, 1, h)
        h10 = theta**3 - 2 * theta**2 + theta
        h01 = -2 * theta**3 + 3 * theta**2
        h11 = theta**3 - theta**2
        u, v = ((h10 * h) * s0 + h01 * big + (h11 * h) * s1 for s0, big, s1 in zip(self.slope0, self.increment, self.slope1))
        return self.method.apply_increment((jnp.asarray(u), jnp.asarray(v)), self.y0)
