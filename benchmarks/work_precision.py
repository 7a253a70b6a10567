"""Work–precision: error at T = 10 against wall time after compilation.

Free rigid body (paper inertia and momentum, random attitude). PRKMK methods
(symplectic Euler, Störmer–Verlet, Lobatto IIIA–IIIB 4; exp and Cayley
coordinates; Lobatto IIIA–IIIB 6 and the compositions of Störmer–Verlet of
order 4, 6 and 8) run on T*SO(3) in body form through `diffrax.diffeqsolve`
with fixed steps over a sweep of h, and Lobatto with step doubling under a
PIDController over a sweep of rtol. The peers run on the embedding ℝ⁹×ℝ³:
diffrax Tsit5, Dopri5 and Dopri8 (adaptive over rtol = atol, and fixed
step), SciPy solve_ivp DOP853 and RK45 (adaptive; single trajectory only,
SciPy has no batch mode).

Errors: the geodesic distance on SO(3) between Q(T) and the reference, and
|Π(T) − Π_ref(T)|; the reference is DOP853 at rtol = atol = 1e-13. In the
batch regime (1024 trajectories timed together) the error is the maximum
over the first 32 trajectories.

The implicit PRKMK runs stop their stages at the tolerance
(`iterate_until="tolerance"`, 1e-12, below every error measured here), as a
user sweeping accuracy over a short horizon would (`docs/concepts/choosing.md`);
the default goes on to round-off, which long runs need (`round_off.py`).

Writes work_precision_{single,batch}.png, work_precision.csv and
work_precision.json (with the target check) to --out.

This script compares the PRKMK variants with each other (tableaus,
coordinates, compositions, step-size control). Accuracy per second of every
family side by side — the exact-flow splittings, PRKMK (Lobatto IIIA–IIIB 6,
RKMK 8), diffrax with constant steps and with a PID controller, and a
hand-written splitting kernel — on the free body and the heavy top, one
trajectory and batches, is `splitting.py`'s (its charts are
`results/splitting*.png`).

    python benchmarks/work_precision.py --out benchmarks/results
    python benchmarks/work_precision.py --quick
"""

import csv
import json
import time

import diffrax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk

T_END = 10.0
TARGETS = (1e-8, 1e-10)

STAGE_STOP = "tolerance"
"""Where the implicit PRKMK runs stop their stage iteration (module docstring)."""


def _methods(quick):
    prkmk = []
    for name, tableau in (
        ("SE", pk.symplectic_euler),
        ("SV", pk.stormer_verlet),
        ("Lobatto4", pk.lobatto_iiia_iiib4),
    ):
        for coords in ("exp", "cayley"):
            prkmk.append(
                (
                    f"PRKMK {name} {coords}",
                    "prkmk",
                    C.prkmk_final(C.prkmk_solver(tableau, coords, iterate_until=STAGE_STOP)),
                    False,
                )
            )
    # High order that keeps the structure: Lobatto IIIA–IIIB 6 and symmetric
    # compositions of Störmer–Verlet (symmetric on T*SO(3) with exp at its
    # default truncation; `symmetry_defect` in the tests).
    sv = C.prkmk_solver(pk.stormer_verlet, iterate_until=STAGE_STOP).method
    for name, method in (
        ("Lobatto6 exp", C.prkmk_solver(pk.lobatto_iiia_iiib6, iterate_until=STAGE_STOP).method),
        ("SV∘Suzuki5 exp", pk.Composition(sv, pk.suzuki_5, assume_symmetric_base=True)),
        ("SV∘KahanLi6 exp", pk.Composition(sv, pk.kahan_li_6, assume_symmetric_base=True)),
        ("SV∘McLachlan8 exp", pk.Composition(sv, pk.mclachlan_8, assume_symmetric_base=True)),
        ("SV∘KahanLi8 exp", pk.Composition(sv, pk.kahan_li_8, assume_symmetric_base=True)),
    ):
        prkmk.append((f"PRKMK {name}", "prkmk", C.prkmk_final(pk.PRKMKSolver(method)), False))
    prkmk.append(
        (
            "PRKMK Lobatto4 exp adaptive",
            "prkmk",
            C.prkmk_final(C.prkmk_solver(pk.lobatto_iiia_iiib4, adaptive=True, iterate_until=STAGE_STOP), adaptive=True),
            True,
        )
    )
    peers = []
    for name, solver in (
        ("Tsit5", diffrax.Tsit5()),
        ("Dopri5", diffrax.Dopri5()),
        ("Dopri8", diffrax.Dopri8()),
    ):
        peers.append((f"diffrax {name} adaptive", "diffrax", C.diffrax_final(solver, True), True))
        peers.append((f"diffrax {name} fixed", "diffrax", C.diffrax_final(solver, False), False))
    if quick:
        keep = ("PRKMK SV exp", "PRKMK SV∘KahanLi6 exp", "PRKMK Lobatto4 exp adaptive")
        return [m for m in prkmk if m[0] in keep] + peers[:2]
    return prkmk + peers


