"""Accuracy per second of the exact-flow splittings against Dopri8 and a
hand-written splitting kernel, at the error targets 1e-6, 1e-8 and 1e-10.

Scenes: the free rigid body (paper inertia and momentum, random attitudes)
and the heavy top (`HeavyTop`, inertia (1, 0.8, 0.4), lever (0.1, 0.2, 0.9)),
T = 10. Methods:

- the library's `Splitting` of the scene (Strang, and composed to order 4,
  6 and 8), through `prkmk_jax.integrate`, the batch in the state;
- the floor of that family: the order-8 (Kahan–Li s17) splitting written by
  hand on the packed (12, batch) array, the axes in the library's order,
  the outer rotations merged, with the same vectorised sine and cosine
  (`prkmk_jax.groups.sincos`) and no other library code;
- diffrax Dopri8 with constant steps on the embedding ℝ⁹×ℝ³, vmapped.

For each method a sweep of step counts gives the error at T (max over the
state's entries and the first 32 trajectories, against SciPy DOP853 at
rtol = atol = 1e-13); at each target the smallest step count that reaches
it is timed, all methods interleaved (median of the rounds, compile
excluded). Writes splitting.json and splitting.md (the table) to --out.

    python benchmarks/splitting.py --out benchmarks/results
    python benchmarks/splitting.py --quick
    python benchmarks/splitting.py --short --regimes 1024,16384 --name splitting_gpu   # on a GPU
"""

import json
import statistics
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import _common as C
import prkmk_jax as pk
from prkmk_jax.groups import sincos
from prkmk_jax.scenes import FreeRigidBody, HeavyTop, TopParameters

T_END = 10.0
TARGETS = (1e-6, 1e-8, 1e-10)
TOP_ARGS = TopParameters(jnp.array([1.0, 0.8, 0.4]), jnp.array([0.1, 0.2, 0.9]))
SCENES = {"free body": (FreeRigidBody(), jnp.asarray(C.INERTIA)), "heavy top": (HeavyTop(), TOP_ARGS)}


def _floor_kernel(scene_name, args, fractions):
    """The hand-written splitting on the packed (12, *batch) array: Strang
    steps with fractions γ, outer part merged between them."""
    moments = np.asarray(args.inertia if scene_name == "heavy top" else args)
    lever = None if scene_name == "free body" else np.asarray(args.lever)
    outer_parts = ["kick"] if lever is not None else []
    # The axes by increasing inertia, the largest in the middle (as the library orders them).
    parts = outer_parts + [int(a) for a in np.argsort(moments)]

    def apply(part, z, h):
        rows = list(z)
        if part == "kick":
            g = rows[6:9]
            torque = (g[1] * lever[2] - g[2] * lever[1], g[2] * lever[0] - g[0] * lever[2], g[0] * lever[1] - g[1] * lever[0])
            for k in range(3):
                rows[9 + k] = rows[9 + k] + h * torque[k]
            return jax.lax.optimization_barrier(jnp.stack(rows))
        j, k = (part + 1) % 3, (part + 2) % 3
        s, c = sincos(h * rows[9 + part] / moments[part])
        for a, b in [(3 * r + j, 3 * r + k) for r in range(3)] + [(9 + j, 9 + k)]:
            rows[a], rows[b] = c * rows[a] + s * rows[b], c * rows[b] - s * rows[a]
        return jax.lax.optimization_barrier(jnp.stack(rows))

    def step(z, h):
        pending = 0.0  # the outer part's merged step, applied before the next inner sequence
        for gamma in fractions:
            z = apply(parts[0], z, (pending + gamma / 2) * h)
            for p in parts[1:-1]:
                z = apply(p, z, gamma / 2 * h)
            z = apply(parts[-1], z, gamma * h)
            for p in reversed(parts[1:-1]):
                z = apply(p, z, gamma / 2 * h)
            pending = gamma / 2
        return apply(parts[0], z, pending * h)

    return step


def _runners(scene_name, n, floor_fractions=pk.kahan_li_8.fractions, dtype=jnp.float64):
    scene, args = SCENES[scene_name]
    args = jax.tree.map(lambda a: jnp.asarray(a, dtype), args)
    h = T_END / n

    def library(method):
        def run(q, p):
            y = pk.integrate(method, scene, pk.BundleElement(pk.SO3(q), p), 0.0, h, n, args, save_every=n).ys
            return jnp.concatenate([y.base.matrix[-1].reshape(*q.shape[:-2], 9), y.fiber[-1]], axis=-1)

        return run

    def floor(q, p):
        step = _floor_kernel(scene_name, args, floor_fractions)
        z = jnp.moveaxis(jnp.concatenate([q.reshape(*q.shape[:-2], 9), p], axis=-1), -1, 0)
        z = jax.lax.fori_loop(0, n, lambda i, z: step(z, h), z)
        return jnp.moveaxis(z, 0, -1)

    def dopri8(q, p):
        def one(q, p):
            z0 = jnp.concatenate([q.reshape(9), p])
            term = diffrax.ODETerm(scene.embedding_field)
            sol = diffrax.diffeqsolve(
                term,
                diffrax.Dopri8(),
                0.0,
                T_END,
                h,
                z0,
                args,
                saveat=diffrax.SaveAt(t1=True),
                stepsize_controller=diffrax.ConstantStepSize(),
                max_steps=n,
            )
            return sol.ys[-1]

        return jax.vmap(one)(q, p) if q.ndim == 3 else one(q, p)

    out = {
        f"splitting {name}": library(scene.splitting(c))
        for name, c in (("Strang", None), ("order 4", pk.suzuki_5), ("order 6", pk.kahan_li_6), ("order 8", pk.kahan_li_8))
    }
    out["floor order 8 (hand-written)"] = floor
    out["Dopri8 fixed"] = dopri8
    return out


