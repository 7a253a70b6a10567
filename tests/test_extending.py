"""What a contributor adds, in one file: a coordinate map and a rotation group
written here, outside the package, run through every bundle, both drivers
and the splitting methods with nothing else changed (CONTRIBUTING,
"Adding a coordinate map", "Adding a base group")."""

from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from test_groups import bundle_algebra, tangent_to_algebra

import prkmk_jax as pk
from helpers import empirical_order, max_leaf_difference, scene_order
from prkmk_jax.groups import AbstractRotationGroup
from prkmk_jax.scenes import FreeRigidBody, random_rotation


# --- a coordinate map: φ(u) = cay(u/2)², on SO(3) ------------------------------------------
class SquaredHalfCayley(pk.AbstractCoordinates):
    """φ(u) = cay(u/2)²: a fourth-order rational approximation of exp (it
    turns by 4·atan(θ/4)), with φ(−u) = φ(u)⁻¹. It says φ, φ⁻¹ and dφ⁻¹
    only: the action, the changes, the planar rotation of the splittings and
    the tangent lift to G ⋉ 𝔤 (ψ_{σu} = dφ_{σu}) are the defaults."""

    truncation: None = eqx.field(static=True, default=None)
    maps_lines_to_subgroups: ClassVar[bool] = False

    def check_group(self, group):
        if group is not pk.SO3:
            raise TypeError(f"SquaredHalfCayley is written for SO3 only, got {group.__name__}.")

    def group_map(self, group, u):
        half = group.cayley(0.5 * u)
        return half.multiply(half)

    def group_inverse_map(self, g):
        root = type(g).exp(0.5 * g.log())
        return 2.0 * root.cayley_inverse()

    def group_inverse_differential(self, group, u, x):
        rotation = group.cayley(0.5 * u).matrix
        eye = jnp.broadcast_to(jnp.eye(3, dtype=rotation.dtype), rotation.shape)
        z = jnp.linalg.solve(eye + rotation, x[..., None])[..., 0]  # (I + Ad_c)⁻¹ x
        return 2.0 * group.dcayley_inv(0.5 * u, z)


TOY_MAP = SquaredHalfCayley()
SO3_BUNDLES = {
    "direct": pk.DirectProduct(pk.SO3),
    "semidirect-left": pk.Semidirect(pk.SO3, "left"),
    "semidirect-right": pk.Semidirect(pk.SO3, "right"),
    "cotangent": pk.Cotangent(pk.SO3),
    "cartesian": pk.Cartesian(pk.SO3),
}


def test_the_toy_map_is_what_it_says_on_so3():
    """cay(u/2)² against the matrix formula, and a rotation by 4·atan(θ/4)."""
    u = jnp.array([0.3, -0.7, 0.5])
    half = np.linalg.solve(np.eye(3) - np.asarray(pk.hat(u)) / 4, np.eye(3) + np.asarray(pk.hat(u)) / 4)
    np.testing.assert_allclose(TOY_MAP.group_map(pk.SO3, u).matrix, half @ half, atol=1e-14)
    theta = float(jnp.linalg.norm(u))
    turned = pk.SO3.exp(u / theta * 4 * np.arctan(theta / 4)).matrix
    np.testing.assert_allclose(TOY_MAP.group_map(pk.SO3, u).matrix, turned, atol=1e-14)
    sine, cosine = TOY_MAP.planar_rotation(jnp.asarray(theta))
    np.testing.assert_allclose([sine, cosine], [np.sin(4 * np.arctan(theta / 4)), np.cos(4 * np.arctan(theta / 4))], atol=1e-15)


@pytest.mark.parametrize("name", SO3_BUNDLES)
@pytest.mark.parametrize("scale", [1e-7, 0.3, 1.0])
def test_the_lifted_toy_map_inverts_and_its_inverse_differential_matches_autodiff(name, scale):
    """On every bundle, as each bundle lifts it: f⁻¹(f(U)) = U, and with
    X = d/dt f(U + tV)·f(U)⁻¹ (jax.jvp), df⁻¹_U(X) = V."""
    bundle = SO3_BUNDLES[name]
    rng = np.random.default_rng(4)
    U = bundle_algebra(bundle, scale * rng.normal(size=6), scale * rng.normal(size=6))
    V = bundle_algebra(bundle, rng.normal(size=6), rng.normal(size=6))
    assert max_leaf_difference(bundle.inverse_map(TOY_MAP, bundle.map(TOY_MAP, U)), U) < 1e-12
    f_inverse = bundle.inverse(bundle.map(TOY_MAP, U))
    tangent = jax.jvp(lambda W: bundle.multiply(bundle.map(TOY_MAP, W), f_inverse), (U,), (V,))[1]
    X = tangent_to_algebra(bundle, tangent)
    assert max_leaf_difference(bundle.inverse_differential(TOY_MAP, U, X, method_order=4), V) < 1e-11


