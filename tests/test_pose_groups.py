"""The groups of a rotation and a translation. SE(3): every map against
the 4×4 homogeneous matrices (expm, the commutator, the matrix Cayley map,
autodiff of both maps for their differentials), the changes, gradients at
the identity (bad inputs: `test_bad_inputs.py`), and PRKMK methods on a bundle over it reaching their orders
against a DOP853 reference of the equations on ℝ¹⁸. SE(3) and SO(3) × ℝ³:
what they write in closed form against the defaults built from the methods
every group must write. (The group laws, log∘exp, the bracket as the
commutator and the bundles' exact inverse differentials are
`test_groups.py`'s and `test_coordinates.py`'s, for both.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from jax.scipy.linalg import expm
from scipy.integrate import solve_ivp

import prkmk_jax as pk
from helpers import algebra_vectors, assert_closed_forms_are_the_defaults, assert_jacobians_at_the_identity, final_state_by_steps

G = pk.SE3
vectors6 = algebra_vectors(dim=6, max_norm=3.0)


def _close(a, b, tol=1e-12):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=tol)


def twist_matrix(u):
    """[[ω̂, v], [0, 0]]."""
    top = jnp.concatenate([pk.hat(u[..., :3]), u[..., 3:, None]], axis=-1)
    return jnp.concatenate([top, jnp.zeros(top.shape[:-2] + (1, 4), top.dtype)], axis=-2)


def twist_of(m):
    return jnp.concatenate([pk.vee(m[..., :3, :3]), m[..., :3, 3]], axis=-1)


def matrix_cayley(u):
    eye = jnp.eye(4)
    return jnp.linalg.solve(eye - twist_matrix(u) / 2, eye + twist_matrix(u) / 2)


def _matrix_differential(matrix_map, u, x):
    """d/dt f(u + t x)·f(u)⁻¹ at t = 0, as a twist, by autodiff of the 4×4 map."""
    m, dm = jax.jvp(matrix_map, (u,), (x,))
    return twist_of(dm @ jnp.linalg.inv(m))


@jax.jit
def _maps_and_their_matrices(u, v, x):
    g, h = G.exp(u), G.exp(v)
    return {
        "exp": (g.as_matrix(), expm(twist_matrix(u))),
        "product": ((g @ h).as_matrix(), g.as_matrix() @ h.as_matrix()),
        "inverse": (g.inverse().as_matrix(), jnp.linalg.inv(g.as_matrix())),
        "adjoint": (twist_matrix(g.adjoint(x)), g.as_matrix() @ twist_matrix(x) @ jnp.linalg.inv(g.as_matrix())),
        "bracket": (twist_matrix(G.bracket(u, x)), twist_matrix(u) @ twist_matrix(x) - twist_matrix(x) @ twist_matrix(u)),
        "dexp": (G.dexp(u, x), _matrix_differential(lambda w: expm(twist_matrix(w)), u, x)),
        "cayley": (G.cayley(u).as_matrix(), matrix_cayley(u)),
        "dcayley": (G.dcayley_inv(u, _matrix_differential(matrix_cayley, u, x)), x),
        "log": (G.exp(u).log(), u),
        "cayley inverse": (G.cayley(u).cayley_inverse(), u),
        "dexp_inv": (G.dexp_inv(u, G.dexp(u, x)), x),
        "exp change": (jax.tree.leaves(G.exp_change(u)), [g.rotation - jnp.eye(3), g.translation]),
        "cayley change": (jax.tree.leaves(G.cayley_change(u)), [G.cayley(u).rotation - jnp.eye(3), G.cayley(u).translation]),
        "product change": (
            jax.tree.leaves(g.product_change(G.exp_change(v), "right")),
            [(g @ h).rotation - g.rotation, (g @ h).translation - g.translation],
        ),
        "left product change": (
            jax.tree.leaves(g.product_change(G.exp_change(v), "left")),
            [(h @ g).rotation - g.rotation, (h @ g).translation - g.translation],
        ),
        "shifted ad": (G.inverse_shifted_ad(u, x, 0.5) + 0.5 * G.bracket(u, G.inverse_shifted_ad(u, x, 0.5)), x),
    }


@given(a=vectors6, b=vectors6, c=vectors6)
def test_every_map_is_the_homogeneous_matrices(a, b, c):
    u, v, x = (jnp.asarray(w) for w in (a, b, c))
    for name, (ours, theirs) in _maps_and_their_matrices(u, v, x).items():
        tol = 1e-10 if name in ("log", "cayley inverse", "dexp_inv", "dcayley", "dexp") else 1e-12
        try:
            _close(ours, theirs, tol)
        except AssertionError as error:
            raise AssertionError(name) from error


@given(a=vectors6, b=vectors6, c=vectors6)
def test_group_laws(a, b, c):
    x, y, z = (G.exp(jnp.asarray(w)) for w in (a, b, c))
    _close((x @ y) @ z, x @ (y @ z))
    _close(x @ x.inverse(), x.identity_like())
    _close(x.inverse() @ x, x.identity_like())


@pytest.mark.parametrize("fn", ["exp", "log", "dexp", "dexp_inv", "cayley", "dcayley_inv"])
def test_gradients_finite_and_right_at_the_identity(fn):
    x = jnp.asarray([0.3, -0.2, 0.5, 0.1, 0.7, -0.4])
    funcs = {
        "exp": lambda u: G.exp(u).as_matrix(),
        "log": lambda u: G.exp(u).log(),
        "dexp": lambda u: G.dexp(u, x),
        "dexp_inv": lambda u: G.dexp_inv(u, x),
        "cayley": lambda u: G.cayley(u).as_matrix(),
        "dcayley_inv": lambda u: G.dcayley_inv(u, x),
    }
    assert_jacobians_at_the_identity(funcs[fn], 6)


# --- PRKMK on a bundle over SE(3) -------------------------------------------------------
MASS, INERTIA = 2.0, jnp.asarray([0.8, 0.6, 0.3])


def free_body_in_space(t, y, args):
    """A free rigid body with body momenta (Π, P) on SE(3) × se(3): velocity
    ξ = (I⁻¹Π, P/m), and Kirchhoff's equations Π' = Π × Ω (P × V = 0),
    P' = P × Ω."""
    del t, args
    pi, p = y.fiber[..., :3], y.fiber[..., 3:]
    omega = pi / INERTIA
    return jnp.concatenate([omega, p / MASS]), jnp.concatenate([jnp.cross(pi, omega), jnp.cross(p, omega)])


