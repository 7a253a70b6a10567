"""A satellite: a rigid body in a central gravity field, its orbit and
attitude coupled by the gravity gradient, on T*(SO(3) × ℝ³).

With R the attitude (body → inertial), r the position of the centre of
mass, Π the body angular momentum and p = m r' the linear momentum, the
potential of a body of mass m and principal moments I in the field of a
point mass (gravitational parameter μ), to second order in the body's size
(MacCullagh), is

    V(R, r) = −μm/|r| − μ/(2|r|³) (tr I − 3 r̂·I r̂),   r̂ = Rᵀr/|r| (body frame),

and Hamilton's equations on T*(SO(3) × ℝ³), left-trivialised, body form:

    R' = RΩ̂,  r' = p/m,  Π' = Π × Ω + τ,  p' = F,   Ω = I⁻¹Π,

with the torque τ = −∂V/∂ε of V(R exp(ε̂), r) at ε = 0 (= 3μ/|r|³ r̂ × I r̂)
and the force F = −∂V/∂r, both derived from V by autodiff. The energy
½Π·Ω + |p|²/(2m) + V and the total angular momentum RΠ + r × p are kept by
the exact flow.

The smallest model that is exact for it: the translation enters the
kinetic energy without the attitude, so SO(3) × ℝ³ (`SO3xR3`, whose
cotangent bundle is a `Cotangent`) carries it. On SE(3)
(`DirectProduct(SE3)`) the same body moves with body-frame velocities:
its linear momentum is held in the body frame, P = Rᵀp, and turns with
it, P' = P × Ω + RᵀF (Π' gains P × P/m = 0); the state is embedded with
p = RP, so both models have the same embedding and reference.

It splits (`splitting()`, on SO(3) × ℝ³) into the potential's kick
(Π, p) ↦ (Π + hτ, p + hF), the drift r ↦ r + hp/m and the rotation's
kinetic energy, as three axis terms or the free body's exact flow
(`free_part`). Each part's Hamiltonian is invariant under turning the
whole system, (R, r, p) ↦ (QR, Qr, Qp), so each part keeps RΠ + r × p,
and the splitting keeps it to round-off.
"""

from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import exact_flows
from .._bundles import AbstractBundle, BundleElement, Cotangent, DirectProduct
from ..groups import SE3, SO3, SO3xR3, hat
from ..groups.pose import AbstractRotationAndTranslation
from . import body_frame
from .base import AbstractScene, checked_moments, checked_parameters, rotation_matrix
from .free_flow import FreeBodyFlow


class SatelliteParameters(eqx.Module):
    """The physical parameters of a `Satellite` (pass them as `args`)."""

    inertia: Float[Array, "3"]
    """Principal moments of inertia about the centre of mass, body frame."""
    mass: Float[Array, ""]
    """m."""
    mu: Float[Array, ""]
    """The central body's gravitational parameter μ = GM."""

    def __post_init__(self):
        # Shapes are checked at construction; signs where the data is known
        # (eagerly, or at run time under jit), as `checked_moments` does.
        self.inertia = checked_moments("SatelliteParameters.inertia", self.inertia)
        self.mass, self.mu = (_positive_scalar(name, value) for name, value in (("mass", self.mass), ("mu", self.mu)))


def _positive_scalar(name: str, value) -> Array:
    value = jnp.asarray(value)
    if value.shape != ():
        raise ValueError(f"SatelliteParameters.{name} is a scalar, got shape {value.shape}.")
    return eqx.error_if(value, ~(value > 0), f"SatelliteParameters.{name} must be > 0.")


def potential(rotation: Array, position: Array, args: SatelliteParameters) -> Array:
    """V(R, r) (module docstring), for states with leading batch axes."""
    distance = jnp.linalg.norm(position, axis=-1)
    body = jnp.einsum("...ji,...j->...i", rotation, position) / distance[..., None]  # r̂ = Rᵀr/|r|
    moments = args.inertia
    gradient_term = jnp.sum(moments, axis=-1) - 3 * jnp.sum(moments * body * body, axis=-1)
    return -args.mu * args.mass / distance - args.mu / (2 * distance**3) * gradient_term


def torque_and_force(rotation: Array, position: Array, args: SatelliteParameters) -> tuple[Array, Array]:
    """(τ, F): the body torque −∂V/∂ε of V(R exp(ε̂), r) at ε = 0 and the
    force −∂V/∂r, by reverse-mode autodiff of `potential` (summed over a
    batch: each trajectory's derivatives are its own)."""

    def total(turn, position):
        turned = rotation @ SO3.exp(turn).matrix
        return jnp.sum(potential(turned, position, args))

    gradient_turn, gradient_position = jax.grad(total, argnums=(0, 1))(jnp.zeros_like(position), position)
    return -gradient_turn, -gradient_position


