"""Per-step cost of `diffrax.diffeqsolve` + `PRKMKSolver` against the bare
`lax.scan` integrator `prkmk_jax.integrate`, same method, same steps.

Free rigid body on T*SO(3) (Cotangent, body form), Störmer–Verlet, exp
coordinates, h = 0.01, a vmapped batch of initial momenta. Reports compile
time and the median of repeated runs after compilation, side by side.

    python benchmarks/against_scan.py            # batches 1, 64, 4096
    python benchmarks/against_scan.py --quick    # seconds; CI smoke test
"""

import argparse
import json
import platform
import statistics
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import prkmk_jax as pk
from prkmk_jax.scenes import rigid_body as rb


def _time(fn, *args, repeats):
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(*args))  # warm-up
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - start)
    return compile_s, statistics.median(runs)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    batches, steps, repeats = ((1, 8), 20, 2) if args.quick else ((1, 64, 4096), 200, 7)
    h = 0.01
    bundle = pk.Cotangent(pk.SO3)
    field = rb.unreduced_rigid_body(bundle)
    method = pk.PRKMK(bundle, pk.Exp(), pk.stormer_verlet, form="body")
    inertia = jnp.asarray(rb.PAPER_INERTIA)
    g0 = jnp.asarray(rb.random_rotation(rb.PAPER_SEED))

    def scan_run(pi0):
        y0 = pk.BundleElement(pk.SO3(g0), pi0)
        return pk.integrate(method, field, y0, 0.0, h, steps, inertia, save_every=steps).ys

    def diffrax_run(pi0):
        y0 = pk.BundleElement(pk.SO3(g0), pi0)
        return diffrax.diffeqsolve(pk.PRKMKTerm(field), pk.PRKMKSolver(method), 0.0, steps * h, h, y0, inertia, max_steps=steps).ys

    rows = []
    print(f"{'batch':>6s} {'scan compile s':>15s} {'diffrax compile s':>18s} {'scan ns/step':>13s} {'diffrax ns/step':>16s} {'ratio':>6s}")
    for batch in batches:
        pis = jnp.asarray(rb.PAPER_MOMENTUM) * (1 + 0.1 * jnp.asarray(np.random.default_rng(0).normal(size=(batch, 1))))
        scan_c, scan_t = _time(jax.vmap(scan_run), pis, repeats=repeats)
        dfx_c, dfx_t = _time(jax.vmap(diffrax_run), pis, repeats=repeats)
        per = lambda t: t / (steps * batch) * 1e9
        row = dict(batch=batch, steps=steps, scan_compile_s=scan_c, diffrax_compile_s=dfx_c, scan_ns_per_step=per(scan_t), diffrax_ns_per_step=per(dfx_t), ratio=dfx_t / scan_t)
        rows.append(row)
        print(f"{batch:6d} {scan_c:15.2f} {dfx_c:18.2f} {row['scan_ns_per_step']:13.0f} {row['diffrax_ns_per_step']:16.0f} {row['ratio']:6.2f}")
    meta = dict(machine=platform.platform(), devices=[str(d) for d in jax.devices()], jax=jax.__version__, repeats=repeats, rows=rows)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(meta, f, indent=2)


if __name__ == "__main__":
    main()