# Each bundle once, each tableau on two of them.
@pytest.mark.parametrize(
    "name, tableau",
    [
        ("cotangent", pk.stormer_verlet),
        ("cartesian", pk.lobatto_iiia_iiib4),
        ("semidirect-right", pk.lobatto_iiia_iiib4),
        ("direct", pk.stormer_verlet),
    ],
    ids=["cotangent-SV", "cartesian-Lobatto4", "semidirect-right-Lobatto4", "direct-SV"],
)
def test_prkmk_with_the_toy_map_has_the_tableau_order(name, tableau):
    form = "body" if name == "cotangent" else "space"
    slope, _ = empirical_order(pk.PRKMK(SO3_BUNDLES[name], TOY_MAP, tableau, form=form))
    assert abs(slope - tableau.order) < 0.25, slope


def test_the_toy_map_refuses_other_groups():
    with pytest.raises(TypeError, match="SO3 only"):
        pk.PRKMK(pk.Cotangent(pk.SOn), TOY_MAP, pk.stormer_verlet)


def test_a_splitting_with_the_toy_map_is_symmetric_and_of_order_two():
    scene = FreeRigidBody()
    inertia = jnp.array([7 / 8, 5 / 8, 1 / 4])
    y0 = pk.BundleElement(pk.SO3(jnp.asarray(random_rotation(3))), jnp.array([0.25, 0.625, 0.875]))
    method = scene.splitting(coordinates=TOY_MAP)
    assert pk.symmetry_defect(method, scene, y0, 0.2, inertia) < 1e-13
    slope, errors = scene_order(method, scene, y0, inertia, 2.0, [20, 40, 80])
    assert abs(slope - 2) < 0.2, (slope, errors)


# --- a rotation group: SO(2), the planar pendulum on T*SO(2) ---------------------------------
class SO2(AbstractRotationGroup):
    """Rotations of the plane; the algebra is ℝ (shape (1,)), abelian."""

    matrix: jax.Array
    """The rotation matrix, shape (*batch, 2, 2)."""
    algebra_ndim: ClassVar[int] = 1
    bi_invariant_pairing: ClassVar[bool] = True

    @staticmethod
    def _turn(sine, cosine):
        return SO2(jnp.stack([jnp.stack([cosine, -sine], -1), jnp.stack([sine, cosine], -1)], -2)[..., 0, :, :])

    @classmethod
    def exp(cls, u):
        return cls._turn(jnp.sin(u), jnp.cos(u))

    def log(self):
        return jnp.arctan2(self.matrix[..., 1, 0], self.matrix[..., 0, 0])[..., None]

    def adjoint(self, u):
        return u

    @classmethod
    def bracket(cls, u, v):
        return jnp.zeros_like(v)

    @classmethod
    def cayley(cls, u):
        quarter = 0.25 * u * u
        return cls._turn(u / (1.0 + quarter), (1.0 - quarter) / (1.0 + quarter))

    def cayley_inverse(self):
        return 2.0 * self.matrix[..., 1, 0:1] / (1.0 + self.matrix[..., 0, 0:1])

    @classmethod
    def dcayley_inv(cls, u, v):
        return v * (1.0 + 0.25 * u * u)


def _pendulum(t, y, args):
    """θ'' = −sin θ on T*SO(2), body form: (ξ, η) = (p, −sin θ)."""
    return y.fiber, -y.base.matrix[..., 1, 0:1]


def _pendulum_reference(theta0, p0, t_end):
    def field(t, z):
        return [z[1], -np.sin(z[0])]

    return scipy.integrate.solve_ivp(field, (0.0, t_end), [theta0, p0], method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]


@pytest.mark.parametrize("coordinates", [pk.Exp(), pk.Cayley()], ids=["exp", "cayley"])
def test_a_new_rotation_group_runs_the_pendulum_at_the_tableau_order(coordinates):
    """SO(2) above holds only its algebra (seven methods): the product,
    inverse, checks and corrections come from `AbstractRotationGroup`, the
    differentials, actions and changes are the defaults, and both drivers
    run it."""
    method = pk.PRKMK(pk.Cotangent(SO2), coordinates, pk.stormer_verlet, form="body")
    theta0, p0, t_end = 1.2, 0.3, 4.0
    y0 = pk.BundleElement(SO2.exp(jnp.array([theta0])), jnp.array([p0]))
    expected = _pendulum_reference(theta0, p0, t_end)
    errors = []
    for n in (40, 80, 160):
        y = jax.tree.map(lambda leaf: leaf[-1], pk.integrate(method, _pendulum, y0, 0.0, t_end / n, n, save_every=n).ys)
        errors.append(max(abs(float(y.base.log()[0]) - expected[0]), abs(float(y.fiber[0]) - expected[1])))
    slope = np.polyfit(np.log(t_end / np.array([40, 80, 160])), np.log(errors), 1)[0]
    assert abs(slope - 2) < 0.1, (slope, errors)
    solution = diffrax.diffeqsolve(pk.PRKMKTerm(_pendulum), pk.PRKMKSolver(method), 0.0, t_end, t_end / 160, y0)
    assert solution.ys is not None
    np.testing.assert_allclose(solution.ys.fiber[-1], y.fiber, atol=1e-13)
    with pytest.raises(Exception, match="SO2"):
        SO2(jnp.array([[1.0, 0.0], [0.0, 2.0]])).check()
