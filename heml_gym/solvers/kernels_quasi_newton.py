"""Numba kernels of the quasi-Newton (L-BFGS) backward Euler solver: one world per call
of :func:`_lbfgs_world`, worlds over threads in :func:`lbfgs_steps_parallel`, and the
assembly and factorisation of its scalar initial Hessians (:func:`factor_jobs`). The
kernels take the model's bundles (:mod:`heml_gym.kernel_data`) and the solver's own
(:class:`InitialHessians`, :class:`LbfgsMemory`, :class:`Bdf2History`, :class:`Substep`).

Each step minimises the incremental potential of backward Euler (or of BDF2) over the free
vertices,

    Phi(x) = c/2 sum_i m_i |x_i - x_hat_i|^2 + W(x) - sum_i (f_ext,i + m_i g) . x_i
             + sum_i k_i/2 min(d_i(x), 0)^2,

backward Euler: ``c = 1/h^2 + alpha/h``, ``x_hat = x_n + h v_n / (1 + alpha h)``;
BDF2 (second order, ``v_n+1 = (3 x_n+1 - 4 x_n + x_n-1) / 2h``, the same for the
acceleration): ``c = 9/(4 h^2) + 3 alpha/(2 h)``, ``x_hat = (3 p/(4 h^2) + q/(2 h) + alpha
p/(2 h)) / c`` with ``p = 4 x_n - x_n-1``, ``q = 4 v_n - v_n-1`` (see :func:`inertia`),

by L-BFGS whose initial Hessian is, on each axis ``a``, the scalar matrix

    A_a = c M + s (lambda + mu) L + diag(k_i n_ia^2 over the vertices in contact),

``L`` the mesh's P1 Laplacian (edge weights ``sum V0 a_k`` over the tets of an edge: the
Hessian of ``V0 (I1 - 3) / 2`` on one axis; Neo-Hookean's ``I1`` stiffness is ``mu L``),
``lambda + mu`` the material's small-strain stiffness (the Laplacian at that weight
approximates the shear and volumetric stiffness together; ``s`` the solver's
``hessian_scale``, 1 by default), held and fixed vertices
eliminated (their rows made identity), the support penalty of the vertices in contact on
the diagonal. Unlike the rest stiffness ``K(X)`` it does not depend on the orientation
of the tissue, so it stays a good model of the Hessian when the tissue turns over (Liu,
Bouaziz and Kavan 2017 use the same Laplacian, from Projective Dynamics). A backtracking
line search on ``Phi`` (Armijo, or a smaller residual near convergence) keeps every
iterate finite. Units: m, s, kg, N.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba import prange

from typing import NamedTuple

from ..forces.kernels_heml import (constant_psi1_energy_and_forces_chunk, constant_psi1_forces_chunk,
                                   heml_energy_chunk, heml_forces_chunk)
from ..kernel_data import world_law, world_supports
from ..kernels_cholesky import envelope_cholesky, envelope_solve, envelope_solve_pair
from ..kernels_contact import signed_distances, tool_signed_distance
from .kernels_wrist import begin_wrist, radius, settle, subset_forces, tets_touching, world_wrist


# ------------------------------------------------------------------------ bundles
# (the model's: heml_gym.kernel_data.HemlBody / HemlLaws / WorldLaw / SupportArrays)
class InitialHessians(NamedTuple):
    """The solver's factorised initial Hessians (envelope storage, float32), per world two
    entries of up to three factors (one per distinct contact penalty over the axes)."""

    inverse: np.ndarray  #: (n,) int64: vertex -> row of the factor (a bandwidth-reducing order)
    first: np.ndarray  #: (n,) envelope layout (see :mod:`heml_gym.kernels_cholesky`)
    ptr: np.ndarray  #: (n + 1,)
    values: np.ndarray  #: (N, 2, 3, size) float32 factors
    entry: np.ndarray  #: (N,) int64: the entry in use
    axis_slot: np.ndarray  #: (N, 2, 3) int64: the factor of each axis
    edge_i: np.ndarray  #: (E,) int64 the Laplacian's edges
    edge_j: np.ndarray  #: (E,) int64
    edge_w: np.ndarray  #: (E,) edge weights (m)
    stiffness: np.ndarray  #: (N,) the Laplacian's weight (Pa)


class WorldHessian(NamedTuple):
    """One world's current initial Hessian (see :func:`world_hessian`)."""

    inverse: np.ndarray
    first: np.ndarray
    ptr: np.ndarray
    values: np.ndarray  #: (3, size) float32
    axis_slot: np.ndarray  #: (3,)
    edge_i: np.ndarray
    edge_j: np.ndarray
    edge_w: np.ndarray
    stiffness: float


class LbfgsMemory(NamedTuple):
    """L-BFGS curvature pairs kept from step to step (stacked over worlds, or one world's)."""

    s_hist: np.ndarray  #: ([N,] history, n, 3) steps (m)
    y_hist: np.ndarray  #: ([N,] history, n, 3) gradient changes (N)
    rho: np.ndarray  #: ([N,] history) 1 / (s . y)
    memory: np.ndarray  #: ([N,] 2) int64: pairs stored, newest


