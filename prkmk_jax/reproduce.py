"""Reproduce the paper's §5: `python -m prkmk_jax.reproduce --out DIR`.

Writes `fig5_1.png … fig5_4.png` (exp coordinates left, Cayley right; rows:
energy error, body-momentum norm, spatial momentum), `results.json` (one
record per run), `trajectories.npz` (`<run>/Q`, `<run>/P` or `<run>/g`,
`<run>/Pi`, `<run>/t`, `<run>/inertia`) and prints a summary table.
"""

import argparse
import concurrent.futures
import dataclasses
import functools
import json
import multiprocessing
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from . import diagnostics
from ._bundles import AbstractBundle, Cartesian, Cotangent, DirectProduct
from ._integrate import integrate
from .coordinates import Cayley, Exp
from .groups import SO3, SOn
from .methods import PRKMK, RESULTS
from .scenes import AbstractScene
from .scenes import rigid_body as rb
from .tableaus import PartitionedTableau, stormer_verlet, symplectic_euler

COORDINATES = {"exp": Exp(), "cayley": Cayley()}
SO4_MASSES = np.array([0.9, 0.7, 0.5, 0.3])
"""J of the n = 4 scene: M = JΩ + ΩJ."""


@dataclasses.dataclass(frozen=True)
class Run:
    name: str
    scene: AbstractScene
    """The symmetric body (§5.1) or the unreduced body (§5.2), on its bundle."""
    coordinates: str
    tableau: PartitionedTableau
    h: float
    t_end: float
    figure: str | None = None
    n: int = 3
    save_every: int = 1

    @property
    def num_steps(self) -> int:
        return int(round(self.t_end / self.h))

    @property
    def bundle(self) -> AbstractBundle:
        return self.scene.bundle

    @property
    def is_symmetric_body(self) -> bool:
        return isinstance(self.scene, rb.SymmetricRigidBody)

    @property
    def scene_label(self) -> str:
        """ "symmetric" or "unreduced", as `results.json` names the scenes."""
        return "symmetric" if self.is_symmetric_body else "unreduced"


def paper_runs(time_scale: float = 1.0) -> list[Run]:
    """The runs of §5 (figures 5.1–5.4) and the companion runs; `time_scale`
    shortens every T (for smoke tests)."""
    symmetric, symmetric_so4 = rb.SymmetricRigidBody(Cartesian(SO3)), rb.SymmetricRigidBody(Cartesian(SOn))
    unreduced, unreduced_direct = rb.FreeRigidBody(Cotangent(SO3)), rb.FreeRigidBody(DirectProduct(SO3))
    runs = []
    for coords in COORDINATES:
        runs += [
            Run(f"sym_SE_{coords}", symmetric, coords, symplectic_euler, 0.1, 50 * time_scale, "fig5_1"),
            Run(f"sym_SV_{coords}", symmetric, coords, stormer_verlet, 0.1, 100 * time_scale, "fig5_2"),
            Run(f"unreduced_SE_{coords}", unreduced, coords, symplectic_euler, 0.01, 50 * time_scale, "fig5_3"),
            Run(f"unreduced_SV_{coords}", unreduced, coords, stormer_verlet, 0.01, 50 * time_scale, "fig5_4"),
            Run(f"unreduced_direct_SE_{coords}", unreduced_direct, coords, symplectic_euler, 0.01, 50 * time_scale),
            Run(f"unreduced_direct_SV_{coords}", unreduced_direct, coords, stormer_verlet, 0.01, 50 * time_scale),
        ]
    runs += [
        Run("sym_SE_exp_T1000", symmetric, "exp", symplectic_euler, 0.1, 1000 * time_scale, save_every=10),
        Run("sym_so4_SE_exp", symmetric_so4, "exp", symplectic_euler, 0.1, 50 * time_scale, n=4),
        Run("sym_so4_SV_exp", symmetric_so4, "exp", stormer_verlet, 0.1, 100 * time_scale, n=4),
    ]
    return runs


