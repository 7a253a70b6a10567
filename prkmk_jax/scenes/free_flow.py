"""The free rigid body's flow in closed form: Euler's equations Π' = Π × Ω
and the attitude Q' = QΩ (body form, Ω = I⁻¹Π, principal moments I),
from (Q, Π) at any time to (Q, Π) a time h later.

**The momentum** (Landau & Lifshitz §37). Name the axes c, s, d so that Π_c
= A_c cn u, Π_s = A_s sn u, Π_d = ±A_d dn u with u = σλt + u₀ and the
parameter k²: the dn axis d is the one of largest inertia when
|Π|² > 2H·I_mid (the body turns about it), of smallest otherwise; s is the
middle axis. The amplitudes, λ² and k² are ratios of the differences
2H·I_d − |Π|², |Π|² − 2H·I_c and |Π|² − 2H·I_s, each written as a sum over
the components of Π that does not cancel. u₀ = F(φ₀ | k²) with the phase
φ₀ = atan2(Π_s/A_s, Π_c/A_c); the direction σ follows from Euler's equation
for Π_s.

**The attitude** (after Celledoni, Fassò, Säfström & Zanna, SIAM J. Sci.
Comput. 30, 2008, in another frame). The spatial momentum QΠ is constant.
Let P(Π) be the rotation of least angle that takes Π/|Π| to e = ±e_d, the
sign of Π_d (Π never reaches −e: Π_d keeps its sign). Then

    Q(t) = Q(0) P(Π(0))ᵀ R_e(ψ(t)) P(Π(t)),

R_e(ψ) the rotation by ψ about e: it maps Π(t) to Q(0)Π(0)'s body image,
and Qᵀ Q' = Ω̂ holds when

    ψ' = (2H + |Π| Π_e/I_d)/(|Π| + Π_e) = |Π|/I_d + G/(|Π| + Π_e),

with Π_e = Π·e = A_d dn u > 0 and G = 2H − |Π|²/I_d. Since
1/(|Π| + Π_e) = (|Π| − A_d dn u)/(A_c² + (A_s² − A_c²) sn²u),

    ψ(h) = |Π|h/I_d + G/(σλ) [ |Π|/A_c² (Π(n; φ₁) − Π(n; φ₀)) − A_d/(A_c A_s) (Θ(φ₁) − Θ(φ₀)) ],

with n = 1 − A_s²/A_c² ≤ 0, φ = am u, Π(n; φ) = Π(n; φ | k²) the integral
of the third kind (`elliptic.ellippi`) and Θ(φ) = arctan((A_s/A_c) tan φ)
continued through every quarter turn. Every term is bounded; a body turning
steadily about its d axis (A_c = A_s = 0) turns by |Π|h/I_d, and the
symmetric bodies (two equal moments: k² = 0, sn = sin) and the sphere are
the same formulas. Differentiable in (Q, Π, I, h).

**Accuracy.** Both integrals are evaluated as functions of u, not of the
amplitude φ (`elliptic._third_kind_increment`): their integrands in u are
bounded, where Π(n; φ)'s sensitivity to φ, 1/((1 − n sin²φ)Δ), grows without
bound near a quarter turn as 1 − k² → 0 and magnified φ's rounding; sn, cn
and dn come with their own relative accuracy (`elliptic._reduced_jacobi`).
So a body near its middle axis (the Dzhanibekov spin: φ near a quarter turn,
1 − k² of the order of the squared offset) keeps its attitude to round-off.
A step's increments of the two integrals are summed from the differences
of like parts (`elliptic._third_kind_increment`), not taken as the
difference of their values at the ends: where Π precesses slowly (λ small)
ψ divides them by λ, and the ends' rounding would be multiplied.
The distance from the separatrix, |Π|² − 2H·I_mid, which sets 1 − k² and
the axis Π circles, is a difference of the state's terms and is computed
in twice the precision (`_separatrix_distance`), so that it is rounded
relative to itself. Closer to the separatrix than about 1e-10 (relative)
the flow itself is ill-conditioned (over T = 100 an ulp of Π moves the
exact attitude by up to 1e-3): the errors there are those of the problem,
since sn, cn and dn keep their relative accuracy as 1 − k² → 0 too
(`elliptic._jacobi_near_one`; design notes).
"""