SWEEPS = {
    "splitting Strang": [400, 1600, 6400],
    "splitting order 4": [50, 100, 200, 400, 800],
    "splitting order 6": [30, 45, 70, 100, 150, 220],
    "splitting order 8": [20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 128],
    "floor order 8 (hand-written)": [20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 128],
    "Dopri8 fixed": [35, 42, 50, 60, 70, 85, 100, 120, 140, 170, 200],
}


QUICK_SKIPS = ("splitting order 6", "splitting order 8")


def _reference(scene_name, z0s):
    scene, args = SCENES[scene_name]
    field = jax.jit(scene.embedding_field)
    out = []
    for z0 in z0s:
        sol = solve_ivp(lambda t, z: np.asarray(field(t, jnp.asarray(z), args)), (0.0, T_END), z0, method="DOP853", rtol=1e-13, atol=1e-13)
        out.append(sol.y[:, -1])
    return np.stack(out)


SHORT_SWEEPS = {  # --short: the library's order 8 and Dopri8, around the step counts that reach the targets
    "splitting order 8": [32, 48, 64, 96, 128],
    "Dopri8 fixed": [50, 70, 100, 140, 200],
}


def run(regime, scene_name, quick, rounds, short=False, dtype=jnp.float64):
    batch = None if regime == "single" else int(regime)
    q0, p0 = C.initial_conditions(batch, seed=1)
    if scene_name == "heavy top":
        p0 = np.asarray(p0) * np.array([1.0, -1.0, 2.0])
    q, p = jnp.asarray(q0, dtype), jnp.asarray(p0, dtype)
    z0 = np.concatenate([np.asarray(q0).reshape(-1, 9), np.asarray(p0).reshape(-1, 3)], axis=-1)
    checked = z0[: (1 if batch is None else 32)]
    reference = _reference(scene_name, checked)
    rows = []
    chosen = {}
    for method in SHORT_SWEEPS if short else SWEEPS:
        if quick and method in QUICK_SKIPS:
            continue
        sweep = SWEEPS[method][:1] if quick else (SHORT_SWEEPS if short else SWEEPS)[method]
        for n in sweep:
            # --quick: every code path once; the floor composes Suzuki's 5 steps (quicker to compile).
            fractions = pk.suzuki_5.fractions if quick else pk.kahan_li_8.fractions
            fn = jax.jit(_runners(scene_name, n, fractions, dtype)[method])
            start = time.perf_counter()
            compiled = fn.lower(q, p).compile()
            compile_s = time.perf_counter() - start
            z = np.asarray(compiled(q, p)).reshape(-1, 12)[: len(checked)]
            error = float(np.max(np.abs(z - reference)))
            rows.append(
                dict(regime=regime, scene=scene_name, method=method, steps=n, error=error, compile_s=compile_s, dtype=jnp.dtype(dtype).name)
            )
            print(f"{scene_name:9s} {regime:6s} {method:30s} n={n:5d} error {error:8.1e} compile {compile_s:5.1f} s", flush=True)
            for target in TARGETS:
                if error <= target and (method, target) not in chosen:
                    chosen[(method, target)] = (n, compiled, rows[-1])
    for target in TARGETS:
        picks = {m: v for (m, t), v in chosen.items() if t == target}
        if not picks:
            continue
        times = {m: [] for m in picks}
        for _ in range(rounds):
            for m, (_, compiled, _) in picks.items():
                start = time.perf_counter()
                jax.block_until_ready(compiled(q, p))
                times[m].append(time.perf_counter() - start)
        for m, (_, _, row) in picks.items():
            row.setdefault("wall_s_at_target", {})[f"{target:.0e}"] = statistics.median(times[m])
    return rows


