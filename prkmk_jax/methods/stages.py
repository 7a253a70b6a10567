"""The pieces of a PRKMK step around its stages: the tableau sums, the
explicit stages laid out in a loop, and the warm start of the implicit
stages from the previous step's slopes (`PRKMK`, `Adjoint`)."""

import math
from collections.abc import Callable
from typing import Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .._bundles import AlgebraPair
from ..tableaus import PartitionedTableau
from .base import RESULTS, differentiated_as, first_failure
from .stage_plan import Explicit

STAGE_LOOP_BATCH = 16
"""From this many trajectories in the state on, `explicit_stages="auto"`
evaluates an explicit tableau's stages in a loop (`PRKMK`). The rule: the
loop from the batch at which the two layouts' step times are level, for
beyond it the arithmetic on the batch sets a step's time and the loop is
as fast or faster (and a many-stage tableau compiles faster in the loop).
`benchmarks/throughput.py`
times both layouts at 1, 8, 16 and 1024 trajectories, for RK 4 and
Dormand–Prince 8 on T*SO(3) and G×g. Derivatives take the loop at every
batch (`unrolled_unless_differentiated`)."""


def check_stage_pairs(name, pairs, zeros, count=None):
    """Trace-time check that `pairs` is None or a sequence of `count` algebra
    pairs (ξ, η) with the shapes of `zeros`."""
    if pairs is None:
        return
    if not isinstance(pairs, (tuple, list)) or (count is not None and len(pairs) != count):
        raise ValueError(f"{name} must be a tuple of {count or 1} algebra pairs (ξ, η), got {jax.tree.structure(pairs)}.")
    for pair in pairs:
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2) or any(
            tuple(jnp.shape(x)) != tuple(z.shape) for x, z in zip(pair, zeros)
        ):
            raise ValueError(
                f"{name}: every entry must be a pair (ξ, η) of shapes {tuple(z.shape for z in zeros)}, got {jax.tree.map(jnp.shape, pair)}."
            )


def static_combination(dt, coefficients, slopes, zero):
    """dt·Σ_j coefficients[j]·slopes[j] over the nonzero (static) coefficients
    and the slopes that are not None (zero, or not needed: see `stage_plan`),
    or None when no term is left.

    Three terms or more are summed as one contraction of the stacked slopes:
    XLA then computes each slope once, where a chain of multiply-adds lets it
    fuse (and so recompute) each slope's whole arithmetic into every stage
    that sums it."""
    terms = [(c, slope) for c, slope in zip(coefficients, slopes) if c != 0 and slope is not None]
    if not terms:
        return None
    if len(terms) >= 3:
        weights = jnp.asarray([c for c, _ in terms], zero.dtype)
        return dt * jnp.tensordot(weights, jnp.stack([slope for _, slope in terms]), axes=1)
    acc = None
    for c, slope in terms:
        term = slope if c == 1 else jnp.asarray(c, zero.dtype) * slope
        acc = term if acc is None else acc + term
    return dt * acc


def stages_in_loop(layout: Literal["auto", "unrolled", "loop"], tableau: PartitionedTableau, zeros, algebra_ndim: int) -> bool:
    """Whether a step evaluates its (explicit) stages in a loop: `layout`
    as `PRKMK(explicit_stages=...)` gives it; "auto" takes the loop for an
    explicit tableau on a state of at least `STAGE_LOOP_BATCH` trajectories."""
    if layout != "auto":
        return layout == "loop"
    batch_shape = zeros[0].shape[: zeros[0].ndim - algebra_ndim]
    return tableau.is_explicit and math.prod(batch_shape) >= STAGE_LOOP_BATCH