import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import expm
from jaxtyping import Array, Float

from .. import elliptic, exact_flows
from .._bundles import BundleElement
from .._exact_sums import pair_times, two_product, two_sum
from ..groups import SO3, hat
from .base import attitude_like, rotation_matrix
from .body_frame import Attitude, InertiaOrderedFrame, body_rows, packed_in_frame, unpacked_from_frame


def _least_rotation(v: Array, e: Array) -> Array:
    """The rotation of least angle taking the unit vector v to the unit
    vector e (v·e > 0): I + ŵ + ŵ²/(1 + v·e), w = v × e."""
    w_hat = hat(jnp.cross(v, e))
    cosine = jnp.sum(v * e, axis=-1)[..., None, None]
    return jnp.eye(3, dtype=v.dtype) + w_hat + w_hat @ w_hat / (1 + cosine)


def _turn_about(e: Array, angle: Array) -> Array:
    """The rotation by `angle` about the unit vector e (Rodrigues)."""
    e_hat = hat(e)
    return jnp.eye(3, dtype=e.dtype) + jnp.sin(angle)[..., None, None] * e_hat + (1 - jnp.cos(angle))[..., None, None] * (e_hat @ e_hat)


def _take(v: Array, index: Array) -> Array:
    """v[..., index] for an index per row, as a sum of selected entries
    (elementwise arithmetic XLA fuses, where a gather is a kernel of its own)."""
    return jnp.sum(jnp.where(jnp.arange(3) == index[..., None], v, 0), axis=-1)


def _separatrix_distance(p_lo: Array, p_hi: Array, i_lo: Array, i_mid: Array, i_hi: Array) -> Array:
    """|Π|² − 2H·I_mid = Π_hi²(I_hi − I_mid)/I_hi − Π_lo²(I_mid − I_lo)/I_lo
    (Π_mid's terms cancel), to its own relative accuracy.

    Near the separatrix the two terms cancel, and rounded as they stand
    they would leave this difference, hence 1 − k² and the side of the
    separatrix, with an error of eps relative to the terms: an error of
    the evaluation, not of the state, which the period's logarithm
    ln(1/(1 − k²)) turns into an error in the phase. Computed as
    Π_hi²(I_hi − I_mid)I_lo − Π_lo²(I_mid − I_lo)I_hi in twice the working
    precision (exact squares and differences, products to ~eps²) and
    divided by I_hi·I_lo once, it is rounded relative to itself."""
    zero = jnp.zeros_like(p_lo)
    above = pair_times(pair_times(two_product(p_hi, p_hi), two_sum(i_hi, -i_mid)), (i_lo, zero))
    below = pair_times(pair_times(two_product(p_lo, p_lo), two_sum(i_mid, -i_lo)), (i_hi, zero))
    high, low = two_sum(above[0], -below[0])
    return (high + (low + (above[1] - below[1]))) / (i_hi * i_lo)


def free_body_flow(
    rotation: Float[Array, "*batch 3 3"], momentum: Float[Array, "*batch 3"], inertia: Float[Array, "*batch 3"], h: Float[Array, "*batch"]
) -> tuple[Float[Array, "*batch 3 3"], Float[Array, "*batch 3"]]:
    """(Q, Π) of the free rigid body a time h after (Q, Π) = (rotation,
    momentum), for principal moments `inertia` (module docstring). Leading
    batch axes broadcast.

    Where Π stands still (on a principal axis, Π = 0, or a sphere) the body
    turns steadily, Q exp(hΩ̂); there the elliptic formulas are 0/0, and the
    derivatives come from the flow's linearisation about the steady turn
    (`_steady_flow`), so gradients are finite and right everywhere."""
    dtype = jnp.result_type(rotation, momentum, inertia, h)
    q, pi, inertia, h = (jnp.asarray(a, dtype) for a in (rotation, momentum, inertia, h))
    pi, inertia = jnp.broadcast_arrays(pi, inertia)
    # Π stands still where it is an eigenvector of the inertia, tested
    # exactly: Π_i Π_j (I_i − I_j) = 0 for every pair of axes.
    standing = functools.reduce(
        jnp.logical_and, [pi[..., i] * pi[..., j] * (inertia[..., i] - inertia[..., j]) == 0 for i, j in ((0, 1), (1, 2), (0, 2))]
    )
    # The elliptic branch at a generic stand-in where Π stands still (double
    # `where`: its derivatives there are never 0·∞).
    pi_moving = jnp.where(standing[..., None], jnp.asarray([0.3, 0.5, 0.8], dtype), pi)
    inertia_moving = jnp.where(standing[..., None], jnp.asarray([1.0, 2.0, 3.0], dtype), inertia)
    q_moving, pi_next_moving = _moving_flow(q, pi_moving, inertia_moving, h)
    q_steady, pi_steady = _steady_flow(q, pi, inertia, jnp.broadcast_to(h, standing.shape))
    return jnp.where(standing[..., None, None], q_steady, q_moving), jnp.where(standing[..., None], pi_steady, pi_next_moving)


