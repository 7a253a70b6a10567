"""Throughput, compile time and gradient cost.

1. Trajectory-steps per second against batch size, free rigid body, h = 0.01:
   PRKMK Störmer–Verlet (T*SO(3), body form, exp) through `lax.scan`
   (`prkmk_jax.integrate`) and through `diffeqsolve`, in float64 and
   float32, and diffrax Tsit5 with constant steps on the embedding ℝ⁹×ℝ³.
   The step count per run shrinks with the batch so every run does a
   similar amount of work; the four run in alternation (7 rounds; medians,
   and the median per-round ratio to Tsit5); also reported: implicit
   iterations per step.
2. Compile time (lower + compile of a fresh jit) against the number of
   stages: symplectic Euler (1), Störmer–Verlet (2), Lobatto IIIA–IIIB (3).
3. Forward against forward + backward: `jax.grad` of a loss of the final
   momenta with respect to the inertia, batch 64, 200 steps, through the
   scan integrator and through diffeqsolve (RecursiveCheckpointAdjoint);
   forward and gradient alternate, 9 rounds, and the ratio is the median
   of the per-round ratios.

    python benchmarks/throughput.py --out benchmarks/results
    python benchmarks/throughput.py --quick
"""

import functools
import json
import statistics

import diffrax
import jax
import jax.numpy as jnp

import _common as C
import prkmk_jax as pk

H = 0.01


def _scan(method, steps):
    final = C.integrate_final(method, steps, H)

    def run(q0, pi0, inertia):
        _, pi, iterations = final(q0, pi0, inertia)
        return pi, iterations

    return run


def _diffeqsolve(method, steps, adjoint=None):
    def run(q0, pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(q0), pi0)
        sol = diffrax.diffeqsolve(
            pk.PRKMKTerm(C.SCENE),
            pk.PRKMKSolver(method),
            0.0,
            steps * H,
            H,
            y0,
            inertia,
            max_steps=steps,
            adjoint=diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
        )
        return sol.ys.fiber[-1], jnp.nan

    return run


def _tsit5(steps):
    def run(q0, pi0, inertia):
        z0 = jnp.concatenate([q0.reshape(9), pi0])
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(C.embedding_rhs),
            diffrax.Tsit5(),
            0.0,
            steps * H,
            H,
            z0,
            inertia,
            max_steps=steps,
        )
        return sol.ys[-1, 9:], jnp.nan

    return run


