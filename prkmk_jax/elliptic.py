"""Jacobi's elliptic functions and Legendre's elliptic integrals of the first
and third kinds, in JAX: jittable, vmappable, differentiable in forward and
reverse mode, in float32 and float64.

They are what the free rigid body's exact flow is written in
(`scenes.free_flow`): its body momentum is (cn, sn, dn) of a linear
function of time and its attitude turns by an integral of the third kind.
The parameter is m = k² (SciPy's convention); every function takes arrays
that broadcast against each other.

* `jacobi(u, m)`: sn, cn, dn and the amplitude am(u | m) for 0 ≤ m ≤ 1, by
  the arithmetic–geometric mean and descending Landen transformations
  (Abramowitz & Stegun 16.4), a fixed number of levels, enough for the
  parameter nearest 1 the dtype holds. The amplitude is continuous in u
  (it grows by π every 2K), which the third kind's argument needs.
* `carlson_rf`, `carlson_rd`, `carlson_rj`: Carlson's symmetric integrals by
  duplication (Carlson, Numer. Algorithms 10, 1995; DLMF 19.36), a fixed
  number of steps and the fifth-order series after them.
* `ellipk(m)`, `ellipf(phi, m)`, `ellippi(n, phi, m)`: the complete and
  incomplete integrals of the first kind and the incomplete integral of the
  third kind (DLMF 19.2.4, 19.2.7), for any real amplitude through their
  quasi-periodicity F(φ + jπ) = F(φ) + 2jK.

Derivatives: autodiff through the iterations, except in the amplitude of
the incomplete integrals, whose derivative is written out (1/Δ and
1/((1 − n sin²φ)Δ), Δ = √(1 − m sin²φ)): in Carlson's form the amplitude
enters as cos²φ, which vanishes at φ = π/2, where the chain rule would
multiply an infinite partial derivative by zero.

Outside the domain (m > 1 or m < 0, n sin²φ ≥ 1) the values are NaN, as
`jnp.sqrt` of a negative number is; m = 1 gives the limits (sn = tanh,
K = ∞).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

# Levels of the arithmetic–geometric mean: it converges quadratically once
# a and b are within a factor of 2, which from b₀ = √(1 − m) takes about
# log₂(ln(4/b₀)) levels; 16 cover 1 − m down to the smallest float64.
_AGM_LEVELS = 16
# Duplication steps: once the arguments are within a small factor of each
# other, each step divides their relative spread by 4, and the series after
# the steps errs by about the sixth power of that spread: from a spread of 4,
# ten steps leave 4·4⁻¹⁰ ≈ 4e-6, whose sixth power is far below float64's
# epsilon. R_F pulls its arguments together quadratically (their ratios
# square-root at each step); R_J's p comes down only by 4 per step towards x,
# y and z, so R_J takes log₄ of p's ratio to them more: 16 steps keep it
# accurate for p up to about 10⁶ times the largest of x, y, z.
_DUPLICATIONS = 10
_RJ_DUPLICATIONS = 16


def _float(*xs: ArrayLike) -> tuple[Array, ...]:
    dtype = jnp.result_type(float, *xs)
    return tuple(jnp.asarray(x, dtype) for x in xs)


def _sqrt(x: Array) -> Array:
    """√x, with a finite derivative at 0 (the square roots of duplication
    meet x = 0 at a complete integral, where the derivative of the result
    is finite)."""
    return jnp.sqrt(jnp.maximum(x, jnp.finfo(x.dtype).tiny))


# --- Jacobi's functions ------------------------------------------------------------


def jacobi(u: ArrayLike, m: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """(sn, cn, dn, am) of u for the parameter 0 ≤ m ≤ 1 (`scipy.special.ellipj`)."""
    u, m = _float(u, m)
    return _jacobi(u, m, 1 - m)


def _jacobi(u: Array, m: Array, m1: Array) -> tuple[Array, Array, Array, Array]:
    """`jacobi` with the complementary parameter m1 = 1 − m given on its
    own, for a caller that knows it more accurately than 1 − m rounds it."""
    u, m, m1 = jnp.broadcast_arrays(u, m, m1)
    at_one = m1 == 0
    m1_safe = jnp.where(at_one, 0.5, m1)
    m_safe = jnp.where(at_one, 0.5, m)

    # a, b, c of the arithmetic–geometric mean from (1, √m1, √m), with
    # c_{j+1} = c_j²/(4 a_{j+1}) = (a_j − b_j)/2 computed without the difference.
    def mean_level(carry, _):
        a, b, c_squared = carry
        a_next = (a + b) / 2
        c_next = c_squared / (4 * a_next)
        return (a_next, jnp.sqrt(a * b), c_next * c_next), (a_next, c_next)

    start = (jnp.ones_like(u), jnp.sqrt(m1_safe), m_safe)
    (a, _, _), (a_levels, c_levels) = jax.lax.scan(mean_level, start, length=_AGM_LEVELS)

    # φ_N = 2^N a_N u, then φ_{j−1} = (φ_j + arcsin(c_j sin φ_j / a_j))/2: the
    # scalings by powers of 2 are exact, so φ keeps u's relative precision.
    def landen_level(phi, level):
        a_j, c_j = level
        return (phi + jnp.arcsin(c_j / a_j * jnp.sin(phi))) / 2, None

    phi, _ = jax.lax.scan(landen_level, (2.0**_AGM_LEVELS) * a * u, (a_levels, c_levels), reverse=True)
    sn, cn = jnp.sin(phi), jnp.cos(phi)
    # dn² = m1 + m cn²: two terms ≥ 0, no cancellation as m → 1.
    dn = jnp.sqrt(m1_safe + m_safe * cn * cn)
    # m = 1: sn = tanh u, cn = dn = sech u, am = gd(u).
    sech = 1 / jnp.cosh(jnp.where(at_one, u, 0.0))
    sn = jnp.where(at_one, jnp.tanh(u), sn)
    cn = jnp.where(at_one, sech, cn)
    dn = jnp.where(at_one, sech, dn)
    am = jnp.where(at_one, 2 * jnp.arctan(jnp.tanh(u / 2)), phi)
    return sn, cn, dn, am


_NEAR_ONE = 1e-3
"""Below this 1 − m, `_reduced_jacobi` takes the functions from
`_jacobi_near_one`, whose `_ASCENDING_LEVELS` leave a parameter within
about (1 − m)⁸/(3·10⁸) of 1 (each level squares it and divides by 16)."""
_ASCENDING_LEVELS = 3


def _jacobi_near_one(x: Array, m1: Array) -> tuple[Array, Array, Array]:
    """(sn, cn, dn) of x for 1 − m = m1 ≤ `_NEAR_ONE` and |x| ≤ K/2, each to
    its own relative accuracy, by ascending Landen transformations
    (DLMF 22.7.4–6): with k = √m and k₂′ = (1 − k)/(1 + k) = m1/(1 + k)²,
    sn(x, k) = 2/(1 + k)·sn cn/dn, cn(x, k) = (1 + k)/(2k)·(dn² − k₂′)/dn and
    dn(x, k) = (1 + k)/2·(dn² + k₂′)/dn, the right-hand sides at
    w = (1 + k)x/2 and modulus k₂, whose 1 − k₂² is about (m1/4)². After
    `_ASCENDING_LEVELS` the parameter is 1 to far below an ulp over
    |w| ≤ K/2 (the error of taking it as 1 grows like the last level's 1 − m times e^{2|w|}),
    where sn = tanh w and cn = dn = sech w: no amplitude is formed, so cn
    and dn keep their relative accuracy where they are small (near K/2,
    both about √k′). dn² − k₂′ does not cancel there: k₂′ ≈ k′²/4 against
    dn² ≈ k′."""
    moduli, complements = [], [m1]
    for _ in range(_ASCENDING_LEVELS):
        k = jnp.sqrt(1 - complements[-1])
        moduli.append(k)
        complements.append((complements[-1] / (1 + k) ** 2) ** 2)
    # w = x·Π(1 + k)/2 as x − x·δ, δ = 1 − Π(1 − (1 − k)/2) small and
    # (1 − k)/2 = m1/(2(1 + k)): w rounded once, as sech w's relative
    # accuracy asks (it loses w's absolute error).
    shrink = jnp.zeros_like(m1)
    for k, m1_level in zip(moduli, complements):
        part = m1_level / (2 * (1 + k))
        shrink = shrink + part - shrink * part
    w = x - x * shrink
    sech = 1 / jnp.cosh(w)
    sn, cn, dn = jnp.tanh(w), sech, sech
    for level in reversed(range(_ASCENDING_LEVELS)):
        k, k2_complement = moduli[level], complements[level] / (1 + moduli[level]) ** 2
        dn_squared = dn * dn
        sn, cn, dn = (
            2 / (1 + k) * sn * cn / dn,
            (1 + k) / (2 * k) * (dn_squared - k2_complement) / dn,
            (1 + k) / 2 * (dn_squared + k2_complement) / dn,
        )
    # sn² + cn² = 1 and dn² = m1 + m·cn² to round-off, as sin, cos and
    # `_jacobi`'s dn hold them: a state built from these stays on its
    # invariant surfaces without a lean (the transformations' own rounding
    # need not cancel on average).
    radius = jnp.sqrt(sn * sn + cn * cn)
    sn, cn = sn / radius, cn / radius
    return sn, cn, jnp.sqrt(m1 + (1 - m1) * cn * cn)


def _reduced_jacobi(u: Array, m: Array, m1: Array) -> tuple[Array, Array, Array, Array]:
    """u = 2jK + r with |r| ≤ K: (j, sn r, cn r ≥ 0, dn r), for 0 ≤ m < 1.

    Each to a few ulps *relative*, cn r and dn r too where they are small:
    `_jacobi` gives cn = cos φ of an amplitude φ that rounds to an absolute
    error of an ulp of φ, which is much of cn near a quarter turn (cn r →
    0) when 1 − m is small. Past half a quarter period, |r| > K/2, the
    functions come from v = K − |r| instead: sn(K − v) = cn v/dn v,
    cn(K − v) = k′ sn v/dn v, dn(K − v) = k′/dn v (k′ = √m1), where v's
    amplitude is at most am(K/2) and cn v at least √(k′/(1 + k′)). For
    1 − m ≤ `_NEAR_ONE` the functions of |r| or v ≤ K/2 come from
    `_jacobi_near_one` instead: `_jacobi`'s descending Landen recursion works
    there with an arcsin near 1 and multiplies the amplitude's rounding by
    about 1/dn, which near K/2 left cn and dn (both near √k′) with a
    relative error of about ε/k′ (ε the machine epsilon)."""
    quarter = _ellipk(m1)  # ∞ at m = 1: then j = 0, r = u and the near branch
    u, m, m1, quarter = jnp.broadcast_arrays(u, m, m1, quarter)
    j = jnp.round(u / (2 * quarter))
    r = jnp.where(j == 0, u, u - 2 * j * quarter)
    far = jnp.abs(r) > quarter / 2
    within_half = jnp.where(far, quarter - jnp.abs(r), r)
    sn_v, cn_v, dn_v, _ = _jacobi(within_half, m, m1)
    near_one = m1 <= _NEAR_ONE
    # Both branches are finite for every m1 (double `where`): the other's stand-in is m = 1.
    near = _jacobi_near_one(within_half, jnp.where(near_one, m1, 0.0))
    sn_v, cn_v, dn_v = (jnp.where(near_one, a, b) for a, b in zip(near, (sn_v, cn_v, dn_v)))
    k1 = jnp.sqrt(m1)
    sn = jnp.where(far, jnp.sign(r) * cn_v / dn_v, sn_v)
    cn = jnp.where(far, k1 * sn_v / dn_v, cn_v)
    dn = jnp.where(far, k1 / dn_v, dn_v)
    return j, sn, cn, dn


# --- Carlson's symmetric integrals -------------------------------------------------


def carlson_rf(x: ArrayLike, y: ArrayLike, z: ArrayLike) -> Array:
    """R_F(x, y, z) = ½∫₀^∞ dt/√((t + x)(t + y)(t + z)), x, y, z ≥ 0, at most
    one of them 0 (`scipy.special.elliprf`)."""
    x, y, z = jnp.broadcast_arrays(*_float(x, y, z))

    def duplication(_, xyz):
        x, y, z = xyz
        sx, sy, sz = _sqrt(x), _sqrt(y), _sqrt(z)
        lam = sx * sy + sy * sz + sz * sx
        return (x + lam) / 4, (y + lam) / 4, (z + lam) / 4

    x, y, z = jax.lax.fori_loop(0, _DUPLICATIONS, duplication, (x, y, z))
    a = (x + y + z) / 3
    dx, dy = 1 - x / a, 1 - y / a
    dz = -dx - dy
    e2, e3 = dx * dy - dz * dz, dx * dy * dz
    return jnp.asarray((1 - e2 / 10 + e3 / 14 + e2 * e2 / 24 - 3 * e2 * e3 / 44) / jnp.sqrt(a))


def _rc_one(e: Array) -> Array:
    """R_C(1, 1 + e) = arctan(√e)/√e (e > 0), artanh(√−e)/√−e (−1 < e < 0),
    its series near e = 0 (double `where`: finite derivatives there)."""
    small = jnp.abs(e) < 1e-3
    safe = jnp.where(small, 1.0, e)
    root = jnp.sqrt(jnp.abs(safe))
    far = jnp.where(safe > 0, jnp.arctan(root), jnp.arctanh(root)) / root
    near = 1 - e / 3 + e**2 / 5 - e**3 / 7 + e**4 / 9 - e**5 / 11
    return jnp.where(small, near, far)


def carlson_rj(x: ArrayLike, y: ArrayLike, z: ArrayLike, p: ArrayLike) -> Array:
    """R_J(x, y, z, p) = 3/2 ∫₀^∞ dt/((t + p)√((t + x)(t + y)(t + z))),
    x, y, z ≥ 0 (at most one 0), p > 0 and at most about 10⁶·max(x, y, z)
    (`scipy.special.elliprj`)."""
    x, y, z, p = jnp.broadcast_arrays(*_float(x, y, z, p))
    delta = (p - x) * (p - y) * (p - z)

    def duplication(j, carry):
        x, y, z, p, total = carry
        sx, sy, sz, sp = _sqrt(x), _sqrt(y), _sqrt(z), _sqrt(p)
        lam = sx * sy + sy * sz + sz * sx
        d = (sp + sx) * (sp + sy) * (sp + sz)
        quarter = jnp.asarray(0.25, x.dtype) ** j
        e = delta * quarter**3 / (d * d)
        total = total + quarter * _rc_one(e) / d
        return (x + lam) / 4, (y + lam) / 4, (z + lam) / 4, (p + lam) / 4, total

    x, y, z, p, total = jax.lax.fori_loop(0, _RJ_DUPLICATIONS, duplication, (x, y, z, p, jnp.zeros_like(x)))
    a = (x + y + z + 2 * p) / 5
    dx, dy, dz = 1 - x / a, 1 - y / a, 1 - z / a
    dp = -(dx + dy + dz) / 2
    xyz = dx * dy * dz
    e2 = dx * dy + dx * dz + dy * dz - 3 * dp * dp
    e3 = xyz + 2 * e2 * dp + 4 * dp**3
    e4 = (2 * xyz + e2 * dp + 3 * dp**3) * dp
    e5 = xyz * dp * dp
    series = 1 - 3 * e2 / 14 + e3 / 6 + 9 * e2 * e2 / 88 - 3 * e4 / 22 - 9 * e2 * e3 / 52 + 3 * e5 / 26
    return series / (4.0**_RJ_DUPLICATIONS * a * jnp.sqrt(a)) + 6 * total


def carlson_rd(x: ArrayLike, y: ArrayLike, z: ArrayLike) -> Array:
    """R_D(x, y, z) = R_J(x, y, z, z), z > 0 (`scipy.special.elliprd`)."""
    return carlson_rj(x, y, z, z)


# --- Legendre's integrals ----------------------------------------------------------


def ellipk(m: ArrayLike) -> Array:
    """K(m) = F(π/2 | m), m ≤ 1 (`scipy.special.ellipk`)."""
    (m,) = _float(m)
    return _ellipk(1 - m)


def _ellipk(m1: Array) -> Array:
    """K from the complementary parameter m1 = 1 − m."""
    return carlson_rf(jnp.zeros_like(m1), m1, jnp.ones_like(m1))


def _quarter_turns(phi: Array) -> tuple[Array, Array, Array]:
    """φ = jπ + φ_r with |φ_r| ≤ π/2: (j, sin φ_r, cos φ_r), cos φ_r ≥ 0. The
    incomplete integrals, and any function of φ continued through every
    quarter turn, are written on φ_r."""
    j = jnp.round(phi / jnp.pi)
    reduced = phi - j * jnp.pi
    return j, jnp.sin(reduced), jnp.cos(reduced)


def ellipf(phi: ArrayLike, m: ArrayLike) -> Array:
    """F(φ | m) = ∫₀^φ dθ/√(1 − m sin²θ), any real φ, m < 1
    (`scipy.special.ellipkinc`)."""
    phi, m = jnp.broadcast_arrays(*_float(phi, m))
    return _ellipf(phi, m, 1 - m)


@jax.custom_jvp
def _ellipf(phi: Array, m: Array, m1: Array) -> Array:
    return _ellipf_value(phi, m, m1)


def _ellipf_value(phi, m, m1):
    del m  # read through m1
    j, s, c = _quarter_turns(phi)
    c2, s2 = c * c, s * s
    # 1 − m sin²φ as cos²φ + m1 sin²φ: no cancellation as m → 1.
    reduced = s * carlson_rf(c2, c2 + m1 * s2, jnp.ones_like(phi))
    return jnp.where(j == 0, reduced, reduced + 2 * j * _ellipk(m1))


@_ellipf.defjvp
def _ellipf_jvp(primals, tangents):
    phi, m, m1 = primals
    d_phi, d_m, d_m1 = tangents
    s2 = jnp.sin(phi) ** 2
    value, d_params = jax.jvp(lambda m, m1: _ellipf_value(jax.lax.stop_gradient(phi), m, m1), (m, m1), (d_m, d_m1))
    return value, d_params + d_phi / jnp.sqrt(jnp.cos(phi) ** 2 + m1 * s2)


def ellippi(n: ArrayLike, phi: ArrayLike, m: ArrayLike) -> Array:
    """Π(n; φ | m) = ∫₀^φ dθ/((1 − n sin²θ)√(1 − m sin²θ)), any real φ,
    m < 1, n < 1 (SciPy has no incomplete third kind; with Carlson's forms,
    DLMF 19.25.14)."""
    n, phi, m = jnp.broadcast_arrays(*_float(n, phi, m))
    return _ellippi(n, phi, m, 1 - m)


@jax.custom_jvp
def _ellippi(n: Array, phi: Array, m: Array, m1: Array) -> Array:
    return _ellippi_value(n, phi, m, m1)


def _parameters_ones(n: Array, m1: Array, dtype) -> Array:
    """Ones at the parameters' shape, where a complete integral is computed:
    amplitudes stacked on a leading axis (several ends of one interval)
    share it."""
    return jnp.ones(jnp.broadcast_shapes(jnp.shape(n), jnp.shape(m1)), dtype)


def _reduced_pair(n, s, c2, s2, m1):
    """(F(φ_r), Π(n; φ_r)) of a reduced amplitude, |φ_r| ≤ π/2, from its sine
    s, cos²φ_r = c2 and sin²φ_r = s2."""
    delta2 = c2 + m1 * s2
    ones = jnp.ones_like(s)
    first = s * carlson_rf(c2, delta2, ones)
    return first, first + n / 3 * s * s2 * carlson_rj(c2, delta2, ones, 1 - n * s2)


def _ellippi_value(n, phi, m, m1):
    del m  # read through m1
    j, s, c = _quarter_turns(phi)
    reduced = _reduced_pair(n, s, c * c, s * s, m1)[1]
    ones = _parameters_ones(n, m1, reduced.dtype)
    complete = _reduced_pair(n, ones, 0 * ones, ones, m1)[1]
    return jnp.where(j == 0, reduced, reduced + 2 * j * complete)


@_ellippi.defjvp
def _ellippi_jvp(primals, tangents):
    n, phi, m, m1 = primals
    d_n, d_phi, d_m, d_m1 = tangents
    s2 = jnp.sin(phi) ** 2
    frozen = jax.lax.stop_gradient(phi)
    value, d_params = jax.jvp(lambda n, m, m1: _ellippi_value(n, frozen, m, m1), (n, m, m1), (d_n, d_m, d_m1))
    return value, d_params + d_phi / ((1 - n * s2) * jnp.sqrt(jnp.cos(phi) ** 2 + m1 * s2))


def _incomplete_pair(n: Array, j: Array, s: Array, c: Array, m1: Array) -> tuple[Array, Array]:
    """(F(φ | m), Π(n; φ | m)) at the amplitude φ = jπ + φ_r with sin φ_r =
    s and cos φ_r = c ≥ 0 as given (`_reduced_jacobi`'s), not recomputed
    from φ."""
    first, third = _reduced_pair(n, s, c * c, s * s, m1)
    ones = _parameters_ones(n, m1, s.dtype)
    complete_first, complete_third = _reduced_pair(n, ones, 0 * ones, ones, m1)
    within = j == 0  # the complete integrals, ∞ at m = 1, are not read there
    return jnp.where(within, first, first + 2 * j * complete_first), jnp.where(within, third, third + 2 * j * complete_third)


@jax.custom_jvp
def _third_kind_increment(n: Array, u: Array, m: Array, m1: Array, reduced: tuple[Array, Array, Array, Array]) -> Array:
    """∫ du′/(1 − n sn²(u′ | m)) from u₀ to u₁ = Π(n; am u₁) − Π(n; am u₀),
    0 ≤ m < 1, n < 1, for the two ends u = (u₀, u₁) stacked on the first
    axis, from `reduced` = `_reduced_jacobi(u, m, m1)` (which the caller has).

    The integrand is bounded, so this is a well-conditioned function of the
    ends; written through the amplitude, Π(n; φ)'s derivative
    1/((1 − n sin²φ)Δ) would magnify φ's rounding near a quarter turn with
    1 − m small by 1/Δ. Here sn, cn, dn of u come with their own relative
    accuracy, and the derivative in u is the integrand. Π(n; am u) is u
    plus (n/3)(s³R_J(c², Δ², 1, 1 − ns²) + 2jR_J(0, m₁, 1, 1 − n)) for
    u = 2jK + r (s, c, Δ of r; the first kind's part is u itself, which in
    Carlson's form would grow like ln(1/(c + Δ)) near a quarter turn and
    turn the rounding of c and Δ into an absolute error). The increment is
    summed from the differences of like parts — u₁ − u₀, the two R_J terms,
    j₁ − j₀ — so that a short step far along (u₁ − u₀ small against u₀) is
    not left with the rounding of the two whole values: over such steps the
    attitude's turn divides the increment by the step's small rate in u.
    `reduced`'s tangents are not read: they are u's and the parameters',
    which the derivative accounts for."""
    j, s, c, dn = reduced
    s2 = s * s
    partial = s * s2 * carlson_rj(c * c, dn * dn, jnp.ones_like(s), 1 - n * s2)
    ones = _parameters_ones(n, m1, s.dtype)
    complete = carlson_rj(0 * ones, m1 * ones, ones, 1 - n)
    turns = j[1] - j[0]
    # Π(n; jπ + φ_r) = 2jΠ(n) + Π(n; φ_r), with Π = F + (n/3)·s³R_J and 2jK + F(φ_r) = u.
    return (u[1] - u[0]) + n / 3 * jnp.where(turns == 0, partial[1] - partial[0], (partial[1] - partial[0]) + 2 * turns * complete)


@_third_kind_increment.defjvp
def _third_kind_increment_jvp(primals, tangents):
    # At each end, in the parameters at fixed u: Π(n; am u)'s partials at
    # fixed φ, plus ∂Π/∂φ · ∂am/∂m1 at fixed u, where ∂am/∂m1 = −Δ ∂F/∂m1
    # (from F(am u) = u) and ∂Π/∂φ = 1/((1 − n sin²φ)Δ): no division by Δ.
    n, u, m, m1, reduced = primals
    d_n, d_u, _, d_m1, _ = tangents
    j, s, c, _ = (jax.lax.stop_gradient(x) for x in reduced)
    integrand = 1 / (1 - n * s * s)

    _, (d_first, d_third) = jax.jvp(lambda n, m1: _incomplete_pair(n, j, s, c, m1), (n, m1), (d_n, d_m1))
    at_ends = d_third - d_first * integrand + d_u * integrand
    return _third_kind_increment(n, u, m, m1, reduced), at_ends[1] - at_ends[0]
