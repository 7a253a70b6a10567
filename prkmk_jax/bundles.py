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
a faithful matrix representation and every df⁻¹ is right-trivialised,
df_U(V) = d/dt f(U + tV)·f(U)⁻¹. For the semidirect product that
representation is a + ε a u (left) or a + ε u a (right) over dual numbers
ε² = 0; in both the algebra element (x, y) is x + εy, which gives the bracket
of Table 2.2 and the following exact forms, obtained by expanding an analytic
function Φ(U, X) of the dual-number matrices:

    Φ(u + εv, x + εy) = Φ(u, x) + ε (Φ(u, y) + D_uΦ(u, x)[v]).

Applied to Φ = dexp⁻¹ this is `_dual_lift` below (the exact semidirect dexp⁻¹).

The semidirect Cayley map is the one of §4.4, the Cayley transform for the
algebra product (u, v)·(x, y) = (ux, −ad_x v) of (4.16):
cay(u, v) = (cay(u), (I ± ½ad_u)⁻¹ v) (+ left, − right trivialisation). It is
not the Cayley transform of the dual-number representation (the two differ at
second order in U); both are valid coordinates. Its inverse differential is
derived in `AbstractSemidirect.dcayley_inv`. The bracket-only formula printed
in §4.4, (dcay⁻¹_u x, y − ½([u,y] + [v,x]) − ¼[u,[x,v]]), agrees with it on
so(3) but not on so(n), n ≥ 4 (see `paper_semidirect_dcayley_inv`).
"""

import abc
from typing import ClassVar, Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .groups.base import AbstractLieGroup, AbstractQuadraticGroup

Algebra = Float[Array, "..."]
"""An element of g or g* of the base group: any leading batch axes, then
`algebra_ndim` axes (3-vectors for SO(3), n×n skew matrices for SO(n))."""
AlgebraPair = tuple[Algebra, Algebra]
"""(u, v) ∈ 𝔤 of a bundle group: the base's part and the fiber's."""
Increment = tuple[Algebra, Algebra | None]
"""(u, v) as `exp_multiply` and `cayley_multiply` take it: v None is a zero
known at trace time, whose arithmetic the product skips."""


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


def _dual_lift(fn, u, v, x, y):
    """ε-expansion of Φ(u + εv, x + εy) for Φ = fn (see module docstring)."""
    first = fn(u, x)
    _, d_first = jax.jvp(lambda uu: fn(uu, x), (u,), (v,))
    return first, fn(u, y) + d_first


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

    @property
    def supports_cayley(self) -> bool:
        return issubclass(self.base, AbstractQuadraticGroup)

    @property
    def quadratic_base(self) -> type[AbstractQuadraticGroup]:
        """`base`, for the Cayley maps, which exist on quadratic groups only."""
        base = self.base
        if not issubclass(base, AbstractQuadraticGroup):
            raise TypeError(f"Cayley coordinates need a quadratic base group; {base.__name__} is not an AbstractQuadraticGroup.")
        return base

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
        `exp_multiply`) replaced by the zeros of the algebra at y."""
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

    @abc.abstractmethod
    def exp(self, U: AlgebraPair) -> BundleElement:
        """The exponential map of the bundle."""

    @abc.abstractmethod
    def log(self, a: BundleElement) -> AlgebraPair:
        """Inverse of `exp` near the identity."""

    @abc.abstractmethod
    def dexp_inv(self, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
        """Exact dexp⁻¹_U(X) (from the base group's closed form)."""

    @abc.abstractmethod
    def cayley(self, U: AlgebraPair) -> BundleElement:
        """The Cayley map of the bundle (§4.4)."""

    @abc.abstractmethod
    def cayley_inverse(self, a: BundleElement) -> AlgebraPair:
        """The U with cay(U) = a (the inverse of `cayley`, as `log` is of `exp`)."""

    @abc.abstractmethod
    def dcayley_inv(self, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
        """Exact dcay⁻¹_U(X)."""

    # --- the update of a PRKMK step ------------------------------------------------
    @abc.abstractmethod
    def exp_multiply(self, U: Increment, y: BundleElement, form: Literal["space", "body"]) -> BundleElement:
        """y·exp(U) (`form="body"`) or exp(U)·y (`"space"`), without forming
        exp(U) where the product only needs its action.

        U = (u, v), and v may be None: a zero known at trace time (a PRKMK
        stage that no L enters, as for a field with η ≡ 0). The product then
        skips the fiber part of exp(u, 0), which is zero but would cost its
        arithmetic: XLA does not fold 0·x for floats. On G ⋉ g that part is
        dexp_{∓u}(v); skipping it makes the free body's step on T*SO(3)
        quicker (`benchmarks/against_revision.py` measures it)."""

    @abc.abstractmethod
    def cayley_multiply(self, U: Increment, y: BundleElement, form: Literal["space", "body"]) -> BundleElement:
        """y·cay(U) or cay(U)·y, as `exp_multiply`."""


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

    def exp(self, U):
        return BundleElement(self.base.exp(U[0]), U[1])

    def log(self, a):
        return a.base.log(), a.fiber

    def dexp_inv(self, U, X):
        return self.base.dexp_inv(U[0], X[0]), X[1]

    def cayley(self, U):
        return BundleElement(self.quadratic_base.cayley(U[0]), U[1])

    def cayley_inverse(self, a):
        return _quadratic(a.base).cayley_inverse(), a.fiber

    def dcayley_inv(self, U, X):
        return self.quadratic_base.dcayley_inv(U[0], X[0]), X[1]

    def exp_multiply(self, U, y, form):
        return _multiply_in_form(self, self.exp(self.zero_filled(U, y)), y, form)

    def cayley_multiply(self, U, y, form):
        return _multiply_in_form(self, self.cayley(self.zero_filled(U, y)), y, form)


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

    def exp(self, U):
        return BundleElement(self.base.exp(U[0]), self.base.exp(U[1]))

    def log(self, a):
        return a.base.log(), a.fiber.log()

    def dexp_inv(self, U, X):
        return self.base.dexp_inv(U[0], X[0]), self.base.dexp_inv(U[1], X[1])

    def cayley(self, U):
        return BundleElement(self.quadratic_base.cayley(U[0]), self.quadratic_base.cayley(U[1]))

    def cayley_inverse(self, a):
        return _quadratic(a.base).cayley_inverse(), _quadratic(a.fiber).cayley_inverse()

    def dcayley_inv(self, U, X):
        return self.quadratic_base.dcayley_inv(U[0], X[0]), self.quadratic_base.dcayley_inv(U[1], X[1])

    def exp_multiply(self, U, y, form):
        return _multiply_in_form(self, self.exp(self.zero_filled(U, y)), y, form)

    def cayley_multiply(self, U, y, form):
        return _multiply_in_form(self, self.cayley(self.zero_filled(U, y)), y, form)


class AbstractSemidirect(AbstractBundle):
    """G ⋉ g with the lifted product (2.4) in left or right trivialisation.

    exp(u, v) = (exp(u), dexp_{∓u}(v)): the trivialised differential of the
    base exp, left (−u) or right (+u) as the trivialisation (Table 2.2, §4.4).
    Cayley: the §4.4 forms (module docstring).
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

    def exp(self, U):
        u, v = U
        return BundleElement(self.base.exp(u), self.base.dexp(self._sign() * u, v))

    def log(self, a):
        u = a.base.log()
        return u, self.base.dexp_inv(self._sign() * u, a.fiber)

    def dexp_inv(self, U, X):
        return _dual_lift(self.base.dexp_inv, U[0], U[1], X[0], X[1])

    def _cayley_fiber(self, u, v):
        # (cay(−ad_u) − I)/(−ad_u) = (I + ½ad_u)⁻¹ (left); (I − ½ad_u)⁻¹ (right).
        return self.base.inverse_shifted_ad(u, v, -0.5 * self._sign())

    def cayley(self, U):
        u, v = U
        return BundleElement(self.quadratic_base.cayley(u), self._cayley_fiber(u, v))

    def cayley_inverse(self, a):
        # The fiber of cay(u, v) is (I + α ad_u)⁻¹ v with α = ±½ (`_cayley_fiber`).
        u = _quadratic(a.base).cayley_inverse()
        return u, a.fiber - 0.5 * self._sign() * self.base.bracket(u, a.fiber)

    def dcayley_inv(self, U, X):
        # Differentiate cay(U + tV)·cay(U)⁻¹ with w = fiber of cay(U) and
        # x_V = dcay⁻¹_u(x); solving the fiber part for y_V gives
        #   left:  y_V = (I + ½ad_u) Ad_{cay(u)⁻¹} y + ½[x_V, w]
        #   right: y_V = (I − ½ad_u)(y + [x, w]) − ½[x_V, w].
        (u, v), (x, y) = U, X
        br = self.base.bracket
        w = self._cayley_fiber(u, v)
        x_v = self.quadratic_base.dcayley_inv(u, x)
        if self.trivialization == "left":
            z = self.quadratic_base.cayley_adjoint(-u, y)  # Ad_{cay(−u)} = Ad_{cay(u)⁻¹}, without forming the matrix
            y_v = z + 0.5 * br(u, z) + 0.5 * br(x_v, w)
        else:
            z = y + br(x, w)
            y_v = z - 0.5 * br(u, z) - 0.5 * br(x_v, w)
        return x_v, y_v

    def exp_multiply(self, U, y, form):
        u, v = U
        base = self.base
        fiber_part = None if v is None else base.dexp(self._sign() * u, v)
        return self._multiply_increment(y, base.exp(u), fiber_part, lambda x, sign: base.exp_adjoint(sign * u, x), form)

    def cayley_multiply(self, U, y, form):
        u, v = U
        base = self.quadratic_base
        fiber_part = None if v is None else self._cayley_fiber(u, v)
        return self._multiply_increment(y, base.cayley(u), fiber_part, lambda x, sign: base.cayley_adjoint(sign * u, x), form)

    def _multiply_increment(self, y, g, w, act, form):
        """The product (multiply) of y with the increment (g, w), where g is
        exp(u) or cay(u) and act(x, ±1) = Ad_{g^{±1}} x is computed without g
        (g itself only enters the base, which XLA drops when unused)."""
        left = self.trivialization == "left"
        if form == "body":  # y·(g, w)
            fiber = act(y.fiber, -1.0) if left else y.fiber
            if w is not None:  # None: w = 0 (`exp_multiply`)
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


def _quadratic(element: AbstractLieGroup) -> AbstractQuadraticGroup:
    """`element`, for the inverse Cayley map (quadratic groups only)."""
    if not isinstance(element, AbstractQuadraticGroup):
        raise TypeError(f"the inverse Cayley map needs an element of a quadratic group, got {type(element).__name__}.")
    return element


def paper_semidirect_dcayley_inv(bundle: AbstractSemidirect, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
    """The §4.4 formula as printed: (dcay⁻¹_u x, y − ½([u,y] + [v,x]) − ¼[u,[x,v]]).

    Kept for comparison only: it is the inverse differential of the §4.4
    Cayley map on so(3) (both trivialisations), but not on so(n) for n ≥ 4,
    where the derivation through the product (4.16) does not hold.
    """
    (u, v), (x, y) = U, X
    br = bundle.base.bracket
    return bundle.quadratic_base.dcayley_inv(u, x), y - 0.5 * (br(u, y) + br(v, x)) - 0.25 * br(u, br(x, v))
