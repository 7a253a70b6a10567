"""Fixed-point iteration against Newton for the implicit stages, per tableau.

Free rigid body on T*SO(3) (Cotangent, body form, exp), h = 0.01, a batch of
random attitudes and momenta, `integrate` with the default stage solver
(fixed-point iteration) and with `root_finder=optx.Newton(rtol, atol)` at
the same tolerance (1e-12). Interleaved; times are medians; the final states
are asserted to agree (1e-10). Columns: ns per trajectory-step and implicit
iterations per step of each, their ratio. The default of `PRKMK` is the
faster one here; Newton pays off where the fixed-point iteration converges
slowly or not at all (large h·|Ω|, see `stability.py`).

    python benchmarks/root_finders.py --out benchmarks/results
    python benchmarks/root_finders.py --quick
"""

import json
import statistics

import jax
import jax.numpy as jnp
import optimistix as optx

import _common as C
import prkmk_jax as pk

H = 0.01
TOLERANCE = 1e-12


def compare(tableau, batch, steps, rounds):
    qs, pis = C.initial_conditions(batch, seed=3)
    args = (jnp.asarray(qs), jnp.asarray(pis), jnp.asarray(C.INERTIA))
    solvers = {"fixed_point": None, "newton": optx.Newton(rtol=TOLERANCE, atol=TOLERANCE)}
    fns = {
        name: jax.vmap(C.integrate_final(C.SCENE.method(tableau, root_finder=solver), steps, H), in_axes=(0, 0, None))
        for name, solver in solvers.items()
    }
    compiled, compile_s, outputs = C.compile_all(fns, *args)
    difference = float(jnp.max(jnp.abs(outputs["fixed_point"][1] - outputs["newton"][1])))
    assert difference <= 1e-10, difference
    times = C.interleaved_times(compiled, *args, rounds=rounds)
    ns = {name: statistics.median(t) / (batch * steps) * 1e9 for name, t in times.items()}
    iterations = {name: float(jnp.mean(out[2])) / steps for name, out in outputs.items()}
    return dict(
        tableau=tableau.name,
        batch=batch,
        steps=steps,
        ns_per_traj_step=ns,
        iterations_per_step=iterations,
        newton_over_fixed_point=ns["newton"] / ns["fixed_point"],
        compile_s=compile_s,
        max_abs_difference=difference,
    )


def main(argv=None):
    args, out = C.cli(__doc__, argv)
    batches, steps, rounds = ((4,), 10, 2) if args.quick else ((64, 1024), 200, 7)
    rows = []
    print(f"{'tableau':40s} {'batch':>5s} {'fixed-point ns':>14s} {'it':>5s} {'Newton ns':>10s} {'it':>5s} {'ratio':>6s}")
    for tableau in (pk.stormer_verlet, pk.lobatto_iiia_iiib4):
        for batch in batches:
            row = compare(tableau, batch, steps, rounds)
            rows.append(row)
            ns, it = row["ns_per_traj_step"], row["iterations_per_step"]
            print(
                f"{tableau.name:40s} {batch:5d} {ns['fixed_point']:14.0f} {it['fixed_point']:5.2f} "
                f"{ns['newton']:10.0f} {it['newton']:5.2f} {row['newton_over_fixed_point']:6.2f}",
                flush=True,
            )
    with open(out / "root_finders.json", "w") as f:
        json.dump(dict(machine=C.machine(), rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