class Bdf2History(NamedTuple):
    """BDF2's state one step back (``(.., 0, 3)`` arrays under backward Euler) and that
    step's length (s; 0: none), stacked over worlds or one world's (``history_h``: a
    one-element slice)."""

    x_prev: np.ndarray
    v_prev: np.ndarray
    history_h: np.ndarray


class Substep(NamedTuple):
    """What one call's sub-steps share."""

    h: float  #: sub-step length (s)
    fraction: float  #: held vertices move this fraction of the way to their targets
    order: int  #: 1: backward Euler, 2: BDF2
    first_substep: bool  #: the step's first (its start's holding force is computed)
    max_iter: int  #: L-BFGS iterations at most
    kappa: float  #: support penalty stiffness in units of a vertex's inertia ``c m_i``


class SubstepWork(NamedTuple):
    """A sub-step's working arrays (``(n, 3)``; ``x_m, v_m``: ``(0, 3)`` under backward
    Euler; ``held``: ``(n,)`` bool), filled by :func:`begin_substep`."""

    x_n: np.ndarray
    v_n: np.ndarray
    x_m: np.ndarray
    v_m: np.ndarray
    x_hat: np.ndarray
    load: np.ndarray
    held: np.ndarray
    jump: np.ndarray
    f: np.ndarray


class Holds(NamedTuple):
    """What holds vertices (leading axis: the worlds' N, or none for one world):
    ``kinematic`` (n,) bool, the held vertices; ``stiffness`` (n,) N/m, 0 for a vertex held
    exactly (it follows its target), else the stiffness of the spring that holds it to its
    ``anchor`` (n, 3) m, which follows the target instead (a vertex the jaws hold in part)."""

    kinematic: np.ndarray
    stiffness: np.ndarray
    anchor: np.ndarray


@nb.njit(cache=True, inline="always")
def world_hessian(hessians, s):
    """World ``s``'s current :class:`WorldHessian` of ``hessians`` (:class:`InitialHessians`)."""
    e = hessians.entry[s]
    return WorldHessian(hessians.inverse, hessians.first, hessians.ptr, hessians.values[s, e],
                        hessians.axis_slot[s, e], hessians.edge_i, hessians.edge_j, hessians.edge_w,
                        hessians.stiffness[s])


@nb.njit(cache=True, inline="always")
def substep_work(n, order):
    """Fresh :class:`SubstepWork` for ``n`` vertices."""
    kept = n if order == 2 else 0  # (backward Euler reads neither)
    return SubstepWork(np.empty((n, 3)), np.empty((n, 3)), np.empty((kept, 3)), np.empty((kept, 3)),
                       np.empty((n, 3)), np.empty((n, 3)), np.empty(n, dtype=np.bool_), np.empty((n, 3)),
                       np.empty((n, 3)))


@nb.njit(cache=True)
def inertia(order, h, alpha):
    """``c`` (1/s^2) of a step of length ``h`` (s) with mass damping ``alpha`` (1/s):
    the weight of ``M`` in the incremental potential and its Hessian; ``order`` 1:
    backward Euler, 2: BDF2."""
    if order == 2:
        return 2.25 / (h * h) + 1.5 * alpha / h
    return 1.0 / (h * h) + alpha / h


# ------------------------------------------------------------------ initial Hessians
@nb.njit(cache=True)
def assemble_factor(values, first, ptr, diag_pos, edge_pos, edge_i, edge_j, edge_w, lap_diag, mass, c, stiffness,
                    held, extra):
    """Assemble ``c M + stiffness L + diag(extra)`` with the ``held`` rows and columns made
    identity into envelope storage ``values`` and factorise it in place.

    ``diag_pos (n,)`` / ``edge_pos (E,)``: positions of the diagonal and edge entries in
    ``values``; ``edge_w (E,)`` the Laplacian's edge weights (m), ``lap_diag (n,)`` its
    diagonal. Returns -1, or the factor row whose pivot was not positive.
    """
    values[:] = 0.0
    n = mass.shape[0]
    for i in range(n):
        if held[i]:
            values[diag_pos[i]] = 1.0
        else:
            values[diag_pos[i]] = c * mass[i] + stiffness * lap_diag[i] + extra[i]
    for e in range(edge_i.shape[0]):
        i = edge_i[e]
        j = edge_j[e]
        if not (held[i] or held[j]):
            values[edge_pos[e]] = -stiffness * edge_w[e]
    return envelope_cholesky(first, ptr, values)


