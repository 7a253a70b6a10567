"""Long runs at the round-off limit: how the invariants' errors grow with the
number of steps, and what solving the implicit stages to round-off costs
(`PRKMK(iterate_until="round-off")`, the default, against
`iterate_until="tolerance"`, which stops at the default tolerance 1e-12).

Growth: for each method and setting, a batch of random initial states
(Haar-random attitudes, unit |Π| in a random direction), h = 0.1, run
for up to `--max-steps` steps (vmapped, each trajectory its own stage
iterations). For each invariant, the largest error up to step N (relative
for the energy and the Casimirs, the largest entry of QᵀQ − I for the
attitude) is taken per trajectory, its median over the batch is recorded
at N = 10³ … and the growth exponent is the least-squares slope of
log(median) against log N over N ≥ 10⁴. A random walk of roundings gives
0.5, a bias (a stage tolerance, a systematic rounding) 1.

* Free body (T*SO(3), exp and Cayley, body form): Störmer–Verlet keeps the
  energy and |Π| exactly in exact arithmetic, so their errors are rounding
  alone; also SV∘Kahan–Li 6 and Symmetrized Lobatto IIIA–IIIB 4.
* Heavy top (T*SO(3), inertia (1, 0.8, 0.4), lever (0.1, 0.2, 0.9)):
  Symmetrized SV; its energy error is the method's bounded O(h²)
  oscillation, and the vertical momentum's too.

Cost: the same methods, one trajectory and a batch of 64 in the state,
both settings compiled and run interleaved: ns per trajectory-step,
implicit iterations a step, and their ratios.

    python benchmarks/round_off.py --out benchmarks/results
    python benchmarks/round_off.py --quick
"""

import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, TopParameters
from prkmk_jax.scenes.rigid_body import PAPER_INERTIA, random_rotation

H = 0.1
SETTINGS = ("round-off", "tolerance")
FREE = FreeRigidBody()
TOP = HeavyTop()
TOP_ARGS = TopParameters(jnp.array([1.0, 0.8, 0.4]), jnp.array([0.1, 0.2, 0.9]))
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


def initial_states(batch, seed=0, dtype=jnp.float64):
    rng = np.random.default_rng(seed)
    momenta = rng.normal(size=(batch, 3))
    momenta /= np.linalg.norm(momenta, axis=1, keepdims=True)
    attitudes = np.stack([random_rotation(seed * 1009 + k) for k in range(batch)])
    return pk.BundleElement(pk.SO3(jnp.asarray(attitudes, dtype)), jnp.asarray(momenta, dtype))


def growth(method, scene_name, num_steps, batch, every, dtype=jnp.float64):
    """Median (over the batch) of the largest error up to each saved step,
    per invariant, and the wall time of the run (compile included)."""
    scene, args = SCENES[scene_name]
    args = jax.tree.map(lambda a: jnp.asarray(a, dtype), args)
    y0 = initial_states(batch, dtype=dtype)
    run = jax.jit(jax.vmap(lambda y: pk.integrate(method, scene, y, 0.0, H, num_steps, args, save_every=every)))
    start = time.perf_counter()
    trajectory = jax.block_until_ready(run(y0))
    seconds = time.perf_counter() - start
    if not bool(jnp.all(trajectory.result == pk.RESULTS.successful)):
        raise RuntimeError(f"{scene_name}: a stage failed to converge")
    invariants = scene.invariants(trajectory.ys, args)
    errors = {}
    for name, values in invariants.items():
        values = np.asarray(values, np.float64)
        if ERROR_KINDS.get(name) == "absolute":
            error = values
        elif values.ndim == 3:  # a vector (the spatial momentum): its largest change over its largest entry
            error = np.max(np.abs(values - values[:, :1]), axis=2) / np.max(np.abs(values[:, :1]), axis=2)
        else:
            error = np.abs(values / values[:, :1] - 1)
        errors[name] = np.median(np.maximum.accumulate(error, axis=1), axis=0)
    return errors, seconds


def exponent(steps, errors, smallest=10_000):
    """Least-squares slope of log(error) against log(steps), over steps ≥
    `smallest`, at points spaced evenly in log(steps)."""
    steps, errors = np.asarray(steps, float), np.asarray(errors, float)
    targets = np.exp(np.linspace(np.log(smallest), np.log(steps[-1]), 13))
    picks = sorted({int(np.argmin(np.abs(np.log(steps) - np.log(t)))) for t in targets})
    if len(picks) < 2:
        return float("nan")
    return float(np.polyfit(np.log(steps[picks]), np.log(np.maximum(errors[picks], 1e-300)), 1)[0])


