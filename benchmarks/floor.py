"""The floor: hand-fused closed-form steps against the generic PRKMK step.

Free rigid body on T*SO(3) (Cotangent, body form, exp coordinates), h = 0.01,
the paper's inertia, a batch of random attitudes and momenta. Two methods:

- Störmer–Verlet (the §5 pair). With the generator (Ω, 0) and dexp⁻¹ ≈ I
  (truncation for order 2), the step is u = (h/2)(Ωₙ + Ω₁),
  Ω₁ = I⁻¹ exp(−û)Πₙ solved by fixed-point iteration, then
  Qₙ₊₁ = Qₙ exp(û), Πₙ₊₁ = exp(−û)Πₙ.
- Lobatto IIIA–IIIB, 3 stages, order 4: η = 0 makes every L zero (so v = 0)
  and K₁ = Ωₙ; K₂ and K₃ are iterated together, dexp⁻¹ truncated at ad² on
  the semidirect algebra, fiber update exp(−û)Πₙ.

The hand-fused kernels are written here on 3-vectors with Rodrigues'
formula, independently of the library (no prkmk_jax code inside them). They
use the library's default stage criterion (max |ΔK|/(tol + tol|K|) < 1,
tol = max(1e-12, 50 eps), then on while that increment shrinks, and one
evaluation more: `iterate_until="round-off"`) and its starting guess (each stage slope of the
previous step, moved by the change of the field at the step's start), so they
give the same trajectory; the script asserts agreement (1e-10 in float64,
1e-4 in float32) before timing. Both kernels use what η = 0 gives (L ≡ 0,
the first stage explicit), as the generic step does since it reads the
field's dependences from its trace (`prkmk_jax.stage_plan`). The iteration
columns count what each one runs.

Columns: the fused floor, `prkmk_jax.integrate` (lax.scan), diffeqsolve with
`PRKMKSolver` (ConstantStepSize), and for Störmer–Verlet diffrax Tsit5 with
the same step on the embedding ℝ⁹×ℝ³, each vmapped over the trajectories;
then (batch > 1) `integrate` and diffeqsolve once more with the batch in the
state, one solve of all trajectories whose stages iterate until every one
has converged. Runs are interleaved (one of each per
round); times are medians, ratios are medians of per-round ratios; compile
time is reported separately.

    python benchmarks/floor.py --out benchmarks/results
    python benchmarks/floor.py --quick
"""

import functools
import json

import diffrax
import jax
import jax.numpy as jnp

import _common as C
import prkmk_jax as pk

H = 0.01


# --- the hand-fused kernels ----------------------------------------------------------
def _sq(w):
    return jnp.sum(w * w, axis=-1, keepdims=True)


def _trig(w):
    """(sin θ/θ, (1 − cos θ)/θ², (θ − sin θ)/θ³) of θ = |w|, Taylor near 0."""
    t2 = _sq(w)
    small = t2 < 1e-2
    safe = jnp.where(small, 1.0, t2)
    th = jnp.sqrt(safe)
    s, c = jnp.sin(th), jnp.cos(th)
    a = jnp.where(small, 1 - t2 / 6 + t2 * t2 / 120 - t2**3 / 5040, s / th)
    b = jnp.where(small, 0.5 - t2 / 24 + t2 * t2 / 720 - t2**3 / 40320, (1 - c) / safe)
    d = jnp.where(small, 1 / 6 - t2 / 120 + t2 * t2 / 5040 - t2**3 / 362880, (th - s) / (safe * th))
    return a, b, d


def _rotate(w, x):
    """exp(ŵ) x."""
    a, b, _ = _trig(w)
    wx = jnp.cross(w, x)
    return x + a * wx + b * jnp.cross(w, wx)


def _rotation_matrix(w):
    a, b, _ = _trig(w)
    x, y, z = w[0], w[1], w[2]
    wh = jnp.array([[0, -z, y], [z, 0, -x], [-y, x, 0]], w.dtype)
    return jnp.eye(3, dtype=w.dtype) + a * wh + b * (wh @ wh)


