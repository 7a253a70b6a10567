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
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import elliptic
from ..groups import hat


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
    return jnp.take_along_axis(v, index[..., None], axis=-1)[..., 0]


def free_body_flow(
    rotation: Float[Array, "*batch 3 3"], momentum: Float[Array, "*batch 3"], inertia: Float[Array, "*batch 3"], h: Float[Array, "*batch"]
) -> tuple[Float[Array, "*batch 3 3"], Float[Array, "*batch 3"]]:
    """(Q, Π) of the free rigid body a time h after (Q, Π) = (rotation,
    momentum), for principal moments `inertia` (module docstring). Leading
    batch axes broadcast."""
    q, pi, inertia = rotation, momentum, inertia
    dtype = jnp.result_type(q, pi, inertia, h)
    q, pi, inertia, h = (jnp.asarray(a, dtype) for a in (q, pi, inertia, h))
    pi, inertia = jnp.broadcast_arrays(pi, inertia)
    squares = pi * pi
    mu2 = jnp.sum(squares, axis=-1)
    mu = jnp.sqrt(mu2)

    # The axes: lo, mid, hi by inertia; d = hi where |Π|² > 2H·I_mid, i.e.
    # Π_hi²(I_hi − I_mid)/I_hi > Π_lo²(I_mid − I_lo)/I_lo (the other terms
    # cancel), with ties going to the axis further from the middle one.
    order = jnp.argsort(inertia, axis=-1)
    lo, mid, hi = order[..., 0], order[..., 1], order[..., 2]
    i_lo, i_mid, i_hi = _take(inertia, lo), _take(inertia, mid), _take(inertia, hi)
    above = _take(squares, hi) * (i_hi - i_mid) / i_hi
    below = _take(squares, lo) * (i_mid - i_lo) / i_lo
    about_hi = (above > below) | ((above == below) & (i_hi - i_mid >= i_mid - i_lo))
    c, s, d = jnp.where(about_hi, lo, hi), mid, jnp.where(about_hi, hi, lo)
    i_c, i_s, i_d = _take(inertia, c), _take(inertia, s), _take(inertia, d)
    p_c, p_s, p_d = _take(pi, c), _take(pi, s), _take(pi, d)

    # The differences of 2H·I and |Π|², as sums that do not cancel.
    d_c = p_c**2 * (i_d - i_c) / i_c + p_s**2 * (i_d - i_s) / i_s  # 2H·I_d − |Π|²
    d_d = p_s**2 * (i_s - i_c) / i_s + p_d**2 * (i_d - i_c) / i_d  # |Π|² − 2H·I_c
    d_s = p_c**2 * (i_c - i_s) / i_c + p_d**2 * (i_d - i_s) / i_d  # |Π|² − 2H·I_s
    g = p_c**2 * (1 / i_c - 1 / i_d) + p_s**2 * (1 / i_s - 1 / i_d)  # 2H − |Π|²/I_d
    # Where Π stands still (on the d axis, or a sphere), every ratio below
    # is 0/0: safe stand-ins (double `where`), and Π(h) = Π, ψ = |Π|h/I_d.
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
    sn, cn, dn, phi1 = elliptic._jacobi(u0 + sigma * lam * h, k2, k2c)
    new_c, new_s, new_d = a_c * cn, a_s * sn, sign_d * a_d * dn
    axes = jnp.arange(3)
    pi_next = sum(jnp.where(axes == axis[..., None], value[..., None], 0.0) for axis, value in ((c, new_c), (s, new_s), (d, new_d)))
    pi_next = jnp.where(moving[..., None], pi_next, pi)

    # The turn ψ about e.
    n = 1 - a_s2 / a_c2

    def theta(phi):
        turns = jnp.round(phi / jnp.pi)
        reduced = phi - turns * jnp.pi
        return jnp.arctan2(a_s * jnp.sin(reduced), a_c * jnp.cos(reduced)) + turns * jnp.pi

    # Both ends in one evaluation of each integral (one program, not two).
    ends = jnp.stack(jnp.broadcast_arrays(phi0, phi1))
    third = elliptic._ellippi(n, ends, k2, k2c)
    bracket = mu / a_c2 * (third[1] - third[0]) - a_d / (a_c * a_s) * (theta(ends[1]) - theta(ends[0]))
    psi = mu * h / i_d + jnp.where(moving, g / (sigma * lam) * bracket, 0.0)

    e = sign_d[..., None] * jnp.where(axes == d[..., None], 1.0, 0.0).astype(dtype)
    before = _least_rotation(pi / mu[..., None], e)
    after = _least_rotation(pi_next / jnp.linalg.norm(pi_next, axis=-1, keepdims=True), e)
    q_next = q @ jnp.swapaxes(before, -1, -2) @ _turn_about(e, psi) @ after
    # Π on a principal axis (or Π = 0) stands still, and the body turns
    # steadily about it: Q exp(hΩ̂). (On the middle axis this is the
    # separatrix's fixed point, where u₀ above is infinite.)
    omega = pi / inertia
    standing = jnp.all(jnp.cross(pi, omega) == 0, axis=-1) | (mu2 == 0)
    rate2 = jnp.sum(omega * omega, axis=-1)
    rate = jnp.sqrt(jnp.where(standing & (rate2 > 0), rate2, 1.0))
    axis = omega / rate[..., None]
    steady = q @ _turn_about(axis, jnp.where(standing, rate * h, 0.0))
    return jnp.where(standing[..., None, None], steady, q_next), jnp.where(standing[..., None], pi, pi_next)
