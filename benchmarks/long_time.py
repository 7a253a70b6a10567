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

With `--scene satellite` or `--scene double_pendulum`: that scene
(`scenes.Satellite`, `scenes.DoublePendulum`) over 10⁵ steps of h = 0.01,
on each model it lives on, with each method that applies (`SCENE_RUNS`):
the largest drifts of its invariants, the error at the first saved state
against DOP853 (both scenes' motion is chaotic: over a whole run no
solution stays near the exact one), the implicit iterations a step, and
the time a step (median of interleaved rounds); `long_time_<scene>.json`.
With `--costs` as well: each of those runs to the time of that first save,
its step count doubled from 4 until its error is below 1e-8 (at most
65,536 steps), the error and the time of each (`scene_costs`); the table
gives the cheapest run that reaches each target; `long_time_<scene>_costs.json`.

    python benchmarks/long_time.py
    python benchmarks/long_time.py --quick
    python benchmarks/long_time.py --scene satellite
    python benchmarks/long_time.py --scene satellite --costs
"""

import csv
import functools
import json
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import DoublePendulum, PendulumParameters, Satellite, SatelliteParameters
from prkmk_jax.scenes.double_pendulum import body_momenta

KEYS = ("energy", "momentum_norm", "spatial_momentum", "orthogonality")


def drifts(q, pi, inertia=C.INERTIA):
    """Relative drifts of the scene's invariants over a run
    (`diagnostics.max_drift`), and the largest entry of QᵀQ − I."""
    inv = C.invariants(q, pi, inertia)
    relative = {key: float(pk.diagnostics.max_drift(inv[key.replace("_", " ")], relative=True)) for key in KEYS[:3]}
    return relative | dict(orthogonality=float(np.max(inv["orthogonality"])))


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
        runs += [(f"PRKMK {name} exp", "prkmk", "h", h, _prkmk_fixed(body(tab), t_end)) for h in fixed_h]
    # Order 6 and 8 (a step of h is 9 or 17 Störmer–Verlet steps for the
    # compositions, so their steps are longer).
    high_h = [0.25] if quick else [0.5, 0.2, 0.1]
    for name, method in (
        ("Lobatto6", body(pk.lobatto_iiia_iiib6)),
        ("SV∘KahanLi6", pk.Composition(body(pk.stormer_verlet), pk.kahan_li_6)),
        ("SV∘KahanLi8", pk.Composition(body(pk.stormer_verlet), pk.kahan_li_8)),
    ):
        runs += [(f"PRKMK {name} exp", "prkmk", "h", h, _prkmk_fixed(method, t_end)) for h in high_h]
    if not quick:
        solver = C.prkmk_solver(pk.lobatto_iiia_iiib4, adaptive=True)
        runs += [
            ("PRKMK Lobatto4 exp adaptive", "prkmk", "rtol", r, _dense(C.prkmk_final, solver, t_end, True)) for r in [1e-6, 1e-8, 1e-10]
        ]
    for name, solver in (("Tsit5", diffrax.Tsit5()), ("Dopri5", diffrax.Dopri5()), ("Dopri8", diffrax.Dopri8())):
        runs += [(f"diffrax {name} adaptive", "diffrax", "rtol", r, _dense(C.diffrax_final, solver, t_end, True)) for r in rtols]
    if not quick:
        runs += [("diffrax Tsit5 fixed", "diffrax", "h", h, _dense(C.diffrax_final, diffrax.Tsit5(), t_end, False)) for h in fixed_h]
    # --quick: one run of each kind of code.
    return [r for r in runs if not quick or r[0] in ("PRKMK SV exp", "PRKMK SV∘KahanLi6 exp", "diffrax Tsit5 adaptive")]


def matched_cost(rows):
    peers, out = [r for r in rows if r["family"] == "diffrax" and r["ok"]], []
    for r in (r for r in rows if r["family"] == "prkmk" and r["ok"]):
        cheaper = [p for p in peers if p["wall_s"] <= r["wall_s"]]
        entry = dict(method=r["method"], parameter=r["parameter"], wall_s=r["wall_s"])
        for key in KEYS[:3]:
            entry[f"{key}_ratio"] = min(p[key] for p in cheaper) / max(r[key], 1e-300) if cheaper else float("nan")
        out.append(entry)
    return out


def plot(rows, path, t_end):
    fig, axes = C.subplots(2, 2, figsize=(12, 9), sharex=True)
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
    C.save(fig, path)


def long_time_table(results: Path) -> str:
    """`long_time.py`: the invariants' largest drifts over T = 1000 and the
    time each run took."""
    data = C.results_file(results, "long_time.json")
    rows = [
        [r["method"], f"{r['kind']} = {r['parameter']:g}", f"{r['wall_s']:.3f}"] + [C.number(r[k], ".1e") for k in KEYS]
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
PENDULUM_ARGS = PendulumParameters(
    [[0.02, 0.03, 0.01], [0.015, 0.01, 0.02]], [1.0, 0.8], [[0.05, 0, -0.5], [0, 0.03, -0.4]], [0.02, 0, -1], 9.81
)


def satellite_runs():
    """(y0, args, steps between saves, [(model, method name, scene, method)]) of the satellite."""
    attitude = pk.SO3.exp(jnp.asarray([0.4, -0.3, 0.9])).matrix
    y0 = pk.BundleElement(pk.SO3xR3(attitude, jnp.asarray([1.0, 0.1, -0.05])), jnp.asarray([5e-4, -1e-3, 2e-3, 0.05, 0.95, 0.1]))
    runs = []
    for model, bundle in SATELLITE_MODELS.items():
        scene, tableaus = Satellite(bundle), {"SV": (pk.stormer_verlet, pk.Exp()), "Lobatto 4 Cayley": (pk.lobatto_iiia_iiib4, pk.Cayley())}
        tableaus |= {"RKMK 8 Cayley": (pk.dormand_prince_8, pk.Cayley())} if isinstance(bundle, pk.DirectProduct) else {}
        runs += [(model, name, scene, scene.method(*tableau)) for name, tableau in tableaus.items()]
    scene = Satellite()
    splittings = (("Strang", {}), ("Strang, exact free part", {"free_part": "exact"}), ("Kahan–Li 6", {"coefficients": pk.kahan_li_6}))
    return y0, SATELLITE_ARGS, 1000, runs + [("T*(SO(3)×ℝ³)", f"splitting {n}", scene, scene.splitting(**o)) for n, o in splittings]


def pendulum_runs():
    """As `satellite_runs`, the double pendulum (its links swinging by about 0.2 rad: near a quasi-periodic motion)."""
    rotations = jnp.stack([pk.SO3.exp(jnp.array([0.1, -0.05, 0.2])).matrix, pk.SO3.exp(jnp.array([-0.1, 0.1, 0.05])).matrix])
    y0 = pk.BundleElement(pk.SO3Power(rotations), body_momenta(rotations, jnp.array([[0.1, 0.2, -0.3], [0.1, -0.2, 0.5]]), PENDULUM_ARGS))
    cotangent, direct = DoublePendulum(), DoublePendulum(pk.DirectProduct(pk.SO3Power))
    sv, newton = cotangent.method(pk.stormer_verlet), cotangent.method(pk.stormer_verlet, root_finder=optx.Newton(1e-12, 1e-12))
    runs = [("SV", sv), ("SV, Newton", newton), ("symmetrized SV", pk.Symmetrized(sv))]
    runs += [("Lobatto 4 Cayley", cotangent.method(pk.lobatto_iiia_iiib4, pk.Cayley()))]
    on_direct = [("SV", direct.method(pk.stormer_verlet)), ("RKMK 8 Cayley", direct.method(pk.dormand_prince_8, pk.Cayley()))]
    return y0, PENDULUM_ARGS, 100, [("T*SO(3)²", n, cotangent, m) for n, m in runs] + [("SO(3)²×ℝ⁶", n, direct, m) for n, m in on_direct]


SCENE_RUNS = {"satellite": satellite_runs, "double_pendulum": pendulum_runs}


def scene_rows(scene_name: str, quick: bool, rounds: int) -> dict:
    """The `--scene` rows (module docstring)."""
    y0, args, every, runs = SCENE_RUNS[scene_name]()
    h, steps, every = 0.01, 20 * every if quick else 100_000, every // 10 if quick else every
    z0, reference = runs[0][2].to_embedding(y0), runs[0][2].reference_solution(y0, [h * every], args)[-1]  # every model embeds alike
    runs = {f"{name} on {model}": (model, name, scene, method) for model, name, scene, method in runs}

    def run(z0, args, scene, method):
        trajectory = pk.integrate(method, scene, scene.from_embedding(z0), 0.0, h, steps, args, save_every=every)
        return trajectory.ys, trajectory.stats["num_iterations"]

    compiled, compile_s, outputs = C.compile_all({k: functools.partial(run, scene=r[2], method=r[3]) for k, r in runs.items()}, z0, args)
    times = C.interleaved_times(compiled, z0, args, rounds=rounds)
    rows = []
    for key, (model, name, scene, _) in runs.items():
        (ys, iterations), row = outputs[key], dict(model=model, method=name, compile_s=compile_s[key])
        invariants = {k: v for k, v in scene.invariants(ys, args).items() if k != "orthogonality"}
        row |= dict(step_us=1e6 * float(np.median(times[key])) / steps, iterations=int(iterations) / steps)
        row["error"] = float(np.max(np.abs(np.asarray(scene.to_embedding(jax.tree.map(lambda a: a[1], ys))) - reference)))
        for k, v in invariants.items():  # the largest drift (relative), and its growth: last tenth of the run over first
            error, tenth = np.max(np.abs(np.asarray(v - v[0])).reshape(len(v), -1), axis=1), len(v) // 10
            row |= {k: float(np.max(error) / np.max(np.abs(v[0]))), f"{k} growth": float(np.max(error[-tenth:]) / np.max(error[1:tenth]))}
        rows.append(row)
    return dict(machine=C.machine(), h=h, steps=steps, every=every, rows=rows)


COST_TARGETS = (1e-4, 1e-6, 1e-8)


def scene_costs(scene_name: str, quick: bool, rounds: int) -> dict:
    """The `--costs` rows: each run to T = h·(steps between saves) in 4·2ᵏ steps, its error at T and time (median of
    interleaved rounds), the step count doubled until the error is below the smallest target."""
    y0, args, every, runs = SCENE_RUNS[scene_name]()
    t_end, rows = 0.01 * every, []
    z0, reference = runs[0][2].to_embedding(y0), runs[0][2].reference_solution(y0, [t_end], args)[-1]
    for model, name, scene, method in runs:
        compiled, errors = {}, {}
        for steps in [4 * 2**k for k in range(2 if quick else 15)]:
            trajectory = functools.partial(pk.integrate, method, scene, dt=t_end / steps, num_steps=steps, save_every=steps, throw=False)

            def final(z0, args, trajectory=trajectory, scene=scene):  # a step too long for the stage solve: an infinite error
                run = trajectory(scene.from_embedding(z0), 0.0, args=args)
                return jnp.where(run.result == pk.RESULTS.successful, scene.to_embedding(jax.tree.map(lambda a: a[-1], run.ys)), jnp.inf)

            compiled[steps], _ = C.compile_fn(final, z0, args)
            errors[steps] = float(np.max(np.abs(np.asarray(compiled[steps](z0, args)) - reference)))
            if errors[steps] < min(COST_TARGETS):
                break
        times = C.interleaved_times(compiled, z0, args, rounds=rounds)
        rows.append(dict(model=model, method=name, points=[dict(steps=n, error=errors[n], ms=1e3 * np.median(times[n])) for n in compiled]))
        print(f"{name:28} {model:16} " + " ".join(f"{p['steps']}: {p['error']:.1e} {p['ms']:.2f}" for p in rows[-1]["points"]), flush=True)
    return dict(machine=C.machine(), t_end=t_end, rows=rows)


def cost_table(data: dict) -> str:
    """The cheapest run of each method and model that reaches each target (`scene_costs`)."""
    rows = []
    for r in data["rows"]:
        cells = []
        for target in COST_TARGETS:
            reached = [p for p in r["points"] if p["error"] <= target]
            best = min(reached, key=lambda p: p["ms"]) if reached else None
            cells.append(f"{best['ms']:.3g} ({best['steps']:,})" if best else f"– (> {r['points'][-1]['steps']:,})")
        rows.append([r["method"], r["model"]] + cells)
    headers = ["method", "model"] + [f"ms to {t:.0e} (steps)" for t in COST_TARGETS]
    return C.measured_on(data) + f" The error at T = {data['t_end']:g} (largest entry of the embedding).\n\n" + C.table(headers, rows)


def scene_table(results: Path, scene_name: str) -> str:
    """`long_time.py --scene NAME`: each model and method over 10⁵ steps."""
    data = C.results_file(results, f"long_time_{scene_name}.json")
    invariants = [k for k in data["rows"][0] if k not in ("model", "method", "compile_s", "step_us", "iterations", "error")]
    first = [[r["method"], r["model"], f"{r['step_us']:.2f}", f"{r['iterations']:.1f}", f"{r['compile_s']:.1f}"] for r in data["rows"]]
    rows = [row + [C.number(r[k], ".2g") for k in ["error"] + invariants] for row, r in zip(first, data["rows"])]
    headers = ["method", "model", "µs a step", "iterations a step", "compile s", f"error at T = {data['h'] * data['every']:g}"]
    drifts = C.measured_on(data) + f" {data['steps']:,} steps of h = {data['h']:g}.\n\n" + C.table(headers + invariants, rows)
    costs = results / f"long_time_{scene_name}_costs.json"
    return drifts + (f"\n\nThe cost to a target error:\n\n{cost_table(C.results_file(results, costs.name))}" if costs.exists() else "")


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from those of its results files that `results` holds (`write_tables.py`)."""
    found = {"long_time": long_time_table(results)} if (results / "long_time.json").exists() else {}
    return found | {name: scene_table(results, name) for name in SCENE_RUNS if (results / f"long_time_{name}.json").exists()}


def main(argv=None):
    def arguments(parser):
        parser.add_argument("--scene", choices=list(SCENE_RUNS), help="that scene's rows")
        parser.add_argument("--costs", action="store_true", help="with --scene: the step count swept, the cost to each target error")

    args, out = C.cli(__doc__, argv, arguments)
    if args.scene:
        rows, name = (scene_costs, f"{args.scene}_costs") if args.costs else (scene_rows, args.scene)
        (out / f"long_time_{name}.json").write_text(json.dumps(rows(args.scene, args.quick, 1 if args.quick else 3), indent=1))
        return out
    t_end, repeats = (20.0, 1) if args.quick else (1000.0, 3)
    q0, pi0, inertia = (jnp.asarray(x) for x in (*C.initial_conditions(None), C.INERTIA))
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