def explicit_slopes_in_loop(tableau: PartitionedTableau, stage_slope, slope_at: Callable, computed: set, t, dt, zeros):
    """The slopes of an explicit tableau, stage after stage in a
    `lax.fori_loop`: stage i reads the rows A¹ᵢ, A²ᵢ and the slopes found
    so far (zeros in the later entries, which the strictly lower
    triangular rows do not reach). `stage_slope(0, …)` gives the first
    stage, `slope_at(time, (u, v))` the slope at an increment; `computed`
    holds the components the plan computes. Returns the two lists of
    slopes, None for a component the plan never computes (L when η ≡ 0)."""
    tab = tableau
    dtype = zeros[0].dtype
    first_slope = stage_slope(0, [None] * tab.num_stages, [None] * tab.num_stages)
    buffers = []
    for c, zero in enumerate(zeros):
        buffer = jnp.zeros((tab.num_stages, *zero.shape), dtype)
        buffers.append(buffer.at[0].set(first_slope[c]) if c in computed else buffer)
    a_first, a_second, c_first = (jnp.asarray(x, dtype) for x in (tab.a_first, tab.a_second, tab.c_first))

    def one_stage(i, buffers):
        first, second = buffers
        u = dt * jnp.tensordot(a_first[i], first, axes=1)
        v = dt * jnp.tensordot(a_second[i], second, axes=1) if 1 in computed else None
        pair = slope_at(t + c_first[i] * dt, (u, v))
        return tuple(b.at[i].set(p) if c in computed else b for c, (b, p) in enumerate(zip(buffers, pair)))

    buffers = jax.lax.fori_loop(1, tab.num_stages, one_stage, tuple(buffers))
    return tuple(list(b) if c in computed else [None] * tab.num_stages for c, b in enumerate(buffers))


def explicit_slopes(layout, tableau: PartitionedTableau, plan, stage_slope, slope_at: Callable, t, dt, zeros, algebra_ndim: int) -> list:
    """The slopes of an explicit tableau ([K₁…K_s], [L₁…L_s], None for a
    component the plan never computes): in a loop or unrolled as
    `stages_in_loop` says, and in the loop wherever they are differentiated
    (`unrolled_unless_differentiated`). `stage_slope(i, first, second)` and
    `slope_at(time, (u, v))` as `PRKMK` gives them."""
    computed = {c for part in plan if isinstance(part, Explicit) for c in part.components}

    def loop():
        return list(explicit_slopes_in_loop(tableau, stage_slope, slope_at, computed, t, dt, zeros))

    if stages_in_loop(layout, tableau, zeros, algebra_ndim):
        return loop()
    unrolled = lambda: slopes_by_plan(plan, tableau.num_stages, stage_slope, None, None, zeros[0].dtype)[0]  # noqa: E731
    return unrolled_unless_differentiated(unrolled, loop, tableau.num_stages)


def unrolled_unless_differentiated(unrolled: Callable[[], list], loop: Callable[[], list], num_stages: int) -> list:
    """The slopes of an explicit tableau ([K₁…K_s], [L₁…L_s], None where not
    computed) as `unrolled()` gives them, and, where they are differentiated
    (forward or reverse mode), as `loop()` (`explicit_slopes_in_loop`) does.

    The two are the same function; what differs is the program XLA compiles
    for the derivative. Unrolled, the derivative of all the stages at once
    is one graph of small arithmetic that XLA's fusion copies into each of
    its consumers (a gradient of Dormand–Prince 8 at one trajectory
    compiles for minutes); in the loop it is one stage's derivative,
    compiled once. A differentiated run's states then differ from the
    plain run's in the last bits, as the two layouts' do."""
    positions: list[tuple[int, int]] = []

    def unrolled_leaves():
        slopes = unrolled()
        positions[:] = [(c, i) for c, part in enumerate(slopes) for i, slope in enumerate(part) if slope is not None]
        return [slopes[c][i] for c, i in positions]

    def loop_leaves():
        slopes = loop()
        return [slopes[c][i] for c, i in positions]

    leaves = differentiated_as(unrolled_leaves, loop_leaves)
    slopes: list[list] = [[None] * num_stages, [None] * num_stages]
    for (c, i), leaf in zip(positions, leaves, strict=True):
        slopes[c][i] = leaf
    return slopes


