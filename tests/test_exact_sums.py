"""`_exact_sums.rounded_once_combination` against the exact rational value of
dt·Σⱼ cⱼxⱼ (Python fractions), alone and fused into several consumers,
under XLA's default code generator as the tests run (where LLVM may
contract a·b + c into a fused multiply-add); and the PRKMK step's increment
against the exact value from its own stage slopes."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from helpers import INERTIA, random_rotation, rigid_body_field
from prkmk_jax._exact_sums import pair_times, rounded_once_combination, two_product

WEIGHTS = {
    "symplectic Euler": (1.0,),
    "a power of two": (-0.25,),
    "Störmer–Verlet": (0.5, 0.5),
    "Lobatto 3": (1 / 6, 2 / 3, 1 / 6),
    "Lobatto 4": (1 / 12, 5 / 12, 5 / 12, 1 / 12),
}


def rounding_errors(dt, coefficients, slopes, computed) -> tuple[np.ndarray, np.ndarray]:
    """For each entry: |computed − exact| in ulps of the exact value, and
    its excess over half an ulp in units of Σⱼ|dt·cⱼ·xⱼ|·eps^1.5 (the
    rounding left in the sum's tail, which shows where the final rounding
    is a near-tie or the terms cancel), with the coefficients taken at
    their value in the computed dtype."""
    dtype = computed.dtype
    eps = Fraction(float(np.finfo(dtype).eps))
    step = Fraction(float(np.asarray(dt, dtype)))
    weights = [step * Fraction(float(np.asarray(c, dtype))) for c in coefficients]
    in_ulps, excess_in_tail_units = [], []
    for k in range(computed.size):
        terms = [w * Fraction(float(x[k])) for w, x in zip(weights, slopes)]
        exact = sum(terms)
        error = abs(Fraction(float(computed[k])) - exact)
        # The spacing of floats at the exact value (the smaller one at a power of two).
        ulp = Fraction(float(np.spacing(np.asarray(abs(float(exact)) * (1 - float(eps)), dtype))))
        in_ulps.append(float(error / ulp))
        excess = max(Fraction(0), error - ulp / 2)
        size = sum(abs(t) for t in terms)
        excess_in_tail_units.append(float(excess / (size * eps * Fraction(float(np.sqrt(float(eps)))))) if size else 0.0)
    return np.array(in_ulps), np.array(excess_in_tail_units)


def random_slopes(count, size, dtype, seed):
    """Slopes of either sign over six decades: sums that cancel included."""
    rng = np.random.default_rng(seed)
    return [np.asarray(rng.normal(size=size) * 10.0 ** rng.integers(-3, 3, size=size), dtype) for _ in range(count)]


def combination_errors(dtype_name: str, fused: bool, size: int = 1500) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """`rounding_errors` of `rounded_once_combination` for each of WEIGHTS,
    compiled alone or fused into consumers that read it several times."""
    dtype = jnp.dtype(dtype_name)
    out = {}
    for seed, (name, coefficients) in enumerate(WEIGHTS.items()):
        slopes = random_slopes(len(coefficients), size, dtype, seed)

        def combined(dt, *slopes, coefficients=coefficients):
            u = rounded_once_combination(dt, coefficients, slopes, slopes[0])
            assert u is not None
            if not fused:
                return u
            return u, jnp.sin(u) * u + u * u - 3.0 * u, jnp.sqrt(u * u + 1.0)

        result = jax.jit(combined)(jnp.asarray(0.1, dtype), *slopes)
        computed = np.asarray(result[0] if fused else result)
        out[name] = rounding_errors(0.1, coefficients, slopes, computed)
    return out


def assert_rounded_once(errors: dict[str, tuple[np.ndarray, np.ndarray]]):
    for name, (in_ulps, excess) in errors.items():
        # Within half an ulp but for the tail's rounding, which shows only where
        # the terms cancel or the result is a near-tie; the nearest float nearly
        # always.
        assert np.all(excess <= 1), (name, in_ulps.max(), excess.max())
        assert np.mean(in_ulps <= 0.5) >= 0.995, (name, np.mean(in_ulps <= 0.5))


@pytest.mark.parametrize("dtype_name", ["float64", "float32"])
@pytest.mark.parametrize("fused", [False, True], ids=["alone", "fused"])
def test_combination_is_rounded_once(dtype_name, fused):
    assert_rounded_once(combination_errors(dtype_name, fused))


def test_combination_refuses_integer_slopes():
    with pytest.raises(TypeError, match="float32 or float64"):
        rounded_once_combination(0.1, (0.5, 0.5), (jnp.arange(3), jnp.arange(3)), jnp.arange(3))


def test_combination_without_terms_is_none():
    zero = jnp.zeros(3)
    assert rounded_once_combination(0.1, (0.0, 0.5), (zero, None), zero) is None


@pytest.mark.parametrize(
    "tableau,coordinates,adjoint",
    [
        (pk.stormer_verlet, pk.Exp(), False),
        (pk.stormer_verlet, pk.Cayley(), False),
        (pk.lobatto_iiia_iiib6, pk.Exp(), False),
        (pk.lobatto_iiia_iiib4, pk.Exp(), True),
    ],
    ids=["SV exp", "SV Cayley", "Lobatto 6 exp", "Adjoint of Lobatto 4"],
)
def test_step_increment_is_rounded_once_from_its_stages(tableau, coordinates, adjoint):
    """The increment u = h·Σ bᵢKᵢ a batch of steps returns, against the exact
    value from the stage slopes the same steps return: the step rounds it
    once, not by the stages' own formula (whose rounding error, the stages
    being its fixed point, would lean the same way every step)."""
    bundle = pk.Cotangent(pk.SO3)
    method = pk.PRKMK(bundle, coordinates, tableau, form="body")
    method = pk.Adjoint(method) if adjoint else method
    field = rigid_body_field(bundle, "body")
    momenta = np.random.default_rng(4).normal(size=(200, 3))
    rotations = np.stack([random_rotation(seed) for seed in range(200)])
    y0 = pk.BundleElement(pk.SO3(jnp.asarray(rotations)), jnp.asarray(momenta))

    @jax.jit
    @jax.vmap
    def steps(y):
        step = method.step(field, 0.0, y, 0.1, jnp.asarray(INERTIA))
        return step.increment[0], [k for k, _ in step.carried[1]], step.result

    u, slopes, result = steps(y0)
    assert bool(jnp.all(result == pk.RESULTS.successful))
    u, slopes = np.asarray(u).ravel(), [np.asarray(k).ravel() for k in slopes]
    in_ulps, excess = rounding_errors(0.1, tableau.b_first, slopes, u)
    assert np.all(excess <= 1), (in_ulps.max(), excess.max())
    assert np.mean(in_ulps <= 0.5) >= 0.995


def test_combination_differentiates_as_the_sum():
    """The masked high halves carry no derivative and the low halves all of
    it: first and second derivatives are those of dt·Σⱼ cⱼxⱼ."""
    coefficients = WEIGHTS["Lobatto 4"]
    slopes = tuple(jnp.asarray(x) for x in random_slopes(len(coefficients), 5, jnp.float64, 7))

    def combined(dt, slopes):
        return rounded_once_combination(dt, coefficients, slopes, slopes[0])

    def plain(dt, slopes):
        return dt * sum(c * x for c, x in zip(coefficients, slopes))

    tangents = (jnp.asarray(0.7), tuple(jnp.asarray(x) for x in random_slopes(len(coefficients), 5, jnp.float64, 8)))
    (_, derivative), (_, expected) = (jax.jvp(fn, (jnp.asarray(0.1), slopes), tangents) for fn in (combined, plain))
    np.testing.assert_allclose(derivative, expected, rtol=1e-14)
    # ∂²/∂dt∂x₀ of Σ_k out_k is c₀ in every entry.
    second = jax.grad(lambda dt: jnp.sum(jax.grad(lambda s: jnp.sum(combined(dt, s)))(slopes)[0]))(jnp.asarray(0.1))
    np.testing.assert_allclose(second, 5 * coefficients[0], rtol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_two_product_and_pair_times_to_eps_squared(dtype):
    """(high, low) of a·b, and of (a·b)·c as a pair times a number, within
    a few eps² of the exact products (fractions), over magnitudes 1e-3…1e3."""
    rng = np.random.default_rng(7)
    a, b, c = (np.asarray(rng.choice([-1, 1], 500) * 10.0 ** rng.uniform(-3, 3, 500), dtype) for _ in range(3))
    eps = float(np.finfo(dtype).eps)

    @jax.jit
    def products(a, b, c):
        pair = two_product(a, b)
        return pair, pair_times(pair, (c, jnp.zeros_like(c)))

    (ab_high, ab_low), (abc_high, abc_low) = products(a, b, c)
    for k in range(a.size):
        ab = Fraction(float(a[k])) * Fraction(float(b[k]))
        assert abs(Fraction(float(ab_high[k])) + Fraction(float(ab_low[k])) - ab) <= 2 * eps**2 * abs(ab)
        abc = ab * Fraction(float(c[k]))
        assert abs(Fraction(float(abc_high[k])) + Fraction(float(abc_low[k])) - abc) <= 4 * eps**2 * abs(abc)
