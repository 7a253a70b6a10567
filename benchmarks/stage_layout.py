"""Explicit tableaus: the stages unrolled against the stages in a loop
(`PRKMK(explicit_stages=...)`), interleaved in one process.

The heavy top (`HeavyTop`, inertia (1, 0.8, 0.4), lever (0.1, 0.2, 0.9)),
body form, Cayley coordinates, h = 0.05, on T*SO(3) and on G×g; the
tableaus `dormand_prince_8` (13 stages) and `classical_rk4` (4 stages).
Regimes: one trajectory, a batch in the state (64 and 1024 trajectories)
and `jax.vmap` of one-trajectory runs over 1024. Columns: ns per
trajectory-step of each layout, the median of the per-round ratios
loop/unrolled, the compile times, and the largest difference of the final
states.

    python benchmarks/stage_layout.py --out benchmarks/results
    python benchmarks/stage_layout.py --quick
"""

import json

import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import HeavyTop, TopParameters

H = 0.05
ARGS = TopParameters(jnp.array([1.0, 0.8, 0.4]), jnp.array([0.1, 0.2, 0.9]))
SCENES = {"T*SO(3)": HeavyTop(), "G×g": HeavyTop(pk.DirectProduct(pk.SO3))}
TABLEAUS = {"DP8": pk.dormand_prince_8, "RK4": pk.classical_rk4}


def _run(scene, tableau, layout, steps, vmapped):
    method = pk.PRKMK(scene.bundle, pk.Cayley(), tableau, form="body", explicit_stages=layout)

    def final(q, p):
        y = pk.integrate(method, scene, pk.BundleElement(pk.SO3(q), p), 0.0, H, steps, ARGS, save_every=steps).ys
        return y.base.matrix[-1], y.fiber[-1]

    return jax.vmap(final) if vmapped else final


def compare(scene_name, tableau_name, regime, steps, rounds):
    batch = 1 if regime == "single" else int(regime.split()[-1])
    vmapped = regime.startswith("vmap")
    q0, p0 = C.initial_conditions(None if regime == "single" else batch, seed=2)
    q, p = jnp.asarray(q0), jnp.asarray(p0) * jnp.array([1.0, -1.0, 2.0])
    fns = {layout: _run(SCENES[scene_name], TABLEAUS[tableau_name], layout, steps, vmapped) for layout in ("unrolled", "loop")}
    compiled, compile_s, outputs = C.compile_all(fns, q, p)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(outputs["loop"]), jax.tree.leaves(outputs["unrolled"])))
    times = C.interleaved_times(compiled, q, p, rounds=rounds)
    return dict(
        scene=scene_name,
        tableau=tableau_name,
        regime=regime,
        batch=batch,
        steps=steps,
        ns_per_traj_step=C.ns_per_trajectory_step(times, batch, steps),
        loop_over_unrolled=C.median_ratio(times, "loop", "unrolled"),
        compile_s=compile_s,
        max_abs_difference=gap,
    )


def main(argv=None):
    args, out = C.cli(__doc__, argv)
    regimes = ("single", "batch 4") if args.quick else ("single", "batch 64", "batch 1024", "vmap 1024")
    rounds = 2 if args.quick else 9
    columns = ("unrolled ns", 11), ("loop ns", 8), ("ratio", 6), ("cmp unr", 7), ("cmp loop", 8), ("diff", 8)
    print(f"{'scene':8s} {'tableau':7s} {'regime':10s} " + " ".join(f"{name:>{width}s}" for name, width in columns))
    rows = []
    for scene_name in SCENES:
        for tableau_name in TABLEAUS:
            for regime in regimes:
                batch = 1 if regime == "single" else int(regime.split()[-1])
                steps = 8 if args.quick else int(max(20, min(400, 100_000 // batch)))
                row = compare(scene_name, tableau_name, regime, steps, rounds)
                rows.append(row)
                ns, cs = row["ns_per_traj_step"], row["compile_s"]
                ratio, gap = row["loop_over_unrolled"], row["max_abs_difference"]
                print(
                    f"{scene_name:8s} {tableau_name:7s} {regime:10s} {ns['unrolled']:11.0f} {ns['loop']:8.0f} {ratio:6.2f} "
                    f"{cs['unrolled']:7.2f} {cs['loop']:8.2f} {gap:8.1e}",
                    flush=True,
                )
    with open(out / "stage_layout.json", "w") as f:
        json.dump(dict(machine=C.machine(), h=H, rounds=rounds, rows=rows), f, indent=1)
    print(f"median loop/unrolled over the batches ≥ 64: {np.median([r['loop_over_unrolled'] for r in rows if r['batch'] >= 64]):.2f}")


if __name__ == "__main__":
    main()
