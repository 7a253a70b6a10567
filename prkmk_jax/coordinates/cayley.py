"""Cayley coordinates (paper §4.4): f = cay, for bundles over quadratic groups.

On G ⋉ 𝔤 the map is the one of §4.4, the Cayley transform for the algebra
product (u, v)·(x, y) = (ux, −ad_x v) of (4.16):

    cay(u, v) = (cay(u), (I ± ½ad_u)⁻¹ v)   (+ left, − right trivialisation).

It is not the tangent lift of cay (the two differ at second order in U);
both are valid coordinates. Its inverse differential is derived in
`Cayley.semidirect_inverse_differential`. The bracket-only formula printed in
§4.4, (dcay⁻¹_u x, y − ½([u,y] + [v,x]) − ¼[u,[x,v]]), agrees with it on
so(3) but not on so(n), n ≥ 4 (`paper_semidirect_dcayley_inv`).
"""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from ..groups.base import AbstractLieGroup, AbstractQuadraticGroup
from ..groups.trig import computed_once
from .base import AbstractCoordinates, AlgebraPair, Truncation, check_truncation


def _quadratic_group(group: type[AbstractLieGroup]) -> type[AbstractQuadraticGroup]:
    if not issubclass(group, AbstractQuadraticGroup):
        raise TypeError(
            f"Cayley coordinates need a quadratic base group (cay(u) = (1 − u/2)⁻¹(1 + u/2) must map g into G); "
            f"{group.__name__} is not an AbstractQuadraticGroup. Use Exp() instead."
        )
    return group


def _quadratic_element(element: AbstractLieGroup) -> AbstractQuadraticGroup:
    if not isinstance(element, AbstractQuadraticGroup):
        raise TypeError(f"the inverse Cayley map needs an element of a quadratic group, got {type(element).__name__}.")
    return element


class Cayley(AbstractCoordinates):
    """Cayley coordinates (paper §4.4), for bundles over quadratic groups.

    dcay⁻¹_U(X) is a polynomial of degree 2 in U, so it is cheap to use
    exactly. `truncation`: `"auto"` drops the U-dependent terms (dcay⁻¹ ≈ I)
    for methods of order ≤ 2, where they are O(h²) and do not affect the order,
    and is exact otherwise; 0 forces dcay⁻¹ ≈ I; `None` or 2 is exact.
    Degree 1 alone is not offered: the degree-2 term is also O(h²), so keeping
    only the bracket term gains no order.
    """

    truncation: Truncation = eqx.field(static=True, default="auto")
    maps_lines_to_subgroups: ClassVar[bool] = False  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        check_truncation(self.truncation, allowed_max=2)
        if self.truncation == 1:
            raise ValueError("Cayley truncation 1 gains no order over 0 (the degree-2 term is also O(h²)); use 0, 2 or None.")

    def check_group(self, group):
        _quadratic_group(group)

    def resolve_truncation(self, method_order):
        if self.truncation == "auto":
            return 0 if method_order <= 2 else None
        return None if self.truncation == 2 else self.truncation

    def group_map(self, group, u):
        return _quadratic_group(group).cayley(u)

    def group_inverse_map(self, g):
        return _quadratic_element(g).cayley_inverse()

    def group_inverse_differential(self, group, u, x):
        return _quadratic_group(group).dcayley_inv(u, x)

    def group_adjoint(self, group, u, x, sign):
        # cay(u)⁻¹ = cay(−u).
        return _quadratic_group(group).cayley_adjoint(sign * u, x)

    def group_map_change(self, group, u):
        return _quadratic_group(group).cayley_change(u)

    def group_adjoint_change(self, group, u, x, sign):
        return _quadratic_group(group).cayley_adjoint_change(sign * u, x)

    def fiber_map(self, group, u, v, sign):
        # (cay(σ ad_u) − I)/(σ ad_u) = (I − ½σ ad_u)⁻¹.
        return _quadratic_group(group).inverse_shifted_ad(u, v, -0.5 * sign)

    def fiber_map_inverse(self, group, u, w, sign):
        return w - 0.5 * sign * group.bracket(u, w)

    def semidirect_inverse_differential(self, group, sign, U, X):
        # Differentiate cay(U + tV)·cay(U)⁻¹ with w = fiber of cay(U) and
        # x_V = dcay⁻¹_u(x); solving the fiber part for y_V gives
        #   left:  y_V = (I + ½ad_u) Ad_{cay(u)⁻¹} y + ½[x_V, w]
        #   right: y_V = (I − ½ad_u)(y + [x, w]) − ½[x_V, w].
        (u, v), (x, y) = U, X
        group = _quadratic_group(group)
        br = group.bracket
        left = sign < 0
        w = self.fiber_map(group, u, v, sign)
        x_v = group.dcayley_inv(u, x)
        if left:
            y_v = group.shifted_cayley_adjoint_inverse(u, y) + 0.5 * br(x_v, w)
        else:
            z = y + br(x, w)
            y_v = z - 0.5 * br(u, z) - 0.5 * br(x_v, w)
        return x_v, y_v

    def planar_rotation(self, angle):
        # cay(aE) turns by 2·atan(a/2): cos = (1 − a²/4)/(1 + a²/4), sin = a/(1 + a²/4).
        quarter = 0.25 * angle * angle
        scale = 1.0 / (1.0 + quarter)
        return computed_once(angle * scale, (1.0 - quarter) * scale)

    def planar_half_rotation(self, angle):
        # cay(aE) on S³ is (2 + a e)/√(4 + a²): cos θ/2 = 2/√(4 + a²), sin θ/2 = a/√(4 + a²).
        # Two quotients by one r = √(4 + a²), as `UnitQuaternion.cayley`:
        # written as 2/√(4 + a²) alone, XLA computes it by rsqrt, whose
        # rounding leans one way (s² + c² below 1 on average), and a long
        # run of turns would add the bias up in |q| (design notes).
        r = jnp.sqrt(4.0 + angle * angle)
        return computed_once(angle / r, 2.0 / r)

    def truncated_inverse_differential(self, bracket, U, X, truncation):
        # The only truncation short of exact: dcay⁻¹ ≈ I.
        del bracket, U, truncation
        return X


def paper_semidirect_dcayley_inv(group: type[AbstractLieGroup], U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
    """The §4.4 formula as printed: (dcay⁻¹_u x, y − ½([u,y] + [v,x]) − ¼[u,[x,v]]).

    Kept for comparison only: it is the inverse differential of the §4.4
    Cayley map on so(3) (both trivialisations), but not on so(n) for n ≥ 4,
    where the derivation through the product (4.16) does not hold.
    """
    (u, v), (x, y) = U, X
    group = _quadratic_group(group)
    br = group.bracket
    return group.dcayley_inv(u, x), y - 0.5 * (br(u, y) + br(v, x)) - 0.25 * br(u, br(x, v))