def _pose(y: BundleElement) -> AbstractRotationAndTranslation:
    if not isinstance(y.base, (SO3xR3, SE3)):
        raise TypeError(f"a Satellite's state lives on SO3xR3 or SE3 (attitude and position), got a {type(y.base).__name__} base.")
    return y.base


def _rows(x: Array) -> Array:
    """Components first (`exact_flows.Packed`)."""
    return jnp.moveaxis(x, -1, 0)


def _columns(z: Array) -> Array:
    """Components last: `_rows`' inverse."""
    return jnp.moveaxis(z, 0, -1)


_BODY = body_frame.body_rows(SO3)
"""The packed state's first rows: the body's R (row-major) and Π (`body_frame`)."""
ANGULAR_MOMENTUM = slice(_BODY - 3, _BODY)
"""Where the packed state holds Π (the body's last rows)."""
POSITION = slice(_BODY, _BODY + 3)
"""Where it holds r."""
LINEAR_MOMENTUM = slice(_BODY + 3, _BODY + 6)
"""Where it holds p."""
_ROWS = tuple(range(_BODY + 6))


def gravity_kick(frame: body_frame.InertiaOrderedFrame, moments: Array) -> exact_flows.Shift:
    """The potential's flow (Π, p) ↦ (Π + hτ, p + hF) on the packed state
    (`Satellite.pack`): τ and F by `torque_and_force` from the relabelled
    matrix R' = R·P and moments I[σ], which give the same potential. Turning
    R' by exp(ε̂) turns R by exp(det P·(Pε)^), so −∂V/∂ε there is the
    parity times τ in the frame's components."""
    ordered = frame.vector(moments)

    def torque_and_force_rows(t, z, args: SatelliteParameters):
        rotation = _columns(z[:9]).reshape(*z.shape[1:], 3, 3)
        in_frame = eqx.tree_at(lambda a: a.inertia, args, ordered)
        torque, force = torque_and_force(rotation, _columns(z[POSITION]), in_frame)
        return jnp.concatenate([frame.parity * _rows(torque), _rows(force)])

    return exact_flows.Shift(_ROWS[ANGULAR_MOMENTUM] + _ROWS[LINEAR_MOMENTUM], torque_and_force_rows)


def _drift_rate(t, z, args: SatelliteParameters) -> Array:
    return z[LINEAR_MOMENTUM] / args.mass


DRIFT = exact_flows.Shift(_ROWS[POSITION], _drift_rate)
"""The flow of |p|²/(2m): r ↦ r + hp/m."""


