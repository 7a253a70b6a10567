"""XLA's two CPU code generators on this library's programs: compile and run time.

XLA_FLAGS=--xla_cpu_use_fusion_emitters=false makes XLA's CPU backend emit
each fusion with its older code generator instead of the fusion emitters.
XLA reads the flag once per process, so every round starts two child
processes of this script, one with XLA_FLAGS empty (XLA's default) and one
with the flag, in alternation. Each child compiles the same programs
(`jax.jit(...).lower(...).compile()`, timed) and runs each of them
`--repeats` times after a warm-up (median). Reported per program: the median
over rounds of each setting's compile and run time, the median of the
per-round ratios flag/default, the largest difference between the two
settings' states and gradients relative to their size, and the implicit
iterations each setting's `integrate` runs took in all. The tests compile with the flag
(tests/conftest.py).

Programs: the free rigid body on T*SO(3) (body form, h = 0.01, random
attitudes and momenta), Störmer–Verlet and Lobatto IIIA–IIIB 4 through
`integrate` (lax.scan) and `diffeqsolve`, the gradient of a loss of the final
states in the inertia through both (through the stored steps, and with
`ReversibleGradient` and `ReversibleAdjoint` beside the forward runs they
are timed against, also for the Strang splitting), and diffrax Tsit5 on
the embedding ℝ⁹×ℝ³ as the peer.

    python benchmarks/xla_codegen.py --out benchmarks/results
    python benchmarks/xla_codegen.py --quick
"""

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk

H = 0.01
FLAG = "--xla_cpu_use_fusion_emitters=false"
SETTINGS = {"default": "", "no fusion emitters": FLAG}


def _method(name):
    """The free body's method: the Strang splitting, or SV etc. by tableau name."""
    return C.SCENE.splitting() if name == "splitting" else C.SCENE.method(getattr(pk, name))


def _integrate(name, steps, gradient=None):
    """(Q₀, Π₀, inertia) -> (Q, Π, implicit iterations) through `integrate`."""
    return C.integrate_final(_method(name), steps, H, gradient)


def _diffeqsolve(name, steps, adjoint=None):
    """(Q₀, Π₀, inertia) -> (Q, Π) through `diffeqsolve`, differentiated by
    `adjoint` (diffrax's default `RecursiveCheckpointAdjoint` if None)."""
    solver = pk.PRKMKSolver(_method(name))
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint

    def run(q0, pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(q0), pi0)
        t0, t1, dt = (jnp.asarray(x, q0.dtype) for x in (0.0, steps * H, H))
        sol = diffrax.diffeqsolve(pk.PRKMKTerm(C.SCENE), solver, t0, t1, dt, y0, inertia, max_steps=steps, adjoint=adjoint)
        return sol.ys.base.matrix[-1], sol.ys.fiber[-1]

    return run


def _tsit5(steps):
    def run(q0, pi0, inertia):
        z0 = jnp.concatenate([q0.reshape(9), pi0])
        sol = diffrax.diffeqsolve(diffrax.ODETerm(C.embedding_rhs), diffrax.Tsit5(), 0.0, steps * H, H, z0, inertia, max_steps=steps)
        return C.from_vector(sol.ys[-1])

    return run


def _batched(run):
    return jax.vmap(run, in_axes=(0, 0, None))


def _value_and_grad(run):
    def loss(qs, pis, inertia):
        q, pi = _batched(run)(qs, pis, inertia)[:2]
        return jnp.sum(q[..., 0, :] ** 2 * jnp.arange(3)) + jnp.sum(pi**2)

    return jax.value_and_grad(loss, argnums=2)


def programs(quick):
    """name -> (function of (qs, pis, inertia), batch, steps, dtype)."""
    if quick:
        # One program: the script measures and compares every program alike.
        return {"SV diffeqsolve": (_batched(_diffeqsolve("stormer_verlet", 10)), 8, 10, jnp.float64)}
    found = {
        "SV integrate": (_batched(_integrate("stormer_verlet", 400)), 1, 400, jnp.float64),
        "SV integrate, batch 1024": (_batched(_integrate("stormer_verlet", 200)), 1024, 200, jnp.float64),
        "SV integrate, batch 1024, float32": (_batched(_integrate("stormer_verlet", 200)), 1024, 200, jnp.float32),
        "SV integrate, batch 16384": (_batched(_integrate("stormer_verlet", 20)), 16384, 20, jnp.float64),
        "SV diffeqsolve, batch 1024": (_batched(_diffeqsolve("stormer_verlet", 200)), 1024, 200, jnp.float64),
        "Lobatto 4 integrate, batch 64": (_batched(_integrate("lobatto_iiia_iiib4", 200)), 64, 200, jnp.float64),
        "Lobatto 4 diffeqsolve, batch 64": (_batched(_diffeqsolve("lobatto_iiia_iiib4", 200)), 64, 200, jnp.float64),
        "SV integrate, value_and_grad, batch 64": (_value_and_grad(_integrate("stormer_verlet", 200)), 64, 200, jnp.float64),
        "SV diffeqsolve, value_and_grad, batch 64": (_value_and_grad(_diffeqsolve("stormer_verlet", 200)), 64, 200, jnp.float64),
    }
    # The reversible gradients beside the forward runs they are timed against.
    for name, fn in (
        ("SV integrate, batch 64", _batched(_integrate("stormer_verlet", 200))),
        ("SV integrate, ReversibleGradient, batch 64", _value_and_grad(_integrate("stormer_verlet", 200, pk.ReversibleGradient(None)))),
        ("SV diffeqsolve, batch 64", _batched(_diffeqsolve("stormer_verlet", 200))),
        ("SV diffeqsolve, ReversibleAdjoint, batch 64", _value_and_grad(_diffeqsolve("stormer_verlet", 200, pk.ReversibleAdjoint(None)))),
        ("splitting integrate, batch 64", _batched(_integrate("splitting", 200))),
        ("splitting integrate, ReversibleGradient, batch 64", _value_and_grad(_integrate("splitting", 200, pk.ReversibleGradient(None)))),
    ):
        found[name] = (fn, 64, 200, jnp.float64)
    found["Tsit5 (embedding), batch 1024"] = (_batched(_tsit5(200)), 1024, 200, jnp.float64)
    found["Tsit5 (embedding), batch 16384"] = (_batched(_tsit5(20)), 16384, 20, jnp.float64)
    return found


