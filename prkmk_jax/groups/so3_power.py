"""SO(3)ⁿ, the attitudes of n bodies at once (a chain of rigid bodies),
multiplied body by body.

An element holds n rotation matrices, shape (*batch, n, 3, 3); its algebra
is n angular velocities, shape (*batch, n, 3) (`algebra_ndim` 2: the body
axis belongs to the algebra element, not to the batch). Every map is
SO(3)'s on each body: the bracket, Ad, exp, log, dexp⁻¹, Cayley and their
actions and changes, evaluated by `SO3` with the body axis as one more
leading axis. The pairing Σₖ ⟨uₖ, vₖ⟩ is bi-invariant, so T*SO(3)ⁿ is a
`Cotangent` bundle: the body angular momenta of the n bodies.
"""

from typing import ClassVar, Self

import equinox as eqx
from jaxtyping import Array, Float

from ._util import as_array, check_floating
from .rotation import AbstractRotationGroup
from .so3 import SO3

Velocities = Float[Array, "*batch n 3"]
"""An algebra element: one angular velocity (ℝ³ ≅ so(3)) per body."""


class SO3Power(AbstractRotationGroup):
    """The attitudes of n bodies, each a rotation, multiplied body by body
    (module docstring); leading batch axes allowed."""

    matrix: Float[Array, "*batch n 3 3"] = eqx.field(converter=as_array)
    """The n rotation matrices, one per body."""

    algebra_ndim: ClassVar[int] = 2  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    bi_invariant_pairing: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        check_floating(self.matrix, "an SO3Power matrix")
        if self.matrix.ndim < 3 or self.matrix.shape[-2:] != (3, 3):
            raise ValueError(f"SO3Power needs (..., n, 3, 3) matrices (n bodies), got shape {self.matrix.shape}.")

    @property
    def bodies(self) -> SO3:
        """The n attitudes as one `SO3` with the body axis last among its batch axes."""
        return SO3(self.matrix)

    # --- group -----------------------------------------------------------------
    @classmethod
    def exp(cls, u: Velocities) -> Self:
        return cls(SO3.exp(u).matrix)

    def log(self) -> Velocities:
        return self.bodies.log()

    def adjoint(self, u: Velocities) -> Velocities:
        return self.bodies.adjoint(u)

    @classmethod
    def bracket(cls, u: Velocities, v: Velocities) -> Velocities:
        return SO3.bracket(u, v)

    # --- differentials and actions: SO(3)'s, body by body ------------------------
    @classmethod
    def dexp(cls, u: Velocities, v: Velocities) -> Velocities:
        return SO3.dexp(u, v)

    @classmethod
    def dexp_inv(cls, u: Velocities, v: Velocities) -> Velocities:
        return SO3.dexp_inv(u, v)

    @classmethod
    def exp_adjoint(cls, u: Velocities, x: Velocities) -> Velocities:
        return SO3.exp_adjoint(u, x)

    @classmethod
    def inverse_shifted_ad(cls, u: Velocities, v: Velocities, alpha: float) -> Velocities:
        return SO3.inverse_shifted_ad(u, v, alpha)

    @classmethod
    def exp_change(cls, u: Velocities) -> Float[Array, "*batch n 3 3"]:
        return SO3.exp_change(u)

    @classmethod
    def exp_adjoint_change(cls, u: Velocities, x: Velocities) -> Velocities:
        return SO3.exp_adjoint_change(u, x)

    # --- Cayley ------------------------------------------------------------------
    @classmethod
    def cayley(cls, u: Velocities) -> Self:
        return cls(SO3.cayley(u).matrix)

    @classmethod
    def cayley_change(cls, u: Velocities) -> Float[Array, "*batch n 3 3"]:
        return SO3.cayley_change(u)

    def cayley_inverse(self) -> Velocities:
        return self.bodies.cayley_inverse()

    @classmethod
    def dcayley(cls, u: Velocities, v: Velocities) -> Velocities:
        return SO3.dcayley(u, v)

    @classmethod
    def dcayley_inv(cls, u: Velocities, v: Velocities) -> Velocities:
        return SO3.dcayley_inv(u, v)

    @classmethod
    def cayley_adjoint(cls, u: Velocities, x: Velocities) -> Velocities:
        return SO3.cayley_adjoint(u, x)

    @classmethod
    def shifted_cayley_adjoint_inverse(cls, u: Velocities, x: Velocities) -> Velocities:
        return SO3.shifted_cayley_adjoint_inverse(u, x)

    @classmethod
    def cayley_adjoint_change(cls, u: Velocities, x: Velocities) -> Velocities:
        return SO3.cayley_adjoint_change(u, x)