def throughput(quick, rounds):
    batches = [8] if quick else [1, 64, 1024, 16384, 65536]
    method64 = C.SCENE.method(pk.stormer_verlet)
    rows = []
    for batch in batches:
        steps = 10 if quick else int(min(400, max(10, 2_000_000 // (batch * 10))))
        qs, pis = C.initial_conditions(batch, seed=3)
        columns = {
            "PRKMK SV scan": (jnp.float64, _scan(method64, steps)),
            "PRKMK SV scan float32": (jnp.float32, _scan(method64, steps)),
            "PRKMK SV diffeqsolve": (jnp.float64, _diffeqsolve(method64, steps)),
            "diffrax Tsit5 (embedding)": (jnp.float64, _tsit5(steps)),
        }
        compiled, compile_s, iterations, args_of = {}, {}, {}, {}
        for name, (dtype, run) in columns.items():
            args_of[name] = (jnp.asarray(qs, dtype), jnp.asarray(pis, dtype), jnp.asarray(C.INERTIA, dtype))
            compiled[name], compile_s[name] = C.compile_fn(jax.vmap(run, in_axes=(0, 0, None)), *args_of[name])
            iterations[name] = jax.block_until_ready(compiled[name](*args_of[name]))[1]
        # The four columns run in alternation, one of each per round, so that
        # a slow spell of the machine (or of this process) hits all of them;
        # each is bound to its own arguments (the float32 column has its own).
        bound = {name: functools.partial(fn, *args_of[name]) for name, fn in compiled.items()}
        times = C.interleaved_times(bound, rounds=rounds)
        for name in columns:
            wall = statistics.median(times[name])
            rate = batch * steps / wall
            iters = iterations[name]
            iters_per_step = float(jnp.mean(iters)) / steps if jnp.all(jnp.isfinite(iters)) else float("nan")
            rows.append(
                dict(
                    batch=batch,
                    method=name,
                    steps=steps,
                    wall_s=wall,
                    compile_s=compile_s[name],
                    traj_steps_per_s=rate,
                    iterations_per_step=iters_per_step,
                    over_tsit5=C.median_ratio(times, name, "diffrax Tsit5 (embedding)"),
                )
            )
            print(
                f"batch {batch:6d} {name:28s} steps={steps:4d} wall={wall:8.4f}s  {rate:10.3e} "
                f"traj-steps/s  time / Tsit5 {rows[-1]['over_tsit5']:5.2f}  compile {compile_s[name]:5.2f}s  "
                f"iterations/step {iters_per_step:.1f}",
                flush=True,
            )
    return rows


def compile_vs_stages(quick):
    rows = []
    qs, pis = C.initial_conditions(8, seed=3)
    args = (jnp.asarray(qs), jnp.asarray(pis), jnp.asarray(C.INERTIA))
    tableaus = (("SE", pk.symplectic_euler), ("SV", pk.stormer_verlet), ("Lobatto4", pk.lobatto_iiia_iiib4))
    for name, tab in tableaus[1:2] if quick else tableaus:
        method = C.SCENE.method(tab)
        for path, make in (("scan", _scan), ("diffeqsolve", _diffeqsolve)):
            _, compile_s = C.compile_fn(jax.vmap(make(method, 50), in_axes=(0, 0, None)), *args)
            rows.append(dict(tableau=name, stages=tab.num_stages, path=path, compile_s=compile_s))
            print(
                f"{name:9s} stages={tab.num_stages}  {path:12s} compile {compile_s:5.2f}s",
                flush=True,
            )
    return rows


def gradient_cost(quick, rounds):
    batch, steps = (8, 20) if quick else (64, 200)
    method = C.SCENE.method(pk.stormer_verlet)
    qs, pis = C.initial_conditions(batch, seed=4)
    qs, pis = jnp.asarray(qs), jnp.asarray(pis)
    target = jnp.asarray(C.MOMENTUM)
    rows = []
    # diffrax's default adjoint keeps O(√steps) checkpoints and recomputes
    # steps in the backward pass; with one checkpoint per step it recomputes
    # each step once, as `integrate` does.
    paths = (
        ("scan", _scan(method, steps)),
        ("diffeqsolve", _diffeqsolve(method, steps)),
        ("diffeqsolve-ckpt", _diffeqsolve(method, steps, diffrax.RecursiveCheckpointAdjoint(checkpoints=steps))),
    )
    for path, one in paths:
        run = jax.vmap(one, in_axes=(0, 0, None))

        def loss(inertia, run=run):
            return jnp.mean(jnp.sum((run(qs, pis, inertia)[0] - target) ** 2, axis=-1))

        inertia = jnp.asarray(C.INERTIA)
        fwd, fwd_c = C.compile_fn(loss, inertia)
        bwd, bwd_c = C.compile_fn(jax.value_and_grad(loss), inertia)
        # Forward and gradient alternate, and the ratio is the median of the
        # per-round ratios, so that a slow spell of the machine hits both.
        for fn in (fwd, bwd):
            jax.block_until_ready(fn(inertia))
        times = C.interleaved_times({"forward": fwd, "gradient": bwd}, inertia, rounds=rounds)
        fwd_t, bwd_t = statistics.median(times["forward"]), statistics.median(times["gradient"])
        ratio = C.median_ratio(times, "gradient", "forward")
        rows.append(
            dict(
                path=path,
                batch=batch,
                steps=steps,
                forward_s=fwd_t,
                forward_backward_s=bwd_t,
                ratio=ratio,
                forward_compile_s=fwd_c,
                gradient_compile_s=bwd_c,
            )
        )
        print(
            f"{path:16s} forward {fwd_t:8.4f}s  forward+backward {bwd_t:8.4f}s  ratio {ratio:5.2f}  compile {fwd_c:5.2f}s / {bwd_c:5.2f}s",
            flush=True,
        )
    return rows


def main(argv=None):
    args, out = C.cli(
        __doc__,
        argv,
        lambda p: p.add_argument("--parts", default="throughput,compile,gradient"),
    )
    rounds = 1 if args.quick else 7
    result = dict(machine=C.machine())
    parts = args.parts.split(",")
    if "throughput" in parts:
        result["throughput"] = throughput(args.quick, rounds)
    if "compile" in parts:
        result["compile_vs_stages"] = compile_vs_stages(args.quick)
    if "gradient" in parts:
        result["gradient"] = gradient_cost(args.quick, 2 if args.quick else 9)
    with open(out / "throughput.json", "w") as f:
        json.dump(result, f, indent=1)
    if "throughput" in result:
        plot(result["throughput"], out / "throughput.png")


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for name in dict.fromkeys(r["method"] for r in rows):
        pts = [r for r in rows if r["method"] == name]
        ax.loglog(
            [p["batch"] for p in pts],
            [p["traj_steps_per_s"] for p in pts],
            "-o",
            label=name,
        )
    ax.axhline(3e7, color="k", ls=":", label="target 3·10⁷ (batch ≥ 10⁴)")
    ax.set_xlabel("batch size (trajectories)")
    ax.set_ylabel("trajectory-steps per second")
    ax.set_title("Free rigid body, h = 0.01, CPU")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
