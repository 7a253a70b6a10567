"""Stability map: the largest h·|Ω₀| at which each fixed-step method stays
bounded over T = 1000.

Two scenes, each swept over the angular-momentum magnitude s·Π₀ at a fixed
step h = 0.1 (the free rigid body is homogeneous: scaling Π by s is scaling
time by s, so this is a sweep of h·|Ω₀|, |Ω₀| = |I⁻¹Π₀|):

- "fast spin": the paper's inertia (5.2), Π₀ along the paper's momentum (5.1);
- "unequal inertia": I = (1, 0.1, 0.01), Π₀ along the same direction, so
  the three body rates differ by a factor up to 100.

A run counts as bounded when every state is finite, every implicit stage
converged, and max |H/H₀ − 1| < 10 % over t ∈ {0, 1, …, T}. The whole sweep
of one method runs as one vmapped batch. PRKMK methods (T*SO(3), body form,
exp coordinates) use fixed-point iteration for implicit stages, and
Störmer–Verlet also Newton, which separates divergence of the implicit stage
from instability of the method. Peers: diffrax Tsit5, Dopri5, Dopri8 with
constant steps on the embedding ℝ⁹×ℝ³.

    python benchmarks/stability.py
    python benchmarks/stability.py --quick
"""

import csv
import json
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import _common as C
import prkmk_jax as pk

H = 0.1
SCENES = {"fast spin": C.INERTIA, "unequal inertia": np.array([1.0, 0.1, 0.01])}


def _prkmk(tableau, root_finder=None, coordinates=pk.Exp()):
    method = C.SCENE.method(tableau, coordinates, root_finder=root_finder)

    def make(n, every):
        def run(q0, pi0, inertia):
            y0 = pk.BundleElement(pk.SO3(q0), pi0)
            traj = pk.integrate(method, C.SCENE, y0, 0.0, H, n, inertia, save_every=every, throw=False)
            return (traj.ys.base.matrix, traj.ys.fiber, traj.result == pk.RESULTS.successful)

        return run

    return make


