"""Accuracy per second at the error targets 1e-6, 1e-8 and 1e-10, T = 10, for
the free rigid body and the heavy top (`--scenes "forced body"`: the forced
body's splittings with the exact free part): the library's splittings
(Strang, orders 4, 6, 8) and PRKMK (Lobatto 6 with exp and Cayley, stages
stopped at the tolerance; RKMK 8 with Cayley), diffrax Dopri8 and Tsit5 on
the embedding ℝ⁹×ℝ³ (constant steps and PID), and the floors written by hand
with no library code: the order-8 splitting (`_floor_kernel`) and the free
body's RKMK 8 Cayley (`_rkmk8_kernel`). Each step count (or tolerance) is
swept against SciPy DOP853 (rtol = atol = 1e-13); at each target the
cheapest run that reaches it is timed again, all interleaved.

    python benchmarks/accuracy.py
    python benchmarks/accuracy.py --quick
    python benchmarks/accuracy.py --short --regimes 1024,16384 --name accuracy_gpu   # on a GPU
    python benchmarks/accuracy.py --growth --float32 --regimes 64 --name accuracy_float32_growth
"""

import concurrent.futures
import functools
import json
import os
import statistics
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

import _common as C
import prkmk_jax as pk
from prkmk_jax.groups import sincos
from prkmk_jax.scenes import ForcedParameters, ForcedRigidBody, FreeRigidBody, HarmonicTorque, HeavyTop

T_END = 10.0
TARGETS = (1e-6, 1e-8, 1e-10)
TARGETS_FLOAT32 = (1e-4, 1e-5, 1e-6)
TOP_ARGS = C.top_parameters()
FORCED_ARGS = ForcedParameters(jnp.asarray(C.INERTIA), HarmonicTorque(jnp.array([0.3, 0.2, 0.1]), jnp.array([1.0, 2.0, 3.0]), jnp.zeros(3)))
SCENES = {"free body": (FreeRigidBody(), jnp.asarray(C.INERTIA)), "heavy top": (HeavyTop(), TOP_ARGS)}
SCENES["forced body"] = (ForcedRigidBody(), FORCED_ARGS)  # its rows: the exact free part's (`--scenes`)


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


def _rkmk8_kernel(moments):
    """RKMK 8 with Cayley on T*SO(3) = SO(3)⋉ℝ³, the free body's (Π/I, 0), by
    hand on the rows of (Q, Π): a stage (u, m) sits at Π_i = cay(−u)Π + (I + û/2)⁻¹m,
    its slope is (I + U/2)(Ω_i, 0)(I − U/2) in the matrices [[û, 0], [mᵀ, 0]]."""
    tableau, moments = diffrax.Dopri8.tableau, [float(m) for m in np.asarray(moments)]

    def cross(a, b):
        return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]

    def moved(u, m, x):  # cay(−u)x + (I + û/2)⁻¹m
        ux, um, dot, scale = cross(u, x), cross(u, m), sum(a * b for a, b in zip(u, m)), 4.0 / (4.0 + sum(a * a for a in u))
        return [x[i] + scale * (0.5 * uux - ux[i] + m[i] - 0.5 * um[i] + 0.25 * u[i] * dot) for i, uux in enumerate(cross(u, ux))]

    def slope(u, m, pi):  # one kernel a stage
        omega = [a / b for a, b in zip(moved(u, m, pi), moments)]
        uo, dot, z = cross(u, omega), sum(a * b for a, b in zip(u, omega)), [0.5 * c for c in cross(m, omega)]
        x = [omega[i] + 0.5 * uo[i] + 0.25 * u[i] * dot for i in range(3)]
        return list(jax.lax.optimization_barrier(jnp.stack(x + [z[i] + 0.5 * uz for i, uz in enumerate(cross(u, z))])))

    def step(z, h):
        rows = list(z)
        slopes = [[a / b for a, b in zip(rows[9:], moments)] + [0.0 * rows[9]] * 3]
        for row in [*tableau.a_lower, tableau.b_sol]:  # the stages' rows, then b: the step's increment U
            U = [h * sum(float(c) * k[i] for c, k in zip(row, slopes) if c != 0) for i in range(6)]
            slopes += [] if row is tableau.b_sol else [slope(U[:3], U[3:], rows[9:])]
        q = [x for r in range(3) for x in moved(U[:3], [0.0] * 3, rows[3 * r : 3 * r + 3])]  # the rows of Q·cay(u)
        return jax.lax.optimization_barrier(jnp.stack(q + moved(U[:3], U[3:], rows[9:])))

    return step


