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
    for t_signed in range(lo, hi):
        t = np.uint64(t_signed)
        i0, i1, i2, i3 = tet_vertices(tets, t)
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
        c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(
            e01x, e01y, e01z, e02x, e02y, e02z, e03x, e03y, e03z)
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


#: Tets per block of the constant-``Psi_1`` kernel: its arithmetic runs in SIMD lanes.
BLOCK = 64


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def constant_psi1_forces_chunk(x, tets, inv_det, w, law, p, f, lo, hi):
    """Add the HEML forces (N) of tets ``lo..hi-1`` for a law with constant ``Psi_1``.

    For such a law (Neo-Hookean) the edge weights ``w[k, t] = 2 V0 Psi_1 a_k`` are
    constants: the I1 part is a fixed linear spring network, and ``Psi_J`` depends on J
    alone. ``inv_det`` is ``1 / det(Dm) = 1 / (6 V0)`` per tet. Tets are processed in
    blocks of :data:`BLOCK`: gather the edge vectors; compute the spring forces, the cross
    products, J and ``Psi_J`` (inline logarithm) in a loop that vectorises; scatter. A
    block holding a tet whose J is not positive and normal is redone for those tets with
    ``law_gradient`` (NaN where the law is undefined).
    """
    edges = np.empty((9, BLOCK), dtype=x.dtype)
    work = np.empty((12, BLOCK), dtype=x.dtype)
    for start in range(lo, hi, BLOCK):
        size = min(BLOCK, hi - start)
        first = np.uint64(start)
        for k in range(size):
            i0, i1, i2, i3 = tet_vertices(tets, first + np.uint64(k))
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
        for k in range(size):  # vectorises: no calls, no branches, unit-stride arrays
            t = first + np.uint64(k)
            ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
            c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
            jac = (ax * c1x + ay * c1y + az * c1z) * inv_det[t]
            good = jac >= SMALLEST_NORMAL and jac < math.inf
            n_bad += 0 if good else 1
            g = volumetric_gradient_fast(law, p[0], p[1], jac if good else 1.0) * (1.0 / 6.0)
            _store_tet_forces(work, k, ax, ay, az, bx, by, bz, cx, cy, cz,
                              c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g,
                              c3x * g, c3y * g, c3z * g,
                              w[0, t], w[1, t], w[2, t], w[3, t], w[4, t], w[5, t])
        if n_bad:  # rare: inverted, flat or non-finite tets take the general path
            for k in range(size):
                t = start + k
                ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
                c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
                jac = (ax * c1x + ay * c1y + az * c1z) * inv_det[t]
                if not (jac >= SMALLEST_NORMAL and jac < math.inf):
                    d1, d2, dj = law_gradient(law, p, 0.0, 0.0, jac)
                    g = dj * (1.0 / 6.0)
                    _store_tet_forces(work, k, ax, ay, az, bx, by, bz, cx, cy, cz,
                                      c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g,
                                      c3x * g, c3y * g, c3z * g,
                                      w[0, t], w[1, t], w[2, t], w[3, t], w[4, t], w[5, t])
        for k in range(size):
            i0, i1, i2, i3 = tet_vertices(tets, first + np.uint64(k))
            f[i0, 0] += work[0, k]
            f[i0, 1] += work[1, k]
            f[i0, 2] += work[2, k]
            f[i1, 0] += work[3, k]
            f[i1, 1] += work[4, k]
            f[i1, 2] += work[5, k]
            f[i2, 0] += work[6, k]
            f[i2, 1] += work[7, k]
            f[i2, 2] += work[8, k]
            f[i3, 0] += work[9, k]
            f[i3, 1] += work[10, k]
            f[i3, 2] += work[11, k]


