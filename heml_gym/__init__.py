"""heml-gym: fast HEML (Hyper-Elastic Mass-Links) soft-tissue physics.

The physics backend depends only on numpy, numba, scipy and meshio (gmsh for the
procedural organs). Units are SI throughout: metres, seconds, pascals, kilograms.

The pieces, after NVIDIA Newton's split: a :class:`Model` (mesh, rest data, masses,
fixed vertices, per-world materials, supports; built once for N worlds), a
:class:`State` (positions and velocities), a :class:`Control` (held vertices, their
targets, external forces) and a solver (:class:`ExplicitSolver`,
:class:`ImplicitSolver`, :class:`StaticSolver`) that steps every world:
``solver.step(state_in, state_out, control, dt)``. :class:`Simulation` is the
single-world facade over them.
"""

from pathlib import Path as _Path

from .numba_cache import stamp_with_package_sources, tolerate_stale_indexes

tolerate_stale_indexes()  # before any kernel is compiled or loaded (see heml_gym.numba_cache)
stamp_with_package_sources(_Path(__file__).parent)  # a changed callee recompiles its callers

from . import kinematics, materials, organs  # noqa: E402
from .contact import MeshSupport, PlaneSupport
from .control import Control
from .forces import (FemForce, ForceField, HemlForce, MassSpringForce, MassTensorForce, QuadraticFemForce,
                     QuadraticTetMesh)
from .mesh import TetMesh, box_mesh, load_mesh, save_mesh
from .model import FORCE_FIELDS, Damping, Model
from .simulation import NotConverged, NotConvergedWarning, Simulation
from .solvers import ExplicitSolver, ImplicitSolver, QuasiNewtonSolver, SimulationDiverged, StaticSolver, StepStats
from .state import State
from .tools import Box, Capsule

__version__ = "0.1.0"

__all__ = [
    "Model",
    "State",
    "Control",
    "ExplicitSolver",
    "ImplicitSolver",
    "QuasiNewtonSolver",
    "StaticSolver",
    "StepStats",
    "Simulation",
    "SimulationDiverged",
    "NotConverged",
    "NotConvergedWarning",
    "Damping",
    "PlaneSupport",
    "MeshSupport",
    "Capsule",
    "Box",
    "FORCE_FIELDS",
    "TetMesh",
    "QuadraticTetMesh",
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
    "QuadraticFemForce",
]