def _runners(scene_name, n, floor_fractions=pk.kahan_li_8.fractions, dtype=jnp.float64):
    scene, args = SCENES[scene_name]
    args = jax.tree.map(lambda a: jnp.asarray(a, dtype), args)
    h = T_END / n

    def library(method, on=scene):
        def run(q, p):
            y = pk.integrate(method, on, pk.BundleElement(pk.SO3(q), p), 0.0, h, n, args, save_every=n).ys
            return jnp.concatenate([y.base.matrix[-1].reshape(*q.shape[:-2], 9), y.fiber[-1]], axis=-1)

        return run

    def floor(q, p):
        step = _floor_kernel(scene_name, args, floor_fractions)
        z = jnp.moveaxis(jnp.concatenate([q.reshape(*q.shape[:-2], 9), p], axis=-1), -1, 0)
        z = jax.lax.fori_loop(0, n, lambda i, z: step(z, h), z)
        return jnp.moveaxis(z, 0, -1)

    def by_hand(q, p):  # the free body's RKMK 8 Cayley, one trajectory (vmapped over a batch)
        return jax.lax.fori_loop(0, n, lambda i, z: _rkmk8_kernel(args)(z, h), jnp.concatenate([q.reshape(9), p]))

    def fixed_step(solver):
        """diffrax with constant steps on the embedding ℝ⁹×ℝ³, vmapped."""
        return _on_embedding(scene, args, solver, h, diffrax.ConstantStepSize(), n, lambda sol: sol.ys[-1])

    out = {
        f"splitting {name}": library(scene.splitting(c))
        for name, c in (("Strang", None), ("order 4", pk.suzuki_5), ("order 6", pk.kahan_li_6), ("order 8", pk.kahan_li_8))
    }
    # Stages stopped at the tolerance (1e-12), below every error target here;
    # the default iterates on to round-off, which pays off over long runs.
    out["PRKMK Lobatto 6"] = library(scene.method(pk.lobatto_iiia_iiib6, iterate_until="tolerance"))
    out["PRKMK Lobatto 6 Cayley"] = library(scene.method(pk.lobatto_iiia_iiib6, pk.Cayley(), iterate_until="tolerance"))
    out["PRKMK DP8 Cayley"] = library(scene.method(pk.dormand_prince_8, pk.Cayley()))
    # The families of the growth sweep (`GROWTH_SWEEPS`) that the sweeps above leave out.
    out["PRKMK DP8"] = library(scene.method(pk.dormand_prince_8))
    out["PRKMK SV"] = library(scene.method(pk.stormer_verlet))
    out["PRKMK SV Cayley"] = library(scene.method(pk.stormer_verlet, pk.Cayley()))
    out["PRKMK Symmetrized SV∘Kahan–Li 6"] = library(pk.Composition(pk.Symmetrized(scene.method(pk.stormer_verlet)), pk.kahan_li_6))
    if scene_name == "heavy top":  # on G×g the fiber's part of each stage is a sum (Cayley's dcay⁻¹ is I there)
        on_g_x_g = HeavyTop(pk.DirectProduct(pk.SO3))
        out["PRKMK DP8 Cayley G×g"] = library(on_g_x_g.method(pk.dormand_prince_8, pk.Cayley()), on_g_x_g)
    if scene_name == "free body":
        out["exact flow"] = library(scene.exact_flow())
        out[HAND_RKMK8] = lambda q, p: jax.vmap(by_hand)(q, p) if q.ndim == 3 else by_hand(q, p)
    for name, c in (("order 6", pk.kahan_li_6), ("order 8", pk.kahan_li_8)) if scene_name != "free body" else ():
        out[f"splitting {name} (exact free part)"] = library(scene.splitting(c, free_part="exact"))  # the kinetic energy whole
    if scene_name != "forced body":  # the hand-written kernel has the free body's and the heavy top's parts
        out["floor order 8 (hand-written)"] = floor
    out["Dopri8 fixed"] = fixed_step(diffrax.Dopri8())
    out["Tsit5 fixed"] = fixed_step(diffrax.Tsit5())
    return out