def _peer(solver):
    def make(n, every):
        ts = jnp.arange(n // every + 1) * (every * H)

        def run(q0, pi0, inertia):
            z0 = jnp.concatenate([q0.reshape(9), pi0])
            options = dict(saveat=diffrax.SaveAt(ts=ts), max_steps=n + 1, throw=False)
            sol = diffrax.diffeqsolve(diffrax.ODETerm(C.embedding_rhs), solver, 0.0, n * H, H, z0, inertia, **options)
            z = sol.ys
            return (z[:, :9].reshape(-1, 3, 3), z[:, 9:], sol.result == diffrax.RESULTS.successful)

        return run

    return make


METHODS = {
    "PRKMK SE": _prkmk(pk.symplectic_euler),
    "PRKMK SV": _prkmk(pk.stormer_verlet),
    "PRKMK SV (Newton)": _prkmk(pk.stormer_verlet, optx.Newton(rtol=1e-12, atol=1e-12)),
    "PRKMK SV Cayley": _prkmk(pk.stormer_verlet, coordinates=pk.Cayley()),
    "PRKMK Lobatto4": _prkmk(pk.lobatto_iiia_iiib4),
    "diffrax Tsit5": _peer(diffrax.Tsit5()),
    "diffrax Dopri5": _peer(diffrax.Dopri5()),
    "diffrax Dopri8": _peer(diffrax.Dopri8()),
}


def stability_table(results: Path) -> str:
    """`stability.py`: the largest h·|Ω₀| each method stays stable to, and
    the first failure beyond it."""
    data = C.results_file(results, "stability.json")
    rows = []
    for r in data["thresholds"]:
        bounded_throughout = C.number(r["first_failure"], "g") == "–"
        threshold = f"≥ {r['threshold']:.3g} (the grid's top)" if bounded_throughout else f"{r['threshold']:.3g}"
        rows.append([r["scene"], r["method"], threshold, C.number(r["first_failure"], ".3g"), r["reason"]])
    headers = ["scene", "method", "stable to h·\\|Ω₀\\|", "first failure", "why"]
    return C.measured_on(data) + f" T = {data['t_end']:g}.\n\n" + C.table(headers, rows)


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from its results in `results` (`write_tables.py`)."""
    return {"stability": stability_table(results)}


def main(argv=None):
    args, out = C.cli(__doc__, argv)
    t_end = 20.0 if args.quick else 1000.0
    n, every = int(round(t_end / H)), int(round(1.0 / H))
    hw_targets = np.geomspace(0.05, 20.0, 6 if args.quick else 25)  # h·|Ω₀| values swept
    methods = {k: METHODS[k] for k in (["PRKMK SV", "diffrax Tsit5"] if args.quick else METHODS)}
    q0 = jnp.asarray(C.initial_conditions(None)[0])
    direction = C.MOMENTUM / np.linalg.norm(C.MOMENTUM)
    rows, thresholds = [], {}
    for scene, inertia in SCENES.items():
        unit_rate = np.linalg.norm(direction / inertia)  # |Ω₀| for |Π₀| = 1
        scales = hw_targets / (H * unit_rate)
        pis = jnp.asarray(scales[:, None] * direction)
        qs = jnp.broadcast_to(q0, (len(scales), 3, 3))
        for name, make in methods.items():
            fn = jax.vmap(make(n, every), in_axes=(0, 0, None))
            compiled, compile_s = C.compile_fn(fn, qs, pis, jnp.asarray(inertia))
            q, pi, converged = (np.asarray(x) for x in compiled(qs, pis, jnp.asarray(inertia)))
            energy = pk.diagnostics.energy(pi, pi / inertia)
            codes = np.asarray(pk.diagnostics.run_status(energy, converged, (q, pi)))
            status = [pk.diagnostics.RUN_STATUS[c] for c in codes]
            first = pk.diagnostics.first_unbounded(codes)
            thresholds[(scene, name)] = dict(
                threshold=pk.diagnostics.stability_threshold(hw_targets, codes),
                first_failure=float("nan") if first is None else float(hw_targets[first]),
                reason="none" if first is None else status[first],
                compile_s=compile_s,
            )
            for hw, s, st in zip(hw_targets, scales, status):
                rows.append(dict(scene=scene, method=name, h_omega=hw, momentum_scale=s, status=st))
            found = thresholds[(scene, name)]
            first_failure = f"first failure at {found['first_failure']:6.3f} ({found['reason']})"
            print(f"{scene:16s} {name:20s} stable to h|Ω₀| = {found['threshold']:6.3f}; {first_failure}", flush=True)
    with open(out / "stability.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    threshold_rows = [dict(scene=s, method=m, **v) for (s, m), v in thresholds.items()]
    (out / "stability.json").write_text(json.dumps(dict(machine=C.machine(), h=H, t_end=t_end, thresholds=threshold_rows), indent=1))
    plot(thresholds, hw_targets, out / "stability.png", t_end)
    return out


def plot(thresholds, grid, path, t_end):
    scenes = list(SCENES)
    methods = sorted({m for _, m in thresholds})
    fig, ax = C.subplots(figsize=(11, 5))
    width = 0.8 / len(scenes)
    for k, scene in enumerate(scenes):
        vals = [thresholds.get((scene, m), {}).get("threshold", np.nan) for m in methods]
        ax.bar(np.arange(len(methods)) + k * width, vals, width, label=scene)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(methods)) + width * (len(scenes) - 1) / 2)
    ax.set_xticklabels(methods, rotation=30, ha="right")
    ax.set_ylabel("largest stable h·|Ω₀| (dimensionless)")
    ax.set_title(f"Bounded over T = {t_end:g} (finite, implicit stages converged, energy error < 10 %); grid {grid[0]:.2g}…{grid[-1]:.2g}")
    ax.legend()
    ax.grid(True, axis="y", which="both", alpha=0.3)
    C.save(fig, path)


if __name__ == "__main__":
    print("\n\n".join(tables(main()).values()))
