"""Which rounding makes the energy drift that `energy_drift.py` measures: the
free-body step of SV Cayley written again in NumPy, operation by operation,
so that chosen parts of it can be computed in extended precision (NumPy's
long double: a 64-bit significand on x86-64, 2¹¹ times float64's) while the
rest rounds as float64 does.

The step (body form, the paper's inertia; L ≡ 0, and dcay⁻¹ truncated to the
identity, as `PRKMK` does for a method of order 2):

    K₁ = I⁻¹Πₙ,   K₂ = I⁻¹(Πₙ + C(h(½K₁ + ½K₂), Πₙ)),   u = h(½K₁ + ½K₂),
    Πₙ₊₁ = Πₙ + C(u, Πₙ),

with C(w, x) = cay(−ŵ)x − x = 4/(4 + |w|²) (x×w + ½ w×(w×x)). In exact
arithmetic the energy is kept exactly: C(u, Πₙ) is orthogonal to u, and u is
h times the mean of I⁻¹Πₙ and I⁻¹Πₙ₊₁. Each variant below is the library's
arithmetic (the stages iterated to round-off by its stopping rule, frozen
per trajectory as under `vmap`, and evaluated once more; u rounded once from
its exact value; the update summed with compensation) but for the part it
names:

- `nothing (float64)`: nothing changed. Its first step is checked against the
  library's own step (`PRKMK`, Cayley, SV) before the runs.
- `stages exact`: the stage equation solved in long double from the float64
  stages (K₁ too), and u rounded once from that solution.
- `stages refined once`: one long-double evaluation of the stage from the
  float64 stages, u rounded once from it.
- `stages exact, K₁ float64`: as `stages exact`, but with the float64 quotient
  I⁻¹Πₙ for K₁ (the field at the step's start as the library computes it).
- `stage point double-word`: the stage point Πₙ + C(U, Πₙ) at the float64
  stages kept as an unevaluated sum of two float64 (its rounding error
  carried), U's own rounding added to first order, and the field applied to
  both parts (linear here): what a refinement that neither evaluates the
  field nor the rotation in extended precision could do.
- `update exact`: the update's change C(u, Πₙ) computed in long double and
  rounded once.

These runs start every step's stage iteration from K₂ = K₁, as the library
starts only its first step.

Each run: `--batch` random initial states (unit |Π| in a random direction, a
seed per set), `--steps` steps of h = 0.1; each trajectory's drift is the
least-squares slope of its signed relative energy error (computed in long
double) against the step number. Reported: the mean over the batch with its
standard error, and the spread (standard deviation) of the trajectories'
drifts, which over 10⁵ steps is mostly the random walk of the rounding.

One-ulp pairs (`--part pairs`), as `energy_drift.py` runs them for the
library: `nothing (float64)` and `stages exact` at h = 0.15, where the
library's drifts are mostly set by the initial state, from set 0 and again
from its momenta scaled by 1 + ε. The correlation of the two runs' drifts
per trajectory, and their spread split into noise and the part both runs
share, say whether the stage solve's rounding is also what makes each
trajectory drift its own way (the drifts that lift the growth exponents
above a random walk's).

The starts from the previous step's stages (`--part start`): `nothing
(float64)` and `stages exact` again, with each step's iteration started
from the previous step's stages moved by the change of K₁ ("extrapolated",
the guess Gᵢ of `PRKMK.extrapolated_guesses`) or on either side of that
guess, G ± (K₂ − K₁) of the previous step by the parity of Π's last bits
("either side", the library's start at round-off, which `--part start`
runs), and with the field as the library's compiled step computes it: Π
times the rounded 1/I, since XLA turns a division by the inertia
broadcast over the batch into that product. Before the runs, the float64
step here is started from the library's own states over 200 steps of 64
trajectories, with the library's carried stages for its start, and the
share of its momenta that differ from the library's next ones is
recorded for the K₁ start and the library's, and for the library's start
again with the library compiled under
`--xla_backend_optimization_level=0`: XLA contracts products and sums
into fused multiply-adds on CPU by default, which NumPy does not, and
that flag turns it off.

    python benchmarks/drift_emulation.py --jobs 2       # every part, two runs at a time
    python benchmarks/drift_emulation.py --part pairs   # the pairs again, the rest kept
    python benchmarks/drift_emulation.py --part start   # the library's start (either side) again, the rest kept
    python benchmarks/drift_emulation.py --part check   # the checks against the library alone
    python benchmarks/drift_emulation.py --quick
"""