def _on_embedding(scene, args, solver, dt0, controller, max_steps, result):
    """(q, p) ↦ `result(sol)` of diffrax's solve from 0 to T on the embedding
    ℝ⁹×ℝ³, vmapped over a batch of initial states. The times in the state's
    dtype: diffrax promotes the state to the times' dtype, so float64 times
    would run a float32 solve in float64."""
    dtype = jnp.result_type(*jax.tree.leaves(args))

    def one(q, p):
        t0, t1, dt = jnp.asarray(0.0, dtype), jnp.asarray(T_END, dtype), None if dt0 is None else jnp.asarray(dt0, dtype)
        options = dict(saveat=diffrax.SaveAt(t1=True), stepsize_controller=controller, max_steps=max_steps)
        y0 = jnp.concatenate([q.reshape(9), p])
        return result(diffrax.diffeqsolve(diffrax.ODETerm(scene.embedding_field), solver, t0, t1, dt, y0, args, **options))

    return lambda q, p: jax.vmap(one)(q, p) if q.ndim == 3 else one(q, p)


def _adaptive_runner(scene_name, solver, rtol, dtype=jnp.float64):
    """diffrax with a PID controller at rtol = atol on the embedding,
    vmapped; returns (final state, accepted steps of each trajectory)."""
    scene, args = SCENES[scene_name]
    args = jax.tree.map(lambda a: jnp.asarray(a, dtype), args)
    controller = diffrax.PIDController(rtol=rtol, atol=rtol)
    return _on_embedding(scene, args, solver, None, controller, 100_000, lambda sol: (sol.ys[-1], sol.stats["num_accepted_steps"]))


ADAPTIVE = {"Dopri8 PID": diffrax.Dopri8(), "Tsit5 PID": diffrax.Tsit5()}
"""diffrax with step-size control: their sweeps are over rtol = atol."""

SWEEPS = {
    "splitting Strang": [400, 1600, 6400],
    "splitting order 4": [50, 100, 200, 400, 800],
    "splitting order 6": [30, 45, 70, 100, 150, 220],
    "splitting order 8": [16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 128, 160],
    "PRKMK Lobatto 6": [40, 60, 90, 140, 200, 300, 450],
    "PRKMK Lobatto 6 Cayley": [60, 90, 140, 200, 300, 450, 700],
    "PRKMK DP8 Cayley": [30, 40, 50, 60, 70, 85, 100, 120, 140, 170, 200, 250],
    "PRKMK DP8 Cayley G×g": [30, 40, 50, 60, 70, 85, 100, 120, 140, 170, 200, 250],
    "RKMK 8 Cayley (hand-written)": [30, 40, 50, 60, 70, 85, 100, 120, 140, 170, 200, 250],
    "floor order 8 (hand-written)": [16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 128, 160],
    "splitting order 6 (exact free part)": [30, 45, 70, 100, 150, 220],
    "splitting order 8 (exact free part)": [16, 20, 24, 28, 32, 40, 48, 64, 80, 96],
    "exact flow": [1, 2],
    "Dopri8 fixed": [25, 35, 42, 50, 60, 70, 85, 100, 120, 140, 170, 200, 250],
    "Tsit5 fixed": [100, 160, 250, 400, 630, 1000, 1600, 2500],
    "Dopri8 PID": [1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12],
    "Tsit5 PID": [1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12],
}

GROWTH_METHODS = ("splitting Strang", "splitting order 8", "PRKMK SV", "PRKMK SV Cayley", "PRKMK Lobatto 6 Cayley", "PRKMK DP8")
GROWTH_METHODS += ("PRKMK DP8 Cayley", "PRKMK Symmetrized SV∘Kahan–Li 6", "Dopri8 fixed")
GROWTH_SWEEPS = {method: [40 * 2**k for k in range(8)] for method in GROWTH_METHODS}
"""--growth: a family from each of the library's kinds and diffrax's Dopri8,
the step count doubled from 40 to 5120: where rounding takes over from
truncation (the floor), and how the error grows past it."""

