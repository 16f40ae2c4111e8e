"""heml-gym: fast HEML (Hyper-Elastic Mass-Links) soft-tissue physics.

The physics backend depends only on numpy, numba, scipy and meshio (gmsh for the
procedural organs). Units are SI throughout: metres, seconds, pascals, kilograms.
"""

from . import kinematics, materials, organs
from .forces import FemForce, ForceField, HemlForce, MassSpringForce, MassTensorForce
from .mesh import TetMesh, box_mesh, load_mesh, save_mesh
from .simulation import Damping, Simulation, SimulationDiverged

__version__ = "0.1.0"

__all__ = [
    "Simulation",
    "SimulationDiverged",
    "Damping",
    "TetMesh",
    "box_mesh",
    "load_mesh",
    "save_mesh",
    "materials",
    "organs",
    "kinematics",
    "ForceField",
    "HemlForce",
    "FemForce",
    "MassTensorForce",
    "MassSpringForce",
]