def _reference(y0, t_end):
    """(R, p, Π, P) at t_end, DOP853 at 1e-13 on ℝ¹⁸."""
    inertia = np.asarray(INERTIA)

    def rhs(t, z):
        r, pi, p = z[:9].reshape(3, 3), z[12:15], z[15:]
        omega = pi / inertia
        return np.concatenate(
            [(r @ np.asarray(pk.hat(jnp.asarray(omega)))).ravel(), r @ (p / MASS), np.cross(pi, omega), np.cross(p, omega)]
        )

    z0 = np.concatenate([np.asarray(y0.base.rotation).ravel(), np.asarray(y0.base.translation), np.asarray(y0.fiber)])
    return solve_ivp(rhs, (0.0, t_end), z0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]


@pytest.mark.parametrize(
    "tableau, coordinates, order",
    [(pk.stormer_verlet, pk.Exp(), 2), (pk.lobatto_iiia_iiib4, pk.Cayley(), 4)],
    ids=["SV, exp", "Lobatto 4, Cayley"],
)
def test_prkmk_on_se3_reaches_its_order(tableau, coordinates, order):
    bundle = pk.DirectProduct(G)
    y0 = pk.BundleElement(G.exp(jnp.asarray([0.3, -0.5, 0.8, 1.0, 0.0, -0.5])), jnp.asarray([0.4, -0.3, 1.2, 0.5, 1.0, -0.2]))
    t_end, steps = 2.0, (10, 20, 40, 80)
    reference = _reference(y0, t_end)
    run = final_state_by_steps(pk.PRKMK(bundle, coordinates, tableau, form="body"), free_body_in_space)
    errors = []
    for n in steps:
        y, converged = run(y0, t_end / n, n, None)
        assert converged
        state = np.concatenate([np.asarray(y.base.rotation).ravel(), np.asarray(y.base.translation), np.asarray(y.fiber)])
        errors.append(np.max(np.abs(state - reference)))
    slope = np.polyfit(np.log(t_end / np.asarray(steps)), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.2, (slope, errors)


# --- closed forms against the defaults --------------------------------------------------
def _written_with_the_required_methods_only(group):
    """`group` with only the methods every (quadratic) group must write, the
    others taken from `AbstractQuadraticGroup`'s defaults (series, dense
    solves, the identity subtracted after the fact)."""

    class Plain(pk.groups.AbstractQuadraticGroup):
        rotation: jax.Array
        translation: jax.Array
        algebra_ndim = 1
        bi_invariant_pairing = group.bi_invariant_pairing

        def _of(self):
            return group(self.rotation, self.translation)

        @classmethod
        def _from(cls, g):
            return cls(g.rotation, g.translation)

        @classmethod
        def exp(cls, u):
            return cls._from(group.exp(u))

        def log(self):
            return self._of().log()

        def multiply(self, other):
            return self._from(self._of() @ other._of())

        def inverse(self):
            return self._from(self._of().inverse())

        def identity_like(self):
            return self._from(self._of().identity_like())

        def adjoint(self, u):
            return self._of().adjoint(u)

        @classmethod
        def bracket(cls, u, v):
            return group.bracket(u, v)

        def check(self):
            return self

        def project(self):
            return self

        @classmethod
        def cayley(cls, u):
            return cls._from(group.cayley(u))

        def cayley_inverse(self):
            return self._of().cayley_inverse()

        @classmethod
        def dcayley_inv(cls, u, v):
            return group.dcayley_inv(u, v)

    return Plain


@pytest.mark.parametrize("group", [pk.SE3, pk.SO3xR3], ids=lambda g: g.__name__)
def test_the_closed_forms_agree_with_the_defaults(group):
    plain = _written_with_the_required_methods_only(group)
    rng = np.random.default_rng(3)
    u = jnp.asarray(0.8 * rng.normal(size=(2, 6)) / 3)
    x = jnp.asarray(rng.normal(size=(2, 6)))
    assert_closed_forms_are_the_defaults(group, plain, u, x)
    g, change = group.exp(x), group.exp_change(u)
    for side in ["right", "left"]:
        _close(g.product_change(change, side), plain._from(g).product_change(plain.exp_change(u), side), tol=1e-15)
