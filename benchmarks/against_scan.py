"""Per-step cost of `diffrax.diffeqsolve` + `PRKMKSolver` against the bare
`lax.scan` integrator `prkmk_jax.integrate`, same method, same steps.

Free rigid body on T*SO(3) (Cotangent, body form), Störmer–Verlet, exp
coordinates, h = 0.01, a vmapped batch of initial momenta. A third column is
a control: the same step in a bare `lax.while_loop` (diffrax's loop is a
while loop, because its steps may be adaptive), which separates the cost of
the loop construct from the cost of diffrax's bookkeeping.

Compile time is reported separately; run times are medians after
compilation. The runs of the three variants are interleaved (scan, diffrax,
while, scan, …) so that all see the same machine load, and the ratios are
medians of the per-round ratios.

    python benchmarks/against_scan.py            # batches 1, 64, 4096
    python benchmarks/against_scan.py --quick    # seconds; CI smoke test
"""

import argparse
import json
import platform
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import prkmk_jax as pk
from _common import compile_fn, interleaved_times, median_ratio, ns_per_trajectory_step
from prkmk_jax.scenes import FreeRigidBody
from prkmk_jax.scenes import rigid_body as rb


def _compile(fn, *args):
    compiled, compile_s = compile_fn(fn, *args)
    jax.block_until_ready(compiled(*args))  # warm-up
    return compiled, compile_s


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--out", help="folder for against_scan.json")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    batches, steps, repeats = ((1, 8), 20, 2) if args.quick else ((1, 64, 4096), 200, args.repeats)
    h = 0.01
    field = FreeRigidBody()
    method = field.method(pk.stormer_verlet)
    inertia = jnp.asarray(rb.PAPER_INERTIA)
    g0 = jnp.asarray(rb.random_rotation(rb.PAPER_SEED))

    def initial(pi0):
        return pk.BundleElement(pk.SO3(g0), pi0)

    def scan_run(pi0):
        return pk.integrate(method, field, initial(pi0), 0.0, h, steps, inertia, save_every=steps).ys

    def diffrax_run(pi0):
        term, solver = pk.PRKMKTerm(field), pk.PRKMKSolver(method)
        return diffrax.diffeqsolve(term, solver, 0.0, steps * h, h, initial(pi0), inertia, max_steps=steps).ys

    def while_run(pi0):
        def body(carry):
            n, y = carry
            return n + 1, method.step(field, n * h, y, h, inertia).y

        return jax.lax.while_loop(lambda carry: carry[0] < steps, body, (0, initial(pi0)))[1]

    rows = []
    header = (
        "batch",
        "compile s scan/diffrax",
        "ns/step scan",
        "diffrax",
        "while",
        "diffrax/scan",
        "while/scan",
        "diffrax/while",
    )
    print(
        f"{header[0]:>6s} {header[1]:>23s} {header[2]:>13s} {header[3]:>8s} "
        f"{header[4]:>8s} {header[5]:>13s} {header[6]:>11s} {header[7]:>14s}"
    )
    for batch in batches:
        pis = jnp.asarray(rb.PAPER_MOMENTUM) * (1 + 0.1 * jnp.asarray(np.random.default_rng(0).normal(size=(batch, 1))))
        compiled = [_compile(jax.vmap(fn), pis) for fn in (scan_run, diffrax_run, while_run)]
        times = interleaved_times(dict(enumerate(c for c, _ in compiled)), pis, rounds=repeats)
        per = ns_per_trajectory_step(times, batch, steps)

        row = dict(
            batch=batch,
            steps=steps,
            scan_compile_s=compiled[0][1],
            diffrax_compile_s=compiled[1][1],
            scan_ns_per_step=per[0],
            diffrax_ns_per_step=per[1],
            while_ns_per_step=per[2],
            diffrax_over_scan=median_ratio(times, 1, 0),
            while_over_scan=median_ratio(times, 2, 0),
            diffrax_over_while=median_ratio(times, 1, 2),
        )
        rows.append(row)
        print(
            f"{batch:6d} {row['scan_compile_s']:11.2f}/{row['diffrax_compile_s']:<11.2f} {row['scan_ns_per_step']:13.0f} "
            f"{row['diffrax_ns_per_step']:8.0f} {row['while_ns_per_step']:8.0f} {row['diffrax_over_scan']:13.2f} "
            f"{row['while_over_scan']:11.2f} {row['diffrax_over_while']:14.2f}",
            flush=True,
        )
    meta = dict(
        machine=platform.platform(),
        devices=[str(d) for d in jax.devices()],
        jax=jax.__version__,
        repeats=repeats,
        rows=rows,
    )
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        with open(Path(args.out) / "against_scan.json", "w") as f:
            json.dump(meta, f, indent=2)


if __name__ == "__main__":
    main()
