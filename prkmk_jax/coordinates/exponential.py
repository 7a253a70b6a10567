"""Exponential coordinates (paper §4.2): f = exp, df⁻¹ = dexp⁻¹."""

from typing import ClassVar

import equinox as eqx

from .._series import default_truncation, dexp_inv_series
from ..groups.trig import sincos
from .base import AbstractCoordinates, Truncation, check_truncation


class Exp(AbstractCoordinates):
    """Exponential coordinates, dexp⁻¹ by the Bernoulli series of the bundle bracket.

    `truncation`: `"auto"` keeps the terms ad^k with k ≤ max(p − 2, 0) for a
    method of order p (enough for order p, see `series`); an int q keeps
    k ≤ q; `None` uses the exact form (closed form of the base group, lifted
    to the bundle).

    On G ⋉ 𝔤 the map is the bundle's own exponential, exp(u, v) =
    (exp(u), dexp_{∓u} v) (Table 2.2), the tangent lift of exp, so its exact
    dexp⁻¹ is the tangent lift of the base group's (the default
    `semidirect_inverse_differential`).
    """

    truncation: Truncation = eqx.field(static=True, default="auto")
    maps_lines_to_subgroups: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        check_truncation(self.truncation)

    def resolve_truncation(self, method_order):
        if self.truncation == "auto":
            return default_truncation(method_order)
        return self.truncation

    def group_map(self, group, u):
        return group.exp(u)

    def group_inverse_map(self, g):
        return g.log()

    def group_inverse_differential(self, group, u, x):
        return group.dexp_inv(u, x)

    def group_adjoint(self, group, u, x, sign):
        # exp(u)⁻¹ = exp(−u).
        return group.exp_adjoint(sign * u, x)

    def group_map_change(self, group, u):
        return group.exp_change(u)

    def group_adjoint_change(self, group, u, x, sign):
        return group.exp_adjoint_change(sign * u, x)

    def fiber_map(self, group, u, v, sign):
        return group.dexp(sign * u, v)

    def planar_rotation(self, angle):
        return sincos(angle)

    def planar_half_rotation(self, angle):
        return sincos(0.5 * angle)

    def truncated_inverse_differential(self, bracket, U, X, truncation):
        return dexp_inv_series(bracket, U, X, truncation)
