"""Which stage slopes a PRKMK step must solve for together, and which it can
evaluate directly.

A stage of Algorithm 4.2 evaluates (Kᵢ, Lᵢ) = df⁻¹_{Uᵢ}(X(f(Uᵢ)⊙yₙ)) at
Uᵢ = h(Σⱼ a¹ᵢⱼKⱼ, Σⱼ a²ᵢⱼLⱼ). The tableau alone says which slopes enter which
stage point; the field, the bundle and the coordinate map often say that a
slope does not depend on all of them:

* The free rigid body on T*SO(3) has η ≡ 0 (the group product moves the
  fiber). Then L ≡ 0 is the solution of every stage, on every bundle and in
  both coordinate maps: the pairs (u, 0) form a subalgebra that df⁻¹ and the
  bracket keep, so U stays in it. Only the K's are unknowns, linked by A¹
  alone: Störmer–Verlet's first stage becomes explicit (K₁ = ξ(yₙ)) and
  Lobatto IIIA–IIIB 4 iterates two stages instead of three.
* A separable field (4.15), ξ = ξ(w) and η = η(g), on a bundle whose stage
  point moves g by u only and w by v only (G×g, G×G) and with df⁻¹ = I (the
  truncated equations: order ≤ 2), makes K depend on v and L on u only:
  symplectic Euler and Störmer–Verlet are then explicit, as the paper's
  remark after (4.15) says.

`stage_dependence` reads these facts from the traced program of one stage
evaluation (a superset of the true dependence, so never too few), and
`plan_stages` orders the slopes: strongly connected sets are solved by
fixed-point iteration, everything else is evaluated once, in dependency
order.
"""

import dataclasses
import functools
from typing import Any

import jax
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr, Literal

from ..tableaus import PartitionedTableau

_CLOSED = -1
"""Label of a value the traced function closed over (time, args, the state)."""


def output_dependence(fn, *inputs) -> list[tuple[frozenset[int], Any]]:
    """For each output leaf of `fn(*inputs)`: the positions of the `inputs`
    it depends on in the traced program, and its value when it depends on
    nothing at all (a constant; None otherwise).

    The dependence is structural: an operation's outputs depend on all its
    inputs, except inside nested jitted functions, which are followed. It can
    only over-state what the function depends on (x − x "depends" on x).
    """
    closed = jax.make_jaxpr(fn)(*inputs)
    labels = [frozenset({k}) for k, x in enumerate(inputs) for _ in jax.tree.leaves(x)]
    constants = [frozenset({_CLOSED})] * len(closed.jaxpr.constvars)
    env = _propagate(closed.jaxpr, constants, labels)
    out = []
    for var in closed.jaxpr.outvars:
        deps = _read(env, var)
        value = _constant(closed.jaxpr, var, {}) if not deps else None
        out.append((deps - {_CLOSED}, value))
    return out


def _read(env, var) -> frozenset:
    return frozenset() if isinstance(var, Literal) else env[var]


def _nested(eqn) -> Jaxpr | None:
    """The jaxpr of a call-like equation (a nested jit, a custom derivative)
    whose inputs and outputs are the equation's, or None."""
    for key in ("jaxpr", "call_jaxpr"):
        inner = eqn.params.get(key)
        if isinstance(inner, ClosedJaxpr):
            inner = inner.jaxpr
        if isinstance(inner, Jaxpr) and len(inner.invars) == len(eqn.invars) and len(inner.outvars) == len(eqn.outvars):
            return inner
    return None


def _propagate(jaxpr: Jaxpr, constants, arguments) -> dict:
    env = dict(zip(jaxpr.constvars, constants))
    env.update(zip(jaxpr.invars, arguments))
    for eqn in jaxpr.eqns:
        ins = [_read(env, v) for v in eqn.invars]
        inner = _nested(eqn)
        if inner is not None:
            inner_env = _propagate(inner, [frozenset()] * len(inner.constvars), ins)
            outs = [_read(inner_env, v) for v in inner.outvars]
        else:
            outs = [functools.reduce(frozenset.union, ins, frozenset())] * len(eqn.outvars)
        env.update(zip(eqn.outvars, outs))
    return env


def _constant(jaxpr: Jaxpr, var, memo):
    """The value of `var`, which depends on no input or closed-over value,
    computed from the literals it comes from; None where that needs an
    equation with effects (a callback is not run at trace time)."""
    if isinstance(var, Literal):
        return np.asarray(var.val)
    if var in memo:
        return memo[var]
    producer = next((eqn for eqn in jaxpr.eqns if var in eqn.outvars), None)
    if producer is None or producer.effects:
        return None
    values = [_constant(jaxpr, v, memo) for v in producer.invars]
    if any(v is None for v in values):
        return None
    with jax.ensure_compile_time_eval():
        outs = producer.primitive.bind(*values, **producer.params)
    outs = outs if producer.primitive.multiple_results else [outs]
    for v, value in zip(producer.outvars, outs):
        memo[v] = np.asarray(value)
    return memo[var]


