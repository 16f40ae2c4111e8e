"""Force fields over a tet mesh: HEML and the baselines it is judged against."""

from .base import ForceField
from .fem import FemForce
from .heml import HemlForce
from .mass_tensor import MassTensorForce
from .mass_spring import MassSpringForce

__all__ = ["ForceField", "HemlForce", "FemForce", "MassSpringForce", "MassTensorForce"]
