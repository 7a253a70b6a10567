"""Partitioned Runge–Kutta–Munthe-Kaas integrators on (co)tangent bundles of Lie groups."""

from . import (
    compositions as compositions,
    diagnostics as diagnostics,
    groups as groups,
    scenes as scenes,
    tableaus as tableaus,
)
from .bundles import (
    AbstractBundle as AbstractBundle,
    BundleElement as BundleElement,
    Cartesian as Cartesian,
    Cotangent as Cotangent,
    DirectProduct as DirectProduct,
    Semidirect as Semidirect,
)
from .composed import (
    Adjoint as Adjoint,
    Composition as Composition,
    Symmetrized as Symmetrized,
    symmetry_defect as symmetry_defect,
)
from .compositions import (
    CompositionCoefficients as CompositionCoefficients,
    kahan_li_6 as kahan_li_6,
    kahan_li_8 as kahan_li_8,
    mclachlan_8 as mclachlan_8,
    suzuki_5 as suzuki_5,
    suzuki_fractal as suzuki_fractal,
    triple_jump as triple_jump,
    yoshida_triple_jump as yoshida_triple_jump,
)
from .coordinates import AbstractCoordinates as AbstractCoordinates, Cayley as Cayley, Exp as Exp
from .groups import SO3 as SO3, SOn as SOn, VectorSpace as VectorSpace, hat as hat, vee as vee
from .method import AbstractMethod as AbstractMethod
from .integrate import (
    Continuation as Continuation,
    Trajectory as Trajectory,
    integrate as integrate,
    resume as resume,
)
from .series import dexp_inv_series as dexp_inv_series, dexp_series as dexp_series
from .step import PRKMK as PRKMK, RESULTS as RESULTS
from .tableaus import (
    PartitionedTableau as PartitionedTableau,
    lobatto_iiia_iiib4 as lobatto_iiia_iiib4,
    lobatto_iiia_iiib6 as lobatto_iiia_iiib6,
    stormer_verlet as stormer_verlet,
    stormer_verlet_adjoint as stormer_verlet_adjoint,
    symplectic_euler as symplectic_euler,
    symplectic_euler_adjoint as symplectic_euler_adjoint,
)
from .interpolation import OnGroupInterpolation as OnGroupInterpolation
from .solver import PRKMKSolver as PRKMKSolver, PRKMKTerm as PRKMKTerm
from .batch import batch_sharding as batch_sharding, shard_batch as shard_batch

__version__ = "0.1.0"
