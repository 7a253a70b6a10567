"""Invariants of rigid-body trajectories, the symplecticity defect of a step
map, and how the runs of a stability sweep ended.

Everything here takes the body attitude g ∈ SO(n) and body angular momentum
Π (arrays with any leading axes, e.g. a time axis): a 3-vector for SO(3), or a
skew (n, n) matrix with `matrix=True`, paired by ⟨A, B⟩ = ½ tr(AᵀB) so that
both forms agree for n = 3. The scenes convert their states to (g, Π)
(`scenes.rigid_body.attitude_and_momentum`).
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PyTree

from .groups import SO3
from .groups._util import orthogonality_defect as _orthogonality_defect


def _pairing(a, b, matrix):
    if matrix:
        return 0.5 * jnp.sum(a * b, axis=(-2, -1))
    return jnp.sum(a * b, axis=-1)


def energy(momentum: Array, velocity: Array, matrix: bool = False) -> Array:
    """Hamiltonian H = ½⟨Π, Ω⟩ with Ω = I⁻¹Π the body angular velocity."""
    return 0.5 * _pairing(momentum, velocity, matrix)


def body_momentum_norm(momentum: Array, matrix: bool = False) -> Array:
    """|Π| = ⟨Π, Π⟩^½, the Casimir of the rigid body."""
    return jnp.sqrt(_pairing(momentum, momentum, matrix))


def spatial_momentum(g: Array, momentum: Array, matrix: bool = False) -> Array:
    """Ad_g Π: gΠ (vector form) or gΠgᵀ (matrix form), constant along the exact flow."""
    if matrix:
        return g @ momentum @ jnp.swapaxes(g, -1, -2)
    return jnp.einsum("...ij,...j->...i", g, momentum)


def orthogonality_defect(g: Float[Array, "*t n n"]) -> Float[Array, "*t"]:
    """max |gᵀg − I|."""
    return _orthogonality_defect(g)


def max_drift(values: Float[Array, " t *c"], relative: bool = False) -> Array:
    """max_t |values(t) − values(0)| (over all components), optionally divided by max|values(0)|."""
    drift = jnp.max(jnp.abs(values - values[0]))
    if relative:
        drift = drift / jnp.max(jnp.abs(values[0]))
    return drift


RUN_STATUS = ("bounded", "energy drift", "implicit stage failed", "non-finite")
"""What `run_status` calls its codes 0, 1, 2, 3."""


def run_status(
    energy: Float[Array, "runs t"], converged: Bool[Array, " runs"], states: PyTree[Array] = None, tolerance: float = 0.1
) -> Int[Array, " runs"]:
    """How each of a batch of runs ended, as an index into `RUN_STATUS`.

    3 (non-finite) if the energy or any leaf of `states` (leading axis: the
    runs) is not finite somewhere; else 2 if an implicit stage did not
    converge (`converged` false); else 0 (bounded) if
    max_t |H(t)/H(0) − 1| < `tolerance`, and 1 (energy drift) if not.
    """
    energy = jnp.asarray(energy)
    runs = energy.shape[0]
    finite = jnp.all(jnp.isfinite(energy), axis=1)
    for leaf in jax.tree.leaves(states):
        finite = finite & jnp.all(jnp.isfinite(jnp.reshape(leaf, (runs, -1))), axis=1)
    drift = jnp.max(jnp.abs(energy / energy[:, :1] - 1), axis=1)
    return jnp.where(~finite, 3, jnp.where(~jnp.asarray(converged), 2, jnp.where(drift < tolerance, 0, 1)))


def first_unbounded(status: Int[Array, " runs"]) -> int | None:
    """The index of the first run of a sweep that did not stay bounded
    (status ≠ 0 in `run_status`), or None if every run did."""
    failed = np.flatnonzero(np.asarray(status) != 0)
    return int(failed[0]) if failed.size else None


def stability_threshold(values: Float[Array, " runs"], status: Int[Array, " runs"]) -> float:
    """The largest of the ascending sweep `values` before the first run that
    did not stay bounded (`first_unbounded`); 0.0 if the first run fails,
    the last value if none does."""
    values_ = np.asarray(values)
    if values_.shape != np.shape(status) or np.any(np.diff(values_) <= 0):
        raise ValueError("stability_threshold needs ascending values, one status per value.")
    first = first_unbounded(status)
    first = values_.size if first is None else first
    return float(values_[first - 1]) if first > 0 else 0.0


def to_canonical(g0: Float[Array, "3 3"], g: Float[Array, "3 3"], pi: Float[Array, "3"]) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Canonical coordinates (q, p) on T*SO(3) near g₀: g = g₀ exp(q) and p
    the momentum conjugate to q, ⟨Π, g⁻¹ġ⟩ = ⟨p, q̇⟩.

    g⁻¹ġ = dexp_{−q} q̇, so p = dexp_{−q}ᵀ Π. In so(3) ≅ ℝ³ the matrix of
    dexp_u is I + b û + c û² with b, c even in |u|, and ûᵀ = −û, so
    dexp_{−q}ᵀ = dexp_q: p = dexp_q Π, in closed form (`SO3.dexp`).
    """
    q = SO3(g0.T @ g).log()
    return q, SO3.dexp(q, pi)


def from_canonical(g0: Float[Array, "3 3"], q: Float[Array, "3"], p: Float[Array, "3"]) -> tuple[Float[Array, "3 3"], Float[Array, "3"]]:
    """Inverse of `to_canonical`: g = g₀ exp(q), Π = dexp_q⁻¹ p (`SO3.dexp_inv`,
    closed form; |q| ≤ π from the logarithm)."""
    return g0 @ SO3.exp(q).matrix, SO3.dexp_inv(q, p)


def symplecticity_defect(step_map: Callable, g0: Float[Array, "3 3"], pi0: Float[Array, "3"]) -> Array:
    """max |ΦᵀJΦ − J| for Φ the Jacobian, by `jax.jacfwd`, of a map on T*SO(3)
    written in the canonical coordinates of `to_canonical` around g₀.

    `step_map(g, Π) -> (g', Π')` is one step of an integrator on (g, Π). The
    exact flow and every symplectic method give 0 up to round-off.
    """

    def in_coordinates(z):
        g, pi = from_canonical(g0, z[:3], z[3:])
        g1, pi1 = step_map(g, pi)
        q1, p1 = to_canonical(g0, g1, pi1)
        return jnp.concatenate([q1, p1])

    z0 = jnp.concatenate(to_canonical(g0, g0, pi0))
    return canonical_symplecticity_defect(in_coordinates, z0)


def canonical_symplecticity_defect(map_: Callable, z0: Float[Array, "2n"]) -> Array:
    """max |ΦᵀJΦ − J| of a map ℝ²ⁿ → ℝ²ⁿ in canonical coordinates z = (q, p)."""
    n = z0.shape[0] // 2
    phi = jax.jacfwd(map_)(z0)
    eye, zero = jnp.eye(n, dtype=z0.dtype), jnp.zeros((n, n), z0.dtype)
    J = jnp.block([[zero, eye], [-eye, zero]])
    return jnp.max(jnp.abs(phi.T @ J @ phi - J))
