"""The signed energy drift a step of Störmer–Verlet at the round-off limit:
what is left of a bias once the stages are solved to round-off and the
updates summed with compensation (`round_off.py` fits how the errors grow;
this script looks at their sign).

The free body on T*SO(3) (body form, the paper's inertia), SV with the
exponential and with the Cayley map, the defaults (`iterate_until=
"round-off"`, `compensated_sum=True`). A batch of `--batch` random initial
states (`round_off.initial_states`, one set per seed), `--steps` steps of
size h, the relative energy error H/H₀ − 1 saved 200 times. Each
trajectory's drift is the least-squares slope of its signed error against
the step number.

- Mean over the batch and its standard error, for several sets of initial
  states at h = 0.1: rounding that is unbiased gives means of either sign,
  a bias (of the rounding or of the method) means of one sign in every set.
- The same for |Π|², which the rotation of Π keeps in exact arithmetic:
  whether a drift moves |Π| or the energy at fixed |Π|.
- How much of each trajectory's drift its initial state sets: the first set
  run again from momenta scaled by 1 + ε, a move of one or two ulps (from
  the first step on, the rounding is a different one), at several h. The
  two runs' drifts per trajectory are correlated (near 0 where rounding
  alone makes them, near 1 where the initial state does: the method's
  truncation, or a rounding that repeats along the motion), and their
  spread splits into noise (var(difference)/2) and the part both runs
  share.

    python benchmarks/energy_drift.py
    python benchmarks/energy_drift.py --quick
"""

import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import round_off as R

import _common as C
import prkmk_jax as pk

SEEDS = (0, 1, 2, 3)
PAIR_STEPS = (0.05, 0.1, 0.15)
SAVES = 200


def signed_drifts(coordinates, h, steps, batch, seed, perturbed):
    """Per trajectory, the least-squares slope (a step) of the signed
    relative error of the energy and of |Π|², and the run's seconds."""
    method = pk.PRKMK(R.FREE.bundle, coordinates, pk.stormer_verlet, form="body")
    inertia = jnp.asarray(R.PAPER_INERTIA)
    y0 = R.initial_states(batch, seed=seed)
    if perturbed:
        y0 = pk.BundleElement(y0.base, y0.fiber * (1 + np.finfo(np.float64).eps))
    every = max(steps // SAVES, 1)
    run = jax.jit(jax.vmap(lambda y: pk.integrate(method, R.FREE, y, 0.0, h, steps, inertia, save_every=every)))
    start = time.perf_counter()
    momenta = np.asarray(jax.block_until_ready(run(y0)).ys.fiber)
    seconds = time.perf_counter() - start
    step_numbers = every * np.arange(momenta.shape[1])
    energy = np.sum(momenta**2 / np.asarray(R.PAPER_INERTIA), axis=-1)
    norm_sq = np.sum(momenta**2, axis=-1)

    def slopes(values):
        relative = values / values[:, :1] - 1
        return np.polyfit(step_numbers, relative.T, 1)[0]

    return slopes(energy), slopes(norm_sq), seconds


def summary(values):
    return dict(mean=float(np.mean(values)), standard_error=float(np.std(values) / np.sqrt(len(values))))


def pair_statistics(first, second):
    """The correlation of two runs' per-trajectory drifts, their spread, its
    noise (what differs between the runs) and the part both share."""
    spread = float(np.sqrt((np.var(first) + np.var(second)) / 2))
    noise = float(np.std(first - second) / np.sqrt(2))
    return dict(
        correlation=float(np.corrcoef(first, second)[0, 1]),
        spread=spread,
        noise=noise,
        shared=float(np.sqrt(max(spread**2 - noise**2, 0.0))),
    )


def main(argv=None):
    args, out = C.cli(__doc__, argv, _arguments)
    steps, batch = (2_000, 8) if args.quick else (int(args.steps), args.batch)
    seeds = SEEDS[:2] if args.quick else SEEDS
    maps = {"SV exp": pk.Exp(), "SV Cayley": pk.Cayley()}
    runs, rows = {}, []

    def run(name, h, seed, perturbed):
        key = (name, h, seed, perturbed)
        if key not in runs:
            energy, norm_sq, seconds = signed_drifts(maps[name], h, steps, batch, seed, perturbed)
            runs[key] = energy
            row = dict(method=name, h=h, seed=seed, perturbed=perturbed, steps=steps, batch=batch)
            row.update(energy=summary(energy), momentum_norm_sq=summary(norm_sq), seconds=seconds)
            row["trajectory_drifts"] = [float(x) for x in energy]
            rows.append(row)
            e = row["energy"]
            print(
                f"{name:10s} h = {h:<5} seed {seed}{' (one ulp)' if perturbed else ''}: "
                f"energy {e['mean']:+.2e} ± {e['standard_error']:.1e} a step "
                f"(|Π|² {row['momentum_norm_sq']['mean']:+.2e} ± {row['momentum_norm_sq']['standard_error']:.1e})  {seconds:.0f} s",
                flush=True,
            )
        return runs[key]

    for name in maps:
        for seed in seeds:
            run(name, 0.1, seed, False)
    pairs = []
    for h in PAIR_STEPS:
        statistics = pair_statistics(run("SV exp", h, 0, False), run("SV exp", h, 0, True))
        pairs.append(dict(method="SV exp", h=h, seed=0, **statistics))
        correlation, shared, noise = statistics["correlation"], statistics["shared"], statistics["noise"]
        print(f"one-ulp pair, SV exp h = {h}: correlation {correlation:.2f}, shared {shared:.1e}, noise {noise:.1e}")
    with open(out / "energy_drift.json", "w") as f:
        json.dump(dict(machine=C.machine(), runs=rows, pairs=pairs), f, indent=1)


def _arguments(parser):
    parser.add_argument("--steps", type=float, default=1e6, help="steps of each run (default 1e6)")
    parser.add_argument("--batch", type=int, default=64, help="trajectories of each run (default 64)")


if __name__ == "__main__":
    main()
