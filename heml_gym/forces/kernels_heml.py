"""Numba kernels of the HEML force field (edge form of P1 hyperelasticity).

Per tet the precomputation stores ``coef[t] = (V0, 1/(6 V0), a_0..a_5)`` with
``a_k = tr A_k`` and, for laws that need ``I2``, ``q[t]`` = the 21 upper-triangle entries
of ``Q_kl = a_k a_l - tr(A_k A_l)``, where ``C = sum_k s_k A_k`` and ``s_k`` are the six
squared edge lengths in the order of :data:`heml_gym.mesh.EDGE_PAIRS`.

At run time, with ``e_k = x_b - x_a`` for edge ``k = (a, b)``:

* ``I1 = a . s``, ``I2 = s^T Q s / 2``, ``J = det(Ds) / (6 V0)``,
* edge weight ``w_k = 2 V0 (Psi_1 a_k + Psi_2 (Q s)_k)``: ``f_a += w_k e_k``, ``f_b -= w_k e_k``,
* volume term ``f_a -= s Psi_J / 6 * d det(Ds) / d x_a`` (cross products of the edges),

with ``s`` the tet's relative stiffness (``coef[t, 8]``, 1 unless E varies over the body;
``coef[t, 0]`` is then ``s V0``).

The force kernels work in blocks of :data:`BLOCK` tets (gather the edges, compute in
loops that vectorise across the block, scatter), reading the per-tet constants
constant-major (``coef_t (9, m)``, ``q_t (21, m)``); indices are unsigned (see
:func:`tet_vertices`). Neo-Hookean, whose ``Psi_1`` is constant, has a kernel of its own
with precomputed spring weights.

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
from ..laws import law_energy, law_gradient, volumetric_energy_fast, volumetric_gradient_fast
from ..materials import ST_VENANT_KIRCHHOFF, STABLE_NEO_HOOKEAN


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def heml_forces_chunk(x, tets, coef_t, q_t, use_q, law, p, f, lo, hi):
    """Add the HEML forces (N) of tets ``lo..hi-1`` at positions ``x`` (m) into ``f``, any law.

    ``coef_t (9, m)`` and ``q_t (21, m)`` are the per-tet constants stored constant-major
    (``q_t`` is read only if ``use_q``). Tets are processed in blocks of :data:`BLOCK`:
    gather the edges; compute the squared edge lengths, ``Q s``, the invariants and the
    cross products in loops that vectorise; the law's derivatives per tet; the edge
    weights and forces (vectorised); scatter.
    """
    edges = np.empty((9, BLOCK), dtype=x.dtype)
    qs = np.zeros((6, BLOCK), dtype=x.dtype)  # stays zero unless use_q
    inv = np.empty((3, BLOCK), dtype=x.dtype)
    grad = np.empty((3, BLOCK), dtype=x.dtype)
    work = np.empty((12, BLOCK), dtype=x.dtype)
    for start in range(lo, hi, BLOCK):
        size = min(BLOCK, hi - start)
        first = np.uint64(start)
        gather_block(x, tets, first, size, edges)
        for k in range(size):  # invariants: vectorises
            t = first + np.uint64(k)
            ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
            s0, s1, s2, s3, s4, s5 = squared_edge_lengths(ax, ay, az, bx, by, bz, cx, cy, cz)
            inv[0, k], inv[2, k] = i1_and_j(coef_t, t, ax, ay, az, bx, by, bz, cx, cy, cz, s0, s1, s2, s3, s4, s5)
            if use_q:
                q0, q1, q2, q3, q4, q5 = _qs_t(q_t, t, s0, s1, s2, s3, s4, s5)
                qs[0, k] = q0
                qs[1, k] = q1
                qs[2, k] = q2
                qs[3, k] = q3
                qs[4, k] = q4
                qs[5, k] = q5
                inv[1, k] = 0.5 * (s0 * q0 + s1 * q1 + s2 * q2 + s3 * q3 + s4 * q4 + s5 * q5)
            else:
                inv[1, k] = 0.0
        law_gradients(law, p, inv, grad, size)
        for k in range(size):  # edge weights and forces: vectorises
            t = first + np.uint64(k)
            ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
            c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
            v2 = 2.0 * coef_t[0, t]
            w1 = v2 * grad[0, k]
            w2 = v2 * grad[1, k] if use_q else 0.0
            g = grad[2, k] * (1.0 / 6.0) * coef_t[8, t]  # (times 1: exact, E uniform)
            _store_tet_forces(work, k, (ax, ay, az, bx, by, bz, cx, cy, cz),
                              (c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g, c3x * g, c3y * g, c3z * g),
                              (w1 * coef_t[2, t] + w2 * qs[0, k], w1 * coef_t[3, t] + w2 * qs[1, k],
                               w1 * coef_t[4, t] + w2 * qs[2, k], w1 * coef_t[5, t] + w2 * qs[3, k],
                               w1 * coef_t[6, t] + w2 * qs[4, k], w1 * coef_t[7, t] + w2 * qs[5, k]))
        scatter_block(f, tets, first, size, work)


@nb.njit(cache=True, inline="always")
def law_gradients(law, p, inv, grad, size):
    """``grad[:, k] = law_gradient(law, p, *inv[:, k])`` for lanes ``k < size``.

    The laws whose derivatives call no library function (Stable Neo-Hookean, StVK) get a
    loop of their own, with the law a constant, so that it vectorises.
    """
    if law == STABLE_NEO_HOOKEAN:
        for k in range(size):
            grad[0, k], grad[1, k], grad[2, k] = law_gradient(STABLE_NEO_HOOKEAN, p, inv[0, k], inv[1, k], inv[2, k])
    elif law == ST_VENANT_KIRCHHOFF:
        for k in range(size):
            grad[0, k], grad[1, k], grad[2, k] = law_gradient(ST_VENANT_KIRCHHOFF, p, inv[0, k], inv[1, k], inv[2, k])
    else:
        for k in range(size):
            grad[0, k], grad[1, k], grad[2, k] = law_gradient(law, p, inv[0, k], inv[1, k], inv[2, k])


@nb.njit(cache=True, inline="always")
def squared_edge_lengths(ax, ay, az, bx, by, bz, cx, cy, cz):
    """``s_k = |e_k|^2`` of the six edges (order of ``EDGE_PAIRS``) from the edges ``a, b, c``
    from vertex 0 (m^2)."""
    dx = bx - ax
    dy = by - ay
    dz = bz - az
    ex = cx - ax
    ey = cy - ay
    ez = cz - az
    fx = cx - bx
    fy = cy - by
    fz = cz - bz
    return (ax * ax + ay * ay + az * az, bx * bx + by * by + bz * bz, cx * cx + cy * cy + cz * cz,
            dx * dx + dy * dy + dz * dz, ex * ex + ey * ey + ez * ez, fx * fx + fy * fy + fz * fz)


@nb.njit(cache=True, inline="always")
def _qs_t(q_t, t, s0, s1, s2, s3, s4, s5):
    """``Q s`` for tet ``t`` with Q's 21 upper-triangle entries stored as ``q_t[:, t]``."""
    qs0 = q_t[0, t] * s0 + q_t[1, t] * s1 + q_t[2, t] * s2 + q_t[3, t] * s3 + q_t[4, t] * s4 + q_t[5, t] * s5
    qs1 = q_t[1, t] * s0 + q_t[6, t] * s1 + q_t[7, t] * s2 + q_t[8, t] * s3 + q_t[9, t] * s4 + q_t[10, t] * s5
    qs2 = q_t[2, t] * s0 + q_t[7, t] * s1 + q_t[11, t] * s2 + q_t[12, t] * s3 + q_t[13, t] * s4 + q_t[14, t] * s5
    qs3 = q_t[3, t] * s0 + q_t[8, t] * s1 + q_t[12, t] * s2 + q_t[15, t] * s3 + q_t[16, t] * s4 + q_t[17, t] * s5
    qs4 = q_t[4, t] * s0 + q_t[9, t] * s1 + q_t[13, t] * s2 + q_t[16, t] * s3 + q_t[18, t] * s4 + q_t[19, t] * s5
    qs5 = q_t[5, t] * s0 + q_t[10, t] * s1 + q_t[14, t] * s2 + q_t[17, t] * s3 + q_t[19, t] * s4 + q_t[20, t] * s5
    return qs0, qs1, qs2, qs3, qs4, qs5