@jax.custom_jvp
def _steady_flow(q: Array, pi: Array, inertia: Array, h: Array) -> tuple[Array, Array]:
    """The flow from a state whose Π stands still: (Q exp(hΩ̂), Π)."""
    return q @ SO3.exp(pi / inertia * h[..., None]).matrix, pi


@_steady_flow.defjvp
def _steady_flow_jvp(primals, tangents):
    """About a steady turn Ω = I⁻¹Π, a perturbation Q ↦ Q(1 + ξ̂), Π ↦ Π + η
    moves by the constant-coefficient linear system ξ' = ξ × Ω + I⁻¹η + δ(I⁻¹)Π,
    η' = η × Ω + Π × I⁻¹η + Π × δ(I⁻¹)Π: (ξ, η)(h) = E (0, δΠ) + W b with
    E = exp(hM) and W = ∫₀ʰ exp(sM) ds, both read off one exponential of
    [[M, 1], [0, 0]]; the tangent in h is the field, (QΩ̂, 0)."""
    q, pi, inertia, h = primals
    dq, dpi, dinertia, dh = tangents
    omega = pi / inertia
    turn = SO3.exp(omega * h[..., None]).matrix
    q_next = q @ turn
    zeros = jnp.zeros(pi.shape + (3,), pi.dtype)
    inverse_inertia = jnp.eye(3, dtype=pi.dtype) / inertia[..., None, :]
    m = jnp.concatenate(
        [jnp.concatenate([-hat(omega), inverse_inertia], -1), jnp.concatenate([zeros, -hat(omega) + hat(pi) @ inverse_inertia], -1)], -2
    )
    augmented = jnp.concatenate(
        [jnp.concatenate([m, jnp.broadcast_to(jnp.eye(6, dtype=pi.dtype), m.shape)], -1), jnp.zeros(m.shape[:-2] + (6, 12), pi.dtype)], -2
    )
    exponential = jax.lax.stop_gradient(expm(h[..., None, None] * augmented))
    e, w = exponential[..., :6, :6], exponential[..., :6, 6:]
    kick = -dinertia / inertia**2 * pi  # δ(I⁻¹)Π
    b = jnp.concatenate([kick, jnp.cross(pi, kick)], -1)
    start = jnp.concatenate([jnp.zeros_like(dpi), dpi], -1)
    moved = jnp.einsum("...ij,...j->...i", e, start) + jnp.einsum("...ij,...j->...i", w, b)
    xi = moved[..., :3] + omega * dh[..., None]
    return (q_next, pi), (dq @ turn + q_next @ hat(xi), moved[..., 3:])