# --quick runs one method of each kind (the code each kind runs is the same).
QUICK_SKIPS = ("splitting order 4", "splitting order 6", "splitting order 8", "PRKMK Lobatto 6", "Tsit5 fixed", "Tsit5 PID")


@functools.cache
def _reference_one(scene_name, z0):
    scene, args = SCENES[scene_name]
    z0 = np.asarray(z0)
    y0 = pk.BundleElement(pk.SO3(jnp.asarray(z0[:9].reshape(3, 3))), jnp.asarray(z0[9:]))
    return scene.reference_solution(y0, [T_END], args)[-1]


def _reference(scene_name, z0s):
    """SciPy DOP853 at rtol = atol = 1e-13, for each initial state (kept between regimes)."""
    return np.stack([_reference_one(scene_name, tuple(float(v) for v in z0)) for z0 in z0s])


SHORT_SWEEPS = {  # --short: the order-8 methods and the peers, around the step counts that reach the targets
    "splitting order 8": [32, 48, 64, 96, 128],
    "floor order 8 (hand-written)": [32, 48, 64, 96, 128],
    "Dopri8 fixed": [50, 70, 100, 140, 200],
    "Tsit5 fixed": [250, 400, 630, 1000, 1600, 2500],
    "PRKMK DP8 Cayley": [50, 70, 100, 140, 200],
    "PRKMK DP8 Cayley G×g": [50, 70, 100, 140, 200],
    "Dopri8 PID": [1e-7, 1e-9, 1e-11],
}
SHORT_SWEEPS_FLOAT32 = {  # --short --float32: around the float32 targets
    "splitting order 8": [16, 24, 32, 48],
    "floor order 8 (hand-written)": [16, 24, 32, 48],
    "Dopri8 fixed": [25, 35, 50, 70],
    "Tsit5 fixed": [100, 160, 250, 400],
    "PRKMK DP8 Cayley": [25, 35, 50, 70],
    "PRKMK DP8 Cayley G×g": [25, 35, 50, 70],
}


def _compiled(jitted, q, p, parallel):
    """(key, (jitted function, seconds of the first call, which compiles it)), a key at a time (the caller frees
    programs as it goes). Later calls go through `jax.jit`'s dispatch, as users' do (a `Compiled` with host callbacks,
    as the library's and diffrax's checks are, is dispatched from Python). `parallel`: on threads first, no seconds."""
    if parallel:
        with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count()) as pool:  # XLA compiles outside the GIL
            list(pool.map(lambda fn: fn(q, p), jitted.values()))
    for key in list(jitted):
        yield key, (jitted[key], None if parallel else C.call_seconds(jitted[key], q, p))


