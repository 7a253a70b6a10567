"""The rigid body's frame for the exact-flow splittings: the state (Q, Π)
packed components first in the body axes ordered by inertia, and the axis
rotations ½Πᵢ²/Iᵢ of the kinetic energy on it. SO(3)-specific; the generic
exact flows (`AxisRotation`, `Shift`) are in `prkmk_jax.exact_flows`.

The attitude is packed as its representation stores it: a rotation matrix
row-major (rows 0–8, Π in rows 9–11), or a unit quaternion (w, x, y, z)
(rows 0–3, Π in rows 4–6). An axis term turns the matrix's two other
columns by θ, and the quaternion's pairs (q_axis, w) and (q_j, q_k) by θ/2
(q ↦ q·(cos θ/2 + sin θ/2·e_axis))."""

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._bundles import BundleElement
from ..exact_flows import AxisRotation, Packed, Shift, renormalized_rotations
from ..groups.base import AbstractLieGroup
from ..groups.quaternion import UnitQuaternion
from ..groups.so3 import SO3


class InertiaOrderedFrame(eqx.Module):
    """The body axes relabelled by increasing moment of inertia: virtual axis
    a is body axis σ(a), σ = argsort(moments).

    The splittings are written in this frame, with the axis terms in the order
    of the virtual axes (0 outermost, 2 in the middle with the full step): the
    axis of smallest inertia (fastest rotation) outermost and the axis of
    largest inertia in the middle gave the smallest error of the six orders
    on the free body and the heavy top (`docs/design-notes.md`). Moments that vary over a batch give each trajectory its own σ.
    An odd σ makes the virtual frame left-handed: a rotation there turns
    the other way (`parity`), and a cross product changes sign."""

    order: Array
    """σ, shape (*batch, 3), int."""
    parity: Array
    """+1 where σ is even (a cyclic shift), −1 where it is odd; (*batch,)."""

    @classmethod
    def of(cls, moments: Array) -> "InertiaOrderedFrame":
        order = jnp.argsort(moments, axis=-1, stable=True)
        s0, s1, s2 = order[..., 0], order[..., 1], order[..., 2]
        parity = jnp.sign((s1 - s0) * (s2 - s0) * (s2 - s1)).astype(moments.dtype)
        return cls(order, parity)

    def vector(self, v: Array) -> Array:
        """v[σ] along the last axis: a body vector's components in this frame."""
        return jnp.take_along_axis(v, jnp.broadcast_to(self.order, jnp.shape(v)[:-1] + (3,)), axis=-1)

    def _rows(self, num_rows: int, matrix_rows: tuple[int, ...], vector_rows: tuple[int, ...]) -> Array:
        """For each row of the relabelled state, the row of z it comes from:
        shape (num_rows, *batch) for `order` of shape (*batch, 3). Written as
        one elementwise expression in σ, so XLA computes it in one loop."""
        blocks = [first + 3 * r for first in matrix_rows for r in range(3)] + list(vector_rows)
        base = np.arange(num_rows)
        picks = np.zeros((3, num_rows), base.dtype)  # picks[a, i] = 1: row i reads the block's σ(a)
        for first in blocks:
            base[first : first + 3] = first
            picks[np.arange(3), first + np.arange(3)] = 1
        sources = base + sum(picks[a] * self.order[..., a, None] for a in range(3))
        return jnp.moveaxis(jnp.asarray(sources, self.order.dtype), -1, 0)

    def _inverse(self) -> "InertiaOrderedFrame":
        """The frame of σ⁻¹ (σ⁻¹(b) = the a with σ(a) = b), by arithmetic."""
        inverse = sum(a * (self.order[..., a, None] == jnp.arange(3)) for a in range(3))
        return InertiaOrderedFrame(jnp.asarray(inverse, self.order.dtype), self.parity)

    def relabel(self, z: Packed, matrix_rows: tuple[int, ...], vector_rows: tuple[int, ...]) -> Packed:
        """z with the columns of its matrices and the components of its
        vectors in this frame."""
        return _rows_taken(z, self._rows(z.shape[0], matrix_rows, vector_rows))

    def restore(self, z: Packed, matrix_rows: tuple[int, ...], vector_rows: tuple[int, ...]) -> Packed:
        """Inverse of `relabel`: the relabelling by σ⁻¹."""
        return self._inverse().relabel(z, matrix_rows, vector_rows)


