"""Force fields over a tet mesh: HEML, the baselines it is judged against, and quadratic tets."""

from .base import ForceField
from .fem import FemForce
from .heml import HemlForce
from .mass_tensor import MassTensorForce
from .mass_spring import MassSpringForce
from .quadratic import QuadraticFemForce, QuadraticTetMesh

__all__ = ["ForceField", "HemlForce", "FemForce", "MassSpringForce", "MassTensorForce", "QuadraticFemForce",
           "QuadraticTetMesh"]