class Satellite(AbstractScene, exact_flows.AbstractSplitScene):
    """A rigid body in a central gravity field, orbit and attitude coupled
    (module docstring); `args` is `SatelliteParameters`.

    `bundle` is `Cotangent(SO3xR3)` (default), where the product supplies
    Π × Ω and the generator is ((Ω, p/m), (τ, F)); `DirectProduct(SO3xR3)`,
    with ((Ω, p/m), (Π × Ω + τ, F)); or `DirectProduct(SE3)`, the fiber
    (Π, P) in the body frame, with ((Ω, P/m), (Π × Ω + τ, P × Ω + RᵀF)).
    The state is `BundleElement(SO3xR3(R, r), (Π, p))` (on SE3,
    `BundleElement(SE3(R, r), (Π, P))`). The splitting (`splitting()`)
    lives on SO(3) × ℝ³."""

    bundle: AbstractBundle = eqx.field(default_factory=lambda: Cotangent(SO3xR3))
    form: ClassVar[Literal["space", "body"]] = "body"  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar

    def __check_init__(self):
        on_product = isinstance(self.bundle, (Cotangent, DirectProduct)) and self.bundle.base is SO3xR3
        if not (on_product or (isinstance(self.bundle, DirectProduct) and self.bundle.base is SE3)):
            raise TypeError(f"Satellite lives on Cotangent(SO3xR3), DirectProduct(SO3xR3) or DirectProduct(SE3), got {self.bundle!r}.")

    def checked_args(self, args: SatelliteParameters) -> SatelliteParameters:
        return checked_parameters("Satellite", args, SatelliteParameters)

    def __call__(self, t, y: BundleElement, args: SatelliteParameters):
        angular, linear = y.fiber[..., :3], y.fiber[..., 3:]
        omega = angular / args.inertia
        pose = _pose(y)
        torque, force = torque_and_force(pose.rotation, pose.translation, args)
        if isinstance(self.bundle, DirectProduct):
            torque = torque + jnp.cross(angular, omega)
        if self.bundle.base is SE3:
            force = jnp.cross(linear, omega) + jnp.einsum("...ji,...j->...i", pose.rotation, force)
        return jnp.concatenate([omega, linear / args.mass], axis=-1), jnp.concatenate([torque, force], axis=-1)

    def _inertial_momentum(self, y: BundleElement) -> Array:
        """p: the fiber's linear part, turned to the inertial frame on SE3."""
        linear = y.fiber[..., 3:]
        if self.bundle.base is SE3:
            return jnp.einsum("...ij,...j->...i", _pose(y).rotation, linear)
        return linear

    def invariants(self, y: BundleElement, args: SatelliteParameters) -> dict[str, Array]:
        """The energy and the total angular momentum RΠ + r × p (inertial frame)."""
        rotation, position = _pose(y).rotation, _pose(y).translation
        angular, linear = y.fiber[..., :3], self._inertial_momentum(y)
        kinetic = 0.5 * jnp.sum(angular * angular / args.inertia, axis=-1) + 0.5 * jnp.sum(linear * linear, axis=-1) / args.mass
        spin = jnp.einsum("...ij,...j->...i", rotation, angular)
        return {
            "energy": kinetic + potential(rotation, position, args),
            "angular momentum": spin + jnp.cross(position, linear),
        }

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 18"]:
        """(R row-major, r, Π, p), p inertial on either group."""
        pose = _pose(y)
        rotation = pose.rotation
        flat = rotation.reshape(*rotation.shape[:-2], 9)
        return jnp.concatenate([flat, pose.translation, y.fiber[..., :3], self._inertial_momentum(y)], axis=-1)

    def from_embedding(self, z: Float[Array, "*batch 18"]) -> BundleElement:
        rotation = z[..., :9].reshape(*z.shape[:-1], 3, 3)
        if self.bundle.base is SE3:
            body = jnp.einsum("...ji,...j->...i", rotation, z[..., 15:])
            return BundleElement(SE3(rotation, z[..., 9:12]), jnp.concatenate([z[..., 12:15], body], axis=-1))
        return BundleElement(SO3xR3(rotation, z[..., 9:12]), z[..., 12:])

    # --- the splitting (on SO(3) × ℝ³) ---------------------------------------------
    def _split_moments(self, args: SatelliteParameters) -> Array:
        if self.bundle.base is not SO3xR3:
            raise TypeError(
                "Satellite splits on SO(3) × ℝ³ (its linear momentum inertial, the drift r ↦ r + hp/m): "
                f"use Cotangent(SO3xR3) or DirectProduct(SO3xR3), got {self.bundle!r}."
            )
        return body_frame.principal_moments(args.inertia, "Satellite", batched=True)

    def exact_flows(self, args: SatelliteParameters, free_part="axes"):
        """The kick of the potential (outermost), the drift, then the
        rotation's kinetic energy (module docstring). The drift commutes with
        the rotation (they move and read disjoint rows), so the Strang step
        kick · drift · rotation · drift · kick is kick · (the free motion) · kick."""
        moments = self._split_moments(args)
        frame = body_frame.InertiaOrderedFrame.of(moments)
        parts = (gravity_kick(frame, moments), DRIFT)
        if free_part == "exact":
            return parts + (FreeBodyFlow(frame, moments, SO3),)
        return parts + body_frame.body_axis_rotations(frame, moments, SO3)

    def pack(self, y, args: SatelliteParameters):
        """The body's (R, Π) as `body_frame.packed_body_state`, then r and p
        (`POSITION`, `LINEAR_MOMENTUM`)."""
        pose = _pose(y)
        body = BundleElement(SO3(pose.rotation), y.fiber[..., :3])
        packed = body_frame.packed_body_state(body, self._split_moments(args))
        return jnp.concatenate([packed, _rows(pose.translation), _rows(y.fiber[..., 3:])])

    def unpack(self, z, like, args: SatelliteParameters):
        del like  # every such state has the same structure
        frame = body_frame.InertiaOrderedFrame.of(self._split_moments(args))
        body = body_frame.unpacked_from_frame(z[:_BODY], SO3, frame)
        translation, linear = _columns(z[POSITION]), _columns(z[LINEAR_MOMENTUM])
        return BundleElement(SO3xR3(rotation_matrix(body.base), translation), jnp.concatenate([body.fiber, linear], axis=-1))

    def onto_group(self, z):
        return body_frame.renormalized_body_state(z, SO3)


def embedding_field(t, z: Float[Array, " 18"], args: SatelliteParameters) -> Float[Array, " 18"]:
    """The equations on (R, r, Π, p) ∈ ℝ¹⁸ written out (module docstring),
    the torque in MacCullagh's closed form 3μ/|r|³ r̂ × I r̂ and the force
    −∂V/∂r by autodiff: what the tests compare the scene with."""
    del t
    rotation, position, angular, linear = z[:9].reshape(3, 3), z[9:12], z[12:15], z[15:]
    omega = angular / args.inertia
    distance = jnp.linalg.norm(position)
    body = rotation.T @ position / distance
    torque = 3 * args.mu / distance**3 * jnp.cross(body, args.inertia * body)
    force = -jax.grad(lambda r: potential(rotation, r, args))(position)
    return jnp.concatenate([(rotation @ hat(omega)).reshape(9), linear / args.mass, jnp.cross(angular, omega) + torque, force])
