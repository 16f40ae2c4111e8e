"""Numba kernels of the explicit (symplectic Euler) solver.

One update serves every path: :func:`integrate_dof` advances one coordinate of one
vertex (free, or held on a path or fixed; :func:`free_dof` and :func:`held_dof` are it
for a vertex whose kind is known) and :func:`~heml_gym.kernels_contact.project_out_of_supports`
keeps free vertices out of the supports; the kernels below differ only in how they get
the elastic forces and how they lay out the worlds:

* :func:`symplectic_euler_update`: one sub-step of one world given its forces (any field);
* :func:`split_substeps_serial` / ``_parallel``: all sub-steps of N worlds of a law with
  constant ``Psi_1`` (Neo-Hookean HEML), per-world spring weights, one call;
* :func:`heml_substeps_serial` / ``_parallel``: the same for any law (per-world law and
  constants);
* :func:`lane_substeps`: Neo-Hookean HEML worlds in lockstep, vectorised across worlds
  (state stored world-last, blocks of up to :data:`LANES` worlds, one per thread).

Units: m, s, kg, N, Pa. Every kernel reports per world the first vertex found
non-finite or faster than ``max_speed`` (m/s), or -1.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from numba import prange

from ..fastlog import SMALLEST_NORMAL
from ..forces.kernels_heml import (
    _store_tet_forces,
    constant_psi1_forces_chunk,
    edge_cofactors,
    edge_vectors,
    heml_forces_chunk,
)
from ..kernels_contact import (axis_plane_contact, plane_axis, plane_contact, project_free_vertices,
                               project_out_of_supports)
from ..laws import volumetric_gradient_fast

#: worlds per block of :func:`lane_substeps` (SIMD lanes); its arrays end in it
LANES = 32


class ExplicitWorlds(NamedTuple):
    """The N worlds' arrays of a fused explicit step (leading axis N): ``x, v`` (m, m/s),
    ``f``, ``sub_reaction`` scratch, ``reaction`` (N: the constraint forces averaged over
    the sub-steps), ``ext`` (N), ``kinematic`` (N, n) held vertices moved from
    ``kin_from`` to ``kin_to`` (m) over the sub-steps."""

    x: np.ndarray
    v: np.ndarray
    f: np.ndarray
    reaction: np.ndarray
    sub_reaction: np.ndarray
    ext: np.ndarray
    kinematic: np.ndarray
    kin_from: np.ndarray
    kin_to: np.ndarray


class LaneWorlds(NamedTuple):
    """Worlds in blocks of ``L`` lanes (see :func:`lane_substeps`): ``x, v, f, reaction,
    ext, kin_from, kin_to`` ``(B, n, 3, L)``, ``kinematic`` ``(B, n, L)``, the Neo-Hookean
    constants ``p0, p1`` and ``psi1`` (Pa) ``(B, L)``, and the report ``bad_vertex (B, L)``."""

    x: np.ndarray
    v: np.ndarray
    f: np.ndarray
    reaction: np.ndarray
    ext: np.ndarray
    kinematic: np.ndarray
    kin_from: np.ndarray
    kin_to: np.ndarray
    p0: np.ndarray
    p1: np.ndarray
    psi1: np.ndarray
    bad_vertex: np.ndarray


class ExplicitStep(NamedTuple):
    """``n_sub`` sub-steps of ``h`` s; a vertex faster than ``max_speed`` (m/s) is flagged."""

    h: float
    n_sub: int
    max_speed: float


@nb.njit(cache=True, inline="always")
def total_force(f, ext, m, g, alpha, v):
    """Elastic + external + gravity + mass-proportional damping force (N) on one coordinate."""
    return f + ext + m * g - alpha * m * v


@nb.njit(cache=True, inline="always")
def integrate_dof(x, v, force, m, h, held, target):
    """One symplectic Euler sub-step of length ``h`` (s) of one coordinate of one vertex.

    A free vertex: ``v += h force / m``, then ``x += h v``. A held one (kinematic, or
    fixed with ``target = x``) moves to ``target`` with the velocity that takes it there.
    Returns ``(x, v, reaction)``: ``reaction`` (N) is the constraint force on a held
    vertex (``m a`` minus every other force), 0 on a free one. Written with selects only,
    so that a loop over worlds around it vectorises.
    """
    vn = (target - x) / h if held else v + h * force / m
    reaction = m * (vn - v) / h - force if held else 0.0
    xn = target if held else x + h * vn
    return xn, vn, reaction


@nb.njit(cache=True, inline="always")
def free_dof(x, v, force, m, h):
    """:func:`integrate_dof` of a free vertex: ``(x, v)``."""
    xn, vn, _ = integrate_dof(x, v, force, m, h, False, 0.0)
    return xn, vn


@nb.njit(cache=True, inline="always")
def held_dof(x, v, force, m, h, target):
    """:func:`integrate_dof` of a held vertex: ``(x, v, reaction)``."""
    return integrate_dof(x, v, force, m, h, True, target)


@nb.njit(cache=True, inline="always")
def _flagged(vx, vy, vz, px, py, pz, limit):
    """Whether a vertex is non-finite, exploded or faster than ``sqrt(limit)`` m/s."""
    speed2 = vx * vx + vy * vy + vz * vz
    return not (speed2 <= limit and abs(px) + abs(py) + abs(pz) < 1e300)


@nb.njit(cache=True)
def symplectic_euler_update(x, v, f, mass, gravity, ext, alpha, h, fixed, kinematic,
                            kin_from, kin_to, frac, max_speed, reaction, supports):
    """One symplectic Euler sub-step of one world, in place, given its elastic forces ``f`` (N).

    ``x, v, f, ext, kin_from, kin_to, reaction``: ``(n, 3)``; ``fixed``, ``kinematic``:
    ``(n,)`` masks. Fixed vertices keep ``x`` and get ``v = 0``; kinematic ones move to
    ``kin_from + frac (kin_to - kin_from)``; free ones integrate and are kept out of the
    ``supports`` (:class:`~heml_gym.kernel_data.SupportArrays`). ``reaction`` receives
    the constraint force (N) on held vertices, 0 elsewhere. Returns the first vertex that
    went non-finite or too fast, or -1.
    """
    n = x.shape[0]
    limit = max_speed * max_speed
    bad = -1
    for i in range(n):
        m = mass[i]
        if fixed[i] or kinematic[i]:
            for d in range(3):
                xd = x[i, d]
                target = xd if fixed[i] else kin_from[i, d] + frac * (kin_to[i, d] - kin_from[i, d])
                force = total_force(f[i, d], ext[i, d], m, gravity[d], alpha, v[i, d])
                x[i, d], v[i, d], reaction[i, d] = held_dof(xd, v[i, d], force, m, h, target)
        else:
            for d in range(3):
                force = total_force(f[i, d], ext[i, d], m, gravity[d], alpha, v[i, d])
                x[i, d], v[i, d] = free_dof(x[i, d], v[i, d], force, m, h)
                reaction[i, d] = 0.0
        # checked before the supports: their projection removes speed and moves a vertex by
        # at most its depth, so it cannot turn a good vertex bad
        if bad < 0 and _flagged(v[i, 0], v[i, 1], v[i, 2], x[i, 0], x[i, 1], x[i, 2], limit):
            bad = i
    if supports.planes.shape[0] + supports.grids.shape[0]:
        project_free_vertices(x, v, fixed, kinematic, supports.planes, supports.grids, supports.grid_values)
    return bad


@nb.njit(cache=True, inline="always")
def _add_mean_reaction(reaction, sub_reaction, fixed, kinematic, n_sub):
    for i in range(reaction.shape[0]):
        if fixed[i] or kinematic[i]:
            for d in range(3):
                reaction[i, d] += sub_reaction[i, d] / n_sub


# ------------------------------------------------------- fused kernels, world by world
@nb.njit(cache=True, inline="always")
def _update_world(s, k, worlds, body, supports, step):
    """Sub-step ``k`` (1..n_sub) of world ``s`` from its elastic forces ``worlds.f[s]``:
    the update and the reaction's mean; returns the first bad vertex or -1."""
    kinematic = worlds.kinematic[s]
    n_sub = step.n_sub
    bad = symplectic_euler_update(worlds.x[s], worlds.v[s], worlds.f[s], body.mass, body.gravity, worlds.ext[s],
                                  body.alpha, step.h, body.fixed, kinematic, worlds.kin_from[s], worlds.kin_to[s],
                                  k / n_sub, step.max_speed, worlds.sub_reaction[s], supports)
    if bad < 0:
        _add_mean_reaction(worlds.reaction[s], worlds.sub_reaction[s], body.fixed, kinematic, n_sub)
    return bad


