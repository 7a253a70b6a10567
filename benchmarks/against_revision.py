"""This working tree against an earlier revision of the library, interleaved.

A speed claim is a before/after ratio measured in one process: the package
as it was at `--rev` is exported with `git archive` under the name
`prkmk_jax_at_rev` (its imports are relative) and imported next to the
working tree's `prkmk_jax`. Both build the same method on the same problem —
the free rigid body on T*SO(3) (body form, h = 0.01, the paper's inertia, a
batch of random attitudes and momenta), or the heavy top on T*SO(3) (the
same, with the gravity torque Γ × ℓ, ℓ = (0.1, 0.2, 0.9), as η) — and are
compiled, checked to give
the same final states (≤ 1e-11 in float64, 1e-4 in float32), and then timed
in alternation. Columns: ns per trajectory-step of each, the median of the
per-round ratios now/before, and the compile times.

Methods: a PRKMK tableau with exp or Cayley coordinates ("symmetrized
lobatto_iiia_iiib4": its `Symmetrized`; "plain stormer_verlet": with
`compensated_sum=False`, where the revision has the option), or the free body's exact-flow
splitting ("splitting": Strang; "splitting kahan_li_8":
composed to order 8). Paths: `integrate` (lax.scan) vmapped over the batch,
`in_state` (the batch as leading axes of the state, one run),
`diffeqsolve(PRKMKSolver)`, and `value_and_grad` of a loss on the final
state with respect to the inertia through `integrate` (vmapped), through
its stored steps or (`reversible_grad`) by `ReversibleGradient(None)`, and
through `diffeqsolve` by `ReversibleAdjoint(None)` (`reversible_adjoint`).

    python benchmarks/against_revision.py --rev a1a3087 --out benchmarks/results
    python benchmarks/against_revision.py --quick          # against HEAD
    python benchmarks/against_revision.py --rev a1a3087 --float32 --name against_revision_float32
    python benchmarks/against_revision.py --rev a1a3087 --gradients --name against_revision_gradients
"""

import dataclasses
import importlib
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp

import _common as C
import prkmk_jax as pk

H = 0.01
LEVER = jnp.array([0.1, 0.2, 0.9])
ROOT = Path(__file__).resolve().parents[1]