def _sweep(name, adaptive, quick, batch):
    if quick:  # one compilation per method: the smoke test runs every path once
        return [1e-4] if adaptive else [20]
    if adaptive:
        if name.startswith("PRKMK"):
            return [1e-4, 1e-6, 1e-8, 1e-10] if batch else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10]
        return [1e-3, 1e-5, 1e-7, 1e-9, 1e-11] if batch else [10.0**-k for k in range(3, 13)]
    if name.startswith("PRKMK SE"):
        return [50, 100, 200, 400] if batch else [50, 100, 200, 400, 800, 1600, 3200]
    if name.startswith(("PRKMK SV∘", "PRKMK Lobatto6", "diffrax Dopri8")):
        # Order 6 and 8 (a composed step is 5–17 Störmer–Verlet steps): fewer
        # steps, finer sweep, since the error falls as h^6–h^8; the same sweep
        # for fixed-step Dopri8, the peer they are measured against.
        if batch:
            return [13, 25, 35, 50, 70, 100, 140, 200]
        return [13, 18, 25, 35, 50, 70, 100, 140, 200, 280, 400]
    return [50, 100, 200, 400] if batch else [50, 100, 200, 400, 800, 1600]


def _errors(q, pi, q_ref, pi_ref):
    att = C.geodesic_distance(q, q_ref)
    mom = np.linalg.norm(np.asarray(pi) - pi_ref, axis=-1)
    return float(np.max(att)), float(np.max(mom))


def run_regime(regime, quick, repeats):
    batch = None if regime == "single" else (4 if quick else 1024)
    n_check = None if batch is None else min(batch, 32)
    t_end = 1.0 if quick else T_END
    q0, pi0 = C.initial_conditions(batch, seed=1)
    if batch is None:
        q_ref, pi_ref = C.reference(q0, pi0, t_end)
    else:
        refs = [C.reference(q0[k], pi0[k], t_end) for k in range(n_check)]
        q_ref, pi_ref = np.stack([r[0] for r in refs]), np.stack([r[1] for r in refs])
    inertia = jnp.asarray(C.INERTIA)
    q0j, pi0j = jnp.asarray(q0), jnp.asarray(pi0)
    rows = []
    for name, family, run, adaptive in _methods(quick):
        fn = run if batch is None else C.batched(run)
        args = (
            q0j,
            pi0j,
            jnp.asarray(t_end),
            jnp.asarray(0.1),
            jnp.asarray(1e-6),
            inertia,
        )
        compiled, compile_s = C.compile_fn(fn, *args)
        for value in _sweep(name, adaptive, quick, batch is not None):
            dt, rtol = (0.1, value) if adaptive else (t_end / value, 1e-6)
            args = (
                q0j,
                pi0j,
                jnp.asarray(t_end),
                jnp.asarray(dt),
                jnp.asarray(rtol),
                inertia,
            )
            try:
                wall, ((q, pi), steps) = C.median_time(compiled, *args, repeats=repeats)
                ok = bool(np.all(np.isfinite(np.asarray(pi))))
            except Exception as err:  # an implicit stage that does not converge raises (throw=True)
                print(f"  {name} at {value}: failed ({type(err).__name__})")
                wall, q, pi, steps, ok = float("nan"), None, None, 0, False
            if ok:
                qc, pic = (q, pi) if batch is None else (np.asarray(q)[:n_check], np.asarray(pi)[:n_check])
                att, mom = _errors(qc, pic, q_ref, pi_ref)
            else:
                att = mom = float("nan")
            row = dict(
                regime=regime,
                method=name,
                family=family,
                adaptive=adaptive,
                parameter=value,
                steps=int(np.max(np.asarray(steps))),
                wall_s=wall,
                compile_s=compile_s,
                attitude_error=att,
                momentum_error=mom,
                ok=ok,
            )
            rows.append(row)
            print(
                f"{regime:6s} {name:30s} {'rtol' if adaptive else 'n':>4s}={value:<8.0e} "
                f"steps={row['steps']:6d} wall={wall:9.4f}s  att={att:8.1e}  mom={mom:8.1e}",
                flush=True,
            )
    if batch is None:
        rows += _scipy_rows(q0, pi0, t_end, q_ref, pi_ref, quick, repeats)
    return rows


