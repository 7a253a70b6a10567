"""Long-time behaviour against cost: invariant drift over T = 1000.

One free rigid body (paper inertia and momentum). For each run: the largest
relative drift over t ∈ {0, 1, …, T} of the scene's invariants
(`FreeRigidBody.invariants`, `diagnostics.max_drift`): the energy, |Π| and
the spatial momentum QΠ (its largest component change over the largest
component of Q₀Π₀); the largest entry of QᵀQ − I; and the wall time after
compilation (median). PRKMK fixed-step methods (T*SO(3),
body form, exp coordinates; SE, SV, Lobatto IIIA–IIIB 4 and 6, and the
compositions of SV of order 6 and 8) run through `prkmk_jax.integrate` and
are read at step points; PRKMK Lobatto with step doubling and the diffrax peers on the
embedding run through `diffeqsolve` with `SaveAt(ts=…)` (dense output).

"At matched cost": for each PRKMK run, the smallest error any diffrax run
reached in no more wall time, divided by the PRKMK run's error.

With `--satellite`: the satellite (`scenes.Satellite`) over 10⁵ steps of
h = 0.01 (about 160 orbits), on each model (T*(SO(3) × ℝ³), the direct
products over SO(3) × ℝ³ and SE(3)) with each method that applies, and
the splittings: the largest drifts of the energy and of the total angular
momentum, the error after the first hundredth of the run against DOP853,
and the time per step (median of interleaved rounds);
`long_time_satellite.json`.

    python benchmarks/long_time.py
    python benchmarks/long_time.py --quick
    python benchmarks/long_time.py --satellite
"""

import csv
import json
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import Satellite, SatelliteParameters

KEYS = ("energy", "momentum_norm", "spatial_momentum", "orthogonality")


def drifts(q, pi, inertia=C.INERTIA):
    """Relative drifts of the scene's invariants over a run
    (`diagnostics.max_drift`), and the largest entry of QᵀQ − I."""
    inv = C.invariants(q, pi, inertia)
    return dict(
        energy=float(pk.diagnostics.max_drift(inv["energy"], relative=True)),
        momentum_norm=float(pk.diagnostics.max_drift(inv["momentum norm"], relative=True)),
        spatial_momentum=float(pk.diagnostics.max_drift(inv["spatial momentum"], relative=True)),
        orthogonality=float(np.max(inv["orthogonality"])),
    )


def _prkmk_fixed(method, t_end):
    def make(h):
        n, every = int(round(t_end / h)), int(round(1.0 / h))

        def run(q0, pi0, inertia):
            y0 = pk.BundleElement(pk.SO3(q0), pi0)
            ys = pk.integrate(method, C.SCENE, y0, 0.0, h, n, inertia, save_every=every).ys
            return ys.base.matrix, ys.fiber

        return run

    return make


def _dense(final_factory, solver, t_end, adaptive):
    ts = jnp.linspace(0.0, t_end, int(t_end) + 1)
    run = final_factory(solver, adaptive, t_eval=ts)

    def make(param):
        dt, rtol = (0.1, param) if adaptive else (param, 1e-6)

        def go(q0, pi0, inertia):
            (q, pi), _ = run(q0, pi0, t_end, dt, rtol, inertia)
            return q, pi

        return go

    return make


def _runs(quick, t_end):
    fixed_h = [0.05] if quick else [0.1, 0.05, 0.02]
    rtols = [1e-6] if quick else [1e-4, 1e-6, 1e-8, 1e-10]
    runs = []

    def body(tab):
        return C.SCENE.method(tab)

    for name, tab in (("SE", pk.symplectic_euler), ("SV", pk.stormer_verlet), ("Lobatto4", pk.lobatto_iiia_iiib4)):
        if quick and name != "SV":
            continue
        runs += [(f"PRKMK {name} exp", "prkmk", "h", h, _prkmk_fixed(body(tab), t_end)) for h in fixed_h]
    # Order 6 and 8 (a step of h is 9 or 17 Störmer–Verlet steps for the
    # compositions, so their steps are longer).
    high_h = [0.25] if quick else [0.5, 0.2, 0.1]
    for name, method in (
        ("Lobatto6", body(pk.lobatto_iiia_iiib6)),
        ("SV∘KahanLi6", pk.Composition(body(pk.stormer_verlet), pk.kahan_li_6)),
        ("SV∘KahanLi8", pk.Composition(body(pk.stormer_verlet), pk.kahan_li_8)),
    ):
        if quick and name != "SV∘KahanLi6":
            continue
        runs += [(f"PRKMK {name} exp", "prkmk", "h", h, _prkmk_fixed(method, t_end)) for h in high_h]
    if not quick:
        solver = C.prkmk_solver(pk.lobatto_iiia_iiib4, adaptive=True)
        runs += [
            ("PRKMK Lobatto4 exp adaptive", "prkmk", "rtol", r, _dense(C.prkmk_final, solver, t_end, True)) for r in [1e-6, 1e-8, 1e-10]
        ]
    for name, solver in (("Tsit5", diffrax.Tsit5()), ("Dopri5", diffrax.Dopri5()), ("Dopri8", diffrax.Dopri8())):
        if quick and name != "Tsit5":
            continue
        runs += [(f"diffrax {name} adaptive", "diffrax", "rtol", r, _dense(C.diffrax_final, solver, t_end, True)) for r in rtols]
    if not quick:
        runs += [("diffrax Tsit5 fixed", "diffrax", "h", h, _dense(C.diffrax_final, diffrax.Tsit5(), t_end, False)) for h in fixed_h]
    return runs


