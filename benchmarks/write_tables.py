"""The tables made from the benchmarks' results files, written into the
documents that quote them: the accuracy-per-second tables from
`benchmarks/splitting.py` (in `benchmarks/README.md`, the docs and notebook
05), and one or more tables of every other script's results in
`benchmarks/README.md`, each opening with the machine and jax version it
was measured on.

Each document holds its table between the lines

    <!-- write_tables.py: NAME -->
    <!-- /write_tables.py -->

and this script rewrites what is between them; nothing there is edited by
hand. Beside each results file it writes that file's `accuracy` table
(`results/splitting*.md`). Notebook 05 shows the decision table as the output of the cell that
calls `decision_table`, which this script writes too. `--check` rewrites
nothing and exits with status 1 where a document differs from what the
results give (the test suite runs it).

    python benchmarks/write_tables.py            # after a benchmark run
    python benchmarks/write_tables.py --check

Tables:

- `accuracy`: for each scene, batch, device and dtype, and each error
  target, the fastest run of the library (a splitting or PRKMK) against the
  fastest of diffrax's (Dopri8 and Tsit5 with constant steps or a PID
  controller, whichever reached the target sooner), their
  ratio, and the library's order-8 splitting per step over the
  hand-written kernel's (the floor of that family: the same arithmetic
  with no library code around it).
- `summary`: one row per scene, batch, device and dtype: the library's
  time over diffrax's at each target, for the library's fastest run and
  for its fastest symplectic run (a splitting or a Lobatto IIIA–IIIB
  pair; the RKMK runs keep the group but not the symplectic form).
- `stage_layout`: `stage_layout.json`, one row per case.
- `round_off`, `round_off_cost`: `round_off.json`, the growth of the
  invariants' errors over long runs and what solving the stages to
  round-off costs.
- `energy_drift`: `energy_drift.json`, the signed energy drift a step of
  SV at the round-off limit, and how much of it the initial state sets.
- `drift_emulation`: `drift_emulation.json`, the same drift of SV Cayley
  emulated in NumPy with parts of the step in extended precision, its
  one-ulp pairs, and its runs started as the library starts its steps.
- `decision`: the rows of `accuracy`, with the method to pick (the
  fastest run that reached the target; the hand-written kernel left out,
  it is not something a user calls), the runner-up, and the fastest
  symplectic run.
- `work_precision`, `long_time`, `heavy_top`, `throughput`, `stability`,
  `floor`, `against_scan`, `explicit_stages`, `root_finders`,
  `against_revision`, `gradients`, `ensembles`, `xla_codegen`: the script of the same name's results
  file, as its function's docstring says; `against_revision_gradients`:
  `against_revision.py --gradients`' file.
"""

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The checkout whose documents and `benchmarks/results` this script reads and writes."""
SOURCES = ("splitting.json", "splitting_16384.json", "splitting_gpu_float64.json", "splitting_gpu_float32.json")
"""The results files, in the order their rows are listed (those present)."""
DOCUMENTS = {
    "benchmarks/README.md": (
        "accuracy",
        "stage_layout",
        "work_precision",
        "long_time",
        "round_off",
        "round_off_cost",
        "energy_drift",
        "drift_emulation",
        "stability",
        "throughput",
        "against_scan",
        "floor",
        "heavy_top",
        "explicit_stages",
        "root_finders",
        "against_revision",
        "against_revision_gradients",
        "gradients",
        "ensembles",
        "xla_codegen",
    ),
    "docs/concepts/choosing.md": ("decision", "summary"),
}
FLOOR = "floor order 8 (hand-written)"
FAMILIES = (("splittings", "splitting"), ("PRKMK", "PRKMK"))
"""The library's families: name, and the prefix of their methods in the results."""
DIFFRAX = ("Dopri8 fixed", "Tsit5 fixed", "Dopri8 PID", "Tsit5 PID")


def is_library(method: str) -> bool:
    return method.startswith(("splitting", "PRKMK"))


def is_symplectic(method: str) -> bool:
    """The library's symplectic runs: the splittings and the Lobatto
    IIIA–IIIB pairs (the explicit RKMK tableaus keep the group, not the
    symplectic form)."""
    return method.startswith("splitting") or method.startswith("PRKMK Lobatto")


def device_name(machine: dict) -> str:
    card = machine.get("card (nvidia-smi)") or machine.get("device_kind", "")
    if machine.get("devices", ["cpu"])[0].startswith("cpu") or card.lower() == "cpu":
        return f"CPU, {machine['cpus']} cores"
    return card


