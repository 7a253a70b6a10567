"""Parts of a vector field whose flows are known in closed form, for the
exact-flow splitting methods (`splitting.Splitting`).

A scene that splits (`AbstractSplitScene`) writes its field as a sum of
parts f = f₁ + … + f_k and gives each part's exact flow. The rigid-body
scenes need two kinds:

* `AxisRotation`: the flow of one axis term ½Πᵢ²/Iᵢ of the kinetic energy.
  Along it Πᵢ, hence ωᵢ = Πᵢ/Iᵢ, is constant, and the state turns about the
  body axis eᵢ at the rate ωᵢ: on T*SO(3) this is y·exp(t(ωᵢeᵢ, 0)), the
  bundle group's own exponential (Q ↦ Q Rᵢ, Π ↦ Rᵢᵀ Π). With `Cayley`
  coordinates the rotation is cay(tωᵢeᵢ), turned by 2·atan(tωᵢ/2) instead of
  tωᵢ: not the exact flow, but a symmetric second-order one along the same
  orbit, which keeps everything the exact one keeps.
* `Shift`: rows moved by h times a rate read from other rows. The flow of a
  potential, or of an external torque at a frozen time, is one: the
  attitude stands still and the momentum moves by h times a torque that
  depends on the attitude (and time) only, y·exp((0, hτ)); so is a
  position's drift by its momentum, r ↦ r + hp/m.

Flows act on the state packed as one array with its components first
(`AbstractSplitScene.pack`): (d, *batch), each row one entry of the state,
contiguous over the batch: the layout XLA vectorises. A rotation's sine and
cosine are computed once (`groups.computed_once`) and read by every row it
turns; XLA fuses the rest of a step into few loops. In low precision a
rotation turns its rows by three shears (`PlanarTurn`), whose rounding does
not scale them; a `Splitting` step there moves the state's change instead
(`AbstractExactFlow.moved_change`) and adds it to the state once.
"""

import abc
import functools
from collections.abc import Callable
from typing import ClassVar, Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from ._bundles import BundleElement
from ._fields import AbstractFieldOnBundle
from .coordinates import AbstractCoordinates
from .groups._util import drifted, is_low_precision
from .groups.trig import computed_once

FreePart = Literal["axes", "exact"]
"""How a split rigid body's kinetic energy enters a splitting: its three axis
terms, each a rotation, or the free body's whole flow in closed form."""

Packed = Float[Array, "d *batch"]
"""A state packed with its components first: one row per entry (for T*SO(3):
Q row-major, then Π), any batch axes after."""


class PlanarTurn(NamedTuple):
    """A planar rotation by θ written as F·S(t)·K(s)·S(t): S(t) adds t times
    the second row of a pair to the first, K(s) subtracts s times the first
    from the second, F = ±1, t = tan(φ/2) and s = sin φ for the angle
    φ = θ (F = 1) or θ − π (F = −1) with |φ| ≤ π/2, so |t| ≤ 1 (`turn_of`).

    Each shear has determinant 1 whatever t and s are rounded to, so a
    rounded turn repeated at the same angle (a steady spin) keeps the
    rows on an ellipse near the circle. The matrix [[c, s], [−s, c]] with
    rounded sine and cosine scales the rows by √(c² + s²) ≠ 1 instead, much
    the same factor at every step of a slow or steady motion: in float32 the
    norms drift in proportion to the number of steps. The flows turn by
    shears in low precision only (`AxisRotation.moved`); in float64 that
    drift is far below a run's other errors and the matrix, which XLA
    fuses with less work, stays."""

    half_tangent: Array
    sine: Array
    sign: Array


def turn_of(sine: Array, cosine: Array) -> PlanarTurn:
    """The `PlanarTurn` of the rotation with this sine and cosine: for
    cos θ ≥ 0, tan(θ/2) = sin θ/(1 + cos θ); otherwise the turn by θ − π,
    tan = −sin θ/(1 − cos θ), and F = −1. The denominator is 1 + |cos θ|
    either way, at least 1."""
    sign = jnp.where(cosine >= 0, 1.0, -1.0).astype(jnp.result_type(sine))
    # Computed once: every row the turn moves reads all three.
    return computed_once(PlanarTurn(sign * sine / (1 + jnp.abs(cosine)), sign * sine, sign))


