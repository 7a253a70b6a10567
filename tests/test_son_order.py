"""Empirical order on SO(4): the generalised rigid body with M = JΩ + ΩJ,
i.e. Ω_ij = M_ij/(J_i + J_j), on the semidirect and Cartesian bundles."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

import prkmk_jax as pk
from helpers import final_state_by_steps

J = np.array([0.9, 0.7, 0.5, 0.3])
DENOM = J[:, None] + J[None, :]
rng = np.random.default_rng(21)
G0 = expm((lambda a: a - a.T)(rng.normal(size=(4, 4))))
M0 = (lambda a: 0.5 * (a - a.T))(rng.normal(size=(4, 4)))


def omega(m):
    return m / DENOM


def reference(t_end):
    def rhs(t, z):
        g, m = z[:16].reshape(4, 4), z[16:].reshape(4, 4)
        w = omega(m)
        return np.concatenate([(g @ w).ravel(), (m @ w - w @ m).ravel()])

    return solve_ivp(rhs, (0, t_end), np.concatenate([G0.ravel(), M0.ravel()]), method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]


def body_field(bundle):
    """g' = gΩ, M' = [M, Ω] in body form."""

    def field(t, y, args):
        m = y.fiber
        w = omega(m)
        if isinstance(bundle, pk.Semidirect):  # left: the product supplies M' = −[Ω, M]
            return w, jnp.zeros_like(m)
        return w, m @ w - w @ m  # direct product: η = M'

    return field


@pytest.mark.parametrize("tab", [pk.stormer_verlet, pk.lobatto_iiia_iiib4], ids=lambda t: t.name)
@pytest.mark.parametrize("bundle", [pk.Semidirect(pk.SOn, "left"), pk.DirectProduct(pk.SOn)], ids=["semidirect", "direct"])
@pytest.mark.parametrize("coords", [pk.Exp(), pk.Cayley()], ids=["exp", "cayley"])
def test_order_on_so4(tab, bundle, coords):
    method = pk.PRKMK(bundle, coords, tab, form="body")
    y0 = pk.BundleElement(pk.SOn(jnp.asarray(G0)), jnp.asarray(M0))
    t_end = 1.0
    steps = (10, 20, 40, 80) if tab.order == 4 else (40, 80, 160, 320)
    ref = reference(t_end)
    run = final_state_by_steps(method, body_field(bundle))
    errs = []
    for n in steps:
        y, converged = run(y0, t_end / n, n, None)
        assert converged
        errs.append(np.abs(np.concatenate([np.ravel(y.base.matrix), np.ravel(y.fiber)]) - ref).max())
    slope = np.polyfit(np.log(1 / np.asarray(steps)), np.log(errs), 1)[0]
    assert abs(slope - tab.order) <= 0.15, (slope, errs)