def _scipy_rows(q0, pi0, t_end, q_ref, pi_ref, quick, repeats):
    from scipy.integrate import solve_ivp

    rows = []
    z0 = C.to_vector(q0, pi0)
    for method in ("DOP853", "RK45"):
        for rtol in [1e-4, 1e-6] if quick else [10.0**-k for k in range(3, 13)]:
            walls = []
            for _ in range(max(repeats, 1)):
                start = time.perf_counter()
                sol = solve_ivp(
                    C.embedding_rhs_np,
                    (0.0, t_end),
                    z0,
                    method=method,
                    rtol=rtol,
                    atol=rtol,
                    args=(C.INERTIA,),
                )
                walls.append(time.perf_counter() - start)
            q, pi = C.from_vector(sol.y[:, -1])
            att, mom = _errors(q, pi, q_ref, pi_ref)
            row = dict(
                regime="single",
                method=f"SciPy {method}",
                family="scipy",
                adaptive=True,
                parameter=rtol,
                steps=int(sol.t.size - 1),
                wall_s=float(np.median(walls)),
                compile_s=0.0,
                attitude_error=att,
                momentum_error=mom,
                ok=bool(sol.success),
            )
            rows.append(row)
            print(
                f"single {row['method']:30s} rtol={rtol:<8.0e} steps={row['steps']:6d} "
                f"wall={row['wall_s']:9.4f}s  att={att:8.1e}  mom={mom:8.1e}",
                flush=True,
            )
    return rows


def fastest_at(rows, regime, target):
    """Per method, the fastest measured run whose errors are both ≤ target."""
    best = {}
    for r in rows:
        if r["regime"] != regime or not r["ok"] or max(r["attitude_error"], r["momentum_error"]) > target:
            continue
        if r["method"] not in best or r["wall_s"] < best[r["method"]]["wall_s"]:
            best[r["method"]] = r
    return best


def plot(rows, regime, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), sharex=True)
    C.plot_against_wall(
        axes,
        ("attitude_error", "momentum_error"),
        [r for r in rows if r["regime"] == regime],
    )
    axes[0].set_ylabel("attitude error at T (rad, geodesic on SO(3))")
    axes[1].set_ylabel("momentum error |Π − Π_ref| at T")
    for ax in axes:
        ax.set_xlabel("wall time after compilation (s)")
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=7, ncol=2)
    what = "one trajectory" if regime == "single" else "a vmapped batch of 1024"
    fig.suptitle(f"Free rigid body to T = {T_END:g}: work–precision, {what}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    args, out = C.cli(__doc__, argv, lambda p: p.add_argument("--regimes", default="single,batch"))
    rows = []
    for regime in args.regimes.split(","):
        rows += run_regime(
            regime,
            args.quick,
            repeats=1 if args.quick else (5 if regime == "single" else 3),
        )
        plot(rows, regime, out / f"work_precision_{regime}.png")
    with open(out / "work_precision.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    summary = dict(machine=C.machine(), target_errors=TARGETS, fastest_at_target={}, best_prkmk_over_dopri8={})
    for target in TARGETS:
        for regime in args.regimes.split(","):
            best = fastest_at(rows, regime, target)
            summary["fastest_at_target"][f"{regime} {target:.0e}"] = {
                m: dict(wall_s=r["wall_s"], parameter=r["parameter"], steps=r["steps"])
                for m, r in sorted(best.items(), key=lambda kv: kv[1]["wall_s"])
            }
            print(f"\n{regime}: fastest run with attitude and momentum error ≤ {target:.0e}")
            for m, r in sorted(best.items(), key=lambda kv: kv[1]["wall_s"]):
                print(f"  {m:30s} {r['wall_s']:9.4f} s  ({'rtol' if r['adaptive'] else 'n'} = {r['parameter']:.0e}, {r['steps']} steps)")
            structure = [r for m, r in best.items() if m.startswith("PRKMK")]
            dopri8 = [r for m, r in best.items() if m.startswith("diffrax Dopri8")]
            if structure and dopri8:
                fastest = min(structure, key=lambda r: r["wall_s"])
                peer = min(dopri8, key=lambda r: r["wall_s"])
                ratio = fastest["wall_s"] / peer["wall_s"]
                summary["best_prkmk_over_dopri8"][f"{regime} {target:.0e}"] = dict(
                    method=fastest["method"], dopri8=peer["method"], ratio=ratio
                )
                print(f"  best PRKMK ({fastest['method']}) / best Dopri8 ({peer['method']}) = {ratio:.2f}")
    with open(out / "work_precision.json", "w") as f:
        json.dump(dict(summary=summary, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
