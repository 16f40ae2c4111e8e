"""Numba kernels of the HEML force field (edge form of P1 hyperelasticity).

Per tet the precomputation stores ``coef[t] = (V0, 1/(6 V0), a_0..a_5)`` with
``a_k = tr A_k`` and, for laws that need ``I2``, ``q[t]`` = the 21 upper-triangle entries
of ``Q_kl = a_k a_l - tr(A_k A_l)``, where ``C = sum_k s_k A_k`` and ``s_k`` are the six
squared edge lengths in the order of :data:`heml_gym.mesh.EDGE_PAIRS`.

At run time, with ``e_k = x_b - x_a`` for edge ``k = (a, b)``:

* ``I1 = a . s``, ``I2 = s^T Q s / 2``, ``J = det(Ds) / (6 V0)``,
* edge weight ``w_k = 2 V0 (Psi_1 a_k + Psi_2 (Q s)_k)``: ``f_a += w_k e_k``, ``f_b -= w_k e_k``,
* volume term ``f_a -= Psi_J / 6 * d det(Ds) / d x_a`` (cross products of the edges).

Each kernel comes as a serial ``*_chunk`` over a range of tets and a ``*_parallel``
wrapper. The parallel one is race-free: tets are split into ``buf.shape[0]`` contiguous
chunks, each chunk adds into its own ``(n, 3)`` slice of ``buf``, and the slices are then
summed into ``buf[0]``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba import prange

from ..fastlog import SMALLEST_NORMAL
from ..laws import law_energy, law_gradient, volumetric_gradient_fast


@nb.njit(cache=True, inline="always")
def _qs(q, t, s0, s1, s2, s3, s4, s5):
    """``Q s`` for tet ``t`` with Q stored as 21 upper-triangle entries, row by row."""
    r = q[t]
    qs0 = r[0] * s0 + r[1] * s1 + r[2] * s2 + r[3] * s3 + r[4] * s4 + r[5] * s5
    qs1 = r[1] * s0 + r[6] * s1 + r[7] * s2 + r[8] * s3 + r[9] * s4 + r[10] * s5
    qs2 = r[2] * s0 + r[7] * s1 + r[11] * s2 + r[12] * s3 + r[13] * s4 + r[14] * s5
    qs3 = r[3] * s0 + r[8] * s1 + r[12] * s2 + r[15] * s3 + r[16] * s4 + r[17] * s5
    qs4 = r[4] * s0 + r[9] * s1 + r[13] * s2 + r[16] * s3 + r[18] * s4 + r[19] * s5
    qs5 = r[5] * s0 + r[10] * s1 + r[14] * s2 + r[17] * s3 + r[19] * s4 + r[20] * s5
    return qs0, qs1, qs2, qs3, qs4, qs5


@nb.njit(cache=True)
def heml_forces_chunk(x, tets, coef, q, use_q, law, p, f, lo, hi):
    """Add the HEML elastic forces (N) of tets ``lo..hi-1`` at positions ``x`` (m) into ``f``."""
    for t in range(lo, hi):
        i0 = tets[t, 0]
        i1 = tets[t, 1]
        i2 = tets[t, 2]
        i3 = tets[t, 3]
        x0x = x[i0, 0]
        x0y = x[i0, 1]
        x0z = x[i0, 2]
        x1x = x[i1, 0]
        x1y = x[i1, 1]
        x1z = x[i1, 2]
        x2x = x[i2, 0]
        x2y = x[i2, 1]
        x2z = x[i2, 2]
        x3x = x[i3, 0]
        x3y = x[i3, 1]
        x3z = x[i3, 2]
        # edge vectors e_k = x_b - x_a
        e01x = x1x - x0x
        e01y = x1y - x0y
        e01z = x1z - x0z
        e02x = x2x - x0x
        e02y = x2y - x0y
        e02z = x2z - x0z
        e03x = x3x - x0x
        e03y = x3y - x0y
        e03z = x3z - x0z
        e12x = x2x - x1x
        e12y = x2y - x1y
        e12z = x2z - x1z
        e13x = x3x - x1x
        e13y = x3y - x1y
        e13z = x3z - x1z
        e23x = x3x - x2x
        e23y = x3y - x2y
        e23z = x3z - x2z
        s0 = e01x * e01x + e01y * e01y + e01z * e01z
        s1 = e02x * e02x + e02y * e02y + e02z * e02z
        s2 = e03x * e03x + e03y * e03y + e03z * e03z
        s3 = e12x * e12x + e12y * e12y + e12z * e12z
        s4 = e13x * e13x + e13y * e13y + e13z * e13z
        s5 = e23x * e23x + e23y * e23y + e23z * e23z
        v0 = coef[t, 0]
        a0 = coef[t, 2]
        a1 = coef[t, 3]
        a2 = coef[t, 4]
        a3 = coef[t, 5]
        a4 = coef[t, 6]
        a5 = coef[t, 7]
        i_1 = a0 * s0 + a1 * s1 + a2 * s2 + a3 * s3 + a4 * s4 + a5 * s5
        # d det(Ds) / d x_1, x_2, x_3
        c1x = e02y * e03z - e02z * e03y
        c1y = e02z * e03x - e02x * e03z
        c1z = e02x * e03y - e02y * e03x
        c2x = e03y * e01z - e03z * e01y
        c2y = e03z * e01x - e03x * e01z
        c2z = e03x * e01y - e03y * e01x
        c3x = e01y * e02z - e01z * e02y
        c3y = e01z * e02x - e01x * e02z
        c3z = e01x * e02y - e01y * e02x
        jac = (e01x * c1x + e01y * c1y + e01z * c1z) * coef[t, 1]
        if use_q:
            qs0, qs1, qs2, qs3, qs4, qs5 = _qs(q, t, s0, s1, s2, s3, s4, s5)
            i_2 = 0.5 * (s0 * qs0 + s1 * qs1 + s2 * qs2 + s3 * qs3 + s4 * qs4 + s5 * qs5)
            d1, d2, dj = law_gradient(law, p, i_1, i_2, jac)
            v2 = 2.0 * v0
            w1 = v2 * d1
            w2 = v2 * d2
            w01 = w1 * a0 + w2 * qs0
            w02 = w1 * a1 + w2 * qs1
            w03 = w1 * a2 + w2 * qs2
            w12 = w1 * a3 + w2 * qs3
            w13 = w1 * a4 + w2 * qs4
            w23 = w1 * a5 + w2 * qs5
        else:
            d1, d2, dj = law_gradient(law, p, i_1, 0.0, jac)
            w1 = 2.0 * v0 * d1
            w01 = w1 * a0
            w02 = w1 * a1
            w03 = w1 * a2
            w12 = w1 * a3
            w13 = w1 * a4
            w23 = w1 * a5
        g = dj * (1.0 / 6.0)
        # edge forces: zero-rest-length springs with state-dependent weights
        e01x *= w01
        e01y *= w01
        e01z *= w01
        e02x *= w02
        e02y *= w02
        e02z *= w02
        e03x *= w03
        e03y *= w03
        e03z *= w03
        e12x *= w12
        e12y *= w12
        e12z *= w12
        e13x *= w13
        e13y *= w13
        e13z *= w13
        e23x *= w23
        e23y *= w23
        e23z *= w23
        c1x *= g
        c1y *= g
        c1z *= g
        c2x *= g
        c2y *= g
        c2z *= g
        c3x *= g
        c3y *= g
        c3z *= g
        f[i0, 0] += e01x + e02x + e03x + c1x + c2x + c3x
        f[i0, 1] += e01y + e02y + e03y + c1y + c2y + c3y
        f[i0, 2] += e01z + e02z + e03z + c1z + c2z + c3z
        f[i1, 0] += e12x + e13x - e01x - c1x
        f[i1, 1] += e12y + e13y - e01y - c1y
        f[i1, 2] += e12z + e13z - e01z - c1z
        f[i2, 0] += e23x - e02x - e12x - c2x
        f[i2, 1] += e23y - e02y - e12y - c2y
        f[i2, 2] += e23z - e02z - e12z - c2z
        f[i3, 0] -= e03x + e13x + e23x + c3x
        f[i3, 1] -= e03y + e13y + e23y + c3y
        f[i3, 2] -= e03z + e13z + e23z + c3z


@nb.njit(cache=True, parallel=True)
def heml_forces_parallel(x, tets, coef, q, use_q, law, p, buf):
    """HEML forces over all tets, one chunk per thread, summed into ``buf[0]`` (zero on entry)."""
    n_chunks = buf.shape[0]
    m = tets.shape[0]
    for c in prange(n_chunks):
        heml_forces_chunk(x, tets, coef, q, use_q, law, p, buf[c], c * m // n_chunks, (c + 1) * m // n_chunks)
    reduce_chunks(buf)


@nb.njit(cache=True)
def spring_network_chunk(x, edges, weights, f, lo, hi):
    """Add the fixed zero-rest-length springs ``f_i += w (x_j - x_i)``, ``f_j -= ...`` (N).

    For a law with constant ``Psi_1`` (Neo-Hookean) the I1 part of the HEML force is this
    linear network on the mesh's unique edges, ``w_e = sum over tets of 2 V0 Psi_1 a_k``.
    """
    for e in range(lo, hi):
        i = edges[e, 0]
        j = edges[e, 1]
        w = weights[e]
        dx = (x[j, 0] - x[i, 0]) * w
        dy = (x[j, 1] - x[i, 1]) * w
        dz = (x[j, 2] - x[i, 2]) * w
        f[i, 0] += dx
        f[i, 1] += dy
        f[i, 2] += dz
        f[j, 0] -= dx
        f[j, 1] -= dy
        f[j, 2] -= dz


#: Tets per block of the volume-term kernel: its arithmetic runs on blocks in SIMD lanes.
VOLUME_BLOCK = 64


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def volume_term_chunk(x, tets, inv_det, law, p, f, lo, hi):
    """Add the volume term ``-V0 Psi_J dJ/dx`` (N) of tets ``lo..hi-1`` into ``f``.

    Only for laws whose ``Psi_J`` depends on J alone (those with a constant ``Psi_1``);
    ``inv_det`` is ``1 / det(Dm) = 1 / (6 V0)`` per tet. Works on blocks of
    :data:`VOLUME_BLOCK` tets: gather the edges, compute the cross products and ``Psi_J``
    in a loop that vectorises (inline logarithm), scatter. A block holding a tet with
    ``J`` not positive and normal is redone with ``law_gradient`` (NaN where undefined).
    """
    edges = np.empty((9, VOLUME_BLOCK), dtype=x.dtype)
    work = np.empty((9, VOLUME_BLOCK), dtype=x.dtype)
    for start in range(lo, hi, VOLUME_BLOCK):
        size = min(VOLUME_BLOCK, hi - start)
        for k in range(size):
            t = start + k
            i0 = tets[t, 0]
            i1 = tets[t, 1]
            i2 = tets[t, 2]
            i3 = tets[t, 3]
            x0x = x[i0, 0]
            x0y = x[i0, 1]
            x0z = x[i0, 2]
            edges[0, k] = x[i1, 0] - x0x
            edges[1, k] = x[i1, 1] - x0y
            edges[2, k] = x[i1, 2] - x0z
            edges[3, k] = x[i2, 0] - x0x
            edges[4, k] = x[i2, 1] - x0y
            edges[5, k] = x[i2, 2] - x0z
            edges[6, k] = x[i3, 0] - x0x
            edges[7, k] = x[i3, 1] - x0y
            edges[8, k] = x[i3, 2] - x0z
        n_bad = 0
        for k in range(size):
            ax = edges[0, k]
            ay = edges[1, k]
            az = edges[2, k]
            bx = edges[3, k]
            by = edges[4, k]
            bz = edges[5, k]
            cx = edges[6, k]
            cy = edges[7, k]
            cz = edges[8, k]
            c1x = by * cz - bz * cy
            c1y = bz * cx - bx * cz
            c1z = bx * cy - by * cx
            c2x = cy * az - cz * ay
            c2y = cz * ax - cx * az
            c2z = cx * ay - cy * ax
            c3x = ay * bz - az * by
            c3y = az * bx - ax * bz
            c3z = ax * by - ay * bx
            jac = (ax * c1x + ay * c1y + az * c1z) * inv_det[start + k]
            good = jac >= SMALLEST_NORMAL and jac < math.inf
            n_bad += 0 if good else 1
            g = volumetric_gradient_fast(law, p, jac if good else 1.0) * (1.0 / 6.0)
            work[0, k] = c1x * g
            work[1, k] = c1y * g
            work[2, k] = c1z * g
            work[3, k] = c2x * g
            work[4, k] = c2y * g
            work[5, k] = c2z * g
            work[6, k] = c3x * g
            work[7, k] = c3y * g
            work[8, k] = c3z * g
        if n_bad:  # rare: inverted, flat or non-finite tets take the general path
            for k in range(size):
                ax = edges[0, k]
                ay = edges[1, k]
                az = edges[2, k]
                bx = edges[3, k]
                by = edges[4, k]
                bz = edges[5, k]
                cx = edges[6, k]
                cy = edges[7, k]
                cz = edges[8, k]
                jac = (ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz)
                       + az * (bx * cy - by * cx)) * inv_det[start + k]
                if not (jac >= SMALLEST_NORMAL and jac < math.inf):
                    d1, d2, dj = law_gradient(law, p, 0.0, 0.0, jac)
                    g = dj * (1.0 / 6.0)
                    work[0, k] = (by * cz - bz * cy) * g
                    work[1, k] = (bz * cx - bx * cz) * g
                    work[2, k] = (bx * cy - by * cx) * g
                    work[3, k] = (cy * az - cz * ay) * g
                    work[4, k] = (cz * ax - cx * az) * g
                    work[5, k] = (cx * ay - cy * ax) * g
                    work[6, k] = (ay * bz - az * by) * g
                    work[7, k] = (az * bx - ax * bz) * g
                    work[8, k] = (ax * by - ay * bx) * g
        for k in range(size):
            t = start + k
            i0 = tets[t, 0]
            i1 = tets[t, 1]
            i2 = tets[t, 2]
            i3 = tets[t, 3]
            c1x = work[0, k]
            c1y = work[1, k]
            c1z = work[2, k]
            c2x = work[3, k]
            c2y = work[4, k]
            c2z = work[5, k]
            c3x = work[6, k]
            c3y = work[7, k]
            c3z = work[8, k]
            f[i0, 0] += c1x + c2x + c3x
            f[i0, 1] += c1y + c2y + c3y
            f[i0, 2] += c1z + c2z + c3z
            f[i1, 0] -= c1x
            f[i1, 1] -= c1y
            f[i1, 2] -= c1z
            f[i2, 0] -= c2x
            f[i2, 1] -= c2y
            f[i2, 2] -= c2z
            f[i3, 0] -= c3x
            f[i3, 1] -= c3y
            f[i3, 2] -= c3z


@nb.njit(cache=True)
def heml_split_forces_chunk(x, tets, inv_det, edges, weights, law, p, f, t_lo, t_hi, e_lo, e_hi):
    """Constant-``Psi_1`` HEML forces: springs ``e_lo..e_hi-1`` plus volume terms of tets ``t_lo..t_hi-1``."""
    spring_network_chunk(x, edges, weights, f, e_lo, e_hi)
    volume_term_chunk(x, tets, inv_det, law, p, f, t_lo, t_hi)


@nb.njit(cache=True, parallel=True)
def heml_split_forces_parallel(x, tets, inv_det, edges, weights, law, p, buf):
    """Constant-``Psi_1`` HEML forces, one chunk of edges and tets per thread, into ``buf[0]``."""
    n_chunks = buf.shape[0]
    m = tets.shape[0]
    ne = edges.shape[0]
    for c in prange(n_chunks):
        heml_split_forces_chunk(x, tets, inv_det, edges, weights, law, p, buf[c],
                                c * m // n_chunks, (c + 1) * m // n_chunks,
                                c * ne // n_chunks, (c + 1) * ne // n_chunks)
    reduce_chunks(buf)


@nb.njit(cache=True, parallel=True)
def reduce_chunks(buf):
    """Sum ``buf[1:]`` into ``buf[0]`` (parallel over vertices)."""
    n_chunks = buf.shape[0]
    if n_chunks == 1:
        return
    n = buf.shape[1]
    for i in prange(n):
        for c in range(1, n_chunks):
            buf[0, i, 0] += buf[c, i, 0]
            buf[0, i, 1] += buf[c, i, 1]
            buf[0, i, 2] += buf[c, i, 2]


@nb.njit(cache=True, inline="always")
def tet_invariants(x, tets, coef, q, use_q, t):
    """``(I1, I2, J)`` of tet ``t`` at positions ``x`` (I2 = 0 unless ``use_q``)."""
    i0 = tets[t, 0]
    i1 = tets[t, 1]
    i2 = tets[t, 2]
    i3 = tets[t, 3]
    ax = x[i1, 0] - x[i0, 0]
    ay = x[i1, 1] - x[i0, 1]
    az = x[i1, 2] - x[i0, 2]
    bx = x[i2, 0] - x[i0, 0]
    by = x[i2, 1] - x[i0, 1]
    bz = x[i2, 2] - x[i0, 2]
    cx = x[i3, 0] - x[i0, 0]
    cy = x[i3, 1] - x[i0, 1]
    cz = x[i3, 2] - x[i0, 2]
    dx = bx - ax
    dy = by - ay
    dz = bz - az
    ex = cx - ax
    ey = cy - ay
    ez = cz - az
    fx = cx - bx
    fy = cy - by
    fz = cz - bz
    s0 = ax * ax + ay * ay + az * az
    s1 = bx * bx + by * by + bz * bz
    s2 = cx * cx + cy * cy + cz * cz
    s3 = dx * dx + dy * dy + dz * dz
    s4 = ex * ex + ey * ey + ez * ez
    s5 = fx * fx + fy * fy + fz * fz
    i_1 = (coef[t, 2] * s0 + coef[t, 3] * s1 + coef[t, 4] * s2
           + coef[t, 5] * s3 + coef[t, 6] * s4 + coef[t, 7] * s5)
    i_2 = 0.0
    if use_q:
        qs0, qs1, qs2, qs3, qs4, qs5 = _qs(q, t, s0, s1, s2, s3, s4, s5)
        i_2 = 0.5 * (s0 * qs0 + s1 * qs1 + s2 * qs2 + s3 * qs3 + s4 * qs4 + s5 * qs5)
    det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    return i_1, i_2, det * coef[t, 1]


@nb.njit(cache=True)
def heml_energy_chunk(x, tets, coef, q, use_q, law, p, lo, hi):
    """Elastic energy (J) of tets ``lo..hi-1`` at positions ``x`` (m): sum of ``V0 Psi``."""
    total = 0.0
    for t in range(lo, hi):
        i_1, i_2, jac = tet_invariants(x, tets, coef, q, use_q, t)
        total += coef[t, 0] * law_energy(law, p, i_1, i_2, jac)
    return total


@nb.njit(cache=True, parallel=True)
def heml_energy_parallel(x, tets, coef, q, use_q, law, p, n_chunks):
    """Total elastic energy (J), one chunk of tets per thread."""
    m = tets.shape[0]
    total = 0.0
    for c in prange(n_chunks):
        total += heml_energy_chunk(x, tets, coef, q, use_q, law, p, c * m // n_chunks, (c + 1) * m // n_chunks)
    return total