def initial_data(run: Run, seed: int):
    """(y0, inertia) of a run; attitudes are `rb.random_rotation(seed, n)`."""
    q0 = rb.random_rotation(seed, run.n)
    if run.n == 3:
        inertia = jnp.asarray(rb.PAPER_INERTIA)
        if run.is_symmetric_body:
            return rb.symmetric_initial_state(q0, rb.PAPER_MOMENTUM), inertia
        return rb.from_attitude_and_momentum(run.bundle, jnp.asarray(q0), jnp.asarray(rb.PAPER_MOMENTUM)), inertia
    a = np.random.default_rng(seed + 1).normal(size=(run.n, run.n))
    m0 = 0.4 * (a - a.T)
    return rb.symmetric_initial_state(q0, m0), jnp.asarray(SO4_MASSES)


def _step_map(method, field, bundle, h, inertia):
    """One step as a map (g, Π) ↦ (g', Π') on T*SO(3)."""

    def step(g, pi):
        y = rb.from_attitude_and_momentum(bundle, g, pi)
        y1 = method.step(field, 0.0, y, h, inertia).y
        return rb.attitude_and_momentum(bundle, y1)

    return step


def method_of(run: Run) -> PRKMK:
    """The symmetric body on SO(3)² at h = 0.1 has h·Lip ≈ 0.8: fixed-point
    iteration needs about 94 iterations a step there, Newton 4. The other
    runs converge in ≤ 24 fixed-point iterations, cheaper than Newton's
    dense Jacobians (on SO(4)² Newton is the slower of the two)."""
    root_finder = optx.Newton(rtol=1e-12, atol=1e-12) if (run.is_symmetric_body and run.n == 3) else None
    return run.scene.method(run.tableau, COORDINATES[run.coordinates], root_finder=root_finder)


DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "prkmk_jax" / "xla"
"""Where compiled programs are kept between invocations (JAX's persistent
compilation cache). JAX keeps only programs without host callbacks: the
step-map Jacobians of the symplecticity check and the diagnostics' small
programs. The integrations are compiled again by every new process: their
run-time checks (`eqx.error_if`) are host callbacks. Within a process,
`execute` compiles each run's integration once (`_simulator`)."""


def use_compilation_cache(cache_dir: Path | None) -> None:
    """Keep the compiled programs JAX can store (see `DEFAULT_CACHE`) in `cache_dir` (None: no cache)."""
    if cache_dir is None:
        return
    jax.config.update("jax_compilation_cache_dir", str(cache_dir))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


@functools.partial(jax.jit, static_argnums=0)
def _trajectory_diagnostics(scene: AbstractScene, ys, inertia) -> tuple[dict, dict]:
    """The scene's invariants along a saved trajectory and their worst
    drifts, as one compiled program per trajectory length and scene.
    Computed op by op, each operation is a program of its own, ~20 compiled
    for every new trajectory length."""
    invariants = scene.invariants(ys, inertia)
    curves = {
        "energy": invariants["energy"],
        "body_momentum_norm": invariants["momentum norm"],
        "spatial_momentum": invariants["spatial momentum"],
    }
    drifts = {
        "max_body_momentum_norm_drift": diagnostics.max_drift(curves["body_momentum_norm"], relative=True),
        "max_spatial_momentum_drift": diagnostics.max_drift(curves["spatial_momentum"], relative=True),
        "max_orthogonality_defect": jnp.max(invariants["orthogonality"]),
    }
    return curves, drifts


@functools.cache
def _simulator(run: Run):
    """(method, scene, jitted integration) of a run, one per run for the
    process: executing an equal run again (another seed, or the module's
    tests before the command) reuses its compiled program. JAX's persistent
    cache cannot keep it (`DEFAULT_CACHE`)."""
    method, field = method_of(run), run.scene
    simulate = jax.jit(lambda y0, inertia: integrate(method, field, y0, 0.0, run.h, run.num_steps, inertia, save_every=run.save_every))
    return method, field, simulate


def _step_of(run: Run) -> Run:
    """The run with what its step does not depend on (its name, length and
    saving) set to one value: runs of the same step share its programs."""
    return dataclasses.replace(run, name="", t_end=run.h, figure=None, save_every=1)


@functools.cache
def _symplecticity_defect(step_run: Run):
    """The symplecticity defect of a run's step at (y0, inertia), compiled
    once for each step (`_step_of`): the step-map Jacobian is the costliest
    program of a run to compile."""
    method, bundle = method_of(step_run), step_run.bundle

    @jax.jit
    def defect(y0, inertia):
        step = _step_map(method, step_run.scene, bundle, step_run.h, inertia)
        return diagnostics.symplecticity_defect(step, *rb.attitude_and_momentum(bundle, y0))

    return defect