import json
import multiprocessing
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from energy_drift import pair_statistics

import _common as C
from prkmk_jax.exact_sums import two_sum  # additions only: the same on NumPy arrays

VARIANTS = (
    "nothing (float64)",
    "stages exact",
    "stages refined once",
    "stages exact, K₁ float64",
    "stage point double-word",
    "update exact",
)
SEEDS = (0, 1)
STEP = 0.1
PAIR_VARIANTS = ("nothing (float64)", "stages exact")
START_VARIANTS = ("nothing (float64)", "stages exact")
LIBRARY_CHECK_BATCH = 64
LIBRARY_CHECK_STEPS = 200
PAIR_STEP = 0.15
PAIR_STEPS = 200_000
PAIR_BATCH = 256
INERTIA = (7 / 8, 5 / 8, 1 / 4)
SAVES = 200
EXACT_EVALUATIONS = 6
"""Long-double evaluations that solve the stage from the float64 stages. The
stage map contracts by about ½h·max(I⁻¹)·|Π| ≤ 0.2 here (h = 0.1, |Π| = 1,
max(I⁻¹) = 4), so five take float64's round-off (2⁻⁵³) below long double's
(2⁻⁶⁴); six leave a margin."""
TOLERANCE = max(1e-12, 50 * float(np.finfo(np.float64).eps))
LONG = np.longdouble


def _cross(a, b):
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _rotation_change(w, x):
    """cay(−ŵ)x − x, in the arithmetic of w and x (float64 or long double)."""
    m = -w
    theta_sq = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    mx = _cross(m, x)
    return 4.0 / (4.0 + theta_sq) * (mx + 0.5 * _cross(m, mx))


def _long(x):
    return np.asarray(x, LONG)


def _increment(h, k1, k2):
    """h(½K₁ + ½K₂) in long double, from long-double (or float64) slopes."""
    return _long(h) * (_long(k1) + _long(k2)) * LONG(0.5)


def _start_side(momentum):
    """±1 per trajectory: the parity of the sum of the lowest bits of Π's
    entries, as `PRKMK.extrapolated_guesses` picks its side."""
    parity = (np.ascontiguousarray(momentum).view(np.uint64) & np.uint64(1)).sum(axis=0)
    return np.where(parity % 2 == 0, 1.0, -1.0)


def _stages_float64(momentum, inertia, h, carried=None, library_field=False, either_side=False):
    """The library's stage solve: (K₁, K₂, iterations of the batch). K₂ starts
    from K₁ (the first step's start), or with `carried` = (K₁, K₂) of the
    previous step from G = K₂ + the change of K₁ since then (the
    extrapolation of `PRKMK.extrapolated_guesses`), and with `either_side`
    from G ± (K₂ − K₁) of the previous step, the side by the parity of Π's
    last bits, as `PRKMK` starts every step after the first when it solves
    to round-off. `library_field`: I⁻¹Π as
    the library's compiled field computes it, Π times the rounded 1/I (XLA
    turns a division by the inertia broadcast over the batch into that
    product); otherwise the quotient."""
    if library_field:
        reciprocal = 1.0 / inertia

        def field(x):
            return x * reciprocal
    else:

        def field(x):
            return x / inertia

    k1 = field(momentum)

    def stage(k2):
        return field(momentum + _rotation_change(h * (0.5 * k1 + 0.5 * k2), momentum))

    k2 = k1.copy() if carried is None else carried[1] + (k1 - carried[0])
    if carried is not None and either_side:
        k2 = k2 + _start_side(momentum) * (carried[1] - carried[0])
    batch = momentum.shape[1]
    error, previous = np.full(batch, np.inf), np.full(batch, np.inf)
    active = np.ones(batch, bool)
    iterations = 0
    while active.any() and iterations < 100:
        new = stage(k2)
        increment = np.max(np.abs(k2 - new) / (TOLERANCE + TOLERANCE * np.abs(new)), axis=0)
        k2 = np.where(active, new, k2)
        previous, error = np.where(active, error, previous), np.where(active, increment, error)
        active &= (error >= 1) | ((error > 0) & (error < previous))
        iterations += 1
    return k1, stage(k2), iterations