def _next_attitude(q, u):
    """Q·exp(û); in float32 followed by the Björck step Q + ½Q(I − QᵀQ), as
    the library's step does in low precision (it keeps QᵀQ = I to rounding)."""
    q = q @ _rotation_matrix(u)
    if jnp.finfo(q.dtype).eps > 1e-10:
        q = 1.5 * q - 0.5 * q @ (q.T @ q)
    return q


def _stage_tolerance(dtype):
    return max(1e-12, 50 * float(jnp.finfo(dtype).eps))


def _iterate(update, start, tol, max_iterations=100):
    """Fixed-point iteration with the library's default stop
    (`iterate_until="round-off"`): past the tolerance it goes on while the
    scaled increment still shrinks, then evaluates once more; returns
    (z, iterations)."""

    def relative_change(new, old):
        return functools.reduce(jnp.maximum, [jnp.max(jnp.abs(o - n) / (tol + tol * jnp.abs(n))) for n, o in zip(new, old)])

    def keep_going(state):
        _, error, previous, n = state
        return ((error >= 1) | ((error > 0) & (error < previous))) & (n < max_iterations)

    def body(state):
        z, error, _, n = state
        new = update(z)
        return new, relative_change(new, z), error, n + 1

    inf = jnp.asarray(jnp.inf, start[0].dtype)
    z, _, _, n = jax.lax.while_loop(keep_going, body, (start, inf, inf, 0))
    return update(z), n + 1


def fused_sv(q, pi, inertia, steps):
    """Störmer–Verlet on T*SO(3) for one trajectory; (Q, Π, iterations)."""
    tol = _stage_tolerance(pi.dtype)

    def step(carry, _):
        q, pi, total, w0_prev, w1_prev = carry
        w0 = pi / inertia
        # The first stage is explicit here: its slope is Ωₙ. The second starts
        # from the previous step's, moved as Ω moved: w1_prev + Ωₙ − Ωₙ₋₁.
        (w1,), n = _iterate(lambda z: (_rotate(-0.5 * H * (w0 + z[0]), pi) / inertia,), (w1_prev + w0 - w0_prev,), tol)
        u = 0.5 * H * (w0 + w1)
        return (_next_attitude(q, u), _rotate(-u, pi), total + n, w0, w1), None

    w = pi / inertia
    (q, pi, total, _, _), _ = jax.lax.scan(step, (q, pi, 0, w, w), None, length=steps)
    return q, pi, total


_LOBATTO_A1 = ((0.0, 0.0, 0.0), (5 / 24, 1 / 3, -1 / 24), (1 / 6, 2 / 3, 1 / 6))
_LOBATTO_B = (1 / 6, 2 / 3, 1 / 6)


def _combine(row, vectors):
    return H * sum(c * x for c, x in zip(row, vectors) if c != 0)


def fused_lobatto(q, pi, inertia, steps):
    """Lobatto IIIA–IIIB 4 on T*SO(3) for one trajectory; (Q, Π, iterations).

    η = 0 here, so every L is 0 and v = 0 (the pairs (u, 0) are a subalgebra
    that dexp⁻¹ keeps); the first row of A¹ is 0, so K₁ = Ωₙ; K₂ and K₃ are
    iterated together."""
    tol = _stage_tolerance(pi.dtype)

    def slope(pi, u):
        # dexp⁻¹_{−U}(x, 0) = x − ½(−u)×x + (1/12)(−u)×((−u)×x) with U = (u, 0).
        x = _rotate(-u, pi) / inertia
        ax = jnp.cross(-u, x)
        return x - 0.5 * ax + jnp.cross(-u, ax) / 12

    def slopes(pi, k1, z):
        ks = (k1, *z)
        return tuple(slope(pi, _combine(_LOBATTO_A1[i], ks)) for i in (1, 2))

    def step(carry, _):
        q, pi, total, w0_prev, z_prev = carry
        w0 = pi / inertia
        # K₂, K₃ start from the previous step's, moved as Ω moved: K + Ωₙ − Ωₙ₋₁.
        z, n = _iterate(lambda z: slopes(pi, w0, z), tuple(k + w0 - w0_prev for k in z_prev), tol)
        u = _combine(_LOBATTO_B, (w0, *z))
        return (_next_attitude(q, u), _rotate(-u, pi), total + n, w0, z), None

    w = pi / inertia
    (q, pi, total, _, _), _ = jax.lax.scan(step, (q, pi, 0, w, (w, w)), None, length=steps)
    return q, pi, total