@nb.njit(cache=True, inline="always")
def gather_block(x, tets, first, size, edges):
    """``edges[:, k]`` = the edges ``a, b, c`` from vertex 0 (m) of the block's tets ``first + k``."""
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


@nb.njit(cache=True, inline="always")
def scatter_block(f, tets, first, size, work):
    """Add the forces ``work[:, k]`` of the block's tets ``first + k`` into ``f`` (N)."""
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


@nb.njit(cache=True, parallel=True)
def heml_forces_parallel(x, tets, coef_t, q_t, use_q, law, p, buf):
    """HEML forces over all tets, one chunk per thread, summed into ``buf[0]`` (zero on entry)."""
    n_chunks = buf.shape[0]
    m = tets.shape[0]
    for c in prange(n_chunks):
        heml_forces_chunk(x, tets, coef_t, q_t, use_q, law, p, buf[c], c * m // n_chunks, (c + 1) * m // n_chunks)
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
    # the law's constants in scalars: loaded from ``p`` inside the loop, LLVM cannot prove
    # they do not alias the stores to ``work`` and leaves the loop scalar (on AVX2 CPUs:
    # 18 against 40+ M tets/s)
    p0 = p[0]
    p1 = p[1]
    for start in range(lo, hi, BLOCK):
        size = min(BLOCK, hi - start)
        first = np.uint64(start)
        gather_block(x, tets, first, size, edges)
        n_bad = 0
        for k in range(size):  # vectorises: no calls, no branches, unit-stride arrays
            t = first + np.uint64(k)
            ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
            c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
            jac = (ax * c1x + ay * c1y + az * c1z) * inv_det[t]
            good = jac >= SMALLEST_NORMAL and jac < math.inf
            n_bad += 0 if good else 1
            g = volumetric_gradient_fast(law, p0, p1, jac if good else 1.0) * (1.0 / 6.0)
            _store_tet_forces(work, k, (ax, ay, az, bx, by, bz, cx, cy, cz),
                              (c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g, c3x * g, c3y * g, c3z * g),
                              (w[0, t], w[1, t], w[2, t], w[3, t], w[4, t], w[5, t]))
        if n_bad:  # rare: inverted, flat or non-finite tets take the general path
            for k in range(size):
                t = start + k
                ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
                c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
                jac = (ax * c1x + ay * c1y + az * c1z) * inv_det[t]
                if not (jac >= SMALLEST_NORMAL and jac < math.inf):
                    d1, d2, dj = law_gradient(law, p, 0.0, 0.0, jac)
                    g = dj * (1.0 / 6.0)
                    _store_tet_forces(work, k, (ax, ay, az, bx, by, bz, cx, cy, cz),
                                      (c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g, c3x * g, c3y * g, c3z * g),
                                      (w[0, t], w[1, t], w[2, t], w[3, t], w[4, t], w[5, t]))
        scatter_block(f, tets, first, size, work)


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def constant_psi1_energy_and_forces_chunk(x, tets, inv_det, volume, w, psi1, law, p, f, lo, hi):
    """Add the forces (N) of tets ``lo..hi-1`` into ``f`` as
    :func:`constant_psi1_forces_chunk` and return their energy (J) in the same pass:
    ``sum_k w_k s_k / 2 - 3 Psi_1 V0`` (the springs) plus ``V0 Psi_vol(J)``. ``volume``
    is ``V0`` per tet, ``psi1`` the law's constant ``Psi_1`` (Pa). Returns ``inf`` (and
    leaves ``f`` partly summed) as soon as a tet's J is not positive and normal: the law
    is undefined there, which is what line searches need to know.
    """
    edges = np.empty((9, BLOCK), dtype=x.dtype)
    work = np.empty((12, BLOCK), dtype=x.dtype)
    lane_energy = np.empty(BLOCK, dtype=x.dtype)  # summed after the loop: a sum inside would not vectorise
    p0 = p[0]
    p1 = p[1]
    total = 0.0
    for start in range(lo, hi, BLOCK):
        size = min(BLOCK, hi - start)
        first = np.uint64(start)
        gather_block(x, tets, first, size, edges)
        n_bad = 0
        for k in range(size):  # vectorises, as constant_psi1_forces_chunk
            t = first + np.uint64(k)
            ax, ay, az, bx, by, bz, cx, cy, cz = edge_vectors(edges, k)
            s0, s1, s2, s3, s4, s5 = squared_edge_lengths(ax, ay, az, bx, by, bz, cx, cy, cz)
            c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
            jac = (ax * c1x + ay * c1y + az * c1z) * inv_det[t]
            good = jac >= SMALLEST_NORMAL and jac < math.inf
            n_bad += 0 if good else 1
            j_safe = jac if good else 1.0
            lane_energy[k] = (0.5 * (w[0, t] * s0 + w[1, t] * s1 + w[2, t] * s2 + w[3, t] * s3 + w[4, t] * s4
                              + w[5, t] * s5)
                       + volume[t] * (volumetric_energy_fast(law, p0, p1, j_safe) - 3.0 * psi1))
            g = volumetric_gradient_fast(law, p0, p1, j_safe) * (1.0 / 6.0)
            _store_tet_forces(work, k, (ax, ay, az, bx, by, bz, cx, cy, cz),
                              (c1x * g, c1y * g, c1z * g, c2x * g, c2y * g, c2z * g, c3x * g, c3y * g, c3z * g),
                              (w[0, t], w[1, t], w[2, t], w[3, t], w[4, t], w[5, t]))
        if n_bad:
            return math.inf
        for k in range(size):
            total += lane_energy[k]
        scatter_block(f, tets, first, size, work)
    return total


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
def tet_edges(x, tets, t):
    """The edges ``a, b, c`` from vertex 0 of tet ``t`` at positions ``x`` (m)."""
    i0, i1, i2, i3 = tet_vertices(tets, t)
    x0x = x[i0, 0]
    x0y = x[i0, 1]
    x0z = x[i0, 2]
    return (x[i1, 0] - x0x, x[i1, 1] - x0y, x[i1, 2] - x0z,
            x[i2, 0] - x0x, x[i2, 1] - x0y, x[i2, 2] - x0z,
            x[i3, 0] - x0x, x[i3, 1] - x0y, x[i3, 2] - x0z)


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
def _store_tet_forces(work, k, edges, volume, springs):
    """Write the forces on the 4 vertices of the tet in lane ``k`` into ``work[:, k]``.

    ``edges = (ax, ay, az, bx, by, bz, cx, cy, cz)``: its edges ``a, b, c`` from vertex 0;
    ``volume``: the volume-term vectors ``c1..c3`` (already scaled), 9 numbers;
    ``springs``: the spring weights of edges 01, 02, 03, 12, 13, 23.
    """
    ax, ay, az, bx, by, bz, cx, cy, cz = edges
    c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = volume
    w01, w02, w03, w12, w13, w23 = springs
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
def i1_and_j(coef_t, t, ax, ay, az, bx, by, bz, cx, cy, cz, s0, s1, s2, s3, s4, s5):
    """``(I1, J)`` of tet ``t`` from its edges ``a, b, c`` from vertex 0 (m) and its squared
    edge lengths ``s`` (m^2)."""
    i_1 = (coef_t[2, t] * s0 + coef_t[3, t] * s1 + coef_t[4, t] * s2
           + coef_t[5, t] * s3 + coef_t[6, t] * s4 + coef_t[7, t] * s5)
    det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    return i_1, det * coef_t[1, t]


@nb.njit(cache=True)
def heml_energy_chunk(x, tets, coef_t, q_t, use_q, law, p, lo, hi):
    """Elastic energy (J) of tets ``lo..hi-1`` at positions ``x`` (m): sum of ``V0 Psi``."""
    total = 0.0
    for t_signed in range(lo, hi):
        t = np.uint64(t_signed)
        ax, ay, az, bx, by, bz, cx, cy, cz = tet_edges(x, tets, t)
        s0, s1, s2, s3, s4, s5 = squared_edge_lengths(ax, ay, az, bx, by, bz, cx, cy, cz)
        i_1, jac = i1_and_j(coef_t, t, ax, ay, az, bx, by, bz, cx, cy, cz, s0, s1, s2, s3, s4, s5)
        i_2 = 0.0
        if use_q:
            q0, q1, q2, q3, q4, q5 = _qs_t(q_t, t, s0, s1, s2, s3, s4, s5)
            i_2 = 0.5 * (s0 * q0 + s1 * q1 + s2 * q2 + s3 * q3 + s4 * q4 + s5 * q5)
        total += coef_t[0, t] * law_energy(law, p, i_1, i_2, jac)
    return total


@nb.njit(cache=True, parallel=True)
def heml_energy_parallel(x, tets, coef_t, q_t, use_q, law, p, n_chunks):
    """Total elastic energy (J), one chunk of tets per thread."""
    m = tets.shape[0]
    total = 0.0
    for c in prange(n_chunks):
        total += heml_energy_chunk(x, tets, coef_t, q_t, use_q, law, p, c * m // n_chunks, (c + 1) * m // n_chunks)
    return total