def _stages_long(momentum, inertia, h, k1, k2, evaluations):
    """`evaluations` long-double evaluations of the stage from K₂ for the given K₁."""
    p, i, hl, k1 = _long(momentum), _long(inertia), _long(h), _long(k1)
    k2 = _long(k2)
    for _ in range(evaluations):
        k2 = (p + _rotation_change(hl * (LONG(0.5) * k1 + LONG(0.5) * k2), p)) / i
    return k1, k2


def step(variant, momentum, compensation, inertia, h, carried=None, library_field=False, either_side=False):
    """One step of `variant` from (Πₙ, its compensation): (Πₙ₊₁,
    compensation, iterations, the float64 stages (K₁, K₂) for the next
    step's start). `carried`, `library_field` and `either_side`: see
    `_stages_float64`."""
    k1, k2, iterations = _stages_float64(momentum, inertia, h, carried, library_field, either_side)
    solved = (k1, k2)
    if variant in ("stages exact", "stages refined once"):
        evaluations = EXACT_EVALUATIONS if variant == "stages exact" else 1
        k1, k2 = _stages_long(momentum, inertia, h, _long(momentum) / _long(inertia), k2, evaluations)
    elif variant == "stages exact, K₁ float64":
        k1, k2 = _stages_long(momentum, inertia, h, k1, k2, EXACT_EVALUATIONS)
    elif variant == "stage point double-word":
        exact = _increment(h, k1, k2)
        high = exact.astype(np.float64)
        low = (exact - _long(high)).astype(np.float64)
        point_change = _rotation_change(high, momentum) + _cross(momentum, low)  # C(U, Πₙ) to first order in U's low part
        point_high, point_low = two_sum(momentum, point_change)
        k2 = _long(point_high / inertia) + _long(point_low / inertia)
    u = _increment(h, k1, k2).astype(np.float64)  # rounded once
    if variant == "update exact":
        change = _rotation_change(_long(u), _long(momentum)).astype(np.float64)
    else:
        change = _rotation_change(u, momentum)
    total, lost = two_sum(momentum, change)
    momentum, compensation = two_sum(total, lost + compensation)
    return momentum, compensation, iterations, solved


def initial_momenta(batch, seed):
    rng = np.random.default_rng(seed)
    momenta = rng.normal(size=(3, batch))
    return momenta / np.linalg.norm(momenta, axis=0)


def energy(momentum, inertia):
    return 0.5 * np.sum(_long(momentum) ** 2 / _long(inertia), axis=0)