def matched_cost(rows):
    out = []
    peers = [r for r in rows if r["family"] == "diffrax" and r["ok"]]
    for r in rows:
        if r["family"] != "prkmk" or not r["ok"]:
            continue
        cheaper = [p for p in peers if p["wall_s"] <= r["wall_s"]]
        entry = dict(method=r["method"], parameter=r["parameter"], wall_s=r["wall_s"])
        for key in ("energy", "momentum_norm", "spatial_momentum"):
            best = min((p[key] for p in cheaper), default=float("nan"))
            entry[f"{key}_ratio"] = best / max(r[key], 1e-300) if cheaper else float("nan")
        out.append(entry)
    return out


def plot(rows, path, t_end):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 9), sharex=True)
    labels = dict(
        energy="max |H/H₀ − 1|",
        momentum_norm="max ||Π| − |Π₀|| / |Π₀|",
        spatial_momentum="max |QΠ − Q₀Π₀|_∞ / |Q₀Π₀|_∞",
        orthogonality="max |QᵀQ − I|",
    )
    C.plot_against_wall(axes.ravel(), KEYS, rows)
    for ax, key in zip(axes.ravel(), KEYS):
        ax.set_ylabel(labels[key])
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("wall time after compilation (s)")
    axes[0, 1].legend(fontsize=7)
    fig.suptitle(f"Free rigid body, invariant drift over T = {t_end:g} against cost (values below 1e-17 drawn at 1e-17)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def long_time_table(results: Path) -> str:
    """`long_time.py`: the invariants' largest drifts over T = 1000 and the
    time each run took."""
    data = C.results_file(results, "long_time.json")
    rows = [
        [
            r["method"],
            f"{r['kind']} = {r['parameter']:g}",
            f"{r['wall_s']:.3f}",
            C.number(r["energy"], ".1e"),
            C.number(r["momentum_norm"], ".1e"),
            C.number(r["spatial_momentum"], ".1e"),
            C.number(r["orthogonality"], ".1e"),
        ]
        for r in data["rows"]
    ]
    headers = ["method", "setting", "s", "energy", "\\|Π\\|", "QΠ", "QᵀQ − I"]
    return C.measured_on(data) + f" T = {data['t_end']:g}.\n\n" + C.table(headers, rows)


SATELLITE_ARGS = SatelliteParameters(jnp.asarray([3e-3, 2e-3, 1e-3]), jnp.asarray(1.0), jnp.asarray(1.0))  # μ = m = 1, |r| ≈ 1
SATELLITE_MODELS = {
    "T*(SO(3)×ℝ³)": pk.Cotangent(pk.SO3xR3),
    "(SO(3)×ℝ³)×ℝ⁶": pk.DirectProduct(pk.SO3xR3),
    "SE(3)×ℝ⁶": pk.DirectProduct(pk.SE3),
}


def satellite_methods():
    """(model, method name, scene, method) for each model and method that applies to it."""
    for model, bundle in SATELLITE_MODELS.items():
        scene = Satellite(bundle)
        yield model, "SV", scene, scene.method(pk.stormer_verlet)
        yield model, "Lobatto 4 Cayley", scene, scene.method(pk.lobatto_iiia_iiib4, pk.Cayley())
        if isinstance(bundle, pk.DirectProduct):
            yield model, "RKMK 8 Cayley", scene, scene.method(pk.dormand_prince_8, pk.Cayley())
    scene = Satellite()
    splittings = (("Strang", {}), ("Strang, exact free part", {"free_part": "exact"}), ("Kahan–Li 6", {"coefficients": pk.kahan_li_6}))
    for name, options in splittings:
        yield "T*(SO(3)×ℝ³)", f"splitting {name}", scene, scene.splitting(**options)


def satellite(quick: bool, rounds: int) -> dict:
    """The `--satellite` rows (module docstring)."""
    h, steps = 0.01, 200 if quick else 100_000
    attitude = pk.SO3.exp(jnp.asarray([0.4, -0.3, 0.9])).matrix
    y0 = pk.BundleElement(pk.SO3xR3(attitude, jnp.asarray([1.0, 0.1, -0.05])), jnp.asarray([5e-4, -1e-3, 2e-3, 0.05, 0.95, 0.1]))
    # The error at the first saved state, a hundredth of the run: the attitude's
    # motion is chaotic, and over the whole run no solution stays near the exact one.
    z0, reference = Satellite().to_embedding(y0), Satellite().reference_solution(y0, [h * steps / 100], SATELLITE_ARGS)[-1]
    runs = {f"{name} on {model}": (model, name, scene, method) for model, name, scene, method in satellite_methods()}

    def run(scene, method):
        return lambda z0, args: pk.integrate(method, scene, scene.from_embedding(z0), 0.0, h, steps, args, save_every=steps // 100).ys

    compiled, compile_s, outputs = C.compile_all({key: run(*r[2:]) for key, r in runs.items()}, z0, SATELLITE_ARGS)
    times = C.interleaved_times(compiled, z0, SATELLITE_ARGS, rounds=rounds)
    rows = []
    for key, (model, name, scene, _) in runs.items():
        invariants, first = scene.invariants(outputs[key], SATELLITE_ARGS), jax.tree.map(lambda a: a[1], outputs[key])
        row = dict(model=model, method=name, step_us=1e6 * float(np.median(times[key])) / steps, compile_s=compile_s[key])
        row["error"] = float(np.max(np.abs(np.asarray(scene.to_embedding(first)) - reference)))
        rows.append(row | {k: float(pk.diagnostics.max_drift(invariants[k], relative=True)) for k in ("energy", "angular momentum")})
        print(f"{key:45s} " + "  ".join(f"{k}={v:.2e}" for k, v in rows[-1].items() if isinstance(v, float)), flush=True)
    return dict(machine=C.machine(), h=h, steps=steps, rows=rows)


def satellite_table(results: Path) -> str:
    """`long_time.py --satellite`: each model and method over 10⁵ steps."""
    data = C.results_file(results, "long_time_satellite.json")
    rows = [
        [r["method"], r["model"], f"{r['step_us']:.2f}", f"{r['compile_s']:.1f}"]
        + [C.number(r[k], ".1e") for k in ("error", "energy", "angular momentum")]
        for r in data["rows"]
    ]
    headers = ["method", "model", "µs a step", "compile s", f"error at T = {data['h'] * data['steps'] / 100:g}", "energy", "RΠ + r × p"]
    return C.measured_on(data) + f" {data['steps']:,} steps of h = {data['h']:g}.\n\n" + C.table(headers, rows)


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from those of its results files that `results` holds (`write_tables.py`)."""
    makers = {"long_time": (long_time_table, "long_time.json"), "satellite": (satellite_table, "long_time_satellite.json")}
    return {name: make(results) for name, (make, file) in makers.items() if (results / file).exists()}


def main(argv=None):
    args, out = C.cli(__doc__, argv, lambda parser: parser.add_argument("--satellite", action="store_true", help="the satellite's rows"))
    if args.satellite:
        result = satellite(args.quick, rounds=1 if args.quick else 5)
        (out / "long_time_satellite.json").write_text(json.dumps(result, indent=1))
        return out
    t_end = 20.0 if args.quick else 1000.0
    repeats = 1 if args.quick else 3
    q0, pi0 = C.initial_conditions(None)
    q0, pi0, inertia = jnp.asarray(q0), jnp.asarray(pi0), jnp.asarray(C.INERTIA)
    rows = []
    for name, family, kind, param, make in _runs(args.quick, t_end):
        compiled, compile_s = C.compile_fn(make(param), q0, pi0, inertia)
        try:
            wall, (q, pi) = C.median_time(compiled, q0, pi0, inertia, repeats=repeats)
            q, pi = np.asarray(q), np.asarray(pi)
            ok = bool(np.all(np.isfinite(pi)))
        except Exception as err:
            print(f"  {name} {kind}={param}: failed ({type(err).__name__})")
            wall, ok = float("nan"), False
        row = dict(method=name, family=family, kind=kind, parameter=param, wall_s=wall, compile_s=compile_s, ok=ok)
        row.update(drifts(q, pi) if ok else {k: float("nan") for k in KEYS})
        rows.append(row)
        print(f"{name:30s} {kind}={param:<7.0e} wall={wall:8.3f}s  " + "  ".join(f"{k}={row[k]:8.1e}" for k in KEYS), flush=True)
    plot(rows, out / "long_time.png", t_end)
    with open(out / "long_time.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with open(out / "long_time.json", "w") as f:
        json.dump(dict(machine=C.machine(), t_end=t_end, rows=rows, matched_cost=matched_cost(rows)), f, indent=1)
    return out


if __name__ == "__main__":
    print("\n\n".join(tables(main()).values()))
