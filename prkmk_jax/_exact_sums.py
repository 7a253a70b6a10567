"""Sums of products rounded once: dt·Σⱼ cⱼ·xⱼ to the nearest float.

The implicit stages of a PRKMK step solved to round-off are a fixed point of
their own rounded formula dt·Σⱼ aᵢⱼKⱼ. Were the step's increment
u = dt·Σⱼ bⱼKⱼ rounded by that same formula (it is the last stage's, for a
stiffly accurate tableau such as Störmer–Verlet's), its rounding error would
lean the same way at every step: a bias in the free body's energy that
overtakes the random walk of the rounding errors over millions of steps.
Rounded once from its exact value, it does not.

Every product here is exact: each factor is split into a high half, its
significand truncated to half its bits by masking them off (integer
arithmetic), and the rest, so that a product of halves fits one float. XLA
on CPU (and GPU) contracts a·b + c into a fused multiply-add where it sees
fit, which would break the usual error-free product (Dekker's, which
subtracts the rounded product from the product of its halves) in some
fusions and not in others; a contraction of an exact product changes
nothing. The exact terms are then added with Knuth's error-free sum.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

# The significand's stored bits that the high half drops: the high half keeps
# half the significand (its leading bit included), the low half the rest.
_DROPPED_BITS = {jnp.dtype(jnp.float64): 27, jnp.dtype(jnp.float32): 12}
_BITS_TYPE = {jnp.dtype(jnp.float64): jnp.uint64, jnp.dtype(jnp.float32): jnp.uint32}


def rounded_once_combination(dt, coefficients, slopes, zero):
    """dt·Σⱼ coefficients[j]·slopes[j], computed exactly and rounded once,
    over the nonzero (static) coefficients and the slopes that are not None;
    None when no term is left. `dt` is a scalar; the coefficients are Python
    or NumPy floats, taken at their value in the slopes' dtype (float32 or
    float64, the dtype of `zero`).

    The result is within half an ulp of the exact value plus the rounding
    left in the sum's small parts, of order eps^1.5·Σⱼ|dt·cⱼ·xⱼ|: it is
    the nearest float but where the exact value lies that close to a tie
    or the terms cancel (`tests/test_exact_sums.py` checks the bound).
    Differentiable: the masked high halves carry no derivative and the
    low halves all of it, so the derivative is that of dt·Σⱼ cⱼxⱼ."""
    dtype = jnp.dtype(zero.dtype)
    if dtype not in _DROPPED_BITS:
        raise TypeError(f"rounded_once_combination: float32 or float64 slopes, got {dtype}.")
    terms = [(c, slope) for c, slope in zip(coefficients, slopes) if c != 0 and slope is not None]
    if not terms:
        return None
    dt = jnp.asarray(dt, dtype)
    if len(terms) == 1 and math.frexp(float(terms[0][0]))[0] in (0.5, -0.5):
        # c·x is exact for c = ±2ᵏ: dt·(c·x) is rounded once as it stands
        # (symplectic Euler's u = h·K).
        ((c, slope),) = terms
        return dt * (slope if c == 1 else jnp.asarray(c, dtype) * slope)
    exact_terms, small_terms = [], []
    for c, slope in terms:
        # wⱼ = dt·cⱼ as an unevaluated sum high + low (a scalar: cheap).
        weight_high, weight_low = _exact_product(dt, jnp.asarray(np.asarray(c, dtype), dtype))
        weight_high_half, weight_low_half = _split(weight_high)
        slope_high, slope_low = _split(slope)
        exact_terms.append(weight_high_half * slope_high)
        # Each of the next two products is exact and ≈ 2⁻²⁶ of the one above;
        # their sum's rounding (≈ 2⁻⁸⁰ of it) falls far below the result's ulp.
        small_terms.append(weight_high_half * slope_low + weight_low_half * slope_high)
        small_terms.append(weight_low_half * slope_low + weight_low * slope)
    total, error = exact_terms[0], None
    for term in exact_terms[1:]:
        total, sum_error = two_sum(total, term)
        error = sum_error if error is None else error + sum_error
    tail = functools.reduce(jnp.add, small_terms if error is None else [error, *small_terms])
    # The two parts added in one contraction: XLA materialises its result once,
    # where an elementwise sum would be fused, and the whole arithmetic above
    # recomputed, into every one of the increment's consumers.
    return jnp.tensordot(jnp.ones(2, dtype), jnp.stack([total, tail]), axes=1)


def two_sum(a, b):
    """(a + b rounded, its rounding error), whose sum is a + b exactly
    whatever their magnitudes (Knuth's error-free sum: additions only,
    which XLA neither reassociates nor contracts)."""
    total = a + b
    b_virtual = total - a
    return total, (a - (total - b_virtual)) + (b - b_virtual)


def two_product(a, b):
    """a·b as (high, low), high + low within about eps² of a·b: the
    products of the factors' halves (`_split`) are exact, and the two
    middle ones are added without error (where `_exact_product` rounds
    their sum, about eps^1.5 of a·b)."""
    a_high, a_low = _split(a)
    b_high, b_low = _split(b)
    middle, middle_error = two_sum(a_high * b_low, a_low * b_high)
    high, error = two_sum(a_high * b_high, middle)
    return high, error + (middle_error + a_low * b_low)


def pair_times(pair, factor):
    """The product of two unevaluated sums (high, low)·(high′, low′) as
    (high, low), within about eps² of it (low·low′ dropped)."""
    high, low = two_product(pair[0], factor[0])
    return high, low + (pair[0] * factor[1] + pair[1] * factor[0])


def _split(x):
    """x = high + low exactly, high with the leading half of x's significand
    (the rest masked off) and low with the rest, so that the product of any
    two halves is exact (but low·low in float64, one bit too wide: its
    rounding, ≈ 2⁻¹⁰⁶ of x², is the only one in these sums)."""
    bits_type = _BITS_TYPE[jnp.dtype(x.dtype)]
    mask = np.asarray(~((1 << _DROPPED_BITS[jnp.dtype(x.dtype)]) - 1) & np.iinfo(bits_type).max, bits_type)
    high = jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(x, bits_type) & mask, x.dtype)
    return high, x - high


def _exact_product(a, b):
    """a·b as (high, low), high + low exact but for low's own rounding."""
    a_high, a_low = _split(a)
    b_high, b_low = _split(b)
    total, error = two_sum(a_high * b_high, a_high * b_low + a_low * b_high)
    return total, error + a_low * b_low
