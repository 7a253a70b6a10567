"""A scene: a mechanical system on a bundle group, as one object.

It owns what every user of the system needs and would otherwise write again:
its bundle and form, its generator (the vector field of a `PRKMK` method),
the methods built for it, its invariants, and its field on the Euclidean
embedding ℝ⁹×ℝ³ for the solvers it is compared with.
"""

import abc
import functools
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from .._bundles import AbstractBundle, AlgebraPair, BundleElement, Cotangent
from .._fields import AbstractFieldOnBundle, Time
from ..compositions import CompositionCoefficients
from ..coordinates import AbstractCoordinates, Exp
from ..exact_flows import FreePart
from ..groups import SO3, AbstractLieGroup, AbstractRotationGroup, UnitQuaternion
from ..methods.prkmk import PRKMK
from ..methods.splitting import Splitting
from ..tableaus import PartitionedTableau


class AbstractScene(AbstractFieldOnBundle):
    """A system y' = y·(ξ, η) (body form) or (ξ, η)·y (space form) on a
    bundle group (`bundle`, `form`). Calling the scene is its generator, so
    it is itself the vector field: `integrate(scene.method(tableau), scene,
    y0, …)`, `PRKMKTerm(scene)`; a method built on another bundle or form
    refuses it. Physical parameters are `args` (differentiable, no
    recompilation)."""

    @abc.abstractmethod
    def __call__(self, t: Time, y: BundleElement, args: PyTree) -> AlgebraPair:
        """The generator (ξ, η) at (t, y)."""

    @abc.abstractmethod
    def invariants(self, y: BundleElement, args: PyTree, /) -> dict[str, Array]:
        """The quantities the exact flow keeps, for states with any leading
        axes (a trajectory): name → values."""

    @abc.abstractmethod
    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch d"]:
        """The state as a flat vector of the Euclidean embedding."""

    @abc.abstractmethod
    def from_embedding(self, z: Float[Array, "*batch d"]) -> BundleElement:
        """The state of a point of the embedding (`to_embedding`'s inverse);
        the point need not lie on the group, and nothing is checked."""

    def embedding_field(self, t: Time, z: Float[Array, " d"], args: PyTree, /) -> Float[Array, " d"]:
        """dz/dt on the embedding, for Euclidean solvers (`diffrax.ODETerm`).
        Nothing there keeps the state on the group: that is what such a
        comparison measures. Derived from the generator
        (`derived_embedding_field`); a scene may write it out for speed,
        tested equal to the derived one."""
        return derived_embedding_field(self, t, z, args)

    def reference_solution(
        self, y0: BundleElement, ts, args: PyTree, *, t0: float = 0.0, rtol: float = 1e-13, atol: float = 1e-13
    ) -> np.ndarray:
        """The exact flow from (t0, y0), embedded (`to_embedding`), at each
        time of `ts`: SciPy's DOP853 at `rtol`, `atol` on `embedding_field`,
        which knows nothing of this library's methods, so it is the
        reference for their errors and orders. One trajectory (`y0` without
        batch axes), in float64 (it needs `jax_enable_x64`); the field runs
        as one small compiled program on the host's CPU, where SciPy calls
        it, whatever the default device. Returns a NumPy array with one row
        per time of `ts`."""
        from scipy.integrate import solve_ivp  # SciPy only where a reference is asked for

        if jax.dtypes.canonicalize_dtype(np.float64) != np.float64:
            raise ValueError("reference_solution solves in float64: enable it with jax.config.update('jax_enable_x64', True).")
        times = np.atleast_1d(np.asarray(ts, dtype=float))
        if times.ndim != 1 or times.size == 0 or np.any(np.diff(times) < 0) or times[0] < t0:
            raise ValueError(f"ts must be one or more increasing times from t0 = {t0} on, got {ts!r}.")
        z0 = np.asarray(self.to_embedding(y0), dtype=float)
        if z0.ndim != 1:
            raise ValueError(f"reference_solution takes one trajectory (y0 without batch axes); its embedding has shape {z0.shape}.")
        if times[-1] == t0:
            return np.repeat(z0[None], times.size, axis=0)
        cpu = jax.devices("cpu")[0]
        field = _compiled_embedding_field(self)
        args_on_cpu = jax.device_put(args, cpu)

        def rhs(t, z):  # t as a float64 array: SciPy passes a float first, NumPy scalars after (one compile, not two)
            return np.asarray(field(np.asarray(t, np.float64), z, args_on_cpu))

        # SciPy's arrays go to the CPU as the default device: a `device_put`
        # of each state would cost several times the field's evaluation.
        with jax.default_device(cpu):
            solution = solve_ivp(rhs, (t0, times[-1]), z0, method="DOP853", rtol=rtol, atol=atol, t_eval=times)
        if not solution.success:
            raise RuntimeError(f"the reference solve (DOP853) failed: {solution.message}")
        return solution.y.T

    def method(self, tableau: PartitionedTableau, coordinates: AbstractCoordinates | None = None, **options) -> PRKMK:
        """The PRKMK method of `tableau` for this scene's bundle and form
        (exp coordinates unless given; `options` go to `PRKMK`)."""
        return PRKMK(self.bundle, Exp() if coordinates is None else coordinates, tableau=tableau, form=self.form, **options)

    def splitting(
        self,
        coefficients: CompositionCoefficients | None = None,
        coordinates: AbstractCoordinates | None = None,
        free_part: FreePart = "axes",
    ) -> Splitting:
        """The exact-flow splitting of this scene (`Splitting`), of order 2 or,
        with `coefficients`, of their order, its kinetic energy split into
        axis terms or taken whole (`free_part`); `TypeError` for a scene that
        does not split."""
        coordinates = Exp() if coordinates is None else coordinates
        # Splitting checks the scene's type itself, with its own message.
        return Splitting(scene=self, coefficients=coefficients, coordinates=coordinates, free_part=free_part)  # pyright: ignore[reportCallIssue, reportArgumentType]  # equinox: AbstractVars implemented by properties are not __init__ fields


