"""A chain of two rigid bodies in gravity: a 3D double pendulum on T*SO(3)².

Body 1 hangs from a fixed pivot by a ball joint; body 2 hangs from body 1 by
a ball joint. With Rₖ the attitude of body k (body → space), Ωₖ its body
angular velocity, e₃ pointing up and, in each body's own frame, c₁ the
pivot → centre of mass of body 1, d the pivot → joint, c₂ the joint → centre
of mass of body 2, the centres of mass are at

    x₁ = R₁c₁,   x₂ = R₁d + R₂c₂,

and the kinetic and potential energies are

    T = ½ Σₖ (Ωₖ·IₖΩₖ + mₖ|ẋₖ|²),  ẋ₁ = R₁(Ω₁ × c₁),  ẋ₂ = R₁(Ω₁ × d) + R₂(Ω₂ × c₂),
    V = g Σₖ mₖ e₃·xₖ,

with Iₖ the principal moments about each centre of mass. The joint
constraints are gone with the choice of coordinates: the configuration is
(R₁, R₂) ∈ SO(3)² (`SO3Power`). T = ½ Ωᵀ M(R₁ᵀR₂) Ω couples the bodies
through the mass matrix M (6 × 6, its off-diagonal block
m₂ d̂ᵀR₁ᵀR₂ĉ₂), so with the body momenta Π = MΩ the Hamiltonian
H = ½ Πᵀ M⁻¹ Π + V does not separate: a PRKMK method's stages are implicit
(symplectic Euler and Störmer–Verlet included), and no splitting into
exact flows applies.

Hamilton's equations, left-trivialised, body form: Rₖ' = RₖΩ̂ₖ with
Ω = ∂H/∂Π = M⁻¹Π, and Πₖ' = Πₖ × Ωₖ − ∂H/∂εₖ, the derivative of
H(R·exp(ε̂), Π) at ε = 0 with Π held fixed (gravity's torque and the
kinetic energy's dependence on the relative attitude): both by autodiff of
H, which is written once (`hamiltonian`). Conserved: the energy H and the
vertical angular momentum e₃·(R₁Π₁ + R₂Π₂) (H is invariant under turning
the whole chain about e₃).
"""

from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import diagnostics
from .._bundles import AbstractBundle, BundleElement, Cotangent, DirectProduct
from ..groups import SO3, SO3Power, hat
from .base import AbstractScene, checked_moments, checked_parameters


class PendulumParameters(eqx.Module):
    """The physical parameters of a `DoublePendulum` (pass them as `args`)."""

    inertia: Float[Array, "2 3"]
    """Each body's principal moments of inertia about its centre of mass."""
    mass: Float[Array, "2"]
    """The two masses."""
    centre: Float[Array, "2 3"]
    """Body 1's centre of mass from the pivot, body 2's from the joint, each in its own frame."""
    joint: Float[Array, "3"]
    """The joint from the pivot, in body 1's frame."""
    gravity: Float[Array, ""]
    """g, along −e₃."""

    def __post_init__(self):
        # Shapes at construction; signs where the data is known (eagerly, or
        # at run time under jit), as `checked_moments` does.
        self.inertia = checked_moments("PendulumParameters.inertia", self.inertia)
        shapes = {"inertia": (2, 3), "mass": (2,), "centre": (2, 3), "joint": (3,), "gravity": ()}
        for name, shape in shapes.items():
            value = jnp.asarray(getattr(self, name))
            if value.shape != shape:
                raise ValueError(f"PendulumParameters.{name} must have shape {shape}, got {value.shape}.")
            setattr(self, name, value if jnp.issubdtype(value.dtype, jnp.floating) else value.astype(float))
        self.mass = eqx.error_if(self.mass, ~jnp.all(self.mass > 0), "PendulumParameters.mass: both masses must be > 0.")


def centres_of_mass(rotations: Float[Array, "*batch 2 3 3"], args: PendulumParameters) -> Float[Array, "*batch 2 3"]:
    """x₁ = R₁c₁ and x₂ = R₁d + R₂c₂ (module docstring), in space."""
    first, second = rotations[..., 0, :, :], rotations[..., 1, :, :]
    x1 = first @ args.centre[0]
    return jnp.stack([x1, first @ args.joint + second @ args.centre[1]], axis=-2)


def kinetic_energy(rotations: Float[Array, "*batch 2 3 3"], velocities: Float[Array, "*batch 2 3"], args: PendulumParameters) -> Array:
    """T(R, Ω) (module docstring), written with the bodies' velocities."""
    first, second = rotations[..., 0, :, :], rotations[..., 1, :, :]
    omega1, omega2 = velocities[..., 0, :], velocities[..., 1, :]
    v1 = jnp.einsum("...ij,...j->...i", first, jnp.cross(omega1, args.centre[0]))
    v2 = jnp.einsum("...ij,...j->...i", first, jnp.cross(omega1, args.joint)) + jnp.einsum(
        "...ij,...j->...i", second, jnp.cross(omega2, args.centre[1])
    )
    spin = jnp.sum(velocities * args.inertia * velocities, axis=(-2, -1))
    return 0.5 * (spin + args.mass[0] * jnp.sum(v1 * v1, axis=-1) + args.mass[1] * jnp.sum(v2 * v2, axis=-1))


