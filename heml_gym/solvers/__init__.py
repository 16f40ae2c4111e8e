"""Solvers over a :class:`~heml_gym.model.Model`: each steps all N worlds at once.

``solver.step(state_in, state_out, control, dt)`` returns :class:`StepStats` (per world:
iterations, residual against tolerance, converged, diverged, constraint reactions).

* :class:`ExplicitSolver`: symplectic Euler, sub-stepped below the critical step;
* :class:`ImplicitSolver`: backward Euler, Newton with the analytic Hessian;
* :class:`QuasiNewtonSolver`: backward Euler (or BDF2), L-BFGS from a constant factorised Hessian;
* :class:`StaticSolver`: equilibrium (``solve(state, control)``).

:func:`make_solver` builds a time-stepping one from its name and settings (the one place
that knows which integrator goes with which field and scheme).
"""

from .base import WorldStepStats, SimulationDiverged, Solver, StepStats
from .explicit import ExplicitSolver
from .implicit import ImplicitSolver
from .quasi_newton import QuasiNewtonSolver
from .factory import INTEGRATORS, SCHEMES, SolverChoiceError, check_solver_choice, make_solver
from .statics import StaticSolver

__all__ = ["ExplicitSolver", "ImplicitSolver", "QuasiNewtonSolver", "StaticSolver", "StepStats", "WorldStepStats",
           "SimulationDiverged", "Solver", "INTEGRATORS", "SCHEMES", "SolverChoiceError", "check_solver_choice",
           "make_solver"]
