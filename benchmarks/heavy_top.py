"""The heavy top: long-time invariants against cost, and error against cost.

The scene is `prkmk_jax.scenes.HeavyTop` (Π' = Π × Ω + Γ × ℓ, Γ = Qᵀe₃): the
fiber moves on its own (η ≠ 0), unlike the free body. Parameters: principal
moments (1.0, 0.8, 0.4), ℓ = m g χ = (0.1, 0.2, 0.9), Q₀ a random rotation
(seed 5), Π₀ = (0.3, −0.4, 1.5). PRKMK methods run through `integrate`
(T*SO(3), body form, or G×g where the name says so); the peers are diffrax (Tsit5, Dopri8, adaptive) on the
embedding ℝ⁹×ℝ³ through `HeavyTop.embedding_field`, and SciPy DOP853.

* Long time, T = 1000: the largest error of the energy H = ½Π·Ω + ℓ·Γ and of
  the vertical momentum Γ·Π over t ∈ {0, 1, …, T}, ‖QᵀQ − I‖, and the wall
  time after compilation (median of 3).
* Error against cost, T = 10: the largest entry error of (Q, Π) at T against
  DOP853 at rtol = atol = 1e-13, and the wall time (median of 5).

The heavy top's accuracy per second against every family (the splittings,
RKMK 8, diffrax with constant steps and a PID controller, one trajectory
and batches) is `splitting.py`'s.

    python benchmarks/heavy_top.py --out benchmarks/results
    python benchmarks/heavy_top.py --quick
"""

import json
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import HeavyTop, TopParameters, random_rotation

jax.config.update("jax_enable_x64", True)  # before the module's arrays are made
TOP = HeavyTop()
TOP_ON_G_X_G = HeavyTop(pk.DirectProduct(pk.SO3))
ARGS = TopParameters(jnp.array([1.0, 0.8, 0.4]), jnp.array([0.1, 0.2, 0.9]))
Y0 = pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(5))), jnp.array([0.3, -0.4, 1.5]))
Z0 = TOP.to_embedding(Y0)


def prkmk_methods():
    """name: (scene, method); the scene is the vector field of its bundle."""
    sv = TOP.method(pk.stormer_verlet)
    symmetric = pk.Symmetrized(sv)
    return {
        "PRKMK SV exp": (TOP, sv),
        "PRKMK SV cayley": (TOP, TOP.method(pk.stormer_verlet, pk.Cayley())),
        "PRKMK Symmetrized SV": (TOP, symmetric),
        "PRKMK Symmetrized SV ∘ triple jump": (TOP, pk.Composition(symmetric, pk.yoshida_triple_jump)),
        "PRKMK Lobatto4": (TOP, TOP.method(pk.lobatto_iiia_iiib4)),
        "PRKMK SV exp, G×g": (TOP_ON_G_X_G, TOP_ON_G_X_G.method(pk.stormer_verlet)),
        "PRKMK Lobatto4, G×g": (TOP_ON_G_X_G, TOP_ON_G_X_G.method(pk.lobatto_iiia_iiib4)),
    }


def _prkmk_run(scene, method, h, t_end, every):
    n = int(round(t_end / h))

    def run(y0, args):
        ys = pk.integrate(method, scene, y0, 0.0, h, n, args, save_every=every).ys
        return scene.to_embedding(ys)

    return run


def _diffrax_run(solver, rtol, t_end, ts):
    def run(z0, args):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(TOP.embedding_field),
            solver,
            0.0,
            t_end,
            None,
            z0,
            args,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=None,
        )
        return sol.ys

    return run


def _errors(zs):
    """Largest |ΔH|, |Δ(Γ·Π)| and ‖QᵀQ − I‖ along embedded states zs (t, 12)."""
    ys = pk.BundleElement(pk.SO3(jnp.asarray(zs[:, :9].reshape(-1, 3, 3))), jnp.asarray(zs[:, 9:]))
    inv = TOP.invariants(ys, ARGS)
    return dict(
        energy=float(jnp.max(jnp.abs(inv["energy"] - inv["energy"][0]))),
        vertical_momentum=float(jnp.max(jnp.abs(inv["vertical momentum"] - inv["vertical momentum"][0]))),
        orthogonality=float(jnp.max(inv["orthogonality"])),
    )


def _timed(fn, *args, repeats):
    compiled, compile_s = C.compile_fn(fn, *args)
    wall, out = C.median_time(compiled, *args, repeats=repeats)
    return np.asarray(out), wall, compile_s


