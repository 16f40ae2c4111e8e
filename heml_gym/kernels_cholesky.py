"""Numba kernels of a sparse Cholesky factorisation in envelope (skyline) storage.

Row ``i`` of the lower factor ``L`` is stored densely from its first nonzero column
``first[i]`` to the diagonal, at ``values[ptr[i] : ptr[i + 1]]`` (``ptr[i + 1] - ptr[i] =
i - first[i] + 1``). Cholesky creates no fill outside the envelope of ``A``, so with a
bandwidth-reducing ordering (reverse Cuthill-McKee) the factor of a mesh's stiffness
matrix stays small, and every inner loop is a dot product or an update over a contiguous
stretch of memory, which vectorises. Indices are unsigned: Numba's wrap-around of negative
signed indices would turn those contiguous loads into gathers. See
:class:`heml_gym.linear_solvers.EnvelopeCholesky`.

:func:`pcg_envelope` runs conjugate gradients preconditioned by such a factor entirely in
Numba (CSR products, the two triangular solves and the vector updates), with no Python
between iterations.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_FAST = {"reassoc", "contract", "nsz", "arcp"}  # lets the dot products vectorise


@nb.njit(cache=True, inline="always")
def _row(first, ptr, i):
    """``(first column, offset)`` of row ``i``: ``values[offset + k]`` is ``L[i, k]``."""
    f = np.uint64(first[i])
    return f, np.uint64(ptr[i]) - f


@nb.njit(cache=True, fastmath=_FAST)
def envelope_cholesky(first, ptr, values):
    """Factorise in place ``values`` (the envelope of a symmetric matrix's lower triangle)
    into ``L`` with ``A = L L^T`` (up-looking, row by row).

    Returns -1 on success, else the row whose pivot was not positive (the matrix is not
    positive definite; ``values`` is then left partly factorised).
    """
    n = first.shape[0]
    for i_signed in range(n):
        i = np.uint64(i_signed)
        fi, pi = _row(first, ptr, i)
        for j in range(fi, i):
            fj, pj = _row(first, ptr, j)
            s = values[pi + j]
            for k in range(max(fi, fj), j):
                s -= values[pi + k] * values[pj + k]
            values[pi + j] = s / values[pj + j]
        d = values[pi + i]
        for k in range(fi, i):
            d -= values[pi + k] * values[pi + k]
        if not d > 0.0:
            return i_signed
        values[pi + i] = math.sqrt(d)
    return -1


@nb.njit(cache=True, fastmath=_FAST)
def envelope_solve(first, ptr, values, b, x):
    """Solve ``L L^T x = b`` with the factor from :func:`envelope_cholesky` (``x`` is
    overwritten; ``b`` is kept)."""
    n = first.shape[0]
    for i_signed in range(n):  # forward: L y = b
        i = np.uint64(i_signed)
        fi, pi = _row(first, ptr, i)
        s = b[i]
        for k in range(fi, i):
            s -= values[pi + k] * x[k]
        x[i] = s / values[pi + i]
    for i_signed in range(n - 1, -1, -1):  # backward: L^T x = y, row by row of L
        i = np.uint64(i_signed)
        fi, pi = _row(first, ptr, i)
        xi = x[i] / values[pi + i]
        x[i] = xi
        for k in range(fi, i):
            x[k] -= values[pi + k] * xi


@nb.njit(cache=True, fastmath=_FAST)
def envelope_solve_pair(first, ptr, values, b0, b1, x0, x1):
    """Solve ``L L^T x0 = b0`` and ``L L^T x1 = b1`` in one pass over the factor (read once
    for both right-hand sides: the factor of a mid-size mesh does not fit in the L2
    cache). ``b0``, ``b1`` are kept."""
    n = first.shape[0]
    for i_signed in range(n):  # forward: L y = b
        i = np.uint64(i_signed)
        fi, pi = _row(first, ptr, i)
        s0 = b0[i]
        s1 = b1[i]
        for k in range(fi, i):
            lik = values[pi + k]
            s0 -= lik * x0[k]
            s1 -= lik * x1[k]
        d = values[pi + i]
        x0[i] = s0 / d
        x1[i] = s1 / d
    for i_signed in range(n - 1, -1, -1):  # backward: L^T x = y, row by row of L
        i = np.uint64(i_signed)
        fi, pi = _row(first, ptr, i)
        d = values[pi + i]
        xi0 = x0[i] / d
        xi1 = x1[i] / d
        x0[i] = xi0
        x1[i] = xi1
        for k in range(fi, i):
            lik = values[pi + k]
            x0[k] -= lik * xi0
            x1[k] -= lik * xi1


@nb.njit(cache=True)
def scatter_into_envelope(data, target, values):
    """``values[:] = 0``, then ``values[target[e]] += data[e]`` for the kept entries
    (``target[e] >= 0``) of a CSR matrix's ``data``."""
    values[:] = 0.0
    for e in range(data.shape[0]):
        t = target[e]
        if t >= 0:
            values[t] += data[e]


@nb.njit(cache=True)
def csr_matvec(indptr, indices, data, x, y):
    """``y = A x`` for the CSR matrix ``(data, indices, indptr)``. Scalar on purpose: rows
    of ~30 entries and an indexed load each run 2.7x slower when LLVM vectorises them
    with gathers (``fastmath``)."""
    for i in range(y.shape[0]):
        s = 0.0
        for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + 1])):
            s += data[k] * x[np.uint64(indices[k])]
        y[i] = s