@functools.cache
def _compiled_embedding_field(scene: AbstractScene):
    """`scene.embedding_field` jitted once per scene, so that every reference
    solve of a scene reuses one compiled program."""
    return jax.jit(scene.embedding_field)


def _floating_array(value) -> Array:
    """`value` as an array, integers converted to floats (a parameter given
    as `[1, 2, 3]` is meant as moments, not as integer data)."""
    value = jnp.asarray(value)
    return value if jnp.issubdtype(value.dtype, jnp.floating) else value.astype(float)


def checked_moments(owner: str, moments, allow_scalar: bool = False) -> Array:
    """`moments` as an array of principal moments of inertia, shape (…, 3)
    (or () where `allow_scalar`): a wrong shape is a `ValueError` naming
    `owner`; a moment that is not > 0 (a negative, zero or NaN moment: the
    inertia is not positive definite) raises where the data is known, eagerly
    or at run time under `jax.jit` (`eqx.error_if`)."""
    moments = _floating_array(moments)
    shape = moments.shape
    if not ((allow_scalar and shape == ()) or (len(shape) >= 1 and shape[-1] == 3)):
        allowed = "() or (…, 3)" if allow_scalar else "(…, 3)"
        raise ValueError(f"{owner}: the principal moments of inertia must have shape {allowed}, got {shape}.")
    return eqx.error_if(
        moments, ~jnp.all(moments > 0), f"{owner}: every principal moment of inertia must be > 0 (a positive-definite inertia)."
    )


def checked_inertia_tensor(owner: str, tensor) -> Array:
    """A body-frame inertia tensor (3, 3): symmetric and positive definite,
    checked where the data is known (`eqx.error_if`), as `checked_moments`."""
    tensor = _floating_array(tensor)
    if tensor.shape != (3, 3):
        raise ValueError(f"{owner}: an inertia tensor must have shape (3, 3), got {tensor.shape}.")
    scale = jnp.max(jnp.abs(tensor))
    symmetric = jnp.max(jnp.abs(tensor - tensor.T)) <= 1e3 * jnp.finfo(tensor.dtype).eps * scale
    # eigvalsh reads one triangle; the symmetry test above covers the other.
    positive = jnp.min(jnp.linalg.eigvalsh(tensor)) > 0
    return eqx.error_if(tensor, ~(symmetric & positive), f"{owner}: the inertia tensor must be symmetric and positive definite.")


def checked_pair_masses(owner: str, masses) -> Array:
    """The masses J (…, n) of the symmetric body on SO(n) (M = JΩ + ΩJ): the
    inertia Ω ↦ JΩ + ΩJ is positive definite where every Jᵢ + Jⱼ (i ≠ j) is
    > 0, checked where the data is known (`eqx.error_if`)."""
    masses = _floating_array(masses)
    if masses.ndim < 1 or masses.shape[-1] < 2:
        raise ValueError(f"{owner}: the masses J must have shape (…, n) with n ≥ 2, got {masses.shape}.")
    n = masses.shape[-1]
    sums = masses[..., :, None] + masses[..., None, :]
    off_diagonal = ~jnp.eye(n, dtype=bool)
    message = f"{owner}: every Jᵢ + Jⱼ (i ≠ j) must be > 0 (a positive-definite inertia)."
    return eqx.error_if(masses, ~jnp.all(jnp.where(off_diagonal, sums > 0, True)), message)


