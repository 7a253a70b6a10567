"""The PRKMK step: Algorithm 4.2 of the paper, generic over bundle group,
coordinate map and partitioned tableau.

Two forms of the vector field `f(t, y, args) -> (ξ, η)` are supported:

* `form="space"` (the paper's, Algorithm 4.2): y' = (ξ, η)·y. With
  y = f(U)·yₙ the algebra ODE is U' = df⁻¹_U(ξ, η) and yₙ₊₁ = f(Uₙ₊₁)·yₙ.
* `form="body"`: y' = y·(ξ, η), e.g. Q' = QΩ of (3.3). With y = yₙ·f(U),
  y⁻¹ = f(−U)·yₙ⁻¹ solves (y⁻¹)' = −(ξ, η)·y⁻¹ (both coordinate maps satisfy
  f(−U) = f(U)⁻¹), so the space form applied to −U gives
  U' = df⁻¹_{−U}(ξ, η) and yₙ₊₁ = yₙ·f(Uₙ₊₁). For exp this is the series
  Σ B_k/k! (−ad_U)^k, the left-trivialised dexp⁻¹ of Table 2.2.

Stage slopes (K, L) are found block by block: the stage dependency pattern
of the two A matrices splits into consecutive blocks; a block that depends
only on earlier stages is evaluated directly, an implicit block is solved by
fixed-point iteration (or any optimistix root finder) to `rtol`/`atol` within
`max_iterations`. Non-convergence is returned as a `diffrax.RESULTS` value.
"""

from collections.abc import Callable
from typing import Any, Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, PyTree

from .bundles import AbstractBundle, AlgebraPair, BundleElement
from .coordinates import AbstractCoordinates, Exp
from .tableaus import PartitionedTableau, stormer_verlet

RESULTS = diffrax.RESULTS
VectorField = Callable[[Array, BundleElement, PyTree], AlgebraPair]


def stage_blocks(tableau: PartitionedTableau) -> list[tuple[tuple[int, ...], bool]]:
    """Consecutive stage blocks and whether each is implicit.

    A cut before stage k is allowed when no stage i < k depends on a stage
    j ≥ k in either A matrix; a block is implicit when a stage in it depends
    on itself or on a later stage of the block.
    """
    dep = (tableau.a_first != 0) | (tableau.a_second != 0)
    s = tableau.num_stages
    blocks, start = [], 0
    for k in range(1, s + 1):
        if k == s or not dep[:k, k:].any():
            idx = tuple(range(start, k))
            sub = dep[np.ix_(idx, idx)]
            blocks.append((idx, bool(np.triu(sub).any())))
            start = k
    return blocks


def _tree_scale(alpha, tree):
    return jax.tree.map(lambda x: alpha * x, tree)


def _default_float_max_norm(x):
    # FixedPointIteration starts its error state as jnp.array(inf), i.e. in the
    # default float dtype; returning the norm in that dtype keeps its loop
    # state type-stable for float32 states under jax_enable_x64.
    return jnp.asarray(optx.max_norm(x), jnp.result_type(float))


