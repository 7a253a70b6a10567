"""Partitioned Runge–Kutta tableaus (paper §4.1, eq. (4.2), §5).

The first method advances the first component (ξ → u, the group part), the
second method the second component (η → v). A tableau validates itself: shapes,
row sums c = A·1, Σb = 1, and every order condition of the partitioned method
(one per bicoloured rooted tree) up to the declared order.
"""

import dataclasses
import functools
from fractions import Fraction as F

import diffrax
import numpy as np


@functools.cache
def bicoloured_trees(order: int) -> tuple:
    """All bicoloured rooted trees with `order` nodes, as canonical nested
    tuples (colour, (children...)) with children sorted."""
    if order == 1:
        return ((0, ()), (1, ()))
    out = []
    for colour in (0, 1):
        for forest in _forests(order - 1, None):
            out.append((colour, forest))
    return tuple(out)


@functools.cache
def monochrome_trees(order: int) -> tuple:
    """The rooted trees with `order` nodes, every node of colour 0 (the
    conditions of a Runge–Kutta method that is not partitioned)."""
    if order == 1:
        return ((0, ()),)
    return tuple((0, forest) for forest in _forests(order - 1, None, monochrome_trees))


@functools.cache
def _forests(size: int, max_tree, trees=bicoloured_trees) -> tuple:
    """Multisets of trees (from `trees`) of total `size`, as non-increasing
    tuples bounded by `max_tree`."""
    if size == 0:
        return ((),)
    out = []
    for first_size in range(1, size + 1):
        for tree in trees(first_size):
            if max_tree is not None and tree > max_tree:
                continue
            for rest in _forests(size - first_size, tree, trees):
                out.append((tree,) + rest)
    return tuple(out)


def _tree_order(tree) -> int:
    return 1 + sum(_tree_order(child) for child in tree[1])


def _gamma(tree) -> int:
    g = _tree_order(tree)
    for child in tree[1]:
        g *= _gamma(child)
    return g


def _internal_weight(tree, a):
    """ψ(t)_i = Π_children (A^{colour(child)} ψ(child))_i."""
    psi = np.ones(a[0].shape[0])
    for child in tree[1]:
        psi = psi * (a[child[0]] @ _internal_weight(child, a))
    return psi