@nb.njit(cache=True)
def envelope_precondition(first, ptr, values, inverse, r, z, work_b, work_x):
    """``z = A^-1 r`` with ``A = P^T L L^T P``: ``inverse[i]`` is row ``i``'s position in the
    factor's order; ``work_b``, ``work_x`` are scratch vectors."""
    n = r.shape[0]
    for i in range(n):
        work_b[np.uint64(inverse[i])] = r[i]
    envelope_solve(first, ptr, values, work_b, work_x)
    for i in range(n):
        z[i] = work_x[np.uint64(inverse[i])]


@nb.njit(cache=True)
def pcg_envelope(indptr, indices, data, b, first, ptr, values, inverse, rtol, max_iter, x):
    """Conjugate gradients on the CSR matrix ``A`` from ``x0 = P^-1 b``, preconditioned by an
    envelope Cholesky factor ``P`` (of an earlier matrix). ``x`` receives the solution.

    Returns ``(iterations, converged)``; converged means ``|b - A x| <= rtol |b|``. Stops
    unconverged when ``A`` is not positive definite along a search direction.
    """
    n = b.shape[0]
    r = np.empty(n)
    z = np.empty(n)
    p = np.empty(n)
    ap = np.empty(n)
    work_b = np.empty(n)
    work_x = np.empty(n)
    b_norm = math.sqrt(np.dot(b, b))
    envelope_precondition(first, ptr, values, inverse, b, x, work_b, work_x)
    csr_matvec(indptr, indices, data, x, ap)
    for i in range(n):
        r[i] = b[i] - ap[i]
    tol = rtol * b_norm
    if b_norm == 0.0 or math.sqrt(np.dot(r, r)) <= tol:
        return 0, True
    envelope_precondition(first, ptr, values, inverse, r, z, work_b, work_x)
    p[:] = z
    rz = np.dot(r, z)
    for k in range(1, max_iter + 1):
        csr_matvec(indptr, indices, data, p, ap)
        pap = np.dot(p, ap)
        if not pap > 0.0:  # not positive definite along p (or NaN)
            return k, False
        step = rz / pap
        for i in range(n):
            x[i] += step * p[i]
            r[i] -= step * ap[i]
        if math.sqrt(np.dot(r, r)) <= tol:
            return k, True
        envelope_precondition(first, ptr, values, inverse, r, z, work_b, work_x)
        rz_new = np.dot(r, z)
        beta = rz_new / rz
        for i in range(n):
            p[i] = z[i] + beta * p[i]
        rz = rz_new
    return max_iter, False
