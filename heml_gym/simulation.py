"""Dynamics over any force field: lumped masses, gravity, damping, fixed and grasped vertices.

Equation of motion (SI units: m, s, kg, N)::

    M x'' = f_elastic(x) + f_ext + M g - alpha M x' - beta K(x) x'

with the lumped mass ``M = rho V / 4`` per vertex per incident tet, Rayleigh damping
``alpha`` (1/s, mass-proportional) and ``beta`` (s, stiffness-proportional), fixed
(Dirichlet) vertices that never move and kinematic vertices whose positions are driven
(that is how a gripper holds tissue). Integrators:

* ``"explicit"``: symplectic Euler, sub-stepped automatically below ``safety *
  critical_dt()``;
* ``"implicit"``: backward Euler, Newton on the incremental potential with the analytic
  Hessian (projected per element to be positive semi-definite), a sparse direct solve and
  a backtracking line search.

A step whose state goes non-finite or explodes raises :class:`SimulationDiverged` and
leaves the state as it was before the step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import kernels_dynamics
from .linear_solvers import DiagonalAdd, FreeSubmatrix, LaggedFactorPCG
from .forces.base import ForceField
from .forces.heml import HemlForce

__all__ = ["Simulation", "SimulationDiverged", "Damping", "StepStats"]


class SimulationDiverged(RuntimeError):
    """A step produced a non-finite or exploding state; the previous state was kept.

    Attributes: ``step`` (index of the failed step), ``elements`` (tets with a non-finite
    or inverted state, at most 20), ``reason`` (text).
    """

    def __init__(self, step: int, reason: str, elements=()):
        self.step = int(step)
        self.reason = reason
        self.elements = np.asarray(elements, dtype=np.int64)[:20]
        where = f"; elements {self.elements.tolist()}" if self.elements.size else ""
        super().__init__(f"simulation diverged at step {self.step}: {reason}{where}")


@dataclass(frozen=True)
class Damping:
    """Rayleigh damping ``C = alpha M + beta K``.

    ``alpha`` (1/s) damps every motion, rigid motion included (like drag in a fluid);
    ``beta`` (s) damps deformation rates only, more at high frequencies.
    """

    alpha: float = 0.0
    beta: float = 0.0

    def __post_init__(self):
        for name in ("alpha", "beta"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"Damping.{name} must be finite and >= 0, got {v}")


@dataclass
class StepStats:
    """What the last :meth:`Simulation.step` did."""

    substeps: int = 0
    newton_iterations: int = 0
    residual: float = 0.0


class Simulation:
    """Time integration of a tet mesh under a force field.

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
    integrator : {"implicit", "explicit"}
    safety : float
        Explicit sub-steps are at most ``safety * critical_dt()`` seconds. The critical
        step is that of the rest state; large deformations stiffen most laws (a 15 %
        squeeze of a Neo-Hookean cube diverged at 0.9), hence the default of 0.5.
    newton_tol : float
        Implicit: Newton stops when the force residual on the free vertices is below
        ``newton_tol`` times the total load (weight plus external forces; in zero gravity
        and without load, ``E h_min^2``). The default 1e-3 (0.1 % of the weight) moved
        a 1/30 s trajectory of the LapGym-size slab by 0.02 mm from a 1e-9 solve, against
        a 125 mm sag and 69 mm of time-discretisation error (1/30 vs 1/240 s steps)
        (``benchmarks/simulation_speed.py``).
    max_newton : int
        Implicit: Newton iterations per step at most.
    max_speed : float
        A state with a vertex faster than this (m/s) counts as exploded.
    linear_solver : {"pcg", "direct"}
        Implicit steps: ``"pcg"`` solves each Newton system by conjugate gradients
        preconditioned with a sparse Cholesky factorisation kept from an earlier system
        (:class:`heml_gym.linear_solvers.EnvelopeCholesky`; refreshed when CG needs more
        than 8 iterations or the free vertices change; CG stops at a relative residual of
        1e-2, an inexact Newton step); ``"direct"`` factorises every system (SuperLU).
        :meth:`solve_static` always uses ``"direct"``.
    """

    def __init__(
        self,
        field: ForceField,
        density: float,
        gravity=(0.0, 0.0, -9.81),
        fixed=None,
        damping: Damping | float | None = None,
        integrator: str = "implicit",
        safety: float = 0.5,
        newton_tol: float = 1e-3,
        max_newton: int = 20,
        max_speed: float = 1e3,
        linear_solver: str = "pcg",
    ):
        if not isinstance(field, ForceField):
            raise TypeError(f"field must be a heml_gym ForceField, got {type(field).__name__}")
        density = float(density)
        if not math.isfinite(density) or density <= 0:
            raise ValueError(f"density must be a positive number of kg/m^3, got {density}")
        if integrator not in ("implicit", "explicit"):
            raise ValueError(f"integrator must be 'implicit' or 'explicit', got {integrator!r}")
        if integrator == "implicit" and not hasattr(field, "hessian"):
            raise ValueError(f"{type(field).__name__} has no Hessian: use integrator='explicit'")
        gravity = np.asarray(gravity, dtype=np.float64)
        if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
            raise ValueError(f"gravity must be three finite numbers (m/s^2), got {gravity}")
        if damping is None:
            damping = Damping()
        elif not isinstance(damping, Damping):
            damping = Damping(alpha=float(damping))
        if not 0 < safety <= 1:
            raise ValueError(f"safety must lie in (0, 1], got {safety}")
        if linear_solver not in ("pcg", "direct"):
            raise ValueError(f"linear_solver must be 'pcg' or 'direct', got {linear_solver!r}")

        self.field = field
        self.mesh = field.mesh
        self.density = density
        self.gravity = gravity
        self.damping = damping
        self.integrator = integrator
        self.safety = float(safety)
        self.newton_tol = float(newton_tol)
        self.max_newton = int(max_newton)
        self.max_speed = float(max_speed)
        self.linear_solver = linear_solver
        self._pcg = LaggedFactorPCG(rtol=1e-2, max_iter=8, factorization="cholesky")
        self._submatrix = FreeSubmatrix()
        self._add_diagonal = DiagonalAdd()

        n = self.mesh.n_vertices
        self.mass = density * self.mesh.vertex_volumes  # kg per vertex
        self.fixed = self._vertex_mask(fixed, "fixed")
        self.kinematic = np.zeros(n, dtype=bool)
        self._targets = np.zeros((n, 3))
        self.external_forces = np.zeros((n, 3))  # N, user-set, applied every step
        self.time = 0.0
        self.step_count = 0
        self.last = StepStats()
        self._reaction = np.zeros((n, 3))
        self._critical_dt = None
        self.reset()

    # ---------------------------------------------------------------- state
    def reset(self, x=None, v=None) -> None:
        """Back to rest (or to the given positions / velocities), time 0, nothing attached."""
        n = self.mesh.n_vertices
        self.x = np.array(self.mesh.vertices if x is None else x, dtype=np.float64)
        self.v = np.zeros((n, 3)) if v is None else np.array(v, dtype=np.float64)
        if self.x.shape != (n, 3) or self.v.shape != (n, 3):
            raise ValueError(f"positions and velocities must have shape ({n}, 3)")
        self.kinematic[:] = False
        self.external_forces[:] = 0.0
        self._reaction[:] = 0.0
        self.time = 0.0
        self.step_count = 0

    def _vertex_mask(self, vertices, what: str) -> np.ndarray:
        n = self.mesh.n_vertices
        mask = np.zeros(n, dtype=bool)
        if vertices is None:
            return mask
        arr = np.asarray(vertices)
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise ValueError(f"{what} mask must have shape ({n},), got {arr.shape}")
            return arr.copy()
        arr = arr.astype(np.int64).ravel()
        if arr.size and (arr.min() < 0 or arr.max() >= n):
            raise ValueError(f"{what} vertex indices must lie in [0, {n})")
        mask[arr] = True
        return mask

    @property
    def free(self) -> np.ndarray:
        """Mask of the vertices the integrator moves (neither fixed nor kinematic)."""
        return ~(self.fixed | self.kinematic)

    # -------------------------------------------------------- grasped vertices
    def attach(self, vertices, targets=None) -> None:
        """Make ``vertices`` kinematic: from now on they follow :meth:`drive` exactly.

        ``targets`` (m, shape ``(k, 3)``) are their positions at the end of the next step;
        by default they stay where they are.
        """
        idx = np.flatnonzero(self._vertex_mask(vertices, "attached"))
        if np.any(self.fixed[idx]):
            raise ValueError("cannot attach fixed vertices")
        self.kinematic[idx] = True
        self._targets[idx] = self.x[idx]
        if targets is not None:
            self.drive(idx, targets)

    def drive(self, vertices, targets) -> None:
        """Set where kinematic ``vertices`` are at the end of the next step (m).

        They move along a straight line, at constant speed, during the step.
        """
        idx = np.asarray(vertices, dtype=np.int64).ravel()
        targets = np.asarray(targets, dtype=np.float64).reshape(len(idx), 3)
        if not np.all(self.kinematic[idx]):
            raise ValueError("drive() needs attached (kinematic) vertices: call attach() first")
        if not np.all(np.isfinite(targets)):
            raise ValueError("kinematic targets must be finite")
        self._targets[idx] = targets

    def detach(self, vertices=None) -> None:
        """Release kinematic vertices (all when ``vertices`` is None); they keep their velocity."""
        if vertices is None:
            self.kinematic[:] = False
        else:
            self.kinematic[self._vertex_mask(vertices, "detached")] = False

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

        ``method="estimate"``: ``h_min / c`` with ``h_min`` the smallest tet altitude and
        ``c = sqrt((lam + 2 mu) / rho)`` the small-strain P-wave speed. Quick, but off by a
        mesh-dependent factor (measured 0.88 to 1.75 on our meshes).
        ``method="eigen"`` (default): ``2 / omega_max``, with ``omega_max^2`` the largest
        eigenvalue of ``M^-1 K`` at rest found by Lanczos iteration on force differences;
        exact for the rest state, computed once and cached. Stiffening under large strain
        lowers the limit, which is what the explicit integrator's ``safety`` factor is for.
        """
        if method == "estimate":
            return self.mesh.min_height / self.field.material.wave_speed(self.density)
        if method != "eigen":
            raise ValueError(f"method must be 'eigen' or 'estimate', got {method!r}")
        if self._critical_dt is None:
            self._critical_dt = 2.0 / math.sqrt(self._max_eigenvalue_rest())
        return self._critical_dt

    def _max_eigenvalue_rest(self) -> float:
        """Largest eigenvalue (1/s^2) of ``M^-1/2 K M^-1/2`` at the rest shape."""
        x0 = np.array(self.mesh.vertices)
        n = self.mesh.n_vertices
        inv_sqrt_m = 1.0 / np.sqrt(np.repeat(self.mass, 3))
        h = 1e-6 * self.mesh.min_edge_length

        def matvec(y):
            d = (inv_sqrt_m * np.ravel(y)).reshape(n, 3)
            kd = (self.field.forces(x0 - h * d) - self.field.forces(x0 + h * d)) / (2.0 * h)
            return inv_sqrt_m * kd.ravel()

        op = spla.LinearOperator((3 * n, 3 * n), matvec=matvec, dtype=np.float64)
        v0 = np.random.default_rng(0).standard_normal(3 * n)
        lam = spla.eigsh(op, k=1, which="LA", tol=1e-4, v0=v0, return_eigenvectors=False)[0]
        return float(lam)

    def _total_forces(self, x, v) -> np.ndarray:
        """Elastic + external + gravity + damping forces (N) at state ``(x, v)``."""
        f_el = self.field.forces(x)
        f = f_el + self.external_forces + self.mass[:, None] * self.gravity
        if self.damping.alpha:
            f -= self.damping.alpha * self.mass[:, None] * v
        if self.damping.beta:
            # -beta K v, as a directional difference of the elastic forces along v
            vmax = np.abs(v).max()
            if vmax > 0:
                eps = 1e-7 * self.mesh.min_edge_length / vmax
                f += self.damping.beta * (self.field.forces(x + eps * v) - f_el) / eps
        return f

    def step(self, dt: float, substeps: int | None = None) -> StepStats:
        """Advance by ``dt`` seconds (in ``substeps`` equal sub-steps; explicit picks enough).

        Raises :class:`SimulationDiverged` (state unchanged) if the result is non-finite
        or exploding.
        """
        dt = float(dt)
        if not math.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        if substeps is None:
            substeps = 1
            if self.integrator == "explicit":
                substeps = max(1, math.ceil(dt / (self.safety * self.critical_dt())))
        substeps = int(substeps)
        if substeps < 1:
            raise ValueError("substeps must be >= 1")
        x0, v0 = self.x.copy(), self.v.copy()
        start_targets = x0.copy()
        h = dt / substeps
        stats = StepStats(substeps=substeps)
        reaction = np.zeros_like(self.x)
        try:
            with np.errstate(all="ignore"):
                if self.integrator == "explicit" and not self.damping.beta:
                    reaction = self._explicit_substeps_fast(h, substeps, start_targets)
                else:
                    for k in range(1, substeps + 1):
                        targets = start_targets + (self._targets - start_targets) * (k / substeps)
                        if self.integrator == "explicit":
                            sub_reaction = self._explicit_substep(h, targets)
                        else:
                            sub_reaction, it, res = self._implicit_substep(h, targets)
                            stats.newton_iterations += it
                            stats.residual = max(stats.residual, res)
                        reaction += sub_reaction / substeps
                        self._check()
        except SimulationDiverged:
            self.x, self.v = x0, v0
            raise
        self._reaction = reaction
        self.time += dt
        self.step_count += 1
        self.last = stats
        return stats

    def _constrain(self, x, v, targets, h, x_prev):
        """Hold fixed vertices where they are and put kinematic ones on their path."""
        kin = self.kinematic
        x[self.fixed] = x_prev[self.fixed]
        v[self.fixed] = 0.0
        x[kin] = targets[kin]
        v[kin] = (targets[kin] - x_prev[kin]) / h

    def _held_reaction(self, v_prev, total, h) -> np.ndarray:
        """Constraint force (N) on held vertices: ``m a`` minus every other force on them."""
        held = ~self.free
        reaction = np.zeros_like(self.x)
        reaction[held] = self.mass[held, None] * (self.v[held] - v_prev[held]) / h - total[held]
        return reaction

    def _explicit_substeps_fast(self, h, substeps, start_targets):
        """``substeps`` symplectic Euler sub-steps: one force kernel and one update kernel each."""
        n = self.mesh.n_vertices
        f = np.zeros((n, 3))
        reaction = np.zeros((n, 3))  # the mean over the sub-steps
        sub_reaction = np.zeros((n, 3))
        field = self.field
        if isinstance(field, HemlForce) and field.split and field._threads() == 1:
            # Neo-Hookean HEML: every sub-step inside one compiled call
            done, bad = kernels_dynamics.explicit_substeps_constant_psi1(
                self.x, self.v, f, reaction, sub_reaction, self.mass, self.gravity,
                self.external_forces, self.damping.alpha, h, substeps, self.fixed, self.kinematic,
                start_targets, self._targets, self.max_speed, *field._split_args())
            if bad >= 0:
                self._check()
                raise SimulationDiverged(self.step_count, f"vertex {bad} went non-finite or too fast")
            return reaction
        for k in range(1, substeps + 1):
            self.field.forces(self.x, out=f)
            bad = kernels_dynamics.symplectic_euler_update(
                self.x, self.v, f, self.mass, self.gravity, self.external_forces,
                self.damping.alpha, h, self.fixed, self.kinematic, start_targets, self._targets,
                k / substeps, self.max_speed, sub_reaction)
            if bad >= 0:
                self._check()  # names the reason and the elements
                raise SimulationDiverged(self.step_count, f"vertex {bad} went non-finite or too fast")
            reaction += sub_reaction / substeps
        return reaction

    def _explicit_substep(self, h, targets):
        x_prev, v_prev = self.x.copy(), self.v.copy()
        total = self._total_forces(self.x, self.v)
        self.v = self.v + h * total / self.mass[:, None]
        self.x = self.x + h * self.v
        self._constrain(self.x, self.v, targets, h, x_prev)
        return self._held_reaction(v_prev, total, h)

    def _force_scale(self) -> float:
        """Force (N) the Newton tolerances are relative to: total weight plus external load."""
        load = float(np.linalg.norm(self.gravity) * self.mass.sum() + np.abs(self.external_forces).sum())
        if load > 0:
            return load
        return self.field.material.young_modulus * self.mesh.min_edge_length**2

    def _newton(self, x, potential, gradient, hessian, free, tol, max_iter, pcg=None, pcg_key=None):
        """Minimise ``potential`` over the free dofs from ``x`` by Newton's method.

        Each iteration solves with the exact Hessian first and, if that gives no descent
        direction (the law is not convex there), with the per-element projected one,
        which is positive semi-definite; by ``pcg`` (a :class:`LaggedFactorPCG`) if given,
        else by a sparse direct solve. A backtracking line search accepts a step that
        satisfies the Armijo condition on the potential or, near convergence where the
        potential's round-off hides the decrease, that reduces the residual; steps to
        non-finite energies (inverted elements of ln J laws) are halved. Returns
        ``(x, iterations, residual norm in N)``.
        """
        g = gradient(x)
        gnorm = float(np.linalg.norm(g[free]))
        it = 0
        stalled = 0
        phi_x = None
        while gnorm > tol and it < max_iter and stalled < 5:
            it += 1
            gf = g[free]
            for project in (False, True):
                a = self._submatrix(hessian(x, project), free)
                if pcg is not None:
                    dx = pcg.solve(a, -gf, key=(pcg_key, project))
                else:
                    dx = spla.spsolve(a.tocsc(), -gf, permc_spec="MMD_AT_PLUS_A")  # symmetric: 2x faster
                slope = float(gf @ dx)
                ok = bool(np.all(np.isfinite(dx)) and slope < 0)
                if ok:
                    break
            if not ok:  # no Newton direction: steepest descent, scaled by the diagonal
                dx = -gf / float(np.abs(a.diagonal()).max())
                slope = float(gf @ dx)
            phi0 = potential(x) if phi_x is None else phi_x
            step = 1.0
            trial = x.copy()
            for _ in range(40):
                trial.reshape(-1)[free] = x.reshape(-1)[free] + step * dx
                phi = potential(trial)
                if np.isfinite(phi):
                    if phi <= phi0 + 1e-4 * step * slope:
                        g_trial = gradient(trial)
                        break
                    g_trial = gradient(trial)
                    if np.linalg.norm(g_trial[free]) < (1.0 - 1e-4 * step) * gnorm:
                        break
                step *= 0.5
            else:
                break  # no progress possible at this precision: keep the best iterate
            x = trial
            g = g_trial
            phi_x = phi  # the next iteration's phi0
            previous, gnorm = gnorm, float(np.linalg.norm(g[free]))
            # at the round-off floor the residual stops falling: stop after 5 such steps
            stalled = stalled + 1 if gnorm > 0.99 * previous else 0
        if not np.isfinite(gnorm):
            raise SimulationDiverged(self.step_count, "Newton iterate went non-finite")
        return x, it, gnorm

    def _feasible_start(self, x_n, v_n, h, targets, potential, hessian):
        """A Newton starting point with finite energy (no inverted ln J element).

        Tries the explicit predictor ``x_n + h v_n``, then the previous positions, then
        the previous positions plus the linear response of the free vertices to the
        kinematic vertices' motion (one solve with the step matrix at ``x_n``); all with
        fixed vertices held and kinematic ones on their targets. Raises
        :class:`SimulationDiverged` naming the inverted elements if none is feasible.
        """
        for x in (x_n + h * v_n, x_n.copy()):
            v = v_n.copy()
            self._constrain(x, v, targets, h, x_n)
            if np.isfinite(potential(x)):
                return x
        kin = np.repeat(self.kinematic, 3)
        free = np.repeat(self.free, 3)
        if kin.any():
            a = hessian(x_n, True).tocsr()
            d = (targets - x_n).reshape(-1)
            u = np.zeros_like(d)
            u[free] = spla.spsolve(a[free][:, free].tocsc(), -(a[free][:, kin] @ d[kin]))
            u[kin] = d[kin]
            x = x_n + u.reshape(x_n.shape)
            v = v_n.copy()
            self._constrain(x, v, targets, h, x_n)
            if np.isfinite(potential(x)):
                return x
        from .mesh import signed_volumes

        inverted = np.flatnonzero(signed_volumes(x, self.mesh.tets) <= 0)
        raise SimulationDiverged(self.step_count, "no feasible start: the driven vertices invert "
                                 "elements within one step", inverted)

    def _implicit_substep(self, h, targets):
        x_n, v_n = self.x.copy(), self.v.copy()
        m3 = np.repeat(self.mass, 3)
        alpha, beta = self.damping.alpha, self.damping.beta
        c = 1.0 / h**2 + alpha / h
        x_hat = (x_n + h * v_n / (1.0 + alpha * h)).reshape(-1)
        load = (self.external_forces + self.mass[:, None] * self.gravity).reshape(-1)
        # stiffness damping with K frozen at the start of the step keeps this a potential
        k_n = self.field.hessian(x_n) * (beta / h) if beta else None
        x0 = x_n.reshape(-1)
        diag = c * m3

        def potential(x):
            d = x.reshape(-1) - x_hat
            phi = 0.5 * c * float(m3 @ (d * d)) + self.field.energy(x) - float(load @ x.reshape(-1))
            if k_n is not None:
                dn = x.reshape(-1) - x0
                phi += 0.5 * float(dn @ (k_n @ dn))
            return phi

        def gradient(x):
            g = c * m3 * (x.reshape(-1) - x_hat) - self.field.forces(x).reshape(-1) - load
            if k_n is not None:
                g += k_n @ (x.reshape(-1) - x0)
            return g

        def hessian(x, project):
            a = self._add_diagonal(self.field.hessian(x, project=project), diag)
            return a + k_n if k_n is not None else a

        x = self._feasible_start(x_n, v_n, h, targets, potential, hessian)
        free = np.repeat(self.free, 3)
        tol = self.newton_tol * self._force_scale()
        pcg = self._pcg if self.linear_solver == "pcg" else None
        key = (free.tobytes(), h)
        x, it, res = self._newton(x, potential, gradient, hessian, free, tol, self.max_newton, pcg, key)
        self.x = x
        self.v = (x - x_n) / h
        self._constrain(self.x, self.v, targets, h, x_n)
        total = self._total_forces(self.x, self.v)
        return self._held_reaction(v_n, total, h), it, res

    def solve_static(self, load_steps: int = 1, tol: float = 1e-8, max_iter: int = 100) -> StepStats:
        """Static equilibrium under gravity and external forces, by Newton with load stepping.

        Loads are ramped in ``load_steps`` equal increments; each increment is solved to a
        force residual below ``tol`` times the total load (N). Velocities are zeroed.
        The residual cannot go below round-off: HEML's edge springs carry forces of order
        ``E L^2`` that cancel at equilibrium, so the floor is about ``1e-16 E L^2`` per
        vertex (``L`` the edge length); for a stiff, light body that can exceed
        ``1e-10`` of its weight.
        Raises ``RuntimeError`` if the last increment does not converge.
        """
        if self.kinematic.any():
            self._constrain(self.x, self.v, self._targets, 1.0, self.x.copy())
        free = np.repeat(self.free, 3)
        stats = StepStats(substeps=load_steps)
        x = self.x.copy()
        with np.errstate(all="ignore"):
            for k in range(1, load_steps + 1):
                load = (k / load_steps) * (self.external_forces + self.mass[:, None] * self.gravity).reshape(-1)

                def potential(y, load=load):
                    return self.field.energy(y) - float(load @ y.reshape(-1))

                def gradient(y, load=load):
                    return -self.field.forces(y).reshape(-1) - load

                def hessian(y, project):
                    return self.field.hessian(y, project=project)

                x, it, res = self._newton(x, potential, gradient, hessian, free,
                                          tol * self._force_scale(), max_iter)
                stats.newton_iterations += it
                stats.residual = res
        if not np.all(np.isfinite(x)):
            raise SimulationDiverged(self.step_count, "static solve went non-finite")
        self.x = x
        self.v[:] = 0.0
        self.last = stats
        if res > tol * self._force_scale():
            raise RuntimeError(
                f"static solve did not converge: residual {res:.3e} N after {max_iter} iterations "
                f"(target {tol * self._force_scale():.3e} N); try more load_steps"
            )
        f = self.field.forces(self.x) + self.external_forces + self.mass[:, None] * self.gravity
        self._reaction = np.where(self.free[:, None], 0.0, -f)
        return stats

    def _check(self):
        x, v = self.x, self.v
        bad_vertices = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        speed = np.sqrt((v * v).sum(axis=1))
        if bad_vertices.any() or speed.max(initial=0.0) > self.max_speed:
            bad = bad_vertices | (speed > self.max_speed)
            tets = np.flatnonzero(bad[self.mesh.tets].any(axis=1))
            what = "non-finite positions or velocities" if bad_vertices.any() else (
                f"speed {speed.max():.3g} m/s above max_speed {self.max_speed:g} m/s")
            raise SimulationDiverged(self.step_count, what, tets)

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