# --- the runs compared -----------------------------------------------------------------
def _fused_run(kernel, steps):
    return lambda q0, pi0, inertia: kernel(q0, pi0, inertia, steps)


def _times(steps, dtype):
    """t0, t1, dt0 in the state's dtype: diffeqsolve promotes the state to the
    dtype of the times, so Python floats would make a float32 run float64."""
    return jnp.asarray(0.0, dtype), jnp.asarray(steps * H, dtype), jnp.asarray(H, dtype)


def _diffeqsolve_run(method, steps):
    def run(q0, pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(q0), pi0)
        t0, t1, dt = _times(steps, q0.dtype)
        sol = diffrax.diffeqsolve(pk.PRKMKTerm(C.SCENE), pk.PRKMKSolver(method), t0, t1, dt, y0, inertia, max_steps=steps)
        return sol.ys.base.matrix[-1], sol.ys.fiber[-1], jnp.array(-1)

    return run


def _tsit5_run(steps):
    def run(q0, pi0, inertia):
        z0 = jnp.concatenate([q0.reshape(9), pi0])
        t0, t1, dt = _times(steps, q0.dtype)
        sol = diffrax.diffeqsolve(diffrax.ODETerm(C.embedding_rhs), diffrax.Tsit5(), t0, t1, dt, z0, inertia, max_steps=steps)
        q, pi = C.from_vector(sol.ys[-1])
        return q, pi, jnp.array(-1)

    return run


METHODS = {
    "SV": (pk.stormer_verlet, fused_sv),
    "Lobatto4": (pk.lobatto_iiia_iiib4, fused_lobatto),
}


def compare(method_name, batch, dtype, steps, rounds):
    """One row: interleaved timings of floor, integrate, diffeqsolve (and Tsit5)."""
    tableau, kernel = METHODS[method_name]
    method = C.SCENE.method(tableau)
    qs, pis = C.initial_conditions(batch, seed=3)
    args = (jnp.asarray(qs, dtype), jnp.asarray(pis, dtype), jnp.asarray(C.INERTIA, dtype))
    columns = {
        "floor": _fused_run(kernel, steps),
        "integrate": C.integrate_final(method, steps, H),
        "diffeqsolve": _diffeqsolve_run(method, steps),
    }
    if method_name == "SV":
        columns["tsit5"] = _tsit5_run(steps)
    batched = {name: jax.vmap(run, in_axes=(0, 0, None)) for name, run in columns.items()}
    if batch > 1:
        # The same two library paths with the batch in the state (one solve of
        # all trajectories, stages iterated until all have converged) rather
        # than vmapped over single trajectories.
        batched["integrate_state"] = columns["integrate"]
        batched["diffeqsolve_state"] = columns["diffeqsolve"]
    compiled, compile_s, outputs = C.compile_all(batched, *args)
    for name, output in outputs.items():
        if output[0].dtype != dtype:
            raise AssertionError(f"{method_name} {name} ran in {output[0].dtype}, not {jnp.dtype(dtype).name}")
    tolerance = 1e-10 if dtype == jnp.float64 else 1e-4
    for name in ("integrate", "diffeqsolve", "integrate_state", "diffeqsolve_state"):
        if name not in outputs:
            continue
        gap = max(float(jnp.max(jnp.abs(outputs[name][k] - outputs["floor"][k]))) for k in (0, 1))
        if not gap <= tolerance:
            raise AssertionError(f"{method_name} {name} differs from the hand-fused step by {gap:.2e} > {tolerance:.0e}")
    times = C.interleaved_times(compiled, *args, rounds=rounds)
    per_step = C.ns_per_trajectory_step(times, batch, steps)
    ratio = {name: C.median_ratio(times, name, "floor") for name in times}
    row = dict(
        method=method_name,
        dtype=jnp.dtype(dtype).name,
        batch=batch,
        steps=steps,
        ns_per_traj_step=per_step,
        over_floor=ratio,
        compile_s=compile_s,
        iterations_per_step=dict(
            floor=float(jnp.mean(outputs["floor"][2])) / steps,
            integrate=float(jnp.mean(outputs["integrate"][2])) / steps,
        ),
    )
    if "tsit5" in times:
        row["integrate_over_tsit5"] = C.median_ratio(times, "integrate", "tsit5")
    row["diffeqsolve_over_integrate"] = C.median_ratio(times, "diffeqsolve", "integrate")
    if "integrate_state" in times:
        row["iterations_per_step"]["integrate_state"] = float(outputs["integrate_state"][2]) / steps
        row["state_over_vmap"] = C.median_ratio(times, "integrate_state", "integrate")
        row["diffeqsolve_over_integrate_state"] = C.median_ratio(times, "diffeqsolve_state", "integrate_state")
    return row


