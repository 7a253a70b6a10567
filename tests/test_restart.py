"""Restarts: a run split at a save point and continued with `resume` equals
the uninterrupted run bit for bit; through diffeqsolve, diffrax's own
`solver_state` route continues it to round-off."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, initial_state, rigid_body_field

COTANGENT = pk.Cotangent(pk.SO3)
FREE_BODY = rigid_body_field(COTANGENT, "body")


def forced_body(t, y, inertia):
    """Π' = Π×Ω + τ(t): a time-dependent torque, so the stage times matter."""
    return y.fiber / inertia, jnp.stack([jnp.sin(t), 0.3 * jnp.cos(2 * t), 0.1 * jnp.ones_like(t)])


SV = pk.PRKMK(COTANGENT, pk.Exp(), pk.stormer_verlet, form="body")
CASES = {
    "SV, free body": (SV, FREE_BODY),
    "Lobatto 4, forced body": (pk.PRKMK(COTANGENT, pk.Exp(), pk.lobatto_iiia_iiib4, form="body"), forced_body),
    "SV∘Suzuki 5, forced body": (pk.Composition(SV, pk.suzuki_5), forced_body),
}
DT, SAVE_EVERY, NUM_SAVES = 0.07, 3, 2


def _assert_identical(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_split_at_every_save_point_equals_the_single_run_bit_for_bit(case):
    """Plain calls: `integrate` and `resume` compile themselves, with the
    start time and the step as data (a user's `jit` around them traces the
    same programs)."""
    method, field = CASES[case]
    args, y0, t0, dt = jnp.asarray(INERTIA), initial_state(COTANGENT), 0.3, DT

    def first_part(y, t0, dt, n):
        return pk.integrate(method, field, y, t0, dt, n, args, save_every=SAVE_EVERY)

    def second_part(c, n):
        return pk.resume(method, field, c, n, args, save_every=SAVE_EVERY)

    whole = first_part(y0, t0, dt, SAVE_EVERY * NUM_SAVES)
    for k in range(1, NUM_SAVES):
        head = first_part(y0, t0, dt, SAVE_EVERY * k)
        tail = second_part(head.continuation, SAVE_EVERY * (NUM_SAVES - k))
        _assert_identical(head.ys, jax.tree.map(lambda a: a[: k + 1], whole.ys))
        _assert_identical(tail.ys, jax.tree.map(lambda a: a[k:], whole.ys))
        np.testing.assert_array_equal(tail.ts, whole.ts[k:])
        # A continued continuation is the uninterrupted run's as well.
        _assert_identical(tail.continuation, whole.continuation)


def test_continuation_survives_serialisation(tmp_path):
    method, field = CASES["SV∘Suzuki 5, forced body"]
    args, y0 = jnp.asarray(INERTIA), initial_state(COTANGENT)
    run = lambda y: pk.integrate(method, field, y, 0.0, DT, 6, args)  # noqa: E731
    head = run(y0)
    path = tmp_path / "continuation.eqx"
    eqx.tree_serialise_leaves(path, head.continuation)
    template = jax.eval_shape(run, y0).continuation
    loaded = eqx.tree_deserialise_leaves(path, template)
    whole = pk.integrate(method, field, y0, 0.0, DT, 10, args)
    _assert_identical(pk.resume(method, field, loaded, 4, args).ys, jax.tree.map(lambda a: a[6:], whole.ys))


def test_resume_under_vmap():
    args = jnp.asarray(INERTIA)
    y0s = jax.tree.map(lambda *a: jnp.stack(a), *[initial_state(COTANGENT, seed=s) for s in range(3)])
    run = jax.vmap(lambda y, n=4: pk.integrate(SV, FREE_BODY, y, 0.0, DT, n, args))
    head = run(y0s)
    tail = jax.vmap(lambda c: pk.resume(SV, FREE_BODY, c, 4, args))(head.continuation)
    whole = jax.vmap(lambda y: pk.integrate(SV, FREE_BODY, y, 0.0, DT, 8, args))(y0s)
    _assert_identical(tail.ys, jax.tree.map(lambda a: a[:, 4:], whole.ys))


def test_resume_refuses_what_is_not_its_own_continuation():
    args, y0 = jnp.asarray(INERTIA), initial_state(COTANGENT)
    head = pk.integrate(SV, FREE_BODY, y0, 0.0, DT, 2, args)
    with pytest.raises(TypeError, match="Trajectory's `continuation`"):
        pk.resume(SV, FREE_BODY, head.ys, 2, args)
    lobatto = pk.PRKMK(COTANGENT, pk.Exp(), pk.lobatto_iiia_iiib4, form="body")
    with pytest.raises(TypeError, match="another method"):
        pk.resume(lobatto, FREE_BODY, head.continuation, 2, args)


def test_diffeqsolve_continues_through_its_solver_state():
    """diffrax's route: `SaveAt(solver_state=True)` out, `solver_state=` in.
    diffrax accumulates its step times, so the split run differs from the
    single one by round-off in the times; the states agree to 1e-13."""
    args, y0 = jnp.asarray(INERTIA), initial_state(COTANGENT)
    term, solver = pk.PRKMKTerm(forced_body), pk.PRKMKSolver(SV)

    def solve(y, t0, t1, state=None):
        return diffrax.diffeqsolve(term, solver, t0, t1, DT, y, args, solver_state=state, saveat=diffrax.SaveAt(t1=True, solver_state=True))

    whole = solve(y0, 0.0, 40 * DT)
    head = solve(y0, 0.0, 25 * DT)
    tail = solve(jax.tree.map(lambda a: a[-1], head.ys), 25 * DT, 40 * DT, head.solver_state)
    for a, b in zip(jax.tree.leaves(tail.ys), jax.tree.leaves(whole.ys)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