def long_time(quick):
    t_end = 50.0 if quick else 1000.0
    ts = jnp.arange(0.0, t_end + 0.5)
    rows = []
    steps = {"PRKMK Symmetrized SV ∘ triple jump": (0.1,), "PRKMK Lobatto4": (0.1, 0.05), "PRKMK Lobatto4, G×g": (0.1, 0.05)}
    for name, (scene, method) in prkmk_methods().items():
        for h in (0.1,) if quick else steps.get(name, (0.05, 0.025)):
            zs, wall, compile_s = _timed(_prkmk_run(scene, method, h, t_end, int(round(1 / h))), Y0, ARGS, repeats=1 if quick else 3)
            rows.append(dict(method=name, parameter=h, wall_s=wall, compile_s=compile_s, **_errors(zs)))
            print(f"{name:36s} h={h:<6g} {wall:8.3f} s  {rows[-1]}", flush=True)
    for name, solver in (("diffrax Tsit5", diffrax.Tsit5()), ("diffrax Dopri8", diffrax.Dopri8())):
        for rtol in (1e-6,) if quick else (1e-6, 1e-8, 1e-10, 1e-12):
            zs, wall, compile_s = _timed(_diffrax_run(solver, rtol, t_end, ts), Z0, ARGS, repeats=1 if quick else 3)
            rows.append(dict(method=name, parameter=rtol, wall_s=wall, compile_s=compile_s, **_errors(zs)))
            print(f"{name:36s} rtol={rtol:<6g} {wall:8.3f} s  {rows[-1]}", flush=True)
    return rows


def _reference(t_end, rtol=1e-13):
    """The scene's `reference_solution` at `t_end` and its wall time (SciPy's
    DOP853 as a peer: its cost at a tolerance)."""
    start = time.perf_counter()
    z = TOP.reference_solution(Y0, [t_end], ARGS, rtol=rtol, atol=rtol)[-1]
    return z, time.perf_counter() - start


def work_precision(quick):
    t_end = 10.0
    reference, _ = _reference(t_end)
    rows = []
    sweeps = {
        "PRKMK Symmetrized SV ∘ triple jump": [25, 50, 100, 200],
        "PRKMK Lobatto4": [25, 50, 100, 200],
        "PRKMK Lobatto4, G×g": [25, 50, 100, 200],
    }
    for name, (scene, method) in prkmk_methods().items():
        for n in [50] if quick else sweeps.get(name, [100, 200, 400, 800]):
            zs, wall, _ = _timed(_prkmk_run(scene, method, t_end / n, t_end, n), Y0, ARGS, repeats=1 if quick else 5)
            rows.append(dict(method=name, parameter=n, wall_s=wall, error=float(np.max(np.abs(zs[-1] - reference)))))
            print(f"{name:36s} n={n:<6d} {wall * 1e3:8.2f} ms  error {rows[-1]['error']:.1e}", flush=True)
    for name, solver in (("diffrax Tsit5", diffrax.Tsit5()), ("diffrax Dopri8", diffrax.Dopri8())):
        for rtol in [1e-6] if quick else [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]:
            zs, wall, _ = _timed(_diffrax_run(solver, rtol, t_end, jnp.array([t_end])), Z0, ARGS, repeats=1 if quick else 5)
            rows.append(dict(method=name, parameter=rtol, wall_s=wall, error=float(np.max(np.abs(zs[-1] - reference)))))
            print(f"{name:36s} rtol={rtol:<6g} {wall * 1e3:8.2f} ms  error {rows[-1]['error']:.1e}", flush=True)
    for rtol in [1e-6] if quick else [1e-6, 1e-9]:
        z, wall = _reference(t_end, rtol)
        rows.append(dict(method="SciPy DOP853", parameter=rtol, wall_s=wall, error=float(np.max(np.abs(z - reference)))))
        print(f"{'SciPy DOP853':36s} rtol={rtol:<6g} {wall * 1e3:8.2f} ms  error {rows[-1]['error']:.1e}", flush=True)
    return rows


def markdown(result):
    """The README tables, rendered from the results."""
    lines = ["| method | h / rtol | wall s | energy | Γ·Π | ‖QᵀQ − I‖ |", "|---|---:|---:|---:|---:|---:|"]
    for r in result["long_time"]:
        lines.append(
            f"| {r['method']} | {r['parameter']:g} | {r['wall_s']:.3f} | {r['energy']:.1e} "
            f"| {r['vertical_momentum']:.1e} | {r['orthogonality']:.1e} |"
        )
    lines += ["", "| method | n / rtol | wall ms | error at T = 10 |", "|---|---:|---:|---:|"]
    for r in result["work_precision"]:
        lines.append(f"| {r['method']} | {r['parameter']:g} | {r['wall_s'] * 1e3:.2f} | {r['error']:.1e} |")
    return "\n".join(lines)


def main(argv=None):
    args, out = C.cli(__doc__, argv)
    result = dict(machine=C.machine(), long_time=long_time(args.quick), work_precision=work_precision(args.quick))
    with open(out / "heavy_top.json", "w") as f:
        json.dump(result, f, indent=1)
    print(markdown(result))


if __name__ == "__main__":
    main()
