"""Backward Euler (or BDF2) by quasi-Newton (L-BFGS) from a scalar Laplacian initial Hessian.

After Liu, Bouaziz and Kavan (2017), "Quasi-Newton methods for real-time simulation of
hyperelastic materials": each step minimises backward Euler's incremental potential (the
same as :class:`~heml_gym.solvers.ImplicitSolver`'s, supports included) by L-BFGS whose
initial Hessian is, axis by axis, the scalar matrix ``c M + (lambda + mu) L``: the mesh's
P1 Laplacian ``L`` (for HEML, the constant spring network of ``I1``: Neo-Hookean's ``I1``
stiffness is exactly ``mu L``) weighted by the material's small-strain stiffness, with
the support penalty of the vertices in contact on its diagonal (see
:mod:`heml_gym.solvers.kernels_quasi_newton`). It is a third of the size of the full
Hessian, does not depend on how the tissue is turned (the rest stiffness ``K(X)`` does,
and stalls L-BFGS once the tissue has rotated), and is factorised (an envelope Cholesky
factor per world and axis, stored in single precision: it only preconditions) only when
what it holds changes: the world's material, the held vertices (a grasp or a release),
the step length, or, by more than ``contact_refresh`` vertices, the set of vertices in
contact. Each world keeps its two latest initial Hessians, so that undoing a change (a
release after a grasp, the normal step after a refined one) costs no factorisation.

``scheme="bdf2"`` replaces backward Euler by the second-order backward differentiation
formula (``v_n+1 = (3 x_n+1 - 4 x_n + x_n-1) / 2h``, the same for the acceleration): the
same potential to minimise with another weight of the inertia and another predicted
position, so the same cost per step, and far less numerical damping (backward Euler's
error is first order in the step). On the retraction scenes' 0.05-0.1 s steps it is no
more accurate and less robust: those steps do not resolve the tissue's sag oscillation,
which backward Euler damps out (docs/studies/dynamics.md). It reads the state one step back; a world without
one (its first step, or after :meth:`QuasiNewtonSolver.forget`, a refined step, or a change
of step length) expands it about the step's start with the start's acceleration, which
keeps the scheme second order. Both schemes are A-stable.

The constraint force on held vertices is reported as the step mean, by the trapezoidal
rule between each sub-step's start and end (backward Euler's own force is the end's: half
a step late against the step-mean force of the explicit solver).

All iterations of all worlds run in one compiled call, worlds over threads. Each world
reports its iterations, residual against its tolerance and whether it converged. Units:
m, s, kg, N.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import scipy.sparse as sp

from ..control import Control
from ..forces.heml import HemlForce, assembled_edge_weights
from ..kernel_data import world_law, world_supports
from ..linear_solvers import DiagonalAdd, DiagonalBlockAdd, EnvelopeLayout, FreeSubmatrix, LaggedFactorPCG
from ..model import Model
from ..state import State
from ..tools import Tools
from . import kernels_quasi_newton as kq
from .kernels_wrist import Wrist
from .base import Solver, StepStats, checked_tool_stiffness
from .newton import minimize

__all__ = ["QuasiNewtonSolver", "incremental_hessian", "penalised_hessian"]


def penalised_hessian(field, mass, y, c, project, add_diagonal, add_blocks, touching, normal, k_contact,
                      springs=None, tools=None):
    """The Hessian (CSR, 3n x 3n) at ``y`` (m) of a sub-step's incremental potential, the
    vertices in contact given: the ``field``'s stiffness (its per-element projection if
    ``project``), ``c M`` (1/s^2 times the lumped ``mass``), the hold ``springs`` (n,) N/m
    if any on the diagonal, and the support penalty ``k_contact m_i n n^T`` of the
    ``touching`` vertices (indices; ``normal`` (n, 3) the supports' normals);
    ``add_diagonal`` / ``add_blocks``: a :class:`~heml_gym.linear_solvers.DiagonalAdd` and
    :class:`~heml_gym.linear_solvers.DiagonalBlockAdd` (they cache the pattern); ``tools``:
    the rigid tools' :class:`~heml_gym.tools.ToolPenalty` at ``y``, whose blocks are added too."""
    diagonal = c * mass if springs is None else c * mass + springs
    hess = add_diagonal(field.hessian(y, project=project), np.repeat(diagonal, 3))
    blocks = None
    if len(touching):
        nrm = normal[touching]
        k = k_contact * mass[touching]
        if tools is not None:  # (a support is as stiff as the tools where they press tissue onto it)
            k = np.maximum(k, tools.stiffness[touching])
        blocks = k[:, None, None] * nrm[:, :, None] * nrm[:, None, :]
    if tools is not None and len(tools.touching):
        merged = np.zeros((len(mass), 3, 3))
        if blocks is not None:
            merged[touching] = blocks
        merged[tools.touching] += tools.blocks
        touching = np.union1d(touching, tools.touching)
        blocks = merged[touching]
    if blocks is not None:
        hess = add_blocks(hess, touching, blocks)
    return hess


def incremental_hessian(field, mass, y, c, k_contact, held, potential_args, project, add_diagonal, add_blocks,
                        springs=None):
    """:func:`penalised_hessian` with the free vertices inside a support located by the
    HEML kernels: ``potential_args`` are :func:`~.kernels_quasi_newton.potential_and_gradient`'s.
    The Newton fallback and the calibration's replay of HEML models use it."""
    n = y.shape[0]
    touching = np.zeros(0, dtype=np.int64)
    normal = None
    supports = potential_args[2]
    if supports.planes.shape[0] + supports.grids.shape[0]:
        g, f = np.zeros((n, 3)), np.zeros((n, 3))
        dist, normal = np.full(n, math.inf), np.zeros((n, 3))
        kq.potential_and_gradient(y, False, g, f, dist, normal, *potential_args)
        touching = np.flatnonzero((dist < 0.0) & ~held)
    tools = None
    if supports.tool_kind.shape[0]:  # (a world's view: one row of poses)
        tools = Tools.from_arrays(supports.tool_kind, supports.tool_size).penalty(
            y, supports.tool_pose[0], supports.tool_k[0], ~held)
    return penalised_hessian(field, mass, y, c, project, add_diagonal, add_blocks, touching, normal, k_contact,
                             springs, tools)


class QuasiNewtonSolver(Solver):
    """Backward Euler for every world of ``model`` by L-BFGS (HEML force fields, any law).

    Parameters
    ----------
    model : Model
        Every world's field must be a :class:`~heml_gym.HemlForce`.
    newton_tol : float
        A step stops when the force residual on the free vertices is below ``newton_tol``
        times the world's load (weight plus external forces), as for the Newton solver.
    max_iter : int
        L-BFGS iterations per step at most; a step that stops above its tolerance is
        reported (``StepStats.converged``), never silently.
    history : int
        L-BFGS memory (pairs of past steps and gradient changes, kept from step to step).
        16 takes 12-22 % fewer iterations than 8 on the retraction scenes, but older
        pairs then outlive the configurations they describe: in the flap's soak, 8 of
        950,000 steps stalled at 66-139x their tolerance even in 16x shorter steps (two
        of those streams re-run with 8: none).
    contact_stiffness : float
        Penalty stiffness of the supports, in units of a vertex's inertia ``c m_i``
        (penetration at rest under gravity ``g / (contact_stiffness c)``: 0.07 mm at
        0.1 s steps).
    tool_stiffness : float
        Penalty stiffness of rigid tools (:mod:`heml_gym.tools`) in units of the tissue's
        own at each vertex (``(lambda + mu) V_i^(1/3)``, N/m; :meth:`tool_penalty_stiffness`),
        so that a tool's force does not depend on the step length.
    contact_refresh : int
        The initial Hessian is factorised again when a rigid tool's contact set changes, or
        when the vertices in contact with the supports differ from
        those it holds by more than this many (a stale contact set costs iterations, a
        factorisation about as much as ten of them).
    refinements : sequence of int
        A sub-step that does not converge in ``max_iter`` iterations is taken again by
        L-BFGS in this many shorter steps, then the next number of them (``()``: never).
    fallback : sequence of int
        A sub-step that L-BFGS and its refinements leave unconverged is taken again, from
        its start, by Newton's method on the same incremental potential (the field's
        analytic Hessian, made positive semi-definite per element when the exact one
        gives no descent; a sparse Cholesky solve; a line search): in this many steps,
        then the next number of them (``()``: never). L-BFGS's convergence on the hard
        steps (the lobe's held edge pushed into its stuck underside, where the tissue
        buckles) depends on the rounding of the CPU it runs on (on an AVX2-only Zen 3,
        2026-11-26, one step of a soak stream stayed unconverged after 4, 16 and 64
        times shorter re-takes that converged it on AVX-512 machines); Newton solved that
        step in 5 + 11 iterations, about 0.5 s (the 64x re-take: 2.2 s).
        ``StepStats.fallback`` says which steps took it.
    max_newton : int
        Newton iterations per fallback step at most.
    hessian_scale : float
        The initial Hessian is ``c M + hessian_scale (lambda + mu) L`` per axis (``L`` the
        P1 Laplacian; plus the contact penalty): a preconditioner, so this changes the
        iterations a step takes, never where it converges (to ``newton_tol``). 1 suits
        bulky tissue (the lobe: 12.4 L-BFGS iterations per env step at 1, 12.9 at 1.25);
        the thin two-layer flap, which bends, converges in 16.9 at 1.25 against 22.5 at 1
        (``TissueRetraction``'s world sets 1.25; ``benchmarks/speed/hessian_scale.py``,
        2026-11-26).
    max_speed : float, m/s
        A vertex faster than this counts as exploded.
    scheme : str
        ``"backward_euler"`` (first order) or ``"bdf2"`` (second order, the same cost per
        step; see the module docstring).
    """

    takes_hold_springs = True
    takes_wrist = True
    takes_tools = True

    SCHEMES = {"backward_euler": 1, "bdf2": 2}

    def __init__(self, model: Model, newton_tol: float = 1e-3, max_iter: int = 50, history: int = 8,
                 contact_stiffness: float = 1000.0, contact_refresh: int = 50, refinements=(4, 16),
                 fallback=(1, 4, 16), max_newton: int = 100, max_speed: float = 1e3,
                 scheme: str = "backward_euler", hessian_scale: float = 1.0, tool_stiffness: float = 100.0):
        super().__init__(model, max_speed)
        self.tool_stiffness = checked_tool_stiffness(tool_stiffness)
        if scheme not in self.SCHEMES:
            raise ValueError(f"scheme must be one of {sorted(self.SCHEMES)}, got {scheme!r}")
        self.scheme = scheme
        self.order = self.SCHEMES[scheme]
        for f in model.fields:
            if not isinstance(f, HemlForce):
                raise ValueError(f"the quasi-Newton solver needs HEML force fields, got {type(f).__name__}: "
                                 "use the implicit (Newton) solver")
        newton_tol = float(newton_tol)
        if not (math.isfinite(newton_tol) and newton_tol > 0):
            raise ValueError(f"newton_tol must be a positive number, got {newton_tol}")
        for name, value, low in (("max_iter", max_iter, 1), ("history", history, 1),
                                 ("contact_refresh", contact_refresh, 0), ("max_newton", max_newton, 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        contact_stiffness = float(contact_stiffness)
        if not (math.isfinite(contact_stiffness) and contact_stiffness > 0):
            raise ValueError(f"contact_stiffness must be a positive number, got {contact_stiffness}")
        hessian_scale = float(hessian_scale)
        if not (math.isfinite(hessian_scale) and hessian_scale > 0):
            raise ValueError(f"hessian_scale must be a positive number, got {hessian_scale}")
        self.hessian_scale = hessian_scale
        self.newton_tol = newton_tol
        self.max_iter = int(max_iter)
        self.history = int(history)
        self.contact_stiffness = contact_stiffness
        self.contact_refresh = int(contact_refresh)
        refinements = tuple(refinements)
        if not all(isinstance(r, (int, np.integer)) and not isinstance(r, bool) and r > 1 for r in refinements):
            raise ValueError(f"refinements must be integers > 1 (sub-steps to split an unconverged one into), "
                             f"got {refinements!r}")
        self.refinements = tuple(int(r) for r in refinements)
        fallback = tuple(fallback)
        if not all(isinstance(r, (int, np.integer)) and not isinstance(r, bool) and r >= 1 for r in fallback):
            raise ValueError(f"fallback must be integers >= 1 (Newton steps to take an unconverged sub-step in), "
                             f"got {fallback!r}")
        self.fallback = tuple(int(r) for r in fallback)
        self.max_newton = int(max_newton)
        self._newton_linear: dict = {}  # per world: the Newton fallback's lagged factorisation
        self._free_submatrix = FreeSubmatrix()
        self._add_diagonal = DiagonalAdd()
        self._add_blocks = DiagonalBlockAdd()
        mesh = model.mesh
        n = mesh.n_vertices
        # the P1 Laplacian: per tet the Hessian of V0 (I1 - 3) / 2 on one axis, edge weights V0 a_k
        edges, weights = assembled_edge_weights(mesh, model.heml_body().edge_weights.T)
        self._edge_i = np.ascontiguousarray(edges[:, 0], dtype=np.int64)
        self._edge_j = np.ascontiguousarray(edges[:, 1], dtype=np.int64)
        self._edge_w = np.ascontiguousarray(0.5 * weights)
        self._lap_diag = (np.bincount(self._edge_i, self._edge_w, minlength=n)
                          + np.bincount(self._edge_j, self._edge_w, minlength=n))
        rows = np.concatenate([np.arange(n), self._edge_i, self._edge_j])
        cols = np.concatenate([np.arange(n), self._edge_j, self._edge_i])
        pattern = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
        self.layout = EnvelopeLayout.of(pattern)
        self._diag_pos = self.layout.positions(np.arange(n), np.arange(n))
        self._edge_pos = self.layout.positions(self._edge_i, self._edge_j)
        self._contact_margin = 0.01 * mesh.min_edge_length  # m: closer to a support than this is in contact
        N = model.n_worlds
        # per world two initial Hessians ("entries", the current one ``_entry[s]``), each up to
        # three factors (one per distinct contact penalty over the axes, ``_axis_slot``)
        self._values = np.zeros((N, 2, 3, self.layout.size), dtype=np.float32)
        self._axis_slot = np.zeros((N, 2, 3), dtype=np.int64)
        self._entry = np.zeros(N, dtype=np.int64)
        self._factor_key: list = [[None, None] for _ in range(N)]  # (held mask bytes, stiffness, c) per entry
        # the contact set each factor holds (with tools: the supports' then the tools')
        self._factor_contact = np.zeros((N, 2, n * (2 if len(model.tools) else 1)), dtype=bool)
        self._extra = np.zeros((N, 2, 3, n))  # the contact penalty on the diagonal of each factor
        # L-BFGS curvature pairs kept from step to step (dropped when the initial Hessian's
        # material, held set or step length changes): memory[s] = (pairs stored, newest)
        self._s_hist = np.zeros((N, self.history, n, 3))
        self._y_hist = np.zeros((N, self.history, n, 3))
        self._rho = np.zeros((N, self.history))
        self._memory = np.zeros((N, 2), dtype=np.int64)
        self._memory[:, 1] = -1
        # BDF2: each world's state one step back, and that step's length (0: none)
        kept = n if self.order == 2 else 0  # (backward Euler keeps none)
        self._x_prev = np.zeros((N, kept, 3))
        self._v_prev = np.zeros((N, kept, 3))
        self._history_h = np.zeros(N)
        self._stiffness = (-1, None)  # (model.material_revision, stiffness per world), see _stiffnesses
        self.factorizations = 0

    def laplacian(self) -> sp.csr_matrix:
        """The mesh's P1 Laplacian ``L`` (m), ``n x n``: the initial Hessian per axis is
        ``c M + (lambda + mu) L`` (plus the supports' penalty); ``x^T L x = sum V0 |F|^2``
        summed over the axes of ``x``."""
        n = self.model.n_vertices
        w = self._edge_w
        off = sp.coo_matrix((np.r_[w, w], (np.r_[self._edge_i, self._edge_j], np.r_[self._edge_j, self._edge_i])),
                            shape=(n, n))
        return (sp.diags(self._lap_diag) - off).tocsr()

    def forget(self, worlds) -> None:
        """Drop the initial Hessians, curvature pairs, the Newton fallback's lagged
        factorisation and (BDF2) the state one step back of ``worlds`` (see
        :meth:`Solver.forget`): their next step factorises afresh and starts BDF2 from the
        expansion of its start (see :mod:`.kernels_quasi_newton`)."""
        for s in np.atleast_1d(worlds):
            s = int(s)
            self._factor_key[s] = [None, None]
            self._factor_contact[s] = False
            self._memory[s] = (0, -1)
            self._history_h[s] = 0.0
            self._newton_linear.pop(s, None)  # the fallback's lagged factorisation

    def inertia(self, h: float) -> float:
        """The weight ``c`` (1/s^2) of the mass matrix in a step of ``h`` s: ``1/h^2 +
        alpha/h`` (backward Euler), ``9/(4 h^2) + 3 alpha/(2 h)`` (BDF2)."""
        return float(kq.inertia(self.order, float(h), float(self.model.damping.alpha)))

    # ------------------------------------------------------------ initial Hessians
    def stiffness(self, world: int) -> float:
        """``hessian_scale (lambda + mu)`` (Pa), ``lambda + mu`` of ``world``'s material at
        small strain: the weight of the Laplacian in its initial Hessian."""
        mat = self.model.materials[world]
        return self.hessian_scale * float(mat.lame_lambda + mat.shear_modulus)

    def _refresh_factors(self, worlds: np.ndarray, held: np.ndarray, x: np.ndarray, c: np.ndarray,
                         springs: np.ndarray, control: Control | None = None) -> None:
        """Make current, for each of ``worlds``, the initial Hessian of its material, held
        set and step length: the current entry, else the other one if it holds it (a grasp
        undone, a refined step over), else factorised into the other (older) entry; and
        factorise it again when the contact set moved by more than ``contact_refresh``
        vertices (then only the factors of the axes the contact acts on). L-BFGS's
        curvature pairs are dropped whenever the initial Hessian changes entry."""
        m = self.model
        n = m.n_vertices
        if len(worlds) == 0:
            return
        stiffness = self._stiffnesses()
        contact_any = m.has_contact
        contact = np.zeros((len(worlds), n), dtype=bool)
        if len(m.supports):
            d, normal = m.supports.signed_distance(x if len(worlds) == m.n_worlds else x[worlds])
            contact = (d.reshape(len(worlds), n) <= self._contact_margin) & ~held[worlds]
            normal = normal.reshape(len(worlds), n, 3)
        tool_diag = None
        if len(m.tools):  # each tool on its own, as in the potential: its penalty's diagonal (N/m)
            tool_diag = np.zeros((len(worlds), 3, n))  # N/m
            tool_k = self.tool_penalty_stiffness()
            tool_contact = np.zeros((len(worlds), n), dtype=bool)
            for k, s in enumerate(worlds):
                d_t, normal_t = m.tools.each_distance(x[s], control.tool_pose[s])  # (T, n), (T, n, 3)
                near = (d_t <= self._contact_margin) & ~held[s][None, :]
                tool_contact[k] = near.any(axis=0)
                tool_diag[k] = tool_k[s][None, :] * (near[:, :, None] * normal_t ** 2).sum(axis=0).T
            contact_key = np.concatenate([contact, tool_contact], axis=1)  # (what a refresh compares)
        jobs = []
        for k, s in enumerate(worlds):
            key = (held[s].tobytes(), springs[s].tobytes(), stiffness[s], c[s])
            ent = int(self._entry[s])
            if key != self._factor_key[s][ent]:
                ent = 1 - ent
                self._entry[s] = ent
                self._memory[s] = (0, -1)
            same_key = key == self._factor_key[s][ent]
            if contact_any:
                key_now = contact[k] if tool_diag is None else contact_key[k]
                changed = key_now != self._factor_contact[s, ent]
                # a tool's contact is stiff: any change of it refactorises (the supports' tolerate a few)
                if same_key and np.count_nonzero(changed[:n]) <= self.contact_refresh and not changed[n:].any():
                    continue
                self._factor_contact[s, ent] = key_now
                if len(m.supports) and tool_diag is not None:  # (as stiff as the tools: the potential's)
                    k_support = np.maximum(self.contact_stiffness * c[s] * m.mass, tool_k[s])
                    extra = (k_support * contact[k])[None, :] * normal[k].T ** 2
                elif len(m.supports):
                    extra = (self.contact_stiffness * c[s] * m.mass * contact[k])[None, :] * normal[k].T ** 2  # (3, n)
                else:
                    extra = np.zeros((3, n))
                if tool_diag is not None:
                    extra = extra + tool_diag[k]
                extra = extra + springs[s][None, :]  # (the hold springs, on every axis)
            elif same_key:
                continue
            else:
                extra = np.zeros((3, n)) + springs[s][None, :]
            slots, distinct = [0, 0, 0], [extra[0]]
            for a in (1, 2):
                for i, e in enumerate(distinct):
                    if np.array_equal(extra[a], e):
                        slots[a] = i
                        break
                else:
                    slots[a] = len(distinct)
                    distinct.append(extra[a])
            for i, penalty in enumerate(distinct):
                if not (same_key and np.array_equal(self._extra[s, ent, i], penalty)):  # else: held already
                    self._extra[s, ent, i] = penalty
                    jobs.append((s, ent, i))
            self._axis_slot[s, ent] = slots
            self._factor_key[s][ent] = key
        if not jobs:
            return
        jobs = np.array(jobs, dtype=np.int64)
        status = np.empty(len(jobs), dtype=np.int64)
        kq.factor_jobs(jobs[:, 0], jobs[:, 1], jobs[:, 2], self._values, self.layout.first, self.layout.ptr,
                       self._diag_pos, self._edge_pos, self._edge_i, self._edge_j, self._edge_w, self._lap_diag,
                       m.mass, c, stiffness, held, self._extra, status)
        self.factorizations += len(jobs)
        if np.any(status >= 0):  # c M is positive definite: only a broken material gets here
            bad = int(np.argmax(status >= 0))
            s = int(jobs[bad, 0])
            self._factor_key[s][int(jobs[bad, 1])] = None
            raise ValueError(f"the initial Hessian of world {s} is not positive definite: check its material "
                             f"({m.materials[s]!r})")

    # ------------------------------------------------------------------------ step
    def step(self, state_in: State, state_out: State, control: Control, dt: float,
             substeps: int = 1, active=None) -> StepStats:
        """Advance the ``active`` worlds (default: all) by ``dt`` s in ``substeps`` equal
        steps of the scheme (backward Euler or BDF2). A sub-step whose L-BFGS stops above
        its tolerance, or that has no start without inverted elements (held vertices driven
        into the tissue faster than it can give way), is taken again in ``refinements[0]``
        shorter steps, then ``refinements[1]``, ... (more inertia per step: a better
        conditioned, more convex potential, e.g. when the tissue buckles; and a shorter
        move of the held vertices);
        ``StepStats.refinement`` says by how much. A sub-step still unconverged is taken
        again by Newton's method in ``fallback[0]`` steps, then ``fallback[1]``, ...
        (``StepStats.fallback``; its ``refinement`` then counts the Newton steps). A world
        that goes non-finite, explodes or still cannot start is flagged ``diverged`` (its
        state kept); one whose solve still stops above tolerance ``converged = False``."""
        dt, active = self._check(state_in, state_out, control, dt, active)
        substeps = int(substeps)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        m = self.model
        N = m.n_worlds
        stats = StepStats.empty(N, m.n_vertices, substeps)
        stats.residual[:] = 0.0
        h = dt / substeps
        held = control.exactly_held() | m.fixed[None, :]
        tol = self.newton_tol * self.force_scales(control)
        stats.tolerance[:] = tol
        x, v = state_out.x, state_out.v
        x0, v0 = x.copy(), v.copy()
        wrist_start = self._wrist_state(control)
        r_prev = np.zeros_like(x)
        stats.reaction[:] = 0.0
        feasible = np.ones(N, dtype=bool)
        args = self._kernel_args(state_out, control, held, tol)
        tool_sum = np.zeros((N, len(m.tools), 3)) if len(m.tools) else None  # the tools' impulses over dt
        with np.errstate(all="ignore"):
            for k in range(1, substeps + 1):
                run = active & feasible
                saved = x.copy(), v.copy(), r_prev.copy()  # (whole arrays: cheaper than a masked gather)
                wrist_saved = self._wrist_state(control)
                history = self._x_prev.copy(), self._v_prev.copy(), self._history_h.copy()  # (BDF2's)
                residual_before, converged_before = stats.residual.copy(), stats.converged.copy()
                contribution = np.zeros_like(x)
                out = self._advance(args, run, h, 1.0 / (substeps - k + 1), k == 1, r_prev, contribution)
                tool_part = np.where(run[:, None, None], args["tool_force"], 0.0) if tool_sum is not None else None
                self._count(stats, run, out, feasible)
                retry = run & (out[:, 2] < 0.5)  # unconverged, or no feasible start
                refined, by_fallback = np.ones(N, dtype=np.int64), np.zeros(N, dtype=bool)  # this sub-step's
                retakes = [(f, self._advance, False) for f in self.refinements]
                retakes += [(f, self._newton_advance, True) for f in self.fallback]
                for factor, advance, by_newton in retakes:
                    if not retry.any():
                        break
                    # take the sub-step again in ``factor`` shorter ones, from its start (the
                    # held vertices move a ``factor``-th as far per step, and the tissue in
                    # front of them has time to give way)
                    x[retry], v[retry], r_prev[retry] = saved[0][retry], saved[1][retry], saved[2][retry]
                    self._restore_wrist(control, wrist_saved, retry)
                    self._x_prev[retry], self._v_prev[retry] = history[0][retry], history[1][retry]
                    self._history_h[retry] = history[2][retry]
                    finer = np.zeros_like(x)
                    finer_tool = np.zeros_like(tool_part) if tool_part is not None else None
                    feasible[retry] = True
                    stats.converged[retry] = True  # this re-take's verdict (earlier sub-steps': below)
                    stats.residual[retry] = residual_before[retry]
                    by_fallback[retry] = by_newton
                    for j in range(1, factor + 1):
                        go = retry & feasible
                        remaining = (substeps - k) * factor + factor - j + 1
                        part = np.zeros_like(x)
                        out = advance(args, go, h / factor, 1.0 / remaining, k == 1 and j == 1, r_prev, part)
                        finer += part
                        if finer_tool is not None:
                            finer_tool[go] += args["tool_force"][go]
                        self._count(stats, go, out, feasible)
                    contribution[retry] = finer[retry] / factor
                    if tool_part is not None:
                        tool_part[retry] = finer_tool[retry] / factor
                    refined[retry] = factor
                    retry &= ~(feasible & stats.converged)
                stats.converged &= converged_before
                stats.refinement = np.maximum(stats.refinement, refined)
                stats.fallback |= by_fallback
                stats.reaction += contribution
                if tool_sum is not None:
                    tool_sum += tool_part
        stats.reaction /= substeps
        check = active & ~(feasible & stats.converged)  # (the others: only those divergence may flag)
        check[self.suspect_worlds(x, v, np.flatnonzero(active))] = True
        for s in np.flatnonzero(check):
            reason, elements = self.divergence(x[s], v[s])
            if not feasible[s]:
                reason = "no feasible start: the held vertices invert elements within one step"
            if reason:
                x[s], v[s] = x0[s], v0[s]
                self._restore_wrist(control, wrist_start, s)
                self._memory[s] = (0, -1)
                self._history_h[s] = 0.0
                stats.diverged[s] = True
                stats.converged[s] = False
                stats.reaction[s] = 0.0
                stats.messages[s] = reason
                stats.elements[s] = elements
            elif not stats.converged[s] and stats.fallback[s] and control.turns[s].any():
                stats.messages[s] = (f"L-BFGS stopped at a force residual above its tolerance of {tol[s]:.3g} N in "
                                     f"every re-take, and its Newton fallback does not step jaws on a free wrist")
            elif not stats.converged[s]:
                method = "Newton (the fallback)" if stats.fallback[s] else "L-BFGS"
                stats.messages[s] = (f"{method} stopped at a force residual of {stats.residual[s]:.3g} N, above its "
                                     f"tolerance of {tol[s]:.3g} N, after {stats.newton_iterations[s]} iterations "
                                     f"in all (sub-steps refined {stats.refinement[s]}x)")
        stats.reaction[~active] = 0.0
        if tool_sum is not None:  # step-mean: each sub-step's end force (backward Euler's) weighted by its length
            stats.tool_force = np.where((active & ~stats.diverged)[:, None, None], tool_sum / substeps, 0.0)
        return stats

    @staticmethod
    def _wrist_state(control: Control) -> tuple:
        """What a step changes of the wrists (pivot, angle, stiffness estimate), copied."""
        return control.pivot.copy(), control.wrist_angle.copy(), control.wrist_stiffness.copy()

    @staticmethod
    def _restore_wrist(control: Control, saved: tuple, worlds) -> None:
        control.pivot[worlds], control.wrist_angle[worlds], control.wrist_stiffness[worlds] = (
            saved[0][worlds], saved[1][worlds], saved[2][worlds])

    def _kernel_args(self, state: State, control: Control, held: np.ndarray, tol: np.ndarray) -> dict:
        """What every call of the L-BFGS kernel in one step shares."""
        m = self.model
        springs = control.spring_stiffness(m.fixed)
        return dict(x=state.x, v=state.v, control=control, held=held, tol=tol, body=m.heml_body(),
                    laws=m.heml_laws(), supports=m.contact_args(control, self.tool_penalty_stiffness()),
                    stiffness=self._stiffnesses(),
                    springs=springs, holds=kq.Holds(control.kinematic, control.hold_stiffness, control.anchors),
                    tool_force=np.zeros((m.n_worlds, len(m.tools), 3)))

    def _stiffnesses(self) -> np.ndarray:
        """:meth:`stiffness` of every world (Pa), kept until a world's material changes."""
        revision, stiffness = self._stiffness
        if revision != self.model.material_revision:
            stiffness = np.array([self.stiffness(s) for s in range(self.model.n_worlds)])
            self._stiffness = (self.model.material_revision, stiffness)
        return stiffness

    def _advance(self, a: dict, run: np.ndarray, h: float, fraction: float, first_substep: bool,
                 r_prev: np.ndarray, contribution: np.ndarray) -> np.ndarray:
        """One backward Euler step of length ``h`` (s) of the ``run`` worlds, their held
        vertices moved a ``fraction`` of the way to their targets; the step-mean reaction
        added into ``contribution``. Returns the kernel's ``(N, 4)`` report."""
        m = self.model
        N = m.n_worlds
        out = np.zeros((N, 4))
        if not run.any():
            return out
        x, v = a["x"], a["v"]
        c = np.full(N, self.inertia(h))
        control = a["control"]
        self._refresh_factors(np.flatnonzero(run), a["held"], x, c, a["springs"], control)
        hessians = kq.InitialHessians(self.layout.inverse, self.layout.first, self.layout.ptr, self._values,
                                      self._entry, self._axis_slot, self._edge_i, self._edge_j, self._edge_w,
                                      a["stiffness"])
        kernel = kq.lbfgs_steps_parallel if N > 1 and numba.get_num_threads() > 1 else kq.lbfgs_steps_serial
        wrist = Wrist(control.turns, control.arms, control.wrist_axis, control.pivot, control.pivot_target,
                      control.wrist_angle, control.wrist_stiffness)
        kernel(x, v, control.targets, a["holds"], control.external_forces, a["body"], a["laws"],
               a["supports"], hessians, self._lbfgs_memory(), a["tol"], self._substep(h, fraction, first_substep),
               self._bdf2_history(), run, r_prev, contribution, out, wrist, a["tool_force"])
        return out

    def _substep(self, h: float, fraction: float, first_substep: bool) -> kq.Substep:
        return kq.Substep(float(h), float(fraction), int(self.order), bool(first_substep), int(self.max_iter),
                          float(self.contact_stiffness))

    def _lbfgs_memory(self) -> kq.LbfgsMemory:
        return kq.LbfgsMemory(self._s_hist, self._y_hist, self._rho, self._memory)

    def _bdf2_history(self) -> kq.Bdf2History:
        return kq.Bdf2History(self._x_prev, self._v_prev, self._history_h)

    def _newton_advance(self, a: dict, run: np.ndarray, h: float, fraction: float, first_substep: bool,
                        r_prev: np.ndarray, contribution: np.ndarray) -> np.ndarray:
        """:meth:`_advance` by Newton's method, world after world: the same sub-step
        (:func:`~.kernels_quasi_newton.begin_substep`, the same incremental potential,
        :func:`~.kernels_quasi_newton.end_substep`), minimised by
        :func:`heml_gym.solvers.newton.minimize` from the lower-potential of the explicit
        predictor and the step's start. The world's L-BFGS curvature pairs are dropped
        (its next step starts them afresh)."""
        m = self.model
        out = np.zeros((m.n_worlds, 4))
        for s in np.flatnonzero(run):
            if a["control"].turns[s].any():  # (not stepped by Newton: reported unconverged, from its start)
                out[s] = (0.0, math.inf, 0.0, 1.0)
                continue
            out[s] = self._newton_world(a, int(s), h, fraction, first_substep, r_prev[s], contribution[s])
            self._memory[s] = (0, -1)
        return out

    def _newton_world(self, a: dict, s: int, h: float, fraction: float, first_substep: bool,
                      r_prev: np.ndarray, reaction: np.ndarray) -> tuple:
        """One sub-step of world ``s`` by Newton; returns ``(iterations, residual (N),
        converged, feasible)`` as the L-BFGS kernel reports them."""
        m = self.model
        n = m.n_vertices
        control = a["control"]
        x, v = a["x"][s], a["v"][s]
        field = m.fields[s]
        body, law, supports = a["body"], world_law(a["laws"], s), world_supports(a["supports"], s)
        work = kq.substep_work(n, self.order)
        x_n, v_n, held, f = work.x_n, work.v_n, work.held, work.f
        sub = self._substep(h, fraction, first_substep)
        history = kq.Bdf2History(self._x_prev[s], self._v_prev[s], self._history_h[s:s + 1])
        holds = kq.Holds(control.kinematic[s], control.hold_stiffness[s], control.anchors[s])
        c, _ = kq.begin_substep(x, v, control.targets[s], holds, control.external_forces[s], body, law,
                                sub, history, r_prev, work)
        n_supports = supports.planes.shape[0] + supports.grids.shape[0]
        k_contact = self.contact_stiffness * c
        potential_args = (body, law, supports, c, work.x_hat, work.load, held, k_contact, holds)
        springs = a["springs"][s]
        g = np.zeros((n, 3))
        dist, normal = np.full(n, math.inf), np.zeros((n, 3))

        def potential(y):
            return kq.potential_and_gradient(y.reshape(n, 3), False, g, f, dist, normal, *potential_args)

        def gradient(y):
            kq.potential_and_gradient(y.reshape(n, 3), True, g, f, dist, normal, *potential_args)
            return g.reshape(-1).copy()

        def hessian(y, project):
            return incremental_hessian(field, m.mass, y.reshape(n, 3), c, k_contact, held, potential_args, project,
                                       self._add_diagonal, self._add_blocks, springs)

        start, best = None, math.inf
        for candidate in (x_n + h * v_n, x_n.copy()):
            candidate[held] = x[held]
            phi = potential(candidate)
            if phi < best:  # (finite)
                start, best = candidate, phi
        if start is None:  # no start without inverted elements
            x[:] = x_n
            return 0.0, math.inf, 0.0, 0.0
        free = np.repeat(~held, 3)
        linear = self._newton_linear.setdefault(s, LaggedFactorPCG(rtol=1e-2, max_iter=8, factorization="cholesky"))
        with np.errstate(all="ignore"):
            result = minimize(start, potential, gradient, hessian, free, float(a["tol"][s]), self.max_newton,
                              self._free_submatrix, linear, (free.tobytes(), h), stall_limit=10)
        x[:] = result.x
        if not result.finite:
            return float(result.iterations), math.inf, 0.0, 1.0
        kq.potential_and_gradient(x, True, g, f, dist, normal, *potential_args)  # f, dist, normal at x
        if len(m.tools):
            kq.tool_contact_forces(x, held, supports, a["tool_force"][s])
        kq.end_substep(x, v, work, dist, normal, n_supports, True, reaction, r_prev, body, law, sub, history, holds)
        return float(result.iterations), result.residual, float(result.converged), 1.0

    @staticmethod
    def _count(stats: StepStats, run: np.ndarray, out: np.ndarray, feasible: np.ndarray) -> None:
        """Add one kernel call's report of the ``run`` worlds to ``stats`` (and ``feasible``)."""
        kq.count_report(run, out, stats.newton_iterations, stats.residual, stats.converged, feasible)
