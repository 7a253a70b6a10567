"""Jacobi's elliptic functions and Legendre's and Carlson's integrals
(`prkmk_jax.elliptic`) against SciPy, quadrature and their own identities,
with their derivatives against the closed forms and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.special as sp

from prkmk_jax import elliptic

RNG = np.random.default_rng(20031)
U = RNG.uniform(-60, 60, 3000)
M = np.concatenate([RNG.uniform(0, 1, 2980), np.zeros(10), 1 - 10.0 ** -RNG.uniform(1, 15, 10)])
PHI = RNG.uniform(-20, 20, 3000)
# SciPy's ellipj switches to an expansion valid only for small u once
# 1 − m < 1e-9; there the identities check instead.
SCIPY_HOLDS = M < 1 - 1e-9


@jax.jit
def _all(u, m, phi):
    return elliptic.jacobi(u, m), elliptic.ellipf(phi, m), elliptic.ellipk(m)


def test_against_scipy_in_float64():
    (sn, cn, dn, am), f, k = _all(U, M, PHI)
    want = sp.ellipj(U, M)
    for got, ref in zip((sn, cn, dn, am), want):
        np.testing.assert_allclose(np.asarray(got)[SCIPY_HOLDS], ref[SCIPY_HOLDS], rtol=0, atol=2e-14 * np.max(np.abs(U)) / 10)
    np.testing.assert_allclose(f, sp.ellipkinc(PHI, M), rtol=4e-15)
    np.testing.assert_allclose(k, sp.ellipk(M), rtol=4e-15)
    x, y, z = RNG.uniform(0, 3, (3, 500))
    x[:50] = 0
    p = 10.0 ** RNG.uniform(-3, 6, 500)
    np.testing.assert_allclose(elliptic.carlson_rf(x, y, z), sp.elliprf(x, y, z), rtol=4e-15)
    np.testing.assert_allclose(elliptic.carlson_rd(x, y, z + 0.01), sp.elliprd(x, y, z + 0.01), rtol=4e-15)
    np.testing.assert_allclose(elliptic.carlson_rj(x, y, z, p), sp.elliprj(x, y, z, p), rtol=3e-14)


def test_third_kind_against_quadrature():
    rng = np.random.default_rng(3)
    n = np.concatenate([rng.uniform(-1, 0.9, 20), -(10.0 ** rng.uniform(-3, 4, 20))])
    phi, m = rng.uniform(-8, 8, 40), rng.uniform(0, 0.999, 40)
    got = np.asarray(elliptic.ellippi(n, phi, m))
    for i in range(40):
        integrand = lambda t: 1 / ((1 - n[i] * np.sin(t) ** 2) * np.sqrt(1 - m[i] * np.sin(t) ** 2))  # noqa: E731
        points = np.arange(np.ceil(min(0, phi[i]) / np.pi), np.floor(max(0, phi[i]) / np.pi) + 1) * np.pi
        want = scipy.integrate.quad(integrand, 0, phi[i], points=points if len(points) else None, epsabs=0, epsrel=2e-14, limit=400)[0]
        assert abs(got[i] - want) <= 2e-13 * abs(want), (n[i], phi[i], m[i], got[i], want)


def test_identities_up_to_the_parameter_one():
    """sn² + cn² = 1, dn² + m sn² = 1, F(am u | m) = u, and the limits at m = 1."""
    (sn, cn, dn, am), _, _ = _all(U, M, PHI)
    np.testing.assert_allclose(sn**2 + cn**2, 1, atol=4e-16)
    np.testing.assert_allclose(dn**2 + M * sn**2, 1, atol=4e-16)
    # F is as sensitive to its amplitude as 1/dn: the round trip errs by that much.
    back = np.asarray(elliptic.ellipf(am, M))
    assert np.all(np.abs(back - U) <= 4e-15 * np.max(np.abs(U)) / np.sqrt(1 - M))
    u = np.linspace(-5, 5, 11)
    sn1, cn1, dn1, am1 = elliptic.jacobi(u, 1.0)
    np.testing.assert_allclose(sn1, np.tanh(u), atol=1e-15)
    np.testing.assert_allclose(cn1, 1 / np.cosh(u), atol=1e-15)
    np.testing.assert_allclose(dn1, 1 / np.cosh(u), atol=1e-15)
    np.testing.assert_allclose(am1, 2 * np.arctan(np.tanh(u / 2)), atol=1e-15)
    near = elliptic.jacobi(u, 1 - 1e-15)
    np.testing.assert_allclose(near[0], np.tanh(u), atol=1e-13)


def _closed_form_derivatives(u, m, phi, n):
    sn, cn, dn, _ = elliptic.jacobi(u, m)
    d_sn = jax.vmap(jax.grad(lambda u, m: elliptic.jacobi(u, m)[0]))(u, m)
    d_am = jax.vmap(jax.grad(lambda u, m: elliptic.jacobi(u, m)[3]))(u, m)
    d_f = jax.vmap(jax.grad(elliptic.ellipf))(phi, m)
    d_pi = jax.vmap(jax.grad(elliptic.ellippi, argnums=1))(n, phi, m)
    return (d_sn, cn * dn), (d_am, dn), d_f, d_pi


def _parameter_derivatives(u, m, phi, n, h):
    """For each function of a parameter (elementwise over the arrays):
    fourth-order central differences, forward mode, reverse mode."""
    out = {}
    for name, f, x in [
        ("sn", lambda m: elliptic.jacobi(u, m)[0], m),
        ("am", lambda m: elliptic.jacobi(u, m)[3], m),
        ("F", lambda m: elliptic.ellipf(phi, m), m),
        ("Π in m", lambda m: elliptic.ellippi(n, phi, m), m),
        ("Π in n", lambda n: elliptic.ellippi(n, phi, m), n),
    ]:
        # The four shifted arguments in one evaluation (the functions are elementwise).
        shifted = f(x + h * jnp.array([-2.0, -1.0, 1.0, 2.0])[:, None])
        fd = (shifted[0] - 8 * shifted[1] + 8 * shifted[2] - shifted[3]) / (12 * h)
        out[name] = (fd, jax.jvp(f, (x,), (jnp.ones_like(x),))[1], jax.grad(lambda x: jnp.sum(f(x)))(x))
    return out


def _jacobi_in_long_double(u, m1):
    """sn, cn, dn by the arithmetic–geometric mean and descending Landen
    transformations in NumPy's 80-bit long double: cn's relative error is
    about its eps (1e-19) over k′, ulps of float64 for k′ ≥ 1e-3."""
    ld = np.longdouble
    a, b, c = [ld(1)], [np.sqrt(ld(m1))], [np.sqrt(1 - ld(m1))]
    while c[-1] > 1e-21:
        a, b, c = a + [(a[-1] + b[-1]) / 2], b + [np.sqrt(a[-1] * b[-1])], c + [(a[-1] - b[-1]) / 2]
    phi = 2 ** (len(a) - 1) * a[-1] * ld(u)
    for j in range(len(a) - 1, 0, -1):
        phi = (phi + np.arcsin(c[j] / a[j] * np.sin(phi))) / 2
    return np.sin(phi), np.cos(phi), np.sqrt(ld(m1) + (1 - ld(m1)) * np.cos(phi) ** 2)


@pytest.mark.parametrize("m1", [1e-4, 1e-6])
def test_reduced_jacobi_keeps_relative_accuracy_near_half_a_quarter_period(m1):
    """Up to u = K/2 with 1 − m small, where cn and dn come down to about
    √k′: each of sn, cn, dn within 8 ulps of itself (`elliptic._reduced_jacobi`,
    which the exact flow's attitude reads there), against long double.
    (Past K/2 the functions are read at K − u, and K's rounding is one
    more error of the argument.)"""
    quarter = float(sp.ellipk(1 - m1))
    u = quarter / 2 * np.array([0.3, 0.6, 0.9, 0.97, 1.0, -1.0])
    computed = jax.jit(elliptic._reduced_jacobi)(u, np.full_like(u, 1 - m1), np.full_like(u, m1))[1:]
    for k, x in enumerate(u):
        for got, want in zip(computed, _jacobi_in_long_double(x, m1)):
            assert abs(float(got[k]) - want) <= 8 * np.finfo(float).eps * abs(want), (m1, x, float(got[k]), float(want))


def test_derivatives():
    """In u and φ against the closed forms (also at φ = ±π/2, 3π/2, where
    Carlson's form would give 0·∞); in m and n against central differences
    (error ~h⁴ times the fifth derivative); reverse mode equal to forward
    mode."""
    u, m, phi = U[:300], M[:300], PHI[:300]
    n = -RNG.uniform(0, 5, 300)
    (d_sn, want_sn), (d_am, want_am), d_f, d_pi = jax.jit(_closed_form_derivatives)(u, m, phi, n)
    np.testing.assert_allclose(d_sn, want_sn, atol=1e-13)
    np.testing.assert_allclose(d_am, want_am, atol=1e-12)
    delta = np.sqrt(np.cos(phi) ** 2 + (1 - m) * np.sin(phi) ** 2)
    np.testing.assert_allclose(d_f, 1 / delta, rtol=1e-13)
    np.testing.assert_allclose(d_pi, 1 / ((1 - n * np.sin(phi) ** 2) * delta), rtol=1e-13)
    at = jnp.array([jnp.pi / 2, -jnp.pi / 2, 3 * jnp.pi / 2])
    _, _, d_f, d_pi = jax.jit(_closed_form_derivatives)(at, jnp.full(3, 0.7), at, jnp.full(3, -2.0))
    np.testing.assert_allclose(d_f, 1 / np.sqrt(0.3), rtol=1e-14)
    np.testing.assert_allclose(d_pi, 1 / (3 * np.sqrt(0.3)), rtol=1e-14)
    moderate = (m > 0.01) & (m < 0.99)
    results = jax.jit(_parameter_derivatives)(u[moderate], m[moderate], phi[moderate], n[moderate], 1e-4)
    for name, (fd, forward, reverse) in results.items():
        np.testing.assert_allclose(forward, fd, rtol=1e-6, atol=1e-7, err_msg=name)
        np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.parametrize("function", ["jacobi", "ellipf", "ellippi"])
def test_float32_within_a_few_ulps_of_float64(function):
    u, m, phi = U[:500] / 10, M[:500], PHI[:500] / 4
    f = {
        "jacobi": lambda u, m, phi: jnp.stack(elliptic.jacobi(u, m)),
        "ellipf": lambda u, m, phi: elliptic.ellipf(phi, m),
        "ellippi": lambda u, m, phi: elliptic.ellippi(-2.0, phi, m),
    }[function]
    low = f(*(jnp.asarray(a, jnp.float32) for a in (u, m, phi)))
    high = f(*(np.asarray(a, np.float32).astype(float) for a in (u, m, phi)))
    assert low.dtype == jnp.float32
    scale = np.maximum(np.abs(high), 1) * np.maximum(np.abs(u), 1) if function == "jacobi" else np.maximum(np.abs(high), 1)
    assert np.max(np.abs(np.asarray(low, float) - high) / scale) < 8 * np.finfo(np.float32).eps
