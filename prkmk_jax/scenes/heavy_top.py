"""The heavy top: a rigid body about a fixed point, in gravity, on T*SO(3).

With e₃ pointing up, Q the attitude (body → space), Π the body angular
momentum, Ω = I⁻¹Π and Γ = Qᵀe₃ the vertical seen from the body:

    Q' = QΩ̂,   Π' = Π × Ω + Γ × ℓ,   ℓ = m g χ,

where χ is the body-frame vector from the fixed point to the centre of mass
(the Euler–Poisson equations; Γ' = Γ × Ω follows from Q'). The energy
H = ½Π·Ω + ℓ·Γ (kinetic plus m g times the height of the centre of mass)
and the vertical angular momentum Γ·Π = e₃·QΠ are kept by the exact flow.
For a Lagrange top (I₁ = I₂, χ on the symmetry axis e₃) the spin Π₃ is kept
as well.

On the left-trivialised cotangent bundle, body form, the product supplies
Π × Ω, so the generator is (ξ, η) = (Ω, Γ × ℓ): unlike the free body, the
fiber moves on its own (η ≠ 0). On G×g (`DirectProduct`) it is
(Ω, Π × Ω + Γ × ℓ).

`SphericalTop` is the isotropic case on G×g, where the field is separable.
"""

from typing import ClassVar, Literal

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import diagnostics, exact_flows
from .._bundles import AbstractBundle, BundleElement, Cotangent, DirectProduct
from ..groups import SO3, hat
from . import body_frame
from .base import (
    ATTITUDES,
    AbstractScene,
    checked_moments,
    checked_parameters,
    checked_vector,
    rotation_and_vector_embedding,
    rotation_and_vector_state,
    rotation_matrix,
)
from .free_flow import FreeBodyFlow


class TopParameters(eqx.Module):
    """The physical parameters of a heavy top (pass them as `args`)."""

    inertia: Float[Array, "3"] | Float[Array, ""]
    """Principal moments of inertia about the fixed point, body frame (for
    `SphericalTop`, the one moment α)."""
    lever: Float[Array, "3"]
    """ℓ = m g χ: the weight times the body-frame vector from the fixed point
    to the centre of mass."""

    def __post_init__(self):
        # Shapes are checked at construction; the moments' signs where they
        # are known (eagerly, or at run time under jit).
        self.inertia = checked_moments("TopParameters.inertia", self.inertia, allow_scalar=True)
        self.lever = checked_vector("TopParameters.lever", self.lever)