@dataclasses.dataclass(frozen=True)
class PartitionedTableau:
    """Coefficients of a partitioned RK pair; the stage times are `c_first`
    (time is integrated as part of the first component, which keeps the order
    for non-autonomous fields)."""

    name: str
    a_first: np.ndarray
    b_first: np.ndarray
    c_first: np.ndarray
    a_second: np.ndarray
    b_second: np.ndarray
    c_second: np.ndarray
    order: int
    tolerance: float = 1e-12

    def __post_init__(self):
        for field in ("a_first", "b_first", "c_first", "a_second", "b_second", "c_second"):
            value = np.asarray(getattr(self, field), dtype=np.float64)
            value.setflags(write=False)
            object.__setattr__(self, field, value)
        if self.b_first.ndim != 1 or self.b_first.size == 0:
            raise ValueError(f"{self.name}: b_first must be a non-empty vector of weights, got shape {self.b_first.shape}.")
        s = self.b_first.shape[0]
        shapes = {"a_first": (s, s), "a_second": (s, s), "b_first": (s,), "b_second": (s,), "c_first": (s,), "c_second": (s,)}
        for field, shape in shapes.items():
            if getattr(self, field).shape != shape:
                raise ValueError(f"{self.name}: {field} has shape {getattr(self, field).shape}, expected {shape} for {s} stages.")
        if not isinstance(self.order, int) or self.order < 1:
            raise ValueError(f"{self.name}: order must be a positive int, got {self.order!r}.")
        tol = self.tolerance
        for which in ("first", "second"):
            a, b, c = (getattr(self, f"{x}_{which}") for x in "abc")
            if not np.allclose(a.sum(axis=1), c, rtol=0, atol=tol):
                raise ValueError(f"{self.name}: row sums of a_{which} {a.sum(axis=1)} differ from c_{which} {c}.")
            if abs(b.sum() - 1) > tol:
                raise ValueError(f"{self.name}: b_{which} sums to {b.sum()}, not 1.")
        failed = self.violated_conditions(self.order)
        if failed:
            raise ValueError(
                f"{self.name}: {len(failed)} order conditions up to order {self.order} fail, e.g. "
                f"tree {failed[0][0]} gives {failed[0][1]:.3e} instead of {failed[0][2]:.3e}."
            )

    @classmethod
    def unpartitioned(cls, name: str, a, b, c, order: int, tolerance: float = 1e-12) -> "PartitionedTableau":
        """One Runge–Kutta method (a, b, c) for both components: with it the
        PRKMK step is the RKMK method of Munthe-Kaas (BIT 38, 1998) on the
        bundle group."""
        return cls(name, a, b, c, a, b, c, order, tolerance)

    @classmethod
    def from_butcher(cls, name: str, tableau: diffrax.ButcherTableau, order: int) -> "PartitionedTableau":
        """The explicit method of a `diffrax.ButcherTableau` (`c`, `a_lower`,
        `b_sol`) for both components, without trailing stages that carry no
        weight and that no weighted stage reads (the first-same-as-last stage
        diffrax evaluates for its error estimate and interpolation)."""
        if tableau.a_diagonal is not None:
            raise ValueError(f"{name}: only explicit Butcher tableaus convert (this one has a diagonal).")
        stages = len(tableau.b_sol)
        a = np.zeros((stages, stages))
        for i, row in enumerate(tableau.a_lower):
            a[i + 1, : len(row)] = row
        b = np.asarray(tableau.b_sol, dtype=np.float64)
        c = np.concatenate([[0.0], np.asarray(tableau.c, dtype=np.float64)])
        kept = stages
        while kept > 1 and b[kept - 1] == 0 and not a[:kept, kept - 1].any():
            kept -= 1
        return cls.unpartitioned(name, a[:kept, :kept], b[:kept], c[:kept], order)

    @property
    def num_stages(self) -> int:
        return self.b_first.shape[0]

    @property
    def is_explicit(self) -> bool:
        """Whether both A matrices are strictly lower triangular: every stage
        reads only the stages before it."""
        return not (np.triu(self.a_first).any() or np.triu(self.a_second).any())

    @property
    def is_partitioned(self) -> bool:
        """Whether the two methods differ (otherwise one Runge–Kutta method
        advances both components)."""
        return not all(np.array_equal(getattr(self, f"{x}_first"), getattr(self, f"{x}_second")) for x in "abc")

    def violated_conditions(self, order: int) -> list:
        """(tree, b·ψ(t), 1/γ(t)) for each bicoloured tree of order ≤ `order`
        whose condition b^{colour(root)}·ψ(t) = 1/γ(t) fails. When the two
        methods are one, a tree's condition does not depend on its colours,
        so the trees of one colour suffice."""
        a = (self.a_first, self.a_second)
        b = (self.b_first, self.b_second)
        trees = bicoloured_trees if self.is_partitioned else monochrome_trees
        failed = []
        for n in range(1, order + 1):
            for tree in trees(n):
                value = b[tree[0]] @ _internal_weight(tree, a)
                target = 1.0 / _gamma(tree)
                if abs(value - target) > self.tolerance:
                    failed.append((tree, value, target))
        return failed

    def is_symplectic(self) -> bool:
        """b = b̂ and b_i â_ij + b̂_j a_ji − b_i b̂_j = 0 (symplectic PRK conditions)."""
        b, bh, a, ah = self.b_first, self.b_second, self.a_first, self.a_second
        cond = b[:, None] * ah + bh[None, :] * a.T - b[:, None] * bh[None, :]
        return bool(np.allclose(cond, 0, atol=self.tolerance))

    def swapped(self, name: str | None = None) -> "PartitionedTableau":
        """The pair with the two methods exchanged."""
        return PartitionedTableau(
            name or f"{self.name} (swapped)",
            self.a_second,
            self.b_second,
            self.c_second,
            self.a_first,
            self.b_first,
            self.c_first,
            self.order,
            self.tolerance,
        )

    def _arrays(self) -> tuple[np.ndarray, ...]:
        return (self.a_first, self.b_first, self.c_first, self.a_second, self.b_second, self.c_second)

    def __hash__(self):
        return hash((self.order, *(a.shape for a in self._arrays()), *(a.tobytes() for a in self._arrays())))

    def __eq__(self, other):
        """Equal where the coefficients and the order are: the same method
        whatever its name (one compiled program serves both, as the tableau
        is a static field of `PRKMK`)."""
        if not isinstance(other, PartitionedTableau):
            return NotImplemented
        return self.order == other.order and all(
            a.shape == b.shape and np.array_equal(a, b) for a, b in zip(self._arrays(), other._arrays())
        )


def _f(rows):
    return np.array([[float(F(x)) for x in row] for row in rows]) if isinstance(rows[0], list) else np.array([float(F(x)) for x in rows])


symplectic_euler = PartitionedTableau(
    "symplectic Euler (4.2)",
    a_first=_f([["1"]]),
    b_first=_f(["1"]),
    c_first=_f(["1"]),
    a_second=_f([["0"]]),
    b_second=_f(["1"]),
    c_second=_f(["0"]),
    order=1,
)
"""Eq. (4.2): implicit Euler on the first component, explicit on the second."""

symplectic_euler_adjoint = symplectic_euler.swapped("symplectic Euler, adjoint")
"""Explicit Euler on the first component, implicit on the second."""