def _print_row(row):
    ns, ratio, its = row["ns_per_traj_step"], row["over_floor"], row["iterations_per_step"]
    tsit = f"{ns['tsit5']:8.0f} {row['integrate_over_tsit5']:6.2f}" if "tsit5" in ns else f"{'—':>8s} {'—':>6s}"
    print(
        f"{row['method']:9s} {row['dtype']:8s} {row['batch']:6d} {ns['floor']:8.0f} {ns['integrate']:8.0f} {ns['diffeqsolve']:8.0f} "
        f"{ratio['integrate']:6.2f} {ratio['diffeqsolve']:6.2f} {row['diffeqsolve_over_integrate']:6.2f} {tsit} "
        f"{its['floor']:5.2f} {its['integrate']:5.2f}",
        flush=True,
    )
    if "integrate_state" in ns:
        print(
            f"{'':25s}batch in the state: integrate {ns['integrate_state']:8.0f} diffeqsolve {ns['diffeqsolve_state']:8.0f} "
            f"int/fl {ratio['integrate_state']:6.2f} dfx/int {row['diffeqsolve_over_integrate_state']:6.2f} "
            f"state/vmap {row['state_over_vmap']:6.2f} it {its['integrate_state']:5.2f}",
            flush=True,
        )


def main(argv=None):
    args, out = C.cli(__doc__, argv, lambda p: p.add_argument("--rounds", type=int, default=9))
    batches, rounds = ((8,), 2) if args.quick else ((1, 64, 1024, 16384), args.rounds)
    print(
        f"{'method':9s} {'dtype':8s} {'batch':>6s} {'floor':>8s} {'integr.':>8s} {'diffeqs':>8s} "
        f"{'int/fl':>6s} {'dfx/fl':>6s} {'dfx/int':>6s} {'tsit5':>8s} {'int/ts':>6s} {'it fl':>5s} {'it int':>5s}"
    )
    print(f"{'':34s}(ns per trajectory-step)")
    rows = []
    for method_name in METHODS:
        for dtype in (jnp.float64, jnp.float32):
            for batch in batches:
                work = 400_000 if method_name == "SV" else 100_000
                steps = 10 if args.quick else int(max(20, min(400, work // batch)))
                row = compare(method_name, batch, dtype, steps, rounds)
                rows.append(row)
                _print_row(row)
    with open(out / "floor.json", "w") as f:
        json.dump(dict(machine=C.machine(), rounds=rounds, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
