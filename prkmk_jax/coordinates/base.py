"""Coordinate maps (paper §4.2, §4.4): charts φ: 𝔤 → G of the base group.

A coordinate map is given on the base group G, and each bundle lifts it
(`AbstractBundle.map` and its siblings): componentwise on G × 𝔤 and G × G,
and on G ⋉ 𝔤 as

    f(u, v) = (φ(u), ψ_{σu} v),   σ = −1 (left trivialisation) or 1 (right),

with φ the map on G and ψ a linear map of the fiber that the map chooses
(`fiber_map`; by default the tangent lift ψ_{σu} = dφ_{σu}). A map
therefore implements only what it is on G: φ, φ⁻¹ and dφ⁻¹ (three methods;
the rest default, and a map overrides them for speed, for rounding, or for
another fiber map), and every bundle, present or future, uses it: adding a
map is one new module.
A map knows groups, never bundles.

Differentials are right-trivialised, df_U(V) = d/dt f(U + tV)·f(U)⁻¹;
`AbstractBundle.inverse_differential` returns df⁻¹_U(X), the right-hand
side of the algebra equation U' = df⁻¹_U(ξ, η) of Algorithm 4.2.
"""

import abc
from collections.abc import Callable
from functools import partial
from typing import Any, Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..groups.base import AbstractLieGroup, solve_in_algebra
from ..groups.quaternion import UnitQuaternion
from ..groups.so3 import SO3
from ..groups.trig import computed_once

Truncation = int | None | Literal["auto"]
AlgebraPair = tuple[Array, Array]
"""(u, v): an element of the bundle's algebra, as pairs of base-algebra arrays."""
MAX_SERIES_TRUNCATION = 30
"""The largest truncation accepted: the series is unrolled at trace time, and
beyond a few powers the exact form (`truncation=None`) is cheaper."""