stormer_verlet = PartitionedTableau(
    "Störmer–Verlet (Lobatto IIIA–IIIB)",
    a_first=_f([["0", "0"], ["1/2", "1/2"]]),
    b_first=_f(["1/2", "1/2"]),
    c_first=_f(["0", "1"]),
    a_second=_f([["1/2", "0"], ["1/2", "0"]]),
    b_second=_f(["1/2", "1/2"]),
    c_second=_f(["1/2", "1/2"]),
    order=2,
)
"""The §5 pair: 2-stage Lobatto IIIA on the first component, IIIB on the second
(IIIB's c is written as its row sums, as in the paper)."""

stormer_verlet_adjoint = stormer_verlet.swapped("Störmer–Verlet (Lobatto IIIB–IIIA)")
"""Lobatto IIIB on the first component, IIIA on the second."""

lobatto_iiia_iiib4 = PartitionedTableau(
    "Lobatto IIIA–IIIB, 3 stages",
    a_first=_f([["0", "0", "0"], ["5/24", "1/3", "-1/24"], ["1/6", "2/3", "1/6"]]),
    b_first=_f(["1/6", "2/3", "1/6"]),
    c_first=_f(["0", "1/2", "1"]),
    a_second=_f([["1/6", "-1/6", "0"], ["1/6", "1/3", "0"], ["1/6", "5/6", "0"]]),
    b_second=_f(["1/6", "2/3", "1/6"]),
    c_second=_f(["0", "1/2", "1"]),
    order=4,
)
"""3-stage Lobatto IIIA–IIIB pair, order 4, symplectic."""

_R5 = np.sqrt(5.0)
lobatto_iiia_iiib6 = PartitionedTableau(
    "Lobatto IIIA–IIIB, 4 stages",
    a_first=np.array(
        [
            [0.0, 0.0, 0.0, 0.0],
            [(11 + _R5) / 120, (25 - _R5) / 120, (25 - 13 * _R5) / 120, (-1 + _R5) / 120],
            [(11 - _R5) / 120, (25 + 13 * _R5) / 120, (25 + _R5) / 120, (-1 - _R5) / 120],
            [1 / 12, 5 / 12, 5 / 12, 1 / 12],
        ]
    ),
    b_first=np.array([1 / 12, 5 / 12, 5 / 12, 1 / 12]),
    c_first=np.array([0.0, (5 - _R5) / 10, (5 + _R5) / 10, 1.0]),
    a_second=np.array(
        [
            [1 / 12, (-1 - _R5) / 24, (-1 + _R5) / 24, 0.0],
            [1 / 12, (25 + _R5) / 120, (25 - 13 * _R5) / 120, 0.0],
            [1 / 12, (25 + 13 * _R5) / 120, (25 - _R5) / 120, 0.0],
            [1 / 12, (11 - _R5) / 24, (11 + _R5) / 24, 0.0],
        ]
    ),
    b_second=np.array([1 / 12, 5 / 12, 5 / 12, 1 / 12]),
    c_second=np.array([0.0, (5 - _R5) / 10, (5 + _R5) / 10, 1.0]),
    order=6,
)
"""4-stage Lobatto IIIA–IIIB pair, order 6, symplectic (Hairer, Lubich &
Wanner, Geometric Numerical Integration, §II.2.2 and §VI.4; the Lobatto
IIIA and IIIB coefficients of Hairer & Wanner, Solving ODEs II, §IV.5). Its
order conditions (every bicoloured tree up to order 6) are checked on
construction, like every tableau's."""

classical_rk4 = PartitionedTableau.unpartitioned(
    "classical Runge–Kutta 4",
    a=_f([["0", "0", "0", "0"], ["1/2", "0", "0", "0"], ["0", "1/2", "0", "0"], ["0", "0", "1", "0"]]),
    b=_f(["1/6", "1/3", "1/3", "1/6"]),
    c=_f(["0", "1/2", "1/2", "1"]),
    order=4,
)
"""The classical explicit method of order 4 on both components (RKMK 4).
Explicit, neither symplectic nor symmetric; the step stays on the group."""

dormand_prince_8 = PartitionedTableau.from_butcher("Dormand–Prince 8 (RKMK)", diffrax.Dopri8.tableau, order=8)
"""The explicit 13-stage method of order 8 of Prince & Dormand (J. Comput.
Appl. Math. 7, 1981), with the coefficients `diffrax.Dopri8` uses, on both
components: RKMK 8. Explicit, so its cost per step is fixed (no stage
iteration); neither symplectic nor symmetric, so the energy error grows
with time, but the step stays on the group (QᵀQ = I and coadjoint orbits
to round-off). With `Exp()` the dexp⁻¹ series keeps the terms up to ad⁶
(`_series.default_truncation`); `Cayley()` is exact and cheaper."""

ALL_TABLEAUS = (symplectic_euler, symplectic_euler_adjoint, stormer_verlet, stormer_verlet_adjoint, lobatto_iiia_iiib4, lobatto_iiia_iiib6)
"""The symplectic pairs."""

EXPLICIT_TABLEAUS = (classical_rk4, dormand_prince_8)
"""The explicit methods (RKMK)."""
