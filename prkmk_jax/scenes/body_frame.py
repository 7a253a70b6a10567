"""The rigid body's frame for the exact-flow splittings: the state (Q, Π)
packed components first in the body axes ordered by inertia, and the axis
rotations ½Πᵢ²/Iᵢ of the kinetic energy on it. SO(3)-specific; the generic
exact flows (`AxisRotation`, `MomentumKick`) are in `prkmk_jax.exact_flows`."""

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._bundles import BundleElement
from ..exact_flows import AxisRotation, Packed
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


def axis_rotations(frame: InertiaOrderedFrame, moments: Array, momentum_row: int, matrix_rows: tuple[int, ...]) -> tuple[AxisRotation, ...]:
    """The axis terms ½Πᵢ²/Iᵢ of a rigid body's kinetic energy on the state
    packed in `frame` (`InertiaOrderedFrame.relabel`), in the order of the
    frame's axes: rows `momentum_row` + (0, 1, 2) hold Π, and each 3×3 matrix
    packed from a row in `matrix_rows` turns with the body (its columns)."""
    ordered = frame.vector(moments)

    def rotation(axis):
        pairs = sum((column_pairs(axis, first) for first in matrix_rows), ()) + vector_pair(axis, momentum_row)
        return AxisRotation(axis, pairs, lambda z, args: frame.parity * z[momentum_row + axis] / ordered[..., axis])

    return tuple(rotation(axis) for axis in range(3))


def packed_body_state(y: BundleElement, moments: Array) -> Packed:
    """A state (Q, Π) on T*SO(3) packed components-first in the frame of the
    axes ordered by `moments` (`InertiaOrderedFrame`)."""
    return InertiaOrderedFrame.of(moments).relabel(packed_rotation_and_vector(y), (0,), (9,))


def unpacked_body_state(z: Packed, like: BundleElement, moments: Array) -> BundleElement:
    """Inverse of `packed_body_state`."""
    return unpacked_rotation_and_vector(InertiaOrderedFrame.of(moments).restore(z, (0,), (9,)), like)


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
