"""Coordinate maps of the bundle group: the shared interface (`base`) and one
module per map."""

from .base import AbstractCoordinates as AbstractCoordinates
from .base import Truncation as Truncation
from .base import dual_number_inverse_differential as dual_number_inverse_differential
from .cayley import Cayley as Cayley
from .cayley import paper_semidirect_dcayley_inv as paper_semidirect_dcayley_inv
from .exponential import Exp as Exp