def entries_of(data: dict, source: str) -> list[dict]:
    """The timed rows of one results file (`splitting.py`'s JSON): one entry
    per scene, batch, dtype and target, holding each method's fastest run
    that reached the target (method: (steps, seconds)) and which of the
    library's families the run swept (`families`)."""
    device = device_name(data["machine"])
    entries = []
    keys = dict.fromkeys((r["scene"], r["regime"], r.get("dtype", "float64")) for r in data["rows"])
    for scene, regime, dtype in keys:
        swept = {r["method"] for r in data["rows"] if (r["scene"], r["regime"], r.get("dtype", "float64")) == (scene, regime, dtype)}
        families = " and ".join(name for name, prefix in FAMILIES if any(m.startswith(prefix) for m in swept))
        for target in data.get("targets", (1e-6, 1e-8, 1e-10)):
            label = f"{target:.0e}"
            runs = {}
            for r in data["rows"]:
                timed = r.get("wall_s_at_target", {})
                if (r["scene"], r["regime"], r.get("dtype", "float64")) == (scene, regime, dtype) and label in timed:
                    runs[r["method"]] = (r["steps"], timed[label], r.get("rtol"))
            entries.append(
                dict(source=source, scene=scene, regime=regime, dtype=dtype, device=device, target=target, runs=runs, families=families)
            )
    return entries


def load(root: Path | None = None) -> list[dict]:
    """`entries_of` every results file present under `root` (default `ROOT`),
    in the order of `SOURCES`."""
    paths = [(root or ROOT) / "benchmarks" / "results" / name for name in SOURCES]
    return [e for path in paths if path.exists() for e in entries_of(json.loads(path.read_text()), path.stem)]


def _batch(regime: str) -> str:
    return "1" if regime == "single" else regime


def _fastest(runs: dict, keep) -> tuple[str, int, float] | None:
    found = [(m, n, s, rtol) for m, (n, s, rtol) in runs.items() if keep(m)]
    return min(found, key=lambda e: e[2]) if found else None


def _cell(entry) -> str:
    if entry is None:
        return "not reached | –"
    method, steps, seconds, rtol = entry
    setting = f"n = {steps}" if rtol is None else f"rtol = {rtol:.0e}, {steps} steps"
    return f"{method} ({setting}) | {seconds * 1e3:.2f}"