@nb.njit(cache=True, parallel=True)
def factor_jobs(job_world, job_entry, job_slot, values, first, ptr, diag_pos, edge_pos, edge_i, edge_j, edge_w,
                lap_diag, mass, c, stiffness, held, extra, status):
    """Factorise ``values[s, entry, slot]`` (single precision) for each job ``(s, entry,
    slot)`` (over threads), with the world's ``stiffness[s]``, ``held[s]`` and ``extra[s,
    entry, slot]`` (see :func:`assemble_factor`); ``status[job]`` receives its result. A
    factor whose single-precision pivots fail (a matrix too ill-conditioned for them) is
    factorised in double precision and rounded."""
    for k in prange(job_world.shape[0]):
        s = job_world[k]
        e = job_entry[k]
        slot = job_slot[k]
        target = values[s, e, slot]
        status[k] = assemble_factor(target, first, ptr, diag_pos, edge_pos, edge_i, edge_j, edge_w,
                                    lap_diag, mass, c[s], stiffness[s], held[s], extra[s, e, slot])
        if status[k] >= 0:
            exact = np.empty(target.shape[0])
            status[k] = assemble_factor(exact, first, ptr, diag_pos, edge_pos, edge_i, edge_j, edge_w,
                                        lap_diag, mass, c[s], stiffness[s], held[s], extra[s, e, slot])
            for i in range(target.shape[0]):
                target[i] = exact[i]


@nb.njit(cache=True)
def _precondition(g, z, held, hessian, b, y):
    """``z = A^-1 g`` axis by axis (``A_a`` the factor ``hessian.values[axis_slot[a]]``;
    two axes that share a factor are solved in one pass over it); zero on held vertices.
    ``b``, ``y`` are ``(3, n)`` scratch arrays of the factor's dtype (float32: an
    approximate inverse needs no more, and the solves then run in 8 lanes on AVX2)."""
    n = g.shape[0]
    inverse, first, ptr, values, axis_slot = hessian.inverse, hessian.first, hessian.ptr, hessian.values, \
        hessian.axis_slot
    for a in range(3):
        for i in range(n):
            b[a, np.uint64(inverse[i])] = 0.0 if held[i] else g[i, a]
    done = np.zeros(3, dtype=np.bool_)
    for a in range(3):
        if done[a]:
            continue
        done[a] = True
        pair = -1
        for o in range(a + 1, 3):
            if axis_slot[o] == axis_slot[a]:
                pair = o
                break
        if pair >= 0:
            done[pair] = True
            envelope_solve_pair(first, ptr, values[axis_slot[a]], b[a], b[pair], y[a], y[pair])
        else:
            envelope_solve(first, ptr, values[axis_slot[a]], b[a], y[a])
    for i in range(n):
        k = np.uint64(inverse[i])
        for a in range(3):
            z[i, a] = 0.0 if held[i] else y[a, k]


# ------------------------------------------------------------------------ potential
@nb.njit(cache=True)
def potential_and_gradient(x, want_gradient, g, f, dist, normal, body, law, supports, c, x_hat, load, held,
                           k_contact, holds):
    """``Phi(x)`` (J) and, if ``want_gradient``, its gradient into ``g`` (N; zero on held
    vertices): ``body`` (:class:`~heml_gym.kernel_data.HemlBody`), ``law``
    (:class:`~heml_gym.kernel_data.WorldLaw`), ``supports``
    (:class:`~heml_gym.kernel_data.SupportArrays`), the inertia weight ``c`` (1/s^2), the
    inertial target ``x_hat`` (m), the ``load`` (N), the ``held`` mask, the support
    penalty ``k_contact`` (1/s^2, times a vertex's mass) and the springs of ``holds``
    (:class:`Holds`: ``stiffness / 2 |x - anchor|^2`` on each spring-held vertex). ``f``,
    ``dist``, ``normal`` are scratch (``dist``, ``normal``: the signed distances to the
    supports at ``x``)."""
    n = x.shape[0]
    tets = body.tets
    m = tets.shape[0]
    mass = body.mass
    n_supports = supports.planes.shape[0] + supports.grids.shape[0]
    n_tools = supports.tool_kind.shape[0]
    if law.split and want_gradient:  # energy and forces in one pass
        f[:, :] = 0.0
        phi = constant_psi1_energy_and_forces_chunk(x, tets, body.inv_det, body.coef_t[0], law.weights, law.psi1,
                                                    law.law, law.params, f, 0, m)
        if not math.isfinite(phi):
            return math.inf
    else:
        phi = heml_energy_chunk(x, tets, body.coef_t, law.q_t, law.use_q, law.law, law.params, 0, m)
        if not math.isfinite(phi):
            return math.inf
        if want_gradient:
            elastic_forces(x, f, body, law)
    if n_supports:
        signed_distances(x, supports.planes, supports.grids, supports.grid_values, dist, normal)
    for i in range(n):
        if held[i]:
            if want_gradient:
                g[i, 0] = 0.0
                g[i, 1] = 0.0
                g[i, 2] = 0.0
            continue
        mi = mass[i]
        pen = min(dist[i], 0.0) if n_supports else 0.0
        kc = k_contact * mi
        if n_tools:  # tissue pressed onto a support by a tool: the support as stiff as the tool
            kc = max(kc, supports.tool_k[0, i])
        for d in range(3):
            e = x[i, d] - x_hat[i, d]
            phi += 0.5 * c * mi * e * e - load[i, d] * x[i, d]
            if want_gradient:
                g[i, d] = c * mi * e - f[i, d] - load[i, d] + kc * pen * normal[i, d]
        phi += 0.5 * kc * pen * pen
        ks = holds.stiffness[i]
        if ks > 0.0 and holds.kinematic[i]:  # held by a spring to its anchor
            for d in range(3):
                e = x[i, d] - holds.anchor[i, d]
                phi += 0.5 * ks * e * e
                if want_gradient:
                    g[i, d] += ks * e
    if supports.tool_kind.shape[0]:
        phi += tool_penalty(x, want_gradient, g, held, supports, np.zeros((0, 3)))
    return phi