def _vertical(q: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Γ = Qᵀe₃, the last row of Q."""
    return q[..., 2, :]


def gravity_torque(frame: body_frame.InertiaOrderedFrame, lever: Array, attitude: body_frame.Attitude):
    """(t, z, args) ↦ Γ × ℓ on the state packed in `frame` with `attitude`
    (Γ = Qᵀe₃, `body_frame.body_vertical`), in that frame's components: the
    parity times the cross product of the relabelled vectors."""
    ordered = frame.vector(lever)

    def torque(t, z, args):
        g0, g1, g2 = body_frame.body_vertical(z, frame, attitude)
        l0, l1, l2 = ordered[..., 0], ordered[..., 1], ordered[..., 2]
        return frame.parity * jnp.stack([g1 * l2 - g2 * l1, g2 * l0 - g0 * l2, g0 * l1 - g1 * l0])

    return torque


class HeavyTop(AbstractScene, exact_flows.AbstractSplitScene):
    """The heavy top in body form; `args` is `TopParameters`.

    `bundle` is `Cotangent(SO3)` (default), where the product supplies
    Π × Ω and the generator is (Ω, Γ × ℓ), or `DirectProduct(SO3)`, with
    (Ω, Π × Ω + Γ × ℓ). On G×g the fiber moves by h Σ bᵢ ηᵢ alone (the
    direct product's dexp⁻¹ and Cayley's are the identity on the fiber), so
    a Lagrange top's spin Π₃, whose slope (Π × Ω + Γ × ℓ)₃ vanishes, is kept
    to round-off by every method. On T*SO(3) the fiber is also turned by
    Ad*, and the spin's error is the method's.

    It splits (`splitting()`) into the gravity kick Π ↦ Π + hΓ × ℓ (the
    flow of the potential ℓ·Γ: the attitude stands still) and the three
    axis terms of the kinetic energy, in that order (the kick outermost, then
    the axes by increasing inertia, `body_frame.InertiaOrderedFrame`).
    Each part keeps Γ·Π, so the splitting keeps it to round-off."""

    bundle: AbstractBundle = eqx.field(default_factory=lambda: Cotangent(SO3))
    form: ClassVar[Literal["space", "body"]] = "body"  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar

    def __check_init__(self):
        if not isinstance(self.bundle, (Cotangent, DirectProduct)) or self.bundle.base not in ATTITUDES:
            raise TypeError(f"HeavyTop lives on Cotangent(G) or DirectProduct(G) for G = SO3 or UnitQuaternion, got {self.bundle!r}.")

    def checked_args(self, args: TopParameters) -> TopParameters:
        """`TopParameters` with principal moments (…, 3), each > 0, and a
        lever (…, 3)."""
        args = checked_parameters("HeavyTop", args, TopParameters)
        if jnp.shape(args.inertia) == ():
            raise ValueError("HeavyTop takes the principal moments (3,); one moment α (isotropic inertia) is SphericalTop's.")
        return TopParameters(args.inertia, args.lever)

    def __call__(self, t, y: BundleElement, args: TopParameters):
        checked_parameters("HeavyTop", args, TopParameters)  # trace time: a clear error, whoever calls the field first
        omega = y.fiber / args.inertia
        torque = jnp.cross(_vertical(rotation_matrix(y.base)), args.lever)
        if isinstance(self.bundle, DirectProduct):
            return omega, jnp.cross(y.fiber, omega) + torque
        return omega, torque

    def invariants(self, y: BundleElement, args: TopParameters) -> dict[str, Array]:
        q, pi = rotation_matrix(y.base), y.fiber
        gamma = _vertical(q)
        kinetic = diagnostics.energy(pi, pi / args.inertia)
        return {
            "energy": kinetic + jnp.sum(args.lever * gamma, axis=-1),
            "vertical momentum": jnp.sum(gamma * pi, axis=-1),
            "orthogonality": diagnostics.orthogonality_defect(q),
        }

    def embedding_field(self, t, z: Float[Array, "12"], args: TopParameters) -> Float[Array, "12"]:
        """Written out (the Euclidean peers' field in the benchmarks); equal to
        the generator's (`derived_embedding_field`)."""
        q, pi = z[:9].reshape(3, 3), z[9:]
        omega = pi / args.inertia
        return jnp.concatenate([(q @ hat(omega)).ravel(), jnp.cross(pi, omega) + jnp.cross(_vertical(q), args.lever)])

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 12"]:
        return rotation_and_vector_embedding(y)

    def from_embedding(self, z: Float[Array, "*batch 12"]) -> BundleElement:
        return rotation_and_vector_state(z, self.bundle.base)

    def exact_flows(self, args: TopParameters, free_part="axes"):
        moments = body_frame.principal_moments(args.inertia, "HeavyTop", batched=True)
        frame = body_frame.InertiaOrderedFrame.of(moments)
        attitude = self.bundle.base
        kick = body_frame.momentum_kick(attitude, gravity_torque(frame, jnp.asarray(args.lever), attitude))
        if free_part == "exact":
            return (kick, FreeBodyFlow(frame, moments, attitude))
        return (kick,) + body_frame.body_axis_rotations(frame, moments, attitude)

    def pack(self, y, args: TopParameters):
        return body_frame.packed_body_state(y, body_frame.principal_moments(args.inertia, "HeavyTop", batched=True))

    def unpack(self, z, like, args: TopParameters):
        return body_frame.unpacked_body_state(z, like, body_frame.principal_moments(args.inertia, "HeavyTop", batched=True))

    def onto_group(self, z):
        return body_frame.renormalized_body_state(z, self.bundle.base)


class SphericalTop(AbstractScene):
    """A heavy top whose inertia about the pivot is isotropic (I = α·1), on
    `DirectProduct(SO3)` in body form; `args` is `TopParameters` with a scalar
    `inertia` α.

    Then Π × Ω = 0, and on G×g the generator is (ξ, η) = (Π/α, Γ × ℓ): ξ a
    function of the fiber only and η of the group only, the separable case
    (4.15) of the paper. With df⁻¹ = I (exp or Cayley at order ≤ 2)
    symplectic Euler and Störmer–Verlet need no implicit solve here (`PRKMK`
    finds this from the field's program). The energy ½|Π|²/α + ℓ·Γ, the
    vertical momentum Γ·Π and the spin ℓ·Π about the lever (Π' = Γ × ℓ is
    orthogonal to ℓ) are kept by the exact flow.
    """

    bundle: ClassVar[AbstractBundle] = DirectProduct(SO3)  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar
    form: ClassVar[Literal["space", "body"]] = "body"  # pyright: ignore[reportIncompatibleVariableOverride]  # as above

    def checked_args(self, args: TopParameters) -> TopParameters:
        """`TopParameters` with one moment α > 0 and a lever (…, 3)."""
        _check_isotropic(checked_parameters("SphericalTop", args, TopParameters))
        return TopParameters(args.inertia, args.lever)

    def __call__(self, t, y: BundleElement, args: TopParameters):
        _check_isotropic(checked_parameters("SphericalTop", args, TopParameters))
        return y.fiber / args.inertia, jnp.cross(_vertical(rotation_matrix(y.base)), args.lever)

    def invariants(self, y: BundleElement, args: TopParameters) -> dict[str, Array]:
        _check_isotropic(args)
        q, pi = rotation_matrix(y.base), y.fiber
        gamma = _vertical(q)
        return {
            "energy": 0.5 * jnp.sum(pi * pi, axis=-1) / args.inertia + jnp.sum(args.lever * gamma, axis=-1),
            "vertical momentum": jnp.sum(gamma * pi, axis=-1),
            "spin": jnp.sum(args.lever * pi, axis=-1),
            "orthogonality": diagnostics.orthogonality_defect(q),
        }

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 12"]:
        return rotation_and_vector_embedding(y)

    def from_embedding(self, z: Float[Array, "*batch 12"]) -> BundleElement:
        return rotation_and_vector_state(z)


def _check_isotropic(args: TopParameters) -> None:
    if jnp.shape(args.inertia) != ():
        raise ValueError(
            f"SphericalTop's inertia is one number α (I = α·1), got shape {jnp.shape(args.inertia)}; "
            "for principal moments use HeavyTop on Cotangent(SO3)."
        )
