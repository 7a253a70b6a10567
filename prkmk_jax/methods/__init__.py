"""One-step methods on a bundle group, all behind `AbstractMethod`: PRKMK
(Algorithm 4.2), exact-flow splittings, and the methods made of other
methods' steps (adjoint, symmetrised, composition)."""

from . import stage_plan as stage_plan
from .adjoint import AbstractMadeOfSteps as AbstractMadeOfSteps
from .adjoint import Adjoint as Adjoint
from .base import RESULTS as RESULTS
from .base import AbstractMethod as AbstractMethod
from .base import Step as Step
from .base import compensated as compensated
from .composition import Composition as Composition
from .exact import ExactFlow as ExactFlow
from .prkmk import PRKMK as PRKMK
from .splitting import Splitting as Splitting
from .stage_solve import StageSolve as StageSolve
from .symmetrized import Symmetrized as Symmetrized
from .symmetrized import symmetry_defect as symmetry_defect