def checked_parameters(owner: str, args, kind: type):
    """`args` if it is a `kind` (the scene's parameter Module), else a
    `TypeError` naming `owner`."""
    if not isinstance(args, kind):
        raise TypeError(f"{owner} takes its parameters as args={kind.__name__}(...), got {type(args).__name__}.")
    return args


def checked_vector(owner: str, vector) -> Array:
    """`vector` as a body-frame 3-vector (shape (…, 3)), or a `ValueError`
    naming `owner`."""
    vector = jnp.asarray(vector)
    if vector.ndim < 1 or vector.shape[-1] != 3:
        raise ValueError(f"{owner} must be a body-frame vector of shape (…, 3), got shape {vector.shape}.")
    return vector


def rotation_matrix(element) -> Array:
    """The matrix of a rotation (`SO3`, `SOn`, `UnitQuaternion`; any leading
    axes): the groups the scenes live on."""
    if isinstance(element, UnitQuaternion):
        return element.as_matrix()
    if not isinstance(element, AbstractRotationGroup):
        raise TypeError(f"this scene lives on rotation groups (SO3, SOn, UnitQuaternion), got a {type(element).__name__} element.")
    return element.matrix


ATTITUDES = (SO3, UnitQuaternion)
"""The representations of a body's attitude the one-body scenes accept."""


def attitude_like(element: AbstractLieGroup, matrix: Array) -> SO3 | UnitQuaternion:
    """The rotation `matrix` in `element`'s representation. A quaternion is
    continued from `element` (q times the quaternion with w ≥ 0 of the turn
    qᵀ·matrix), so that a step that turns by less than π never jumps from q
    to −q."""
    if isinstance(element, UnitQuaternion):
        turn = jnp.swapaxes(element.as_matrix(), -1, -2) @ matrix
        return element.multiply(UnitQuaternion.from_matrix(turn))
    return SO3(matrix)


def derived_embedding_field(scene: AbstractScene, t: Time, z: Float[Array, " d"], args: PyTree) -> Float[Array, " d"]:
    """d/ds at s = 0 of the embedded y·exp(s(ξ, η)) (body form) or
    exp(s(ξ, η))·y (space form), y = `scene.from_embedding(z)` and (ξ, η) the
    generator there: the scene's equations on the embedding, by `jax.jvp`
    through the bundle's own product and exponential. Both are polynomial in
    the entries of y, so the field is defined off the group too."""
    y = scene.from_embedding(z)
    xi, eta = scene(t, y, args)

    def moved(s):
        flow = scene.bundle.map(Exp(), (s * xi, s * eta))
        return scene.to_embedding(scene.bundle.multiply(y, flow) if scene.form == "body" else scene.bundle.multiply(flow, y))

    zero = jnp.zeros((), jnp.result_type(z))
    return jax.jvp(moved, (zero,), (jnp.ones_like(zero),))[1]


def attitude_of(matrix: Array, attitude: type[AbstractLieGroup] = SO3) -> SO3 | UnitQuaternion:
    """A rotation matrix as an `SO3`, or, for `attitude` = `UnitQuaternion`,
    as its quaternion with w ≥ 0."""
    return UnitQuaternion.from_matrix(matrix) if attitude is UnitQuaternion else SO3(matrix)


def rotation_and_vector_state(z: Float[Array, "*batch 12"], attitude: type[AbstractLieGroup] = SO3) -> BundleElement:
    """`rotation_and_vector_embedding`'s inverse: (Q, v), Q in the
    representation `attitude` (`attitude_of`)."""
    return BundleElement(attitude_of(z[..., :9].reshape(*z.shape[:-1], 3, 3), attitude), z[..., 9:])


def rotation_and_vector_embedding(y: BundleElement) -> Float[Array, "*batch 12"]:
    """(Q row-major, v) for a state on SO(3) with a 3-vector fiber."""
    q = rotation_matrix(y.base)
    return jnp.concatenate([q.reshape(*q.shape[:-2], 9), y.fiber], axis=-1)


class AbstractBodyOnTStarSO3(AbstractScene):
    """A scene on T*SO(3) (`Cotangent(SO3)`) in body form: state (Q, Π),
    embedded as (Q row-major, Π)."""

    bundle: ClassVar[AbstractBundle] = Cotangent(SO3)  # pyright: ignore[reportIncompatibleVariableOverride]  # equinox lets a ClassVar implement an AbstractVar
    form: ClassVar[Literal["space", "body"]] = "body"  # pyright: ignore[reportIncompatibleVariableOverride]  # as above

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 12"]:
        return rotation_and_vector_embedding(y)

    def from_embedding(self, z: Float[Array, "*batch 12"]) -> BundleElement:
        return rotation_and_vector_state(z)