def turned_rows(z: Packed, pairs: tuple[tuple[int, int], ...], turn: PlanarTurn) -> Packed:
    """z with each pair of rows (j, k) turned in its plane, (z_j, z_k) ↦
    (c z_j + s z_k, c z_k − s z_j), by the shears of `turn`; the whole array
    rebuilt."""
    t, s, sign = turn
    rows = list(z)
    for j, k in pairs:
        a = rows[j] + t * rows[k]
        b = rows[k] - s * a
        rows[j], rows[k] = sign * (a + t * b), sign * b
    return jnp.stack(rows)


def rotated_rows(z: Packed, pairs: tuple[tuple[int, int], ...], sine: Array, cosine: Array) -> Packed:
    """z with each pair of rows (j, k) turned in its plane: (z_j, z_k) ↦
    (c z_j + s z_k, −s z_j + c z_k), the whole array rebuilt."""
    rows = list(z)
    for j, k in pairs:
        a, b = rows[j], rows[k]
        rows[j], rows[k] = cosine * a + sine * b, cosine * b - sine * a
    return jnp.stack(rows)


def _pair_tables(z: Packed, pairs: tuple[tuple[int, int], ...]):
    """For the rows of z turned in pairs: each row's partner (itself if
    unmoved), the sign its partner enters with (+1 for the first of a pair,
    −1 for the second, 0 unmoved) and whether it moves, the last two shaped
    to broadcast against z."""
    partner, sign = np.arange(z.shape[0]), np.zeros(z.shape[0])
    for j, k in pairs:
        partner[j], partner[k], sign[j], sign[k] = k, j, 1.0, -1.0
    shape = (z.shape[0],) + (1,) * (z.ndim - 1)
    return partner, sign.reshape(shape), (sign != 0).reshape(shape)


def rotated_array(z: Packed, pairs: tuple[tuple[int, int], ...], sine: Array, cosine: Array) -> Packed:
    """`rotated_rows` as whole-array arithmetic: z·c + (±s)·z[partner] on the
    moved rows, z on the others. The same values, which XLA computes as one
    array. Rows written out one by one become one small computation per row
    where several consumers read them, as in `Splitting.reverse_step`."""
    partner, sign, moved = _pair_tables(z, pairs)
    scale = jnp.where(moved, cosine, jnp.ones_like(cosine))
    # The partners are in range: "clip" reads them as they are, where the
    # default mode would mask every element against an out-of-range index.
    return scale * z + (sign * sine) * jnp.take(z, partner, axis=0, mode="clip")


class AbstractExactFlow(eqx.Module):
    """One part of a split vector field and its flow."""

    @property
    @abc.abstractmethod
    def reads_unmoved_rows_only(self) -> bool:
        """Whether `coefficients` reads only rows of z that the flow leaves
        unchanged (then not only its value but its derivative is the same at
        the flow's start and end, and `Splitting.reverse_step` evaluates it
        once)."""

    always_materialised: eqx.AbstractClassVar[bool]
    """Whether `Splitting` has XLA compute this flow's result once: a flow
    of cheap arithmetic alone would otherwise be recomputed inside each
    later sub-step that reads it."""

    @abc.abstractmethod
    def coefficients(self, coordinates: AbstractCoordinates, t: Array, z: Packed, h: Array, args: PyTree) -> PyTree:
        """What the flow over time `h` (either sign) does to `z`, the part
        evaluated at time `t` (a part that depends on time is frozen there).
        Its value must be the same at the flow's start
        and at its end (computed from what the flow conserves), so that a
        sub-step can be undone from its end (`Splitting.reverse_step`)."""

    @abc.abstractmethod
    def moved(self, z: Packed, coefficients: PyTree) -> Packed:
        """`z` moved by the flow that `coefficients` describe."""

    @abc.abstractmethod
    def moved_change(self, start: Packed, change: Packed, coefficients: PyTree) -> Packed:
        """The state start + `change` moved, written as its change from
        `start`: `change` plus what the flow adds, computed so that it is
        rounded relative to what the flow adds, not to the state. A
        low-precision `Splitting` step runs its flows this way and adds the
        whole change to the state once."""

    @abc.abstractmethod
    def moved_back(self, z: Packed, coefficients: PyTree) -> Packed:
        """The inverse of `moved` for the same coefficients."""

    @abc.abstractmethod
    def pulled_back(self, z: Packed, coefficients: PyTree, cotangent: Packed) -> tuple[Packed, PyTree]:
        """The VJP of `moved` at (z, coefficients): the cotangents of z and of
        the coefficients for a cotangent of the moved state."""

    def flow(self, coordinates: AbstractCoordinates, t: Array, z: Packed, h: Array, args: PyTree) -> Packed:
        """The state `z` moved by the part's flow over time `h` (either sign),
        the part evaluated at time `t`."""
        return self.moved(z, self.coefficients(coordinates, t, z, h, args))

    def flow_change(self, coordinates: AbstractCoordinates, t: Array, start: Packed, change: Packed, h: Array, args: PyTree) -> Packed:
        """`flow` of start + `change`, as `moved_change`."""
        return self.moved_change(start, change, self.coefficients(coordinates, t, start + change, h, args))