@nb.njit(cache=True, inline="always")
def _split_world(s, worlds, body, laws, supports, step):
    xs, fs = worlds.x[s], worlds.f[s]
    tets = body.tets
    worlds.reaction[s][:, :] = 0.0
    for k in range(1, step.n_sub + 1):
        fs[:, :] = 0.0
        constant_psi1_forces_chunk(xs, tets, body.inv_det, laws.weights[s], laws.law[s], laws.params[s], fs, 0,
                                   tets.shape[0])
        bad = _update_world(s, k, worlds, body, supports, step)
        if bad >= 0:
            return bad
    return -1


@nb.njit(cache=True, inline="always")
def _heml_world(s, worlds, body, laws, supports, step):
    xs, fs = worlds.x[s], worlds.f[s]
    tets = body.tets
    worlds.reaction[s][:, :] = 0.0
    for k in range(1, step.n_sub + 1):
        fs[:, :] = 0.0
        heml_forces_chunk(xs, tets, body.coef_t, laws.q_t, laws.use_q, laws.law[s], laws.params[s], fs, 0,
                          tets.shape[0])
        bad = _update_world(s, k, worlds, body, supports, step)
        if bad >= 0:
            return bad
    return -1


@nb.njit(cache=True)
def split_substeps_serial(worlds, body, laws, supports, step, active, bad):
    """``step.n_sub`` sub-steps of length ``step.h`` (s) of every ``active`` world of a
    constant-``Psi_1`` HEML body (Neo-Hookean: ``laws.split``, the forces from the
    per-world spring weights), world after world, in place: ``worlds``
    (:class:`ExplicitWorlds`), the model's ``body`` and ``laws``
    (:class:`~heml_gym.kernel_data.HemlBody`, :class:`~heml_gym.kernel_data.HemlLaws`),
    ``supports`` (:class:`~heml_gym.kernel_data.SupportArrays`), ``step``
    (:class:`ExplicitStep`). ``bad[s]``: the first bad vertex of world ``s`` (its
    integration stopped there) or -1.
    """
    for s in range(worlds.x.shape[0]):
        bad[s] = -1
        if active[s]:
            bad[s] = _split_world(s, worlds, body, laws, supports, step)