def cost(method, scene_name, batch, num_steps, rounds, setting_methods):
    """ns per trajectory-step and iterations a step of each setting, interleaved."""
    scene, args = SCENES[scene_name]
    y0 = initial_states(batch) if batch > 1 else jax.tree.map(lambda a: a[0], initial_states(1))

    def make(m):
        def run(y):
            trajectory = pk.integrate(m, scene, y, 0.0, H, num_steps, args, save_every=num_steps)
            return trajectory.ys, trajectory.stats["num_iterations"]

        return run

    fns = {setting: make(m) for setting, m in setting_methods.items()}
    compiled, compile_s, outputs = C.compile_all(fns, y0)
    times = C.interleaved_times(compiled, y0, rounds=rounds)
    ns = C.ns_per_trajectory_step(times, batch, num_steps)
    iterations = {setting: int(outputs[setting][1]) / num_steps for setting in fns}
    return dict(
        ns_per_traj_step=ns,
        iterations_per_step=iterations,
        round_off_over_tolerance=C.median_ratio(times, "round-off", "tolerance"),
        compile_s=compile_s,
    )


def main(argv=None):
    def extra(parser):
        parser.add_argument("--max-steps", type=float, default=1e6, help="steps of the growth runs (default 1e6)")
        parser.add_argument("--long-steps", type=float, default=1e7, help="steps of the longest run, SV exp only (default 1e7)")

    args, out = C.cli(__doc__, argv, extra)
    quick = args.quick
    max_steps = 20_000 if quick else int(args.max_steps)
    long_steps = 20_000 if quick else int(args.long_steps)
    batch = 2 if quick else 16
    every = 1000
    by_setting = {setting: methods(setting) for setting in SETTINGS}
    growth_rows = []
    print(f"{'method':28s} {'setting':10s} {'steps':>9s} {'s':>7s}  invariant: median max error (exponent)")
    for name in by_setting["round-off"]:
        for setting in SETTINGS:
            scene_name, method = by_setting[setting][name]
            steps = long_steps if name == "SV exp" else max_steps
            errors, seconds = growth(method, scene_name, steps, batch, every)
            saved = np.arange(len(next(iter(errors.values())))) * every
            row = dict(
                method=name,
                scene=scene_name,
                setting=setting,
                dtype="float64",
                batch=batch,
                steps=steps,
                seconds=seconds,
                checkpoints=[int(n) for n in saved[1:]],
                errors={k: [float(x) for x in v[1:]] for k, v in errors.items()},
                exponent={k: exponent(saved[1:], v[1:]) for k, v in errors.items()},
            )
            growth_rows.append(row)
            summary = "  ".join(f"{k}: {row['errors'][k][-1]:.1e} ({row['exponent'][k]:.2f})" for k in errors)
            print(f"{name:28s} {setting:10s} {steps:9d} {seconds:7.1f}  {summary}", flush=True)
    # float32: SV exp, both settings (the step renormalises the state there).
    for setting in SETTINGS:
        scene_name, method = by_setting[setting]["SV exp"]
        errors, seconds = growth(method, scene_name, max_steps, batch, every, jnp.float32)
        saved = np.arange(len(next(iter(errors.values())))) * every
        row = dict(
            method="SV exp",
            scene=scene_name,
            setting=setting,
            dtype="float32",
            batch=batch,
            steps=max_steps,
            seconds=seconds,
            checkpoints=[int(n) for n in saved[1:]],
            errors={k: [float(x) for x in v[1:]] for k, v in errors.items()},
            exponent={k: exponent(saved[1:], v[1:]) for k, v in errors.items()},
        )
        growth_rows.append(row)
        summary = "  ".join(f"{k}: {row['errors'][k][-1]:.1e} ({row['exponent'][k]:.2f})" for k in errors)
        print(f"{'SV exp, float32':28s} {setting:10s} {max_steps:9d} {seconds:7.1f}  {summary}", flush=True)

    cost_rows = []
    rounds = 2 if quick else 9
    print(f"\n{'method':28s} {'batch':>5s} {'round-off ns':>12s} {'tolerance ns':>12s} {'ratio':>6s} {'it r-o':>7s} {'it tol':>7s}")
    for name in by_setting["round-off"]:
        for cost_batch in (1, 64):
            scene_name = by_setting["round-off"][name][0]
            steps = 50 if quick else max(200, 20_000 // cost_batch)
            row = cost(None, scene_name, cost_batch, steps, rounds, {s: by_setting[s][name][1] for s in SETTINGS})
            row.update(method=name, scene=scene_name, batch=cost_batch, steps=steps)
            cost_rows.append(row)
            ns, it = row["ns_per_traj_step"], row["iterations_per_step"]
            print(
                f"{name:28s} {cost_batch:5d} {ns['round-off']:12.0f} {ns['tolerance']:12.0f} {row['round_off_over_tolerance']:6.2f} "
                f"{it['round-off']:7.1f} {it['tolerance']:7.1f}",
                flush=True,
            )
    with open(out / "round_off.json", "w") as f:
        json.dump(dict(machine=C.machine(), h=H, growth=growth_rows, cost=cost_rows), f, indent=1)


if __name__ == "__main__":
    main()
