"""Partitioned Runge–Kutta–Munthe-Kaas integrators on (co)tangent bundles of Lie groups.

The public face, floor by floor (docs: *Architecture*): groups, bundles,
coordinates and tableaus; methods; scenes; gradients; drivers.
"""

from . import compositions as compositions
from . import diagnostics as diagnostics
from . import elliptic as elliptic
from . import exact_flows as exact_flows
from . import groups as groups
from . import methods as methods
from . import scenes as scenes
from . import tableaus as tableaus
from ._batch import batch_sharding as batch_sharding
from ._batch import gather as gather
from ._batch import local_rows as local_rows
from ._batch import shard_batch as shard_batch
from ._batch import vmap_over_devices as vmap_over_devices
from ._bundles import AbstractBundle as AbstractBundle
from ._bundles import BundleElement as BundleElement
from ._bundles import Cartesian as Cartesian
from ._bundles import Cotangent as Cotangent
from ._bundles import DirectProduct as DirectProduct
from ._bundles import Semidirect as Semidirect
from ._gradients import AbstractGradient as AbstractGradient
from ._gradients import ReversibleGradient as ReversibleGradient
from ._gradients import StoredSteps as StoredSteps
from ._integrate import Continuation as Continuation
from ._integrate import Trajectory as Trajectory
from ._integrate import integrate as integrate
from ._integrate import resume as resume
from ._interpolation import OnGroupInterpolation as OnGroupInterpolation
from ._reversible_adjoint import ReversibleAdjoint as ReversibleAdjoint
from ._series import dexp_inv_series as dexp_inv_series
from ._series import dexp_series as dexp_series
from ._solver import PRKMKSolver as PRKMKSolver
from ._solver import PRKMKTerm as PRKMKTerm
from .compositions import CompositionCoefficients as CompositionCoefficients
from .compositions import kahan_li_6 as kahan_li_6
from .compositions import kahan_li_8 as kahan_li_8
from .compositions import mclachlan_8 as mclachlan_8
from .compositions import suzuki_5 as suzuki_5
from .compositions import suzuki_fractal as suzuki_fractal
from .compositions import triple_jump as triple_jump
from .compositions import yoshida_triple_jump as yoshida_triple_jump
from .coordinates import AbstractCoordinates as AbstractCoordinates
from .coordinates import Cayley as Cayley
from .coordinates import Exp as Exp
from .groups import SE3 as SE3
from .groups import SO3 as SO3
from .groups import SO3xR3 as SO3xR3
from .groups import SOn as SOn
from .groups import UnitQuaternion as UnitQuaternion
from .groups import VectorSpace as VectorSpace
from .groups import hat as hat
from .groups import vee as vee
from .methods import PRKMK as PRKMK
from .methods import RESULTS as RESULTS
from .methods import AbstractMethod as AbstractMethod
from .methods import Adjoint as Adjoint
from .methods import Composition as Composition
from .methods import ExactFlow as ExactFlow
from .methods import Splitting as Splitting
from .methods import Step as Step
from .methods import Symmetrized as Symmetrized
from .methods import compensated as compensated
from .methods import stage_plan as stage_plan
from .methods import symmetry_defect as symmetry_defect
from .tableaus import PartitionedTableau as PartitionedTableau
from .tableaus import classical_rk4 as classical_rk4
from .tableaus import dormand_prince_8 as dormand_prince_8
from .tableaus import lobatto_iiia_iiib4 as lobatto_iiia_iiib4
from .tableaus import lobatto_iiia_iiib6 as lobatto_iiia_iiib6
from .tableaus import stormer_verlet as stormer_verlet
from .tableaus import stormer_verlet_adjoint as stormer_verlet_adjoint
from .tableaus import symplectic_euler as symplectic_euler
from .tableaus import symplectic_euler_adjoint as symplectic_euler_adjoint

__version__ = "0.1.0"
