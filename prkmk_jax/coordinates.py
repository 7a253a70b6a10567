"""Coordinate maps f: Te(TG) → TG and their inverse differentials (paper §4.2, §4.4).

Both are used in right-trivialised form: df_U(V) = d/dt f(U + tV)·f(U)⁻¹, and
`inverse_differential(bundle, U, X, method_order)` returns df⁻¹_U(X), the
right-hand side of the algebra ODE U' = df⁻¹_U(ξ, η) of Algorithm 4.2.
"""

import abc
from typing import Literal

import equinox as eqx

from .bundles import AbstractBundle, AlgebraPair, BundleElement, Increment
from .series import default_truncation, dexp_inv_series

Truncation = int | None | Literal["auto"]
MAX_SERIES_TRUNCATION = 30
"""The largest truncation accepted: the series is unrolled at trace time, and
beyond a few powers the exact form (`truncation=None`) is cheaper."""


class AbstractCoordinates(eqx.Module):
    """A coordinate map on the bundle group and its inverse differential."""

    truncation: eqx.AbstractVar[Truncation]

    @abc.abstractmethod
    def check_bundle(self, bundle: AbstractBundle) -> None:
        """Raise `TypeError` if these coordinates do not exist on `bundle`."""

    @abc.abstractmethod
    def resolve_truncation(self, method_order: int) -> int | None:
        """The truncation used with a method of this order (None = exact)."""

    @abc.abstractmethod
    def map(self, bundle: AbstractBundle, U: AlgebraPair) -> BundleElement:
        """f(U)."""

    @abc.abstractmethod
    def inverse_map(self, bundle: AbstractBundle, g: BundleElement) -> AlgebraPair:
        """f⁻¹(g): the U near 0 with f(U) = g."""

    @abc.abstractmethod
    def apply(self, bundle: AbstractBundle, U: Increment, y: BundleElement, form: Literal["space", "body"]) -> BundleElement:
        """y·f(U) (`form="body"`) or f(U)·y (`"space"`); U's fiber component
        may be None, a zero known at trace time."""

    @abc.abstractmethod
    def inverse_differential(self, bundle: AbstractBundle, U: AlgebraPair, X: AlgebraPair, method_order: int) -> AlgebraPair:
        """df⁻¹_U(X), truncated as `resolve_truncation(method_order)` says."""


def _check_truncation(truncation, allowed_max=None):
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


class Exp(AbstractCoordinates):
    """Exponential coordinates, dexp⁻¹ by the Bernoulli series of the bundle bracket.

    `truncation`: `"auto"` keeps the terms ad^k with k ≤ max(p − 2, 0) for a
    method of order p (enough for order p, see `series`); an int q keeps
    k ≤ q; `None` uses the exact form (closed form of the base group, lifted
    to the bundle).
    """

    truncation: Truncation = eqx.field(static=True, default="auto")

    def __check_init__(self):
        _check_truncation(self.truncation)

    def check_bundle(self, bundle):
        pass

    def resolve_truncation(self, method_order):
        if self.truncation == "auto":
            return default_truncation(method_order)
        return self.truncation

    def map(self, bundle, U):
        return bundle.exp(U)

    def inverse_map(self, bundle, g):
        return bundle.log(g)

    def apply(self, bundle, U, y, form):
        return bundle.exp_multiply(U, y, form)

    def inverse_differential(self, bundle, U, X, method_order):
        q = self.resolve_truncation(method_order)
        if q is None:
            return bundle.dexp_inv(U, X)
        return dexp_inv_series(bundle.bracket, U, X, q)


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

    def __check_init__(self):
        _check_truncation(self.truncation, allowed_max=2)
        if self.truncation == 1:
            raise ValueError("Cayley truncation 1 gains no order over 0 (the degree-2 term is also O(h²)); use 0, 2 or None.")

    def check_bundle(self, bundle):
        if not bundle.supports_cayley:
            raise TypeError(
                f"Cayley coordinates need a quadratic base group (cay(u) = (1 − u/2)⁻¹(1 + u/2) must map g into G); "
                f"{bundle.base.__name__} is not an AbstractQuadraticGroup. Use Exp() instead."
            )

    def resolve_truncation(self, method_order):
        if self.truncation == "auto":
            return 0 if method_order <= 2 else None
        return None if self.truncation == 2 else self.truncation

    def map(self, bundle, U):
        self.check_bundle(bundle)
        return bundle.cayley(U)

    def inverse_map(self, bundle, g):
        self.check_bundle(bundle)
        return bundle.cayley_inverse(g)

    def apply(self, bundle, U, y, form):
        self.check_bundle(bundle)
        return bundle.cayley_multiply(U, y, form)

    def inverse_differential(self, bundle, U, X, method_order):
        self.check_bundle(bundle)
        if self.resolve_truncation(method_order) == 0:
            return X
        return bundle.dcayley_inv(U, X)