def accuracy_table(entries: list[dict]) -> str:
    lines = [
        "| scene | batch | device | dtype | library runs | target | library's fastest | ms | diffrax's fastest | ms | library / diffrax "
        "| order-8 splitting / hand-written, per step |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in entries:
        library, diffrax = _fastest(e["runs"], is_library), _fastest(e["runs"], lambda m: m in DIFFRAX)
        ratio = "–" if library is None or diffrax is None else f"{library[2] / diffrax[2]:.2f}"
        own, floor = e["runs"].get("splitting order 8"), e["runs"].get(FLOOR)
        per_step = "–" if own is None or floor is None else f"{(own[1] / own[0]) / (floor[1] / floor[0]):.2f}"
        lines.append(
            f"| {e['scene']} | {_batch(e['regime'])} | {e['device']} | {e['dtype']} | {e['families']} | {e['target']:.0e} "
            f"| {_cell(library)} | {_cell(diffrax)} | {ratio} | {per_step} |"
        )
    return "\n".join(lines)


def decision_table(entries: list[dict]) -> str:
    lines = [
        "| scene | batch | device, dtype | library runs | target | pick | ms | runner-up | ms | fastest symplectic | ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in entries:
        ranked = sorted(((m, n, s, rtol) for m, (n, s, rtol) in e["runs"].items() if m != FLOOR), key=lambda r: r[2])
        first = _cell(ranked[0]) if ranked else "none of the runs reached it | –"
        second = _cell(ranked[1]) if len(ranked) > 1 else "– | –"
        symplectic = _fastest(e["runs"], is_symplectic)
        where = f"{e['scene']} | {_batch(e['regime'])} | {e['device']}, {e['dtype']} | {e['families']}"
        lines.append(f"| {where} | {e['target']:.0e} | {first} | {second} | {_cell(symplectic)} |")
    return "\n".join(lines)


def summary_table(entries: list[dict]) -> str:
    groups = dict.fromkeys((e["scene"], e["regime"], e["device"], e["dtype"], e["families"]) for e in entries)
    lines = [
        "| scene | batch | device, dtype | library runs | library's fastest | library / diffrax's fastest, at each target "
        "| library's fastest symplectic | symplectic / diffrax's fastest |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key in groups:
        columns = {is_library: ([], []), is_symplectic: ([], [])}
        for e in (e for e in entries if (e["scene"], e["regime"], e["device"], e["dtype"], e["families"]) == key):
            diffrax = _fastest(e["runs"], lambda m: m in DIFFRAX)
            for keep, (cells, names) in columns.items():
                library = _fastest(e["runs"], keep)
                if library is not None and library[0] not in names:
                    names.append(library[0])
                cells.append(f"{e['target']:.0e}: {_ratio(library, diffrax)}")
        scene, regime, device, dtype, families = key
        row = f"| {scene} | {_batch(regime)} | {device}, {dtype} | {families} |"
        for cells, names in columns.values():
            row += f" {', '.join(names) or '–'} | {'; '.join(cells)} |"
        lines.append(row)
    return "\n".join(lines)


def _ratio(library, diffrax) -> str:
    if library is None:
        return "library not reached" if diffrax is not None else "not reached"
    if diffrax is None:
        return "diffrax not reached"
    return f"{library[2] / diffrax[2]:.2f}" + (" **(slower)**" if library[2] > diffrax[2] else "")


def results_file(name: str, root: Path | None = None) -> dict:
    """The results file `benchmarks/results/<name>`, read."""
    return json.loads(((root or ROOT) / "benchmarks" / "results" / name).read_text())


def _table(headers: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _number(value, spec: str) -> str:
    """`value` formatted, or "–" where there is none (None, NaN)."""
    if value is None or (isinstance(value, float) and value != value):
        return "–"
    return format(value, spec)


def _measured_on(data: dict) -> str:
    machine = data["machine"]
    if isinstance(machine, str):  # against_scan.json keeps the platform string and the jax version apart
        return f"Measured on {data['devices'][0].split(':')[0].upper()}, jax {data['jax']}."
    return f"Measured on {device_name(machine)}, jax {machine['jax']}."


def stage_layout_table(_entries=None, root: Path | None = None) -> str:
    """`stage_layout.py`'s results: ns per trajectory-step of an explicit
    tableau's stages unrolled and in a loop."""
    data = results_file("stage_layout.json", root)
    device = device_name(data["machine"])
    rows = []
    for r in data["rows"]:
        ns, cs = r["ns_per_traj_step"], r["compile_s"]
        rows.append(
            [
                r["scene"],
                r["tableau"],
                r["regime"],
                device,
                f"{ns['unrolled']:.0f}",
                f"{ns['loop']:.0f}",
                f"{r['loop_over_unrolled']:.2f}",
                f"{cs['unrolled']:.2f}",
                f"{cs['loop']:.2f}",
            ]
        )
    headers = ["scene", "tableau", "regime", "device", "unrolled, ns", "loop, ns", "loop / unrolled", "compile unrolled, s"]
    return _table([*headers, "compile loop, s"], rows)


def against_revision_table(_entries=None, root: Path | None = None, name: str = "against_revision") -> str:
    """`against_revision.py`'s results: ns per trajectory-step now and at
    the earlier revision, interleaved, and (for the gradient cases) the
    compile times of both."""
    data = results_file(f"{name}.json", root)
    device = device_name(data["machine"])
    with_compile = name == "against_revision_gradients"
    rows = []
    for r in data["rows"]:
        row = [r.get("scene", "free body"), r["tableau"], r["coordinates"], r["path"], r["dtype"], str(r["batch"]), device]
        row += [f"{r['ns_per_traj_step']['now']:.0f}", f"{r['ns_per_traj_step']['before']:.0f}", f"{r['now_over_before']:.2f}"]
        if with_compile:
            row += [f"{r['compile_s']['now']:.2f}", f"{r['compile_s']['before']:.2f}"]
        rows.append([*row, f"{r['max_abs_difference']:.1e}"])
    headers = ["scene", "tableau", "coordinates", "path", "dtype", "batch", "device", "now, ns", f"at {data['sha']}, ns", "now / before"]
    if with_compile:
        headers += ["compile now, s", "compile before, s"]
    return _measured_on(data) + "\n\n" + _table([*headers, "largest difference"], rows)


def against_revision_gradients_table(_entries=None, root: Path | None = None) -> str:
    """`against_revision.py --gradients`' results (`against_revision_table`)."""
    return against_revision_table(_entries, root, "against_revision_gradients")


def round_off_table(_entries=None, root: Path | None = None) -> str:
    """`round_off.py`'s results: how each invariant's error grows with the
    number of steps (the largest error at the last step and the fitted
    exponent), for the stages solved to round-off and stopped at the
    tolerance, for the explicit splittings, and Dopri8 at equal cost."""
    data = results_file("round_off.json", root)

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
    return _table(headers, rows)


def round_off_cost_table(_entries=None, root: Path | None = None) -> str:
    """`round_off.py`'s cost rows: ns per trajectory-step and iterations a
    step with the stages solved to round-off and stopped at the tolerance,
    interleaved."""
    data = results_file("round_off.json", root)
    device = device_name(data["machine"])
    rows = []
    for r in data["cost"]:
        ns, it = r["ns_per_traj_step"], r["iterations_per_step"]
        rows.append(
            [
                r["method"],
                str(r["batch"]),
                device,
                f"{ns['round-off']:.0f}",
                f"{ns['tolerance']:.0f}",
                f"{r['round_off_over_tolerance']:.2f}",
                f"{it['round-off']:.1f}",
                f"{it['tolerance']:.1f}",
            ]
        )
    headers = ["method", "trajectories", "device", "round-off, ns", "tolerance, ns", "round-off / tolerance"]
    return _table([*headers, "iterations a step, round-off", "tolerance"], rows)


def energy_drift_table(_entries=None, root: Path | None = None) -> str:
    """`energy_drift.py`: per run, the mean over the batch of each
    trajectory's signed drift a step (energy and the momentum norm squared, relative) with its
    standard error; for a run from momenta scaled by 1 + ε (one or two ulps), the correlation
    of its trajectories' energy drifts with those of the run it repeats, and
    their spread split into the part both share and the noise."""
    data = results_file("energy_drift.json", root)
    pairs = {(p["method"], p["h"], p["seed"]): p for p in data["pairs"]}

    def drift(summary):
        return f"{summary['mean']:+.1e} ± {summary['standard_error']:.1e}"

    rows = []
    for r in data["runs"]:
        pair = pairs.get((r["method"], r["h"], r["seed"])) if r["perturbed"] else None
        repeat = "–" if pair is None else f"{pair['correlation']:.2f}, {pair['shared']:.1e}, {pair['noise']:.1e}"
        states = f"set {r['seed']}" + (", one ulp off" if r["perturbed"] else "")
        rows.append(
            [
                r["method"],
                f"{r['h']:g}",
                states,
                str(r["batch"]),
                f"{r['steps']:.0e}",
                drift(r["energy"]),
                drift(r["momentum_norm_sq"]),
                repeat,
            ]
        )
    headers = ["method", "h", "initial states", "trajectories", "steps", "energy drift a step", "momentum norm² drift a step"]
    table = _table([*headers, "against the same set: correlation, shared spread, noise"], rows)
    return f"{_measured_on(data)}\n\n{table}"


def drift_emulation_table(_entries=None, root: Path | None = None) -> str:
    """`drift_emulation.py`: per variant (the part of the step computed in
    extended precision) and set of initial states, the mean over the batch
    of each trajectory's signed energy drift a step with its standard error;
    and the spread of the trajectories' drifts, averaged over the sets. Then
    the one-ulp pairs: each run's mean drift, the correlation of the two
    runs' drifts per trajectory, and their spread split into the part both
    share and the noise. Then the runs started from the previous step's
    stages (extrapolated, and either side of that as the library starts at
    round-off), after how near the emulated step is to the library's."""
    data = results_file("drift_emulation.json", root)
    first = data["runs"][0]
    intro = (
        f"{_measured_on(data)} {first['batch']} trajectories, {first['steps']:.0e} steps of h = {data['step']:g} each; "
        f"the float64 emulation's first step is {data['library_check_eps']:.1f} eps from the library's at most."
    )
    text = f"{intro}\n\n{_drift_table(data['runs'])}"
    if data.get("pairs"):
        runs_of = {(r["variant"], r["perturbed"]): r for r in data["pair_runs"]}
        pair_rows = []
        for p in data["pairs"]:
            drifts = [runs_of[(p["variant"], perturbed)] for perturbed in (False, True)]
            pair_rows.append(
                [
                    p["variant"],
                    f"{p['h']:g}",
                    str(p["batch"]),
                    f"{p['steps']:.0e}",
                    *(f"{r['mean']:+.1e} ± {r['standard_error']:.1e}" for r in drifts),
                    f"{p['correlation']:.2f}",
                    f"{p['shared']:.1e}",
                    f"{p['noise']:.1e}",
                ]
            )
        pair_headers = ["computed in long double", "h", "trajectories", "steps", "energy drift a step, set 0", "one ulp off"]
        text += "\n\n" + _table([*pair_headers, "correlation", "shared spread", "noise"], pair_rows)
    if data.get("start_runs"):
        check = data["library_check_steps"]
        by_start = check["by_start"]
        intro = (
            f"Every step started from the previous step's stages, the field as the library computes it. From the library's "
            f"states ({check['batch']} trajectories, {check['steps']} steps), the float64 step here gives other momenta than "
            f"the library's in {by_start['K₁']['fraction_differing']:.1%} of their entries started from K₁, in "
            f"{by_start['either side']['fraction_differing']:.1%} started as the library starts (either side)"
        )
        without = by_start.get("either side, no fused multiply-adds")
        intro += (
            "."
            if without is None
            else f", and in {without['fraction_differing']:.2%} so with the library compiled without fused multiply-adds."
        )
        start_runs = [dict(r, variant=f"{r['variant']}, {r['start']} start") for r in data["start_runs"]]
        text += f"\n\n{intro}\n\n{_drift_table(start_runs)}"
    return text


def _drift_table(runs) -> str:
    """`drift_emulation_table`'s table of runs: per variant, each set's mean
    drift a step with its standard error, and the spread averaged over the
    sets."""
    seeds = sorted({r["seed"] for r in runs})
    by_key = {(r["variant"], r["seed"]): r for r in runs}
    rows = []
    for variant in dict.fromkeys(r["variant"] for r in runs):
        cells = [variant]
        for seed in seeds:
            r = by_key.get((variant, seed))
            cells.append("–" if r is None else f"{r['mean']:+.1e} ± {r['standard_error']:.1e}")
        spreads = [by_key[(variant, seed)]["spread"] for seed in seeds if (variant, seed) in by_key]
        cells.append(f"{sum(spreads) / len(spreads):.1e}")
        rows.append(cells)
    headers = ["computed in long double", *(f"energy drift a step, set {seed}" for seed in seeds), "spread"]
    return _table(headers, rows)


def work_precision_table(_entries=None, root: Path | None = None) -> str:
    """`work_precision.py`: for each method, the fastest run that reached each
    target error, one trajectory and a batch; methods ordered by the first
    column."""
    data = results_file("work_precision.json", root)
    summary = data["summary"]
    keys = list(summary["fastest_at_target"])
    methods = sorted(
        {m for runs in summary["fastest_at_target"].values() for m in runs},
        key=lambda m: summary["fastest_at_target"][keys[0]].get(m, {}).get("wall_s", float("inf")),
    )
    rows = []
    for method in methods:
        cells = []
        for key in keys:
            run = summary["fastest_at_target"][key].get(method)
            cells.append("–" if run is None else f"{run['wall_s'] * 1e3:.2f} ({run['steps']})")
        rows.append([method, *cells])
    headers = ["method", *(f"{key.replace('single', 'one trajectory').replace('batch', 'batch of 1024')}: ms (steps)" for key in keys)]
    return _measured_on(summary) + "\n\n" + _table(headers, rows)


def long_time_table(_entries=None, root: Path | None = None) -> str:
    """`long_time.py`: the invariants' largest drifts over T = 1000 and the
    time each run took."""
    data = results_file("long_time.json", root)
    rows = [
        [
            r["method"],
            f"{r['kind']} = {r['parameter']:g}",
            f"{r['wall_s']:.3f}",
            _number(r["energy"], ".1e"),
            _number(r["momentum_norm"], ".1e"),
            _number(r["spatial_momentum"], ".1e"),
            _number(r["orthogonality"], ".1e"),
        ]
        for r in data["rows"]
    ]
    headers = ["method", "setting", "s", "energy", "\\|Π\\|", "QΠ", "QᵀQ − I"]
    return _measured_on(data) + f" T = {data['t_end']:g}.\n\n" + _table(headers, rows)


def heavy_top_table(_entries=None, root: Path | None = None) -> str:
    """`heavy_top.py`: the invariants over a long run, and the time each
    method takes to reach an error at T = 10."""
    data = results_file("heavy_top.json", root)
    rows = [
        [
            r["method"],
            f"{r['parameter']:g}",
            f"{r['wall_s']:.3f}",
            _number(r["energy"], ".1e"),
            _number(r["vertical_momentum"], ".1e"),
            _number(r["orthogonality"], ".1e"),
        ]
        for r in data["long_time"]
    ]
    long_time = _table(["method", "h or rtol", "s", "energy", "Γ·Π", "QᵀQ − I"], rows)
    targets = (1e-4, 1e-6, 1e-8)
    methods = dict.fromkeys(r["method"] for r in data["work_precision"])
    rows = []
    for method in methods:
        runs = [r for r in data["work_precision"] if r["method"] == method]
        cells = []
        for target in targets:
            reached = [r for r in runs if r["error"] <= target]
            best = min(reached, key=lambda r: r["wall_s"]) if reached else None
            cells.append("–" if best is None else f"{best['wall_s'] * 1e3:.2f} ({best['parameter']:g})")
        rows.append([method, *cells])
    work = _table(["method", *(f"ms to {t:.0e} (steps or rtol)" for t in targets)], rows)
    return _measured_on(data) + "\n\n" + long_time + "\n\n" + work


def throughput_table(_entries=None, root: Path | None = None) -> str:
    """`throughput.py`: trajectory-steps per second against the batch, compile
    time against the number of stages, and the cost of a gradient."""
    data = results_file("throughput.json", root)
    rows = [
        [
            str(r["batch"]),
            r["method"],
            f"{r['traj_steps_per_s']:.3g}",
            _number(r["iterations_per_step"], ".1f"),
            _number(r["over_tsit5"], ".2f"),
            f"{r['compile_s']:.2f}",
        ]
        for r in data["throughput"]
    ]
    rates = _table(["batch", "method", "trajectory-steps/s", "iterations a step", "time / Tsit5", "compile, s"], rows)
    rows = [[r["tableau"], str(r["stages"]), r["path"], f"{r['compile_s']:.2f}"] for r in data["compile_vs_stages"]]
    compile_times = _table(["tableau", "stages", "path", "compile, s"], rows)
    rows = [
        [
            r["path"],
            str(r["batch"]),
            str(r["steps"]),
            f"{r['forward_s'] * 1e3:.1f}",
            f"{r['forward_backward_s'] * 1e3:.1f}",
            f"{r['ratio']:.2f}",
            f"{r['forward_compile_s']:.2f}",
            f"{r['gradient_compile_s']:.2f}",
        ]
        for r in data["gradient"]
    ]
    headers = ["path", "batch", "steps", "forward, ms", "value and gradient, ms", "ratio", "compile forward, s", "compile gradient, s"]
    gradient = _table(headers, rows)
    return _measured_on(data) + "\n\n" + rates + "\n\n" + compile_times + "\n\n" + gradient


def stability_table(_entries=None, root: Path | None = None) -> str:
    """`stability.py`: the largest h·|Ω₀| each method stays stable to, and
    the first failure beyond it."""
    data = results_file("stability.json", root)
    rows = []
    for r in data["thresholds"]:
        bounded_throughout = _number(r["first_failure"], "g") == "–"
        threshold = f"≥ {r['threshold']:.3g} (the grid's top)" if bounded_throughout else f"{r['threshold']:.3g}"
        rows.append([r["scene"], r["method"], threshold, _number(r["first_failure"], ".3g"), r["reason"]])
    headers = ["scene", "method", "stable to h·\\|Ω₀\\|", "first failure", "why"]
    return _measured_on(data) + f" T = {data['t_end']:g}.\n\n" + _table(headers, rows)


def floor_table(_entries=None, root: Path | None = None) -> str:
    """`floor.py`: ns per trajectory-step of the hand-fused kernel (the
    floor), `integrate` and `diffeqsolve` vmapped and with the batch in the
    state, and Tsit5 on the embedding (Störmer–Verlet rows)."""
    data = results_file("floor.json", root)
    rows = []
    for r in data["rows"]:
        ns, over, it = r["ns_per_traj_step"], r["over_floor"], r["iterations_per_step"]
        rows.append(
            [
                r["method"],
                r["dtype"],
                str(r["batch"]),
                f"{ns['floor']:.0f}",
                f"{ns['integrate']:.0f} ({over['integrate']:.2f})",
                f"{ns['diffeqsolve']:.0f} ({over['diffeqsolve']:.2f})",
                "–" if "integrate_state" not in ns else f"{ns['integrate_state']:.0f} ({over['integrate_state']:.2f})",
                "–" if "diffeqsolve_state" not in ns else f"{ns['diffeqsolve_state']:.0f} ({over['diffeqsolve_state']:.2f})",
                "–" if "tsit5" not in ns else f"{ns['tsit5']:.0f} ({over['tsit5']:.2f})",
                f"{it['floor']:.1f} / {it['integrate']:.1f}",
            ]
        )
    headers = ["method", "dtype", "batch", "floor, ns", "integrate, ns (/ floor)", "diffeqsolve", "integrate, batch in the state"]
    headers += ["diffeqsolve, batch in the state", "Tsit5", "iterations a step, floor / integrate"]
    return _measured_on(data) + "\n\n" + _table(headers, rows)


def against_scan_table(_entries=None, root: Path | None = None) -> str:
    """`against_scan.py`: ns per step of `diffeqsolve`, `lax.scan` and a bare
    `while_loop` over the same step."""
    data = results_file("against_scan.json", root)
    rows = [
        [
            str(r["batch"]),
            f"{r['scan_ns_per_step']:.0f}",
            f"{r['diffrax_ns_per_step']:.0f}",
            f"{r['while_ns_per_step']:.0f}",
            f"{r['diffrax_over_scan']:.2f}",
            f"{r['while_over_scan']:.2f}",
            f"{r['scan_compile_s']:.2f}",
            f"{r['diffrax_compile_s']:.2f}",
        ]
        for r in data["rows"]
    ]
    headers = ["batch", "scan, ns", "diffeqsolve, ns", "while_loop, ns", "diffeqsolve / scan", "while / scan", "compile scan, s"]
    headers += ["compile diffeqsolve, s"]
    return _measured_on(data) + "\n\n" + _table(headers, rows)


def explicit_stages_table(_entries=None, root: Path | None = None) -> str:
    """`explicit_stages.py`: the stage plan read from the field against the
    tableau's own, per step."""
    data = results_file("explicit_stages.json", root)
    rows = []
    for r in data["rows"]:
        ns, it = r["ns_per_traj_step"], r["iterations_per_step"]
        rows.append(
            [
                r["scene"],
                r["tableau"],
                r["dtype"],
                str(r["batch"]),
                f"`{r['plan']}`",
                f"{ns['traced']:.0f}",
                f"{ns['tableau']:.0f}",
                f"{r['traced_over_tableau']:.2f}",
                f"{it['traced']:.1f}",
                f"{it['tableau']:.1f}",
            ]
        )
    headers = ["scene", "tableau", "dtype", "batch", "plan", "traced, ns", "tableau, ns", "traced / tableau", "iterations traced"]
    headers += ["iterations tableau"]
    return _measured_on(data) + f" h = {data['h']:g}.\n\n" + _table(headers, rows)


def root_finders_table(_entries=None, root: Path | None = None) -> str:
    """`root_finders.py`: fixed-point iteration against Newton's method on the
    implicit stages."""
    data = results_file("root_finders.json", root)
    rows = []
    for r in data["rows"]:
        ns, it = r["ns_per_traj_step"], r["iterations_per_step"]
        rows.append(
            [
                r["tableau"],
                str(r["batch"]),
                f"{ns['fixed_point']:.0f}",
                f"{ns['newton']:.0f}",
                f"{r['newton_over_fixed_point']:.2f}",
                f"{it['fixed_point']:.1f}",
                f"{it['newton']:.1f}",
            ]
        )
    headers = ["tableau", "batch", "fixed point, ns", "Newton, ns", "Newton / fixed point", "iterations fixed point", "iterations Newton"]
    return _measured_on(data) + "\n\n" + _table(headers, rows)


def gradients_table(_entries=None, root: Path | None = None) -> str:
    """`gradients.py`: the gradient's temporary memory, the process's peak
    memory, its time over the forward run's, and its compile time, against
    the number of steps."""
    data = results_file("gradients.json", root)
    rows = [
        [
            r["path"],
            str(r["batch"]),
            f"{r['steps']:.0e}".replace("e+0", "e"),
            "–" if r["temp_bytes"] is None else f"{r['temp_bytes'] / 1e6:.2f}",
            f"{r['peak_rss_mb']['compiled']:.0f}",
            f"{r['peak_rss_mb']['forward']:.0f}",
            f"{r['peak_rss_mb']['value_and_grad']:.0f}",
            f"{r['ns_per_traj_step']['forward']:.0f}",
            f"{r['ns_per_traj_step']['value_and_grad']:.0f}",
            f"{r['gradient_over_forward']:.2f}",
            f"{r['compile_s']['value_and_grad']:.1f}",
            str(r["rounds"]),
        ]
        for r in data["rows"]
    ]
    headers = [
        "path",
        "batch",
        "steps",
        "temporary memory, MB",
        "peak RSS compiled, MB",
        "peak RSS forward, MB",
        "peak RSS with gradient, MB",
        "forward, ns",
        "value and gradient, ns",
        "gradient / forward",
        "compile, s",
        "rounds",
    ]
    return _measured_on(data) + f" h = {data['h']}; ns per trajectory-step.\n\n" + _table(headers, rows)


def ensembles_table(_entries=None, root: Path | None = None) -> str:
    """`ensembles.py`: ensemble throughput, efficiency per device and memory
    per process against the number of processes and devices per process."""
    data = results_file("ensembles.json", root)
    rows = [
        [
            str(r["processes"]),
            str(r["devices_per_process"]),
            f"{r['median_s']['forward']:.3f}",
            f"{r['median_s']['value_and_grad']:.3f}",
            f"{r['throughput']['forward'] / 1e6:.2f}",
            f"{r['throughput']['value_and_grad'] / 1e6:.2f}",
            f"{r['efficiency_per_device']['forward']:.2f}",
            f"{r['efficiency_per_device']['value_and_grad']:.2f}",
            f"{r['compile_s']['forward']:.1f} / {r['compile_s']['value_and_grad']:.1f}",
            " / ".join(f"{m:.0f}" for m in r["peak_rss_mb"]),
        ]
        for r in data["rows"]
    ]
    headers = [
        "processes",
        "devices each",
        "forward, s",
        "value and gradient, s",
        "forward, 10⁶ trajectory-steps/s",
        "gradient, 10⁶ trajectory-steps/s",
        "efficiency per device, forward",
        "efficiency per device, gradient",
        "compile forward / gradient, s",
        "peak RSS per process, MB",
    ]
    compared = [r for r in data["rows"] if "jit_vmap_over_vmap_over_devices" in r]
    routes = "".join(
        f" With {r['devices']} devices in one process, `jit(vmap(...))` of the sharded batch took "
        f"{r['jit_vmap_over_vmap_over_devices']:.1f}× the time of `vmap_over_devices`."
        for r in compared
    )
    return (
        _measured_on(data)
        + f" Batch {data['batch']} × {data['steps']} steps, h = {data['h']}, median of {data['rounds']} rounds."
        + routes
        + "\n\n"
        + _table(headers, rows)
    )


def xla_codegen_table(_entries=None, root: Path | None = None) -> str:
    """`xla_codegen.py`: compile and run time with XLA's older CPU code
    generator over its default."""
    data = results_file("xla_codegen.json", root)
    rows = [
        [
            r["name"],
            str(r["batch"]),
            r["dtype"],
            f"{r['compile_s']['default']:.2f}",
            f"{r['compile_s_ratio']:.2f}",
            f"{r['run_s']['default'] * 1e3:.2f}",
            f"{r['run_s_ratio']:.2f}",
            f"{r['relative_gap']:.0e}",
        ]
        for r in data["rows"]
    ]
    headers = ["program", "batch", "dtype", "compile default, s", "compile ratio", "run default, ms", "run ratio", "largest relative gap"]
    return _measured_on(data) + f" Ratios: `{data['flag']}` over XLA's default.\n\n" + _table(headers, rows)


OTHER_SOURCES = (
    "stage_layout.json",
    "against_revision.json",
    "against_revision_gradients.json",
    "gradients.json",
    "ensembles.json",
    "round_off.json",
    "energy_drift.json",
    "drift_emulation.json",
    "work_precision.json",
    "long_time.json",
    "heavy_top.json",
    "throughput.json",
    "stability.json",
    "floor.json",
    "against_scan.json",
    "explicit_stages.json",
    "root_finders.json",
    "xla_codegen.json",
)
"""The results files of the tables that read their own file."""
ENTRY_TABLES = ("accuracy", "decision", "summary")
"""The tables made from `splitting.py`'s results; the others read their own file."""
TABLES = {
    "accuracy": accuracy_table,
    "decision": decision_table,
    "summary": summary_table,
    "stage_layout": stage_layout_table,
    "round_off": round_off_table,
    "round_off_cost": round_off_cost_table,
    "energy_drift": energy_drift_table,
    "drift_emulation": drift_emulation_table,
    "work_precision": work_precision_table,
    "long_time": long_time_table,
    "heavy_top": heavy_top_table,
    "throughput": throughput_table,
    "stability": stability_table,
    "floor": floor_table,
    "against_scan": against_scan_table,
    "explicit_stages": explicit_stages_table,
    "root_finders": root_finders_table,
    "against_revision": against_revision_table,
    "against_revision_gradients": against_revision_gradients_table,
    "gradients": gradients_table,
    "ensembles": ensembles_table,
    "xla_codegen": xla_codegen_table,
}


def rewritten(text: str, name: str, table: str) -> str:
    # `??`: an empty block matches as empty, not as everything up to a later block's end.
    pattern = re.compile(rf"(<!-- write_tables\.py: {name} -->\n)(?:.*?\n)??(<!-- /write_tables\.py -->)", re.S)
    if not pattern.search(text):
        raise ValueError(f"no block '<!-- write_tables.py: {name} -->' … '<!-- /write_tables.py -->' to write the {name} table into")
    return pattern.sub(lambda m: m.group(1) + table + "\n" + m.group(2), text)


NOTEBOOK = "notebooks/05_choosing_a_method.ipynb"
"""Its cell that shows `decision_table` holds the table as its output."""


def notebook_with_table(path: Path, table: str) -> tuple[str, str]:
    """(the notebook's text, the text with the output of its decision-table
    cell set to `table`), both as nbformat writes them."""
    import nbformat

    text = path.read_text()
    nb = nbformat.reads(text, as_version=4)
    cells = [c for c in nb.cells if c.cell_type == "code" and "write_tables.decision_table" in c.source]
    if len(cells) != 1:
        raise ValueError(f"{path.name}: expected one code cell showing write_tables.decision_table, found {len(cells)}")
    cells[0].outputs = [
        nbformat.v4.new_output(
            "display_data", data={"text/markdown": table, "text/plain": "<IPython.core.display.Markdown object>"}, metadata={}
        )
    ]
    return nbformat.writes(nbformat.reads(text, as_version=4)) + "\n", nbformat.writes(nb) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 where a document differs from the results")
    args = parser.parse_args(argv)
    entries = load()
    stale = []
    for document, names in DOCUMENTS.items():
        path = ROOT / document
        text = path.read_text()
        new = text
        for name in names:
            new = rewritten(new, name, TABLES[name](entries) if name in ENTRY_TABLES else TABLES[name](root=ROOT))
        if new != text:
            stale.append(document)
            if not args.check:
                path.write_text(new)
    for name in SOURCES:  # each results file's own table beside it
        source = ROOT / "benchmarks" / "results" / name
        if source.exists():
            path = source.with_suffix(".md")
            table = accuracy_table(entries_of(json.loads(source.read_text()), source.stem)) + "\n"
            if not path.exists() or path.read_text() != table:
                stale.append(str(path.relative_to(ROOT)))
                if not args.check:
                    path.write_text(table)
    before, after = notebook_with_table(ROOT / NOTEBOOK, decision_table(entries))
    if before != after:
        stale.append(NOTEBOOK)
        if not args.check:
            (ROOT / NOTEBOOK).write_text(after)
    if args.check and stale:
        print("generated tables out of date in: " + ", ".join(stale) + " (run python benchmarks/write_tables.py)")
        return 1
    print(("checked: " if args.check else "written: ") + ", ".join([*DOCUMENTS, NOTEBOOK]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
