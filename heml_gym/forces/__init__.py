"""Force fields over a tet mesh: HEML and the baselines it is judged against."""

from .base import ForceField
from .fem import FemForce
from .heml import HemlForce

__all__ = ["ForceField", "HemlForce", "FemForce"]
