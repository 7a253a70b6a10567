"""A scene's whole flow in closed form, as a one-step method.

Where a scene is integrable (`exact_flows.AbstractSolvedScene`: the free
rigid body, through Jacobi's elliptic functions), its flow over any step is
a method like the others: `integrate`, `resume`, `PRKMKSolver` and the
reversible gradients run it. One step of any size is exact to round-off, so
the step size only sets where the trajectory is saved and how round-off
accumulates. The flow of a time-independent system is a group (φ_{−h} =
φ_h⁻¹), so the method is symmetric and undoes its own steps.
"""

from typing import ClassVar

import jax
import jax.numpy as jnp

from ..coordinates import AbstractCoordinates, Exp
from ..exact_flows import AbstractSolvedScene
from ..groups._util import is_low_precision
from .base import RESULTS, AbstractOfOneScene, Step, check_parts, flag_nonfinite

EXACT_ORDER = 99
"""The `order` an exact flow reports: it has no truncation error; an integer
above every tableau's and composition's order keeps what the drivers do
with orders (dense output of order min(p, 3)) as it is."""


class ExactFlow(AbstractOfOneScene):
    """The exact flow of `scene` (module docstring); built by the scene's
    `exact_flow()`.

    **Arguments:**

    - `scene`: a scene with a closed-form flow (`FreeRigidBody`).

    The method integrates `scene` only: the drivers refuse another vector
    field. Its steps' increments (for dense output) are read in exponential
    coordinates with the exact dexp⁻¹ (`coordinates`).
    """

    scene: AbstractSolvedScene  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a field implements an AbstractVar, narrowed
    built_by: ClassVar[str] = "scene.exact_flow()"  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        if not isinstance(self.scene, AbstractSolvedScene):
            raise TypeError(
                f"ExactFlow needs a scene whose flow is known in closed form (an AbstractSolvedScene such as FreeRigidBody), "
                f"got {type(self.scene).__name__}; for other fields use a PRKMK method or a splitting."
            )
        check_parts(self.scene.bundle, self.coordinates, self.scene.form)

    @property
    def coordinates(self) -> AbstractCoordinates:  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        """Exponential coordinates, dexp⁻¹ in closed form: a truncation tied
        to the order means nothing for an exact flow."""
        return Exp(truncation=None)

    @property
    def order(self) -> int:
        return EXACT_ORDER

    @property
    def is_symmetric(self) -> bool:
        """An exact flow is a group in h: φ_{−h} = φ_h⁻¹."""
        return True

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        del carried
        dtype = jnp.result_type(*jax.tree.leaves(y))
        t, dt = jnp.asarray(t, dtype), jnp.asarray(dt, dtype)
        y_next = self.scene.solved_flow(t, y, dt, args)
        if is_low_precision(dtype):
            # As `AbstractMethod.advance`: a product of rounded rotations
            # drifts off the group a little every step.
            y_next = self.bundle.renormalized(y_next)
        field_now = self.generator(vector_field, t, y, args)
        result = flag_nonfinite(RESULTS.successful, y_next)
        return Step(y_next, self.increment_between(y, y_next), result, jnp.array(0, jnp.int32), None, field_now)
