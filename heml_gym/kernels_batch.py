"""Explicit sub-steps of many copies of one Neo-Hookean HEML body, vectorised across copies.

All copies (scenes) share the mesh, so tet ``t`` touches the same vertices in every
scene. The state is stored scene-last, ``x[i, d, s]`` (vertex, axis, scene), and the
innermost loops run over scenes: gathers and scatters become contiguous vector loads and
stores, with no index conflicts, and the arithmetic vectorises across scenes (SIMD
lanes). Scenes come in blocks of at most :data:`LANES`, one ``prange`` iteration each, so
threads never share a scene. The scratch buffers are :data:`LANES` wide, a compile-time
constant, on purpose: LLVM only vectorises the loops over lanes when their strides are
known.
Units: m, s, kg, N, Pa.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba import prange

from .fastlog import SMALLEST_NORMAL
from .forces.kernels_heml import _store_tet_forces, edge_cofactors, edge_vectors
from .laws import volumetric_gradient_fast

#: scenes per block (SIMD lanes); the arrays of :func:`lane_explicit_substeps` end in it
LANES = 32


@nb.njit(cache=True, parallel=True, error_model="numpy", fastmath={"contract"})
def lane_explicit_substeps(x, v, f, reaction, mass, gravity, ext, alpha, h, n_sub, fixed,
                           kinematic, kin_from, kin_to, max_speed, tets, inv_det, base_w, law,
                           p0, p1, psi1, bad_vertex, floor_z):
    """``n_sub`` symplectic Euler sub-steps of length ``h`` (s) of every scene, in place.

    Scenes come in blocks of ``L`` <= :data:`LANES`: ``x, v, f, reaction, kin_from, kin_to`` are
    ``(B, n, 3, L)`` (m, m/s, N, N, m, m), entry ``[b, i, d, q]`` being vertex ``i``, axis
    ``d`` of scene ``b L + q``; ``kinematic``: ``(B, n, L)`` held vertices, moved from
    ``kin_from`` to ``kin_to`` over the sub-steps; ``fixed``: ``(n,)`` and ``ext``:
    ``(n, 3)`` external forces (N), shared; ``base_w``: ``(6, m)`` edge weights
    ``2 V0 a_k`` (m^3); ``psi1``: ``(B, L)`` the constant ``Psi_1`` (Pa) of each scene, so
    its spring weights are ``psi1 * base_w``; ``p0, p1``: ``(B, L)`` its Neo-Hookean
    parameters (Pa). The update per vertex, including the support plane ``z = floor_z``
    (m; ``-inf`` for none), is that of :func:`heml_gym.kernels_dynamics.symplectic_euler_update`.

    ``reaction`` receives the constraint forces (N) on fixed and held vertices averaged over
    the sub-steps (the impulse over the step divided by its length).

    ``bad_vertex[b, q]`` becomes the first vertex of the scene found non-finite or faster
    than ``max_speed`` (m/s), else -1. A tet whose J is not positive, normal and finite
    gives NaN forces (Neo-Hookean is undefined there), so such a scene is flagged too.
    Scenes run in lockstep: a flagged scene keeps being integrated (its values are
    meaningless; the caller restores it).
    """
    n_blocks, n, _, lanes = x.shape
    if lanes > LANES:
        raise ValueError("too many scenes per block")
    m = tets.shape[0]
    limit = max_speed * max_speed
    for b in prange(n_blocks):
        xb, vb, fb, rb = x[b], v[b], f[b], reaction[b]
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
                for q in range(lanes):  # vectorises across scenes
                    ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, q)
                    c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
                    jac = (ax * c1x + ay * c1y + az * c1z) * idet
                    good = jac >= SMALLEST_NORMAL and jac < math.inf
                    g = volumetric_gradient_fast(law, p0b[q], p1b[q], jac if good else 1.0) * (1.0 / 6.0)
                    g = g if good else math.nan
                    c = psi1b[q]
                    _store_tet_forces(work, q, ax, ay, az, bx, by, bz, cx, cy, cz,
                                      c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g,
                                      c3x * g, c3y * g, c3z * g,
                                      c * w01, c * w02, c * w03, c * w12, c * w13, c * w23)
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
                        const = ext[i, d] + mi * gravity[d]
                        for q in range(lanes):
                            vq = vb[i, d, q]
                            rb[i, d, q] += (-(fb[i, d, q] + const - alpha * mi * vq) - mi * vq / h) * inv_n
                            vb[i, d, q] = 0.0
                    continue
                speed2[:] = 0.0
                size[:] = 0.0
                for d in range(3):
                    const = ext[i, d] + mi * gravity[d]
                    for q in range(lanes):  # vectorises across scenes (selects, no branches)
                        vq = vb[i, d, q]
                        xq = xb[i, d, q]
                        total = fb[i, d, q] + const - alpha * mi * vq
                        target = start[i, d, q] + frac * (end[i, d, q] - start[i, d, q])
                        is_held = held[i, q]
                        vn = (target - xq) / h if is_held else vq + h * total / mi
                        rb[i, d, q] += (mi * (vn - vq) / h - total) * inv_n if is_held else 0.0
                        xn = target if is_held else xq + h * vn
                        below = d == 2 and xn < floor_z and not is_held  # resting on the support
                        xn = floor_z if below else xn
                        vn = max(vn, 0.0) if below else vn
                        vb[i, d, q] = vn
                        xb[i, d, q] = xn
                        speed2[q] += vn * vn
                        size[q] += abs(xn)
                for q in range(lanes):
                    flagged = not (speed2[q] <= limit and size[q] < 1e300)
                    bad[q] = i if (flagged and bad[q] < 0) else bad[q]