def run(regime, scene_name, quick, rounds, short=False, dtype=jnp.float64, parallel_compile=False, without=(), only=(), growth=False):
    targets = TARGETS if dtype == jnp.float64 else TARGETS_FLOAT32
    batch = None if regime == "single" else int(regime)
    q0, p0 = C.initial_conditions(batch, seed=1)
    if scene_name == "heavy top":
        p0 = np.asarray(p0) * np.array([1.0, -1.0, 2.0])
    q, p = jnp.asarray(q0, dtype), jnp.asarray(p0, dtype)
    z0 = np.concatenate([np.asarray(q0).reshape(-1, 9), np.asarray(p0).reshape(-1, 3)], axis=-1)
    checked = z0[: (1 if batch is None else 32)]
    reference = _reference(scene_name, checked)
    rows, chosen = [], {}
    sweeps = SWEEPS if not short else SHORT_SWEEPS if dtype == jnp.float64 else SHORT_SWEEPS_FLOAT32
    sweeps = GROWTH_SWEEPS if growth else sweeps
    # --quick: every code path once; the floor composes Suzuki's 5 steps (quicker to compile).
    fractions = pk.suzuki_5.fractions if quick else pk.kahan_li_8.fractions

    def runner(method, n):
        if method in ADAPTIVE:
            return _adaptive_runner(scene_name, ADAPTIVE[method], n, dtype)
        return _runners(scene_name, n, fractions, dtype)[method]

    offered = set(ADAPTIVE) | set(_runners(scene_name, 1, fractions, dtype))  # G×g runs: the heavy top only
    jitted = {
        (method, n): jax.jit(runner(method, n))
        for method, sweep in sweeps.items()
        if method in offered and not (quick and method in QUICK_SKIPS) and method not in without and (not only or method in only)
        for n in (sweep[:1] if quick else sweep)
    }
    for (method, n), (compiled, first_call_s) in _compiled(jitted, q, p, parallel_compile):
        wall_s, out = C.median_time(compiled, q, p, repeats=3)  # the chart's point; the table times the picks interleaved
        adaptive = method in ADAPTIVE  # n is rtol; the steps are the most any trajectory took
        z, steps = (out[0], int(np.max(out[1]))) if adaptive else (out, n)
        z = np.asarray(z).reshape(-1, 12)[: len(checked)]
        error = float(np.max(np.abs(z - reference)))
        compile_s = None if first_call_s is None else first_call_s - wall_s  # tracing and compiling
        rows.append(dict(regime=regime, scene=scene_name, method=method, steps=steps, error=error, wall_s=wall_s, compile_s=compile_s))
        rows[-1]["dtype"] = jnp.dtype(dtype).name
        if adaptive:
            rows[-1]["rtol"] = n
        compiling = "" if compile_s is None else f" compile {compile_s:5.1f} s"
        setting = f"rtol={n:.0e}" if adaptive else f"n={n:5d}"
        timing = f"steps {steps:5d} error {error:8.1e} {wall_s * 1e3:9.2f} ms{compiling}"
        print(f"{scene_name:9s} {regime:6s} {method:30s} {setting} {timing}", flush=True)
        for target in targets:
            if error <= target and (method, target) not in chosen:
                chosen[(method, target)] = (steps, compiled, rows[-1])
        if not any(c is compiled for _, c, _ in chosen.values()):  # never timed again: freed (a sweep's hundred programs
            del jitted[(method, n)]  # held at once bring a process near Linux's limit of memory maps)
    for target in targets:
        picks = {m: v for (m, t), v in chosen.items() if t == target}
        if not picks:
            continue
        times = C.interleaved_times({m: compiled for m, (_, compiled, _) in picks.items()}, q, p, rounds=rounds)
        for m, (_, _, row) in picks.items():
            row.setdefault("wall_s_at_target", {})[f"{target:.0e}"] = statistics.median(times[m])
    return rows


def plot(rows, path, targets):
    """Error at T against wall time, one panel per scene and regime, one
    curve per method through its step counts (each point the median of
    three runs, not interleaved: the tables' times are the interleaved ones)."""
    panels = sorted({(r["scene"], r["regime"]) for r in rows}, key=lambda k: (k[0], k[1] != "single", k[1]))
    fig, axes = C.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.5), squeeze=False)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colours = {m: matplotlib.colormaps["tab20"](k % 20) for k, m in enumerate(methods)}  # one colour per method in every panel
    handles = {}
    for ax, (scene, regime) in zip(axes[0], panels):
        for method in methods:
            runs = sorted((r for r in rows if (r["scene"], r["regime"], r["method"]) == (scene, regime, method)), key=lambda r: r["steps"])
            if runs:  # in order of step count: a timing's noise shows as a step back
                style = "-o" if is_library(method) else ("-.v" if "hand-written" in method else "--s")
                errors = [max(r["error"], 1e-17) for r in runs]
                (handles[method],) = ax.loglog([r["wall_s"] for r in runs], errors, style, ms=3, color=colours[method], label=method)
        for target in targets:
            ax.axhline(target, color="0.8", lw=0.8)
        ax.set_title(f"{scene}, {'one trajectory' if regime == 'single' else f'batch {regime}'}")
        ax.set_xlabel("wall time after compilation (s)")
        ax.set_ylabel(f"max error at T = {T_END:g}")
        ax.grid(True, which="both", alpha=0.3)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=min(len(handles), 7), fontsize=7)
    C.save(fig, path, rect=(0, 0.12, 1, 1))