def _rows_taken(z: Packed, sources: Array) -> Packed:
    """z's rows permuted: row i of the result is row `sources[i]` of z, where
    `sources` has shape (d,), one permutation for every trajectory (then
    whole rows move), or (d, *batch), one per trajectory."""
    if sources.ndim == 1:
        return jnp.take(z, sources, axis=0, mode="clip")
    return jnp.take_along_axis(z, jnp.broadcast_to(sources, z.shape), axis=0, mode="clip")


def packed_rotation_and_vector(y: BundleElement) -> Packed:
    """(Q row-major, v) of a state on SO(3) with a 3-vector fiber, components first."""
    if not isinstance(y.base, SO3):
        raise TypeError(f"this scene's state lives on SO3, got a {type(y.base).__name__} base.")
    q, v = y.base.matrix, y.fiber
    flat = jnp.concatenate([q.reshape(*q.shape[:-2], 9), v], axis=-1)
    return jnp.moveaxis(flat, -1, 0)


def unpacked_rotation_and_vector(z: Packed, like: BundleElement | None = None) -> BundleElement:
    """Inverse of `packed_rotation_and_vector`."""
    flat = jnp.moveaxis(z, 0, -1)
    del like  # every such state has the same structure
    return BundleElement(SO3(flat[..., :9].reshape(*flat.shape[:-1], 3, 3)), flat[..., 9:])


Attitude = type[AbstractLieGroup]
"""How a packed body state holds the attitude: `SO3` (a matrix) or `UnitQuaternion`."""


def body_rows(attitude: Attitude) -> int:
    """How many rows a body state packed with `attitude` holds: the attitude
    (9 for a matrix, 4 for a quaternion), then Π's three."""
    return 7 if attitude is UnitQuaternion else 12


def momentum_kick(attitude: Attitude, torque) -> Shift:
    """The kick Π ↦ Π + h·`torque`(t, z, args) on a body state packed with
    `attitude` (Π in its last three rows, `body_rows`)."""
    last = body_rows(attitude)
    return Shift((last - 3, last - 2, last - 1), torque)


def packed_in_frame(y: BundleElement, frame: InertiaOrderedFrame) -> Packed:
    """A state (Q, Π) packed components first in `frame`: its matrix's
    columns and Π's components relabelled, or for a quaternion its vector
    part's and Π's, with w times the frame's parity: then each pair of an
    axis term turns by the same angle whatever the frame's handedness
    (`body_axis_rotations`)."""
    if not isinstance(y.base, UnitQuaternion):
        return frame.relabel(packed_rotation_and_vector(y), (0,), (9,))
    flat = jnp.moveaxis(jnp.concatenate([y.base.wxyz, y.fiber], axis=-1), -1, 0)
    z = frame.relabel(flat, (), (1, 4))
    return z.at[0].multiply(frame.parity)


def unpacked_from_frame(z: Packed, attitude: Attitude, frame: InertiaOrderedFrame) -> BundleElement:
    """Inverse of `packed_in_frame` for a state whose attitude is `attitude`."""
    if attitude is not UnitQuaternion:
        return unpacked_rotation_and_vector(frame.restore(z, (0,), (9,)))
    flat = jnp.moveaxis(frame.restore(z.at[0].multiply(frame.parity), (), (1, 4)), 0, -1)
    return BundleElement(UnitQuaternion(flat[..., :4]), flat[..., 4:])


def packed_body_state(y: BundleElement, moments: Array) -> Packed:
    """A state (Q, Π) on T*SO(3) packed components-first in the frame of the
    axes ordered by `moments` (`InertiaOrderedFrame`, `packed_in_frame`)."""
    return packed_in_frame(y, InertiaOrderedFrame.of(moments))


def unpacked_body_state(z: Packed, like: BundleElement, moments: Array) -> BundleElement:
    """Inverse of `packed_body_state`; `like` is a state of the same structure."""
    return unpacked_from_frame(z, type(like.base), InertiaOrderedFrame.of(moments))


def body_axis_rotations(frame: InertiaOrderedFrame, moments: Array, attitude: Attitude) -> tuple[AxisRotation, ...]:
    """The axis terms ½Πᵢ²/Iᵢ of a rigid body's kinetic energy on a body
    state packed in `frame` (`packed_in_frame`), in the order of the
    frame's axes."""
    if attitude is UnitQuaternion:
        return axis_rotations(frame, moments, momentum_row=4, quaternion_row=0)
    return axis_rotations(frame, moments, momentum_row=9, matrix_rows=(0,))


