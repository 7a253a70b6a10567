"""Shared pieces of the benchmark scripts (not a script itself).

The problem is the free rigid body g' = gΩ̂, Π' = Π × Ω, Ω = Π/I, with the
paper's inertia (5.2) and momentum (5.1) and a random initial attitude. The
PRKMK methods see it on T*SO(3) (`Cotangent(SO3)`, body form); the peers see
the embedding ℝ⁹×ℝ³ (the rotation matrix flattened row-major, then Π).

Accuracy oracle: SciPy DOP853 at rtol = atol = 1e-13 on the embedding. Its
body momentum is cross-checked against the closed-form solution through
Jacobi elliptic functions (`prkmk_jax.scenes.elliptic_momentum`), in
`tests/test_benchmark_reference.py`.
"""

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import prkmk_jax as pk
from prkmk_jax.scenes import FreeRigidBody, TopParameters
from prkmk_jax.scenes import rigid_body as rb
from prkmk_jax.scenes.base import attitude_of, rotation_matrix

INERTIA = np.asarray(rb.PAPER_INERTIA)
MOMENTUM = np.asarray(rb.PAPER_MOMENTUM)


def initial_conditions(batch: int | None, seed: int = 0, scale: float = 1.0):
    """(Q₀, Π₀): the paper's Π₀ and a random attitude (batch=None), or a batch
    of random attitudes and momenta Π₀·(1 + 0.1·N(0, 1)) per component."""
    if batch is None:
        return rb.random_rotation(rb.PAPER_SEED), scale * MOMENTUM
    rng = np.random.default_rng(seed)
    qs = np.stack([rb.random_rotation(seed * 100003 + k) for k in range(batch)])
    pis = scale * MOMENTUM * (1 + 0.1 * rng.normal(size=(batch, 3)))
    return qs, pis


# --- the embedding ℝ⁹×ℝ³ -----------------------------------------------------------


SCENE = FreeRigidBody()
"""The free rigid body on `Cotangent(SO3)`, body form: the PRKMK methods'
vector field (`SCENE.method(tableau)` builds them) and, through
`SCENE.embedding_field`, the peers' field on the flat 12-vector."""
embedding_rhs = SCENE.embedding_field


def top_parameters() -> TopParameters:
    """The heavy top's moments and lever ℓ = m g χ, built when called (JAX's devices are set up after this import)."""
    return TopParameters(jnp.array([1.0, 0.8, 0.4]), jnp.array([0.1, 0.2, 0.9]))


def from_vector(z):
    """(Q, Π) from flat 12-vectors (NumPy or JAX arrays)."""
    return z[..., :9].reshape(*z.shape[:-1], 3, 3), z[..., 9:]


def reference(q0, pi0, t_end, inertia=INERTIA, t_eval=None, tol=1e-13):
    """(Q, Π) at `t_end`, or at each of `t_eval`: the scene's
    `reference_solution` (DOP853 at rtol = atol = `tol` on the embedding)."""
    y0 = pk.BundleElement(pk.SO3(jnp.asarray(q0)), jnp.asarray(pi0))
    rows = SCENE.reference_solution(y0, [t_end] if t_eval is None else t_eval, jnp.asarray(inertia), rtol=tol, atol=tol)
    return from_vector(rows[-1] if t_eval is None else rows)


# --- measures ----------------------------------------------------------------------


def invariants(q, pi, inertia=INERTIA):
    """The free body's invariants along (Q, Π) with a leading time axis,
    from the scene itself (`FreeRigidBody.invariants`): energy, |Π|, spatial
    momentum QΠ and max|QᵀQ − I|."""
    y = pk.BundleElement(pk.SO3(jnp.asarray(q)), jnp.asarray(pi))
    return {name: np.asarray(value) for name, value in SCENE.invariants(y, jnp.asarray(inertia)).items()}


# --- solvers -------------------------------------------------------------------------
MAX_STEPS = 1_000_000