def run(variant, seed, steps, batch, h=STEP, perturbed=None, start="K₁"):
    """The energy drifts a step of one variant and set of initial states (its
    momenta scaled by 1 + ε where `perturbed`): their summary, and with
    `perturbed` given, each trajectory's. `start`: "K₁", every step's stage
    iteration started from K₂ = K₁; "extrapolated", from the previous step's
    stages moved by the change of K₁; "either side" (the library's start at
    round-off), on either side of that by the parity of Π's last bits; the
    last two with the field as the library's compiled step computes it
    (`_stages_float64`)."""
    inertia = np.asarray(INERTIA)[:, None]
    momentum = initial_momenta(batch, seed)
    if perturbed:
        momentum = momentum * (1 + np.finfo(np.float64).eps)
    compensation = np.zeros_like(momentum)
    start_energy = energy(momentum, inertia)
    every = max(steps // SAVES, 1)
    errors, iterations, carried = [], 0, None
    library, either_side = start != "K₁", start == "either side"
    started = time.perf_counter()
    for n in range(steps):
        if n % every == 0:
            errors.append(np.asarray(energy(momentum, inertia) / start_energy - 1, np.float64))
        momentum, compensation, count, solved = step(variant, momentum, compensation, inertia, h, carried, library, either_side)
        carried = solved if library else None
        iterations += count
    drifts = np.polyfit(every * np.arange(len(errors)), np.array(errors), 1)[0]
    row = dict(
        variant=variant,
        seed=seed,
        steps=steps,
        batch=batch,
        h=h,
        mean=float(np.mean(drifts)),
        standard_error=float(np.std(drifts) / np.sqrt(batch)),
        spread=float(np.std(drifts)),
        batch_iterations_a_step=iterations / steps,
        seconds=time.perf_counter() - started,
        start=start,
    )
    if perturbed is not None:
        row.update(perturbed=perturbed, trajectory_drifts=[float(x) for x in drifts])
    return row


def library_check(batch=16, steps=1, start="K₁"):
    """How far a float64 step written here is from the library's SV Cayley
    step from the same state, over `batch` states and `steps` steps of the
    library's run: (the largest difference of the momenta in units of
    float64's eps, the share of their entries that differ). Each step here
    starts from the library's state (no compensation on either side) and,
    for `start="either side"`, from the stages the library carries, as the
    library starts (see `run`)."""
    import jax
    import jax.numpy as jnp

    import prkmk_jax as pk
    from prkmk_jax.scenes import FreeRigidBody

    scene = FreeRigidBody()
    method = pk.PRKMK(scene.bundle, pk.Cayley(), pk.stormer_verlet, form="body")
    momenta = initial_momenta(batch, seed=99)
    y = pk.BundleElement(pk.SO3(jnp.broadcast_to(jnp.eye(3), (batch, 3, 3))), jnp.asarray(momenta.T))
    inertia = jnp.asarray(INERTIA)
    carried = jax.vmap(lambda y: method.initial_carried(scene, 0.0, y, inertia))(y)
    one_step = jax.jit(jax.vmap(lambda y, carried: method.carried_step(scene, 0.0, y, STEP, inertia, carried)))
    library_start = start == "either side"
    inertia_column = np.asarray(INERTIA)[:, None]
    differences = []
    for _ in range(steps):
        stages = (np.asarray(carried[0][0]).T, np.asarray(carried[1][1][0]).T) if library_start else None
        momentum = np.asarray(y.fiber).T
        here, *_ = step("nothing (float64)", momentum, np.zeros_like(momentum), inertia_column, STEP, stages, library_start, library_start)
        result = one_step(y, carried)
        y, carried = result.y, result.carried
        differences.append(np.asarray(y.fiber).T - here)
    differences = np.stack(differences)
    return float(np.max(np.abs(differences)) / np.finfo(np.float64).eps), float(np.mean(differences != 0))


def _check_without_fused_multiply_adds(batch, steps):
    """`library_check` for the library's start (either side), with the library compiled
    under `--xla_backend_optimization_level=0` (no fused multiply-adds, which
    NumPy does not form either), in a process of its own."""
    code = (
        "import json, jax; jax.config.update('jax_enable_x64', True); import drift_emulation as D; "
        f"print(json.dumps(D.library_check({batch}, {steps}, 'either side')))"
    )
    environment = dict(os.environ, XLA_FLAGS="--xla_backend_optimization_level=0")
    done = subprocess.run(
        [sys.executable, "-c", code], env=environment, cwd=Path(__file__).parent, capture_output=True, text=True, check=True
    )
    largest, fraction = json.loads(done.stdout.strip().splitlines()[-1])
    return dict(largest_eps=largest, fraction_differing=fraction)


def _case(arguments):
    return run(*arguments)


def _report(row):
    label = f"set {row['seed']}" + (", one ulp off" if row.get("perturbed") else "")
    label += "" if row["start"] == "K₁" else f", {row['start']} start"
    print(
        f"{row['variant']:26s} h = {row['h']:<5g}{label}: energy {row['mean']:+.2e} ± {row['standard_error']:.1e} a step, "
        f"spread {row['spread']:.1e}  ({row['seconds']:.0f} s)",
        flush=True,
    )


def main(argv=None):
    args, out = C.cli(__doc__, argv, _arguments)
    if np.finfo(LONG).nmant < 60:
        bits = np.finfo(LONG).nmant
        raise SystemExit(f"NumPy's long double here has {bits} stored significand bits; this emulation needs x86's 64-bit one.")
    steps, batch, seeds = (200, 16, SEEDS[:1]) if args.quick else (int(args.steps), args.batch, SEEDS)
    pair_steps, pair_batch = (200, 16) if args.quick else (PAIR_STEPS, PAIR_BATCH)
    check_batch, check_steps = (16, 20) if args.quick else (LIBRARY_CHECK_BATCH, LIBRARY_CHECK_STEPS)
    check, _ = library_check()
    print(f"one float64 step here against the library's: {check:.1f} eps at most")
    if check > 4:
        raise SystemExit("the emulated step no longer matches the library's (more than 4 eps apart): update it first.")
    checks_by_start = {
        start: dict(zip(("largest_eps", "fraction_differing"), library_check(check_batch, check_steps, start)))
        for start in ("K₁", "either side")
    }
    checks_by_start["either side, no fused multiply-adds"] = _check_without_fused_multiply_adds(check_batch, check_steps)
    for start, c in checks_by_start.items():
        print(
            f"{check_steps} steps from the library's states, start {start}: "
            f"{c['fraction_differing']:.2%} of the momenta differ, by {c['largest_eps']:.1f} eps at most"
        )
    path = out / "drift_emulation.json"
    kept = json.loads(path.read_text()) if path.exists() and args.part != "all" else {}
    cases = []
    if args.part in ("drift", "all"):
        cases += [(variant, seed, steps, batch) for seed in seeds for variant in VARIANTS]
    if args.part in ("pairs", "all"):
        cases += [(variant, 0, pair_steps, pair_batch, PAIR_STEP, perturbed) for variant in PAIR_VARIANTS for perturbed in (False, True)]
    if args.part in ("start", "all"):
        cases += [(variant, seed, steps, batch, STEP, None, "either side") for seed in seeds for variant in START_VARIANTS]
    rows, pair_runs, start_runs = [], [], []
    # Spawned, not forked: this process has started JAX's threads (the check).
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        for row in pool.map(_case, cases):
            if row["start"] != "K₁":
                start_runs.append(row)
            else:
                (rows if "perturbed" not in row else pair_runs).append(row)
            _report(row)
    pairs = []
    for variant in PAIR_VARIANTS:
        runs = {r["perturbed"]: r for r in pair_runs if r["variant"] == variant}
        if len(runs) == 2:
            statistics = pair_statistics(*(np.asarray(runs[perturbed]["trajectory_drifts"]) for perturbed in (False, True)))
            pairs.append(dict(variant=variant, h=PAIR_STEP, seed=0, steps=pair_steps, batch=pair_batch, **statistics))
            correlation, shared, noise = statistics["correlation"], statistics["shared"], statistics["noise"]
            print(f"one-ulp pair, {variant}: correlation {correlation:.2f}, shared {shared:.1e}, noise {noise:.1e}")
    results = dict(
        machine=C.machine(),
        library_check_eps=check,
        library_check_steps=dict(batch=check_batch, steps=check_steps, by_start=checks_by_start),
        step=STEP,
        runs=rows or kept.get("runs", []),
        # Runs from another start than this part's are kept.
        start_runs=[r for r in kept.get("start_runs", []) if r["start"] not in {n["start"] for n in start_runs}] + start_runs,
        pair_runs=pair_runs or kept.get("pair_runs", []),
        pairs=pairs or kept.get("pairs", []),
    )
    path.write_text(json.dumps(results, indent=1))


def _arguments(parser):
    parser.add_argument("--steps", type=float, default=1e5, help="steps of each run (default 1e5)")
    parser.add_argument("--batch", type=int, default=1024, help="trajectories of each run (default 1024)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="runs at a time (processes)")
    parser.add_argument(
        "--part",
        choices=("drift", "pairs", "start", "check", "all"),
        default="all",
        help="which runs (the other parts are kept from --out's results file; check: none, the library checks alone)",
    )


if __name__ == "__main__":
    main()
