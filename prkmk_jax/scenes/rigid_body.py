"""Rigid-body scenes of the paper's §3 and §5.

* The symmetric rigid body (3.3) on SO(n)×SO(n) (`Cartesian`), body form:
  Q' = QΩ, P' = PΩ, M = QᵀP − PᵀQ, Ω = I⁻¹M.
* The unreduced rigid body (§3.2) on T*SO(n), body form: g' = gΩ, Π' = [Π, Ω]
  (Π × Ω for n = 3), on `Cotangent`/left `Semidirect` (where it is the
  generator (Ω, 0)) or on `DirectProduct` (generator (Ω, [Π, Ω])).
* The same body on the embedding ℝ⁹×ℝ³ (`embedding_field`), for Euclidean
  solvers to be compared with.

The inertia is passed as `args` (differentiable, no recompiles): for SO(3) a
3-vector I acting on the vector form of M; for SO(n) a vector J of n
"mass" entries with M = JΩ + ΩJ, i.e. Ω_ij = M_ij/(J_i + J_j) (for n = 3 this
is I_k = J_i + J_j).
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .. import diagnostics, exact_flows
from .._bundles import AbstractBundle, AbstractSemidirect, BundleElement, Cartesian, Cotangent, DirectProduct
from ..groups import SO3, SOn, hat, vee
from ..methods.exact import ExactFlow
from . import body_frame
from .base import (
    ATTITUDES,
    AbstractScene,
    attitude_like,
    checked_inertia_tensor,
    checked_moments,
    checked_pair_masses,
    rotation_and_vector_embedding,
    rotation_and_vector_state,
    rotation_matrix,
)
from .free_flow import FreeBodyFlow, free_body_flow

PAPER_INERTIA = np.array([7 / 8, 5 / 8, 1 / 4])
"""Eq. (5.2), acting on the vector form of M."""
PAPER_MOMENTUM = np.array([0.250, 0.625, 0.875])
"""Eq. (5.1), M₀ (and Π₀ in §5.2)."""
PAPER_SEED = 2003
"""Seed of the random initial attitudes (the paper does not give one)."""


def random_rotation(seed: int, n: int = 3) -> np.ndarray:
    """A Haar-random rotation: QR of a Gaussian matrix from
    `numpy.random.default_rng(seed)`, signs fixed so R has det +1."""
    a = np.random.default_rng(seed).normal(size=(n, n))
    q, r = np.linalg.qr(a)
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def skew_arcsinh(m: np.ndarray) -> np.ndarray:
    """The skew S with sinh(S) = m for skew m, i.e. exp(S) − exp(−S) = 2m.

    On each invariant plane S acts as a rotation by θ and sinh(S) as
    sin(θ)·J, so θ = arcsin(μ) for the eigen-angle μ of m: an *arcsin*, defined
    when the spectral norm of m is ≤ 1 (§5.1 uses m = M₀/2, norm 0.552).
    """
    m = np.asarray(m, dtype=np.float64)
    if np.abs(m + m.T).max() > 1e-14 * max(1.0, np.abs(m).max()):
        raise ValueError("skew_arcsinh needs a skew-symmetric matrix.")
    # i·m is Hermitian with real eigenvalues μ; m = −i W diag(μ) Wᴴ.
    mu, w = np.linalg.eigh(1j * m)
    if np.abs(mu).max() >= 1:
        raise ValueError(f"sinh(S) = m has no real skew solution: spectral norm of m is {np.abs(mu).max():.3f} ≥ 1.")
    s = -1j * (w * np.arcsin(mu)) @ w.conj().T
    return np.real(s)


def symmetric_initial_state(q0: np.ndarray, m0: np.ndarray) -> BundleElement:
    """(Q₀, P₀) with P₀ = Q₀ exp(sinh⁻¹(M₀/2)), so Q₀ᵀP₀ − P₀ᵀQ₀ = M₀ (§5.1).

    `m0` is a 3-vector (SO(3), vector form) or a skew (n, n) matrix (SO(n))."""
    m0 = np.asarray(m0, dtype=np.float64)
    if m0.ndim == 1:
        if np.linalg.norm(m0) / 2 >= 1:
            raise ValueError(f"sinh(S) = M₀/2 has no real skew solution: |M₀|/2 = {np.linalg.norm(m0) / 2:.3f} ≥ 1.")
        return from_attitude_and_momentum(Cartesian(SO3), jnp.asarray(q0), jnp.asarray(m0))
    s = skew_arcsinh(m0 / 2)
    p0 = q0 @ np.asarray(SOn.exp(jnp.asarray(s)).matrix)
    return BundleElement(SOn(jnp.asarray(q0)), SOn(jnp.asarray(p0)))


def angular_velocity(momentum: Array, inertia: Array, matrix: bool) -> Array:
    """Ω = I⁻¹M: M_ij/(J_i + J_j) for skew matrices M (`matrix`, SO(n)), or
    M/I for vectors (SO(3)); leading batch axes allowed. The form is said,
    not read from the shape: three SO(3) momenta (3, 3) are not a matrix."""
    if matrix:
        return momentum / (inertia[..., :, None] + inertia[..., None, :])
    return momentum / inertia


def embedding_field(t, z: Float[Array, "12"], inertia: Float[Array, "3"] | Float[Array, "3 3"]) -> Float[Array, "12"]:
    """The free rigid body on the embedding ℝ⁹×ℝ³, for Euclidean solvers
    (`diffrax.ODETerm`) to be compared with: z is Q flattened row-major, then
    Π; Q' = QΩ̂, Π' = Π × Ω, Ω = I⁻¹Π. `inertia` is the principal moments (3,)
    or a symmetric positive-definite tensor (3, 3). Nothing keeps Q
    orthogonal; that is what such a comparison measures."""
    inertia = jnp.asarray(inertia)
    if inertia.shape not in ((3,), (3, 3)):
        raise ValueError(f"inertia must have shape (3,) or (3, 3), got {inertia.shape}.")
    if z.shape != (12,):
        raise ValueError(f"the embedded state is (Q row-major, Π) of shape (12,), got {z.shape}.")
    q, pi = z[:9].reshape(3, 3), z[9:]
    omega = _body_rate(pi, inertia)
    return jnp.concatenate([(q @ hat(omega)).ravel(), jnp.cross(pi, omega)])


def _body_rate(pi, inertia):
    """Ω = I⁻¹Π for principal moments (3,) or a full tensor (3, 3)."""
    inertia = jnp.asarray(inertia)
    return pi / inertia if inertia.ndim == 1 else jnp.linalg.solve(inertia, pi)


def _commutator_or_cross(a, b, matrix: bool):
    """[a, b]: the commutator of skew matrices (`matrix`, SO(n)) or the cross
    product of vectors (SO(3)); leading batch axes allowed."""
    if matrix:
        return a @ b - b @ a
    return jnp.cross(a, b)


def symmetric_rigid_body(t, y: BundleElement, inertia) -> tuple[Array, Array]:
    """Body-form generator (Ω, Ω) of (3.3) on `Cartesian(SO3)` or `Cartesian(SOn)`."""
    q, p = rotation_matrix(y.base), rotation_matrix(y.fiber)
    m = jnp.swapaxes(q, -1, -2) @ p - jnp.swapaxes(p, -1, -2) @ q  # leading batch axes allowed
    omega = angular_velocity(vee(m), inertia, False) if isinstance(y.base, SO3) else angular_velocity(m, inertia, True)
    return omega, omega


def unreduced_rigid_body(bundle):
    """Body-form generator of g' = gΩ, Π' = [Π, Ω] on `bundle`: (Ω, 0) on the
    left semidirect/cotangent bundle (the product supplies Ad*), (Ω, [Π, Ω])
    on the direct product."""
    if isinstance(bundle, AbstractSemidirect):
        if bundle.trivialization != "left":
            raise ValueError("the unreduced rigid body is written for the left-trivialised (body) bundle.")

        def semidirect_field(t, y, inertia):
            omega = angular_velocity(y.fiber, inertia, bundle.base is SOn)
            return omega, jnp.zeros_like(omega)

        return semidirect_field
    if isinstance(bundle, DirectProduct):

        def direct_product_field(t, y, inertia):
            matrix = bundle.base is SOn
            omega = angular_velocity(y.fiber, inertia, matrix)
            return omega, _commutator_or_cross(y.fiber, omega, matrix)

        return direct_product_field
    raise TypeError(f"the unreduced rigid body lives on Cotangent, Semidirect(left) or DirectProduct, not {type(bundle).__name__}.")


def attitude_and_momentum(bundle, y: BundleElement) -> tuple[Array, Array]:
    """(g, Π) of a state (or trajectory): for `Cartesian`, g = Q and
    Π = QᵀP − PᵀQ (vector form on SO(3)); otherwise the base and the fiber."""
    if isinstance(bundle, Cartesian):
        q, p = rotation_matrix(y.base), rotation_matrix(y.fiber)
        m = jnp.swapaxes(q, -1, -2) @ p - jnp.swapaxes(p, -1, -2) @ q
        return q, (vee(m) if isinstance(y.base, SO3) else m)
    return rotation_matrix(y.base), y.fiber


def from_attitude_and_momentum(bundle, g: Array, pi: Array) -> BundleElement:
    """Inverse of `attitude_and_momentum` on SO(3) (P = g exp(sinh⁻¹(Π/2)) for `Cartesian`)."""
    if isinstance(bundle, Cartesian):
        # `skew_arcsinh` of hat(Π/2) in vector form (differentiable): the
        # direction of Π, the angle arcsin(|Π|/2).
        norm = jnp.linalg.norm(pi)
        s = jnp.arcsin(norm / 2) / norm * pi
        return BundleElement(SO3(g), SO3(g @ SO3.exp(s).matrix))
    return BundleElement(SO3(g), pi)


def elliptic_momentum(pi0, inertia, t) -> np.ndarray:
    """Body momentum Π(t) of Euler's equations Π' = Π × I⁻¹Π in closed form
    (NumPy/SciPy, float64), for principal moments `inertia` (3,) with three
    distinct values.

    With the axes ordered so that I_c, I_s, I_d are the inertia of the axes
    carrying cn, sn and dn, Π_c = A_c cn u, Π_s = A_s sn u, Π_d = ±A_d dn u,
    u = ±λt + u₀ (Landau–Lifshitz §37): the dn axis is the one of largest
    inertia when |Π|² > 2H·I_mid, of smallest inertia otherwise. u₀ comes
    from the initial phase, the signs from Π₀ and from Π'(0).
    """
    from scipy.special import ellipj, ellipkinc

    pi0, inertia, t = np.asarray(pi0, float), np.asarray(inertia, float), np.asarray(t, float)
    if inertia.shape != (3,) or len(set(inertia.tolist())) != 3:
        raise ValueError(f"the closed form needs three distinct principal moments, got {inertia}.")
    m2 = pi0 @ pi0
    two_h = pi0 @ (pi0 / inertia)
    lo, mid, hi = np.argsort(inertia)
    c, s, d = (lo, mid, hi) if m2 > two_h * inertia[mid] else (hi, mid, lo)
    i_c, i_s, i_d = inertia[c], inertia[s], inertia[d]
    a_c = i_c * np.sqrt((two_h * i_d - m2) / (i_c * (i_d - i_c)))
    a_s = i_s * np.sqrt((two_h * i_d - m2) / (i_s * (i_d - i_s)))
    a_d = i_d * np.sqrt((m2 - two_h * i_c) / (i_d * (i_d - i_c)))
    lam = np.sqrt((i_d - i_s) * (m2 - two_h * i_c) / (i_c * i_s * i_d))
    k2 = (i_s - i_c) * (two_h * i_d - m2) / ((i_d - i_s) * (m2 - two_h * i_c))
    phi0 = np.arctan2(pi0[s] / a_s, pi0[c] / a_c)
    u0 = ellipkinc(phi0, k2)
    sn0, cn0, dn0, _ = ellipj(u0, k2)
    # The direction of u: match d/dt of the sn and cn components at t = 0.
    dpi0 = np.cross(pi0, pi0 / inertia)
    rate_s, rate_c = a_s * cn0 * dn0 * lam, -a_c * sn0 * dn0 * lam
    sigma = np.sign(dpi0[s] * rate_s + dpi0[c] * rate_c) or 1.0
    sn, cn, dn, _ = ellipj(sigma * lam * t + u0, k2)
    out = np.empty(t.shape + (3,))
    out[..., c], out[..., s], out[..., d] = a_c * cn, a_s * sn, np.sign(pi0[d]) * a_d * dn
    return out


class FreeRigidBody(AbstractScene, exact_flows.AbstractSplitScene, exact_flows.AbstractSolvedScene):
    """The unreduced free rigid body g' = gΩ, Π' = Π × Ω on T*SO(3), body form.

    `bundle` is `Cotangent(SO3)` (default) or `Semidirect(SO3, "left")`,
    where the product supplies Π × Ω and the generator is (Ω, 0), or
    `DirectProduct(SO3)` with (Ω, Π × Ω). `args` is the inertia: principal
    moments (3,) or a symmetric positive-definite tensor (3, 3) in the body
    frame (Ω = I⁻¹Π).

    It splits (`splitting()`) into the three axis terms ½Πᵢ²/Iᵢ of its
    energy, each a rotation about a body axis (principal moments only), the
    axis of smallest inertia outermost (`body_frame.InertiaOrderedFrame`).
    Its whole flow is known in closed form (`exact_flow()`, principal
    moments only: `free_flow.free_body_flow`)."""

    bundle: AbstractBundle = eqx.field(default_factory=lambda: Cotangent(SO3))
    form: Literal["space", "body"] = eqx.field(default="body", static=True)

    def __check_init__(self):
        left = isinstance(self.bundle, AbstractSemidirect) and self.bundle.trivialization == "left"
        if not (left or isinstance(self.bundle, DirectProduct)) or self.bundle.base not in ATTITUDES:
            raise TypeError(
                "FreeRigidBody lives on Cotangent(G), Semidirect(G, 'left') or DirectProduct(G) for G = SO3 or UnitQuaternion, "
                f"got {self.bundle!r}."
            )
        if self.form != "body":
            raise ValueError("FreeRigidBody is written in body form.")

    def checked_args(self, inertia):
        """The inertia: principal moments (3,), each > 0, or a symmetric
        positive-definite tensor (3, 3)."""
        shape = jnp.shape(inertia)
        if shape == (3, 3):
            return checked_inertia_tensor("FreeRigidBody", inertia)
        if shape != (3,):
            raise ValueError(f"FreeRigidBody: the inertia is principal moments (3,) or a tensor (3, 3), got shape {shape}.")
        return checked_moments("FreeRigidBody", inertia)

    def __call__(self, t, y: BundleElement, inertia):
        omega = _body_rate(y.fiber, inertia)
        if isinstance(self.bundle, DirectProduct):
            return omega, jnp.cross(y.fiber, omega)
        return omega, jnp.zeros_like(omega)

    def invariants(self, y: BundleElement, inertia) -> dict[str, Array]:
        g, pi = rotation_matrix(y.base), y.fiber
        omega = jax.vmap(_body_rate, in_axes=(0, None))(pi.reshape(-1, 3), inertia).reshape(pi.shape)
        return {
            "energy": diagnostics.energy(pi, omega),
            "momentum norm": diagnostics.body_momentum_norm(pi),
            "spatial momentum": diagnostics.spatial_momentum(g, pi),
            "orthogonality": diagnostics.orthogonality_defect(g),
        }

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch 12"]:
        return rotation_and_vector_embedding(y)

    def from_embedding(self, z: Float[Array, "*batch 12"]) -> BundleElement:
        return rotation_and_vector_state(z, self.bundle.base)

    def embedding_field(self, t, z, inertia):
        """Written out (`embedding_field`, the Euclidean peers' field in the
        benchmarks); equal to the generator's (`derived_embedding_field`)."""
        return embedding_field(t, z, inertia)

    def exact_flow(self) -> ExactFlow:
        """The method whose every step is this body's exact flow
        (`ExactFlow`, `free_flow.free_body_flow`)."""
        return ExactFlow(self)  # pyright: ignore[reportCallIssue]  # equinox: AbstractVars implemented by properties are not __init__ fields

    def solved_flow(self, t, y, h, inertia):
        del t  # the free body's field does not depend on time
        moments = body_frame.principal_moments(inertia, "FreeRigidBody", closed_form=True)
        q, pi = free_body_flow(rotation_matrix(y.base), y.fiber, moments, h)
        return BundleElement(attitude_like(y.base, q), pi)

    def exact_flows(self, inertia, free_part="axes"):
        moments = body_frame.principal_moments(inertia, "FreeRigidBody")
        frame = body_frame.InertiaOrderedFrame.of(moments)
        if free_part == "exact":
            return (FreeBodyFlow(frame, moments, self.bundle.base),)
        return body_frame.body_axis_rotations(frame, moments, self.bundle.base)

    def pack(self, y, inertia):
        return body_frame.packed_body_state(y, body_frame.principal_moments(inertia, "FreeRigidBody"))

    def unpack(self, z, like, inertia):
        return body_frame.unpacked_body_state(z, like, body_frame.principal_moments(inertia, "FreeRigidBody"))

    def onto_group(self, z):
        return body_frame.renormalized_body_state(z, self.bundle.base)