class AxisRotation(AbstractExactFlow):
    """The flow of one axis term of a kinetic energy: every pair of rows in
    `pairs` turns by the angle θ = h·`rate`(z, args), which this flow leaves
    constant (so the flow is exact for `Exp`, see the module docstring), and
    every pair in `half_pairs` by θ/2 (a unit quaternion's components)."""

    always_materialised: ClassVar[bool] = False  # pyright: ignore[reportIncompatibleVariableOverride]  # its sine and cosine are computed once
    axis: int = eqx.field(static=True)
    """The body axis, 0, 1 or 2."""
    pairs: tuple[tuple[int, int], ...] = eqx.field(static=True)
    """Row pairs (j, k) of the packed state that turn: the attitude's columns
    about `axis` and the momentum's components."""
    rate: Callable[[Packed, PyTree], Array]
    """(z, args) ↦ the angular rate about `axis`, shape (*batch,)."""
    rate_reads_turned_rows: bool = eqx.field(static=True, default=False)
    """Whether `rate` reads rows in `pairs` (its value is still constant
    along the flow, as for a body whose rate is a component of QᵀP − PᵀQ)."""
    half_pairs: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())
    """Row pairs that turn by half the angle: a unit quaternion q ↦ q·r, r
    = cos θ/2 + sin θ/2·e, turns (q_axis, w) and the other two components
    so (`body_frame`)."""

    @property
    def reads_unmoved_rows_only(self) -> bool:
        return not self.rate_reads_turned_rows

    def __check_init__(self):
        if self.axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1 or 2, got {self.axis!r}.")

    def coefficients(self, coordinates, t, z, h, args):
        """(sin, cos) of the planar rotation that the coordinate map gives the
        angle h·rate about the axis (`AbstractCoordinates.planar_rotation`):
        the exponential turns by that angle, the Cayley map by 2·atan(angle/2).
        With `half_pairs`, (sin, cos, sin θ/2, cos θ/2): the half turn's from
        the map (`planar_half_rotation`), the whole turn's from it by the
        double angle, so that a sub-step evaluates one sine and cosine.
        (Evaluated apart, the whole turn would be the matrix's bit for bit:
        a second evaluation each sub-step, and no more accurate.)"""
        angle = h * self.rate(z, args)
        if not self.half_pairs:
            return coordinates.planar_rotation(angle)
        half_sine, half_cosine = coordinates.planar_half_rotation(angle)
        sine, cosine = computed_once(2 * half_sine * half_cosine, (half_cosine - half_sine) * (half_cosine + half_sine))
        return sine, cosine, half_sine, half_cosine

    def _turns(self, coefficients) -> tuple[tuple[tuple[tuple[int, int], ...], Array, Array], ...]:
        """(pairs, sine, cosine) for the whole turn and, with `half_pairs`, the half turn."""
        turns = ((self.pairs, coefficients[0], coefficients[1]),)
        return turns + (((self.half_pairs, coefficients[2], coefficients[3]),) if self.half_pairs else ())

    def moved(self, z, coefficients):
        for pairs, sine, cosine in self._turns(coefficients):
            if is_low_precision(z.dtype):
                # Rounded, the matrix scales the rows by √(c² + s²) ≠ 1, much the
                # same factor step after step (`PlanarTurn`); the shears do not.
                z = turned_rows(z, pairs, turn_of(sine, cosine))
            else:
                z = rotated_rows(z, pairs, sine, cosine)
        return z

    def moved_change(self, start, change, coefficients):
        # (x, y) ↦ (x + (c − 1)x + s y, y + (c − 1)y − s x), with c − 1 =
        # −s²/(1 + c) where the cosine is near 1 and c − 1 itself elsewhere.
        rows = list(change)
        for pairs, sine, cosine in self._turns(coefficients):
            cosine_less_one = computed_once(jnp.where(cosine >= 0, -sine * sine / (1 + jnp.abs(cosine)), cosine - 1))
            for j, k in pairs:
                x, y = start[j] + change[j], start[k] + change[k]
                rows[j], rows[k] = change[j] + (cosine_less_one * x + sine * y), change[k] + (cosine_less_one * y - sine * x)
        return jnp.stack(rows)

    def moved_back(self, z, coefficients):
        for pairs, sine, cosine in self._turns(coefficients):
            z = rotated_array(z, pairs, -sine, cosine)
        return z

    def pulled_back(self, z, coefficients, cotangent):
        # (a, b) ↦ (c a + s b, c b − s a) is a rotation: its transpose is the
        # inverse, and its derivatives in s and c read the rows it turns.
        # The turns move disjoint rows, so each reads and undoes its own rows.
        # The coefficients' cotangents are sums over the turned pairs, written
        # out and computed once: a reduction over the rows runs as a loop of
        # its own per coefficient, slower than the rest of the sub-step.
        cotangent_coefficients = []
        for pairs, sine, cosine in self._turns(coefficients):
            cotangent_sine = sum(cotangent[j] * z[k] - cotangent[k] * z[j] for j, k in pairs)
            cotangent_cosine = sum(cotangent[j] * z[j] + cotangent[k] * z[k] for j, k in pairs)
            cotangent_coefficients += computed_once(cotangent_sine, cotangent_cosine)
            cotangent = rotated_array(cotangent, pairs, -sine, cosine)
        return cotangent, tuple(cotangent_coefficients)


