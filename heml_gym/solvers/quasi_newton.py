"""Backward Euler by quasi-Newton (L-BFGS) with a constant, factorised initial Hessian.

After Liu, Bouaziz and Kavan (2017), "Quasi-Newton methods for real-time simulation of
hyperelastic materials": each step minimises backward Euler's incremental potential
(the same as :class:`~heml_gym.solvers.ImplicitSolver`'s, supports included) by L-BFGS,
whose initial Hessian is the constant matrix ``c M + K(X)`` (``c = 1/h^2 + alpha/h``; the
stiffness at rest of a reference material), factorised once per mesh and step length by
the envelope Cholesky of :mod:`heml_gym.linear_solvers` and shared by every scene. No
Hessian is assembled, and nothing is refactorised when a grasp starts or ends (held
vertices are a projection) or when a scene draws another stiffness (L-BFGS's history
corrects the initial guess). For HEML this is natural: Neo-Hookean's ``I1`` stiffness is
the constant spring Laplacian, and the rest stiffness is exact for small strain.

All iterations of all scenes run in one compiled call, scenes over threads. Each scene
reports its iterations, residual against its tolerance and whether it converged. Units:
m, s, kg, N.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import scipy.sparse as sp

from ..control import Control
from ..forces.heml import HemlForce
from ..linear_solvers import EnvelopeCholesky, FreeSubmatrix, NotPositiveDefinite
from ..materials import Material
from ..model import Model
from ..state import State
from . import kernels_quasi_newton as kq
from .base import Solver, StepStats
from .explicit import _stack_params

__all__ = ["QuasiNewtonSolver"]


class QuasiNewtonSolver(Solver):
    """Backward Euler for every scene of ``model`` by L-BFGS (HEML force fields).

    Parameters
    ----------
    model : Model
        Every scene's field must be a :class:`~heml_gym.HemlForce` (any law).
    newton_tol : float
        A step stops when the force residual on the free vertices is below ``newton_tol``
        times the scene's load (weight plus external forces), as for the Newton solver.
    max_iter : int
        L-BFGS iterations per step at most; a step that stops above its tolerance is
        reported (``StepStats.converged``), never silently.
    history : int
        L-BFGS memory (pairs of past steps and gradient changes).
    reference : Material or None
        The material of the constant Hessian (default: scene 0's at the first step).
    contact_stiffness : float
        Penalty stiffness of the supports, in units of a vertex's inertia ``c m_i``.
    max_speed : float, m/s
        A vertex faster than this counts as exploded.
    """

    def __init__(self, model: Model, newton_tol: float = 1e-3, max_iter: int = 50, history: int = 8,
                 reference: Material | None = None, contact_stiffness: float = 100.0, max_speed: float = 1e3):
        super().__init__(model, max_speed)
        for f in model.fields:
            if not isinstance(f, HemlForce):
                raise ValueError(f"the quasi-Newton solver needs HEML force fields, got {type(f).__name__}: "
                                 "use the implicit (Newton) solver")
        newton_tol = float(newton_tol)
        if not (math.isfinite(newton_tol) and newton_tol > 0):
            raise ValueError(f"newton_tol must be a positive number, got {newton_tol}")
        for name, value in (("max_iter", max_iter), ("history", history)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        contact_stiffness = float(contact_stiffness)
        if not (math.isfinite(contact_stiffness) and contact_stiffness > 0):
            raise ValueError(f"contact_stiffness must be a positive number, got {contact_stiffness}")
        if reference is not None and not isinstance(reference, Material):
            raise TypeError(f"reference must be a heml_gym.materials.Material, got {type(reference).__name__}")
        self.newton_tol = newton_tol
        self.max_iter = int(max_iter)
        self.history = int(history)
        self.contact_stiffness = contact_stiffness
        self.reference = reference
        free = ~model.fixed
        index = -np.ones((model.n_vertices, 3), dtype=np.int64)
        index[free] = np.arange(3 * int(free.sum())).reshape(-1, 3)
        self._dof_index = index
        self._factors: dict[float, EnvelopeCholesky] = {}
        self.factorizations = 0

    def factor(self, h: float) -> EnvelopeCholesky:
        """The envelope Cholesky factor of ``c M + K(X)`` on the non-fixed degrees of
        freedom for step length ``h`` (s), computed once and cached."""
        key = float(h)
        if key not in self._factors:
            m = self.model
            material = self.reference if self.reference is not None else m.materials[0]
            field = m.fields[0].with_material(material)
            c = 1.0 / h ** 2 + m.damping.alpha / h
            a = field.hessian(m.mesh.vertices, project=True).tocsr() + sp.diags(c * np.repeat(m.mass, 3))
            sub = FreeSubmatrix()(a.tocsr(), np.repeat(~m.fixed, 3))
            try:
                self._factors[key] = EnvelopeCholesky(sub)
            except NotPositiveDefinite as exc:  # pragma: no cover - c M alone is positive definite
                raise ValueError(f"the constant Hessian is not positive definite: {exc}") from None
            self.factorizations += 1
        return self._factors[key]

    def step(self, state_in: State, state_out: State, control: Control, dt: float,
             substeps: int = 1, active=None) -> StepStats:
        """Advance the ``active`` scenes (default: all) by ``dt`` s in ``substeps`` equal
        backward Euler steps. A scene that goes non-finite, explodes or cannot start is
        flagged ``diverged`` (its state kept); one whose solve stops above tolerance
        ``converged = False``."""
        dt, active = self._check(state_in, state_out, control, dt, active)
        substeps = int(substeps)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        m = self.model
        N = m.n_scenes
        stats = StepStats.empty(N, m.n_vertices, substeps)
        stats.residual[:] = 0.0
        h = dt / substeps
        factor = self.factor(h)
        fields = m.fields
        rest = fields[0].rest
        split = all(f.split for f in fields)
        use_q = any(f.use_q for f in fields)
        weights = (np.stack([f.spring_weights for f in fields]) if split
                   else np.zeros((N, 6, 1)))
        laws = np.array([f.law_id for f in fields], dtype=np.int64)
        params = _stack_params(fields)
        held = control.kinematic | m.fixed[None, :]
        tol = np.array([self.newton_tol * self.force_scale(s, control) for s in range(N)])
        stats.tolerance[:] = tol
        planes, grids, values = m.supports.kernel_args()
        x0, v0 = state_out.x.copy(), state_out.v.copy()
        x, v = state_out.x, state_out.v
        out = np.zeros((N, 4))
        kernel = kq.lbfgs_steps_parallel if N > 1 and numba.get_num_threads() > 1 else kq.lbfgs_steps_serial
        feasible = np.ones(N, dtype=bool)
        with np.errstate(all="ignore"):
            for k in range(1, substeps + 1):
                targets = x0 + (control.targets - x0) * (k / substeps)
                v_start = v.copy()
                kin = control.kinematic & active[:, None]
                x[kin] = targets[kin]  # held vertices at their end positions; fixed ones stay
                kernel(x, v, m.mass, m.gravity, control.external_forces, m.damping.alpha, h, held, rest.tets,
                       rest.coef_t, rest.q_t if use_q else fields[0].q_t, use_q, laws, params, split, weights,
                       rest.inv_det, planes, grids, values, self.contact_stiffness * (1.0 / h ** 2 + m.damping.alpha / h),
                       self._dof_index, *factor.kernel_args(), tol,
                       self.max_iter, self.history, active, out)
                stats.newton_iterations += out[:, 0].astype(np.int64) * active
                stats.residual = np.maximum(stats.residual, np.where(active, out[:, 1], 0.0))
                stats.converged &= ~active | (out[:, 2] > 0.5)
                feasible &= ~active | (out[:, 3] > 0.5)
                # constraint forces on held vertices: m a minus every other force on them
                f_el = np.zeros_like(x)
                for s in np.flatnonzero(active & feasible):
                    fields[s].forces(x[s], out=f_el[s])
                total = (f_el + control.external_forces + m.mass[None, :, None] * m.gravity
                         - m.damping.alpha * m.mass[None, :, None] * v)
                sub_reaction = m.mass[None, :, None] * (v - v_start) / h - total
                stats.reaction += np.where(held[:, :, None] & active[:, None, None], sub_reaction, 0.0) / substeps
        for s in np.flatnonzero(active):
            reason, elements = self.divergence(x[s], v[s])
            if not feasible[s]:
                reason = "no feasible start: the held vertices invert elements within one step"
            if reason:
                x[s], v[s] = x0[s], v0[s]
                stats.diverged[s] = True
                stats.converged[s] = False
                stats.reaction[s] = 0.0
                stats.messages[s] = reason
                stats.elements[s] = elements
            elif not stats.converged[s]:
                stats.messages[s] = (f"L-BFGS stopped at a force residual of {stats.residual[s]:.3g} N, above its "
                                     f"tolerance of {tol[s]:.3g} N, after {stats.newton_iterations[s]} iterations")
        return stats
