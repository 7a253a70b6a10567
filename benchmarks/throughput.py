"""Throughput and compile time (the gradients' cost: `gradients.py`).

1. Trajectory-steps per second against batch size, free rigid body, h = 0.01:
   PRKMK Störmer–Verlet (T*SO(3), body form, exp) through `lax.scan`
   (`prkmk_jax.integrate`) and through `diffeqsolve`, in float64 and
   float32, diffrax Tsit5 with constant steps on the embedding ℝ⁹×ℝ³, and
   for the cost of a step beside it, RKMK 8 (Cayley), the exact flow and the
   Kahan–Li 6 splitting; SV, RKMK 8 and the splitting again on quaternions.
   The step count per run shrinks with the batch so every run does a
   similar amount of work; all run in alternation (7 rounds; medians,
   and the median per-round ratio to Tsit5); also reported: implicit
   iterations per step.
2. Compile time (lower + compile of a fresh jit) against the number of
   stages: symplectic Euler (1), Störmer–Verlet (2), Lobatto IIIA–IIIB (3).
3. The explicit stages unrolled or in a loop (`PRKMK(explicit_stages=...)`):
   classical RK 4 and Dormand–Prince 8 (RKMK; exp, and Cayley coordinates
   for DP 8) on T*SO(3) and on G×g (at 1024 also the heavy top, whose field moves the fiber), one
   trajectory and batches of 8, 16 and 1024 in the state, the two layouts
   in alternation; time a step, loop over unrolled, and compile times: the
   rows that check the default ("auto": the loop from `STAGE_LOOP_BATCH`
   trajectories in the state on).

    python benchmarks/throughput.py
    python benchmarks/throughput.py --quick
"""

import functools
import json
import statistics
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import FreeRigidBody, HeavyTop

H = 0.01
TOP_ARGS = C.top_parameters()
QUATERNIONS = FreeRigidBody(pk.Cotangent(pk.UnitQuaternion))  # the attitude as a unit quaternion
QUATERNION_RKMK8 = QUATERNIONS.method(pk.dormand_prince_8, pk.Cayley())


def _scan(method, steps, scene=C.SCENE):
    final = C.integrate_final(method, steps, H, scene=scene)

    def run(q0, pi0, inertia):
        _, pi, iterations = final(q0, pi0, inertia)
        return pi, iterations

    return run


def _diffeqsolve(method, steps):
    def run(q0, pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(q0), pi0)
        sol = diffrax.diffeqsolve(pk.PRKMKTerm(C.SCENE), pk.PRKMKSolver(method), 0.0, steps * H, H, y0, inertia, max_steps=steps)
        return sol.ys.fiber[-1], jnp.nan

    return run


def _tsit5(steps):
    def run(q0, pi0, inertia):
        z0 = jnp.concatenate([q0.reshape(9), pi0])
        sol = diffrax.diffeqsolve(diffrax.ODETerm(C.embedding_rhs), diffrax.Tsit5(), 0.0, steps * H, H, z0, inertia, max_steps=steps)
        return sol.ys[-1, 9:], jnp.nan

    return run


