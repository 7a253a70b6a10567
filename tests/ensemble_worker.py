"""One process of an ensemble run, started by tests/test_many_processes.py.

    python tests/ensemble_worker.py --processes P --process-id I --port PORT --devices D --out DIR [--fault F]

Runs a batch of free rigid bodies split over P processes with D CPU
devices each (JAX's distributed runtime, gloo collectives on CPU): the
final states by `integrate` and by `diffeqsolve`, the batch's largest
energy error, and a batch loss with its gradient in the inertia. Process 0
writes what `gather` returns, every process what `local_rows` returns.
`--fault` makes process 1 misbehave: `duplicate` passes process 0's rows
(and only the scan's final states are gathered), `drop` passes none,
`crash` exits before the batch is built.
"""

import argparse
import sys
from pathlib import Path

import jax

BATCH = 8
STEPS = 200
DT = 0.01


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--processes", type=int, required=True)
    parser.add_argument("--process-id", type=int, required=True)
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--devices", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--fault", choices=("none", "duplicate", "drop", "crash"), default="none")
    opts = parser.parse_args()

    jax.config.update("jax_num_cpu_devices", opts.devices)
    jax.config.update("jax_enable_x64", True)
    if opts.processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        # Timeouts short enough that a lost process ends the run in seconds.
        jax.distributed.initialize(
            f"localhost:{opts.port}",
            num_processes=opts.processes,
            process_id=opts.process_id,
            initialization_timeout=120,
            heartbeat_timeout_seconds=10,
            shutdown_timeout_seconds=10,
        )

    import diffrax
    import jax.numpy as jnp
    import numpy as np

    import prkmk_jax as pk
    from prkmk_jax.scenes import FreeRigidBody

    body = FreeRigidBody()
    method = body.method(pk.stormer_verlet)
    rng = np.random.default_rng(7)
    attitudes = np.asarray(jax.vmap(lambda w: pk.SO3.exp(w).matrix)(jnp.asarray(rng.normal(size=(BATCH, 3)))))
    moments = rng.normal(size=(BATCH, 3))
    inertia = jnp.array([7 / 8, 5 / 8, 1 / 4])

    per_process = BATCH // opts.processes
    first = opts.process_id * per_process
    if opts.process_id == 1 and opts.fault == "duplicate":
        first = 0
    rows = slice(first, first + (0 if opts.process_id == 1 and opts.fault == "drop" else per_process))
    if opts.process_id == 1 and opts.fault == "crash":
        sys.exit("process 1 stops on purpose")
    y0 = pk.shard_batch(pk.BundleElement(pk.SO3(attitudes[rows]), moments[rows]))

    def last(saved):
        return jax.tree.map(lambda a: a[-1], saved)

    def by_scan(y, i):
        return last(pk.integrate(method, body, y, 0.0, DT, STEPS, i).ys)

    def by_diffrax(y, i):
        return last(diffrax.diffeqsolve(pk.PRKMKTerm(body), pk.PRKMKSolver(method), 0.0, STEPS * DT, DT, y, i).ys)

    def energy_error(y, i):
        final = by_scan(y, i)
        return jnp.abs(body.invariants(final, i)["energy"] / body.invariants(y, i)["energy"] - 1)

    def loss(i, y):
        final = pk.vmap_over_devices(by_scan, in_axes=(0, None))(y, i)
        weights = jnp.arange(1.0, BATCH + 1.0)
        return jnp.mean(weights * final.fiber[:, 0])

    scan_final = jax.jit(pk.vmap_over_devices(by_scan, in_axes=(0, None)))(y0, inertia)
    if opts.fault == "duplicate":  # what is gathered is all the test looks at
        gathered = pk.gather(scan_final)
        if opts.process_id == 0:
            opts.out.mkdir(parents=True, exist_ok=True)
            np.savez(opts.out / "gathered.npz", scan_attitude=gathered.base.matrix, scan_moment=gathered.fiber)
        print(f"process {opts.process_id} done", flush=True)
        return
    diffrax_final = jax.jit(pk.vmap_over_devices(by_diffrax, in_axes=(0, None)))(y0, inertia)
    worst_energy = jax.jit(lambda y, i: jnp.max(pk.vmap_over_devices(energy_error, in_axes=(0, None))(y, i)))(y0, inertia)
    value, grad = jax.jit(jax.value_and_grad(loss))(inertia, y0)

    everything = pk.gather({"scan": scan_final, "diffrax": diffrax_final})
    mine = pk.local_rows({"scan": scan_final, "y0": y0, "worst_energy": worst_energy})
    opts.out.mkdir(parents=True, exist_ok=True)
    np.savez(
        opts.out / f"local_{opts.process_id}.npz",
        scan_attitude=mine["scan"].base.matrix,
        scan_moment=mine["scan"].fiber,
        y0_moment=mine["y0"].fiber,
        worst_energy=mine["worst_energy"],
    )
    if opts.process_id == 0:
        np.savez(
            opts.out / "gathered.npz",
            scan_attitude=everything["scan"].base.matrix,
            scan_moment=everything["scan"].fiber,
            diffrax_attitude=everything["diffrax"].base.matrix,
            diffrax_moment=everything["diffrax"].fiber,
            worst_energy=np.asarray(worst_energy.addressable_data(0)),
            loss=np.asarray(value.addressable_data(0)),
            grad=np.asarray(grad.addressable_data(0)),
            all_moments=moments,
            all_attitudes=attitudes,
        )
    print(f"process {opts.process_id} done", flush=True)


if __name__ == "__main__":
    main()