@nb.njit(cache=True)
def tool_penalty(x, want_gradient, g, held, supports, forces):
    """The rigid tools' contact penalty ``sum_t sum_i k_i / 2 min(d_it, 0)^2`` (J), ``k_i =
    tool_k[i]`` (N/m), on the free vertices (each tool on its own, so that a vertex
    squeezed between two feels both); if ``want_gradient``, its gradient added into ``g``;
    each tool's force on the tissue, ``k_i |d_it| n_it`` (N), added into ``forces (T, 3)``
    when it has rows. ``supports``: a world's view (one row of poses)."""
    phi = 0.0
    kind, size, pose = supports.tool_kind, supports.tool_size, supports.tool_pose[0]
    report = forces.shape[0] > 0
    for i in range(x.shape[0]):
        if held[i]:
            continue
        k = supports.tool_k[0, i]
        for t in range(kind.shape[0]):
            d, nx, ny, nz = tool_signed_distance(kind[t], size[t], pose[t], x[i, 0], x[i, 1], x[i, 2])
            if d < 0.0:
                phi += 0.5 * k * d * d
                if want_gradient:
                    g[i, 0] += k * d * nx
                    g[i, 1] += k * d * ny
                    g[i, 2] += k * d * nz
                if report:
                    forces[t, 0] -= k * d * nx
                    forces[t, 1] -= k * d * ny
                    forces[t, 2] -= k * d * nz
    return phi


@nb.njit(cache=True)
def elastic_forces(x, f, body, law):
    """``f`` = the HEML forces (N) at ``x``."""
    _forces_of(x, f, body.tets, body.coef_t, law.q_t, law.use_q, law.law, law.params, law.split, law.weights,
               body.inv_det)


@nb.njit(cache=True, inline="always")
def _forces_of(x, f, tets, coef_t, q_t, use_q, law, p, split, w, inv_det):
    """``f`` = the HEML forces (N) at ``x`` of the tets ``tets`` (and their rest data)."""
    f[:, :] = 0.0
    if split:
        constant_psi1_forces_chunk(x, tets, inv_det, w, law, p, f, 0, tets.shape[0])
    else:
        heml_forces_chunk(x, tets, coef_t, q_t, use_q, law, p, f, 0, tets.shape[0])


@nb.njit(cache=True)
def held_forces(x, f, held, body, law):
    """The HEML forces (N) at ``x`` on the ``held`` vertices, exactly (from every tet that
    touches one), into ``f``; ``f`` is zero or partial elsewhere. The reaction on held
    vertices needs no more: a tenth of the tets of the lobe, or fewer."""
    subset_forces(x, f, tets_touching(held, body, law), law)


_FAST = {"reassoc", "contract", "nsz", "arcp"}  # lets the dot products vectorise


@nb.njit(cache=True, fastmath=_FAST)
def _dot(a, b):
    """``sum a * b`` over two ``(n, 3)`` arrays."""
    af = a.reshape(-1)
    bf = b.reshape(-1)
    total = 0.0
    for i in range(af.shape[0]):
        total += af[i] * bf[i]
    return total


@nb.njit(cache=True, fastmath=_FAST)
def _axpy(alpha, x, y):
    """``y += alpha x`` over two ``(n, 3)`` arrays, in place."""
    xf = x.reshape(-1)
    yf = y.reshape(-1)
    for i in range(xf.shape[0]):
        yf[i] += alpha * xf[i]


@nb.njit(cache=True)
def _positive_volumes(x, tets, inv_det, vt_ptr, vt_tets, moved):
    """True when every tet touching a ``moved`` vertex keeps a positive volume at ``x``."""
    for i in range(moved.shape[0]):
        if not moved[i]:
            continue
        for k in range(vt_ptr[i], vt_ptr[i + 1]):
            t = vt_tets[k]
            i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
            ax, ay, az = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
            bx, by, bz = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
            cx, cy, cz = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
            det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
            if not det * inv_det[t] > 0.0:
                return False
    return True


