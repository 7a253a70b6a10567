"""Long runs at the round-off limit: how the invariants' errors grow with the
number of steps, and what solving the implicit stages to round-off costs
(`PRKMK(iterate_until="round-off")`, the default, against
`iterate_until="tolerance"`, which stops at the default tolerance 1e-12).

Growth: for each method and setting (`methods`, `SPLITTINGS`), a batch of
`--batch` random initial states (`initial_states`), h = 0.1 (the heavy top
0.05), run for up to `--max-steps` steps. For each invariant the largest
error up to step N is taken per trajectory (`invariant_errors`), its median
over the batch recorded, and the growth exponent fitted over N ≥ 10⁴
(`exponent`; 0.5 for a random walk of roundings, 1 for a bias) with the
central 90% of its bootstrap distribution (`exponent_interval`). Against
diffrax's Dopri8 on the embedding at the constant step where it costs what
SV costs per unit of simulated time (`dopri8_at_equal_cost`).

Cost: the implicit methods, one trajectory and a batch of 64 in the state,
both settings compiled and run interleaved: ns per trajectory-step,
implicit iterations a step, and their ratios. `benchmarks/README.md` says
more.

    python benchmarks/round_off.py
    python benchmarks/round_off.py --quick
    python benchmarks/round_off.py --float32-rows   # those rows again, the others kept
"""

import json
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import FreeRigidBody, HeavyTop
from prkmk_jax.scenes.rigid_body import PAPER_INERTIA, random_rotation

STEP = {"free body": 0.1, "heavy top": 0.05}
SETTINGS = ("round-off", "tolerance")
FREE = FreeRigidBody()
TOP = HeavyTop()
TOP_ARGS = C.top_parameters()
SCENES = {"free body": (FREE, jnp.asarray(PAPER_INERTIA)), "heavy top": (TOP, TOP_ARGS)}
ERROR_KINDS = {"orthogonality": "absolute"}
"""Errors taken as they are; the others relative to their initial value."""


def methods(setting):
    """name -> (scene name, method), for one `iterate_until` setting."""
    bundle = FREE.bundle

    def prkmk(tableau, coordinates=pk.Exp()):
        return pk.PRKMK(bundle, coordinates, tableau, form="body", iterate_until=setting)

    sv = prkmk(pk.stormer_verlet)
    return {
        "SV exp": ("free body", sv),
        "SV Cayley": ("free body", prkmk(pk.stormer_verlet, pk.Cayley())),
        # SV at Exp's default truncation is symmetric for the free body on T*SO(3).
        "SV∘Kahan–Li 6": ("free body", pk.Composition(sv, pk.kahan_li_6, assume_symmetric_base=True)),
        "Symmetrized Lobatto 4": ("free body", pk.Symmetrized(prkmk(pk.lobatto_iiia_iiib4))),
        "Symmetrized SV, heavy top": ("heavy top", pk.Symmetrized(prkmk(pk.stormer_verlet))),
    }


SPLITTINGS = {
    "splitting (Strang)": ("free body", FREE.splitting()),
    "splitting Kahan–Li 8": ("free body", FREE.splitting(pk.kahan_li_8)),
    "splitting (Strang), heavy top": ("heavy top", TOP.splitting()),
}
"""name -> (scene name, method): explicit, so one setting ("explicit")."""


def initial_states(batch, seed=0, dtype=jnp.float64):
    rng = np.random.default_rng(seed)
    momenta = rng.normal(size=(batch, 3))
    momenta /= np.linalg.norm(momenta, axis=1, keepdims=True)
    attitudes = np.stack([random_rotation(seed * 1009 + k) for k in range(batch)])
    return pk.BundleElement(pk.SO3(jnp.asarray(attitudes, dtype)), jnp.asarray(momenta, dtype))


def growth(method, scene_name, num_steps, batch, every, dtype=jnp.float64):
    """The largest error up to each saved step, per invariant and trajectory
    (`invariant_errors`), and the wall time of the run (compile included)."""
    scene, args = SCENES[scene_name]
    args = jax.tree.map(lambda a: jnp.asarray(a, dtype), args)
    y0 = initial_states(batch, dtype=dtype)
    h = STEP[scene_name]
    run = jax.jit(jax.vmap(lambda y: pk.integrate(method, scene, y, 0.0, h, num_steps, args, save_every=every)))
    start = time.perf_counter()
    trajectory = jax.block_until_ready(run(y0))
    seconds = time.perf_counter() - start
    if not bool(jnp.all(trajectory.result == pk.RESULTS.successful)):
        raise RuntimeError(f"{scene_name}: a stage failed to converge")
    return invariant_errors(scene.invariants(trajectory.ys, args)), seconds


