"""Gradient memory and time against the number of steps.

The free body on T*SO(3) (body form, h = 0.01, the paper's inertia, a batch
of random attitudes), Störmer–Verlet. The loss is a weighted sum of the
final momenta and attitudes; its gradient is taken with respect to the
inertia, by `jax.value_and_grad` of

- `integrate`, through the stored steps (`gradient=None`),
- `integrate` with `ReversibleGradient(checkpoint_every=None)` (the states
  rebuilt backwards from the last one, the only state kept; the SV step is
  undone by its adjoint), and with a `Splitting` (undone and differentiated
  sub-flow by sub-flow, `Splitting.reverse_step`),
- `diffeqsolve(PRKMKSolver)` with diffrax's `RecursiveCheckpointAdjoint`.

For each: the compiled program's temporary memory (XLA's memory analysis),
the compile time, and the time of `value_and_grad` over the time of the
forward run alone, interleaved (the same number of steps and batch).

    python benchmarks/gradients.py
    python benchmarks/gradients.py --quick
"""

import json
import time

import diffrax
import jax
import jax.numpy as jnp

import _common as C
import prkmk_jax as pk

H = 0.01


def _loss_of(final_state):
    def loss(qs, pis, inertia):
        q, pi = jax.vmap(final_state, in_axes=(0, 0, None))(qs, pis, inertia)
        return jnp.sum(q[..., 0, :] * jnp.arange(1.0, 4.0)) + jnp.sum(pi**2 * jnp.arange(1.0, 4.0))

    return loss


def _cases(steps):
    scene = C.SCENE
    verlet, splitting = scene.method(pk.stormer_verlet), scene.splitting()

    def through_integrate(method, gradient):
        def final_state(q0, pi0, inertia):
            y0 = pk.BundleElement(pk.SO3(q0), pi0)
            y = pk.integrate(method, scene, y0, 0.0, H, steps, inertia, save_every=steps, gradient=gradient).ys
            return y.base.matrix[-1], y.fiber[-1]

        return final_state

    def through_diffeqsolve(q0, pi0, inertia):
        y0 = pk.BundleElement(pk.SO3(q0), pi0)
        sol = diffrax.diffeqsolve(
            pk.PRKMKTerm(scene),
            pk.PRKMKSolver(verlet),
            0.0,
            steps * H,
            H,
            y0,
            inertia,
            max_steps=steps,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
        )
        return sol.ys.base.matrix[-1], sol.ys.fiber[-1]

    return {
        "integrate, stored steps": through_integrate(verlet, None),
        "integrate, ReversibleGradient": through_integrate(verlet, pk.ReversibleGradient(checkpoint_every=None)),
        "splitting, ReversibleGradient": through_integrate(splitting, pk.ReversibleGradient(checkpoint_every=None)),
        "diffeqsolve, RecursiveCheckpointAdjoint": through_diffeqsolve,
    }


def measure(name, final_state, batch, steps, rounds):
    qs, pis = C.initial_conditions(batch, seed=4)
    args = (jnp.asarray(qs), jnp.asarray(pis), jnp.asarray(C.INERTIA))
    loss = _loss_of(final_state)
    fns = {"forward": loss, "value_and_grad": jax.value_and_grad(loss, argnums=2)}
    compiled, compile_s, _ = C.compile_all(fns, *args)
    memory = compiled["value_and_grad"].memory_analysis()
    times = C.interleaved_times(compiled, *args, rounds=rounds)
    return dict(
        path=name,
        batch=batch,
        steps=steps,
        temp_bytes=int(memory.temp_size_in_bytes) if memory is not None else None,
        compile_s=compile_s,
        ns_per_traj_step=C.ns_per_trajectory_step(times, batch, steps),
        gradient_over_forward=C.median_ratio(times, "value_and_grad", "forward"),
    )


def main(argv=None):
    args, out = C.cli(__doc__, argv)
    if args.quick:
        grid, batch, rounds = (20,), 4, 2
    else:
        grid, batch, rounds = (1_000, 10_000, 100_000), 64, 5
    rows = []
    print(f"{'path':42s} {'steps':>7s} {'temp MB':>9s} {'grad/fwd':>8s} {'compile s':>9s}")
    for steps in grid:
        for name, final_state in _cases(steps).items():
            start = time.perf_counter()
            row = measure(name, final_state, batch, steps, rounds)
            rows.append(row)
            temp = "–" if row["temp_bytes"] is None else f"{row['temp_bytes'] / 1e6:.2f}"
            print(
                f"{name:42s} {steps:7d} {temp:>9s} {row['gradient_over_forward']:8.2f} {row['compile_s']['value_and_grad']:9.2f}"
                f"   ({time.perf_counter() - start:.0f} s)",
                flush=True,
            )
    with open(out / "gradients.json", "w") as f:
        json.dump(dict(machine=C.machine(), batch=batch, h=H, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
