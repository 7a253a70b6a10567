from .base import AbstractLieGroup as AbstractLieGroup, AbstractQuadraticGroup as AbstractQuadraticGroup
from .so3 import SO3 as SO3, hat as hat, vee as vee
from .son import SOn as SOn
from .vector_space import VectorSpace as VectorSpace
