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
cotangent bundle is a `Cotangent`) carries it; on SE(3) the same body
would move with body-frame velocities and the Coriolis term p × Ω.
"""

from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._bundles import AbstractBundle, BundleElement, Cotangent, DirectProduct
from ..groups import SO3, SO3xR3, hat
from .base import AbstractScene, checked_moments, checked_parameters


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


def _pose(y: BundleElement) -> SO3xR3:
    if not isinstance(y.base, SO3xR3):
        raise TypeError(f"a Satellite's state lives on SO3xR3 (attitude and position), got a {type(y.base).__name__} base.")
    return y.base


class Satellite(AbstractScene):
    """A rigid body in a central gravity field, orbit and attitude coupled
    (module docstring); `args` is `SatelliteParameters`.

    `bundle` is `Cotangent(SO3xR3)` (default), where the product supplies
    Π × Ω and the generator is ((Ω, p/m), (τ, F)), or `DirectProduct(SO3xR3)`
    with ((Ω, p/m), (Π × Ω + τ, F)). The state is
    `BundleElement(SO3xR3(R, r), (Π, p))`."""

    bundle: AbstractBundle = eqx.field(default_factory=lambda: Cotangent(SO3xR3))
    form: ClassVar[Literal["space", "body"]] = "body"  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar

    def __check_init__(self):
        if not isinstance(self.bundle, (Cotangent, DirectProduct)) or self.bundle.base is not SO3xR3:
            raise TypeError(f"Satellite lives on Cotangent(SO3xR3) or DirectProduct(SO3xR3), got {self.bundle!r}.")

    def checked_args(self, args: SatelliteParameters) -> SatelliteParameters:
        return checked_parameters("Satellite", args, SatelliteParameters)

    def __call__(self, t, y: BundleElement, args: SatelliteParameters):
        angular, linear = y.fiber[..., :3], y.fiber[..., 3:]
        omega = angular / args.inertia
        pose = _pose(y)
        torque, force = torque_and_force(pose.rotation, pose.translation, args)
        if isinstance(self.bundle, DirectProduct):
            torque = torque + jnp.cross(angular, omega)
        return jnp.concatenate([omega, linear / args.mass], axis=-1), jnp.concatenate([torque, force], axis=-1)

    def invariants(self, y: BundleElement, args: SatelliteParameters) -> dict[str, Array]:
        """The energy and the total angular momentum RΠ + r × p (inertial frame)."""
        rotation, position = _pose(y).rotation, _pose(y).translation
        angular, linear = y.fiber[..., :3], y.fiber[..., 3:]
        kinetic = 0.5 * jnp.sum(angular * angular / args.inertia, axis=-1) + 0.5 * jnp.sum(linear * linear, axis=-1) / args.mass
        spin = jnp.einsum("...ij,...j->...i", rotation, angular)
        return {
            "energy": kinetic + potential(rotation, position, args),
            "angular momentum": spin + jnp.cross(position, linear),
        }

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 18"]:
        """(R row-major, r, Π, p)."""
        pose = _pose(y)
        rotation = pose.rotation
        return jnp.concatenate([rotation.reshape(*rotation.shape[:-2], 9), pose.translation, y.fiber], axis=-1)

    def from_embedding(self, z: Float[Array, "*batch 18"]) -> BundleElement:
        rotation = z[..., :9].reshape(*z.shape[:-1], 3, 3)
        return BundleElement(SO3xR3(rotation, z[..., 9:12]), z[..., 12:])


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
