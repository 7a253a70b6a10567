"""Gradient memory and time against the number of steps, up to a fit's
gradient over more steps than stored steps could hold.

`jax.value_and_grad` with respect to the inertia of a weighted sum of the
final momenta and attitudes of the free body on T*SO(3) (body form,
h = 0.01, a vmapped batch of random attitudes), along each of `PATHS`:
`integrate` through the stored steps and with
`ReversibleGradient(checkpoint_every=None)`, for Störmer–Verlet and the
Strang splitting (the latter also for Kahan–Li 6), `diffeqsolve` of SV
with diffrax's `RecursiveCheckpointAdjoint` and with `ReversibleAdjoint`,
and the splitting's with `ReversibleAdjoint`; at batch 64 over 10³ … 10⁶
steps (Kahan–Li 6 to 10⁵) and at batch 1024 over 10³, then the fit's scale (`FIT`:
1024 trajectories in the state over 10⁶ steps). Each case runs in a
process of its own and reports XLA's temporary memory of the gradient, the
process's peak resident memory after compiling, after the forward run and
after the gradient, the compile times, and the forward and gradient times
interleaved over the rounds. `benchmarks/README.md` says more.

    python benchmarks/gradients.py
    python benchmarks/gradients.py --quick   # tiny sizes, three of the cases, one process after the first
"""

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp

import _common as C
import prkmk_jax as pk

H = 0.01
PATHS = (
    "integrate, stored steps",
    "integrate, ReversibleGradient",
    "splitting, stored steps",
    "splitting, ReversibleGradient",
    "Kahan–Li 6 splitting, ReversibleGradient",
    "diffeqsolve, RecursiveCheckpointAdjoint",
    "diffeqsolve, ReversibleAdjoint",
    "diffeqsolve, splitting, ReversibleAdjoint",
)
FIT = "fit scale: splitting, ReversibleGradient, batch in the state"


def _final_state(path, steps):
    scene = C.SCENE
    method = scene.splitting(pk.kahan_li_6 if "Kahan–Li" in path else None) if "splitting" in path else scene.method(pk.stormer_verlet)
    if path.startswith("diffeqsolve"):

        def through_diffeqsolve(q0, pi0, inertia):
            y0 = pk.BundleElement(pk.SO3(q0), pi0)
            term, solver = pk.PRKMKTerm(scene), pk.PRKMKSolver(method)
            adjoint = pk.ReversibleAdjoint(None) if path.endswith("ReversibleAdjoint") else diffrax.RecursiveCheckpointAdjoint()
            sol = diffrax.diffeqsolve(term, solver, 0.0, steps * H, H, y0, inertia, max_steps=steps, adjoint=adjoint)
            return sol.ys.base.matrix[-1], sol.ys.fiber[-1]

        return through_diffeqsolve
    gradient = pk.ReversibleGradient(checkpoint_every=None) if path.endswith("ReversibleGradient") else pk.StoredSteps()

    def through_integrate(q0, pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(q0), pi0)
        y = pk.integrate(method, scene, y0, 0.0, H, steps, inertia, save_every=steps, gradient=gradient).ys
        return y.base.matrix[-1], y.fiber[-1]

    return through_integrate


def _weighted(q, pi):
    return jnp.sum(q[..., 0, :] * jnp.arange(1.0, 4.0)) + jnp.sum(pi**2 * jnp.arange(1.0, 4.0))


def _loss(path, steps):
    if path == FIT:
        method, gradient = C.SCENE.splitting(), pk.ReversibleGradient()

        def loss_of_batch_in_state(qs, pis, inertia):
            y0 = pk.BundleElement(pk.SO3(qs), pis)
            y = pk.integrate(method, C.SCENE, y0, 0.0, H, steps, inertia, save_every=steps, gradient=gradient).ys
            return _weighted(y.base.matrix[-1], y.fiber[-1])

        return loss_of_batch_in_state
    final_state = _final_state(path, steps)

    def loss(qs, pis, inertia):
        return _weighted(*jax.vmap(final_state, in_axes=(0, 0, None))(qs, pis, inertia))

    return loss


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3  # kilobytes on Linux


