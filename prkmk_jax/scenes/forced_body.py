"""A rigid body driven by a time-dependent control torque, on T*SO(3).

    Q' = QΩ̂,   Π' = Π × Ω + τ(t),   Ω = I⁻¹Π,

with τ(t) a body-frame torque given by a torque law τ(t, params). The field
is non-autonomous and nothing is conserved but QᵀQ = I; the energy follows
the balance dH/dt = Ω·τ (`power`), so H(T) − H(0) is the work the torque
did. On the left-trivialised cotangent bundle, body form, the generator is
(Ω, τ(t)).
"""

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .. import diagnostics, exact_flows
from .._bundles import AbstractBundle, BundleElement
from .._fields import Time
from . import body_frame
from .base import AbstractBodyOnTStarSO3, checked_moments, checked_parameters, rotation_matrix
from .free_flow import FreeBodyFlow


class HarmonicTorque(eqx.Module):
    """τ(t)_k = a_k sin(ω_k t + φ_k): the parameters of `harmonic_torque`."""

    amplitude: Float[Array, "3"]
    frequency: Float[Array, "3"]
    phase: Float[Array, "3"]


def harmonic_torque(t: Time, params: HarmonicTorque) -> Float[Array, "3"]:
    """The default torque law, body frame."""
    return params.amplitude * jnp.sin(params.frequency * t + params.phase)


class ForcedParameters(eqx.Module):
    """`args` of a `ForcedRigidBody`."""

    inertia: Float[Array, "3"]
    """Principal moments of inertia."""
    torque: PyTree
    """The torque law's parameters (differentiable, e.g. for fitting)."""

    def __post_init__(self):
        self.inertia = checked_moments("ForcedParameters.inertia", self.inertia)


class ForcedRigidBody(AbstractBodyOnTStarSO3, exact_flows.AbstractSplitScene):
    """The rigid body with a control torque on `Cotangent(SO3)`, body form;
    `args` is `ForcedParameters`. `torque_law(t, params)` returns the
    body-frame torque (default `harmonic_torque`).

    It splits (`splitting()`) into the torque's kick Π ↦ Π + hτ(t), at the
    time frozen (outermost), and the three axis terms of the kinetic energy;
    the clock runs in the middle part (`splitting` module), so the split
    holds for any torque law of time."""

    torque_law: Callable[[Time, PyTree], Float[Array, "3"]] = eqx.field(static=True, default=harmonic_torque)

    def __check_init__(self):
        if isinstance(self.torque_law, AbstractBundle):
            raise TypeError(
                f"ForcedRigidBody lives on Cotangent(SO3) only; its one argument is the torque law (t, params) -> torque, "
                f"got the bundle {self.torque_law!r}."
            )
        if not callable(self.torque_law):
            raise TypeError(f"ForcedRigidBody's torque_law must be a function (t, params) -> body torque, got {self.torque_law!r}.")

    def checked_args(self, args: ForcedParameters) -> ForcedParameters:
        """`ForcedParameters` with principal moments (…, 3), each > 0."""
        args = checked_parameters("ForcedRigidBody", args, ForcedParameters)
        return ForcedParameters(args.inertia, args.torque)

    def __call__(self, t, y: BundleElement, args: ForcedParameters):
        checked_parameters("ForcedRigidBody", args, ForcedParameters)  # trace time: a clear error, whoever calls the field first
        # The torque is the same for every trajectory of a batch in the state.
        omega = y.fiber / args.inertia
        return omega, jnp.broadcast_to(self.torque_law(t, args.torque), omega.shape)

    def power(self, t: Time, y: BundleElement, args: ForcedParameters) -> Array:
        """dH/dt = Ω·τ(t), the rate at which the torque does work."""
        return jnp.sum(y.fiber / args.inertia * self.torque_law(t, args.torque), axis=-1)

    def invariants(self, y: BundleElement, args: ForcedParameters) -> dict[str, Array]:
        """Only QᵀQ = I is kept; the energy (returned too, as "energy") obeys
        the balance dH/dt = `power`."""
        return {
            "energy": diagnostics.energy(y.fiber, y.fiber / args.inertia),
            "orthogonality": diagnostics.orthogonality_defect(rotation_matrix(y.base)),
        }

    def exact_flows(self, args: ForcedParameters, free_part="axes"):
        moments = body_frame.principal_moments(args.inertia, "ForcedRigidBody", batched=True)
        frame = body_frame.InertiaOrderedFrame.of(moments)

        def torque(t, z, args):
            body = jnp.broadcast_to(self.torque_law(t, args.torque), z.shape[1:] + (3,))
            return jnp.moveaxis(frame.vector(body), -1, 0)

        attitude = self.bundle.base
        kick = body_frame.momentum_kick(attitude, torque)
        if free_part == "exact":
            return (kick, FreeBodyFlow(frame, moments, attitude))
        return (kick,) + body_frame.body_axis_rotations(frame, moments, attitude)

    def pack(self, y, args: ForcedParameters):
        return body_frame.packed_body_state(y, body_frame.principal_moments(args.inertia, "ForcedRigidBody", batched=True))

    def unpack(self, z, like, args: ForcedParameters):
        return body_frame.unpacked_body_state(z, like, body_frame.principal_moments(args.inertia, "ForcedRigidBody", batched=True))

    def onto_group(self, z):
        return body_frame.renormalized_body_state(z, self.bundle.base)
