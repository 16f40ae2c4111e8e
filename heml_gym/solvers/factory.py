"""One place that builds a time-stepping solver from settings: the integrator registry,
the rules of which integrator goes with which force field and time scheme, and the
meaning of every setting. Used by :class:`heml_gym.Simulation`, the environments
(``physics=``) and their world validation.

    solver = make_solver(model, "quasi_newton", newton_tol=3e-3, max_iterations=100)
"""

from __future__ import annotations

from ..forces.heml import HemlForce
from ..model import FORCE_FIELDS, Model
from .base import Solver
from .explicit import ExplicitSolver
from .implicit import ImplicitSolver
from .quasi_newton import QuasiNewtonSolver

__all__ = ["INTEGRATORS", "SCHEMES", "SolverChoiceError", "check_solver_choice", "make_solver"]

#: Solvers of a time step by name.
INTEGRATORS = {"explicit": ExplicitSolver, "implicit": ImplicitSolver, "quasi_newton": QuasiNewtonSolver}
#: The implicit steps' time discretisations (``quasi_newton`` only: ``bdf2``).
SCHEMES = tuple(QuasiNewtonSolver.SCHEMES)


class SolverChoiceError(ValueError):
    """A setting that no solver accepts, or two that do not go together; ``argument``
    names the setting at fault."""

    def __init__(self, argument: str, message: str):
        super().__init__(f"{argument} {message}")
        self.argument = argument
        self.message = message


def check_solver_choice(integrator: str, field: str | None = None, scheme: str = "backward_euler") -> None:
    """Raise :class:`SolverChoiceError` unless ``integrator`` (a name of
    :data:`INTEGRATORS`), the force ``field`` (a name of ``heml_gym.FORCE_FIELDS``, or None:
    not known yet) and the time ``scheme`` go together: ``bdf2`` needs ``quasi_newton`` on
    HEML; ``implicit`` and ``quasi_newton`` need a field with a Hessian (all have one:
    mass-spring its own). ``quasi_newton`` steps HEML fields by
    :class:`~heml_gym.QuasiNewtonSolver`, any other by the Newton solver's L-BFGS method."""
    if integrator not in INTEGRATORS:
        raise SolverChoiceError("integrator", f"must be one of {sorted(INTEGRATORS)}, got {integrator!r}")
    if field is not None and field not in FORCE_FIELDS:
        raise SolverChoiceError("field", f"must be one of {sorted(FORCE_FIELDS)}, got {field!r}")
    if scheme not in SCHEMES:
        raise SolverChoiceError("scheme", f"must be one of {sorted(SCHEMES)}, got {scheme!r}")
    if scheme == "bdf2" and integrator != "quasi_newton":
        raise SolverChoiceError("scheme", f"'bdf2' needs integrator 'quasi_newton', got {integrator!r}")
    if scheme == "bdf2" and field not in (None, "heml"):
        raise SolverChoiceError("scheme", f"'bdf2' needs field 'heml', got {field!r}")


def make_solver(model: Model, integrator: str = "quasi_newton", *, scheme: str = "backward_euler",
                safety: float = 0.5, newton_tol: float = 1e-3, max_iterations: int | None = None,
                max_speed: float = 1e3, linear_solver: str = "pcg", refinements=(4, 16),
                hessian_scale: float = 1.0, tool_stiffness: float = 100.0) -> Solver:
    """The solver ``integrator`` for ``model``, every setting with one meaning:

    * ``safety``: explicit sub-steps are at most this fraction of the critical step;
    * ``newton_tol``: an implicit (sub-)step stops at a force residual below this
      times the world's load (weight plus external forces);
    * ``max_iterations``: iterations per implicit (sub-)step at most: Newton's
      (``implicit``, default 20) or L-BFGS's (``quasi_newton``, default 50 on HEML, 200 on
      other fields); a solve that stops above its tolerance is re-taken, then reported,
      never silent;
    * ``refinements``: a (sub-)step that fails is taken again in this many times more
      (explicit) or shorter (implicit, quasi-Newton) sub-steps, in turn;
    * ``scheme``: ``"backward_euler"`` or (``quasi_newton`` only) ``"bdf2"``;
    * ``linear_solver``: Newton's linear solves (``implicit``): ``"pcg"`` or ``"direct"``;
    * ``hessian_scale``: the weight of the quasi-Newton initial Hessian's Laplacian in
      units of ``lambda + mu`` (``quasi_newton`` only; speed, not accuracy, see
      :class:`~heml_gym.QuasiNewtonSolver`; on other fields, of the rest stiffness, see
      :class:`~heml_gym.ImplicitSolver`'s ``method="lbfgs"``);
    * ``tool_stiffness``: the rigid tools' contact penalty in units of the tissue's own
      stiffness at each vertex (``quasi_newton`` and ``implicit``; see
      :meth:`~heml_gym.solvers.base.Solver.tool_penalty_stiffness`);
    * ``max_speed`` (m/s): a vertex faster than this counts as exploded.

    Errors name the setting (:class:`SolverChoiceError`, or the solver's own ValueError
    for a field it cannot step, e.g. mass-spring with ``quasi_newton``).
    """
    check_solver_choice(integrator, scheme=scheme)
    if hessian_scale != 1.0 and integrator != "quasi_newton":
        raise SolverChoiceError("hessian_scale", f"applies to integrator 'quasi_newton' only, got {integrator!r}")
    if integrator == "explicit":
        return ExplicitSolver(model, safety=safety, max_speed=max_speed, refinements=refinements)
    other = next((f for f in model.fields if not isinstance(f, HemlForce)), None)
    if integrator == "quasi_newton" and other is not None:
        if scheme != "backward_euler":
            raise SolverChoiceError("scheme", f"{scheme!r} needs HEML force fields, got {type(other).__name__}")
        return ImplicitSolver(model, newton_tol=newton_tol, max_newton=200 if max_iterations is None else max_iterations,
                              method="lbfgs", hessian_scale=hessian_scale, max_speed=max_speed, refinements=refinements,
                              tool_stiffness=tool_stiffness)
    if integrator == "quasi_newton":
        return QuasiNewtonSolver(model, newton_tol=newton_tol, max_iter=50 if max_iterations is None else max_iterations,
                                 refinements=refinements, max_speed=max_speed, scheme=scheme,
                                 hessian_scale=hessian_scale, tool_stiffness=tool_stiffness)
    return ImplicitSolver(model, newton_tol=newton_tol, max_newton=20 if max_iterations is None else max_iterations,
                          linear_solver=linear_solver, max_speed=max_speed, refinements=refinements,
                          tool_stiffness=tool_stiffness)
