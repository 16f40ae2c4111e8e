"""Static equilibrium of N worlds: Newton on the potential energy, with load stepping."""

from __future__ import annotations

import math

import numpy as np

from ..control import Control
from ..linear_solvers import DiagonalAdd, DiagonalBlockAdd, FreeSubmatrix
from ..model import Model
from ..state import State
from .base import Solver, StepStats, checked_tool_stiffness
from .newton import minimize

__all__ = ["StaticSolver"]


class StaticSolver(Solver):
    """Equilibrium ``f_elastic(x) + f_ext + M g = 0`` on the free vertices of every world
    (hold springs pull their vertices towards their targets; rigid tools, posed by the
    control, push with the implicit solvers' penalty: :mod:`heml_gym.tools`).

    Parameters
    ----------
    model : Model
        Its fields need a Hessian; supports are not handled (a ``ValueError`` says so).
    load_steps : int
        Loads are ramped in this many equal increments, each solved to convergence.
    tol : float
        Each increment is solved to a force residual below ``tol`` times the world's
        load (weight plus external forces, N). The residual cannot go below round-off:
        HEML's edge springs carry forces of order ``E L^2`` that cancel at equilibrium,
        so the floor is about ``1e-16 E L^2`` per vertex (``L`` the edge length); for a
        stiff, light body that can exceed ``1e-10`` of its weight.
    max_iter : int
        Newton iterations per increment at most.
    tool_stiffness : float
        Penalty stiffness of rigid tools, in units of the tissue's own stiffness at each
        vertex (:meth:`~heml_gym.solvers.base.Solver.tool_penalty_stiffness`), as the
        implicit solvers'.
    """

    takes_hold_springs = True
    takes_tools = True

    def __init__(self, model: Model, load_steps: int = 1, tol: float = 1e-8, max_iter: int = 100,
                 tool_stiffness: float = 100.0):
        super().__init__(model)
        self.tool_stiffness = checked_tool_stiffness(tool_stiffness)
        for f in model.fields:
            if not f.has_hessian:
                raise ValueError(f"{type(f).__name__} has no Hessian: statics needs one")
        if len(model.supports):
            raise ValueError("the static solver does not handle supports yet: step the model to rest "
                             "with the implicit solver instead")
        if isinstance(load_steps, bool) or not isinstance(load_steps, (int, np.integer)) or load_steps < 1:
            raise ValueError(f"load_steps must be an integer >= 1, got {load_steps!r}")
        tol = float(tol)
        if not (math.isfinite(tol) and tol > 0):
            raise ValueError(f"tol must be a positive number, got {tol}")
        self.load_steps, self.tol, self.max_iter = int(load_steps), tol, int(max_iter)
        self._submatrix = [FreeSubmatrix() for _ in range(model.n_worlds)]
        self._add_diagonal = DiagonalAdd()
        self._add_blocks = DiagonalBlockAdd()

    def solve(self, state: State, control: Control, active=None) -> StepStats:
        """Move the free vertices of the ``active`` worlds (default: all) of ``state`` to
        equilibrium, in place, with held vertices on their targets; velocities become 0.
        ``StepStats.reaction`` holds the forces (N) the constraints then exert.
        A world whose last increment does not converge is flagged ``converged = False``
        (``residual`` and ``tolerance`` say by how much); a non-finite one ``diverged``
        (its state is kept)."""
        _, active = self._check(state, state, control, 1.0, active)
        m = self.model
        stats = StepStats.empty(m.n_worlds, m.n_vertices, self.load_steps)
        if len(m.tools):
            stats.tool_force = np.zeros((m.n_worlds, len(m.tools), 3))
        for s in np.flatnonzero(active):
            field = m.fields[s]
            kin = control.exactly_held()[s]
            x = state.x[s].copy()
            x[kin] = control.targets[s][kin]
            free_v = ~(m.fixed | kin)
            # hold springs (N/m) pull their vertices towards their targets
            k_hold = control.spring_stiffness(m.fixed)[s]
            k3, anchor = np.repeat(k_hold, 3), control.targets[s].reshape(-1)
            free = np.repeat(free_v, 3)
            k_tool = self.tool_penalty_stiffness()[s] if len(m.tools) else None  # N/m per vertex
            cached = [None, None]  # (y, the tools' penalty there): potential, gradient and Hessian ask at one y

            def tools(y):
                if k_tool is None:
                    return None
                if cached[0] is None or not np.array_equal(cached[0], y):
                    cached[:] = [np.array(y, copy=True), m.tools.penalty(y.reshape(-1, 3), control.tool_pose[s],
                                                                       k_tool, free_v)]
                return cached[1]

            scale = self.force_scale(s, control)
            tol = self.tol * scale
            stats.tolerance[s] = tol
            result = None
            with np.errstate(all="ignore"):
                for k in range(1, self.load_steps + 1):
                    load = (k / self.load_steps) * (control.external_forces[s] + m.mass[:, None] * m.gravity).reshape(-1)

                    def potential(y, load=load):
                        e = y.reshape(-1) - anchor
                        phi = field.energy(y) - float(load @ y.reshape(-1)) + 0.5 * float(k3 @ (e * e))
                        return phi + (tools(y).energy if k_tool is not None else 0.0)

                    def gradient(y, load=load):
                        g = -field.forces(y).reshape(-1) - load + k3 * (y.reshape(-1) - anchor)
                        return g + tools(y).gradient.reshape(-1) if k_tool is not None else g

                    def hessian(y, project):
                        h = field.hessian(y, project=project)
                        h = self._add_diagonal(h, k3) if k_hold.any() else h
                        pen = tools(y)
                        if pen is not None and len(pen.touching):
                            h = self._add_blocks(h, pen.touching, pen.blocks)
                        return h

                    result = minimize(x, potential, gradient, hessian, free, tol, self.max_iter, self._submatrix[s])
                    x = result.x
                    stats.newton_iterations[s] += result.iterations
            stats.residual[s] = result.residual
            if not (result.finite and np.all(np.isfinite(x))):
                stats.diverged[s] = True
                stats.converged[s] = False
                stats.messages[s] = "static solve went non-finite"
                continue
            stats.converged[s] = result.converged
            if not result.converged:
                stats.messages[s] = (f"static solve did not converge: residual {result.residual:.3e} N after "
                                     f"{self.max_iter} iterations (target {tol:.3e} N); try more load_steps")
            state.x[s] = x
            state.v[s] = 0.0
            if k_tool is not None:  # each tool's push on the tissue at equilibrium
                stats.tool_force[s] = tools(x).force
            f = field.forces(x) + control.external_forces[s] + m.mass[:, None] * m.gravity
            stats.reaction[s] = np.where(free_v[:, None], 0.0, -f)
            pulled = k_hold > 0
            stats.reaction[s, pulled] = k_hold[pulled, None] * (control.targets[s, pulled] - x[pulled])
            control.anchors[s, pulled] = control.targets[s, pulled]
        return stats