def slopes_by_plan(plan, num_stages: int, stage_slope, guesses, solve, dtype):
    """The stage slopes in the order of the stage plan (`stage_plan`): an
    explicit part evaluated by `stage_slope(i, first, second)`, an implicit
    block solved by `solve(block_slopes, guess)` (a `StageSolve`) from
    `guesses`. Returns ([K₁…K_s], [L₁…L_s]) (None where the plan computes
    nothing: L when η ≡ 0), the first failure and the iterations."""
    slopes: list[list] = [[None] * num_stages, [None] * num_stages]
    result, iterations = RESULTS.successful, jnp.array(0, jnp.int32)
    for part in plan:
        if isinstance(part, Explicit):
            pair = stage_slope(part.stage, *slopes)
            for c in part.components:
                slopes[c][part.stage] = pair[c]
            continue

        def block_slopes(block, part=part):
            trial = [list(slopes[0]), list(slopes[1])]
            for (i, c), value in zip(part.slopes, block):
                trial[c][i] = value
            pairs = {i: stage_slope(i, *trial) for i in part.stages}
            return tuple(pairs[i][c] for i, c in part.slopes)

        guess = tuple(jnp.asarray(guesses[i][c], dtype) for i, c in part.slopes)
        block, block_result, n = solve(block_slopes, guess)
        result, iterations = first_failure(result, block_result), iterations + n
        for (i, c), value in zip(part.slopes, block):
            slopes[c][i] = value
    return slopes, result, iterations


_UNSIGNED_OF_WIDTH = {2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint64}


def start_side(fiber: PyTree) -> Array:
    """+1 or −1: the parity of the sum of the lowest bits of the fiber's
    entries (their binary representation). A deterministic choice that
    the rounding of each step changes at random, with no state to carry;
    with a batch in the state, one choice for the whole batch."""
    parity = 0
    for leaf in jax.tree.leaves(fiber):
        bits = jax.lax.bitcast_convert_type(leaf, _UNSIGNED_OF_WIDTH[jnp.dtype(leaf.dtype).itemsize])
        parity = parity + jnp.sum(bits & 1)
    return jnp.where(parity % 2 == 0, 1, -1)


def extrapolated_guesses(field_now: AlgebraPair, carried, side: Array | None) -> tuple[AlgebraPair, ...]:
    """The implicit stages' starting guesses from what the previous step
    carried, (X(tₙ₋₁, yₙ₋₁), its stage slopes), and the field X(tₙ, yₙ) at
    this step's start: Gᵢ = Kᵢ_prev + X(tₙ, yₙ) − X(tₙ₋₁, yₙ₋₁), an O(h²)
    guess where X(tₙ, yₙ) alone is O(h).

    With a `side` (±1, `start_side`), the guesses are moved to one side of
    Gᵢ or the other, to Gᵢ ± Dᵢ with Dᵢ = Kᵢ_prev − X(tₙ₋₁, yₙ₋₁) (so that
    the − side is the field at the step's start). Solved to round-off, the
    point where the iteration settles depends on the side it comes from,
    and a start on the same side at every step makes the energy error drift
    the same way at every step; starts on either side at random cancel
    that drift, for about one iteration a step more."""
    previous_field, previous_stages = carried
    change = jax.tree.map(jnp.subtract, field_now, previous_field)
    guesses = tuple(jax.tree.map(jnp.add, stage, change) for stage in previous_stages)
    if side is None:
        return guesses
    offsets = tuple(jax.tree.map(jnp.subtract, stage, previous_field) for stage in previous_stages)
    chosen: Array = side
    return tuple(jax.tree.map(lambda g, d: g + chosen.astype(g.dtype) * d, guess, offset) for guess, offset in zip(guesses, offsets))