class Shift(AbstractExactFlow):
    """The flow of a part that moves some rows at a rate read from the
    others: rows `rows` of z grow by h·`rate`(t, z, args). A momentum kick
    (the rate a torque or force of the attitude and position) and a drift
    (the rate a velocity p/m) are such flows."""

    always_materialised: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    rows: tuple[int, ...] = eqx.field(static=True)
    """The rows that move, in the packed state."""
    rate: Callable[[Array, Packed, PyTree], Array]
    """(t, z, args) ↦ the rows' rate of change, shape (len(rows), *batch); it
    must not read the rows it moves."""

    @property
    def reads_unmoved_rows_only(self) -> bool:
        return True  # `rate` must not read the rows it moves

    def coefficients(self, coordinates, t, z, h, args):
        """The change of the rows, h·rate, shape (len(rows), *batch)."""
        return h * self.rate(t, z, args)

    def moved(self, z, coefficients):
        return self._with_rows_changed(z, coefficients)

    def moved_change(self, start, change, coefficients):
        return self._with_rows_changed(change, coefficients)

    def moved_back(self, z, coefficients):
        return self._with_rows_changed(z, -coefficients)

    def pulled_back(self, z, coefficients, cotangent):
        return cotangent, jnp.stack([cotangent[row] for row in self.rows])

    def _with_rows_changed(self, z, change):
        rows = {row: z[row] + change[k] for k, row in enumerate(self.rows)}
        return jnp.stack([rows.get(r, z[r]) for r in range(z.shape[0])])


