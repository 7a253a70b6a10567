"""Exact-flow splitting methods on a bundle group.

A scene that splits (`exact_flows.AbstractSplitScene`: the free rigid body
into its three axis terms, the heavy top into those and a momentum kick, …)
is integrated by composing the parts' exact flows symmetrically (Strang):

    Φ_h = φ₁(h/2) ∘ … ∘ φ_{k−1}(h/2) ∘ φ_k(h) ∘ φ_{k−1}(h/2) ∘ … ∘ φ₁(h/2),

applied right to left: φ₁ first. Φ is symmetric (Φ_{−h} = Φ_h⁻¹) of order
2, explicit, and keeps whatever every part keeps: for the rigid bodies the
group (each part is a group action y·exp(tX), X constant along it), the
momentum map, |Π| and the Casimirs, to round-off. A composition with
coefficients γ₁ … γ_m (`compositions`) raises the order to 4, 6 or 8
(Yoshida 1990; McLachlan 1995). For the free rigid body with axis terms this
is the splitting of Dullweber, Leimkuhler & McLachlan (J. Chem. Phys. 107,
1997) and Reich (1994), studied by Fassò (J. Comput. Phys. 189, 2003); the
NO_SQUISH integrator of molecular dynamics (Miller et al., J. Chem. Phys.
116, 2002) uses the same rotations.

Seen on the bundle group, every sub-step is y·f(hX) with the coordinate map
f: `Exp()` gives the exact flows; `Cayley()` turns each rotation by
2·atan(tω/2) instead of tω, cheaper to evaluate (no sine), still symmetric
and on the group, with a larger error constant.

Time: a part that depends on time (an external torque) is frozen at the
time its sub-step starts on the way in, t, and at t + h on the way back; the
middle part φ_k runs at t + h/2. This is Strang splitting of the system with
the clock t' = 1 added to φ_k, so it keeps symmetry and order 2.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from .._bundles import BundleElement
from .._exact_sums import two_sum
from .._fields import Time
from ..compositions import CompositionCoefficients
from ..coordinates import AbstractCoordinates, Exp
from ..exact_flows import AbstractSplitScene, FreePart
from ..groups._util import LOW_PRECISION_EPS, is_low_precision
from ..groups.trig import computed_once
from .base import RESULTS, AbstractOfOneScene, Step, check_parts, differentiated_as, flag_nonfinite, fractions_and_starts


def sub_steps(num_parts: int, fractions: tuple[float, ...], merge: bool) -> tuple[tuple[int, float, float], ...]:
    """The sequence of sub-steps (part, start time, step), in units of h, of
    the Strang splittings with step fractions `fractions` run one after the
    other. With `merge`, the outermost part's last half step of one Strang
    step and its first of the next, which start at the same time, are one
    sub-step (the exact flows of a part compose: φ(a)∘φ(b) = φ(a + b))."""
    steps: list[tuple[int, float, float]] = []
    start = 0.0
    for gamma in fractions:
        inward = [(p, start, gamma / 2) for p in range(num_parts - 1)]
        middle = [(num_parts - 1, start + gamma / 2, gamma)]
        outward = [(p, start + gamma, gamma / 2) for p in reversed(range(num_parts - 1))]
        for entry in inward + middle + outward:
            if merge and steps and steps[-1][0] == entry[0] == 0 and num_parts > 1 and steps[-1][1] == entry[1]:
                steps[-1] = (0, entry[1], steps[-1][2] + entry[2])
            else:
                steps.append(entry)
        start += gamma
    return tuple(steps)


class Splitting(AbstractOfOneScene):
    """The exact-flow splitting of `scene` (module docstring).

    **Arguments:**

    - `scene`: a scene that splits (`FreeRigidBody`, `HeavyTop`,
      `ForcedRigidBody`, `Satellite`, `SymmetricRigidBody` on SO(3)×SO(3));
      also built by its `splitting()` method.
    - `coefficients`: `None` for the Strang splitting (order 2), or a
      symmetric composition of it (`suzuki_5`, `kahan_li_6`, `kahan_li_8`,
      …; order `coefficients.order`). The composed step is unrolled, and
      with a map that sends lines to subgroups (`Exp()`) adjacent flows of
      the outermost part are merged; differentiated (`jax.grad`,
      `jax.jvp`), its Strang steps run in a `lax.scan`, whose derivative
      compiles as one Strang step's (its states then differ from the plain
      run's in the last bits).
    - `coordinates`: `Exp()` (exact flows, default), `Cayley()` or any
      `AbstractCoordinates` (each rotation turned as its `planar_rotation` says).
    - `free_part`: how a rigid body's kinetic energy is split: "axes"
      (default), its three axis terms, each a rotation about a body axis;
      "exact", one part, the free body's flow in closed form (Jacobi's
      elliptic functions, `scenes.free_body_flow`), so that only the
      potential or the torque is split off: a smaller error constant, but
      each sub-step evaluates elliptic functions where "axes" turns three
      rotations, so it pays only for a nearly free body
      (`docs/concepts/choosing.md`; the heavy top, the forced body). A composed
      step then runs its Strang steps in a `lax.scan`, whose program holds
      one copy of the flow.
    - `compensated_sum`: in low precision (float32), True (default) runs
      the sub-steps on the step's change and adds it to the state once,
      carrying what that sum loses into the next step (`compensated`), so
      that a long run's rounding does not accumulate; False turns the state
      itself, by shears, a quicker step whose rounding does accumulate. In
      float64 the two are the same step.

    The method integrates `scene` only: `integrate`, `resume` and
    `PRKMKSolver` refuse another vector field. A batch runs as fast under
    `jax.vmap` as with the trajectories as leading axes of the state (one
    run of all of them): either way the step packs the state with its
    components first, the layout XLA vectorises, and computes each
    rotation's sine and cosine once (`groups.computed_once`).
    """

    scene: AbstractSplitScene  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox: a field implements an AbstractVar, narrowed
    coefficients: CompositionCoefficients | None = eqx.field(static=True, default=None)
    coordinates: AbstractCoordinates = Exp()
    compensated_sum: bool = eqx.field(static=True, default=True)
    free_part: FreePart = eqx.field(static=True, default="axes")
    built_by: ClassVar[str] = "scene.splitting(), or use a PRKMK method"  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar

    def __check_init__(self):
        if self.free_part not in ("axes", "exact"):
            raise ValueError(f"free_part must be 'axes' or 'exact', got {self.free_part!r}.")
        if not isinstance(self.compensated_sum, bool):
            raise TypeError(f"compensated_sum must be True or False, got {self.compensated_sum!r}.")
        if not isinstance(self.scene, AbstractSplitScene):
            raise TypeError(
                f"Splitting needs a scene that splits into exactly solvable parts (an AbstractSplitScene such as FreeRigidBody), "
                f"got {type(self.scene).__name__}; for other fields use a PRKMK method."
            )
        if self.coefficients is not None:
            if not isinstance(self.coefficients, CompositionCoefficients):
                raise TypeError(f"coefficients must be None or CompositionCoefficients, got {type(self.coefficients).__name__}.")
            if self.coefficients.base_order != 2:
                raise ValueError(
                    f"{self.coefficients.name} raises a symmetric base of order {self.coefficients.base_order}; "
                    "the Strang splitting has order 2 (use e.g. triple_jump(2), suzuki_5, kahan_li_6, kahan_li_8)."
                )
        check_parts(self.scene.bundle, self.coordinates, self.scene.form)

    @property
    def order(self) -> int:
        return 2 if self.coefficients is None else self.coefficients.order

    @property
    def is_symmetric(self) -> bool:
        """The Strang composition of exact flows, and symmetric compositions of it, are symmetric."""
        return True

    def carried_step(self, vector_field, t, y, dt, args, carried) -> Step:
        del carried  # explicit: nothing to start from
        dtype = jnp.result_type(*jax.tree.leaves(y))
        t, dt = jnp.asarray(t, dtype), jnp.asarray(dt, dtype)
        flows = self._parts(args)
        z = self.scene.pack(y, args)
        plan = self._sub_steps(len(flows))
        # At most one Strang step's sub-steps (2n − 1 for n parts) are left
        # to XLA to fuse; then their state is computed once (a barrier). Each
        # rotated row reads two rows of the sub-step before, so a longer fused
        # chain has XLA recompute earlier sub-steps many times over (a
        # composed step has dozens), while a barrier after every sub-step
        # costs more than it saves within one Strang step.
        fused = 2 * len(flows) - 1
        # In low precision the sub-steps move the step's change from z, not
        # z itself (`moved_change`), rounded relative to the change, and the
        # change is added to z once, its rounding handed on (`Step.rounding`):
        # a rounded rotation is much the same step after step of a steady
        # motion, and so is its rounding at the state's scale, which a long
        # run would accumulate.
        low = is_low_precision(dtype)
        change_only = low and self.compensated_sum

        def unrolled():
            z_k = jnp.zeros_like(z) if change_only else z
            for k, (part, start, step) in enumerate(plan, start=1):
                if change_only:
                    z_k = flows[part].flow_change(self.coordinates, t + start * dt, z, z_k, step * dt, args)
                else:
                    z_k = flows[part].flow(self.coordinates, t + start * dt, z_k, step * dt, args)
                if flows[part].always_materialised or (k % fused == 0 and k < len(plan)):
                    z_k = jax.lax.optimization_barrier(z_k)
            return z_k

        # A composed step's derivative is that of its Strang steps in a
        # `lax.scan`: unrolled, XLA compiles the derivative of dozens of
        # sub-steps as one graph, many times larger (`differentiated_as`).
        def in_loop():
            z_end = self._strang_steps_in_loop(flows, t, dt, z, args)
            return z_end - z if change_only else z_end

        if self.coefficients is None:
            z_k = unrolled()
        elif self.free_part == "exact":
            # The free body's exact flow is a program of loops of its own (the
            # elliptic functions): unrolled, a composed step would compile one
            # copy of it for each of its Strang steps.
            z_k = in_loop()
        else:
            z_k = differentiated_as(lambda: _batch_axis_first(unrolled()), lambda: _batch_axis_first(in_loop()))
        rounding = None
        if change_only:
            # What the sum lost is unpacked as the state is (a relabelling of
            # its entries, `AbstractSplitScene.pack`).
            z, lost = two_sum(z, z_k)
            rounding = jax.lax.stop_gradient(self.scene.unpack(lost, y, args))
        else:
            z = z_k
        if low:
            # As `AbstractMethod.advance`: the rounding of each rotation is
            # systematic for steady motions and would pull the state off the group.
            z = self.scene.onto_group(z)
        y_next = self.scene.unpack(z, y, args)
        field_now = self.generator(vector_field, t, y, args)
        result = flag_nonfinite(RESULTS.successful, y_next)
        return Step(y_next, self.increment_between(y, y_next), result, jnp.array(0, jnp.int32), rounding, field_now)

    def pulled_back_step(self, t, y_next, dt, args, cotangent):
        """In float64, `reverse_step`: undone and differentiated from the
        step's end, each sub-flow once. In low precision None: the step's
        renormalisation onto the group has no inverse, and the backward pass
        undoes the step by its step of −dt and differentiates it."""
        if is_low_precision(jnp.result_type(*jax.tree.leaves(y_next))):
            return None
        return self.reverse_step(t, y_next, dt, args, cotangent)

    def _strang_steps_in_loop(self, flows, t, dt, z, args):
        """The composed step as a `lax.scan` of its Strang steps, no flows
        merged (φ(a)∘φ(b) = φ(a + b)): the same map, whose derivative
        compiles as one Strang step's."""
        assert self.coefficients is not None
        fractions, starts = fractions_and_starts(self.coefficients, dt.dtype)

        def strang_step(z, fraction_and_start):
            fraction, start = fraction_and_start
            for part, offset, step in sub_steps(len(flows), (1.0,), merge=False):
                z = flows[part].flow(self.coordinates, t + (start + offset * fraction) * dt, z, step * fraction * dt, args)
            return z, None

        return jax.lax.scan(strang_step, z, (fractions, starts))[0]

    def _parts(self, args: PyTree):
        """The scene's parts for `args`, its kinetic energy as `free_part` says."""
        return self.scene.exact_flows(args, free_part=self.free_part)

    def _sub_steps(self, num_parts: int) -> tuple[tuple[int, float, float], ...]:
        """This method's sub-steps (`sub_steps`): its composition's fractions,
        adjacent flows merged where the map sends lines to subgroups."""
        fractions = (1.0,) if self.coefficients is None else self.coefficients.fractions
        return sub_steps(num_parts, fractions, merge=self.coordinates.maps_lines_to_subgroups)

    def reverse_step(self, t: Time, y_next: BundleElement, dt: Time, args: PyTree, cotangent: BundleElement):
        """The step from t to t + dt that ended at `y_next` undone, and a
        cotangent at its end pulled back through it: (y, the cotangent at y,
        the cotangent of `args`). Sub-step by sub-step from the last: each
        flow's coefficients, conserved along it, are computed at its end and
        undo it; its VJP is written out (`AbstractExactFlow.pulled_back`),
        with the coefficients' own VJP taken at the same point where they
        read only rows the flow leaves unchanged (and at the sub-step's start
        otherwise), so no sub-step is recomputed from its start. In float64
        this is the exact inverse and VJP of `step` to round-off; in low
        precision the step's renormalisation onto the group has no inverse,
        and this raises `ValueError` (undo by `step` of −dt and differentiate
        `step` instead)."""
        dtype = jnp.result_type(*jax.tree.leaves(y_next))
        if is_low_precision(dtype):
            raise ValueError(f"reverse_step needs a dtype with machine epsilon at most {LOW_PRECISION_EPS:g}, got {dtype}.")
        t, dt = jnp.asarray(t, dtype), jnp.asarray(dt, dtype)
        z = self.scene.pack(y_next, args)
        _, pull_unpack = jax.vjp(lambda z: self.scene.unpack(z, y_next, args), z)
        (cotangent_z,) = pull_unpack(cotangent)
        args_dynamic, args_static = eqx.partition(args, eqx.is_inexact_array)
        num_parts = len(self._parts(args))

        def back_through(part, start, step, z, cotangent_z, cotangent_args):
            """One sub-step (part `part` from t + start·dt over step·dt) undone
            from its end, and the cotangents pulled back through it."""

            def coefficients(z, args_dynamic):
                args = eqx.combine(args_dynamic, args_static)
                return self._parts(args)[part].coefficients(self.coordinates, t + start * dt, z, step * dt, args)

            flow = self._parts(args)[part]
            if flow.reads_unmoved_rows_only:
                # The coefficients and their derivatives are the same at the
                # sub-step's end as at its start: computed once.
                c, pull_coefficients = jax.vjp(coefficients, z, args_dynamic)
                z = flow.moved_back(z, c)
            else:
                z = flow.moved_back(z, coefficients(z, args_dynamic))
                c, pull_coefficients = jax.vjp(coefficients, z, args_dynamic)
            cotangent_moved, cotangent_c = flow.pulled_back(z, c, cotangent_z)
            cotangent_read, cotangent_args_part = pull_coefficients(cotangent_c)
            cotangent_args = jax.tree.map(jnp.add, cotangent_args, cotangent_args_part)
            # Each sub-step's state and cotangent are computed once, at any
            # batch: fused across sub-steps, XLA's program and its compile
            # time grow far faster than the number of sub-steps.
            z, cotangent_z = computed_once(z, cotangent_moved + cotangent_read)
            return z, cotangent_z, cotangent_args

        carry = (z, cotangent_z, jax.tree.map(jnp.zeros_like, args_dynamic))
        num_strang_steps = 1 if self.coefficients is None else len(self.coefficients.fractions)
        leading, parts, starts, steps = _as_repeated_steps(self._sub_steps(num_parts), num_parts, num_strang_steps)
        if len(starts) == 1:
            for part, start, step in zip(reversed(parts), reversed(starts[0]), reversed(steps[0])):
                carry = back_through(part, float(start), float(step), *carry)
        else:
            # A composed step's Strang steps from the last, in a `lax.scan`:
            # unrolled, XLA compiles the reverse of dozens of sub-steps.
            def back_one_strang_step(carry, starts_and_steps):
                for part, start, step in zip(reversed(parts), *(jnp.flip(x) for x in starts_and_steps)):
                    carry = back_through(part, start, step, *carry)
                return carry, None

            carry = jax.lax.scan(back_one_strang_step, carry, (jnp.asarray(starts, dtype), jnp.asarray(steps, dtype)), reverse=True)[0]
        for part, start, step in reversed(leading):
            carry = back_through(part, start, step, *carry)
        z, cotangent_z, cotangent_args = carry
        y = self.scene.unpack(z, y_next, args)
        _, pull_pack = jax.vjp(lambda y: self.scene.pack(y, args), y)
        (cotangent_y,) = pull_pack(cotangent_z)
        return y, cotangent_y, cotangent_args