def _moving_flow(q: Array, pi: Array, inertia: Array, h: Array) -> tuple[Array, Array]:
    """The flow where Π moves: the elliptic formulas of the module docstring."""
    dtype = pi.dtype
    mu2 = jnp.sum(pi * pi, axis=-1)
    mu = jnp.sqrt(mu2)

    # The axes: lo, mid, hi by inertia (three distinct indices whatever the
    # ties: the first smallest, the last largest); d = hi where
    # |Π|² > 2H·I_mid, ties going to the axis further from the middle.
    lo = jnp.argmin(inertia, axis=-1)
    hi = 2 - jnp.argmax(inertia[..., ::-1], axis=-1)
    mid = 3 - lo - hi
    i_lo, i_mid, i_hi = _take(inertia, lo), _take(inertia, mid), _take(inertia, hi)
    separatrix_distance = _separatrix_distance(_take(pi, lo), _take(pi, hi), i_lo, i_mid, i_hi)
    about_hi = (separatrix_distance > 0) | ((separatrix_distance == 0) & (i_hi - i_mid >= i_mid - i_lo))
    c, s, d = jnp.where(about_hi, lo, hi), mid, jnp.where(about_hi, hi, lo)
    i_c, i_s, i_d = _take(inertia, c), _take(inertia, s), _take(inertia, d)
    p_c, p_s, p_d = _take(pi, c), _take(pi, s), _take(pi, d)

    # The differences of 2H·I and |Π|², as sums that do not cancel.
    d_c = p_c**2 * (i_d - i_c) / i_c + p_s**2 * (i_d - i_s) / i_s  # 2H·I_d − |Π|²
    d_d = p_s**2 * (i_s - i_c) / i_s + p_d**2 * (i_d - i_c) / i_d  # |Π|² − 2H·I_c
    d_s = separatrix_distance  # |Π|² − 2H·I_s, the same sum whichever of lo and hi is d
    g = p_c**2 * (1 / i_c - 1 / i_d) + p_s**2 * (1 / i_s - 1 / i_d)  # 2H − |Π|²/I_d
    # `free_body_flow` sends no state whose Π stands still here, but squares
    # of tiny components can underflow to a difference of 0, where every
    # ratio below is 0/0: safe stand-ins (double `where`), and Π(h) = Π,
    # ψ = |Π|h/I_d, the steady turn such a state is within round-off of.
    moving = (d_c != 0) & (d_d != 0) & (i_d != i_s)
    d_c, d_d, d_s = (jnp.where(moving, x, 1.0) for x in (d_c, d_d, d_s))
    gap_dc, gap_ds, gap_sc = jnp.where(moving, i_d - i_c, 1.0), jnp.where(moving, i_d - i_s, 1.0), i_s - i_c
    a_c2 = i_c * d_c / gap_dc
    a_s2 = i_s * d_c / gap_ds
    a_d2 = i_d * d_d / gap_dc
    lam = jnp.sqrt(gap_ds * d_d / (i_c * i_s * i_d))
    k2 = gap_sc * d_c / (gap_ds * d_d)
    k2c = gap_dc * d_s / (gap_ds * d_d)  # 1 − k², not cancelled
    a_c, a_s, a_d = jnp.sqrt(a_c2), jnp.sqrt(a_s2), jnp.sqrt(a_d2)

    # The direction of u: Π_s' = ε Π_c Π_d (1/I_c − 1/I_d), ε the sign of the
    # permutation (c, s, d), against Π_s' = A_s cn dn σλ.
    cyclic = (s - c) % 3 == 1
    sign_d = jnp.where(p_d >= 0, 1.0, -1.0).astype(dtype)
    sigma = jnp.where(cyclic, 1.0, -1.0) * sign_d * jnp.sign(i_d - i_c)
    phi0 = jnp.arctan2(p_s / a_s, p_c / a_c)
    u0 = elliptic._ellipf(phi0, k2, k2c)
    # sn, cn, dn at both ends, u = 2jK + r, from r's: each to its own
    # relative accuracy (one evaluation for the two ends). The end u₁ is
    # u₀ + σλh rounded; what the rounding drops (`end_error`, exact) is put
    # back into the attitude's increments below, to first order: over a step
    # short against u₀ it is much of the step's own increment.
    end, end_error = two_sum(u0, sigma * lam * h)
    ends = jnp.stack(jnp.broadcast_arrays(u0, end))
    reduced = elliptic._reduced_jacobi(ends, k2, k2c)
    turns, sine, cosine, delta = reduced
    parity = 1 - 2 * jnp.abs(turns[1] % 2)  # (−1)^j
    new_c, new_s, new_d = a_c * parity * cosine[1], a_s * parity * sine[1], sign_d * a_d * delta[1]
    axes = jnp.arange(3)
    pi_next = sum(jnp.where(axes == axis[..., None], value[..., None], 0.0) for axis, value in ((c, new_c), (s, new_s), (d, new_d)))
    pi_next = jnp.where(moving[..., None], pi_next, pi)

    # The turn ψ about e.
    n = 1 - a_s2 / a_c2

    # The increments of Θ(am u) = jπ + atan2(A_s sn r, A_c cn r) and of the
    # third kind over the step, as functions of u, each summed from the
    # differences of like parts (the ends' whole values are rounded at their
    # own size, which a short step far along would keep and g/λ magnify).
    within = jnp.arctan2(a_s * sine, a_c * cosine)
    theta_rate = a_c * a_s * delta[1] / (a_c2 * cosine[1] ** 2 + a_s2 * sine[1] ** 2)  # dΘ/du at u₁
    theta = (within[1] - within[0]) + (turns[1] - turns[0]) * jnp.pi + theta_rate * end_error
    third = elliptic._third_kind_increment(n, ends, k2, k2c, reduced) + end_error / (1 - n * sine[1] ** 2)
    bracket = mu / a_c2 * third - a_d / (a_c * a_s) * theta
    psi = mu * h / i_d + jnp.where(moving, g / (sigma * lam) * bracket, 0.0)

    e = sign_d[..., None] * jnp.where(axes == d[..., None], 1.0, 0.0).astype(dtype)
    before = _least_rotation(pi / mu[..., None], e)
    after = _least_rotation(pi_next / jnp.linalg.norm(pi_next, axis=-1, keepdims=True), e)
    q_next = q @ jnp.swapaxes(before, -1, -2) @ _turn_about(e, psi) @ after
    return q_next, pi_next