def child(quick, repeats, out):
    """One process's measurements: compile and median run time per program,
    and the outputs (to compare between settings)."""
    jax.config.update("jax_enable_x64", True)
    rows, outputs = {}, {}
    for name, (fn, batch, steps, dtype) in programs(quick).items():
        qs, pis = C.initial_conditions(batch, seed=3)
        args = (jnp.asarray(qs, dtype), jnp.asarray(pis, dtype), jnp.asarray(C.INERTIA, dtype))
        compiled, compile_s = C.compile_fn(fn, *args)
        run_s, value = C.median_time(compiled, *args, repeats=repeats)
        rows[name] = dict(batch=batch, steps=steps, dtype=jnp.dtype(dtype).name, compile_s=compile_s, run_s=run_s)
        for k, leaf in enumerate(jax.tree.leaves(value)):
            outputs[f"{name}/{k}"] = np.asarray(leaf)
    np.savez(out.with_suffix(".npz"), **outputs)
    out.write_text(json.dumps(rows))


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        child(argv[1] == "quick", int(argv[2]), Path(argv[3]))
        return

    def add_arguments(parser):
        parser.add_argument("--rounds", type=int, default=3)
        parser.add_argument("--repeats", type=int, default=7)

    args, out = C.cli(__doc__, argv, add_arguments)
    rounds = 1 if args.quick else args.rounds
    scratch = Path(tempfile.mkdtemp(prefix="prkmk_xla_codegen_"))
    measured = {setting: [] for setting in SETTINGS}
    process_s = {setting: [] for setting in SETTINGS}
    for r in range(rounds):
        for setting, flags in SETTINGS.items():
            path = scratch / f"{r}-{setting.replace(' ', '_')}.json"
            env = dict(os.environ, XLA_FLAGS=flags)
            start = time.perf_counter()
            command = [sys.executable, __file__, "--child", "quick" if args.quick else "full", str(args.repeats), str(path)]
            subprocess.run(command, check=True, env=env)
            process_s[setting].append(time.perf_counter() - start)
            measured[setting].append(json.loads(path.read_text()))
            print(f"round {r + 1}/{rounds}, {setting}: {process_s[setting][-1]:.1f} s", flush=True)
    names = list(measured["default"][0])
    default_out, flag_out = (np.load(scratch / f"0-{s.replace(' ', '_')}.npz") for s in SETTINGS)
    rows = []
    for name in names:
        per = {s: [m[name] for m in measured[s]] for s in SETTINGS}
        row = dict(name=name, **{k: per["default"][0][k] for k in ("batch", "steps", "dtype")})
        for key in ("compile_s", "run_s"):
            row[key] = {s: statistics.median(x[key] for x in per[s]) for s in SETTINGS}
            row[f"{key}_ratio"] = statistics.median(f[key] / d[key] for f, d in zip(per["no fusion emitters"], per["default"]))
        keys = [k for k in default_out.files if k.startswith(name + "/")]
        # States and gradients: relative gap; integer outputs are implicit-iteration totals, compared as counts.
        states = [k for k in keys if np.issubdtype(default_out[k].dtype, np.inexact)]
        counts = [k for k in keys if k not in states]
        row["relative_gap"] = max(float(np.max(np.abs(default_out[k] - flag_out[k])) / np.max(np.abs(default_out[k]))) for k in states)
        row["iterations"] = {s: [int(np.sum(o[k])) for k in counts] for s, o in zip(SETTINGS, (default_out, flag_out))}
        rows.append(row)
    columns = [
        "program",
        "compile default",
        "compile flag",
        "ratio",
        "run default",
        "run flag",
        "ratio",
        "relative gap",
        "iterations default / flag",
    ]
    print("\n| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for row in rows:
        c, r, its = row["compile_s"], row["run_s"], row["iterations"]
        iterations = " ".join(f"{d} / {f}" for d, f in zip(its["default"], its["no fusion emitters"])) or "—"
        print(
            f"| {row['name']} | {c['default']:.2f} s | {c['no fusion emitters']:.2f} s | {row['compile_s_ratio']:.2f} "
            f"| {r['default'] * 1e3:.3g} ms | {r['no fusion emitters'] * 1e3:.3g} ms | {row['run_s_ratio']:.2f} "
            f"| {row['relative_gap']:.0e} | {iterations} |"
        )
    total = {s: statistics.median(process_s[s]) for s in SETTINGS}
    print(f"\nwhole child process (import, compile, run): default {total['default']:.1f} s, flag {total['no fusion emitters']:.1f} s")
    with open(out / "xla_codegen.json", "w") as f:
        json.dump(dict(machine=C.machine(), flag=FLAG, rounds=rounds, repeats=args.repeats, rows=rows, process_s=process_s), f, indent=1)


if __name__ == "__main__":
    main()
