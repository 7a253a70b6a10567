"""Bernoulli series for dexp⁻¹ (and the series for dexp) on any bracket.

One implementation serves every algebra: the base algebras so(n), and the
bundle algebras g×g, g⋉g, g⋉g* of Tables 2.1–2.3, each through its own
bracket. Algebra elements may be any pytree (a bundle algebra element is a
pair of arrays); the bracket is a function of two such pytrees.

Truncation (Munthe-Kaas): in an RKMK step U = O(h) and the stage slope X is
within O(h) of the slope at U = 0, so ad_U^k X = O(h^{k+1}); keeping the
terms k ≤ p − 2 keeps the local error at O(h^{p+1}), i.e. order p.
"""

from collections.abc import Callable
from fractions import Fraction
from functools import cache
from math import comb, factorial
from typing import TypeVar

import jax
import jax.numpy as jnp

Algebra = TypeVar("Algebra")
"""An algebra element: an array of a base group's algebra, or a pair (ξ, η)
of arrays of a bundle's."""


@cache
def bernoulli_numbers(n: int) -> tuple[Fraction, ...]:
    """B_0, …, B_n with the convention B_1 = −1/2."""
    b = [Fraction(1)]
    for m in range(1, n + 1):
        b.append(-sum(comb(m + 1, k) * b[k] for k in range(m)) / Fraction(m + 1))
    return tuple(b)


def default_truncation(method_order: int) -> int:
    """Highest power of ad kept in dexp⁻¹ for a method of order p: max(p − 2, 0)."""
    return max(method_order - 2, 0)


def _axpy(alpha, x, y):
    return jax.tree.map(lambda xi, yi: yi + jnp.asarray(alpha, dtype=xi.dtype) * xi, x, y)


def dexp_inv_series(bracket: Callable[[Algebra, Algebra], Algebra], u: Algebra, x: Algebra, order: int) -> Algebra:
    """Σ_{k=0}^{order} B_k/k! ad_u^k x (right-trivialised dexp_u⁻¹ truncated)."""
    if order < 0:
        raise ValueError(f"series order must be ≥ 0, got {order}.")
    bern = bernoulli_numbers(order)
    acc, term = x, x
    for k in range(1, order + 1):
        term = bracket(u, term)
        if bern[k] != 0:
            acc = _axpy(float(bern[k] / factorial(k)), term, acc)
    return acc


def dexp_series(bracket: Callable[[Algebra, Algebra], Algebra], u: Algebra, x: Algebra, order: int) -> Algebra:
    """Σ_{k=0}^{order} ad_u^k x/(k+1)! (right-trivialised dexp_u truncated)."""
    if order < 0:
        raise ValueError(f"series order must be ≥ 0, got {order}.")
    acc, term = x, x
    for k in range(1, order + 1):
        term = bracket(u, term)
        acc = _axpy(1.0 / factorial(k + 1), term, acc)
    return acc