def throughput(quick, rounds):
    batches = [8] if quick else [1, 64, 1024, 16384, 65536]
    method64 = C.SCENE.method(pk.stormer_verlet)
    rows = []
    for batch in batches:
        steps = 10 if quick else int(min(400, max(10, 2_000_000 // (batch * 10))))
        qs, pis = C.initial_conditions(batch, seed=3)
        columns = {
            "PRKMK SV scan": (jnp.float64, _scan(method64, steps)),
            "PRKMK SV scan float32": (jnp.float32, _scan(method64, steps)),
            "PRKMK SV diffeqsolve": (jnp.float64, _diffeqsolve(method64, steps)),
            "diffrax Tsit5 (embedding)": (jnp.float64, _tsit5(steps)),
            "PRKMK DP8 Cayley scan": (jnp.float64, _scan(C.SCENE.method(pk.dormand_prince_8, pk.Cayley()), steps)),
            "exact flow scan": (jnp.float64, _scan(C.SCENE.exact_flow(), steps)),
            "Kahan–Li 6 splitting scan": (jnp.float64, _scan(C.SCENE.splitting(pk.kahan_li_6), steps)),
            "Kahan–Li 6 splitting scan, quaternion": (jnp.float64, _scan(QUATERNIONS.splitting(pk.kahan_li_6), steps, QUATERNIONS)),
            "PRKMK SV scan, quaternion": (jnp.float64, _scan(QUATERNIONS.method(pk.stormer_verlet), steps, QUATERNIONS)),
            "PRKMK DP8 Cayley scan, quaternion": (jnp.float64, _scan(QUATERNION_RKMK8, steps, QUATERNIONS)),
        }
        # --quick: the columns of each kind of code (the other methods run SV's scan)
        columns = {name: column for name, column in columns.items() if not quick or name.startswith(("PRKMK SV", "diffrax"))}
        compiled, compile_s, iterations, args_of = {}, {}, {}, {}
        for name, (dtype, run) in columns.items():
            args_of[name] = (jnp.asarray(qs, dtype), jnp.asarray(pis, dtype), jnp.asarray(C.INERTIA, dtype))
            compiled[name], compile_s[name] = C.compile_fn(jax.vmap(run, in_axes=(0, 0, None)), *args_of[name])
            iterations[name] = jax.block_until_ready(compiled[name](*args_of[name]))[1]
        # In alternation, so that a slow spell of the machine hits them all; each with its own arguments.
        bound = {name: functools.partial(fn, *args_of[name]) for name, fn in compiled.items()}
        times = C.interleaved_times(bound, rounds=rounds)
        for name in columns:
            wall, iters = statistics.median(times[name]), iterations[name]
            iters_per_step = float(jnp.mean(iters)) / steps if jnp.all(jnp.isfinite(iters)) else float("nan")
            over_tsit5 = C.median_ratio(times, name, "diffrax Tsit5 (embedding)")
            row = dict(batch=batch, method=name, steps=steps, wall_s=wall, compile_s=compile_s[name], traj_steps_per_s=batch * steps / wall)
            rows.append(row | dict(iterations_per_step=iters_per_step, over_tsit5=over_tsit5))
            print(f"batch {batch:6d} {name:28s} {row['traj_steps_per_s']:10.3e} traj-steps/s  time / Tsit5 {over_tsit5:5.2f}", flush=True)
    return rows


def compile_vs_stages(quick):
    rows = []
    qs, pis = C.initial_conditions(8, seed=3)
    args = (jnp.asarray(qs), jnp.asarray(pis), jnp.asarray(C.INERTIA))
    tableaus = (("SE", pk.symplectic_euler), ("SV", pk.stormer_verlet), ("Lobatto4", pk.lobatto_iiia_iiib4))
    for name, tab in tableaus[1:2] if quick else tableaus:
        method = C.SCENE.method(tab)
        for path, make in (("scan", _scan), ("diffeqsolve", _diffeqsolve)):
            _, compile_s = C.compile_fn(jax.vmap(make(method, 50), in_axes=(0, 0, None)), *args)
            rows.append(dict(tableau=name, stages=tab.num_stages, path=path, compile_s=compile_s))
            print(f"{name:9s} stages={tab.num_stages}  {path:12s} compile {compile_s:5.2f}s", flush=True)
    return rows


def _side_by_side(finals, args, steps, rounds):
    """Compile each of `finals` ({name: (Q₀, Π₀, inertia) -> …}, two of
    them) and run them in alternation: µs a step of each, the first's time
    over the second's (the median per-round ratio), and compile seconds."""
    compiled, compile_s, _ = C.compile_all(finals, *args)
    times = C.interleaved_times({k: functools.partial(f, *args) for k, f in compiled.items()}, rounds=rounds)
    first, second = finals
    return {k: 1e6 * statistics.median(v) / steps for k, v in times.items()}, C.median_ratio(times, first, second), compile_s


def stage_layouts(quick, rounds):
    rows = []
    bundles = {"T*SO(3)": pk.Cotangent(pk.SO3), "G×g": pk.DirectProduct(pk.SO3)}
    tableaus = {"RK 4": (pk.classical_rk4, pk.Exp()), "DP 8": (pk.dormand_prince_8, pk.Exp())}
    tableaus["DP 8, Cayley"] = (pk.dormand_prince_8, pk.Cayley())
    if quick:  # one of each layout: the script runs
        bundles, tableaus = {"T*SO(3)": bundles["T*SO(3)"]}, {"DP 8": tableaus["DP 8"]}
    batches = [8] if quick else [1, 8, 16, 1024]
    for batch in batches:
        steps = 10 if quick else max(50, 2000 // batch)
        qs, pis = C.initial_conditions(batch, seed=3)
        args = (jnp.asarray(qs), jnp.asarray(pis), jnp.asarray(C.INERTIA))
        scenes = [(name, FreeRigidBody(bundle), args) for name, bundle in bundles.items()]  # the largest batch: the heavy top too
        scenes += [(f"{name}, heavy top", HeavyTop(b), args[:2] + (TOP_ARGS,)) for name, b in bundles.items() if batch == batches[-1]]
        for bundle_name, scene, scene_args in scenes:
            for tableau_name, (tableau, coordinates) in tableaus.items():
                finals = {
                    k: C.integrate_final(scene.method(tableau, coordinates, explicit_stages=k), steps, H, scene=scene)
                    for k in ("loop", "unrolled")
                }
                step_us, ratio, compile_s = _side_by_side(finals, scene_args, steps, rounds)
                row = dict(bundle=bundle_name, tableau=tableau_name, batch=batch, step_us=step_us)
                rows.append(row | dict(loop_over_unrolled=ratio, compile_s=compile_s))
                print(f"{bundle_name:8s} {tableau_name:5s} batch {batch:5d}  µs a step {step_us}  loop/unrolled {ratio:5.2f}  {compile_s}")
    return rows


def throughput_table(results: Path) -> str:
    """`throughput.py`: trajectory-steps per second against the batch, compile
    time against the number of stages, and the explicit stage layouts (each
    part that the results hold)."""
    data = C.results_file(results, "throughput.json")
    tables = [C.measured_on(data)] if "machine" in data else []
    if "throughput" in data:
        rows = [
            [
                str(r["batch"]),
                r["method"],
                f"{r['traj_steps_per_s']:.3g}",
                C.number(r["iterations_per_step"], ".1f"),
                C.number(r["over_tsit5"], ".2f"),
                f"{r['compile_s']:.2f}",
            ]
            for r in data["throughput"]
        ]
        tables.append(C.table(["batch", "method", "trajectory-steps/s", "iterations a step", "time / Tsit5", "compile, s"], rows))
    if "compile_vs_stages" in data:
        rows = [[r["tableau"], str(r["stages"]), r["path"], f"{r['compile_s']:.2f}"] for r in data["compile_vs_stages"]]
        tables.append(C.table(["tableau", "stages", "path", "compile, s"], rows))
    if "stage_layouts" in data:
        header = ["bundle", "tableau", "batch in the state", "µs a step, unrolled", "µs a step, loop", "loop / unrolled"]
        rows = [
            [r["bundle"], r["tableau"], str(r["batch"])]
            + [f"{r['step_us']['unrolled']:.3g}", f"{r['step_us']['loop']:.3g}", f"{r['loop_over_unrolled']:.2f}"]
            + [f"{r['compile_s']['unrolled']:.2f} / {r['compile_s']['loop']:.2f}"]
            for r in data["stage_layouts"]["rows"]
        ]
        header.append("compile, s (unrolled / loop)")
        tables += ["The explicit stage layouts. " + C.measured_on(data["stage_layouts"]), C.table(header, rows)]
    return "\n\n".join(tables)


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from its results in `results` (`write_tables.py`)."""
    return {"throughput": throughput_table(results)}


def main(argv=None):
    all_parts = ("throughput", "compile", "layouts")
    args, out = C.cli(__doc__, argv, lambda p: p.add_argument("--parts", default=",".join(all_parts)))
    rounds = 1 if args.quick else 7
    parts = args.parts.split(",")
    # A run of some parts keeps the other parts' results in the file.
    previous = out / "throughput.json"
    result = json.loads(previous.read_text()) if previous.exists() and set(parts) != set(all_parts) else {}
    if "throughput" in parts or "compile" in parts:
        result["machine"] = C.machine()
    if "throughput" in parts:
        result["throughput"] = throughput(args.quick, rounds)
    if "compile" in parts:
        result["compile_vs_stages"] = compile_vs_stages(args.quick)
    if "layouts" in parts:
        result["stage_layouts"] = dict(machine=C.machine(), rows=stage_layouts(args.quick, rounds))
    with open(out / "throughput.json", "w") as f:
        json.dump(result, f, indent=1)
    if "throughput" in parts:
        plot(result["throughput"], out / "throughput.png")
    return out


def plot(rows, path):
    fig, ax = C.subplots(figsize=(8, 5))
    for name in dict.fromkeys(r["method"] for r in rows):
        pts = [r for r in rows if r["method"] == name]
        ax.loglog([p["batch"] for p in pts], [p["traj_steps_per_s"] for p in pts], "-o", label=name)
    ax.axhline(3e7, color="k", ls=":", label="target 3·10⁷ (batch ≥ 10⁴)")
    ax.set_xlabel("batch size (trajectories)")
    ax.set_ylabel("trajectory-steps per second")
    ax.set_title("Free rigid body, h = 0.01, CPU")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    C.save(fig, path)


if __name__ == "__main__":
    print("\n\n".join(tables(main()).values()))