def import_revision(rev: str):
    """The package `prkmk_jax` as committed at `rev`, as a separate module."""
    sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, check=True, capture_output=True, text=True).stdout.strip()
    folder = Path(tempfile.mkdtemp(prefix="prkmk_rev_"))
    archive = subprocess.run(["git", "archive", rev, "prkmk_jax"], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    shutil.move(folder / "prkmk_jax", folder / "prkmk_jax_at_rev")
    sys.path.insert(0, str(folder))
    return importlib.import_module("prkmk_jax_at_rev"), sha


def _method(lib, tableau, coordinates):
    coords = lib.Exp() if coordinates == "exp" else lib.Cayley()
    if tableau.startswith("plain "):
        # The step's product as it is, without compensated summation (a
        # revision from before the option has only that).
        method = _method(lib, tableau.removeprefix("plain "), coordinates)
        has_option = "compensated_sum" in {field.name for field in dataclasses.fields(method)}
        return dataclasses.replace(method, compensated_sum=False) if has_option else method
    if tableau.startswith("symmetrized "):
        return lib.Symmetrized(_method(lib, tableau.removeprefix("symmetrized "), coordinates))
    if tableau.startswith("splitting"):
        composition = tableau.removeprefix("splitting").strip()
        return lib.scenes.FreeRigidBody().splitting(getattr(lib, composition) if composition else None, coords)
    return lib.PRKMK(lib.Cotangent(lib.SO3), coords, getattr(lib, tableau), form="body")


def _heavy_top(t, y, inertia):
    """The heavy top's generator (Ω, Γ × ℓ) on T*SO(3), body form, written
    on the state's arrays so that it serves both revisions."""
    return y.fiber / inertia, jnp.cross(y.base.matrix[..., 2, :], LEVER)


def _runs(lib, tableau, coordinates, steps, scene="free body"):
    # Both fields read the state's arrays only, so one function serves both
    # revisions; a splitting integrates its own revision's scene.
    method, field = _method(lib, tableau, coordinates), (C.SCENE if scene == "free body" else _heavy_top)
    if tableau.startswith("splitting"):
        field = method.scene

    def integrate(q0, pi0, inertia, gradient=None):
        y0 = lib.BundleElement(lib.SO3(q0), pi0)
        given = {} if gradient is None else {"gradient": gradient}  # each revision's default otherwise
        traj = lib.integrate(method, field, y0, 0.0, H, steps, inertia, save_every=steps, **given)
        return traj.ys.base.matrix[-1], traj.ys.fiber[-1]

    def diffeqsolve(q0, pi0, inertia, adjoint=None):
        y0 = lib.BundleElement(lib.SO3(q0), pi0)
        # Times in the state's dtype: diffeqsolve promotes the state to theirs.
        t0, t1, dt = (jnp.asarray(x, q0.dtype) for x in (0.0, steps * H, H))
        adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
        sol = diffrax.diffeqsolve(lib.PRKMKTerm(field), lib.PRKMKSolver(method), t0, t1, dt, y0, inertia, max_steps=steps, adjoint=adjoint)
        return sol.ys.base.matrix[-1], sol.ys.fiber[-1]

    def value_and_grad(qs, pis, inertia, gradient=None):
        def loss(inertia):
            q, pi = jax.vmap(lambda q, p: integrate(q, p, inertia, gradient))(qs, pis)
            return jnp.sum(q[..., 0, :] ** 2 * jnp.arange(3)) + jnp.sum(pi**2)

        return jax.value_and_grad(loss)(inertia)

    def reversible_grad(qs, pis, inertia):
        return value_and_grad(qs, pis, inertia, lib.ReversibleGradient(None))

    def reversible_adjoint(qs, pis, inertia):
        def loss(inertia):
            q, pi = jax.vmap(lambda q, p: diffeqsolve(q, p, inertia, lib.ReversibleAdjoint(None)))(qs, pis)
            return jnp.sum(q[..., 0, :] ** 2 * jnp.arange(3)) + jnp.sum(pi**2)

        return jax.value_and_grad(loss)(inertia)

    batched = lambda fn: jax.vmap(fn, in_axes=(0, 0, None))  # noqa: E731
    return {
        "integrate": batched(integrate),
        "in_state": integrate,
        "diffeqsolve": batched(diffeqsolve),
        "value_and_grad": value_and_grad,
        "reversible_grad": reversible_grad,
        "reversible_adjoint": reversible_adjoint,
    }


def compare(before, tableau, coordinates, path, batch, dtype, steps, rounds, scene="free body"):
    qs, pis = C.initial_conditions(batch, seed=3)
    args = (jnp.asarray(qs, dtype), jnp.asarray(pis, dtype), jnp.asarray(C.INERTIA, dtype))
    fns = {"now": _runs(pk, tableau, coordinates, steps, scene)[path], "before": _runs(before, tableau, coordinates, steps, scene)[path]}
    compiled, compile_s, outputs = C.compile_all(fns, *args)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(outputs["now"]), jax.tree.leaves(outputs["before"])))
    scale = max(1.0, max(float(jnp.max(jnp.abs(a))) for a in jax.tree.leaves(outputs["before"])))
    tolerance = (1e-11 if dtype == jnp.float64 else 1e-4) * scale
    if not gap <= tolerance:
        raise AssertionError(f"{tableau} {coordinates} {path}: now and before differ by {gap:.2e} > {tolerance:.0e}")
    times = C.interleaved_times(compiled, *args, rounds=rounds)
    per_step = C.ns_per_trajectory_step(times, batch, steps)
    ratio = C.median_ratio(times, "now", "before")
    return dict(
        scene=scene,
        tableau=tableau,
        coordinates=coordinates,
        path=path,
        dtype=jnp.dtype(dtype).name,
        batch=batch,
        steps=steps,
        ns_per_traj_step=per_step,
        now_over_before=ratio,
        compile_s=compile_s,
        max_abs_difference=gap,
    )