def invariant_errors(invariants):
    """Per trajectory, the largest error up to each saved point, per
    invariant, shape (batch, saves) (relative, but QᵀQ − I as it is)."""
    errors = {}
    for name, values in invariants.items():
        values = np.asarray(values, np.float64)
        if ERROR_KINDS.get(name) == "absolute":
            error = values
        elif values.ndim == 3:  # a vector (the spatial momentum): its largest change over its largest entry
            error = np.max(np.abs(values - values[:, :1]), axis=2) / np.max(np.abs(values[:, :1]), axis=2)
        else:
            error = np.abs(values / values[:, :1] - 1)
        errors[name] = np.maximum.accumulate(error, axis=1)
    return errors


def log_spaced_picks(steps, smallest, count):
    """The indices of the entries of `steps` nearest to `count` points spaced
    evenly in log(steps) from `smallest` to the last, ascending, each once."""
    targets = np.exp(np.linspace(np.log(smallest), np.log(steps[-1]), count))
    return sorted({int(np.argmin(np.abs(np.log(steps) - np.log(t)))) for t in targets})


def stored(row, checkpoints, errors, count=80):
    """`row` with the exponents fitted on every checkpoint, and the
    checkpoints and errors thinned to about `count` spaced evenly in
    log(checkpoints), the last included: what the results file keeps."""
    checkpoints = np.asarray(checkpoints)
    picks = sorted(set(log_spaced_picks(checkpoints, checkpoints[0], count)) | {len(checkpoints) - 1})
    row["exponent"] = {k: exponent(checkpoints, v) for k, v in errors.items()}
    row["checkpoints"] = [int(checkpoints[i]) for i in picks]
    row["errors"] = {k: [float(v[i]) for i in picks] for k, v in errors.items()}
    return row


def growth_row(row, per_trajectory, every):
    """`stored` for the batch's median of errors saved every `every` steps
    from step 0 (left out), with each exponent's bootstrap interval, and
    the line that reports it."""
    per_trajectory = {k: v[:, 1:] for k, v in per_trajectory.items()}
    saved = np.arange(1, next(iter(per_trajectory.values())).shape[1] + 1) * every
    row = stored(row, saved, {k: np.median(v, axis=0) for k, v in per_trajectory.items()})
    row["exponent_interval"] = {k: exponent_interval(saved, v) for k, v in per_trajectory.items()}
    return row, "  ".join(
        f"{k}: {row['errors'][k][-1]:.1e} ({row['exponent'][k]:.2f}, {lo:.2f}–{hi:.2f})" for k, (lo, hi) in row["exponent_interval"].items()
    )


def exponent_interval(steps, per_trajectory, resamples=2000, seed=0, smallest=10_000):
    """The central 90% of the exponent (`exponent`) of the batch's median
    over `resamples` batches drawn from the trajectories with replacement:
    how far the fit moves with the initial states drawn (a bootstrap)."""
    steps = np.asarray(steps, float)
    picks = log_spaced_picks(steps, smallest, 13)
    if len(picks) < 2:
        return [float("nan"), float("nan")]
    columns = np.maximum(per_trajectory[:, picks], 1e-300)
    draws = np.random.default_rng(seed).integers(0, columns.shape[0], (resamples, columns.shape[0]))
    medians = np.median(columns[draws], axis=1)  # (resamples, picks)
    slopes = np.polyfit(np.log(steps[picks]), np.log(medians).T, 1)[0]
    return [float(q) for q in np.quantile(slopes, [0.05, 0.95])]


def exponent(steps, errors, smallest=10_000):
    """Least-squares slope of log(error) against log(steps), over steps ≥
    `smallest`, at points spaced evenly in log(steps)."""
    steps, errors = np.asarray(steps, float), np.asarray(errors, float)
    picks = log_spaced_picks(steps, smallest, 13)
    if len(picks) < 2:
        return float("nan")
    return float(np.polyfit(np.log(steps[picks]), np.log(np.maximum(errors[picks], 1e-300)), 1)[0])


