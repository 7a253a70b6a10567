"""Methods made of another method's steps, and the adjoint Φ*_h = (Φ_{−h})⁻¹.

`AbstractMadeOfSteps` is a method built from the steps of another (on its
bundle, in its coordinates and form): `Adjoint` here, `Symmetrized` and
`Composition` beside it.
"""

import equinox as eqx
import jax

from .base import AbstractMethod, Step


class AbstractMadeOfSteps(AbstractMethod):
    """A method built from the steps of `method`: on its bundle, in its
    coordinates and form. Its backward-pass form has the inner method's."""

    method: eqx.AbstractVar[AbstractMethod]

    @property
    def bundle(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.method.bundle

    @property
    def coordinates(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.method.coordinates

    @property
    def form(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a property implements an AbstractVar
        return self.method.form

    def check_fits(self, vector_field):
        self.method.check_fits(vector_field)

    def for_reconstruction(self) -> AbstractMethod:
        return eqx.tree_at(lambda m: m.method, self, self.method.for_reconstruction())


class Adjoint(AbstractMadeOfSteps):
    """The adjoint Φ*_h = (Φ_{−h})⁻¹ of a PRKMK method Φ, or of a method
    symmetric by construction (a `Splitting`: its adjoint is itself, and its
    steps are taken as they are).

    Φ*_h(yₙ) is the y with Φ_{−h}(y) = yₙ: the method's stages centred at
    the step's end. With U_i = −h(Σⱼ a¹ᵢⱼKⱼ, Σⱼ a²ᵢⱼLⱼ), W = h(Σⱼ b¹ⱼKⱼ, Σⱼ b²ⱼLⱼ),
    yₙ₊₁ = f(W)·yₙ (space form; yₙ·f(W) in body form) and stage points
    Y_i = f(U_i)·yₙ₊₁, the slopes solve (K_i, L_i) = df⁻¹_{U_i}(X(tₙ₊₁ − c_i h,
    Y_i)) — one implicit system for all stages (yₙ₊₁ depends on every slope),
    solved by the method's root finder. Then f(−W)·yₙ₊₁ = yₙ is the reversed
    step, since f(−W) = f(W)⁻¹ for both coordinate maps. In a vector space
    this is the PRK method of the adjoint tableau.

    The system is as small as the method's own stage plan allows: where the
    field has η ≡ 0 (`stage_plan`; not with `coupling="tableau"`) the K's
    alone are unknowns, and a stage whose rows of A are the weights (the
    last of Lobatto IIIA) has U_i = −W, so Y_i = yₙ, where the field is
    known: only df⁻¹_{−W} changes with the iterate. An adjoint step of
    Störmer–Verlet on the free body then costs what the method's step does.
    """

    method: AbstractMethod

    def __check_init__(self):
        if not isinstance(self.method, AbstractMethod) or not self.method.has_adjoint_step:
            raise TypeError(
                f"Adjoint takes a PRKMK method (its stages are re-centred) or a method symmetric by construction, "
                f"got {type(self.method).__name__}."
            )

    @property
    def order(self) -> int:
        return self.method.order

    @property
    def is_symmetric(self) -> bool:
        return self.method.is_symmetric

    @property
    def has_adjoint_step(self) -> bool:
        return self.is_symmetric

    def initial_carried(self, vector_field, t, y, args=None):
        return self.method.initial_carried(vector_field, t, y, args)

    def start_field(self, carried):
        return self.method.start_field(carried)

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        return self.method.adjoint_carried_step(vector_field, t, y, dt, args, carried)

    def undoing_method(self) -> AbstractMethod:
        """The method's step of −h undoes one of its adjoint: Φ*_h = Φ_{−h}⁻¹."""
        return self if self.is_symmetric else self.method

    def step_again(self, vector_field, t, y, dt, args, undone_carried) -> Step:
        """The method's step at −h solved the same stage equations as this
        one: their slopes are evaluated once (as `PRKMK.step_at_stages`)."""
        if self.is_symmetric:  # Φ* = Φ
            return self.method.step_again(vector_field, t, y, dt, args, undone_carried)
        stages = jax.lax.stop_gradient(undone_carried)
        return self.method.adjoint_carried_step(vector_field, t, y, dt, args, stages, stages_solved=True)