def main(argv=None):
    def arguments(parser):
        parser.add_argument("--rev", default="HEAD")
        parser.add_argument("--rounds", type=int, default=9)
        parser.add_argument("--scene", default="", help="run only the cases of this scene ('free body' or 'heavy top')")
        parser.add_argument("--name", default="against_revision", help="stem of the results file")
        parser.add_argument("--splittings", action="store_true", help="the exact-flow splittings' cases instead of PRKMK's")
        parser.add_argument("--float32", action="store_true", help="the float32 cases of both, alone (what renormalises the state)")
        parser.add_argument("--gradients", action="store_true", help="the gradient cases alone, beside their forward runs")

    args, out = C.cli(__doc__, argv, arguments)
    before, sha = import_revision(args.rev)
    if args.quick:
        cases = [
            ("stormer_verlet", "exp", "integrate", 8, jnp.float64, "free body"),
            ("lobatto_iiia_iiib6", "cayley", "integrate", 8, jnp.float64, "heavy top"),
        ]
        rounds, work = 2, 80
    elif args.float32:
        cases = [("stormer_verlet", "exp", "integrate", b, jnp.float32, "free body") for b in (1, 1024, 16384)]
        cases += [("lobatto_iiia_iiib4", "exp", "integrate", 16384, jnp.float32, "free body")]
        cases += [("splitting", "exp", path, b, jnp.float32, "free body") for path, b in (("integrate", 1), ("in_state", 1024))]
        rounds, work = args.rounds, 200_000
    elif args.gradients:
        cases = [
            (tab, coords, path, 64, jnp.float64, "free body")
            for tab, coords in (("stormer_verlet", "exp"), ("stormer_verlet", "cayley"), ("lobatto_iiia_iiib4", "exp"))
            for path in ("integrate", "value_and_grad", "reversible_grad", "reversible_adjoint")
        ]
        symmetrized = "symmetrized lobatto_iiia_iiib4"
        cases += [(symmetrized, "exp", path, 64, jnp.float64, "free body") for path in ("integrate", "reversible_grad")]
        cases += [
            (method, coords, path, 64, jnp.float64, "free body")
            for method, coords in (("splitting", "exp"), ("splitting", "cayley"), ("splitting kahan_li_6", "exp"))
            for path in ("integrate", "value_and_grad", "reversible_grad")
        ]
        rounds, work = args.rounds, 64_000
    elif args.splittings:
        cases = [
            (method, coords, path, batch, jnp.float64, "free body")
            for method, coords in (("splitting", "exp"), ("splitting", "cayley"), ("splitting kahan_li_8", "exp"))
            for path in ("integrate", "in_state")
            for batch in (1, 64, 1024)
            if not (path == "in_state" and batch == 1)
        ]
        cases += [
            (method, "exp", path, 64, jnp.float64, "free body")
            for method in ("splitting", "splitting kahan_li_8")
            for path in ("value_and_grad", "reversible_grad")
        ]
        cases += [("splitting", "exp", "in_state", 16384, jnp.float64, "free body")]
        cases += [("splitting", "exp", path, b, jnp.float32, "free body") for path, b in (("integrate", 1), ("in_state", 1024))]
        rounds, work = args.rounds, 200_000
    else:
        cases = [
            (tab, coords, path, batch, dtype, "free body")
            for tab, coords in (
                ("stormer_verlet", "exp"),
                ("stormer_verlet", "cayley"),
                ("lobatto_iiia_iiib4", "exp"),
                ("symplectic_euler", "exp"),
            )
            for path in ("integrate", "diffeqsolve")
            for batch in (1, 64, 1024)
            for dtype in (jnp.float64,)
        ]
        cases += [("stormer_verlet", "exp", "integrate", b, jnp.float32, "free body") for b in (1, 1024)]
        large = [(tab, dtype) for tab in ("stormer_verlet", "lobatto_iiia_iiib4") for dtype in (jnp.float64, jnp.float32)]
        cases += [(tab, "exp", "integrate", 16384, dtype, "free body") for tab, dtype in large]
        cases += [("stormer_verlet", "exp", "value_and_grad", b, jnp.float64, "free body") for b in (1, 64)]
        cases += [
            (tab, coords, "integrate", batch, jnp.float64, scene)
            for scene in ("free body", "heavy top")
            for tab, coords in (("lobatto_iiia_iiib6", "exp"), ("lobatto_iiia_iiib6", "cayley"), ("stormer_verlet", "cayley"))
            for batch in (1, 1024)
        ]
        # Methods made of steps and the splittings, whose steps the drivers
        # also sum (`compensated`), and the step without compensated
        # summation (`compensated_sum=False`).
        cases += [("symmetrized lobatto_iiia_iiib4", "exp", "integrate", 64, jnp.float64, "free body")]
        cases += [("plain stormer_verlet", coords, "integrate", 64, jnp.float64, "free body") for coords in ("exp", "cayley")]
        cases += [
            (method, "exp", path, batch, jnp.float64, "free body")
            for method in ("splitting", "splitting kahan_li_8")
            for path, batch in (("integrate", 64), ("in_state", 1024))
        ]
        rounds, work = args.rounds, 200_000
    cases = [case for case in cases if not args.scene or case[-1] == args.scene]
    print(f"now: working tree; before: {args.rev} ({sha})")
    print(
        f"{'scene':9s} {'tableau':20s} {'coords':6s} {'path':14s} {'dtype':7s} {'batch':>5s} {'now ns':>8s} "
        f"{'bef. ns':>8s} {'ratio':>6s} {'cmp now':>7s} {'cmp bef':>7s} {'max diff':>8s}"
    )
    rows = []
    for tab, coords, path, batch, dtype, scene in cases:
        steps = int(max(20, min(400, work // batch)))
        row = compare(before, tab, coords, path, batch, dtype, steps, rounds, scene)
        rows.append(row)
        ns, cs = row["ns_per_traj_step"], row["compile_s"]
        print(
            f"{scene:9s} {tab:20s} {coords:6s} {path:14s} {row['dtype']:7s} {batch:5d} {ns['now']:8.0f} {ns['before']:8.0f} "
            f"{row['now_over_before']:6.2f} {cs['now']:7.2f} {cs['before']:7.2f} {row['max_abs_difference']:8.1e}",
            flush=True,
        )
    with open(out / f"{args.name}.json", "w") as f:
        json.dump(dict(machine=C.machine(), rev=args.rev, sha=sha, rounds=rounds, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
