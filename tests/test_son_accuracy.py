"""SOn where its maps are hard: log near angle π and at the identity,
dexp⁻¹ beyond the Bernoulli series' radius, broadcasting of dexp. Checked
against SciPy (rotation vectors, logm), the group's own exp and dexp
(expm and its Fréchet derivative), autodiff and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

import prkmk_jax as pk
from prkmk_jax.groups.son import SERIES_RADIUS, _dexp_inv_closed_form

RNG = np.random.default_rng(7)


@pytest.fixture(autouse=True)
def _same_draws_in_every_order(monkeypatch):
    """Every test draws its inputs from a fresh generator: which tests ran
    before it (xdist deals them out differently each run) does not change
    what it checks."""
    monkeypatch.setattr(f"{__name__}.RNG", np.random.default_rng(7))


def _random_orthonormal(n, rng=None):
    q, _ = np.linalg.qr((RNG if rng is None else rng).normal(size=(n, n)))
    return q


def _generator(angles, n, basis):
    """Skew matrix with the given rotation angles in the planes (e₀, e₁),
    (e₂, e₃), … of `basis`."""
    block = np.zeros((n, n))
    for k, theta in enumerate(angles):
        block[2 * k + 1, 2 * k], block[2 * k, 2 * k + 1] = theta, -theta
    return basis @ block @ basis.T


@pytest.mark.parametrize("eps", [1e-2, 1e-4, 1e-6, 1e-9, 1e-12])
def test_so3_log_near_pi_matches_scipy(eps):
    for _ in range(5):
        axis = RNG.normal(size=3)
        rotvec = axis / np.linalg.norm(axis) * (np.pi - eps)
        matrix = Rotation.from_rotvec(rotvec).as_matrix()
        log = np.asarray(pk.SOn(jnp.asarray(matrix)).log())
        np.testing.assert_allclose(log, np.asarray(pk.hat(jnp.asarray(rotvec))), atol=2e-13)


def test_log_at_angle_pi_exactly_is_a_logarithm():
    for n in (3, 4):
        basis = _random_orthonormal(n)
        u = _generator([np.pi], n, basis)
        matrix = scipy.linalg.expm(u)
        log = pk.SOn(jnp.asarray(matrix)).log()
        assert np.all(np.isfinite(log))
        np.testing.assert_allclose(pk.SOn.exp(log).matrix, matrix, atol=1e-13)
        np.testing.assert_allclose(np.abs(log), np.abs(u), atol=1e-13)  # ±πJ on the same plane


@pytest.mark.parametrize(
    "angles",
    [(np.pi - 1e-9, 1.0), (np.pi - 1e-6, 0.0), (np.pi - 1e-3, np.pi - 0.3), (2.0, 1e-8), (3.0, 3.0), (0.3, 0.2)],
    ids=["pi-1e-9,1", "pi-1e-6,0", "pi-1e-3,pi-0.3", "2,1e-8", "3,3", "0.3,0.2"],
)
@pytest.mark.parametrize("n", [4, 5])
def test_son_log_inverts_exp_and_matches_scipy(angles, n):
    u = _generator(angles, n, _random_orthonormal(n))
    matrix = scipy.linalg.expm(u)
    log = np.asarray(pk.SOn(jnp.asarray(matrix)).log())
    np.testing.assert_allclose(log, u, atol=1e-11)
    if max(angles) < 3.0:  # SciPy's logm is itself inaccurate near π
        np.testing.assert_allclose(log, np.real(scipy.linalg.logm(matrix)), atol=1e-11)


def test_log_gradient_is_finite_at_the_identity_and_matches_finite_differences():
    # Compiled once each (jit), for every base below.
    @jax.jit
    def log_of(params, base):
        u = jnp.zeros((4, 4)).at[jnp.triu_indices(4, 1)].set(params)
        u = u - u.T
        return pk.SOn(base @ pk.SOn.exp(u).matrix).log()[jnp.triu_indices(4, 1)]

    jacobians = jax.jit(lambda p, base: (jax.jacfwd(log_of)(p, base), jax.jacrev(log_of)(p, base)))

    # base = I: the product I·exp(u) is exp(u) exactly, so this is the log at the identity.
    forward, reverse = jacobians(jnp.zeros(6), jnp.eye(4))
    np.testing.assert_allclose(forward, np.eye(6), atol=1e-12)
    assert np.all(np.isfinite(reverse))
    # (R + Rᵀ)/2 has every eigenvalue twice: exactly so in the first basis,
    # up to rounding in the others, where an eigendecomposition's derivative
    # is 0/0 or huge.
    bases = [np.eye(4)] + [_random_orthonormal(4, np.random.default_rng(seed)) for seed in range(4)]
    for basis in bases:
        base = jnp.asarray(scipy.linalg.expm(_generator([1.2, 0.4], 4, basis)))
        params = jnp.zeros(6)
        step = 1e-6
        fd = np.stack([(log_of(params + step * e, base) - log_of(params - step * e, base)) / (2 * step) for e in np.eye(6)], axis=1)
        forward, reverse = jacobians(params, base)
        np.testing.assert_allclose(forward, fd, atol=1e-7)
        np.testing.assert_allclose(reverse, fd, atol=1e-7)


@pytest.mark.parametrize("angles", [(3.0, 3.0), (3.1, 1.0), (2.5, 0.0), (1.0, 0.5), (0.0, 0.0)])
def test_dexp_inv_inverts_dexp_beyond_the_series_radius(angles):
    """‖ad_u‖ = |θ₁| + |θ₂| up to 6.0 (the series needs < 2π and is slow past
    2.5): dexp⁻¹ must undo dexp (the Fréchet derivative of expm)."""
    n = 4
    u = jnp.asarray(_generator(angles, n, _random_orthonormal(n)))
    v = jnp.asarray(_generator([0.7, -0.2], n, _random_orthonormal(n)))
    np.testing.assert_allclose(pk.SOn.dexp_inv(u, pk.SOn.dexp(u, v)), v, atol=1e-11)
    np.testing.assert_allclose(pk.SOn.dexp(u, pk.SOn.dexp_inv(u, v)), v, atol=1e-11)


def test_dexp_inv_branches_agree_at_the_radius_and_its_gradient_is_finite_at_zero():
    u = _generator([1.0, 0.4], 4, _random_orthonormal(4))
    u = jnp.asarray(u / np.linalg.norm(u) * SERIES_RADIUS * 0.999)
    v = jnp.asarray(_generator([0.3, 0.9], 4, _random_orthonormal(4)))
    np.testing.assert_allclose(_dexp_inv_closed_form(u, v), pk.SOn.dexp_inv(u, v), atol=1e-13)
    grad = jax.jacfwd(lambda w: pk.SOn.dexp_inv(w, v))(jnp.zeros((4, 4)))
    assert np.all(np.isfinite(grad))


def test_dexp_and_dexp_inv_broadcast_batch_axes():
    us = jnp.asarray(np.stack([_generator([0.5 * k, 0.1], 4, _random_orthonormal(4)) for k in range(3)]))
    v = jnp.asarray(_generator([0.3, 0.2], 4, _random_orthonormal(4)))
    batched = pk.SOn.dexp(us, v)
    assert batched.shape == (3, 4, 4)
    for k in range(3):
        np.testing.assert_allclose(batched[k], pk.SOn.dexp(us[k], v), atol=1e-14)
    np.testing.assert_allclose(pk.SOn.dexp_inv(us, batched), jnp.broadcast_to(v, us.shape), atol=1e-12)


# --- angles near π: agreement with SciPy relative to the condition number -----------------
TWO_PLANES_FROM_PI = (
    (1e-9, 1e-2),
    (1e-6, 1e-2),
    (1e-9, 1e-9),
    (1e-6, 1e-3),
    (1e-5, 1e-3),
    (1e-9, 1e-6),
    (1e-6, 1e-5),
    (1e-8, 2e-8),
    (1e-5, 1e-4),
    (1e-4, 1e-3),
)
"""Distances from π of two rotation angles: far apart, equal, and close
enough that their cosines (−1 + δ²/2) are closer than S's eigenvectors
resolve."""
NEAR_PI_CASES = [
    (n, angles)
    for n in (3, 4, 5)
    for angles in (
        [(np.pi - d,) for d in (1e-9, 1e-6, 1e-2)]
        # SO(4) meets every other pair; SO(5), whose extra plane is at rest, the others.
        + ([(np.pi - a, np.pi - b) for a, b in TWO_PLANES_FROM_PI[n % 2 :: 2]] if n >= 4 else [])
        + ([(np.pi - 1e-9, 0.5)] if n >= 4 else [])
    )
]


def _condition_number(angles):
    """‖dexp⁻¹_u‖ for u with these rotation angles: the largest |z/(eᶻ − 1)|
    over the eigenvalues z = ±i(θⱼ ± θₖ), ±iθⱼ (and 0) of ad_u on so(n),
    i.e. max α/(2|sin(α/2)|)."""
    alphas = list(angles) + [a + b for k, a in enumerate(angles) for b in angles[k + 1 :]]
    alphas += [abs(a - b) for k, a in enumerate(angles) for b in angles[k + 1 :]]
    return max([1.0] + [a / (2 * abs(np.sin(a / 2))) for a in alphas if a > 0])


def _near_pi_rotation(n, angles, seed):
    return scipy.linalg.expm(_generator(angles, n, _random_orthonormal(n, np.random.default_rng(seed))))


@pytest.mark.parametrize("n,angles", NEAR_PI_CASES)
def test_son_log_near_pi_agrees_with_scipy_within_the_condition_number(n, angles):
    """One or two angles at π − (1e-9 … 1e-2): log R against SciPy's
    `logm` of the same (rounded) matrix, relative error ≤ 1e-12·κ; and
    exp(log R) = R to the same."""
    kappa = _condition_number(angles)
    for seed in range(3):
        r = _near_pi_rotation(n, angles, seed)
        reference = scipy.linalg.logm(r).real
        reference = 0.5 * (reference - reference.T)
        log = np.asarray(pk.SOn(jnp.asarray(r)).log())
        assert np.all(np.isfinite(log))
        np.testing.assert_allclose(log, -log.T, rtol=0, atol=1e-15 * kappa)
        error = np.linalg.norm(log - reference) / np.linalg.norm(reference)
        assert error <= 1e-12 * kappa, (error, kappa)
        np.testing.assert_allclose(np.asarray(pk.SOn.exp(jnp.asarray(log)).matrix), r, rtol=0, atol=1e-13 * kappa)


@pytest.mark.parametrize("n,angles", NEAR_PI_CASES)
def test_son_dexp_inv_near_pi_agrees_with_scipy_within_the_condition_number(n, angles):
    """dexp⁻¹_u v for u with angles near π against the solve of SciPy's
    dexp (the Fréchet derivative of expm, `expm_frechet`, as a matrix on a
    basis of so(n)): relative error ≤ 1e-12·κ, and the result skew."""
    kappa = _condition_number(angles)
    basis_pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]

    def unit(a, b):
        e = np.zeros((n, n))
        e[b, a], e[a, b] = 1.0, -1.0
        return e

    for seed in range(2):
        basis = _random_orthonormal(n, np.random.default_rng(seed))
        u = _generator(angles, n, basis)
        expu = scipy.linalg.expm(u)
        columns = []
        for a, b in basis_pairs:
            _, frechet = scipy.linalg.expm_frechet(u, unit(a, b))
            image = frechet @ expu.T
            columns.append([image[bb, aa] for aa, bb in basis_pairs])
        dexp_matrix = np.array(columns).T
        v = _generator([0.7, -0.2][: n // 2], n, _random_orthonormal(n, np.random.default_rng(100 + seed)))
        coefficients = np.linalg.solve(dexp_matrix, np.array([v[b, a] for a, b in basis_pairs]))
        reference = sum(c * unit(a, b) for c, (a, b) in zip(coefficients, basis_pairs))
        result = np.asarray(pk.SOn.dexp_inv(jnp.asarray(u), jnp.asarray(v)))
        np.testing.assert_allclose(result, -result.T, rtol=0, atol=1e-14 * kappa * np.linalg.norm(reference))
        error = np.linalg.norm(result - reference) / np.linalg.norm(reference)
        assert error <= 1e-12 * kappa, (error, kappa)


@pytest.mark.parametrize(
    "n,angles",
    [
        (3, (np.pi - 1e-9,)),
        (3, (np.pi - 1e-4,)),
        (4, (np.pi - 1e-9, np.pi - 1e-2)),
        (4, (np.pi - 1e-4, np.pi - 1e-2)),
        (5, (np.pi - 1e-6, np.pi - 1e-2)),
    ],
)
def test_son_log_and_dexp_inv_gradients_are_finite_near_pi(n, angles):
    """d log R = dexp⁻¹_u(dR Rᵀ) and the derivative of dexp⁻¹ itself are
    finite at angles near π; where a central difference along a rotation
    (R·exp(sX), s = ±1e-7) stays on one side of π (largest angle ≤ π − 1e-4),
    the directional derivative of log matches it to 1e-6 relative."""
    r = _near_pi_rotation(n, angles, 0)
    direction = _generator([0.3, 0.2][: n // 2], n, _random_orthonormal(n, np.random.default_rng(9)))

    def log_along(s):
        return pk.SOn(jnp.asarray(r) @ pk.SOn.exp(s * jnp.asarray(direction)).matrix).log()

    _, tangent = jax.jvp(log_along, (0.0,), (1.0,))
    assert np.all(np.isfinite(np.asarray(tangent)))
    if max(angles) <= np.pi - 1e-4:
        step = 1e-7
        difference = (log_along(step) - log_along(-step)) / (2 * step)
        np.testing.assert_allclose(tangent, difference, rtol=0, atol=1e-6 * float(np.max(np.abs(difference))))
    u = jnp.asarray(_generator(angles, n, _random_orthonormal(n, np.random.default_rng(3))))
    gradient = jax.grad(lambda w: jnp.sum(pk.SOn.dexp_inv(w, jnp.asarray(direction)) ** 2))(u)
    assert np.all(np.isfinite(np.asarray(gradient)))


@pytest.mark.parametrize("angles", [(np.pi, np.pi), (2 * np.pi, 0.5), (1.5 * np.pi, 0.5 * np.pi)])
def test_son_dexp_inv_refuses_a_u_where_dexp_is_not_invertible(angles):
    """Angles summing to 2π (or one of 2π): an eigenvalue of ad_u is ±2πi, so
    dexp_u has a kernel in so(4) and dexp⁻¹ does not exist: a clear error,
    eagerly and under jit. At (π, π − 0.1) it exists and is finite."""
    u = jnp.asarray(_generator(angles, 4, _random_orthonormal(4)))
    v = jnp.asarray(_generator([0.7, -0.2], 4, _random_orthonormal(4)))
    with pytest.raises(Exception, match="dexp_u is not invertible"):
        jax.block_until_ready(pk.SOn.dexp_inv(u, v))
    with pytest.raises(Exception, match="dexp_u is not invertible"):
        jax.block_until_ready(jax.jit(pk.SOn.dexp_inv)(u, v))
    fine = jnp.asarray(_generator((np.pi, np.pi - 0.1), 4, _random_orthonormal(4)))
    assert np.all(np.isfinite(np.asarray(pk.SOn.dexp_inv(fine, v))))