class AbstractCoordinates(eqx.Module):
    """A coordinate map of the base group G and its inverse differential,
    which every bundle lifts to itself (`AbstractBundle`)."""

    truncation: eqx.AbstractVar[Truncation]
    maps_lines_to_subgroups: eqx.AbstractClassVar[bool]
    """True where f(s·U)·f(t·U) = f((s + t)·U): f maps each line through 0 to a
    one-parameter subgroup (the exponential does, the Cayley map does not).
    Consecutive sub-flows along one direction may then be merged."""

    # --- what a map is on the base group G: every map says these ----------------------
    @abc.abstractmethod
    def group_map(self, group: type[AbstractLieGroup], u: Array) -> AbstractLieGroup:
        """φ(u) ∈ G."""

    @abc.abstractmethod
    def group_inverse_map(self, g: AbstractLieGroup) -> Array:
        """φ⁻¹(g): the u near 0 with φ(u) = g."""

    @abc.abstractmethod
    def group_inverse_differential(self, group: type[AbstractLieGroup], u: Array, x: Array) -> Array:
        """dφ⁻¹_u(x), exact (right-trivialised)."""

    # --- defaults, built from the above; a map overrides them for speed or rounding ----
    def check_group(self, group: type[AbstractLieGroup]) -> None:
        """Raise `TypeError` if the map does not exist on `group` (by default
        it exists on every group)."""
        del group

    def resolve_truncation(self, method_order: int) -> int | None:
        """The truncation used with a method of this order (None = exact,
        the default)."""
        del method_order

    def group_adjoint(self, group: type[AbstractLieGroup], u: Array, x: Array, sign: float) -> Array:
        """Ad_{φ(u)} x (`sign` 1.0) or Ad_{φ(u)⁻¹} x (`sign` −1.0). A map
        overrides it to act without forming φ(u) where the group allows:
        the fiber update of a step on G ⋉ 𝔤 is this action, and φ(u) itself
        only enters the base."""
        g = self.group_map(group, u)
        return (g if sign > 0 else g.inverse()).adjoint(x)

    def group_map_change(self, group: type[AbstractLieGroup], u: Array) -> Any:
        """φ(u) − e in the arrays a `group` element holds, ideally with the
        identity kept out (`AbstractLieGroup.exp_change`)."""
        return self.group_map(group, u).change_from_identity()

    def group_adjoint_change(self, group: type[AbstractLieGroup], u: Array, x: Array, sign: float) -> Array:
        """`group_adjoint` minus x: Ad_{φ(u)^{±1}} x − x, ideally with x kept out."""
        return self.group_adjoint(group, u, x, sign) - x

    # The lift to G ⋉ 𝔤: by default the tangent lift ψ_{σu} = dφ_{σu}, valid
    # for maps with φ(−u) = φ(u)⁻¹ (`dual_number_inverse_differential`). A map
    # lifted otherwise (the Cayley map of §4.4) overrides all three.
    def fiber_map(self, group: type[AbstractLieGroup], u: Array, v: Array, sign: float) -> Array:
        """ψ_{σu} v with σ = `sign`, the fiber part of f(u, v) on G ⋉ 𝔤:
        σ = −1.0 in left and 1.0 in right trivialisation (module docstring).
        By default dφ_{σu} v, the inverse differential solved for v."""
        inverse_differential = partial(self.group_inverse_differential, group)
        return solve_in_algebra(inverse_differential, sign * u, v, group.algebra_ndim)

    def fiber_map_inverse(self, group: type[AbstractLieGroup], u: Array, w: Array, sign: float) -> Array:
        """ψ_{σu}⁻¹ w (by default dφ⁻¹_{σu} w)."""
        return self.group_inverse_differential(group, sign * u, w)

    def semidirect_inverse_differential(self, group: type[AbstractLieGroup], sign: float, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
        """Exact df⁻¹_U(X) on G ⋉ 𝔤 with σ = `sign` (−1.0 left, 1.0 right
        trivialisation); by default that of the tangent lift, the same in
        both (`dual_number_inverse_differential`)."""
        del sign
        return dual_number_inverse_differential(partial(self.group_inverse_differential, group), U, X)

    def planar_rotation(self, angle: Array) -> tuple[Array, Array]:
        """(sin θ, cos θ) of the rotation f(angle·E), where E generates the
        rotations of one coordinate plane (E² = −1 on it): the exact sub-flows
        of a splitting turn through these, each read by several rows of the
        state. By default read off φ on SO(3) about the third axis; a map
        overrides it with a cheaper formula (`Exp`: `groups.sincos`). It
        is returned through `groups.computed_once`, so that the rows reading
        it do not each evaluate it again."""
        axis = jnp.zeros((3,), jnp.result_type(angle)).at[2].set(1.0)
        turned = cast(SO3, self.group_map(SO3, jnp.asarray(angle)[..., None] * axis)).matrix
        return computed_once(turned[..., 1, 0], turned[..., 0, 0])

    def planar_half_rotation(self, angle: Array) -> tuple[Array, Array]:
        """(sin θ/2, cos θ/2) for the turn θ of `planar_rotation(angle)`:
        what a unit quaternion's components turn by (f(angle·E) on S³ is
        cos θ/2 + sin θ/2·e). By default read off φ on `UnitQuaternion`
        about the third axis; a map overrides it with a cheaper formula."""
        axis = jnp.zeros((3,), jnp.result_type(angle)).at[2].set(1.0)
        turned = cast(UnitQuaternion, self.group_map(UnitQuaternion, jnp.asarray(angle)[..., None] * axis)).wxyz
        return computed_once(turned[..., 3], turned[..., 0])

    def truncated_inverse_differential(self, bracket, U: AlgebraPair, X: AlgebraPair, truncation: int) -> AlgebraPair:
        """df⁻¹_U(X) truncated at `truncation` (an int that
        `resolve_truncation` gave), as a series in the bundle's `bracket`.
        A map whose `resolve_truncation` only gives None (exact) needs none."""
        del bracket, U, X
        raise ValueError(f"{type(self).__name__} has no truncated inverse differential (asked for truncation {truncation}).")


def dual_number_inverse_differential(
    group_inverse_differential: Callable[[Array, Array], Array], U: AlgebraPair, X: AlgebraPair
) -> AlgebraPair:
    """df⁻¹ on G ⋉ 𝔤 for the tangent lift of a map φ, f(u, v) = (φ(u), dφ_{σu} v).

    G ⋉ 𝔤 (either trivialisation) is represented by matrices a + εb over the
    dual numbers, ε² = 0, and its algebra element (x, y) by x + εy. The
    tangent lift of φ is φ applied to u + εv, and its inverse differential is
    dφ⁻¹ applied to dual numbers, whose ε-part is a directional derivative:

        dφ⁻¹_{u+εv}(x + εy) = dφ⁻¹_u(x) + ε (dφ⁻¹_u(y) + D_u dφ⁻¹_u(x)[v]).

    Valid where φ(−u) = φ(u)⁻¹, so that the left-trivialised dφ_u is dφ_{−u}."""
    (u, v), (x, y) = U, X
    first = group_inverse_differential(u, x)
    _, derivative = jax.jvp(lambda w: group_inverse_differential(w, x), (u,), (v,))
    return first, group_inverse_differential(u, y) + derivative


def check_truncation(truncation, allowed_max=None):
    """`ValueError` unless `truncation` is "auto", None or an int in range."""
    if truncation is None or truncation == "auto":
        return
    if isinstance(truncation, bool) or not isinstance(truncation, int) or truncation < 0:
        raise ValueError(f"truncation must be 'auto', None (exact) or an int ≥ 0, got {truncation!r}.")
    if truncation > MAX_SERIES_TRUNCATION:
        # The series is unrolled at trace time, one bracket per power.
        raise ValueError(
            f"truncation {truncation} is more than {MAX_SERIES_TRUNCATION} powers of ad; use truncation=None for the exact form."
        )
    if allowed_max is not None and truncation > allowed_max:
        raise ValueError(f"truncation must be ≤ {allowed_max} here (that is already exact), got {truncation}.")