def prkmk_solver(tableau, coordinates="exp", adaptive=False, root_finder=None, **options):
    """`PRKMKSolver` of the scene's method of `tableau`; `options` go to `PRKMK`."""
    coords = pk.Exp() if coordinates == "exp" else pk.Cayley()
    return pk.PRKMKSolver(SCENE.method(tableau, coords, root_finder=root_finder, **options), adaptive=adaptive)


def integrate_final(method, steps, h, gradient=pk.StoredSteps(), scene=SCENE):
    """(Q₀, Π₀, inertia) -> (Q, Π, implicit iterations) after `steps` fixed
    steps of size `h` of `prkmk_jax.integrate` with `method` on the free
    body `scene` (T*SO(3) unless given; differentiated by `gradient`,
    `integrate`'s argument)."""

    def run(q0, pi0, inertia):  # the attitude a matrix, or the scene's quaternion in and out
        y0 = pk.BundleElement(attitude_of(q0, scene.bundle.base), pi0)
        traj = pk.integrate(method, scene, y0, 0.0, h, steps, inertia, save_every=steps, gradient=gradient)
        return rotation_matrix(traj.ys.base)[-1], traj.ys.fiber[-1], traj.stats["num_iterations"]

    return run


def _final(term, solver, to_state, split, adaptive, t_eval):
    """(q0, π0, t1, dt, rtol, inertia) -> ((Q, Π), num_steps) by diffeqsolve;
    dt and rtol are data, so a sweep compiles once. With `t_eval`, values at
    those times instead of at t1. `to_state`/`split` convert (Q, Π) to the
    solver's state and back."""

    def run(q0, pi0, t1, dt, rtol, inertia):
        controller = diffrax.PIDController(rtol=rtol, atol=rtol) if adaptive else diffrax.ConstantStepSize()
        saveat = diffrax.SaveAt(t1=True) if t_eval is None else diffrax.SaveAt(ts=t_eval)
        sol = diffrax.diffeqsolve(
            term, solver, 0.0, t1, dt, to_state(q0, pi0), inertia, saveat=saveat, stepsize_controller=controller, max_steps=MAX_STEPS
        )
        q, pi = split(sol.ys)
        return ((q[-1], pi[-1]) if t_eval is None else (q, pi)), sol.stats["num_accepted_steps"]

    return run


def prkmk_final(solver, adaptive=False, t_eval=None):
    """`_final` for a PRKMKSolver on T*SO(3)."""
    to_state, split = (lambda q0, pi0: pk.BundleElement(pk.SO3(q0), pi0)), (lambda ys: (ys.base.matrix, ys.fiber))
    return _final(pk.PRKMKTerm(SCENE), solver, to_state, split, adaptive, t_eval)


def diffrax_final(solver, adaptive, t_eval=None):
    """`_final` for a diffrax Runge–Kutta solver on the embedding ℝ⁹×ℝ³; an
    adaptive run chooses its own first step."""
    run = _final(
        diffrax.ODETerm(embedding_rhs), solver, lambda q0, pi0: jnp.concatenate([q0.reshape(9), pi0]), from_vector, adaptive, t_eval
    )
    if not adaptive:
        return run
    return lambda q0, pi0, t1, dt, rtol, inertia: run(q0, pi0, t1, None, rtol, inertia)


# --- figures -------------------------------------------------------------------------
FAMILY_STYLES = {"prkmk": "-o", "diffrax": "--s", "scipy": ":^"}


def subplots(*args, **kw):
    """`plt.subplots` on the Agg backend: the scripts draw to files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(*args, **kw)


def save(fig, path, dpi=110, rect=(0, 0, 1, 1)):
    """Lay the figure out inside `rect`, write it to `path` and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=rect)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def plot_against_wall(axes, keys, rows):
    """One log–log curve per method on each axis: `rows[key]` against
    `rows["wall_s"]` for the successful runs (``ok``), in order of cost;
    values below 1e-17 are drawn at 1e-17."""
    for method in sorted({r["method"] for r in rows}):
        pts = sorted((r for r in rows if r["method"] == method and r["ok"]), key=lambda r: r["wall_s"])
        if not pts:
            continue
        for ax, key in zip(axes, keys):
            ax.loglog([p["wall_s"] for p in pts], [max(p[key], 1e-17) for p in pts], FAMILY_STYLES[pts[0]["family"]], ms=4, label=method)