RESULTS_FILES = ("accuracy", "accuracy_16384", "accuracy_gpu_float64")
"""The committed runs, in the order the tables list them (`--name` of each);
not `accuracy_gpu_float32`, whose diffrax runs ran in float64 (README)."""
FLOOR = "floor order 8 (hand-written)"
HAND_RKMK8 = "RKMK 8 Cayley (hand-written)"
FAMILIES = (("splittings", "splitting"), ("PRKMK", "PRKMK"), ("the exact flow", "exact flow"))
"""The library's families: name, and the prefix of their methods in the results."""
DIFFRAX = ("Dopri8 fixed", "Tsit5 fixed", "Dopri8 PID", "Tsit5 PID")


def is_library(method: str) -> bool:
    return method.startswith(("splitting", "PRKMK", "exact flow"))


def is_symplectic(method: str) -> bool:
    """The library's symplectic runs: the splittings, the exact flow and the
    Lobatto IIIA–IIIB pairs (the explicit RKMK tableaus keep the group, not
    the symplectic form)."""
    return method.startswith(("splitting", "exact flow", "PRKMK Lobatto"))


def entries_of(data: dict, source: str) -> list[dict]:
    """The timed rows of one results file : one entry
    per scene, batch, dtype and target, holding each method's fastest run
    that reached the target (method: (steps, seconds)) and which of the
    library's families the run swept (`families`)."""
    device = C.device_name(data["machine"])
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


def load(results: Path) -> list[dict]:
    """`entries_of` every results file of `RESULTS_FILES` in the folder `results`."""
    paths = [results / f"{name}.json" for name in RESULTS_FILES]
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


def _ratio(library, diffrax) -> str:
    if library is None:
        return "library not reached" if diffrax is not None else "not reached"
    if diffrax is None:
        return "diffrax not reached"
    return f"{library[2] / diffrax[2]:.2f}" + (" **(slower)**" if library[2] > diffrax[2] else "")


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
        ranked = sorted(((m, n, s, rtol) for m, (n, s, rtol) in e["runs"].items() if m not in (FLOOR, HAND_RKMK8)), key=lambda r: r[2])
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


EXACT_PAIRS = (("exact flow", "splitting order 8"), ("exact flow", "PRKMK DP8 Cayley"))
EXACT_PAIRS += tuple((f"splitting order {p} (exact free part)", f"splitting order {p}") for p in (6, 8))
"""The exact flows' table: each run against the run it would replace."""
ONE_PAIRS = (("PRKMK DP8 Cayley", HAND_RKMK8),)  # one trajectory: the library's fastest run against its arithmetic by hand


def pairs_table(data: dict, source: str, pairs) -> str:
    """At each target, each run of `pairs` (`EXACT_PAIRS`, `ONE_PAIRS`)
    against its peer, timed interleaved."""
    rows = []
    for e in entries_of(data, source):
        for run, peer in ((a, b) for a, b in pairs if a in e["runs"] and b in e["runs"]):
            (n, seconds, _), (n_peer, seconds_peer, _) = e["runs"][run], e["runs"][peer]
            cells = [f"{run} (n = {n})", f"{seconds * 1e3:.3g}", f"{peer} (n = {n_peer})", f"{seconds_peer * 1e3:.3g}"]
            rows.append([e["scene"], _batch(e["regime"]), f"{e['target']:.0e}", *cells, f"{seconds / seconds_peer:.2f}"])
    headers = ["scene", "batch", "target", "run", "ms", "against", "ms", "ratio"]
    return C.measured_on(data) + f" T = {data['t_end']:g}.\n\n" + C.table(headers, rows)


def growth_table(data: dict) -> str:
    """`--growth`'s results: for each scene, batch, dtype and method, the
    floor (the smallest error of the sweep), the error at the most steps,
    and the growth exponent from the floor on (the least-squares slope of
    log error against log steps, from 3 points: 0.5 for a random walk of
    roundings, 1 for a rounding that leans one way)."""
    rows = []
    for key in dict.fromkeys((r["scene"], r["regime"], r["dtype"], r["method"]) for r in data["rows"]):
        runs = sorted((r for r in data["rows"] if (r["scene"], r["regime"], r["dtype"], r["method"]) == key), key=lambda r: r["steps"])
        steps, errors = np.log([r["steps"] for r in runs]), np.log([r["error"] for r in runs])
        k = int(np.argmin(errors))
        slope = f"{np.polyfit(steps[k:], errors[k:], 1)[0]:.2f}" if len(runs) - k >= 3 else "–"
        cells = [f"{runs[i]['error']:.1e} (n = {runs[i]['steps']})" for i in (k, -1)]
        rows.append([key[0], _batch(key[1]), key[2], key[3], *cells, slope])
    headers = ["scene", "batch", "dtype", "method", "floor (steps)", "error at the most steps", "growth exponent past the floor"]
    caption = f" T = {data['t_end']:g}; the largest error over the entries and 32 trajectories.\n\n"
    return C.measured_on(data) + caption + C.table(headers, rows)


