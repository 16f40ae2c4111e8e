"""Sparse linear solves for Newton's method: free-dof submatrices and a lagged-factor PCG.

An implicit step solves ``(M/h^2 + K) dx = -g`` a few times per step, with ``K`` changing
slowly from one solve to the next. :class:`LaggedFactorPCG` factorises the matrix once
(SuperLU), then solves the following systems by conjugate gradients preconditioned with
that old factorisation, and refactorises only when CG needs more than ``max_iter``
iterations or when the set of free dofs changes. :class:`FreeSubmatrix` extracts the
free-dof block of a CSR matrix of fixed pattern by one gather of its data.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class FreeSubmatrix:
    """``A[free][:, free]`` for CSR matrices that share one sparsity pattern.

    The pattern of the first matrix seen is analysed once; later matrices with the same
    pattern (same ``indptr``, ``indices``) are reduced by gathering their data.
    """

    def __init__(self):
        self._key = None

    def __call__(self, a: sp.csr_matrix, free: np.ndarray) -> sp.csr_matrix:
        a = a.tocsr()
        key = (a.shape, a.nnz, free.tobytes())
        if key != self._key or not (np.array_equal(a.indptr, self._indptr) and np.array_equal(a.indices, self._indices)):
            self._analyse(a, free)
            self._key = key
        return sp.csr_matrix((a.data[self._sel], self._sub_indices, self._sub_indptr), shape=self._shape)

    def _analyse(self, a, free):
        self._indptr, self._indices = a.indptr.copy(), a.indices.copy()
        new_index = np.cumsum(free) - 1
        rows = np.repeat(np.arange(a.shape[0]), np.diff(a.indptr))
        keep = free[rows] & free[a.indices]
        self._sel = np.flatnonzero(keep)
        n_free = int(free.sum())
        counts = np.bincount(new_index[rows[keep]], minlength=n_free)
        self._sub_indptr = np.concatenate([[0], np.cumsum(counts)]).astype(a.indptr.dtype)
        self._sub_indices = new_index[a.indices[keep]].astype(a.indices.dtype)
        self._shape = (n_free, n_free)


class LaggedFactorPCG:
    """Solve SPD systems by CG preconditioned with an earlier system's LU factorisation.

    ``rtol``: CG stops at ``|r| <= rtol |b|``. ``max_iter``: past this many CG
    iterations the current matrix is factorised afresh and used directly. ``key``
    (e.g. the free-dof mask and the time step) forces a new factorisation when it changes.
    Counters: ``factorizations``, ``last_iterations``.
    """

    def __init__(self, rtol: float = 1e-8, max_iter: int = 20):
        self.rtol = float(rtol)
        self.max_iter = int(max_iter)
        self._lu = None
        self._key = None
        self.factorizations = 0
        self.last_iterations = 0

    def reset(self) -> None:
        """Forget the factorisation (the next solve factorises)."""
        self._lu, self._key = None, None

    def _factor(self, a, key):
        self._lu = spla.splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        self._key = key
        self.factorizations += 1

    def solve(self, a: sp.csr_matrix, b: np.ndarray, key=None) -> np.ndarray:
        if self._lu is None or key != self._key:
            self._factor(a, key)
            self.last_iterations = 0
            return self._lu.solve(b)
        x, iterations, converged = pcg(a, b, self._lu.solve, self.rtol, self.max_iter)
        self.last_iterations = iterations
        if converged:
            return x
        self._factor(a, key)
        return self._lu.solve(b)


def pcg(a, b, precondition, rtol: float, max_iter: int):
    """Preconditioned conjugate gradients from ``x0 = P^-1 b``.

    Returns ``(x, iterations, converged)``; converged means ``|b - A x| <= rtol |b|``.
    """
    b_norm = float(np.linalg.norm(b))
    x = precondition(b)
    r = b - a @ x
    if b_norm == 0.0 or np.linalg.norm(r) <= rtol * b_norm:
        return x, 0, True
    z = precondition(r)
    p = z.copy()
    rz = float(r @ z)
    for k in range(1, max_iter + 1):
        ap = a @ p
        pap = float(p @ ap)
        if not pap > 0:  # not positive definite along p
            return x, k, False
        step = rz / pap
        x += step * p
        r -= step * ap
        if np.linalg.norm(r) <= rtol * b_norm:
            return x, k, True
        z = precondition(r)
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, max_iter, False