# --- timing --------------------------------------------------------------------------
def compile_fn(fn, *args):
    """jit-compile; returns (compiled, compile seconds)."""
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - start


def call_seconds(fn, *args):
    """Wall time of one call, its outputs ready."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def median_time(compiled, *args, repeats=5):
    """Median wall time of `repeats` runs after one warm-up, and the output."""
    out = jax.block_until_ready(compiled(*args))
    return statistics.median(call_seconds(compiled, *args) for _ in range(repeats)), out


def compile_all(fns, *args):
    """jit-compile each of a dict of functions and run it once; returns
    (compiled, compile seconds, outputs), each a dict by the same names."""
    compiled, compile_s, outputs = {}, {}, {}
    for name, fn in fns.items():
        compiled[name], compile_s[name] = compile_fn(fn, *args)
        outputs[name] = jax.block_until_ready(compiled[name](*args))
    return compiled, compile_s, outputs


def interleaved_times(compiled, *args, rounds):
    """Wall times of a dict of compiled functions run in alternation, one of
    each per round, so that a slow spell of the machine hits all of them.
    Each is called twice in its turn and the second call timed: a program
    called right after another runs slower (caches), which a one-trajectory
    run feels, and repeated calls are what a run's cost is."""
    times = {name: [] for name in compiled}
    for _ in range(rounds):
        for name, fn in compiled.items():
            jax.block_until_ready(fn(*args))
            times[name].append(call_seconds(fn, *args))
    return times


def ns_per_trajectory_step(times, batch, steps):
    """The median of each entry of `interleaved_times`, in ns per trajectory-step."""
    return {name: statistics.median(ts) / (batch * steps) * 1e9 for name, ts in times.items()}


def median_ratio(times, numerator, denominator):
    """The median of the per-round ratios times[numerator] / times[denominator]
    (runs of the same round saw the same state of the machine)."""
    return statistics.median(a / b for a, b in zip(times[numerator], times[denominator]))


def machine():
    host = dict(platform=platform.platform(), processor=platform.processor() or platform.machine(), cpus=os.cpu_count())
    return host | dict(jax=jax.__version__, devices=[str(d) for d in jax.devices()], device_kind=jax.devices()[0].device_kind)


def device_name(machine: dict) -> str:
    card = machine.get("card (nvidia-smi)") or machine.get("device_kind", "")
    if machine.get("devices", ["cpu"])[0].startswith("cpu") or card.lower() == "cpu":
        return f"CPU, {machine['cpus']} cores"
    return card


def measured_on(data: dict) -> str:
    """The opening line of a table: the machine and jax version of its results."""
    return f"Measured on {device_name(data['machine'])}, jax {data['machine']['jax']}."


def results_file(folder: Path, name: str) -> dict:
    return json.loads((folder / name).read_text())


def table(headers: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def number(value, spec: str) -> str:
    """`value` formatted, or "–" where there is none (None, NaN)."""
    if value is None or (isinstance(value, float) and value != value):
        return "–"
    return format(value, spec)


RESULTS = Path(__file__).resolve().parent / "results"
"""Where full runs write by default (the committed results), whatever the
working directory."""


def cli(doc, argv, add_arguments=None):
    """The scripts' shared command line (--quick, --out): parses `argv`,
    enables float64 and creates the output folder; returns (args, out).
    Without --out a full run writes to `benchmarks/results/` and a --quick
    run to a fresh scratch folder, so a smoke test never overwrites the
    committed results."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    parser.add_argument(
        "--out", default=None, help="folder for PNG/CSV/JSON (default: benchmarks/results, or a scratch folder with --quick)"
    )
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if args.out is not None:
        out = Path(args.out)
    elif args.quick:
        out = Path(tempfile.mkdtemp(prefix="prkmk_benchmark_quick_"))
    else:
        out = RESULTS
    out.mkdir(parents=True, exist_ok=True)
    print(f"writing to {out}")
    return args, out
