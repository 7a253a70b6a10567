"""Ensemble throughput against the number of devices and processes.

A batch of free rigid bodies on T*SO(3) (Störmer–Verlet, body form, h = 0.01,
random attitudes and momenta) split over P processes with D CPU devices
each (`jax.distributed` on localhost, gloo collectives): each process
passes its rows to `shard_batch` and runs

- the forward ensemble, `jit(vmap_over_devices(run))`, the final states
  left where they were computed;
- `value_and_grad` of a batch loss (a weighted mean of the final momenta)
  with respect to the inertia, summed across devices and processes.

Reported per configuration: compile times; the median wall time of each
program over interleaved rounds; throughput in trajectory-steps per second;
the efficiency per device, throughput per device over that of one process
with one device; and each process's peak resident memory. Forced CPU
devices share the machine's cores, so beyond the number of cores the
devices compete for them.

Also, in one process with all the devices: the same ensemble by
`jit(vmap(run))` of the sharded batch, where each implicit stage loop's
stopping test spans the whole batch (an all-reduce across the devices at
every iteration), over `vmap_over_devices`, interleaved.

    python benchmarks/ensembles.py
    python benchmarks/ensembles.py --quick
"""

import json
import os
import resource
import socket
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import prkmk_jax as pk

H = 0.01


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3  # kilobytes on Linux