def tables(results: Path) -> dict[str, str]:
    """This script's tables from its results in `results` (`write_tables.py`):
    `accuracy` (each target's fastest library run against diffrax's, the
    order-8 splitting per step over its hand-written kernel), `decision` (the
    run to pick; hand-written kernels left out), `summary`, `exact_flow` and
    `one_trajectory` (`pairs_table`)."""
    entries = load(results)
    out = {"accuracy": accuracy_table(entries), "decision": decision_table(entries), "summary": summary_table(entries)}
    out["exact_flow"] = pairs_table(C.results_file(results, "accuracy_exact_flow.json"), "accuracy_exact_flow", EXACT_PAIRS)
    out["one_trajectory"] = pairs_table(C.results_file(results, "accuracy_one_trajectory.json"), "accuracy_one_trajectory", ONE_PAIRS)
    return out | {"float32_growth": growth_table(C.results_file(results, "accuracy_float32_growth.json"))}


def _arguments(parser):
    parser.add_argument("--regimes", default="single,1024", help="comma-separated: single, or a batch size")
    parser.add_argument("--short", action="store_true", help="the order-8 splittings and Dopri8 only, near the targets (device runs)")
    parser.add_argument("--float32", action="store_true", help="states and parameters in float32")
    parser.add_argument("--growth", action="store_true", help="sweep GROWTH_SWEEPS (errors against step count) instead")
    parser.add_argument("--name", default="accuracy", help="stem of the results files")
    parser.add_argument("--without", default="", help="comma-separated methods to leave out (e.g. 'Tsit5 fixed')")
    parser.add_argument("--methods", default="", help="comma-separated methods to run (default: all of the sweep)")
    parser.add_argument("--scenes", default="free body,heavy top", help="comma-separated; a file's other scenes' rows are kept")
    parser.add_argument("--parallel-compile", action="store_true", help="compile each sweep on threads (compile times not recorded)")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved rounds timing each target's picks (default 7)")


def main(argv=None):
    args, out = C.cli(__doc__, argv, _arguments)
    if args.quick:  # one regime: the script's code is the same for each
        args.regimes = "4"
    dtype = jnp.float32 if args.float32 else jnp.float64
    scenes, regimes, existing = args.scenes.split(","), args.regimes.split(","), out / f"{args.name}.json"  # others' rows are kept
    rows = C.results_file(out, existing.name)["rows"] if existing.exists() else []
    rows = [r for r in rows if r["scene"] not in scenes or r["regime"] not in regimes]
    targets = TARGETS if dtype == jnp.float64 else TARGETS_FLOAT32

    def write():
        with open(out / f"{args.name}.json", "w") as f:
            json.dump(dict(machine=C.machine(), t_end=T_END, targets=targets, rows=rows), f, indent=1)

    for scene_name in scenes[:1] if args.quick else scenes:
        for regime in regimes:
            only = [m for m in args.methods.split(",") if m]
            options = dict(short=args.short, dtype=dtype, parallel_compile=args.parallel_compile, only=only, growth=args.growth)
            options["without"] = args.without.split(",")
            rows += run(regime, scene_name, args.quick, rounds=3 if args.quick else args.rounds, **options)
            write()  # what a run cut short has measured so far
    plot(rows, out / f"{args.name}.png", targets)
    data = dict(machine=C.machine(), t_end=T_END, targets=targets, rows=rows)
    print(growth_table(data) if args.growth else accuracy_table(entries_of(data, args.name)))
    return out


if __name__ == "__main__":
    main()
