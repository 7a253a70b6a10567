"""Symmetric compositions Ψ_h = Φ_{γ_m h} ∘ … ∘ Φ_{γ₁ h} of a method's steps.

Compositions raise the order of a *symmetric* base (Φ_{−h} ∘ Φ_h = id) and
keep what every sub-step keeps: the state stays on the group, Casimirs and
momentum maps conserved by the base stay conserved, a symplectic base gives
a symplectic method (`compositions` holds the coefficient sets).
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from ..compositions import CompositionCoefficients
from .adjoint import AbstractMadeOfSteps
from .base import RESULTS, AbstractMethod, Step, batched_like, compensated, first_failure, fractions_and_starts, no_compensation


class Composition(AbstractMadeOfSteps):
    """Ψ_h = Φ_{γ_m h} ∘ … ∘ Φ_{γ₁ h}: m steps of `method` with the step
    fractions of `coefficients` (e.g. `kahan_li_6`, `triple_jump(4)`).

    The coefficients raise the order of a *symmetric* base of order
    `coefficients.base_order` (checked: the orders must match) to
    `coefficients.order`; of a base that is not symmetric, the composition
    keeps the base's order (Störmer–Verlet with the exact dexp⁻¹ composed by
    `kahan_li_6` measures order 3, not 6). So `order` is
    `coefficients.order` when the base is symmetric by construction
    (`method.is_symmetric`: `Symmetrized`, `Splitting`) or when
    `assume_symmetric_base=True` says it is on the user's problem (a PRKMK
    method's symmetry depends on the field: check it with
    `symmetry_defect`), and the base's order otherwise. The step is the same
    either way; `order` is what `PRKMKSolver` reports to diffrax (step-size
    control) and what the method promises.

    The sub-steps run in a `lax.scan`, so compile time does not grow with m;
    each sub-step's implicit stages start from the same sub-step of the
    previous step (`Step.carried`). Negative fractions step backwards
    in time, which every PRKMK method allows.
    """

    method: AbstractMethod
    coefficients: CompositionCoefficients = eqx.field(static=True)
    assume_symmetric_base: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if not isinstance(self.method, AbstractMethod):
            raise TypeError(f"Composition composes a PRKMK method (or another composition), got {type(self.method).__name__}.")
        if not isinstance(self.coefficients, CompositionCoefficients):
            raise TypeError(f"coefficients must be CompositionCoefficients, got {type(self.coefficients).__name__}.")
        if self.method.order != self.coefficients.base_order:
            raise ValueError(
                f"{self.coefficients.name} raises a symmetric base of order {self.coefficients.base_order}, but the method "
                f"has order {self.method.order}; use coefficients for that order (e.g. triple_jump({self.method.order}))."
            )
        if not isinstance(self.assume_symmetric_base, bool):
            raise TypeError(f"assume_symmetric_base must be True or False, got {self.assume_symmetric_base!r}.")

    @property
    def order(self) -> int:
        if self.method.is_symmetric or self.assume_symmetric_base:
            return self.coefficients.order
        return self.method.order

    @property
    def is_symmetric(self) -> bool:
        # A palindrome of symmetric steps is symmetric.
        return self.method.is_symmetric or self.assume_symmetric_base

    def initial_carried(self, vector_field, t, y, args=None):
        m = self.coefficients.num_steps
        carried = self.method.initial_carried(vector_field, t, y, args)
        return jax.tree.map(lambda x: jnp.broadcast_to(x, (m,) + jnp.shape(x)), carried)

    def start_field(self, carried):
        return self.method.start_field(jax.tree.map(lambda x: x[0], carried))

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        dtype = jnp.result_type(*jax.tree.leaves(y))
        dt = jnp.asarray(dt, dtype)
        t = jnp.asarray(t, dtype)
        fractions, starts = fractions_and_starts(self.coefficients, dtype)

        sums = []  # whether the sub-step hands on a rounding, seen as the scan traces it

        def substep(state, inputs):
            y_k, lost, result, iterations = state
            fraction, start, carried_k = inputs
            sub = self.method.step(vector_field, t + start * dt, y_k, fraction * dt, args, carried_k)
            # The sub-steps' roundings summed as the drivers sum steps' (`compensated`).
            sums.append(sub.rounding is not None)
            y_k, lost = compensated(sub.y, sub.rounding, lost)
            return (y_k, lost, first_failure(result, sub.result), iterations + sub.iterations), sub.carried

        init = (y, *batched_like((no_compensation(y), RESULTS.successful, jnp.array(0, jnp.int32)), y))
        (y_next, lost, result, iterations), carried = jax.lax.scan(substep, init, (fractions, starts, carried))
        return Step(y_next, self.increment_between(y, y_next), result, iterations, lost if any(sums) else None, carried)