class SymmetricRigidBody(AbstractScene, exact_flows.AbstractSplitScene):
    """The symmetric rigid body (3.3) on SO(n)×SO(n), body form: Q' = QΩ,
    P' = PΩ with M = QᵀP − PᵀQ and Ω = I⁻¹M (`angular_velocity`).

    `bundle` is `Cartesian(SO3)` (default; `args` the principal moments (3,))
    or `Cartesian(SOn)` (`args` the n "masses" J, M = JΩ + ΩJ).

    On SO(3)×SO(3) it splits (`splitting()`) into three axis terms: along
    the i-th, Mᵢ is constant and Q and P turn together about eᵢ at the rate
    Mᵢ/Iᵢ, y·exp(t(ωᵢeᵢ, ωᵢeᵢ))."""

    bundle: AbstractBundle = eqx.field(default_factory=lambda: Cartesian(SO3))
    form: Literal["space", "body"] = eqx.field(default="body", static=True)

    def __check_init__(self):
        if not (isinstance(self.bundle, Cartesian) and self.bundle.base in (SO3, SOn)):
            raise TypeError(f"SymmetricRigidBody lives on Cartesian(SO3) or Cartesian(SOn), got {self.bundle!r}.")
        if self.form != "body":
            raise ValueError("SymmetricRigidBody is written in body form.")

    def checked_args(self, inertia):
        """On SO(3) the principal moments (…, 3), each > 0; on SO(n) the
        masses J (…, n), every Jᵢ + Jⱼ > 0."""
        if self.bundle.base is SO3:
            return checked_moments("SymmetricRigidBody", inertia)
        return checked_pair_masses("SymmetricRigidBody", inertia)

    def __call__(self, t, y: BundleElement, inertia):
        return symmetric_rigid_body(t, y, inertia)

    def invariants(self, y: BundleElement, inertia) -> dict[str, Array]:
        g, m = attitude_and_momentum(self.bundle, y)
        matrix = self.bundle.base is SOn
        return {
            "energy": diagnostics.energy(m, angular_velocity(m, inertia, matrix), matrix),
            "momentum norm": diagnostics.body_momentum_norm(m, matrix),
            "spatial momentum": diagnostics.spatial_momentum(g, m, matrix),
            "orthogonality": jnp.maximum(
                diagnostics.orthogonality_defect(rotation_matrix(y.base)), diagnostics.orthogonality_defect(rotation_matrix(y.fiber))
            ),
        }

    def to_embedding(self, y: BundleElement) -> Float[Array, "*batch d"]:
        q, p = rotation_matrix(y.base), rotation_matrix(y.fiber)
        return jnp.concatenate([q.reshape(*q.shape[:-2], -1), p.reshape(*p.shape[:-2], -1)], axis=-1)

    def from_embedding(self, z: Float[Array, "*batch d"]) -> BundleElement:
        n = int(round((z.shape[-1] // 2) ** 0.5))
        q, p = z[..., : n * n], z[..., n * n :]
        group = SO3 if self.bundle.base is SO3 else SOn
        return BundleElement(group(q.reshape(*z.shape[:-1], n, n)), group(p.reshape(*z.shape[:-1], n, n)))

    def exact_flows(self, inertia, free_part="axes"):
        if free_part != "axes":
            raise ValueError("SymmetricRigidBody splits into its axis terms only (free_part='axes').")
        if self.bundle.base is not SO3:
            raise ValueError("SymmetricRigidBody splits on Cartesian(SO3) only; on SO(n) use a PRKMK method.")
        moments = body_frame.principal_moments(inertia, "SymmetricRigidBody", batched=True)
        ordered = body_frame.InertiaOrderedFrame.of(moments).vector(moments)

        def rate(axis):
            # Mᵢ = Aₖⱼ − Aⱼₖ with A = QᵀP, Aₐᵦ = Σᵣ Q_rₐ P_rᵦ, (i, j, k) cyclic. In
            # the relabelled frame this gives the parity times Mᵢ: the turn the
            # left-handed frame needs (`InertiaOrderedFrame`).
            j, k = (axis + 1) % 3, (axis + 2) % 3

            def entry(z, a, b):
                return sum(z[3 * r + a] * z[9 + 3 * r + b] for r in range(3))

            return lambda z, args: (entry(z, k, j) - entry(z, j, k)) / ordered[..., axis]

        pairs = [body_frame.column_pairs(axis, 0) + body_frame.column_pairs(axis, 9) for axis in range(3)]
        return tuple(exact_flows.AxisRotation(axis, pair, rate(axis), rate_reads_turned_rows=True) for axis, pair in zip(range(3), pairs))

    def pack(self, y, inertia):
        q, p = rotation_matrix(y.base), rotation_matrix(y.fiber)
        flat = jnp.concatenate([q.reshape(*q.shape[:-2], 9), p.reshape(*p.shape[:-2], 9)], axis=-1)
        frame = body_frame.InertiaOrderedFrame.of(body_frame.principal_moments(inertia, "SymmetricRigidBody", batched=True))
        return frame.relabel(jnp.moveaxis(flat, -1, 0), (0, 9), ())

    def unpack(self, z, like, inertia):
        frame = body_frame.InertiaOrderedFrame.of(body_frame.principal_moments(inertia, "SymmetricRigidBody", batched=True))
        flat = jnp.moveaxis(frame.restore(z, (0, 9), ()), 0, -1)
        batch = flat.shape[:-1]
        return BundleElement(SO3(flat[..., :9].reshape(*batch, 3, 3)), SO3(flat[..., 9:].reshape(*batch, 3, 3)))

    def onto_group(self, z):
        return exact_flows.renormalized_rotations(z, (0, 9))