# ----------------------------------------------------------------------- one world
@nb.njit(cache=True)
def begin_substep(x, v, targets, holds, ext, body, law, sub, history, r_prev, work):
    """What a sub-step of length ``h`` (s) needs before its minimisation, whichever method
    minimises (L-BFGS, or Newton as the fallback): fills in ``work`` (:class:`SubstepWork`) the step's start
    ``x_n, v_n``, BDF2's state one step back ``x_m, v_m``, the inertial target ``x_hat``,
    the ``load`` (N: external forces ``ext`` and weight), the ``held`` mask (held exactly
    or fixed) and the held vertices' ``jump`` beyond their own predictor;
    moves the exactly held vertices of ``holds`` (:class:`Holds`) a ``fraction`` of the way to
    their ``targets`` in ``x``, and the anchors of the spring-held ones in ``holds.anchor``; at
    ``sub.first_substep`` puts the start's quasi-static holding force into ``r_prev``
    (``work.f``: scratch). Returns ``(c, any_jump)``: the inertia weight ``c`` (1/s^2, see
    :func:`inertia`) and whether any held vertex jumps.

    BDF2 reads the state one step back from ``history`` (:class:`Bdf2History`) when its
    ``history_h[0]`` is this step's length ``h``, else it expands the state about the step's start with its
    acceleration (``x_n-1 = x_n - h v_n + h^2 a_n / 2``, ``v_n-1 = v_n - h a_n``, supports
    aside): a start that keeps the scheme second order, at the cost of one force
    evaluation.
    """
    n = x.shape[0]
    h, fraction, order = sub.h, sub.fraction, sub.order
    alpha, mass, gravity, fixed = body.alpha, body.mass, body.gravity, body.fixed
    x_n, v_n, x_m, v_m, x_hat, load, held, jump, f = work
    kinematic, spring, anchor = holds.kinematic, holds.stiffness, holds.anchor
    c = inertia(order, h, alpha)
    x_n[:, :] = x
    v_n[:, :] = v
    for i in range(n):
        held[i] = (kinematic[i] and spring[i] == 0.0) or fixed[i]
        for d in range(3):
            load[i, d] = ext[i, d] + mass[i] * gravity[d]
    if order == 2 and history.history_h[0] == h:
        x_m[:, :] = history.x_prev
        v_m[:, :] = history.v_prev
    elif order == 2:
        elastic_forces(x, f, body, law)
        for i in range(n):
            for d in range(3):
                a0 = 0.0 if held[i] else (f[i, d] + load[i, d]) / mass[i] - alpha * v_n[i, d]
                x_m[i, d] = x_n[i, d] - h * v_n[i, d] + 0.5 * h * h * a0
                v_m[i, d] = v_n[i, d] - h * a0
    # the start's holding force: what held vertices need to stay put (quasi-static)
    if sub.first_substep:
        held_forces(x, f, held, body, law)
        for i in range(n):
            for d in range(3):
                if held[i]:
                    r_prev[i, d] = -(f[i, d] + load[i, d] - alpha * mass[i] * v[i, d])
                elif kinematic[i] and spring[i] > 0.0:  # the spring's pull on the tissue
                    r_prev[i, d] = spring[i] * (anchor[i, d] - x[i, d])
                else:
                    r_prev[i, d] = 0.0
    any_jump = False
    for i in range(n):
        for d in range(3):
            if order == 2:
                p_i = 4.0 * x_n[i, d] - x_m[i, d]
                q_i = 4.0 * v_n[i, d] - v_m[i, d]
                x_hat[i, d] = (0.75 * p_i / (h * h) + 0.5 * q_i / h + 0.5 * alpha * p_i / h) / c
            else:
                x_hat[i, d] = x_n[i, d] + h * v_n[i, d] / (1.0 + alpha * h)
            jump[i, d] = 0.0
        if kinematic[i] and spring[i] > 0.0 and not fixed[i]:  # the spring's anchor moves
            for d in range(3):
                anchor[i, d] += (targets[i, d] - anchor[i, d]) * fraction
        elif kinematic[i] and not fixed[i]:
            for d in range(3):
                xi = x[i, d] + (targets[i, d] - x[i, d]) * fraction
                jump[i, d] = xi - x_n[i, d] - h * v_n[i, d]
                any_jump = any_jump or jump[i, d] != 0.0
                x[i, d] = xi
    return c, any_jump


@nb.njit(cache=True)
def tool_contact_forces(x, held, supports, out):
    """``out (T, 3)`` = the force (N) of each rigid tool of a world's ``supports`` (its view:
    one row of poses) on the free vertices inside it at ``x`` (:func:`tool_penalty`'s;
    backward Euler's contact force at the step's end)."""
    out[:, :] = 0.0
    tool_penalty(x, False, out[:0], held, supports, out)


