"""Simulation: the friendly single-world facade over model, state, control and solvers.

Equation of motion (SI units: m, s, kg, N)::

    M x'' = f_elastic(x) + f_ext + M g - alpha M x' - beta K(x) x'

with the lumped mass ``M = rho V / 4`` per vertex per incident tet, Rayleigh damping
``alpha`` (1/s, mass-proportional) and ``beta`` (s, stiffness-proportional), fixed
(Dirichlet) vertices that never move, kinematic vertices whose positions are driven
(that is how a gripper holds tissue) and rigid supports. A :class:`Simulation` is one
world of a :class:`~heml_gym.model.Model` (N = 1) stepped by one of the solvers of
:mod:`heml_gym.solvers`:

* ``"explicit"``: symplectic Euler, sub-stepped automatically below ``safety *
  critical_dt()``;
* ``"implicit"``: backward Euler, Newton on the incremental potential with the analytic
  Hessian (projected per element to be positive semi-definite), a sparse solve and a
  backtracking line search.

A step whose state goes non-finite or explodes raises :class:`SimulationDiverged` and
leaves the state as it was before the step. An implicit step whose Newton solve stops
above its tolerance warns (:class:`NotConvergedWarning`) and says so in
``last.converged``; ``strict=True`` makes it raise :class:`NotConverged` instead.
"""

from __future__ import annotations

import warnings

import numpy as np

from .contact import Support
from .forces.base import ForceField
from .model import Damping, Model
from .solvers import INTEGRATORS, WorldStepStats, SimulationDiverged, StaticSolver, make_solver

__all__ = ["Simulation", "SimulationDiverged", "Damping", "WorldStepStats", "NotConverged", "NotConvergedWarning"]



class NotConverged(RuntimeError):
    """An implicit step's Newton solve stopped above its tolerance (``strict=True``)."""


class NotConvergedWarning(RuntimeWarning):
    """An implicit step's Newton solve stopped above its tolerance."""