def body_vertical(z: Packed, frame: InertiaOrderedFrame, attitude: Attitude) -> list[Array]:
    """Γ = Qᵀe₃ in `frame`'s components, three rows of shape (*batch,), on
    a state packed with `attitude`: the matrix's last row (rows 6–8), or
    from the quaternion Γ = e − 2w(v × e) + 2v × (v × e), e = e₃ in the
    frame (a relabelling multiplies each cross product by the parity, and
    w is packed times it)."""
    if attitude is not UnitQuaternion:
        return [z[6], z[7], z[8]]
    w, v = z[0], [z[1], z[2], z[3]]
    e = [(frame.order[..., a] == 2).astype(z.dtype) for a in range(3)]

    def cross(a, b):
        return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]

    v_e = cross(v, e)
    v_v_e = cross(v, v_e)
    return [e[a] - 2 * w * v_e[a] + 2 * v_v_e[a] for a in range(3)]


def renormalized_body_state(z: Packed, attitude: Attitude) -> Packed:
    """z with its attitude moved back onto the group after a low-precision
    step: one Björck step of the matrix (`renormalized_rotations`), or the
    quaternion's Newton step towards norm 1 (`UnitQuaternion.renormalized`),
    each where it has drifted past a few ulps."""
    if attitude is not UnitQuaternion:
        return renormalized_rotations(z, (0,))
    q = UnitQuaternion(jnp.moveaxis(z[:4], 0, -1)).renormalized().wxyz
    return jnp.concatenate([jnp.moveaxis(q, -1, 0), z[4:]])


def axis_rotations(
    frame: InertiaOrderedFrame, moments: Array, momentum_row: int, matrix_rows: tuple[int, ...] = (), quaternion_row: int | None = None
) -> tuple[AxisRotation, ...]:
    """The axis terms ½Πᵢ²/Iᵢ of a rigid body's kinetic energy on the state
    packed in `frame` (`InertiaOrderedFrame.relabel`), in the order of the
    frame's axes: rows `momentum_row` + (0, 1, 2) hold Π, each 3×3 matrix
    packed from a row in `matrix_rows` turns with the body (its columns),
    and a unit quaternion packed from `quaternion_row` as (parity·w, v)
    (`packed_in_frame`) turns with it by half the angle: q·(cos θ/2 +
    sin θ/2·e_axis) turns (q_axis, w) and (q_j, q_k) by θ/2, and with w
    times the parity both turn by the same signed angle in a left-handed
    frame too."""
    ordered = frame.vector(moments)

    def rotation(axis):
        pairs = sum((column_pairs(axis, first) for first in matrix_rows), ()) + vector_pair(axis, momentum_row)
        half_pairs = ()
        if quaternion_row is not None:
            w, j, k = quaternion_row, (axis + 1) % 3, (axis + 2) % 3
            half_pairs = ((w + 1 + axis, w), (w + 1 + j, w + 1 + k))

        def rate(z, args):
            return frame.parity * z[momentum_row + axis] / ordered[..., axis]

        return AxisRotation(axis, pairs, rate, half_pairs=half_pairs)

    return tuple(rotation(axis) for axis in range(3))


def column_pairs(axis: int, first_row: int = 0) -> tuple[tuple[int, int], ...]:
    """The row pairs of a row-major 3×3 matrix packed from `first_row` whose
    columns (j, k) = (axis + 1, axis + 2) mod 3 turn under M ↦ M·Rₐₓᵢₛ."""
    j, k = (axis + 1) % 3, (axis + 2) % 3
    return tuple((first_row + 3 * r + j, first_row + 3 * r + k) for r in range(3))


def vector_pair(axis: int, first_row: int) -> tuple[tuple[int, int], ...]:
    """The row pair of a 3-vector packed from `first_row` that turns under
    v ↦ Rₐₓᵢₛᵀ v."""
    return (((first_row + (axis + 1) % 3), (first_row + (axis + 2) % 3)),)


def principal_moments(inertia: Any, scene: str, batched: bool = False, closed_form: bool = False) -> Array:
    """`inertia` as principal moments (3,), or (*batch, 3) where `batched`:
    a split into axis terms, or the closed-form flow (`closed_form`), needs
    the body axes to be principal (a diagonal inertia)."""
    shape = jnp.shape(inertia)
    if not (shape == (3,) or (batched and len(shape) > 1 and shape[-1] == 3)):
        what = "the closed-form flow" if closed_form else "the split into axis rotations"
        raise ValueError(
            f"{scene}: {what} needs the principal moments of inertia, shape (3,), got shape {shape}; "
            "for a full inertia tensor use a PRKMK method, or rotate the body frame to the principal axes."
        )
    return jnp.asarray(inertia)