@nb.njit(cache=True, inline="always")
def tet_vertices(tets, t):
    """The four vertex indices of tet ``t`` as unsigned integers.

    Numba wraps negative signed indices around (``i < 0 -> i + n``), a select on every
    access that stops LLVM from vectorising unit-stride loads (it emits gathers) and
    costs the scalar loads too; unsigned indices (and an unsigned ``t``) skip it. Measured
    on the Neo-Hookean block kernel: 35 -> 16 ns per tet on one thread.
    """
    return np.uint64(tets[t, 0]), np.uint64(tets[t, 1]), np.uint64(tets[t, 2]), np.uint64(tets[t, 3])


@nb.njit(cache=True, inline="always")
def edge_vectors(edges, k):
    """The edges ``a, b, c`` (from vertex 0) of the tet in lane ``k`` of a gathered block."""
    return (edges[0, k], edges[1, k], edges[2, k], edges[3, k], edges[4, k], edges[5, k],
            edges[6, k], edges[7, k], edges[8, k])


@nb.njit(cache=True, inline="always")
def edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz):
    """``b x c, c x a, a x b`` for the edges ``a, b, c`` from vertex 0 of a tet: the
    gradients of ``det(Ds) = a . (b x c)`` with respect to vertices 1, 2, 3."""
    return (by * cz - bz * cy, bz * cx - bx * cz, bx * cy - by * cx,
            cy * az - cz * ay, cz * ax - cx * az, cx * ay - cy * ax,
            ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _store_tet_forces(work, k, ax, ay, az, bx, by, bz, cx, cy, cz,
                      c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z,
                      w01, w02, w03, w12, w13, w23):
    """Write the forces on the 4 vertices of the tet in lane ``k`` into ``work[:, k]``.

    ``a, b, c`` are its edges from vertex 0, ``c1..c3`` the volume-term vectors (already
    scaled), ``w..`` the spring weights of edges 01, 02, 03, 12, 13, 23.
    """
    s01x = w01 * ax
    s01y = w01 * ay
    s01z = w01 * az
    s02x = w02 * bx
    s02y = w02 * by
    s02z = w02 * bz
    s03x = w03 * cx
    s03y = w03 * cy
    s03z = w03 * cz
    s12x = w12 * (bx - ax)
    s12y = w12 * (by - ay)
    s12z = w12 * (bz - az)
    s13x = w13 * (cx - ax)
    s13y = w13 * (cy - ay)
    s13z = w13 * (cz - az)
    s23x = w23 * (cx - bx)
    s23y = w23 * (cy - by)
    s23z = w23 * (cz - bz)
    work[0, k] = s01x + s02x + s03x + c1x + c2x + c3x
    work[1, k] = s01y + s02y + s03y + c1y + c2y + c3y
    work[2, k] = s01z + s02z + s03z + c1z + c2z + c3z
    work[3, k] = s12x + s13x - s01x - c1x
    work[4, k] = s12y + s13y - s01y - c1y
    work[5, k] = s12z + s13z - s01z - c1z
    work[6, k] = s23x - s02x - s12x - c2x
    work[7, k] = s23y - s02y - s12y - c2y
    work[8, k] = s23z - s02z - s12z - c2z
    work[9, k] = -(s03x + s13x + s23x + c3x)
    work[10, k] = -(s03y + s13y + s23y + c3y)
    work[11, k] = -(s03z + s13z + s23z + c3z)


@nb.njit(cache=True, parallel=True)
def constant_psi1_forces_parallel(x, tets, inv_det, w, law, p, buf):
    """Constant-``Psi_1`` HEML forces, one chunk of tets per thread, summed into ``buf[0]``."""
    n_chunks = buf.shape[0]
    m = tets.shape[0]
    for c in prange(n_chunks):
        constant_psi1_forces_chunk(x, tets, inv_det, w, law, p, buf[c], c * m // n_chunks, (c + 1) * m // n_chunks)
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
    i0, i1, i2, i3 = tet_vertices(tets, t)
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
    for t_signed in range(lo, hi):
        t = np.uint64(t_signed)
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