def worker(processes, devices, process_id, port, batch, steps, rounds, compare_routes):
    """One process of a configuration (the child's job): prints its results as JSON."""
    jax.config.update("jax_num_cpu_devices", devices)
    jax.config.update("jax_enable_x64", True)
    if processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        timeouts = dict(initialization_timeout=120, heartbeat_timeout_seconds=30, shutdown_timeout_seconds=30)
        jax.distributed.initialize(f"localhost:{port}", num_processes=processes, process_id=process_id, **timeouts)
    method = C.SCENE.method(pk.stormer_verlet)
    qs, pis = C.initial_conditions(batch, seed=11)
    rows = slice(process_id * batch // processes, (process_id + 1) * batch // processes)
    y0 = pk.shard_batch(pk.BundleElement(pk.SO3(qs[rows]), pis[rows]))
    inertia = jnp.asarray(C.INERTIA)

    def run(y, i):
        final = pk.integrate(method, C.SCENE, y, 0.0, H, steps, i, save_every=steps).ys
        return jax.tree.map(lambda a: a[-1], final)

    ensemble = pk.vmap_over_devices(run, in_axes=(0, None))
    weights = jnp.linspace(1.0, 2.0, 3)

    def loss(i, y):
        return jnp.mean(ensemble(y, i).fiber @ weights)

    fns = {"forward": ensemble, "value_and_grad": lambda y, i: jax.value_and_grad(loss)(i, y)}
    if compare_routes:
        fns["forward, jit(vmap)"] = jax.vmap(run, in_axes=(0, None))
    compiled, compile_s = {}, {}
    for name, fn in fns.items():
        compiled[name], compile_s[name] = C.compile_fn(fn, y0, inertia)
    for fn in compiled.values():  # a first run of each, outside the rounds
        jax.block_until_ready(fn(y0, inertia))
    times = C.interleaved_times(compiled, y0, inertia, rounds=rounds)
    return dict(
        process_id=process_id,
        compile_s=compile_s,
        median_s={name: float(np.median(ts)) for name, ts in times.items()},
        times_s=times,
        peak_rss_mb=_peak_rss_mb(),
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def configuration(processes, devices, batch, steps, rounds, compare_routes=False):
    """Runs one configuration's processes; returns their results, process 0 first."""
    port = _free_port()
    started = []
    for process_id in range(processes):
        case = dict(processes=processes, devices=devices, process_id=process_id, port=port, batch=batch, steps=steps)
        case = json.dumps(dict(case, rounds=rounds, compare_routes=compare_routes))
        command = [sys.executable, __file__, "--worker", case]
        started.append(subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    results = []
    for proc in started:
        stdout, stderr = proc.communicate(timeout=1800)
        if proc.returncode != 0:
            for p in started:
                p.kill()
            raise RuntimeError(f"a worker of {processes}×{devices} failed:\n{stderr[-3000:]}")
        results.append(json.loads(stdout.strip().splitlines()[-1]))
    return results


def compared(row) -> bool:
    return "jit_vmap_over_vmap_over_devices" in row


def ensembles_table(results: Path) -> str:
    """`ensembles.py`: ensemble throughput, efficiency per device and memory
    per process against the number of processes and devices per process."""
    data = C.results_file(results, "ensembles.json")
    rows = [
        [
            str(r["processes"]),
            str(r["devices_per_process"]),
            f"{r['median_s']['forward']:.3f}",
            f"{r['median_s']['value_and_grad']:.3f}",
            f"{r['throughput']['forward'] / 1e6:.2f}",
            f"{r['throughput']['value_and_grad'] / 1e6:.2f}",
            f"{r['efficiency_per_device']['forward']:.2f}",
            f"{r['efficiency_per_device']['value_and_grad']:.2f}",
            f"{r['compile_s']['forward']:.1f} / {r['compile_s']['value_and_grad']:.1f}",
            " / ".join(f"{m:.0f}" for m in r["peak_rss_mb"]),
        ]
        for r in data["rows"]
    ]
    headers = ["processes", "devices each", "forward, s", "value and gradient, s", "forward, 10⁶ trajectory-steps/s"]
    headers += ["gradient, 10⁶ trajectory-steps/s", "efficiency per device, forward", "efficiency per device, gradient"]
    headers += ["compile forward / gradient, s", "peak RSS per process, MB"]
    compared = [r for r in data["rows"] if "jit_vmap_over_vmap_over_devices" in r]
    routes = "".join(
        f" With {r['devices']} devices in one process, `jit(vmap(...))` of the sharded batch took "
        f"{r['jit_vmap_over_vmap_over_devices']:.1f}× the time of `vmap_over_devices`."
        for r in compared
    )
    return (
        C.measured_on(data)
        + f" Batch {data['batch']} × {data['steps']} steps, h = {data['h']}, median of {data['rounds']} rounds."
        + routes
        + "\n\n"
        + C.table(headers, rows)
    )


def tables(results: Path) -> dict[str, str]:
    """This script's tables, made from its results in `results` (`write_tables.py`)."""
    return {"ensembles": ensembles_table(results)}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        print(json.dumps(worker(**json.loads(argv[1]))))
        return None  # a worker: its parent writes the results
    args, out = C.cli(__doc__, argv)
    if args.quick:
        layouts, batch, steps, rounds = ((2, 1),), 8, 20, 2  # two processes: the code of every layout
    else:
        layouts, batch, steps, rounds = ((1, 1), (1, 2), (1, 4), (2, 1), (2, 2), (4, 1)), 256, 2000, 7
    rows = []
    print(f"{'processes':>9s} {'devices':>7s} {'forward s':>9s} {'grad s':>8s} {'Msteps/s':>9s} {'eff/device':>10s} {'RSS MB':>14s}")
    for processes, devices in layouts:
        compare = (processes, devices) == (1, max((d for p, d in layouts if p == 1), default=0)) and devices > 1
        results = configuration(processes, devices, batch, steps, rounds, compare_routes=compare)
        first = results[0]
        row = dict(
            processes=processes,
            devices_per_process=devices,
            devices=processes * devices,
            compile_s=first["compile_s"],
            median_s=first["median_s"],
            throughput={name: batch * steps / s for name, s in first["median_s"].items()},
            peak_rss_mb=[r["peak_rss_mb"] for r in results],
        )
        if compare:
            times = first["times_s"]
            row["jit_vmap_over_vmap_over_devices"] = C.median_ratio(times, "forward, jit(vmap)", "forward")
        rows.append(row)
    base = rows[0]["throughput"]
    for row in rows:
        row["efficiency_per_device"] = {name: row["throughput"][name] / row["devices"] / base[name] for name in base}
        print(
            f"{row['processes']:9d} {row['devices_per_process']:7d} {row['median_s']['forward']:9.3f} "
            f"{row['median_s']['value_and_grad']:8.3f} {row['throughput']['forward'] / 1e6:9.2f} "
            f"{row['efficiency_per_device']['forward']:10.2f} {'/'.join(f'{m:.0f}' for m in row['peak_rss_mb']):>14s}"
            + (f"   jit(vmap) / vmap_over_devices {row['jit_vmap_over_vmap_over_devices']:.1f}" if compared(row) else ""),
            flush=True,
        )
    with open(out / "ensembles.json", "w") as f:
        json.dump(dict(machine=C.machine(), cores=os.cpu_count(), batch=batch, steps=steps, h=H, rounds=rounds, rows=rows), f, indent=1)
    return out


if __name__ == "__main__":
    out = main()
    if out is not None:
        print("\n\n".join(tables(out).values()))