class PRKMK(eqx.Module):
    """A partitioned Runge–Kutta–Munthe-Kaas method (Algorithm 4.2).

    **Arguments:**

    - `bundle`: the bundle group, e.g. `Cartesian(SO3)` or `Cotangent(SO3)`.
    - `coordinates`: `Exp()` or `Cayley()`, with their truncation.
    - `tableau`: a `PartitionedTableau`, e.g. `stormer_verlet`.
    - `form`: `"space"` for y' = (ξ, η)·y, `"body"` for y' = y·(ξ, η).
    - `rtol`, `atol`: tolerances of the implicit stages (on the slopes);
      default max(1e-12, 50·eps) of the state's dtype.
    - `max_iterations`: iteration cap of each implicit block.
    - `root_finder`: an optimistix fixed-point solver or root finder (e.g.
      `optx.Newton(rtol, atol)`); default fixed-point iteration, which
      converges when h times the field's Lipschitz constant is below 1 and
      slows down as it approaches 1 (symmetric rigid body at h = 0.1: ~94
      iterations a step, Newton: 4).
    """

    bundle: AbstractBundle
    coordinates: AbstractCoordinates = Exp()
    tableau: PartitionedTableau = eqx.field(static=True, default=stormer_verlet)
    form: Literal["space", "body"] = eqx.field(static=True, default="space")
    rtol: float | None = eqx.field(static=True, default=None)
    atol: float | None = eqx.field(static=True, default=None)
    max_iterations: int = eqx.field(static=True, default=100)
    root_finder: Any = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not isinstance(self.bundle, AbstractBundle):
            raise TypeError(f"bundle must be a bundle group such as Cartesian(SO3), got {self.bundle!r}.")
        if not isinstance(self.coordinates, AbstractCoordinates):
            raise TypeError(f"coordinates must be Exp() or Cayley(), got {self.coordinates!r}.")
        if not isinstance(self.tableau, PartitionedTableau):
            raise TypeError(f"tableau must be a PartitionedTableau, got {type(self.tableau).__name__}.")
        if self.form not in ("space", "body"):
            raise ValueError(f"form must be 'space' (y' = X·y) or 'body' (y' = y·X), got {self.form!r}.")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"max_iterations must be a positive int, got {self.max_iterations!r}.")
        if self.root_finder is not None and not isinstance(
            self.root_finder, (optx.AbstractFixedPointSolver, optx.AbstractRootFinder)
        ):
            raise TypeError("root_finder must be an optimistix fixed-point solver or root finder.")
        self.coordinates.check_bundle(self.bundle)

    @property
    def order(self) -> int:
        return self.tableau.order

    # --- pieces of Algorithm 4.2 ----------------------------------------------------
    def apply_increment(self, U: AlgebraPair, y: BundleElement) -> BundleElement:
        """f(U)·y (space form) or y·f(U) (body form)."""
        f_of_u = self.coordinates.map(self.bundle, U)
        if self.form == "space":
            return self.bundle.multiply(f_of_u, y)
        return self.bundle.multiply(y, f_of_u)

    def slope(self, U: AlgebraPair, X: AlgebraPair) -> AlgebraPair:
        """U' for the generator X at the point reached by the increment U:
        df⁻¹_U(X) (space form) or df⁻¹_{−U}(X) (body form), truncated as
        the coordinates say."""
        if self.form == "body":
            U = _tree_scale(-1.0, U)
        return self.coordinates.inverse_differential(self.bundle, U, X, self.order)

    def generator(self, vector_field: VectorField, t, y: BundleElement, args) -> AlgebraPair:
        """(ξ, η) = vector_field(t, y, args) in the state's dtype, whatever
        precision the user's field returns."""
        zeros = self.bundle.algebra_zeros(y)
        return tuple(jnp.asarray(x, z.dtype) for x, z in zip(vector_field(t, y, args), zeros))

    def check_vector_field(self, vector_field: VectorField, t, y: BundleElement, args) -> None:
        """Trace-time check that `vector_field(t, y, args)` returns a pair
        (ξ, η) of algebra arrays of the right shapes."""
        out = jax.eval_shape(vector_field, t, y, args)
        zeros = self.bundle.algebra_zeros(y)
        if not (isinstance(out, (tuple, list)) and len(out) == 2):
            raise ValueError(
                f"the vector field must return a pair (ξ, η) of algebra elements, got {jax.tree.structure(out)}."
            )
        for name, got, want in zip(("ξ", "η"), out, zeros):
            if not hasattr(got, "shape") or tuple(got.shape) != tuple(want.shape):
                raise ValueError(
                    f"the vector field returned {name} with shape {getattr(got, 'shape', type(got))}, "
                    f"but the algebra of {type(self.bundle).__name__}({self.bundle.base.__name__}) at this state has shape {want.shape}."
                )

    def step(
        self, vector_field: VectorField, t: Array, y: BundleElement, dt: Array, args: PyTree = None
    ) -> tuple[BundleElement, RESULTS, Array]:
        """One step from (t, y) to t + dt. Returns (y_next, result, iterations),
        `iterations` being the number of implicit iterations taken."""
        y_next, _, result, iterations = self.step_with_increment(vector_field, t, y, dt, args)
        return y_next, result, iterations

    def step_with_increment(
        self, vector_field: VectorField, t: Array, y: BundleElement, dt: Array, args: PyTree = None
    ) -> tuple[BundleElement, AlgebraPair, RESULTS, Array]:
        """As `step`, also returning the algebra increment Uₙ₊₁ of the step
        (yₙ₊₁ = `apply_increment(Uₙ₊₁, yₙ)`)."""
        self.check_vector_field(vector_field, t, y, args)
        tab = self.tableau
        dtype = jnp.result_type(*jax.tree.leaves(y))
        dt = jnp.asarray(dt, dtype)
        t = jnp.asarray(t, dtype)
        a1, a2 = jnp.asarray(tab.a_first, dtype), jnp.asarray(tab.a_second, dtype)
        c = jnp.asarray(tab.c_first, dtype)
        zeros = self.bundle.algebra_zeros(y)
        s = tab.num_stages

        def field(tt, Y):
            return self.generator(vector_field, tt, Y, args)
        slopes = jax.tree.map(lambda z: jnp.zeros((s,) + z.shape, z.dtype), zeros)

        def stage_slopes(idx, slopes):
            # U_i = h (Σ_j a¹_ij K_j, Σ_j a²_ij L_j), Y_i = f(U_i)⊙yₙ, slope_i = df⁻¹(X_i).
            idx = jnp.asarray(idx)
            u = dt * jnp.tensordot(a1[idx], slopes[0], axes=1)
            v = dt * jnp.tensordot(a2[idx], slopes[1], axes=1)

            def one(uu, vv, tt):
                return self.slope((uu, vv), field(tt, self.apply_increment((uu, vv), y)))

            return jax.vmap(one)(u, v, t + c[idx] * dt)

        result = RESULTS.successful
        iterations = jnp.array(0, jnp.int32)
        initial_guess = None
        for idx, implicit in stage_blocks(tab):
            if not implicit:
                block = stage_slopes(idx, slopes)
            else:
                if initial_guess is None:
                    # df⁻¹_0 = I: the slope at U = 0 is the field at yₙ.
                    initial_guess = field(t, y)
                guess = jax.tree.map(lambda x: jnp.broadcast_to(x, (len(idx),) + x.shape), initial_guess)

                def fixed_point_fn(block_slopes, _, idx=idx):
                    full = jax.tree.map(lambda f, b: f.at[jnp.asarray(idx)].set(b), slopes, block_slopes)
                    return stage_slopes(idx, full)

                block, block_result, n = self._solve(fixed_point_fn, guess, dtype)
                result = RESULTS.where(result == RESULTS.successful, block_result, result)
                iterations = iterations + n
            slopes = jax.tree.map(lambda f, b: f.at[jnp.asarray(idx)].set(b), slopes, block)

        b1, b2 = jnp.asarray(tab.b_first, dtype), jnp.asarray(tab.b_second, dtype)
        u_next = (dt * jnp.tensordot(b1, slopes[0], axes=1), dt * jnp.tensordot(b2, slopes[1], axes=1))
        y_next = self.apply_increment(u_next, y)
        finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(y_next)]))
        result = RESULTS.where((result == RESULTS.successful) & ~finite, RESULTS.nonfinite, result)
        return y_next, u_next, result, iterations

    def _solve(self, fn, guess, dtype):
        eps = float(jnp.finfo(dtype).eps)
        default_tol = max(1e-12, 50 * eps)
        rtol = default_tol if self.rtol is None else self.rtol
        atol = default_tol if self.atol is None else self.atol
        solver = self.root_finder
        if solver is None:
            solver = optx.FixedPointIteration(rtol=rtol, atol=atol, norm=_default_float_max_norm)
        if isinstance(solver, optx.AbstractFixedPointSolver):
            sol = optx.fixed_point(fn, solver, guess, max_steps=self.max_iterations, throw=False)
        else:
            sol = optx.root_find(
                lambda z, a: jax.tree.map(jnp.subtract, fn(z, a), z), solver, guess, max_steps=self.max_iterations, throw=False
            )
        return sol.value, RESULTS.promote(sol.result), sol.stats["num_steps"].astype(jnp.int32)