@nb.njit(cache=True)
def end_substep(x, v, work, dist, normal, n_supports, f_at_x, reaction, r_prev, body, law, sub, history, holds):
    """What a sub-step does after its minimisation reached ``x``, whichever method
    minimised: vertices inside a support (``dist``, ``normal``: the signed distances at
    ``x``) go onto it, unless that would turn a tet inside out (a sliver on the support),
    and lose their velocity into it; the velocities ``v`` follow from the scheme; the
    step-mean constraint force on held vertices is added into ``reaction`` (N) by the
    trapezoidal rule between ``r_prev`` (the start's) and the end's, which ``r_prev`` then
    holds (on a spring-held vertex of ``holds``, the spring's pull ``k (anchor - x)``);
    BDF2 keeps the step's start in ``history``. ``work``: the sub-step's
    (:func:`begin_substep`); its ``f``: the elastic forces at ``x`` if ``f_at_x``, else
    scratch.

    Held and fixed vertices follow their prescribed path, straight within a step and
    turning between steps (the gripper's commands): their velocity is the step's
    displacement over ``h`` and their inertia in the reaction ``m (v - v_n) / h`` under
    either scheme (BDF2's formula would read a turn as a spurious acceleration).
    """
    n = x.shape[0]
    x_n, v_n, x_m, held, load, f = work.x_n, work.v_n, work.x_m, work.held, work.load, work.f
    mass, alpha, h, order = body.mass, body.alpha, sub.h, sub.order
    trial = np.empty((n, 3))
    inside = np.zeros(n, dtype=np.bool_)
    n_inside = 0
    for i in range(n):
        if n_supports > 0 and not held[i] and dist[i] < 0.0:
            inside[i] = True
            n_inside += 1
            for d in range(3):
                trial[i, d] = x[i, d] - dist[i] * normal[i, d]
        else:
            for d in range(3):
                trial[i, d] = x[i, d]
    moved = False
    if n_inside and _positive_volumes(trial, body.tets, body.inv_det, body.vt_ptr, body.vt_tets, inside):
        x[:, :] = trial
        moved = True
    for i in range(n):
        for d in range(3):
            if order == 2 and not held[i]:
                v[i, d] = (3.0 * x[i, d] - 4.0 * x_n[i, d] + x_m[i, d]) / (2.0 * h)
            else:
                v[i, d] = (x[i, d] - x_n[i, d]) / h
        if inside[i]:
            vn = min(v[i, 0] * normal[i, 0] + v[i, 1] * normal[i, 1] + v[i, 2] * normal[i, 2], 0.0)
            for d in range(3):
                v[i, d] -= vn * normal[i, d]
    # the constraint force on held vertices: m a minus every other force on them
    if moved or not f_at_x:
        held_forces(x, f, held, body, law)
    for i in range(n):
        if held[i]:
            for d in range(3):
                r_end = mass[i] * (v[i, d] - v_n[i, d]) / h - (f[i, d] + load[i, d] - alpha * mass[i] * v[i, d])
                reaction[i, d] += 0.5 * (r_prev[i, d] + r_end)
                r_prev[i, d] = r_end
        elif holds.kinematic[i] and holds.stiffness[i] > 0.0:
            for d in range(3):
                r_end = holds.stiffness[i] * (holds.anchor[i, d] - x[i, d])
                reaction[i, d] += 0.5 * (r_prev[i, d] + r_end)
                r_prev[i, d] = r_end
        else:
            for d in range(3):
                r_prev[i, d] = 0.0
    if order == 2:
        history.x_prev[:, :] = x_n
        history.v_prev[:, :] = v_n
        history.history_h[0] = h