class FreeBodyFlow(exact_flows.AbstractExactFlow):
    """The kinetic energy ½Π·I⁻¹Π as one part of a splitting, its flow the
    free body's in closed form (`free_body_flow`), on a state packed in
    `frame` (`body_frame.packed_in_frame`): unpacked to the body's own
    axes, moved, packed again (a quaternion continued from the sub-step's
    start, `attitude_like`). Its coefficients are the moments and the step,
    so a sub-step is undone by the flow over −h, and its VJP is the flow's
    (`jax.vjp`). The splitting's coordinate map does not enter: the flow is
    exact whatever the map."""

    always_materialised: ClassVar[bool] = True  # pyright: ignore[reportIncompatibleVariableOverride]  # implements an AbstractClassVar
    frame: InertiaOrderedFrame
    moments: Array
    """The principal moments in the body's own axes, (3,) or (*batch, 3)."""
    attitude: Attitude = eqx.field(static=True, default=SO3)
    """How the packed state holds the attitude: `SO3` or `UnitQuaternion`."""

    @property
    def reads_unmoved_rows_only(self) -> bool:
        return True  # the coefficients read no row

    def coefficients(self, coordinates, t, z, h, args):
        del coordinates, t, z, args
        return self.moments, h

    def moved(self, z, coefficients):
        moments, h = coefficients
        # The body's rows come first; rows after them (a position and its
        # momentum, `Satellite`) are not the free body's and stand still.
        rows = body_rows(self.attitude)
        y = unpacked_from_frame(z[:rows], self.attitude, self.frame)
        q, pi = free_body_flow(rotation_matrix(y.base), y.fiber, moments, h)
        moved = packed_in_frame(BundleElement(attitude_like(y.base, q), pi), self.frame)
        return moved if z.shape[0] == rows else jnp.concatenate([moved, z[rows:]])

    def moved_change(self, start, change, coefficients):
        # Rounded relative to the state, not to the change: the closed form
        # has no part that is the change alone.
        return self.moved(start + change, coefficients) - start

    def moved_back(self, z, coefficients):
        moments, h = coefficients
        return self.moved(z, (moments, -h))

    def pulled_back(self, z, coefficients, cotangent):
        _, pull = jax.vjp(self.moved, z, coefficients)
        return pull(cotangent)
