"""Implicit backward Euler over N worlds: Newton on the incremental potential.

Per (sub-)step of length ``h``, each world's free positions minimise

    Phi(x) = 1/2 c |x - x_hat|_M^2 + W(x) - f_ext . x - M g . x + Phi_contact(x)
             [+ beta/(2h) |x - x_n|_K(x_n)^2],   c = 1/h^2 + alpha/h,
    x_hat = x_n + h v_n / (1 + alpha h),

by Newton's method (:func:`heml_gym.solvers.newton.minimize`) with the field's analytic
Hessian, a sparse linear solve (:class:`~heml_gym.linear_solvers.LaggedFactorPCG` or
SuperLU) and a line search, or (``method="lbfgs"``) by L-BFGS
(:func:`heml_gym.solvers.newton.minimize_lbfgs`) from a scalar initial Hessian, axis by
axis ``c M + s K_0 + diag(k_hold, contact)``: ``K_0`` the field's stiffness at rest summed
over its three axis blocks (rest stiffness, so that it does not depend on how the tissue
has turned; for linear tets a multiple of the P1 Laplacian, as
:class:`~heml_gym.QuasiNewtonSolver`'s for HEML fields), ``s`` the ``hessian_scale``, the
support penalty's diagonal on the vertices in contact; then ``v = (x - x_n) / h``. Held vertices follow their
targets, fixed ones stay. A rigid support adds the penalty ``Phi_contact = sum_i k_i /2
min(d_i, 0)^2`` (``d_i`` the vertex's signed distance, ``k_i = contact_stiffness * c m_i``),
so that Newton sees the contact; the result is then projected onto the supports as in
the explicit solver. Worlds are solved one after the other, each with its own cached
factorisation. Units: m, s, kg, N.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from ..control import Control
from ..linear_solvers import DiagonalAdd, DiagonalBlockAdd, EnvelopeCholesky, FreeSubmatrix, LaggedFactorPCG
from ..mesh import signed_volumes
from ..model import Model
from ..state import State
from .base import Solver, StepStats, checked_tool_stiffness, stiffness_damping
from .newton import linear_response, minimize, minimize_lbfgs
from .quasi_newton import penalised_hessian

__all__ = ["ImplicitSolver"]


class _Diverged(Exception):
    def __init__(self, reason, elements=()):
        self.reason, self.elements = reason, np.asarray(elements, dtype=np.int64)


class ImplicitSolver(Solver):
    """Backward Euler with Newton for every world of ``model`` (hold springs included:
    ``1/2 k |x - anchor|^2`` in the potential, the anchor on the held path).

    Parameters
    ----------
    model : Model
        Its force fields need a Hessian (HEML, F-FEM and mass-tensor use HEML's;
        mass-spring has its own).
    newton_tol : float
        Newton stops when the force residual on the free vertices is below ``newton_tol``
        times the world's load (weight plus external forces; in zero gravity and without
        load, ``E h_min^2``). The default 1e-3 (0.1 % of the weight) moved a 1/30 s
        trajectory of the LapGym-size slab by 0.02 mm from a 1e-9 solve, against a 125 mm
        sag and 69 mm of time-discretisation error (``benchmarks/speed/simulation_speed.py``).
    max_newton : int
        Newton iterations per (sub-)step at most. A solve that stops above its tolerance
        is reported in ``StepStats.converged`` (and its residual and tolerance), never
        silently.
    linear_solver : {"pcg", "direct"}
        ``"pcg"``: conjugate gradients preconditioned with a sparse Cholesky factorisation
        kept from an earlier system (refreshed when CG needs more than 8 iterations or the
        free vertices change; CG stops at a relative residual of 1e-2, an inexact Newton
        step); ``"direct"``: SuperLU on every system.
    contact_stiffness : float
        Penalty stiffness of the supports, in units of a vertex's inertia ``c m_i``.
    tool_stiffness : float
        Penalty stiffness of rigid tools (:mod:`heml_gym.tools`), in units of the tissue's
        own at each vertex (as :class:`~heml_gym.solvers.QuasiNewtonSolver`'s).
    stall_limit : int or None
        Newton also stops after this many iterations in a row that cut the residual by
        less than 1 % (the round-off floor); None: only ``max_newton`` stops it.
    max_speed : float, m/s
        A vertex faster than this counts as exploded.
    refinements : sequence of int
        A sub-step that does not converge, goes non-finite or has no start (its held
        vertices invert elements within one step) is taken again in this many shorter
        steps, then the next number of them (``()``: never). Whether Newton finds a start
        can depend on the CPU's rounding: on the lobe with Demiray's law, one of 50 random
        steps had none when compiled for plain x86-64 (SSE2), and converged re-taken in 4.
    method : {"newton", "lbfgs"}
        How each sub-step's potential is minimised: Newton's method (the field's Hessian
        at every iteration) or L-BFGS (one factorisation of the scalar initial Hessian,
        kept while the held vertices, the step length, the hold springs and, to within
        ``contact_refresh`` vertices, the vertices in contact stay the same; see the
        module docstring). ``max_newton`` then counts L-BFGS iterations; Newton's
        ``linear_solver`` and ``stall_limit`` do not apply.
    history : int
        L-BFGS's memory: the pairs of past steps and gradient changes it keeps (within a
        sub-step).
    hessian_scale : float
        The weight ``s`` of the rest stiffness in L-BFGS's initial Hessian (speed, not
        accuracy: it changes the iterations a sub-step takes, not where it converges).
    contact_refresh : int
        L-BFGS's initial Hessian is factorised again when the vertices in contact differ
        from those it holds by more than this many.
    """

    takes_hold_springs = True
    takes_tools = True

    METHODS = ("newton", "lbfgs")

    def __init__(self, model: Model, newton_tol: float = 1e-3, max_newton: int = 20,
                 linear_solver: str = "pcg", contact_stiffness: float = 100.0, stall_limit: int | None = 5,
                 max_speed: float = 1e3, refinements=(4, 16), method: str = "newton", history: int = 8,
                 hessian_scale: float = 1.0, contact_refresh: int = 50, tool_stiffness: float = 100.0):
        super().__init__(model, max_speed)
        for f in model.fields:
            if not f.has_hessian:
                raise ValueError(f"{type(f).__name__} has no Hessian: use the explicit solver")
        newton_tol = float(newton_tol)
        if not (math.isfinite(newton_tol) and newton_tol > 0):
            raise ValueError(f"newton_tol must be a positive number, got {newton_tol}")
        if isinstance(max_newton, bool) or not isinstance(max_newton, (int, np.integer)) or max_newton < 1:
            raise ValueError(f"max_newton must be an integer >= 1, got {max_newton!r}")
        if linear_solver not in ("pcg", "direct"):
            raise ValueError(f"linear_solver must be 'pcg' or 'direct', got {linear_solver!r}")
        contact_stiffness = float(contact_stiffness)
        if not (math.isfinite(contact_stiffness) and contact_stiffness > 0):
            raise ValueError(f"contact_stiffness must be a positive number, got {contact_stiffness}")
        refinements = tuple(refinements)
        if not all(isinstance(r, (int, np.integer)) and not isinstance(r, bool) and r > 1 for r in refinements):
            raise ValueError(f"refinements must be integers > 1 (sub-steps to split a failed one into), "
                             f"got {refinements!r}")
        self.refinements = tuple(int(r) for r in refinements)
        if method not in self.METHODS:
            raise ValueError(f"method must be one of {list(self.METHODS)}, got {method!r}")
        for name, value, low in (("history", history, 1), ("contact_refresh", contact_refresh, 0)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        hessian_scale = float(hessian_scale)
        if not (math.isfinite(hessian_scale) and hessian_scale > 0):
            raise ValueError(f"hessian_scale must be a positive number, got {hessian_scale}")
        self.method = method
        self.history = int(history)
        self.hessian_scale = hessian_scale
        self.contact_refresh = int(contact_refresh)
        self.newton_tol = newton_tol
        self.max_newton = int(max_newton)
        self.linear_solver = linear_solver
        self.contact_stiffness = contact_stiffness
        self.tool_stiffness = checked_tool_stiffness(tool_stiffness)
        self.stall_limit = stall_limit
        n = model.n_worlds
        self.pcg = [LaggedFactorPCG(rtol=1e-2, max_iter=8, factorization="cholesky") for _ in range(n)]
        self._submatrix = [FreeSubmatrix() for _ in range(n)]
        self._add_diagonal = DiagonalAdd()
        self._add_blocks = DiagonalBlockAdd()
        self._rest_stiffness: list = [None] * n  # per world: (field, K_0 scalar CSR n x n, N/m)
        self._initial_hessian: list = [None] * n  # per world: (key, touching mask, factors per axis)

    def forget(self, worlds) -> None:
        """Drop the lagged factorisations of ``worlds`` (see :meth:`Solver.forget`)."""
        for s in np.atleast_1d(worlds):
            self.pcg[int(s)].reset()
            self._initial_hessian[int(s)] = None

    def _scalar_rest_stiffness(self, s, field):
        """World ``s``'s ``K_0`` (CSR, n x n, N/m): its field's stiffness at the rest
        positions, the three axis blocks summed (cached while the world keeps its field; a
        new field drops the world's initial Hessian, which holds the old one)."""
        cached = self._rest_stiffness[s]
        if cached is None or cached[0] is not field:
            k = field.hessian(field.mesh.vertices, project=True).tocsr()
            cached = (field, (k[0::3, 0::3] + k[1::3, 1::3] + k[2::3, 2::3]).tocsr())
            self._rest_stiffness[s] = cached
            self._initial_hessian[s] = None
        return cached[1]

    def _lbfgs_preconditioner(self, s, field, c, free_v, k_hold, touching, normal, k_contact):
        """``r -> A^-1 r`` on the free dofs, ``A`` axis by axis ``c M + s K_0 +
        diag(k_hold) + diag(k_contact n_a^2 on the touching vertices)`` (see the module
        docstring), its factors kept while nothing it holds changes (the vertices in
        contact: to within ``contact_refresh``)."""
        rest = self._scalar_rest_stiffness(s, field)
        key = (free_v.tobytes(), float(c), k_hold.tobytes())
        held = self._initial_hessian[s]
        if (held is None or held[0] != key
                or int(np.count_nonzero(held[1] != touching)) > self.contact_refresh):
            m = self.model
            free = np.flatnonzero(free_v)
            base = (self.hessian_scale * rest)[free][:, free].tocsr()
            diagonal = c * m.mass + k_hold
            penalty = np.zeros((3, m.n_vertices))
            if touching.any():
                penalty[:, touching] = (k_contact[touching, None] * normal[touching] ** 2).T
            factors, done = [], {}
            for a in range(3):
                d = (diagonal + penalty[a])[free]
                tag = d.tobytes()
                if tag not in done:
                    done[tag] = EnvelopeCholesky((base + sp.diags(d)).tocsr())
                factors.append(done[tag])
            held = (key, touching.copy(), factors)
            self._initial_hessian[s] = held
        factors = held[2]

        def precondition(r):
            r = r.reshape(-1, 3)
            z = np.empty_like(r)
            for a in range(3):
                z[:, a] = factors[a].solve(r[:, a])
            return z.reshape(-1)
        return precondition

    def step(self, state_in: State, state_out: State, control: Control, dt: float,
             substeps: int = 1, active=None) -> StepStats:
        """Advance the ``active`` worlds (default: all) by ``dt`` s in ``substeps`` equal
        backward Euler steps. A sub-step whose Newton solve stops above tolerance, goes
        non-finite or cannot start (its held vertices invert elements within one step) is
        taken again from its start in ``refinements[0]`` shorter steps, then
        ``refinements[1]``, ... (``StepStats.refinement``). A world that still goes
        non-finite, explodes or cannot start is flagged ``diverged`` and keeps its state;
        one whose Newton solve still stops above tolerance is flagged ``converged = False``
        (its state is the last iterate)."""
        dt, active = self._check(state_in, state_out, control, dt, active)
        substeps = int(substeps)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        m = self.model
        stats = StepStats.empty(m.n_worlds, m.n_vertices, substeps)
        stats.residual[:] = 0.0
        h = dt / substeps
        self._tool_force = np.zeros((m.n_worlds, len(m.tools), 3))  # the last sub-step's end force
        self._tool_sum = np.zeros((m.n_worlds, len(m.tools), 3))  # their mean over the step, times substeps
        for s in np.flatnonzero(active):
            x0, v0 = state_out.x[s].copy(), state_out.v[s].copy()
            tol = self.newton_tol * self.force_scale(s, control)
            stats.tolerance[s] = tol
            springs = control.spring_stiffness(m.fixed)[s] > 0.0
            origin = np.where(springs[:, None], control.anchors[s], x0)  # (a spring's anchor moves, not its vertex)
            try:
                with np.errstate(all="ignore"):
                    for k in range(1, substeps + 1):
                        # the held vertices' (and anchors') path over this sub-step (from the step's start)
                        path = (origin + (control.targets[s] - origin) * ((k - 1) / substeps),
                                origin + (control.targets[s] - origin) * (k / substeps))
                        converged = self._retaken_substep(s, state_out, control, h, path, tol, stats)
                        if not converged:
                            stats.converged[s] = False
            except _Diverged as exc:
                state_out.x[s], state_out.v[s] = x0, v0
                stats.diverged[s] = True
                stats.converged[s] = False
                stats.reaction[s] = 0.0
                stats.messages[s] = exc.reason
                stats.elements[s] = exc.elements
                continue
            stats.reaction[s] /= substeps
            control.anchors[s, springs] = control.targets[s, springs]
            if not stats.converged[s]:
                stats.messages[s] = (f"Newton stopped at a force residual of {stats.residual[s]:.3g} N, above its "
                                     f"tolerance of {tol:.3g} N, after {stats.newton_iterations[s]} iterations "
                                     f"(sub-steps refined {stats.refinement[s]}x)")
        if len(m.tools):
            stats.tool_force = np.where((active & ~stats.diverged)[:, None, None], self._tool_sum / substeps, 0.0)
        return stats

    def _retaken_substep(self, s, state, control, h, path, tol, stats) -> bool:
        """One sub-step of world ``s`` (the held vertices from ``path[0]`` to ``path[1]``),
        taken again in ``refinements`` shorter steps while it fails; its step-mean reaction
        added into ``stats.reaction[s]``. True when it converged; raises :class:`_Diverged`
        when even the last re-take diverged or found no start."""
        x_start, v_start = state.x[s].copy(), state.v[s].copy()
        residual_before = stats.residual[s]
        for attempt, factor in enumerate((1, *self.refinements)):
            last = attempt == len(self.refinements)
            state.x[s], state.v[s] = x_start, v_start
            stats.residual[s] = residual_before
            reaction = np.zeros_like(x_start)
            tool_force = np.zeros((len(self.model.tools), 3))
            converged = True
            try:
                for j in range(1, factor + 1):
                    targets = path[0] + (path[1] - path[0]) * (j / factor)
                    r, result = self._substep(s, state, control, h / factor, targets, tol)
                    stats.newton_iterations[s] += result.iterations
                    stats.residual[s] = max(stats.residual[s], result.residual)
                    converged &= result.converged
                    reaction += r / factor
                    tool_force += self._tool_force[s] / factor
                    reason, elements = self.divergence(state.x[s], state.v[s])
                    if reason:
                        raise _Diverged(reason, elements)
                    if not (converged or last):
                        break
            except _Diverged:
                if last:
                    raise
                continue
            stats.refinement[s] = max(stats.refinement[s], factor)
            if converged or last:
                stats.reaction[s] += reaction
                self._tool_sum[s] += tool_force
                return converged
        return False  # (not reached: the last attempt returns or raises)

    # ----------------------------------------------------------------- helpers
    def _constrain(self, s, x, v, control, targets, h, x_prev):
        """Hold fixed vertices where they are and put exactly held ones on their path."""
        fixed, kin = self.model.fixed, control.exactly_held()[s]
        x[fixed] = x_prev[fixed]
        v[fixed] = 0.0
        x[kin] = targets[kin]
        v[kin] = (targets[kin] - x_prev[kin]) / h

    def _substep(self, s, state, control, h, targets, tol):
        m = self.model
        field = m.fields[s]
        x_n, v_n = state.x[s].copy(), state.v[s].copy()
        m3 = np.repeat(m.mass, 3)
        alpha, beta = m.damping.alpha, m.damping.beta
        c = 1.0 / h ** 2 + alpha / h
        x_hat = (x_n + h * v_n / (1.0 + alpha * h)).reshape(-1)
        load = (control.external_forces[s] + m.mass[:, None] * m.gravity).reshape(-1)
        k_n = field.hessian(x_n) * (beta / h) if beta else None  # frozen: keeps this a potential
        x0 = x_n.reshape(-1)
        free_v = ~(m.fixed | control.exactly_held()[s])
        # hold springs (N/m) pull their vertices towards their anchors (``targets`` on their rows)
        k_hold = control.spring_stiffness(m.fixed)[s]
        k3 = np.repeat(k_hold, 3)
        anchor = targets.reshape(-1)
        supports = m.supports
        touches = len(supports) > 0
        k_contact = self.contact_stiffness * c * m.mass  # N/m per vertex
        k_tool = self.tool_penalty_stiffness()[s] if len(m.tools) else None  # N/m per vertex
        if k_tool is not None:  # tissue pressed onto a support by a tool: the support as stiff as the tool
            k_contact = np.maximum(k_contact, k_tool)

        def contact(x):
            """(penetration (n,) <= 0 on free vertices, normals (n, 3))"""
            d, normal = supports.signed_distance(x)
            return np.where(free_v, np.minimum(d, 0.0), 0.0), normal

        last_tools = [None, None]  # (x, its penalty): potential, gradient and Hessian ask at the same x

        def tools(x):
            """The rigid tools' penalty at x (:class:`heml_gym.tools.ToolPenalty`), None without tools"""
            if not len(m.tools):
                return None
            if last_tools[0] is None or not np.array_equal(last_tools[0], x):
                last_tools[:] = [np.array(x, copy=True), m.tools.penalty(x, control.tool_pose[s], k_tool, free_v)]
            return last_tools[1]

        def potential(x):
            d = x.reshape(-1) - x_hat
            phi = 0.5 * c * float(m3 @ (d * d)) + field.energy(x) - float(load @ x.reshape(-1))
            if k_hold.any():
                e = x.reshape(-1) - anchor
                phi += 0.5 * float(k3 @ (e * e))
            if k_n is not None:
                dn = x.reshape(-1) - x0
                phi += 0.5 * float(dn @ (k_n @ dn))
            if touches:
                pen, _ = contact(x)
                phi += 0.5 * float(k_contact @ (pen * pen))
            if len(m.tools):
                phi += tools(x).energy
            return phi

        def gradient(x):
            g = c * m3 * (x.reshape(-1) - x_hat) - field.forces(x).reshape(-1) - load
            if k_hold.any():
                g += k3 * (x.reshape(-1) - anchor)
            if k_n is not None:
                g += k_n @ (x.reshape(-1) - x0)
            if touches:
                pen, normal = contact(x)
                g += ((k_contact * pen)[:, None] * normal).reshape(-1)
            if len(m.tools):
                g += tools(x).gradient.reshape(-1)
            return g

        def hessian(x, project):
            touching, normal = np.zeros(0, dtype=np.int64), None
            if touches:
                pen, normal = contact(x)
                touching = np.flatnonzero(pen < 0)
            a = penalised_hessian(field, m.mass, x, c, project, self._add_diagonal, self._add_blocks, touching,
                                  normal, self.contact_stiffness * c, k_hold, tools(x))
            return a if k_n is None else a + k_n

        x = self._feasible_start(s, field, x_n, v_n, h, control, targets, potential, hessian)
        free = np.repeat(free_v, 3)
        if self.method == "lbfgs":
            touching, normal = np.zeros(m.n_vertices, dtype=bool), None
            if touches:
                pen, normal = contact(x)
                touching = pen < 0
            precondition = self._lbfgs_preconditioner(s, field, c, free_v, k_hold, touching, normal, k_contact)
            result = minimize_lbfgs(x, potential, gradient, precondition, free, tol, self.max_newton, self.history)
        else:
            pcg = self.pcg[s] if self.linear_solver == "pcg" else None
            result = minimize(x, potential, gradient, hessian, free, tol, self.max_newton, self._submatrix[s],
                              pcg, (free.tobytes(), h), self.stall_limit)
        if not result.finite:
            raise _Diverged("Newton iterate went non-finite")
        x = result.x
        v = (x - x_n) / h
        if len(m.tools):  # each tool's contact force at the solution
            self._tool_force[s] = tools(x).force
        if touches:  # onto the supports, without velocity into them
            pen, normal = contact(x)
            x -= pen[:, None] * normal
            v = (x - x_n) / h
            vn = np.where(pen < 0, np.minimum((v * normal).sum(axis=1), 0.0), 0.0)
            v -= vn[:, None] * normal
        self._constrain(s, x, v, control, targets, h, x_n)
        state.x[s], state.v[s] = x, v
        # constraint force on held vertices: m a minus every other force on them
        f_el = field.forces(x)
        total = f_el + control.external_forces[s] + m.mass[:, None] * m.gravity - alpha * m.mass[:, None] * v
        if beta:
            total += stiffness_damping(field, x, v, f_el, beta)
        held = ~free_v
        reaction = np.zeros_like(x)
        reaction[held] = m.mass[held, None] * (v[held] - v_n[held]) / h - total[held]
        pulled = k_hold > 0
        reaction[pulled] = k_hold[pulled, None] * (targets[pulled] - x[pulled])  # the springs' pull
        return reaction, result

    def _feasible_start(self, s, field, x_n, v_n, h, control, targets, potential, hessian):
        """A Newton starting point with finite energy (no inverted ln J element).

        Of the explicit predictor ``x_n + h v_n`` and the previous positions, the one of
        lower potential (a fast-moving tissue's predictor can land where an exponential
        law's energy is ~1e16 J, from which Newton does not return within its
        iterations); failing both, the previous positions plus the linear response of the
        free vertices to the kinematic vertices' motion (one solve with the step matrix
        at ``x_n``); all with fixed vertices held and kinematic ones on their targets.
        """
        best, best_phi = None, np.inf
        for x in (x_n + h * v_n, x_n.copy()):
            v = v_n.copy()
            self._constrain(s, x, v, control, targets, h, x_n)
            phi = potential(x)
            if np.isfinite(phi) and phi < best_phi:
                best, best_phi = x, phi
        if best is not None:
            return best
        kin = control.exactly_held()[s]
        if kin.any():
            x_moved = x_n.copy()
            x_moved[kin] = targets[kin]
            # (None: a singular or non-finite step matrix, x_n has inverted elements; reported below)
            following = linear_response(hessian(x_n, True).tocsr(), x_n, x_moved, self.model.fixed | kin)
            if following is not None:
                x = following
                v = v_n.copy()
                self._constrain(s, x, v, control, targets, h, x_n)
                if np.all(np.isfinite(x)) and np.isfinite(potential(x)):
                    return x
        inverted = np.flatnonzero(signed_volumes(x, self.model.mesh.tets) <= 0)
        if len(inverted):
            raise _Diverged("no feasible start: the driven vertices invert elements within one step", inverted)
        # (curved elements, quadratic tets: inverted at a quadrature point, no tet of the linear view)
        raise _Diverged("no feasible start: the energy is not finite at any start (an element inverted at one of "
                        "its quadrature points within one step)")
