"""The tangent bundle TG (and cotangent bundle T*G) as a Lie group (paper §2).

A bundle is a static descriptor (`DirectProduct(SO3)`, …) holding the base
group class; its elements are `BundleElement(base, fiber)` pytrees and its
algebra elements are pairs `(x, y)` of base-algebra arrays.

| bundle                | element (a, u)      | product (Table)                      |
|-----------------------|---------------------|--------------------------------------|
| `DirectProduct(G)`    | G × g               | (ab, u + v)                (2.1)     |
| `Semidirect(G,"left")`| G ⋉_Ad g            | (ab, Ad_{b⁻¹}u + v)        (2.4)     |
| `Semidirect(G,"right")`| G ⋉_Ad g           | (ab, u + Ad_a v)           Table 2.2 |
| `Cotangent(G)`        | G ⋉_{Ad*} g*        | (ab, Ad*_b μ + ν)          §5.2      |
| `Cartesian(G)`        | G × G               | (a₁b₁, a₂b₂)               Table 2.3 |

Algebra conventions are those of `groups.base`: brackets are commutators in
a faithful matrix representation and every differential is right-trivialised.

A bundle lifts any coordinate map of its base group (a chart on G,
`coordinates`) to itself (`map`, `inverse_map`, `inverse_differential`,
`apply`, `apply_change`): the map says what it is on G, the bundle how its
elements are built from that. So a coordinate map is written once for
every bundle, and a bundle once for every map; the maps know nothing of
bundles.
"""

import abc
from typing import ClassVar, Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .coordinates import AbstractCoordinates
from .groups.base import AbstractLieGroup

Algebra = Float[Array, "..."]
"""An element of g or g* of the base group: any leading batch axes, then
`algebra_ndim` axes (3-vectors for SO(3), n×n skew matrices for SO(n))."""
AlgebraPair = tuple[Algebra, Algebra]
"""(u, v) ∈ 𝔤 of a bundle group: the base's part and the fiber's."""
Increment = tuple[Algebra, Algebra | None]
"""(u, v) as `apply` takes it: v None is a zero known at trace
time, whose arithmetic the product skips."""


class BundleElement(eqx.Module):
    """A point of a bundle group: a base-group element and its fiber part."""

    base: AbstractLieGroup
    """The configuration a ∈ G."""
    fiber: PyTree[Array]
    """An algebra array u ∈ g or μ ∈ g* (shape `(*batch, *algebra_shape)`), or a
    second group element for `Cartesian`."""


def _multiply_in_form(bundle, increment, y, form):
    """y·increment (body form) or increment·y (space form)."""
    return bundle.multiply(y, increment) if form == "body" else bundle.multiply(increment, y)


def _side(form) -> Literal["right", "left"]:
    """Where the increment multiplies the state: on the right in body form."""
    return "right" if form == "body" else "left"


def _is_group_class(base) -> bool:
    return isinstance(base, type) and issubclass(base, AbstractLieGroup)


