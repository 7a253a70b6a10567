"""Partitioned Runge–Kutta–Munthe-Kaas integrators on (co)tangent bundles of Lie groups."""

from . import (
    compositions as compositions,
)
from . import (
    diagnostics as diagnostics,
)
from . import (
    exact_flows as exact_flows,
)
from . import (
    groups as groups,
)
from . import (
    scenes as scenes,
)
from . import (
    stage_plan as stage_plan,
)
from . import (
    tableaus as tableaus,
)
from .batch import batch_sharding as batch_sharding
from .batch import gather as gather
from .batch import local_rows as local_rows
from .batch import shard_batch as shard_batch
from .batch import vmap_over_devices as vmap_over_devices
from .bundles import (
    AbstractBundle as AbstractBundle,
)
from .bundles import (
    BundleElement as BundleElement,
)
from .bundles import (
    Cartesian as Cartesian,
)
from .bundles import (
    Cotangent as Cotangent,
)
from .bundles import (
    DirectProduct as DirectProduct,
)
from .bundles import (
    Semidirect as Semidirect,
)
from .compositions import (
    CompositionCoefficients as CompositionCoefficients,
)
from .compositions import (
    kahan_li_6 as kahan_li_6,
)
from .compositions import (
    kahan_li_8 as kahan_li_8,
)
from .compositions import (
    mclachlan_8 as mclachlan_8,
)
from .compositions import (
    suzuki_5 as suzuki_5,
)
from .compositions import (
    suzuki_fractal as suzuki_fractal,
)
from .compositions import (
    triple_jump as triple_jump,
)
from .compositions import (
    yoshida_triple_jump as yoshida_triple_jump,
)
from .coordinates import AbstractCoordinates as AbstractCoordinates
from .coordinates import Cayley as Cayley
from .coordinates import Exp as Exp
from .groups import SO3 as SO3
from .groups import SOn as SOn
from .groups import VectorSpace as VectorSpace
from .groups import hat as hat
from .groups import vee as vee
from .integrate import (
    Continuation as Continuation,
)
from .integrate import (
    Trajectory as Trajectory,
)
from .integrate import (
    integrate as integrate,
)
from .integrate import (
    resume as resume,
)
from .interpolation import OnGroupInterpolation as OnGroupInterpolation
from .made_of_steps import (
    Adjoint as Adjoint,
)
from .made_of_steps import (
    Composition as Composition,
)
from .made_of_steps import (
    Symmetrized as Symmetrized,
)
from .made_of_steps import (
    symmetry_defect as symmetry_defect,
)
from .method import RESULTS as RESULTS
from .method import AbstractMethod as AbstractMethod
from .method import Step as Step
from .method import compensated as compensated
from .reversible import ReversibleAdjoint as ReversibleAdjoint
from .reversible import ReversibleGradient as ReversibleGradient
from .reversible import undoing_method as undoing_method
from .series import dexp_inv_series as dexp_inv_series
from .series import dexp_series as dexp_series
from .solver import PRKMKSolver as PRKMKSolver
from .solver import PRKMKTerm as PRKMKTerm
from .splitting import Splitting as Splitting
from .step import PRKMK as PRKMK
from .tableaus import (
    PartitionedTableau as PartitionedTableau,
)
from .tableaus import (
    classical_rk4 as classical_rk4,
)
from .tableaus import (
    dormand_prince_8 as dormand_prince_8,
)
from .tableaus import (
    lobatto_iiia_iiib4 as lobatto_iiia_iiib4,
)
from .tableaus import (
    lobatto_iiia_iiib6 as lobatto_iiia_iiib6,
)
from .tableaus import (
    stormer_verlet as stormer_verlet,
)
from .tableaus import (
    stormer_verlet_adjoint as stormer_verlet_adjoint,
)
from .tableaus import (
    symplectic_euler as symplectic_euler,
)
from .tableaus import (
    symplectic_euler_adjoint as symplectic_euler_adjoint,
)

__version__ = "0.1.0"