@nb.njit(cache=True, parallel=True)
def split_substeps_parallel(worlds, body, laws, supports, step, active, bad):
    """:func:`split_substeps_serial` with the worlds spread over the threads."""
    for s in prange(worlds.x.shape[0]):
        bad[s] = -1
        if active[s]:
            bad[s] = _split_world(s, worlds, body, laws, supports, step)


@nb.njit(cache=True)
def heml_substeps_serial(worlds, body, laws, supports, step, active, bad):
    """As :func:`split_substeps_serial` for any law (per-world law and constants)."""
    for s in range(worlds.x.shape[0]):
        bad[s] = -1
        if active[s]:
            bad[s] = _heml_world(s, worlds, body, laws, supports, step)


@nb.njit(cache=True, parallel=True)
def heml_substeps_parallel(worlds, body, laws, supports, step, active, bad):
    """:func:`heml_substeps_serial` with the worlds spread over the threads."""
    for s in prange(worlds.x.shape[0]):
        bad[s] = -1
        if active[s]:
            bad[s] = _heml_world(s, worlds, body, laws, supports, step)


# --------------------------------------------------- worlds in lockstep, across lanes
@nb.njit(cache=True, parallel=True, error_model="numpy", fastmath={"contract"})
def lane_substeps(lanes_, body, law, supports, step):
    """``n_sub`` sub-steps of length ``h`` (s) of Neo-Hookean HEML worlds, vectorised across
    worlds: ``lanes_`` (:class:`LaneWorlds`), the model's ``body``
    (:class:`~heml_gym.kernel_data.HemlBody`), the law id ``law``, ``supports``
    (:class:`~heml_gym.kernel_data.SupportArrays`), ``step`` (:class:`ExplicitStep`).

    Worlds come in blocks of ``L`` <= :data:`LANES`: ``x, v, f, reaction, ext, kin_from,
    kin_to`` are ``(B, n, 3, L)`` (m, m/s, N, N, N, m, m), entry ``[b, i, d, q]`` being
    vertex ``i``, axis ``d`` of world ``b L + q``; ``kinematic``: ``(B, n, L)`` held
    vertices, moved from ``kin_from`` to ``kin_to`` over the sub-steps; ``body.fixed``:
    ``(n,)``, shared; ``body.edge_weights``: ``(6, m)`` ``2 V0 a_k`` (m^3); ``psi1``:
    ``(B, L)`` the constant ``Psi_1`` (Pa) of each world, so its spring weights are
    ``psi1 * base_w``; ``p0, p1``: ``(B, L)`` its Neo-Hookean constants (Pa). The update
    per vertex is :func:`integrate_dof` and the supports' projection, as in every path.

    ``reaction`` receives the constraint forces (N) on fixed and held vertices averaged
    over the sub-steps. ``bad_vertex[b, q]`` becomes the first vertex of the world found
    non-finite or faster than ``max_speed`` (m/s), else -1. A tet whose J is not
    positive, normal and finite gives NaN forces (Neo-Hookean is undefined there), so
    such a world is flagged too. Worlds run in lockstep: a flagged world keeps being
    integrated (its values are meaningless; the caller restores it).
    """
    x, v, f, reaction, ext, kinematic, kin_from, kin_to, p0, p1, psi1, bad_vertex = lanes_
    tets, inv_det, base_w, mass, gravity = body.tets, body.inv_det, body.edge_weights, body.mass, body.gravity
    alpha, fixed = body.alpha, body.fixed
    planes, grids, grid_values = supports.planes, supports.grids, supports.grid_values
    h, n_sub, max_speed = step
    n_blocks, n, _, lanes = x.shape
    if lanes > LANES:
        raise ValueError("too many worlds per block")
    m = tets.shape[0]
    limit = max_speed * max_speed
    n_planes = planes.shape[0]
    n_grids = grids.shape[0]
    for b in prange(n_blocks):
        xb, vb, fb, rb, eb = x[b], v[b], f[b], reaction[b], ext[b]
        held, start, end = kinematic[b], kin_from[b], kin_to[b]
        p0b, p1b, psi1b, bad = p0[b], p1[b], psi1[b], bad_vertex[b]
        edges = np.empty((9, LANES))
        work = np.empty((12, LANES))
        speed2 = np.empty(LANES)
        size = np.empty(LANES)
        for q in range(lanes):
            bad[q] = -1
        rb[:] = 0.0
        inv_n = 1.0 / n_sub
        for k in range(1, n_sub + 1):
            frac = k / n_sub
            fb[:] = 0.0
            for t in range(m):
                i0 = tets[t, 0]
                i1 = tets[t, 1]
                i2 = tets[t, 2]
                i3 = tets[t, 3]
                for d in range(3):
                    for q in range(lanes):
                        x0 = xb[i0, d, q]
                        edges[d, q] = xb[i1, d, q] - x0
                        edges[3 + d, q] = xb[i2, d, q] - x0
                        edges[6 + d, q] = xb[i3, d, q] - x0
                idet = inv_det[t]
                w01 = base_w[0, t]
                w02 = base_w[1, t]
                w03 = base_w[2, t]
                w12 = base_w[3, t]
                w13 = base_w[4, t]
                w23 = base_w[5, t]
                for q in range(lanes):  # vectorises across worlds
                    ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, q)
                    c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
                    jac = (ax * c1x + ay * c1y + az * c1z) * idet
                    good = jac >= SMALLEST_NORMAL and jac < math.inf
                    g = volumetric_gradient_fast(law, p0b[q], p1b[q], jac if good else 1.0) * (1.0 / 6.0)
                    g = g if good else math.nan
                    c = psi1b[q]
                    _store_tet_forces(work, q, (ax, ay, az, bx, by, bz, cx, cy, cz),
                                      (c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g, c3x * g, c3y * g, c3z * g),
                                      (c * w01, c * w02, c * w03, c * w12, c * w13, c * w23))
                for d in range(3):  # one loop per vertex: no possible overlap to check
                    for q in range(lanes):
                        fb[i0, d, q] += work[d, q]
                    for q in range(lanes):
                        fb[i1, d, q] += work[3 + d, q]
                    for q in range(lanes):
                        fb[i2, d, q] += work[6 + d, q]
                    for q in range(lanes):
                        fb[i3, d, q] += work[9 + d, q]
            for i in range(n):
                mi = mass[i]
                if fixed[i]:
                    for d in range(3):
                        gd = gravity[d]
                        for q in range(lanes):  # vectorises across worlds
                            vq = vb[i, d, q]
                            xq = xb[i, d, q]
                            force = total_force(fb[i, d, q], eb[i, d, q], mi, gd, alpha, vq)
                            xn, vn, r = held_dof(xq, vq, force, mi, h, xq)
                            rb[i, d, q] += r * inv_n
                            vb[i, d, q] = vn
                    continue
                speed2[:] = 0.0
                size[:] = 0.0
                for d in range(3):
                    gd = gravity[d]
                    for q in range(lanes):  # vectorises across worlds (selects, no branches)
                        vq = vb[i, d, q]
                        xq = xb[i, d, q]
                        force = total_force(fb[i, d, q], eb[i, d, q], mi, gd, alpha, vq)
                        target = start[i, d, q] + frac * (end[i, d, q] - start[i, d, q])
                        xn, vn, r = integrate_dof(xq, vq, force, mi, h, held[i, q], target)
                        rb[i, d, q] += r * inv_n
                        xb[i, d, q] = xn
                        vb[i, d, q] = vn
                        speed2[q] += vn * vn
                        size[q] += abs(xn)
                # flagged before the supports: their projection cannot turn a good vertex bad
                for q in range(lanes):
                    flagged = not (speed2[q] <= limit and size[q] < 1e300)
                    bad[q] = i if (flagged and bad[q] < 0) else bad[q]
                for s in range(n_planes):
                    nx, ny, nz, c = planes[s, 0], planes[s, 1], planes[s, 2], planes[s, 3]
                    axis = plane_axis(nx, ny, nz)
                    if axis >= 0:  # an axis-aligned plane: one coordinate
                        sign = planes[s, axis]
                        for q in range(lanes):  # vectorises across worlds
                            p, w = axis_plane_contact(sign, c, xb[i, axis, q], vb[i, axis, q])
                            free = not held[i, q]
                            xb[i, axis, q] = p if free else xb[i, axis, q]
                            vb[i, axis, q] = w if free else vb[i, axis, q]
                        continue
                    for q in range(lanes):  # vectorises across worlds
                        px, py, pz, vx, vy, vz = plane_contact(nx, ny, nz, c, xb[i, 0, q], xb[i, 1, q], xb[i, 2, q],
                                                               vb[i, 0, q], vb[i, 1, q], vb[i, 2, q])
                        free = not held[i, q]
                        xb[i, 0, q] = px if free else xb[i, 0, q]
                        xb[i, 1, q] = py if free else xb[i, 1, q]
                        xb[i, 2, q] = pz if free else xb[i, 2, q]
                        vb[i, 0, q] = vx if free else vb[i, 0, q]
                        vb[i, 1, q] = vy if free else vb[i, 1, q]
                        vb[i, 2, q] = vz if free else vb[i, 2, q]
                if n_grids:
                    for q in range(lanes):
                        if not held[i, q]:
                            xb[i, 0, q], xb[i, 1, q], xb[i, 2, q], vb[i, 0, q], vb[i, 1, q], vb[i, 2, q] = \
                                project_out_of_supports(planes[:0], grids, grid_values, xb[i, 0, q], xb[i, 1, q],
                                                        xb[i, 2, q], vb[i, 0, q], vb[i, 1, q], vb[i, 2, q])