class AbstractBundle(eqx.Module):
    """A (co)tangent bundle of `base` made a Lie group."""

    base: eqx.AbstractVar[type[AbstractLieGroup]]
    fiber_is_group: eqx.AbstractClassVar[bool]
    """True where the second factor is a group element (G×G)."""

    def __check_init__(self):
        if not _is_group_class(self.base):
            raise TypeError(f"{type(self).__name__} needs a base group class such as SO3, got {self.base!r}.")

    # --- element validation ----------------------------------------------------
    def check(self, y: BundleElement) -> BundleElement:
        """Static checks (types, shapes; `TypeError`/`ValueError`) and run-time
        checks of the data (`eqx.error_if`); returns `y` to be used onwards."""
        if not isinstance(y, BundleElement):
            raise TypeError(f"{type(self).__name__} elements are BundleElement(base, fiber), got {type(y).__name__}.")
        if not isinstance(y.base, self.base):
            raise TypeError(f"the base of this element is {type(y.base).__name__}, but the bundle is over {self.base.__name__}.")
        zeros = y.base.algebra_zeros()
        if self.fiber_is_group:
            if not isinstance(y.fiber, self.base):
                raise TypeError(f"{type(self).__name__} needs a {self.base.__name__} fiber, got {type(y.fiber).__name__}.")
            fiber_shape = y.fiber.algebra_zeros().shape
        else:
            if isinstance(y.fiber, AbstractLieGroup):
                raise TypeError(f"{type(self).__name__} needs an algebra-array fiber, got a {type(y.fiber).__name__} element.")
            fiber_shape = jnp.shape(y.fiber)
        if fiber_shape != zeros.shape:
            raise ValueError(f"fiber shape {fiber_shape} does not match the base algebra shape {zeros.shape}.")
        fiber_dtype = jax.tree.leaves(y.fiber)[0].dtype if self.fiber_is_group else jnp.result_type(y.fiber)
        if fiber_dtype != zeros.dtype:
            raise TypeError(f"the base is {zeros.dtype} but the fiber is {fiber_dtype}; give both the same dtype (the run's precision).")
        base = y.base.check()
        if self.fiber_is_group:
            fiber = y.fiber.check()
        else:
            fiber_array = cast(Array, y.fiber)  # not a group element: checked above
            fiber = eqx.error_if(fiber_array, ~jnp.all(jnp.isfinite(fiber_array)), "bundle fiber is not finite (NaN or inf).")
        return BundleElement(base, fiber)

    def project(self, y: BundleElement) -> BundleElement:
        """`y` with its base (and a group fiber) moved to the nearest valid
        element (`AbstractLieGroup.project`); an algebra fiber is unchanged."""
        fiber = y.fiber.project() if self.fiber_is_group else y.fiber
        return BundleElement(y.base.project(), fiber)

    def renormalized(self, y: BundleElement) -> BundleElement:
        """`y` with its base (and a group fiber) corrected for rounding drift
        (`AbstractLieGroup.renormalized`); an algebra fiber is unchanged."""
        fiber = y.fiber.renormalized() if self.fiber_is_group else y.fiber
        return BundleElement(y.base.renormalized(), fiber)

    def algebra_zeros(self, y: BundleElement) -> AlgebraPair:
        z = y.base.algebra_zeros()
        return z, jnp.zeros_like(z)

    def zero_filled(self, U: Increment, y: BundleElement) -> AlgebraPair:
        """U with a fiber component None (a zero known at trace time, see
        `apply`) replaced by the zeros of the algebra at y."""
        u, v = U
        return u, self.algebra_zeros(y)[1] if v is None else v

    def identity_like(self, y: BundleElement) -> BundleElement:
        fiber = y.fiber.identity_like() if self.fiber_is_group else jnp.zeros_like(y.fiber)
        return BundleElement(y.base.identity_like(), fiber)

    # --- group and algebra ---------------------------------------------------------
    @abc.abstractmethod
    def multiply(self, a: BundleElement, b: BundleElement) -> BundleElement:
        """The group product a·b."""

    @abc.abstractmethod
    def inverse(self, a: BundleElement) -> BundleElement:
        """The group inverse."""

    @abc.abstractmethod
    def bracket(self, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
        """The bracket of the bundle algebra."""

    # --- a coordinate map of the base, lifted ------------------------------------------
    def check_coordinates(self, coordinates: AbstractCoordinates) -> None:
        """Raise `TypeError` if `coordinates` do not exist on this bundle's base."""
        coordinates.check_group(self.base)

    def inverse_differential(
        self, coordinates: AbstractCoordinates, U: AlgebraPair, X: AlgebraPair, method_order: int | None = None
    ) -> AlgebraPair:
        """df⁻¹_U(X), the right-hand side of the algebra equation
        U' = df⁻¹_U(ξ, η) of Algorithm 4.2: exact (`method_order` None), or
        truncated as `coordinates.resolve_truncation(method_order)` says
        (a series in this bundle's bracket)."""
        truncation = None if method_order is None else coordinates.resolve_truncation(method_order)
        if truncation is None:
            return self.exact_inverse_differential(coordinates, U, X)
        return coordinates.truncated_inverse_differential(self.bracket, U, X, truncation)

    @abc.abstractmethod
    def map(self, coordinates: AbstractCoordinates, U: AlgebraPair) -> BundleElement:
        """f(U) for the coordinate map f of the bundle built on `coordinates`."""

    @abc.abstractmethod
    def inverse_map(self, coordinates: AbstractCoordinates, a: BundleElement) -> AlgebraPair:
        """f⁻¹(a): the U near 0 with f(U) = a."""

    @abc.abstractmethod
    def exact_inverse_differential(self, coordinates: AbstractCoordinates, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
        """Exact df⁻¹_U(X)."""

    @abc.abstractmethod
    def apply(self, coordinates: AbstractCoordinates, U: Increment, y: BundleElement, form: Literal["space", "body"]) -> BundleElement:
        """y·f(U) (`form="body"`) or f(U)·y (`"space"`), without forming f(U)
        where the product only needs its action.

        U = (u, v), and v may be None: a zero known at trace time (a PRKMK
        stage that no L enters, as for a field with η ≡ 0). The product then
        skips the fiber part of f(u, 0), which is zero but would cost its
        arithmetic: XLA does not fold 0·x for floats. On G ⋉ 𝔤 that part is
        ψ_{∓u} v (`AbstractCoordinates.fiber_map`); skipping it makes the free
        body's step on T*SO(3) quicker."""

    @abc.abstractmethod
    def apply_change(
        self, coordinates: AbstractCoordinates, U: Increment, y: BundleElement, form: Literal["space", "body"]
    ) -> BundleElement:
        """`apply` minus y, computed with y kept out of every sum:
        a container shaped as y holding the change of each of its arrays
        (not a bundle element), rounded relative to the change rather than
        to y. A step adds it to y and carries the sum's rounding on
        (compensated summation, `AbstractMethod.advance`)."""


class DirectProduct(AbstractBundle):
    """TG ≅ G × g, the direct product (paper §2.1, Table 2.1)."""

    base: type[AbstractLieGroup] = eqx.field(static=True)
    fiber_is_group: ClassVar[bool] = False  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def multiply(self, a, b):
        return BundleElement(a.base.multiply(b.base), a.fiber + b.fiber)

    def inverse(self, a):
        return BundleElement(a.base.inverse(), -a.fiber)

    def bracket(self, U, X):
        return self.base.bracket(U[0], X[0]), jnp.zeros_like(X[1])

    def map(self, coordinates, U):
        return BundleElement(coordinates.group_map(self.base, U[0]), U[1])

    def inverse_map(self, coordinates, a):
        return coordinates.group_inverse_map(a.base), a.fiber

    def exact_inverse_differential(self, coordinates, U, X):
        return coordinates.group_inverse_differential(self.base, U[0], X[0]), X[1]

    def apply(self, coordinates, U, y, form):
        return _multiply_in_form(self, self.map(coordinates, self.zero_filled(U, y)), y, form)

    def apply_change(self, coordinates, U, y, form):
        u, v = self.zero_filled(U, y)
        return BundleElement(y.base.product_change(coordinates.group_map_change(self.base, u), _side(form)), v)


class Cartesian(AbstractBundle):
    """TG ≅ G × G, the Cartesian product (paper §2.3, Table 2.3)."""

    base: type[AbstractLieGroup] = eqx.field(static=True)
    fiber_is_group: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def multiply(self, a, b):
        return BundleElement(a.base.multiply(b.base), a.fiber.multiply(b.fiber))

    def inverse(self, a):
        return BundleElement(a.base.inverse(), a.fiber.inverse())

    def bracket(self, U, X):
        return self.base.bracket(U[0], X[0]), self.base.bracket(U[1], X[1])

    def map(self, coordinates, U):
        return BundleElement(coordinates.group_map(self.base, U[0]), coordinates.group_map(self.base, U[1]))

    def inverse_map(self, coordinates, a):
        return coordinates.group_inverse_map(a.base), coordinates.group_inverse_map(a.fiber)

    def exact_inverse_differential(self, coordinates, U, X):
        return coordinates.group_inverse_differential(self.base, U[0], X[0]), coordinates.group_inverse_differential(self.base, U[1], X[1])

    def apply(self, coordinates, U, y, form):
        return _multiply_in_form(self, self.map(coordinates, self.zero_filled(U, y)), y, form)

    def apply_change(self, coordinates, U, y, form):
        u, v = self.zero_filled(U, y)
        side = _side(form)
        return BundleElement(
            y.base.product_change(coordinates.group_map_change(self.base, u), side),
            y.fiber.product_change(coordinates.group_map_change(self.base, v), side),
        )


class AbstractSemidirect(AbstractBundle):
    """G ⋉ g with the lifted product (2.4) in left or right trivialisation.

    A coordinate map lifts as f(u, v) = (φ(u), ψ_{∓u} v) (left/right), with φ
    and ψ the map's (`coordinates`): for the exponential
    exp(u, v) = (exp(u), dexp_{∓u} v), the trivialised differential of the base
    exp (Table 2.2); for Cayley the §4.4 form (`coordinates.cayley`).
    """

    trivialization: eqx.AbstractVar[Literal["left", "right"]]
    fiber_is_group: ClassVar[bool] = False  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def _sign(self):
        return -1.0 if self.trivialization == "left" else 1.0

    def multiply(self, a, b):
        if self.trivialization == "left":
            fiber = b.base.inverse().adjoint(a.fiber) + b.fiber
        else:
            fiber = a.fiber + a.base.adjoint(b.fiber)
        return BundleElement(a.base.multiply(b.base), fiber)

    def inverse(self, a):
        if self.trivialization == "left":
            fiber = -a.base.adjoint(a.fiber)
        else:
            fiber = -a.base.inverse().adjoint(a.fiber)
        return BundleElement(a.base.inverse(), fiber)

    def bracket(self, U, X):
        (u, v), (x, y) = U, X
        br = self.base.bracket
        return br(u, x), br(u, y) - br(x, v)

    def map(self, coordinates, U):
        u, v = U
        return BundleElement(coordinates.group_map(self.base, u), coordinates.fiber_map(self.base, u, v, self._sign()))

    def inverse_map(self, coordinates, a):
        u = coordinates.group_inverse_map(a.base)
        return u, coordinates.fiber_map_inverse(self.base, u, a.fiber, self._sign())

    def exact_inverse_differential(self, coordinates, U, X):
        return coordinates.semidirect_inverse_differential(self.base, self._sign(), U, X)

    def apply(self, coordinates, U, y, form):
        u, v = U
        base = self.base
        fiber_part = None if v is None else coordinates.fiber_map(base, u, v, self._sign())
        g = coordinates.group_map(base, u)
        return self._multiply_increment(y, g, fiber_part, lambda x, sign: coordinates.group_adjoint(base, u, x, sign), form)

    def apply_change(self, coordinates, U, y, form):
        # The fiber of `_multiply_increment` minus y's: where the action
        # moves y's fiber, its change Ad_{φ(u)^{±1}} μ − μ; where it does
        # not, the added part alone.
        u, v = U
        base = self.base
        w = None if v is None else coordinates.fiber_map(base, u, v, self._sign())
        base_change = y.base.product_change(coordinates.group_map_change(base, u), _side(form))
        left = self.trivialization == "left"
        if form == "body":  # y·(g, w): (a g, Ad_{g⁻¹} μ + w) left, (a g, μ + Ad_a w) right
            moved = coordinates.group_adjoint_change(base, u, y.fiber, -1.0) if left else None
            added = None if w is None else (w if left else y.base.adjoint(w))
        else:  # (g, w)·y: (g a, Ad_{a⁻¹} w + μ) left, (g a, w + Ad_g μ) right
            moved = None if left else coordinates.group_adjoint_change(base, u, y.fiber, 1.0)
            added = None if w is None else (y.base.inverse().adjoint(w) if left else w)
        parts = [part for part in (moved, added) if part is not None]
        fiber_change = sum(parts[1:], parts[0]) if parts else jnp.zeros_like(y.fiber)
        return BundleElement(base_change, fiber_change)

    def _multiply_increment(self, y, g, w, act, form):
        """The product (multiply) of y with the increment (g, w), where g is
        φ(u) and act(x, ±1.0) = Ad_{g^{±1}} x is computed without g
        (g itself only enters the base, which XLA drops when unused)."""
        left = self.trivialization == "left"
        if form == "body":  # y·(g, w)
            fiber = act(y.fiber, -1.0) if left else y.fiber
            if w is not None:  # None: w = 0 (`apply`)
                fiber = fiber + (w if left else y.base.adjoint(w))
            return BundleElement(y.base.multiply(g), fiber)
        # (g, w)·y
        fiber = y.fiber if left else act(y.fiber, 1.0)
        if w is not None:
            fiber = fiber + (y.base.inverse().adjoint(w) if left else w)
        return BundleElement(g.multiply(y.base), fiber)


class Semidirect(AbstractSemidirect):
    """TG ≅ G ⋉_Ad g (paper §2.2, Table 2.2)."""

    base: type[AbstractLieGroup] = eqx.field(static=True)
    trivialization: Literal["left", "right"] = eqx.field(static=True, default="left")

    def __check_init__(self):
        if self.trivialization not in ("left", "right"):
            raise ValueError(f"trivialization must be 'left' or 'right', got {self.trivialization!r}.")


class Cotangent(AbstractSemidirect):
    """T*G ≅ G ⋉_{Ad*} g*, left trivialised (body momenta; paper §3.2, §5.2).

    Product (ab, Ad*_b μ + ν), bracket (ad_u x, −ad*_u ν + ad*_x μ). Only base
    groups with a bi-invariant pairing are accepted: there Ad*_b = Ad_{b⁻¹} and
    ad*_u = −ad_u on g* ≅ g, so every formula is that of `Semidirect(G, "left")`
    with the fiber read as a momentum (for SO(3): Π ∈ ℝ³, Ad*_R Π = RᵀΠ).
    """

    base: type[AbstractLieGroup] = eqx.field(static=True)
    trivialization: ClassVar[Literal["left"]] = "left"  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar

    def __check_init__(self):
        # Runs before AbstractBundle's check, which refuses a base that is not
        # a group class.
        if _is_group_class(self.base) and not self.base.bi_invariant_pairing:
            raise TypeError(
                f"Cotangent({self.base.__name__}) needs a base group whose algebra has a bi-invariant pairing "
                "(g* ≅ g with Ad* = Ad⁻¹); this one does not declare it."
            )
