from .base import AbstractLieGroup as AbstractLieGroup
from .base import AbstractQuadraticGroup as AbstractQuadraticGroup
from .so3 import SO3 as SO3
from .so3 import hat as hat
from .so3 import vee as vee
from .son import SOn as SOn
from .trig import sincos as sincos
from .vector_space import VectorSpace as VectorSpace
