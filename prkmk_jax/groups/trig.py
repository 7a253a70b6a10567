"""Sine and cosine of an angle: a library call for one, arithmetic that XLA
vectorises for many.

XLA's CPU backend evaluates `jnp.sin` and `jnp.cos` of float64 element by
element through a library call: the fastest way to one value, slow on a
batch; an exact-flow splitting step is a chain of planar rotations whose
cost is almost all sines and cosines. `polynomial_sincos` computes both
from one reduction of the angle to [−π/4, π/4] (Cody–Waite: π/2 split into
parts whose products with the quadrant count are exact) and Taylor
polynomials there, with as many terms as the dtype needs; the quadrant then
picks signs and swaps. Accurate to a few units in the last place for
|angle| ≲ 10⁵ (float64) or 10³ (float32): a rotation per sub-step of a
step, far beyond any angle an integrator takes. `sincos` takes the library
call for one angle and the polynomials for many, including one angle per
trajectory under `jax.vmap` (`jax.custom_batching.custom_vmap`), so the
rule follows the batch whichever way it is run. The pair comes back
computed once (`computed_once`), so the rows of a rotation that read it do
not each evaluate it again.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

# π/2 = sum of the parts; the leading parts have few significant bits, so
# n·part is exact for the quadrant counts n that occur (|n| < 2²⁰ in float64
# with the 33-bit parts of fdlibm's __ieee754_rem_pio2, |n| < 2¹⁶ in float32
# with the 8- and 13-bit parts of Cephes' sinf).
_HALF_PI_PARTS = {
    64: (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624879595063154e-21),
    32: (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8),
}
# Taylor terms on |r| ≤ π/4: the first omitted term of sin (r^(2k+1)/(2k+1)!)
# and of cos (r^(2k)/(2k)!) is below half an ulp of the result.
_TERMS = {64: (9, 10), 32: (5, 6)}


def computed_once(*trees: PyTree) -> PyTree:
    """The arrays of `trees`, each computed once by XLA; returns the trees
    (one tree: that tree).

    XLA fuses arithmetic into every consumer that reads it, so a sine and
    cosine read by many rows of a rotation, or a step's change read twice
    by an error-free sum, would be evaluated again in each. A barrier on
    the arrays joined into one keeps them whole (a barrier on a tuple does
    not: XLA's fusion goes through it): stacked where they share a shape of
    two or more axes (a packed state and its cotangent with the batch as
    their last axis), so that the joined array keeps their last axis, along
    which XLA vectorises the loops that write and read it; raveled and
    concatenated otherwise."""
    leaves, structure = jax.tree.flatten(trees)
    if len({jnp.result_type(leaf) for leaf in leaves}) > 1:
        raise TypeError(f"computed_once takes arrays of one dtype, got {sorted({str(jnp.result_type(x)) for x in leaves})}.")
    if len({jnp.shape(leaf) for leaf in leaves}) == 1 and jnp.ndim(leaves[0]) >= 2:
        stacked = jax.lax.optimization_barrier(jnp.stack(leaves))
        parts = list(stacked)
    else:
        flat = jax.lax.optimization_barrier(jnp.concatenate([jnp.ravel(leaf) for leaf in leaves]))
        ends = np.cumsum([jnp.size(leaf) for leaf in leaves])
        parts = [flat[end - jnp.size(leaf) : end].reshape(jnp.shape(leaf)) for leaf, end in zip(leaves, ends)]
    out = jax.tree.unflatten(structure, parts)
    return out[0] if len(trees) == 1 else out


def _series(r2: Array, first: int, count: int) -> Array:
    """Σ_{k<count} (−1)ᵏ r2ᵏ/(first + 2k)!, by Horner: sin r = r·_series(r², 1, ·)
    and cos r = _series(r², 0, ·)."""
    coefficients = [(-1) ** k / math.factorial(first + 2 * k) for k in range(count)]
    acc = jnp.full_like(r2, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        acc = acc * r2 + c
    return acc


def _floating_dtype(angle):
    """The angle's dtype, which must be floating."""
    dtype = jnp.result_type(angle)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"sincos needs a floating angle, got {dtype}.")
    return dtype


def polynomial_sincos(angle: Float[Array, "*batch"]) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """(sin a, cos a) by the reduction and polynomials of the module
    docstring, element by element in arithmetic that XLA vectorises; what
    `sincos` computes for many angles. Not differentiable by itself: use
    `sincos`."""
    dtype = _floating_dtype(angle)
    bits = 64 if jnp.finfo(dtype).bits == 64 else 32
    quadrants = jnp.round(angle * (2 / math.pi))
    r = angle
    for part in _HALF_PI_PARTS[bits]:
        r = r - quadrants * jnp.asarray(part, dtype)
    r2 = r * r
    sine_terms, cosine_terms = _TERMS[bits]
    s = r * _series(r2, 1, sine_terms)
    c = _series(r2, 0, cosine_terms)
    q = quadrants.astype(jnp.int32) & 3
    # a = q·π/2 + r: sin a is s, c, −s, −c and cos a is c, −s, −c, s for q = 0, 1, 2, 3.
    sine = jnp.where(q == 0, s, jnp.where(q == 1, c, jnp.where(q == 2, -s, -c)))
    cosine = jnp.where(q == 0, c, jnp.where(q == 1, -s, jnp.where(q == 2, -c, s)))
    return computed_once(sine, cosine)


@jax.custom_batching.custom_vmap
def _one_or_many(angle):
    """One angle: `jnp.sin` and `jnp.cos` (a library call, the fastest way to
    one value); more than one: `polynomial_sincos`. Under `jax.vmap` the
    angles are many, whatever shape one trajectory sees."""
    if jnp.size(angle) == 1:
        _floating_dtype(angle)
        return computed_once(jnp.sin(angle), jnp.cos(angle))
    return polynomial_sincos(angle)


@_one_or_many.def_vmap
def _many(axis_size, in_batched, angle):
    del axis_size
    (batched,) = in_batched
    out = polynomial_sincos(angle) if batched else _one_or_many(angle)
    return out, (batched, batched)


@jax.custom_jvp
def sincos(angle: Float[Array, "*batch"]) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """(sin a, cos a) for a floating array a (any shape): of one angle by
    `jnp.sin` and `jnp.cos`, of many (an array, or one angle per
    trajectory under `jax.vmap`) by `polynomial_sincos`, whose arithmetic
    XLA vectorises where its sine and cosine are a call per element; see the
    module docstring for its range and accuracy. Differentiable: the
    derivative is (cos a, −sin a)·ȧ."""
    return _one_or_many(angle)


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (angle,), (angle_dot,) = primals, tangents
    sine, cosine = sincos(angle)
    return (sine, cosine), (cosine * angle_dot, -sine * angle_dot)