@dataclasses.dataclass(frozen=True)
class StageDependence:
    """What the slopes (K, L) of one stage depend on: "u" (the stage's
    Σa¹K), "v" (its Σa²L), and whether L is identically zero."""

    first: frozenset[str]
    second: frozenset[str]
    second_zero: bool = False

    def __post_init__(self):
        if not (self.first | self.second) <= {"u", "v"}:
            raise ValueError(f"a stage slope depends on 'u' and/or 'v', got {set(self.first | self.second)}.")


COUPLED = StageDependence(frozenset({"u", "v"}), frozenset({"u", "v"}))
"""Every slope depends on the whole stage point: the tableau's own pattern."""


def stage_dependence(stage_slope, field_at_state, zeros, state) -> StageDependence:
    """Read a `StageDependence` from the traced programs of
    `stage_slope(u, v) -> (K, L)` and of `field_at_state(y) -> (ξ, η)`.

    L is identically zero when the field's η is a constant 0: then the stage
    equations keep v = 0 (see the module docstring), whatever df⁻¹ does to
    pairs with v ≠ 0."""
    eta = output_dependence(lambda y: field_at_state(y)[1], state)
    second_zero = all(not deps and value is not None and not np.any(value) for deps, value in eta)
    n_first = len(jax.tree.leaves(zeros[0]))
    deps = [d for d, _ in output_dependence(stage_slope, *zeros)]
    names = {0: "u", 1: "v"}

    def on(leaf_deps):
        return frozenset(names[k] for d in leaf_deps for k in d)

    return StageDependence(on(deps[:n_first]), on(deps[n_first:]), second_zero)


@dataclasses.dataclass(frozen=True)
class Explicit:
    """Evaluate stage `stage` once; keep its slopes `components` (0: K, 1: L)."""

    stage: int
    components: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class Implicit:
    """Solve for the slopes `slopes` ((stage, component) pairs) together by
    fixed-point iteration; each iteration evaluates each of their stages once."""

    slopes: tuple[tuple[int, int], ...]

    @property
    def stages(self) -> tuple[int, ...]:
        return tuple(sorted({i for i, _ in self.slopes}))


def plan_stages(tableau: PartitionedTableau, dependence: StageDependence = COUPLED) -> tuple[Explicit | Implicit, ...]:
    """The order in which a step finds its stage slopes.

    Slope (i, c) depends on slope (j, 0) when stage i's point uses u and
    a¹ᵢⱼ ≠ 0, on (j, 1) when it uses v and a²ᵢⱼ ≠ 0. Strongly connected sets
    (and slopes that depend on themselves) are solved together; the other
    component of a solved stage joins the set when it depends on nothing
    else still unknown, since the iteration evaluates that stage anyway.
    With `COUPLED` this is the tableau's own block structure."""
    s = tableau.num_stages
    components = (0,) if dependence.second_zero else (0, 1)
    nodes = [(i, c) for i in range(s) for c in components]
    needs = {"u": tableau.a_first, "v": tableau.a_second}
    on = (dependence.first, dependence.second)

    def deps(node):
        i, c = node
        out = set()
        for name in on[c]:
            if name == "v" and dependence.second_zero:
                continue
            row = needs[name][i]
            out |= {(j, 0 if name == "u" else 1) for j in range(s) if row[j] != 0}
        return out

    edges = {node: deps(node) for node in nodes}
    plan, known = [], set()
    for component in _strongly_connected(nodes, edges):
        todo = [n for n in component if n not in known]
        if not todo:
            continue
        implicit = len(todo) > 1 or todo[0] in edges[todo[0]]
        if implicit:
            solved = set(todo)
            for i in sorted({i for i, _ in todo}):
                for c in components:
                    other = (i, c)
                    if other not in known and other not in solved and edges[other] <= known | solved:
                        solved.add(other)
            plan.append(Implicit(tuple(sorted(solved))))
            known |= solved
        else:
            (i, c) = todo[0]
            kept = [c] + [o for o in components if o != c and (i, o) not in known and edges[(i, o)] <= known]
            plan.append(Explicit(i, tuple(sorted(kept))))
            known |= {(i, o) for o in kept}
    return tuple(_merge_shared_stages(plan))


def _merge_shared_stages(plan: list) -> list:
    """Join two implicit parts that evaluate a common stage, with what lies
    between them, into one. Split, each would evaluate that stage every
    iteration and each needs about as many iterations as the joint solve
    (the free body on G×g with Lobatto IIIA–IIIB 4: 19 iterations of two
    stages a step split, 10 of three joint)."""
    while True:
        implicit = [k for k, part in enumerate(plan) if isinstance(part, Implicit)]
        shared = next(
            ((a, b) for a in implicit for b in implicit if a < b and set(plan[a].stages) & set(plan[b].stages)),
            None,
        )
        if shared is None:
            return plan
        a, b = shared
        slopes = set()
        for part in plan[a : b + 1]:
            slopes |= set(part.slopes) if isinstance(part, Implicit) else {(part.stage, c) for c in part.components}
        plan = plan[:a] + [Implicit(tuple(sorted(slopes)))] + plan[b + 1 :]


def _strongly_connected(nodes, edges):
    """Strongly connected components of the graph node → edges[node]
    (dependencies), dependencies first (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            out.append(sorted(component))

    for v in nodes:
        if v not in index:
            visit(v)
    return out
