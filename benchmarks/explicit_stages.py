"""What the stage plan saves: each method with the plan read from the field
(`coupling="traced"`, the default) against the tableau's own plan
(`coupling="tableau"`, every slope of a stage depending on the whole stage
point), interleaved in one process.

Scenes (body form, `integrate`, h = 0.01, a batch of random attitudes):

* the free body on T*SO(3) (η ≡ 0, so L ≡ 0: Störmer–Verlet's first stage is
  explicit, Lobatto IIIA–IIIB 4 iterates two stages of three);
* the heavy top on T*SO(3) (ξ(Π), η(Q), but the fiber of the stage point
  moves with u: SV's first stage is explicit, its second implicit);
* the spherical top on G×g (separable (4.15) with decoupled stage points:
  symplectic Euler and SV explicit, no iteration at all).

Columns: ns per trajectory-step of each plan, the median of the per-round
ratios traced/tableau, the implicit iterations a step of each, and the
largest difference of the final states (both solve the same stage equations
to the same tolerance).

    python benchmarks/explicit_stages.py --out benchmarks/results
    python benchmarks/explicit_stages.py --quick
"""

import json

import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.methods.stage_plan import Explicit
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, SphericalTop, TopParameters

H = 0.01
LEVER = np.array([0.1, 0.2, 0.9])
SCENES = {
    "free body T*SO(3)": (FreeRigidBody(), lambda dtype: jnp.asarray(C.INERTIA, dtype)),
    "heavy top T*SO(3)": (HeavyTop(), lambda dtype: TopParameters(jnp.asarray([1.0, 0.8, 0.4], dtype), jnp.asarray(LEVER, dtype))),
    "spherical top G×g": (SphericalTop(), lambda dtype: TopParameters(jnp.asarray(0.7, dtype), jnp.asarray(LEVER, dtype))),
}
TABLEAUS = {"SE": pk.symplectic_euler, "SV": pk.stormer_verlet, "Lobatto4": pk.lobatto_iiia_iiib4}


def _run(scene, method, steps):
    def run(q0, pi0, args):
        traj = pk.integrate(method, scene, pk.BundleElement(pk.SO3(q0), pi0), 0.0, H, steps, args, save_every=steps)
        return traj.ys.base.matrix[-1], traj.ys.fiber[-1], traj.stats["num_iterations"]

    return jax.vmap(run, in_axes=(0, 0, None))


def compare(scene_name, tableau_name, batch, dtype, steps, rounds):
    scene, make_args = SCENES[scene_name]
    qs, pis = C.initial_conditions(batch, seed=3)
    inputs = (jnp.asarray(qs, dtype), jnp.asarray(pis, dtype), make_args(dtype))
    tab = TABLEAUS[tableau_name]
    fns = {coupling: _run(scene, scene.method(tab, coupling=coupling), steps) for coupling in ("traced", "tableau")}
    compiled, _, outputs = C.compile_all(fns, *inputs)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(outputs["traced"][:2], outputs["tableau"][:2]))
    times = C.interleaved_times(compiled, *inputs, rounds=rounds)
    y0 = pk.BundleElement(pk.SO3(inputs[0][0]), inputs[1][0])
    plan = scene.method(tab).stage_plan(scene, 0.0, y0, inputs[2])
    return dict(
        scene=scene_name,
        tableau=tableau_name,
        dtype=jnp.dtype(dtype).name,
        batch=batch,
        steps=steps,
        plan=" ".join(_describe(part) for part in plan),
        ns_per_traj_step=C.ns_per_trajectory_step(times, batch, steps),
        traced_over_tableau=C.median_ratio(times, "traced", "tableau"),
        iterations_per_step={name: float(jnp.mean(out[2])) / steps for name, out in outputs.items()},
        max_abs_difference=gap,
    )


def _describe(part):
    """'K1 L1' for an explicit evaluation, '[K2 L2]' for an implicit set."""
    names = {0: "K", 1: "L"}
    if isinstance(part, Explicit):
        return " ".join(f"{names[c]}{part.stage + 1}" for c in part.components)
    return "[" + " ".join(f"{names[c]}{i + 1}" for i, c in part.slopes) + "]"


def main(argv=None):
    args, out = C.cli(__doc__, argv, lambda p: p.add_argument("--rounds", type=int, default=9))
    if args.quick:
        cases = [(s, "SV", 4, jnp.float64) for s in SCENES]
        rounds, work = 2, 80
    else:
        cases = [(s, t, b, jnp.float64) for s in SCENES for t in TABLEAUS for b in (1, 1024)]
        cases += [(s, "SV", 1024, jnp.float32) for s in SCENES]
        rounds, work = args.rounds, 200_000
    print(
        f"{'scene':18s} {'tableau':8s} {'dtype':7s} {'batch':>5s} {'traced ns':>9s} {'tableau ns':>10s} {'ratio':>6s} "
        f"{'it traced':>9s} {'it tableau':>10s} {'max diff':>8s}  plan"
    )
    rows = []
    for scene_name, tableau_name, batch, dtype in cases:
        steps = int(max(20, min(400, work // batch)))
        row = compare(scene_name, tableau_name, batch, dtype, steps, rounds)
        rows.append(row)
        ns, its = row["ns_per_traj_step"], row["iterations_per_step"]
        print(
            f"{scene_name:18s} {tableau_name:8s} {row['dtype']:7s} {batch:5d} {ns['traced']:9.0f} {ns['tableau']:10.0f} "
            f"{row['traced_over_tableau']:6.2f} {its['traced']:9.2f} {its['tableau']:10.2f} "
            f"{row['max_abs_difference']:8.1e}  {row['plan']}",
            flush=True,
        )
    with open(out / "explicit_stages.json", "w") as f:
        json.dump(dict(machine=C.machine(), rounds=rounds, h=H, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