def mass_matrix(rotations: Float[Array, "*batch 2 3 3"], args: PendulumParameters) -> Float[Array, "*batch 6 6"]:
    """M(R), T = ½ΩᵀMΩ (`kinetic_energy`) with Ω = (Ω₁, Ω₂) flattened:

        M = [[I₁ + m₁ĉ₁ᵀĉ₁ + m₂d̂ᵀd̂,  m₂d̂ᵀR₁ᵀR₂ĉ₂],
             [m₂ĉ₂ᵀR₂ᵀR₁d̂,          I₂ + m₂ĉ₂ᵀĉ₂]],

    from |ẋ|² with ẋ₁ = −R₁ĉ₁Ω₁, ẋ₂ = −R₁d̂Ω₁ − R₂ĉ₂Ω₂. Written out, where
    autodiff of T (which the tests compare it with) would put a Hessian
    inside every derivative of the field."""
    c1, c2, d = hat(args.centre[0]), hat(args.centre[1]), hat(args.joint)
    (m1, m2), (i1, i2) = args.mass, args.inertia
    relative = jnp.swapaxes(rotations[..., 0, :, :], -1, -2) @ rotations[..., 1, :, :]
    coupling = m2 * d.T @ relative @ c2
    first = jnp.diag(i1) + m1 * c1.T @ c1 + m2 * d.T @ d
    second = jnp.diag(i2) + m2 * c2.T @ c2
    top = jnp.concatenate([jnp.broadcast_to(first, coupling.shape), coupling], axis=-1)
    bottom = jnp.concatenate([jnp.swapaxes(coupling, -1, -2), jnp.broadcast_to(second, coupling.shape)], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def hamiltonian(rotations: Float[Array, "*batch 2 3 3"], momenta: Float[Array, "*batch 2 3"], args: PendulumParameters) -> Array:
    """H(R, Π) = ½ Πᵀ M(R)⁻¹ Π + g Σₖ mₖ e₃·xₖ."""
    flat = momenta.reshape(*momenta.shape[:-2], 6)
    velocities = jnp.linalg.solve(mass_matrix(rotations, args), flat[..., None])[..., 0]
    height = centres_of_mass(rotations, args)[..., 2]
    return 0.5 * jnp.sum(flat * velocities, axis=-1) + args.gravity * jnp.sum(args.mass * height, axis=-1)


def body_momenta(rotations: Float[Array, "*batch 2 3 3"], velocities: Float[Array, "*batch 2 3"], args: PendulumParameters) -> Array:
    """Π = ∂T/∂Ω = MΩ: the state's fiber for given body angular velocities."""
    return jax.grad(lambda w: jnp.sum(kinetic_energy(rotations, w, args)))(velocities)


def _attitudes(y: BundleElement) -> Array:
    if not isinstance(y.base, SO3Power) or y.base.matrix.shape[-3] != 2:
        raise TypeError(f"a DoublePendulum's state lives on SO3Power with two bodies, got a {type(y.base).__name__} base.")
    return y.base.matrix


class DoublePendulum(AbstractScene):
    """Two rigid bodies hanging in a chain from a fixed pivot, in gravity
    (module docstring); `args` is `PendulumParameters`.

    `bundle` is `Cotangent(SO3Power)` (default), where the product supplies
    Πₖ × Ωₖ and the generator is (M⁻¹Π, −∂H/∂ε), or `DirectProduct(SO3Power)`,
    with (M⁻¹Π, Π × Ω − ∂H/∂ε) body by body. The state is
    `BundleElement(SO3Power(R), Π)`, R of shape (…, 2, 3, 3), Π (…, 2, 3)
    (`body_momenta` gives Π from angular velocities)."""

    bundle: AbstractBundle = eqx.field(default_factory=lambda: Cotangent(SO3Power))
    form: ClassVar[Literal["space", "body"]] = "body"  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar

    def __check_init__(self):
        if not isinstance(self.bundle, (Cotangent, DirectProduct)) or self.bundle.base is not SO3Power:
            raise TypeError(f"DoublePendulum lives on Cotangent(SO3Power) or DirectProduct(SO3Power), got {self.bundle!r}.")

    def checked_args(self, args: PendulumParameters) -> PendulumParameters:
        return checked_parameters("DoublePendulum", args, PendulumParameters)

    def __call__(self, t, y: BundleElement, args: PendulumParameters):
        checked_parameters("DoublePendulum", args, PendulumParameters)  # trace time: a clear error, whoever calls the field first
        rotations = _attitudes(y)

        def total(turns, momenta):
            return jnp.sum(hamiltonian(rotations @ SO3.exp(turns).matrix, momenta, args))

        slope, velocities = jax.grad(total, argnums=(0, 1))(jnp.zeros_like(y.fiber), y.fiber)
        if isinstance(self.bundle, DirectProduct):
            return velocities, jnp.cross(y.fiber, velocities) - slope
        return velocities, -slope

    def invariants(self, y: BundleElement, args: PendulumParameters) -> dict[str, Array]:
        """The energy H, the vertical angular momentum e₃·(R₁Π₁ + R₂Π₂) and
        the larger orthogonality defect of the two attitudes."""
        rotations = _attitudes(y)
        spatial = jnp.einsum("...kij,...kj->...i", rotations, y.fiber)
        return {
            "energy": hamiltonian(rotations, y.fiber, args),
            "vertical momentum": spatial[..., 2],
            "orthogonality": jnp.max(diagnostics.orthogonality_defect(rotations), axis=-1),
        }

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 24"]:
        """(R₁ row-major, R₂ row-major, Π₁, Π₂)."""
        rotations = _attitudes(y)
        batch = rotations.shape[:-3]
        return jnp.concatenate([rotations.reshape(*batch, 18), y.fiber.reshape(*batch, 6)], axis=-1)

    def from_embedding(self, z: Float[Array, "*batch 24"]) -> BundleElement:
        batch = z.shape[:-1]
        return BundleElement(SO3Power(z[..., :18].reshape(*batch, 2, 3, 3)), z[..., 18:].reshape(*batch, 2, 3))