def measure(path, batch, steps, rounds):
    """One case, in this process (the child's job)."""
    qs, pis = C.initial_conditions(batch, seed=4)
    args = (jnp.asarray(qs), jnp.asarray(pis), jnp.asarray(C.INERTIA))
    loss = _loss(path, steps)
    fns = {"forward": loss, "value_and_grad": jax.value_and_grad(loss, argnums=2)}
    compiled, compile_s, first, rss = {}, {}, {}, {}
    for name, fn in fns.items():
        compiled[name], compile_s[name] = C.compile_fn(fn, *args)
    rss["compiled"] = _peak_rss_mb()
    for name, fn in compiled.items():
        first[name] = [C.call_seconds(fn, *args)]
        rss[name] = _peak_rss_mb()
    memory = compiled["value_and_grad"].memory_analysis()
    times = C.interleaved_times(compiled, *args, rounds=rounds) if rounds else first
    return dict(
        path=path,
        batch=batch,
        steps=steps,
        rounds=max(rounds, 1),
        temp_bytes=int(memory.temp_size_in_bytes) if memory is not None else None,
        peak_rss_mb=rss,
        compile_s=compile_s,
        ns_per_traj_step=C.ns_per_trajectory_step(times, batch, steps),
        gradient_over_forward=C.median_ratio(times, "value_and_grad", "forward"),
    )


def _in_child(path, batch, steps, rounds):
    """`measure` in a fresh process: its peak memory is this case's alone."""
    case = json.dumps(dict(path=path, batch=batch, steps=steps, rounds=rounds))
    done = subprocess.run([sys.executable, __file__, "--case", case], check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def gradients_table(results: Path) -> str:
    """`gradients.py`: the gradient's temporary memory, the process's peak
    memory, its time over the forward run's, and its compile time, against
    the number of steps."""
    data = C.results_file(results, "gradients.json")
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
    headers = ["path", "batch", "steps", "temporary memory, MB", "peak RSS compiled, MB", "peak RSS forward, MB"]
    headers += ["peak RSS with gradient, MB", "forward, ns", "value and gradient, ns", "gradient / forward", "compile, s", "rounds"]
    return C.measured_on(data) + f" h = {data['h']}; ns per trajectory-step.\n\n" + C.table(headers, rows)


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from its results in `results` (`write_tables.py`)."""
    return {"gradients": gradients_table(results)}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--case"]:
        jax.config.update("jax_enable_x64", True)
        print(json.dumps(measure(**json.loads(argv[1]))))
        return None  # a worker: its parent writes the results

    args, out = C.cli(__doc__, argv)
    if args.quick:
        grid, batch, fit, large = ((20, 2),), 4, (8, 20), None
    else:
        grid, batch, fit, large = ((1_000, 5), (10_000, 3), (100_000, 2), (1_000_000, 0)), 64, (1024, 1_000_000), (1024, 1_000, 3)
    rows = []
    print(f"{'path':62s} {'batch':>5s} {'steps':>8s} {'temp MB':>9s} {'RSS MB':>15s} {'grad/fwd':>8s} {'compile s':>9s}")
    cases = [(path, batch, steps, rounds) for steps, rounds in grid for path in PATHS]
    kept_at_most_steps = ("integrate", "splitting, ReversibleGradient", "diffeqsolve, RecursiveCheckpointAdjoint")
    cases = [c for c in cases if c[2] < 1_000_000 or c[0].startswith(kept_at_most_steps)]
    # The time criterion at a batch where the step's arithmetic, not the
    # number of kernels a step launches, sets the time (--quick: the same
    # code as the rows above).
    cases += [] if large is None else [(path, *large) for path in PATHS if path != "splitting, stored steps"]
    cases.append((FIT, fit[0], fit[1], 0))
    if args.quick:  # one integrate path, one diffeqsolve path and the fit: the script's code, each compiled once
        cases = [c for c in cases if c[0] in ("integrate, ReversibleGradient", "diffeqsolve, ReversibleAdjoint", FIT)]
    for case_number, (path, b, steps, rounds) in enumerate(cases):
        start = time.perf_counter()
        # --quick: the first case in a child as in a full run, the others in
        # this process (their RSS is then not theirs alone).
        row = measure(path, b, steps, rounds) if args.quick and case_number > 0 else _in_child(path, b, steps, rounds)
        rows.append(row)
        temp = "–" if row["temp_bytes"] is None else f"{row['temp_bytes'] / 1e6:.2f}"
        rss = "/".join(f"{row['peak_rss_mb'][k]:.0f}" for k in ("compiled", "forward", "value_and_grad"))
        print(
            f"{path:62s} {b:5d} {steps:8d} {temp:>9s} {rss:>15s} {row['gradient_over_forward']:8.2f} "
            f"{row['compile_s']['value_and_grad']:9.2f}   ({time.perf_counter() - start:.0f} s)",
            flush=True,
        )
    with open(out / "gradients.json", "w") as f:
        json.dump(dict(machine=C.machine(), batch=batch, h=H, rows=rows), f, indent=1)
    return out


if __name__ == "__main__":
    out = main()
    if out is not None:
        print("\n\n".join(tables(out).values()))