def execute(run: Run, seed: int, symplecticity: bool = True, cache_dir: Path | None = None) -> tuple[dict, dict]:
    """Integrate one run; returns (its results record, its arrays).
    `symplecticity=False` skips the (compile-heavy) step-map Jacobian."""
    jax.config.update("jax_enable_x64", True)
    use_compilation_cache(cache_dir)
    method, field, simulate = _simulator(run)
    y0, inertia = initial_data(run, seed)
    start = time.perf_counter()
    compiled = simulate.lower(y0, inertia).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    traj = jax.block_until_ready(compiled(y0, inertia))
    run_s = time.perf_counter() - start

    curves, drifts = _trajectory_diagnostics(field, traj.ys, inertia)
    defect = None
    if run.n == 3 and symplecticity:
        defect = float(_symplecticity_defect(_step_of(run))(y0, inertia))

    h_t = np.asarray(curves["energy"])
    energy_error = h_t - h_t[0]
    quarter = max(len(energy_error) // 4, 1)
    record = {
        "run": run.name,
        "scene": run.scene_label,
        "representation": f"{type(run.bundle).__name__}({run.bundle.base.__name__})",
        "n": run.n,
        "coordinates": run.coordinates,
        "tableau": run.tableau.name,
        "h": run.h,
        "T": run.num_steps * run.h,
        "num_steps": run.num_steps,
        "figure": run.figure,
        "max_abs_energy_error": float(np.abs(energy_error).max()),
        "energy_error_first_quarter": float(np.abs(energy_error[:quarter]).max()),
        "energy_error_last_quarter": float(np.abs(energy_error[-quarter:]).max()),
        "final_energy_error": float(energy_error[-1]),
        **{k: float(v) for k, v in drifts.items()},
        "symplecticity_defect": defect,
        "implicit_iterations_total": int(traj.stats["num_iterations"]),
        "implicit_iterations_max_per_step": int(traj.stats["max_iterations_per_step"]),
        "compile_time_s": compile_s,
        "wall_time_s": run_s,
        "result": "successful" if traj.result == RESULTS.successful else str(traj.result),
    }
    arrays = {"t": np.asarray(traj.ts), "inertia": np.asarray(inertia)}
    if isinstance(run.bundle, Cartesian):
        arrays.update(Q=np.asarray(traj.ys.base.matrix), P=np.asarray(traj.ys.fiber.matrix))
    else:
        arrays.update(g=np.asarray(traj.ys.base.matrix), Pi=np.asarray(traj.ys.fiber))
    arrays.update({k: np.asarray(v) for k, v in curves.items()})
    return record, arrays


FIGURE_TITLES = {
    "fig5_1": "Fig. 5.1 — symmetric rigid body, symplectic Euler, h = 0.1",
    "fig5_2": "Fig. 5.2 — symmetric rigid body, Störmer–Verlet, h = 0.1",
    "fig5_3": "Fig. 5.3 — unreduced rigid body on T*SO(3), symplectic Euler, h = 0.01",
    "fig5_4": "Fig. 5.4 — unreduced rigid body on T*SO(3), Störmer–Verlet, h = 0.01",
}


def draw_figure(path: Path, title: str, columns: dict[str, dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 2, figsize=(11, 8.5), sharex=True, constrained_layout=True)
    for col, (label, arrays) in enumerate(columns.items()):
        t = arrays["t"]
        ax = axes[0, col]
        ax.plot(t, arrays["energy"] - arrays["energy"][0], lw=0.8)
        ax.set_title(f"{label} coordinates")
        ax.set_ylabel("H(t) − H(0)")
        ax = axes[1, col]
        ax.plot(t, arrays["body_momentum_norm"] - arrays["body_momentum_norm"][0], lw=0.8)
        ax.set_ylabel("|Π(t)| − |Π(0)|")
        ax = axes[2, col]
        m = arrays["spatial_momentum"]
        for i in range(3):
            ax.plot(t, m[:, i] - m[0, i], lw=0.8, label=f"m{i + 1}")
        ax.set_ylabel("m(t) − m(0), m = gΠ")
        ax.set_xlabel("t")
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Reproduce the numerical experiments of Engø (2003), §5.")
    parser.add_argument("--out", type=Path, default=Path("figures"), help="output directory")
    parser.add_argument("--seed", type=int, default=rb.PAPER_SEED, help="seed of the random initial attitudes")
    parser.add_argument("--time-scale", type=float, default=1.0, help="multiply every T (e.g. 0.05 for a smoke test)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes (default: up to 2)")
    parser.add_argument(
        "--cache-dir", type=Path, default=DEFAULT_CACHE, help=f"compiled programs kept between invocations (default: {DEFAULT_CACHE})"
    )
    parser.add_argument("--no-cache", action="store_true", help="compile everything afresh, keep nothing")
    args = parser.parse_args(argv)
    cache_dir = None if args.no_cache else args.cache_dir
    jax.config.update("jax_enable_x64", True)
    use_compilation_cache(cache_dir)
    args.out.mkdir(parents=True, exist_ok=True)

    runs = paper_runs(args.time_scale)

    # The step map, hence its symplecticity defect, depends on (bundle,
    # coordinates, tableau, h, initial data) only: compute it once per key.
    def key(r):
        return (r.scene, r.coordinates, r.tableau.name, r.h, r.n)

    first_of_key = {}
    for r in runs:
        first_of_key.setdefault(key(r), r.name)
    jobs = [(r, args.seed, first_of_key[key(r)] == r.name, cache_dir) for r in runs]
    print(
        f"{len(runs)} runs on {args.jobs} worker process(es); compiled programs "
        + (f"cached in {cache_dir}" if cache_dir else "not cached")
        + ". Each line is a finished run:",
        flush=True,
    )
    start = time.perf_counter()
    outputs: list = [None] * len(jobs)

    def report(index, output):
        outputs[index] = output
        record = output[0]
        done = sum(o is not None for o in outputs)
        print(
            f"  [{done:2d}/{len(jobs)}] {record['run']:28s} compile {record['compile_time_s']:5.1f} s, "
            f"run {record['wall_time_s']:5.1f} s   ({time.perf_counter() - start:5.1f} s elapsed)",
            flush=True,
        )

    if args.jobs > 1:
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
            futures = {pool.submit(execute, *job): i for i, job in enumerate(jobs)}
            for future in concurrent.futures.as_completed(futures):
                report(futures[future], future.result())
    else:
        for i, job in enumerate(jobs):
            report(i, execute(*job))
    records = [o[0] for o in outputs]
    arrays = {r.name: o[1] for r, o in zip(runs, outputs)}
    by_name = {rec["run"]: rec for rec in records}
    for r, rec in zip(runs, records):
        if rec["symplecticity_defect"] is None and r.n == 3:
            rec["symplecticity_defect"] = by_name[first_of_key[key(r)]]["symplecticity_defect"]
    for fig, title in FIGURE_TITLES.items():
        columns = {r.coordinates: arrays[r.name] for r in paper_runs(args.time_scale) if r.figure == fig}
        draw_figure(args.out / f"{fig}.png", title, columns)

    total_s = time.perf_counter() - start
    meta = {
        "seed": args.seed,
        "time_scale": args.time_scale,
        "jax": jax.__version__,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "jobs": args.jobs,
        "total_time_s": total_s,
        "runs": records,
    }
    (args.out / "results.json").write_text(json.dumps(meta, indent=2))
    np.savez_compressed(
        args.out / "trajectories.npz", **{f"{run}/{k}": v for run, d in arrays.items() for k, v in d.items()}, seed=args.seed
    )
    _print_table(records)
    print(f"{len(records)} runs in {total_s:.1f} s ({args.jobs} worker processes); files in {args.out}/")


def _print_table(records):
    header = (
        f"{'run':28s} {'T':>6s} {'max|ΔH|':>9s} {'|Π| drift':>9s} {'m drift':>9s} {'orth':>9s} {'sympl':>9s} {'iters':>7s} {'run s':>6s}"
    )
    print(header)
    print("-" * len(header))
    for r in records:
        sym = "—" if r["symplecticity_defect"] is None else f"{r['symplecticity_defect']:.1e}"
        print(
            f"{r['run']:28s} {r['T']:6.0f} {r['max_abs_energy_error']:9.1e} {r['max_body_momentum_norm_drift']:9.1e} "
            f"{r['max_spatial_momentum_drift']:9.1e} {r['max_orthogonality_defect']:9.1e} {sym:>9s} "
            f"{r['implicit_iterations_total']:7d} {r['wall_time_s']:6.2f}"
        )


if __name__ == "__main__":
    main()