def cost(scene_name, batch, num_steps, rounds, setting_methods):
    """ns per trajectory-step and iterations a step of each setting, interleaved."""
    scene, args = SCENES[scene_name]
    y0 = initial_states(batch) if batch > 1 else jax.tree.map(lambda a: a[0], initial_states(1))

    def make(m):
        def run(y):
            trajectory = pk.integrate(m, scene, y, 0.0, STEP[scene_name], num_steps, args, save_every=num_steps)
            return trajectory.ys, trajectory.stats["num_iterations"]

        return run

    fns = {setting: make(m) for setting, m in setting_methods.items()}
    compiled, compile_s, outputs = C.compile_all(fns, y0)
    times = C.interleaved_times(compiled, y0, rounds=rounds)
    ns = C.ns_per_trajectory_step(times, batch, num_steps)
    iterations = {setting: int(outputs[setting][1]) / num_steps for setting in fns}
    ratio = C.median_ratio(times, "round-off", "tolerance")
    return dict(ns_per_traj_step=ns, iterations_per_step=iterations, round_off_over_tolerance=ratio, compile_s=compile_s)


def dopri8_at_equal_cost(sv, num_steps, batch, every, probe_steps):
    """Dopri8 on the embedding of the free body, at the constant step that
    costs per unit of simulated time what `sv` (h = 0.1) costs, over the
    same horizon, saved at the same times. Returns (errors, its step, the
    two costs in ns per trajectory-step)."""
    h = STEP["free body"]
    inertia = jnp.asarray(PAPER_INERTIA)
    y0 = initial_states(batch)
    z0 = FREE.to_embedding(y0)

    def dopri8(z, t_end, dt, ts):
        term, saveat = diffrax.ODETerm(FREE.embedding_field), diffrax.SaveAt(ts=ts)
        return diffrax.diffeqsolve(term, diffrax.Dopri8(), 0.0, t_end, dt, z, inertia, saveat=saveat, max_steps=None).ys

    def sv_run(y):
        return pk.integrate(sv, FREE, y, 0.0, h, probe_steps, inertia, save_every=probe_steps).ys

    probe_ts = jnp.asarray([probe_steps * h])
    sv_fn = jax.jit(jax.vmap(sv_run))
    d8_fn = jax.jit(jax.vmap(lambda z: dopri8(z, probe_steps * h, h, probe_ts)))
    jax.block_until_ready((sv_fn(y0), d8_fn(z0)))
    times = C.interleaved_times({"SV": lambda: sv_fn(y0), "Dopri8": lambda: d8_fn(z0)}, rounds=3)
    ns = C.ns_per_trajectory_step(times, batch, probe_steps)
    sv_ns, d8_ns = ns["SV"], ns["Dopri8"]
    dt = h * d8_ns / sv_ns  # equal cost per unit time: fewer, dearer steps
    ts = np.arange(0, num_steps // every + 1) * every * h
    t_end, saves = float(ts[-1]), jnp.asarray(ts)
    zs = jax.jit(jax.vmap(lambda z: dopri8(z, t_end, dt, saves)))(z0)
    q, pi = zs[..., :9].reshape(*zs.shape[:-1], 3, 3), zs[..., 9:]
    errors = invariant_errors(FREE.invariants(pk.BundleElement(pk.SO3(q), pi), inertia))
    return errors, dt, ns


def chart(rows, dopri, out):
    fig, ax = C.subplots(figsize=(6.4, 4.4))
    h = STEP["free body"]
    styles = {"round-off": "-", "tolerance": "--"}
    charted = {}  # one line per method and setting: its longest run, then its largest batch
    for row in rows:
        if row["scene"] == "free body" and row["dtype"] == "float64" and row["method"] in ("SV exp", "SV∘Kahan–Li 6"):
            key = (row["method"], row["setting"])
            if key not in charted or (row["steps"], row["batch"]) > (charted[key]["steps"], charted[key]["batch"]):
                charted[key] = row
    for row in charted.values():
        ts = np.asarray(row["checkpoints"]) * h
        ax.loglog(ts, row["errors"]["energy"], styles[row["setting"]], label=f"{row['method']}, {row['setting']}")
    ts = np.asarray(dopri["checkpoints"]) * h
    ax.loglog(ts, dopri["errors"]["energy"], ":", label=f"Dopri8 at SV exp's cost (h = {dopri['dt']:.3f})")
    ax.set_xlabel("time (free body, h = 0.1 for SV)")
    ax.set_ylabel("median of the largest relative energy error so far")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    C.save(fig, out / "round_off.png", dpi=120)


def round_off_table(results: Path) -> str:
    """`round_off.py`'s results: how each invariant's error grows with the
    number of steps (the largest error at the last step and the fitted
    exponent), for the stages solved to round-off and stopped at the
    tolerance, for the explicit splittings, and Dopri8 at equal cost."""
    data = C.results_file(results, "round_off.json")

    def growth(run):
        def fit(name):
            interval = run.get("exponent_interval", {}).get(name)
            return f"{run['exponent'][name]:.2f}" + ("" if interval is None else f", {interval[0]:.2f}–{interval[1]:.2f}")

        return ", ".join(f"{name} {run['errors'][name][-1]:.1e} ({fit(name)})" for name in run["errors"])

    rows = [[r["method"], r["scene"], r["setting"], r["dtype"], str(r["batch"]), f"{r['steps']:.0e}", growth(r)] for r in data["growth"]]
    d = data["dopri8"]
    batch, horizon = d.get("batch", data["growth"][0]["batch"]), f"same time as SV's {d['steps_of_sv']:.0e}"
    rows.append([f"Dopri8 at SV's cost (h = {d['dt']:.3f})", "free body", "explicit", "float64", str(batch), horizon, growth(d)])
    last = "largest error at the last step (growth exponent, its 90% interval)"
    headers = ["method", "scene", "stages", "dtype", "trajectories", "steps", last]
    return C.table(headers, rows)


def round_off_cost_table(results: Path) -> str:
    """`round_off.py`'s cost rows: ns per trajectory-step and iterations a
    step with the stages solved to round-off and stopped at the tolerance,
    interleaved."""
    data = C.results_file(results, "round_off.json")
    device = C.device_name(data["machine"])
    rows = []
    for r in data["cost"]:
        ns, it = r["ns_per_traj_step"], r["iterations_per_step"]
        cells = [f"{ns['round-off']:.0f}", f"{ns['tolerance']:.0f}", f"{r['round_off_over_tolerance']:.2f}"]
        rows.append([r["method"], str(r["batch"]), device, *cells, f"{it['round-off']:.1f}", f"{it['tolerance']:.1f}"])
    headers = ["method", "trajectories", "device", "round-off, ns", "tolerance, ns", "round-off / tolerance"]
    return C.table([*headers, "iterations a step, round-off", "tolerance"], rows)


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from its results in `results` (`write_tables.py`)."""
    return {"round_off": round_off_table(results), "round_off_cost": round_off_cost_table(results)}


def main(argv=None):
    def extra(parser):
        parser.add_argument("--max-steps", type=float, default=1e6, help="steps of the growth runs (default 1e6)")
        parser.add_argument("--long-steps", type=float, default=1e7, help="steps of the longest run, SV exp at round-off (default 1e7)")
        parser.add_argument("--batch", type=int, default=64, help="trajectories of each growth run (default 64)")
        parser.add_argument("--float32-rows", action="store_true", help="run the float32 rows again, keeping the results' others")

    args, out = C.cli(__doc__, argv, extra)
    quick = args.quick
    max_steps = 4_000 if quick else int(args.max_steps)
    long_steps = 4_000 if quick else int(args.long_steps)
    batch = 2 if quick else args.batch
    every = 1000

    def growth_of(name, setting, dtype=jnp.float64, steps=max_steps):
        """One growth row: `name` from `methods(setting)` or `SPLITTINGS`."""
        scene_name, method = SPLITTINGS[name] if name in SPLITTINGS else methods(setting)[name]
        errors, seconds = growth(method, scene_name, steps, batch, every, dtype)
        dtype_name = jnp.dtype(dtype).name
        row = dict(method=name, scene=scene_name, setting=setting, dtype=dtype_name, batch=batch, steps=steps, seconds=seconds)
        row, summary = growth_row(row, errors, every)
        label = name if dtype_name == "float64" else f"{name}, {dtype_name}"
        print(f"{label:28s} {setting:10s} {steps:9d} {seconds:7.1f}  {summary}", flush=True)
        return row

    def dopri8_row(sv_steps):
        """The row of Dopri8 at SV's cost over SV's `sv_steps` steps."""
        probe = 500 if quick else 20_000
        sv = methods("round-off")["SV exp"][1]
        dopri_errors, dopri_dt, dopri_cost = dopri8_at_equal_cost(sv, sv_steps, batch, every, probe)
        dopri = dict(method="Dopri8, equal cost", batch=batch, dt=dopri_dt, ns_per_traj_step=dopri_cost, steps_of_sv=sv_steps)
        dopri, summary = growth_row(dopri, dopri_errors, every)
        print(f"{'Dopri8, equal cost':28s} {'h=' + format(dopri_dt, '.3f'):10s} {sv_steps:9d} {'':7s}  {summary}", flush=True)
        return dopri

    def cost_rows():
        """The cost of each implicit method in both settings, interleaved."""
        by_setting = {setting: methods(setting) for setting in SETTINGS}
        rows = []
        rounds = 2 if quick else 9
        print(f"\n{'method':28s} {'batch':>5s} {'round-off ns':>12s} {'tolerance ns':>12s} {'ratio':>6s} {'it r-o':>7s} {'it tol':>7s}")
        # --quick: the cost of the first method only, which runs the same code.
        for name in list(by_setting["round-off"])[:1] if quick else by_setting["round-off"]:
            for cost_batch in (4,) if quick else (1, 64):
                scene_name = by_setting["round-off"][name][0]
                steps = 20 if quick else max(200, 20_000 // cost_batch)
                row = cost(scene_name, cost_batch, steps, rounds, {s: by_setting[s][name][1] for s in SETTINGS})
                row.update(method=name, scene=scene_name, batch=cost_batch, steps=steps)
                rows.append(row)
                ns, it, ratio = row["ns_per_traj_step"], row["iterations_per_step"], row["round_off_over_tolerance"]
                numbers = f"{ns['round-off']:12.0f} {ns['tolerance']:12.0f} {ratio:6.2f} {it['round-off']:7.1f} {it['tolerance']:7.1f}"
                print(f"{name:28s} {cost_batch:5d} {numbers}", flush=True)
        return rows

    if args.float32_rows:  # the chart draws float64 rows only: it stays
        data = json.loads((out / "round_off.json").read_text())
        data["growth"] = [growth_of(r["method"], r["setting"], jnp.float32) if r["dtype"] == "float32" else r for r in data["growth"]]
        (out / "round_off.json").write_text(json.dumps(data, indent=1))
        return out
    by_setting = {setting: methods(setting) for setting in SETTINGS}
    growth_rows = []
    print(f"{'method':28s} {'setting':10s} {'steps':>9s} {'s':>7s}  invariant: median max error (exponent, its 90% interval)")
    # --quick only checks that the script runs: one implicit method, its
    # float32 run and one splitting, each through the same code as the rest.
    growth_settings = SETTINGS[:1] if quick else SETTINGS
    for name in list(by_setting["round-off"])[:1] if quick else by_setting["round-off"]:
        for setting in growth_settings:
            steps = long_steps if (name == "SV exp" and setting == "round-off") else max_steps
            growth_rows.append(growth_of(name, setting, steps=steps))
    # float32: SV exp, both settings (the step renormalises the state there).
    growth_rows += [growth_of("SV exp", setting, jnp.float32) for setting in growth_settings]
    growth_rows += [growth_of(name, "explicit") for name in (list(SPLITTINGS)[:1] if quick else SPLITTINGS)]

    dopri = dopri8_row(max_steps)
    chart(growth_rows, dopri, out)
    with open(out / "round_off.json", "w") as f:
        json.dump(dict(machine=C.machine(), h=STEP, growth=growth_rows, dopri8=dopri, cost=cost_rows()), f, indent=1)
    return out


if __name__ == "__main__":
    print("\n\n".join(tables(main()).values()))