@nb.njit(cache=True)
def _lbfgs_world(x, v, targets, holds, ext, body, law, supports, hessian, memory, tol, sub, history, r_prev,
                 reaction, out, wrist, tool_force):
    """One backward Euler (``sub.order`` 1) or BDF2 (2) sub-step of one world by L-BFGS, in
    place on ``x, v`` ``(n, 3)``: :func:`begin_substep`, L-BFGS from the best of four
    starts, :func:`end_substep`. ``body``, ``law``, ``supports``: the model's (see
    :mod:`heml_gym.kernel_data`); ``hessian``: the world's :class:`WorldHessian`;
    ``memory``: its :class:`LbfgsMemory`; ``history``: its :class:`Bdf2History`; ``tol``:
    the force residual (N) to reach.

    Held vertices (``holds``, :class:`Holds`) move a ``sub.fraction`` of the way from where
    they are to their ``targets`` (the anchors of spring-held ones do); fixed ones stay. The free vertices start from the explicit
    predictor plus the linear response (through the initial Hessian) of the held
    vertices' jump beyond it, else from where they are. ``reaction`` (N) receives the
    step-mean constraint force on held and fixed vertices of this sub-step (see
    :func:`end_substep`). ``out`` receives ``(iterations, residual (N), converged,
    feasible)``.

    A free wrist (``wrist``, :class:`~.kernels_wrist.Wrist`): its patch (held) is turned,
    in every evaluation of the potential, to the angle where the tissue's torque on it
    vanishes (:func:`~.kernels_wrist.settle`); the sub-step ends at that angle.
    """
    n = x.shape[0]
    h = sub.h
    work = substep_work(n, sub.order)
    x_n, v_n, held, jump, f = work.x_n, work.v_n, work.held, work.jump, work.f
    c, any_jump = begin_substep(x, v, targets, holds, ext, body, law, sub, history, r_prev, work)
    has_wrist = False
    for i in range(n):
        has_wrist = has_wrist or wrist.turns[i]
    if has_wrist:
        any_jump = begin_wrist(x, x_n, v_n, jump, h, sub.fraction, wrist)
    patch = tets_touching(wrist.turns if has_wrist else wrist.turns[:0], body, law)  # (none without a wrist)
    scale = radius(wrist) if has_wrist else 1.0
    wrist_tol = 1e-3 * tol  # |dPhi/ds| (N): far below the free vertices' tolerance
    f_wrist = np.zeros((n, 3)) if has_wrist else np.zeros((0, 3))
    k_contact = sub.kappa * c
    n_supports = supports.planes.shape[0] + supports.grids.shape[0]
    g = np.zeros((n, 3))
    g_new = np.zeros((n, 3))
    d_vec = np.empty((n, 3))
    trial = np.empty((n, 3))
    response = np.zeros((n, 3))
    dist = np.full(n, math.inf)
    normal = np.zeros((n, 3))
    nd = hessian.first.shape[0]
    b = np.empty((3, nd), dtype=np.float32)  # the preconditioner's solves run in the
    y = np.empty((3, nd), dtype=np.float32)  # factor's precision: 8 lanes on AVX2
    s_hist, y_hist, rho = memory.s_hist, memory.y_hist, memory.rho
    history_len = rho.shape[0]
    a_coef = np.zeros(history_len)
    if any_jump:  # -A_ff^-1 A_fh jump: the free vertices follow the held ones smoothly
        edge_i, edge_j, edge_w, stiffness = hessian.edge_i, hessian.edge_j, hessian.edge_w, hessian.stiffness
        for e in range(edge_i.shape[0]):
            i = edge_i[e]
            j = edge_j[e]
            if held[i] != held[j]:
                we = stiffness * edge_w[e]
                if held[j]:
                    for d in range(3):
                        g[i, d] += we * jump[j, d]
                else:
                    for d in range(3):
                        g[j, d] += we * jump[i, d]
        _precondition(g, response, held, hessian, b, y)
    args = (body, law, supports, c, work.x_hat, work.load, held, k_contact, holds)
    phi = math.inf
    for attempt in range(4):  # predictor + response, predictor, start + response, start
        for i in range(n):
            for d in range(3):
                trial[i, d] = x[i, d]
                if not held[i]:
                    if attempt < 2:
                        trial[i, d] = x_n[i, d] + h * v_n[i, d]
                    if attempt % 2 == 0:
                        trial[i, d] += response[i, d]
        phi = _reduced_potential(trial, g, f, dist, normal, args, has_wrist, wrist, patch, law, f_wrist, scale,
                                 wrist_tol)
        if math.isfinite(phi):
            break
    if not math.isfinite(phi):
        out[0], out[1], out[2], out[3] = 0.0, math.inf, 0.0, 0.0
        return
    x[:, :] = trial
    angle_at_x = wrist.angle[0]  # (the wrist's angle at x: trials the line search rejects move it)
    last_at_x = True  # ``f`` holds the elastic forces at ``x``
    gnorm = math.sqrt(_dot(g, g))
    stored = memory.memory[0]  # curvature pairs kept from the world's earlier steps (same initial Hessian)
    newest = memory.memory[1]
    it = 0
    while gnorm > tol and it < sub.max_iter:
        it += 1
        # two-loop recursion: d = -H g
        d_vec[:, :] = g
        k = newest
        for _ in range(stored):
            a_coef[k] = rho[k] * _dot(s_hist[k], d_vec)
            _axpy(-a_coef[k], y_hist[k], d_vec)
            k = (k - 1) % history_len
        _precondition(d_vec, trial, held, hessian, b, y)
        d_vec[:, :] = trial
        k = (newest - stored + 1) % history_len
        for _ in range(stored):
            b_coef = rho[k] * _dot(y_hist[k], d_vec)
            _axpy(a_coef[k] - b_coef, s_hist[k], d_vec)
            k = (k + 1) % history_len
        d_vec *= -1.0
        slope = _dot(g, d_vec)
        if not slope < 0.0:  # not a descent direction: restart from the initial Hessian
            stored = 0
            _precondition(g, d_vec, held, hessian, b, y)
            d_vec *= -1.0
            slope = _dot(g, d_vec)
            if not slope < 0.0:
                break
        step = 1.0
        accepted = False
        phi_t = phi
        for _ in range(40):
            for i in range(n):
                for dd in range(3):
                    trial[i, dd] = x[i, dd] + step * d_vec[i, dd]
            phi_t = _reduced_potential(trial, g_new, f, dist, normal, args, has_wrist, wrist, patch, law, f_wrist,
                                       scale, wrist_tol)
            if math.isfinite(phi_t):
                # Armijo on the potential or, near convergence where its round-off hides the
                # decrease, a smaller residual (as Newton's line search)
                if phi_t <= phi + 1e-4 * step * slope or math.sqrt(_dot(g_new, g_new)) < (1.0 - 1e-4 * step) * gnorm:
                    accepted = True
                    break
            step *= 0.5
        if not accepted:
            # no progress possible at this precision: keep the best iterate (its distances)
            potential_and_gradient(x, False, g_new, f, dist, normal, *args)
            last_at_x = False
            break
        phi = phi_t
        angle_at_x = wrist.angle[0]
        newest = (newest + 1) % history_len
        for i in range(n):
            for dd in range(3):
                s_hist[newest, i, dd] = trial[i, dd] - x[i, dd]
                y_hist[newest, i, dd] = g_new[i, dd] - g[i, dd]
        if has_wrist:  # (its turn moves held vertices: L-BFGS's pairs are of the free ones)
            for i in range(n):
                if held[i]:
                    for dd in range(3):
                        s_hist[newest, i, dd] = 0.0
        sy = _dot(s_hist[newest], y_hist[newest])
        if sy > 1e-300:
            rho[newest] = 1.0 / sy
            stored = min(stored + 1, history_len)
        else:
            newest = (newest - 1) % history_len
        x[:, :] = trial
        g[:, :] = g_new
        gnorm = math.sqrt(_dot(g, g))
    if has_wrist:
        wrist.angle[0] = angle_at_x
    if supports.tool_kind.shape[0]:
        tool_contact_forces(x, held, supports, tool_force)
    end_substep(x, v, work, dist, normal, n_supports, last_at_x, reaction, r_prev, body, law, sub, history, holds)
    memory.memory[0] = stored
    memory.memory[1] = newest
    out[0], out[1], out[2], out[3] = float(it), gnorm, 1.0 if gnorm <= tol else 0.0, 1.0


