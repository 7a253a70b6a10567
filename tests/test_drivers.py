"""The drivers agree, the one home of that claim: `diffrax.diffeqsolve` with
`PRKMKTerm` and `PRKMKSolver(method)` at constant steps takes `integrate`'s
steps, for each kind of method (PRKMK tableaus, a method made of steps, an
adjoint, a splitting) and through a time-dependent field."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import FORCED_ARGS, INERTIA, TOP_ARGS, initial_state
from prkmk_jax.scenes import ForcedRigidBody, FreeRigidBody, HeavyTop

FREE, TOP, FORCED = FreeRigidBody(), HeavyTop(), ForcedRigidBody()
ARGS = jnp.asarray(INERTIA)
SV = FREE.method(pk.stormer_verlet)

KINDS = {  # name: (scene, method, args)
    # The drivers do not look inside a step (`AbstractMethod.carried_step`):
    # one kind of each carry stands for the rest: PRKMK with one stage and
    # with four (the carried stage slopes), a method made of steps (a
    # composition; a symmetrised method is another), the adjoint, a
    # splitting, and a time-dependent field.
    **{f"PRKMK {tab.name}": (FREE, FREE.method(tab), ARGS) for tab in (pk.symplectic_euler, pk.lobatto_iiia_iiib6)},
    "Composition of SV": (FREE, pk.Composition(SV, pk.kahan_li_6), ARGS),
    "Adjoint of SV": (FREE, pk.Adjoint(SV), ARGS),
    "splitting, heavy top": (TOP, TOP.splitting(), TOP_ARGS),
    "forced body (time-dependent), Lobatto 4": (FORCED, FORCED.method(pk.lobatto_iiia_iiib4), FORCED_ARGS),
}


@pytest.mark.parametrize("kind", KINDS)
def test_diffeqsolve_at_constant_steps_takes_integrates_steps(kind):
    scene, method, args = KINDS[kind]
    y0, t0, dt, n = initial_state(pk.Cotangent(pk.SO3)), 0.3, 0.02, 50
    sol = diffrax.diffeqsolve(pk.PRKMKTerm(scene), pk.PRKMKSolver(method), t0, t0 + n * dt, dt, y0, args, saveat=diffrax.SaveAt(steps=True))
    traj = pk.integrate(method, scene, y0, t0, dt, n, args)
    assert int(sol.stats["num_steps"]) == n
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda a: a[:n], sol.ys)), jax.tree.leaves(jax.tree.map(lambda a: a[1:], traj.ys))):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
    np.testing.assert_allclose(sol.ts[:n], traj.ts[1:], rtol=0, atol=1e-14)