class Simulation:
    """Time integration of one tet mesh under a force field.

    Parameters
    ----------
    field : ForceField
        Elastic forces (e.g. ``HemlForce(mesh, material)``).
    density : float
        Mass density in kg/m^3.
    gravity : (3,) float
        Gravitational acceleration in m/s^2.
    fixed : array of int or bool mask, optional
        Vertices that never move.
    damping : Damping, float or None
        Rayleigh damping; a float is taken as ``Damping(alpha=value)``.
    integrator : {"implicit", "explicit", "quasi_newton"}
    safety : float
        Explicit sub-steps are at most ``safety * critical_dt()`` seconds (see
        :class:`~heml_gym.solvers.ExplicitSolver`).
    refinements : sequence of int
        A step that goes bad (explicit) or fails to converge or start (implicit,
        quasi-Newton) is taken again with this many times more or shorter sub-steps, in
        turn, before it is reported (``()``: never).
    newton_tol, max_newton, linear_solver
        Implicit steps: the force tolerance relative to the load, the iterations per step
        at most (Newton's, default 20; L-BFGS's with ``"quasi_newton"``, default 50) and
        Newton's linear solver; the settings of :func:`heml_gym.solvers.make_solver`.
    max_speed : float
        A state with a vertex faster than this (m/s) counts as exploded.
    supports : sequence of PlaneSupport / MeshSupport
        Rigid bodies the tissue rests on (:mod:`heml_gym.contact`).
    strict : bool
        Raise :class:`NotConverged` (state kept) instead of warning when an implicit
        step does not converge.

    The pieces are public: ``model`` (:class:`~heml_gym.model.Model`, one world),
    ``state`` (:class:`~heml_gym.state.State`), ``control``
    (:class:`~heml_gym.control.Control`) and ``solver``.
    """

    def __init__(self, field: ForceField, density: float, gravity=(0.0, 0.0, -9.81), fixed=None,
                 damping: Damping | float | None = None, integrator: str = "implicit", safety: float = 0.5,
                 newton_tol: float = 1e-3, max_newton: int | None = None, max_speed: float = 1e3,
                 linear_solver: str = "pcg", supports=(), strict: bool = False, refinements=(4, 16)):
        if not isinstance(field, ForceField):
            raise TypeError(f"field must be a heml_gym ForceField, got {type(field).__name__}")
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {sorted(INTEGRATORS)}, got {integrator!r}")
        if isinstance(supports, Support):
            supports = (supports,)
        self.model = Model(field=field, density=density, fixed=fixed, gravity=gravity, damping=damping,
                           supports=supports)
        if integrator == "implicit" and not field.has_hessian:
            raise ValueError(f"{type(field).__name__} has no Hessian: use integrator='explicit'")
        self.solver = make_solver(self.model, integrator, safety=safety, newton_tol=newton_tol,
                                  max_iterations=max_newton, max_speed=max_speed, linear_solver=linear_solver,
                                  refinements=refinements)
        self.integrator = integrator
        self.safety = float(safety)
        self.strict = bool(strict)
        self.state = self.model.state()
        self.control = self.model.control()
        self.time = 0.0
        self.step_count = 0
        self.last = WorldStepStats()
        self._reaction = np.zeros((self.model.n_vertices, 3))

    # --------------------------------------------------------------- the pieces
    field = property(lambda self: self.model.field)
    mesh = property(lambda self: self.model.mesh)
    density = property(lambda self: self.model.density)
    gravity = property(lambda self: self.model.gravity)
    damping = property(lambda self: self.model.damping)
    mass = property(lambda self: self.model.mass, doc="Lumped mass per vertex (kg).")
    fixed = property(lambda self: self.model.fixed, doc="Mask of the vertices that never move.")
    kinematic = property(lambda self: self.control.kinematic[0], doc="Mask of the held vertices.")
    external_forces = property(lambda self: self.control.external_forces[0],
                               doc="External forces (N) applied every step, ``(n, 3)``, settable in place.")

    newton_tol = property(lambda self: getattr(self.solver, "newton_tol", None))
    max_newton = property(lambda self: getattr(self.solver, "max_newton", None))
    max_speed = property(lambda self: self.solver.max_speed)
    linear_solver = property(lambda self: getattr(self.solver, "linear_solver", None))

    @property
    def x(self) -> np.ndarray:
        """Positions (m), ``(n, 3)`` (a view of the state)."""
        return self.state.x[0]

    @x.setter
    def x(self, value):
        self.state.x[0] = value

    @property
    def v(self) -> np.ndarray:
        """Velocities (m/s), ``(n, 3)`` (a view of the state)."""
        return self.state.v[0]

    @v.setter
    def v(self, value):
        self.state.v[0] = value

    @property
    def free(self) -> np.ndarray:
        """Mask of the vertices the integrator moves (neither fixed nor kinematic)."""
        return ~(self.fixed | self.kinematic)

    # ---------------------------------------------------------------- state
    def reset(self, x=None, v=None) -> None:
        """Back to rest (or to the given positions / velocities), time 0, nothing attached."""
        n = self.mesh.n_vertices
        x = np.array(self.mesh.vertices if x is None else x, dtype=np.float64)
        v = np.zeros((n, 3)) if v is None else np.array(v, dtype=np.float64)
        if x.shape != (n, 3) or v.shape != (n, 3):
            raise ValueError(f"positions and velocities must have shape ({n}, 3)")
        self.state.x[0], self.state.v[0] = x, v
        self.control.clear(0)
        self._reaction[:] = 0.0
        self.time = 0.0
        self.step_count = 0

    # -------------------------------------------------------- grasped vertices
    def attach(self, vertices, targets=None) -> None:
        """Make ``vertices`` kinematic: from now on they follow :meth:`drive` exactly.

        ``targets`` (m, shape ``(k, 3)``) are their positions at the end of the next step;
        by default they stay where they are.
        """
        idx = self.control.indices(vertices)
        if np.any(self.fixed[idx]):
            raise ValueError("cannot attach fixed vertices")
        self.control.attach(0, idx, self.x)
        if targets is not None:
            self.drive(idx, targets)

    def drive(self, vertices, targets) -> None:
        """Set where kinematic ``vertices`` are at the end of the next step (m).

        They move along a straight line, at constant speed, during the step.
        """
        self.control.drive(0, vertices, targets)

    def detach(self, vertices=None) -> None:
        """Release kinematic vertices (all when ``vertices`` is None); they keep their velocity."""
        self.control.detach(0, vertices)

    def reaction_forces(self, vertices=None) -> np.ndarray:
        """Force (N) that the constraints exerted on fixed and kinematic vertices in the last
        step, averaged over its sub-steps (the impulse over the step divided by its length).

        For a vertex held at rest this balances the elastic force, gravity and external
        forces on it; summed over a gripper's vertices it is the grasp force on the tissue
        (with the opposite sign: the force the tissue pulls the gripper with is ``-R``).
        """
        if vertices is None:
            return self._reaction.copy()
        return self._reaction[np.asarray(vertices, dtype=np.int64)].copy()

    # ------------------------------------------------------------- stepping
    def critical_dt(self, method: str = "eigen") -> float:
        """Explicit stability limit in seconds (undamped, lumped mass, at rest).

        ``method="eigen"`` (default): ``2 / omega_max`` from a Lanczos iteration, exact at
        rest, cached (:meth:`heml_gym.Model.critical_dt`). ``method="estimate"``:
        ``h_min / c`` with ``h_min`` the smallest tet altitude and ``c`` the small-strain
        P-wave speed; quick, but off by a mesh-dependent factor (0.88 to 1.75 measured).
        """
        if method == "estimate":
            return self.model.estimated_critical_dt(0)
        if method != "eigen":
            raise ValueError(f"method must be 'eigen' or 'estimate', got {method!r}")
        return self.model.critical_dt(0)

    def step(self, dt: float, substeps: int | None = None) -> WorldStepStats:
        """Advance by ``dt`` seconds (in ``substeps`` equal sub-steps; explicit picks enough).

        Raises :class:`SimulationDiverged` (state unchanged) if the result is non-finite
        or exploding; warns :class:`NotConvergedWarning` (or raises :class:`NotConverged`
        with ``strict=True``, state unchanged) if an implicit solve did not converge.
        """
        dt = float(dt)
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        if substeps is not None and (isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1):
            raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
        if self.integrator == "explicit":
            stats = self.solver.step(self.state, self.state, self.control, dt, substeps=substeps)
        else:
            if self.strict:
                before = self.state.copy()
            stats = self.solver.step(self.state, self.state, self.control, dt, substeps=substeps or 1)
        report = stats.world(0)
        self.last = report
        if report.diverged:
            raise SimulationDiverged(self.step_count, report.message, stats.elements[0])
        if not report.converged:
            if self.strict:
                self.state.assign(before)
                raise NotConverged(f"step {self.step_count}: {report.message}")
            warnings.warn(f"step {self.step_count}: {report.message}", NotConvergedWarning, stacklevel=2)
        self._reaction = stats.reaction[0].copy()
        self.time += dt
        self.step_count += 1
        return report

    def solve_static(self, load_steps: int = 1, tol: float = 1e-8, max_iter: int = 100) -> WorldStepStats:
        """Static equilibrium under gravity and external forces, by Newton with load stepping
        (:class:`~heml_gym.solvers.StaticSolver`). Velocities are zeroed.

        Raises ``RuntimeError`` if the last increment does not converge.
        """
        stats = StaticSolver(self.model, load_steps=load_steps, tol=tol, max_iter=max_iter).solve(
            self.state, self.control)
        report = stats.world(0)
        self.last = report
        if report.diverged:
            raise SimulationDiverged(self.step_count, report.message)
        if not report.converged:
            raise RuntimeError(report.message)
        self._reaction = stats.reaction[0].copy()
        return report

    # ------------------------------------------------------------- energies
    def kinetic_energy(self) -> float:
        """Kinetic energy in joules."""
        return 0.5 * float((self.mass[:, None] * self.v * self.v).sum())

    def potential_energy(self) -> float:
        """Elastic plus gravitational potential energy in joules (gravity relative to x = 0)."""
        grav = -float((self.mass[:, None] * self.gravity * self.x).sum())
        ext = -float((self.external_forces * self.x).sum())
        return self.field.energy(self.x) + grav + ext

    def total_energy(self) -> float:
        """Kinetic plus potential energy in joules."""
        return self.kinetic_energy() + self.potential_energy()