class AbstractSplitScene(AbstractFieldOnBundle):
    """A scene whose field is a sum of parts with exact flows: what a
    `Splitting` method needs of it."""

    @abc.abstractmethod
    def exact_flows(self, args: PyTree, /, free_part: FreePart = "axes") -> tuple[AbstractExactFlow, ...]:
        """The parts, outermost first: `Splitting` runs them as the palindrome
        f₁(h/2) … f_{k−1}(h/2) f_k(h) f_{k−1}(h/2) … f₁(h/2). `free_part`
        says how a rigid body's kinetic energy enters: as its three axis
        terms ("axes"), or as one part, the free body's flow in closed form
        ("exact"). Raises `ValueError` at trace time where `args` admit no
        such split (say, an inertia tensor that is not diagonal) or the
        scene has no such part."""

    @abc.abstractmethod
    def pack(self, y: BundleElement, args: PyTree, /) -> Packed:
        """The state as one array, components first (see `Packed`), in the
        frame the parts of `exact_flows(args)` are written in: a relabelling
        of the state's entries, so that what a low-precision step's sum lost
        unpacks as the state does (`Step.rounding`)."""

    @abc.abstractmethod
    def unpack(self, z: Packed, like: BundleElement, args: PyTree, /) -> BundleElement:
        """Inverse of `pack`; `like` is a state of the same structure."""

    @abc.abstractmethod
    def onto_group(self, z: Packed, /) -> Packed:
        """The packed state moved back onto the group where rounding has
        taken it off (a rotation matrix by `renormalized_rotations`, a unit
        quaternion towards norm 1), by a step whose derivative is that of
        the projection: what `Splitting` applies after each low-precision step."""


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def renormalized_rotations(z: Packed, first_rows: tuple[int, ...]) -> Packed:
    """z with each 3×3 matrix packed row-major from a row in `first_rows`
    taken one Björck step towards SO(3), Q ↦ Q + ½Q(I − QᵀQ)
    (`groups._util.bjorck_step`), where its max|QᵀQ − I| is past a few ulps
    (`groups._util.drifted`, as `SO3.renormalized`), written on the rows:
    elementwise over the batch, so it fuses with the step instead of running
    as batched 3×3 products. Relabelling the columns commutes with it. Its
    derivative is the Björck step's, the correction taken or not (as
    `groups._util.bjorck_step_where_drifted`)."""
    return _bjorck_rows(z, first_rows, only_where_drifted=True)


@renormalized_rotations.defjvp
def _renormalized_rotations_jvp(first_rows, primals, tangents):
    (z,), (z_dot,) = primals, tangents
    _, out_dot = jax.jvp(lambda z: _bjorck_rows(z, first_rows, only_where_drifted=False), (z,), (z_dot,))
    return renormalized_rotations(z, first_rows), out_dot


def _bjorck_rows(z: Packed, first_rows: tuple[int, ...], only_where_drifted: bool) -> Packed:
    """The Björck step of `renormalized_rotations` on the rows, on every
    matrix or (`only_where_drifted`) on those past a few ulps."""
    rows = list(z)
    for first in first_rows:
        q = [[rows[first + 3 * r + c] for c in range(3)] for r in range(3)]
        gram = [[sum(q[k][i] * q[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        defect = functools.reduce(jnp.maximum, [jnp.abs(gram[i][j] - (i == j)) for i in range(3) for j in range(3)])
        correct = drifted(defect)
        for r in range(3):
            for c in range(3):
                corrected = 1.5 * q[r][c] - 0.5 * sum(q[r][k] * gram[k][c] for k in range(3))
                rows[first + 3 * r + c] = jnp.where(correct, corrected, q[r][c]) if only_where_drifted else corrected
    return jnp.stack(rows)


class AbstractSolvedScene(AbstractFieldOnBundle):
    """A scene whose whole flow is known in closed form: what an `ExactFlow`
    method needs of it."""

    @abc.abstractmethod
    def solved_flow(self, t: Array, y: BundleElement, h: Array, args: PyTree, /) -> BundleElement:
        """The state a time h after the state y at time t, exactly (to the
        round-off of the closed form), for any h of either sign. Raises
        `ValueError` at trace time where `args` admit no closed form."""