def _batch_axis_first(z):
    """z unchanged, and under `vmap` with its batch axis first.

    `vmap` batches a custom JVP's function and its rule apart, and each
    result keeps the batch axis where its last operation left it: the
    unrolled sub-steps' rotated rows of the packed state leave it second,
    the scan of Strang steps first. Where a transformation evaluates both
    (a step under `jax.checkpoint` or in a scan, differentiated through a
    batch mapped with `vmap`), JAX pairs the value with the tangent as if
    their batch axes agreed, and the derivative fails on the mismatch.
    Joined by a concatenation, whose batching puts the batch axis first,
    both agree; unbatched, XLA folds the slices and their join away."""
    return jax.lax.concatenate([z[:1], z[1:]], 0)


def _as_repeated_steps(plan, num_parts: int, num_strang_steps: int):
    """`plan` (`sub_steps`) as (leading sub-steps, the parts of one repeated
    stretch, its starts and its steps): each Strang step is the same parts
    in the same order from the second sub-step on, where the outermost
    part's half steps are merged (the first sub-step leads), and from the
    first otherwise. Starts and steps are NumPy arrays, one row a Strang
    step, with the plan's own values."""
    merged = len(plan) < num_strang_steps * (2 * num_parts - 1)
    leading, rest = (plan[:1], plan[1:]) if merged else ((), plan)
    rows = np.asarray([entry[1:] for entry in rest], np.float64).reshape(num_strang_steps, -1, 2)
    parts = tuple(part for part, _, _ in rest[: rows.shape[1]])
    assert all(tuple(part for part, _, _ in rest[k * len(parts) : (k + 1) * len(parts)]) == parts for k in range(num_strang_steps))
    return leading, parts, rows[..., 0], rows[..., 1]