@nb.njit(cache=True, inline="always")
def _reduced_potential(trial, g, f, dist, normal, args, has_wrist, wrist, patch, law, f_wrist, scale, wrist_tol):
    """:func:`potential_and_gradient` (with the gradient) at ``trial``, its wrist's patch
    first turned to where the torque on it vanishes (:func:`~.kernels_wrist.settle`)."""
    if has_wrist and not math.isfinite(settle(trial, wrist, patch, law, f_wrist, scale, wrist_tol, 50)):
        return math.inf
    return potential_and_gradient(trial, True, g, f, dist, normal, *args)


@nb.njit(cache=True, inline="always")
def _world_step(s, x, v, targets, holds, ext, body, laws, supports, hessians, memory, tol, sub, history, r_prev,
                reaction, out, wrist, tool_force):
    """:func:`_lbfgs_world` of world ``s`` of the stacked bundles."""
    _lbfgs_world(x[s], v[s], targets[s], Holds(holds.kinematic[s], holds.stiffness[s], holds.anchor[s]), ext[s],
                 body, world_law(laws, s), world_supports(supports, s),
                 world_hessian(hessians, s),
                 LbfgsMemory(memory.s_hist[s], memory.y_hist[s], memory.rho[s], memory.memory[s]), tol[s], sub,
                 Bdf2History(history.x_prev[s], history.v_prev[s], history.history_h[s:s + 1]), r_prev[s],
                 reaction[s], out[s], world_wrist(wrist, s), tool_force[s])


@nb.njit(cache=True, parallel=True)
def lbfgs_steps_parallel(x, v, targets, holds, ext, body, laws, supports, hessians, memory, tol, sub, history,
                         active, r_prev, reaction, out, wrist, tool_force):
    """:func:`_lbfgs_world` for every ``active`` world (leading axis N of the arrays and of
    ``laws`` (:class:`~heml_gym.kernel_data.HemlLaws`), ``hessians``
    (:class:`InitialHessians`), ``memory`` (:class:`LbfgsMemory`), ``history``
    (:class:`Bdf2History`), ``wrist`` (:class:`~.kernels_wrist.Wrist`)), worlds over
    threads; world ``s`` preconditions with its current initial Hessian
    ``hessians.values[s, hessians.entry[s]]``. ``tool_force (N, T, 3)`` receives each
    rigid tool's force on the tissue at the sub-step's end (:func:`tool_contact_forces`)."""
    for s in prange(x.shape[0]):
        if active[s]:
            _world_step(s, x, v, targets, holds, ext, body, laws, supports, hessians, memory, tol, sub, history,
                        r_prev, reaction, out, wrist, tool_force)


@nb.njit(cache=True)
def lbfgs_steps_serial(x, v, targets, holds, ext, body, laws, supports, hessians, memory, tol, sub, history,
                       active, r_prev, reaction, out, wrist, tool_force):
    """:func:`lbfgs_steps_parallel` world after world."""
    for s in range(x.shape[0]):
        if active[s]:
            _world_step(s, x, v, targets, holds, ext, body, laws, supports, hessians, memory, tol, sub, history,
                        r_prev, reaction, out, wrist, tool_force)


@nb.njit(cache=True)
def count_report(run, out, iterations, residual, converged, feasible):
    """Add one call's ``out (N, 4)`` report (iterations, force residual N, converged,
    feasible start) of the ``run`` worlds into the step's ``iterations``, ``residual``
    (the largest, NaN kept), ``converged`` and ``feasible`` (in place)."""
    for s in range(run.shape[0]):
        if not run[s]:
            continue
        iterations[s] += np.int64(out[s, 0])
        r = out[s, 1]
        if not np.isnan(residual[s]) and (np.isnan(r) or r > residual[s]):
            residual[s] = r
        if not out[s, 2] > 0.5:
            converged[s] = False
        if not out[s, 3] > 0.5:
            feasible[s] = False