def table(rows):
    """Markdown, one row per scene, regime and target: the fastest library
    splitting, the hand-written floor and Dopri8 at that target, and the
    library's time over each."""
    lines = [
        "| scene | regime | target | library splitting | ms | floor (hand-written) | ms | Dopri8 fixed | ms "
        "| library / floor | library / Dopri8 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(r["scene"], r["regime"]) for r in rows}, key=lambda k: (k[0], k[1] != "single", k[1]))
    for scene, regime in keys:
        for target in TARGETS:
            label = f"{target:.0e}"
            timed = [
                (r["method"], r["steps"], r["wall_s_at_target"][label])
                for r in rows
                if r["scene"] == scene and r["regime"] == regime and label in r.get("wall_s_at_target", {})
            ]

            def best(prefix):
                found = [t for t in timed if t[0].startswith(prefix)]
                return min(found, key=lambda t: t[2]) if found else None

            library, floor, dopri8 = best("splitting"), best("floor"), best("Dopri8")

            def cell(entry, name=True):
                if entry is None:
                    return "not reached | –"
                return (f"{entry[0]} (n = {entry[1]})" if name else f"n = {entry[1]}") + f" | {entry[2] * 1e3:.2f}"

            def ratio(other):
                return "–" if library is None or other is None else f"{library[2] / other[2]:.2f}"

            peers = f"{cell(floor, False)} | {cell(dopri8, False)} | {ratio(floor)} | {ratio(dopri8)}"
            lines.append(f"| {scene} | {regime} | {label} | {cell(library)} | {peers} |")
    return "\n".join(lines) + "\n"


def arrangements(quick):
    """Error at T = 10 of the order-2 and order-8 splittings of the heavy top
    and the free body for each order of the axis terms and placement of the
    gravity kick (single trajectory, the scene's parts reordered): the
    comparison behind the scenes' choice."""
    import itertools

    rows = []
    q0, p0 = C.initial_conditions(None, seed=1)
    for scene_name in ("free body",) if quick else SCENES:
        scene, args = SCENES[scene_name]
        momentum = np.asarray(p0) * (np.array([1.0, -1.0, 2.0]) if scene_name == "heavy top" else 1.0)
        y0 = pk.BundleElement(pk.SO3(jnp.asarray(q0)), jnp.asarray(momentum))
        reference = _reference(scene_name, np.concatenate([np.asarray(q0).reshape(1, 9), momentum.reshape(1, 3)], axis=-1))[0]
        parts = scene.exact_flows(args)
        kick, rotations = (parts[:1], parts[1:]) if scene_name == "heavy top" else ((), parts)
        orders = list(itertools.permutations(range(3)))[: 2 if quick else 6]
        for order in orders:
            for placement in ("outer", "middle") if kick else ("none",):
                turned = tuple(rotations[a] for a in order)
                arranged = kick + turned if placement != "middle" else turned + kick
                reordered = _Reordered(scene, arranged)
                for coefficients, n in ((None, 800), (pk.kahan_li_8, 48)):
                    method = pk.Splitting(reordered, coefficients)
                    y = pk.integrate(method, reordered, y0, 0.0, T_END / n, n, args, save_every=n).ys
                    z = np.asarray(scene.to_embedding(jax.tree.map(lambda a: a[-1], y)))
                    rows.append(
                        dict(
                            scene=scene_name,
                            axes_outermost_first=[int(a) for a in order],
                            kick=placement,
                            order=method.order,
                            steps=n,
                            error=float(np.max(np.abs(z - reference))),
                        )
                    )
                    error = rows[-1]["error"]
                    print(f"{scene_name:9s} axes by inertia {order} kick {placement:6s} order {method.order}: error {error:.1e}")
    return rows


class _Reordered(pk.exact_flows.AbstractSplitScene):
    """A scene with its parts in another order (for `arrangements`)."""

    scene: pk.exact_flows.AbstractSplitScene
    parts: tuple

    @property
    def bundle(self):
        return self.scene.bundle

    @property
    def form(self):
        return self.scene.form

    def __call__(self, t, y, args):
        return self.scene(t, y, args)  # type: ignore[operator]

    def exact_flows(self, args):
        return self.parts

    def pack(self, y, args):
        return self.scene.pack(y, args)

    def unpack(self, z, like, args):
        return self.scene.unpack(z, like, args)


def _arguments(parser):
    parser.add_argument("--regimes", default="single,1024", help="comma-separated: single, or a batch size")
    parser.add_argument("--short", action="store_true", help="the order-8 splittings and Dopri8 only, near the targets (device runs)")
    parser.add_argument("--float32", action="store_true", help="states and parameters in float32")
    parser.add_argument("--name", default="splitting", help="stem of the results files")


def main(argv=None):
    args, out = C.cli(__doc__, argv, _arguments)
    if args.quick:
        args.regimes = "single,4"
    dtype = jnp.float32 if args.float32 else jnp.float64
    rows = []
    for scene_name in list(SCENES)[:1] if args.quick else SCENES:
        for regime in args.regimes.split(","):
            rows += run(regime, scene_name, args.quick, rounds=3 if args.quick else 7, short=args.short, dtype=dtype)
    arranged = [] if args.short else arrangements(args.quick)
    with open(out / f"{args.name}.json", "w") as f:
        json.dump(dict(machine=C.machine(), t_end=T_END, rows=rows, arrangements=arranged), f, indent=1)
    (out / f"{args.name}.md").write_text(table(rows))
    print(table(rows))


if __name__ == "__main__":
    main()
