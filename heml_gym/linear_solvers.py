"""Sparse linear solves for Newton's method: free-dof submatrices, a sparse Cholesky and a
lagged-factor PCG.

An implicit step solves ``(M/h^2 + K) dx = -g`` a few times per step, with ``K`` changing
slowly from one solve to the next. :class:`LaggedFactorPCG` factorises the matrix once,
then solves the following systems by conjugate gradients preconditioned with that old
factorisation, and refactorises only when CG needs more than ``max_iter`` iterations or
when the set of free dofs changes. The factorisation is :class:`EnvelopeCholesky` (Numba,
envelope storage after a bandwidth-reducing ordering; a matrix it finds indefinite is
reported, so that Newton can take its projected Hessian) or, on request, SuperLU's LU.
:class:`FreeSubmatrix` extracts the free-dof block of a CSR matrix of fixed pattern by one
gather of its data.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .kernels_cholesky import envelope_cholesky, envelope_precondition, pcg_envelope, scatter_into_envelope


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


class DiagonalAdd:
    """Add a vector to the diagonal of CSR matrices that share one pattern, in place.

    The positions of the diagonal entries are found once per pattern; a matrix without
    every diagonal entry (or with duplicate entries) gets ``a + diag(values)`` instead.
    """

    def __init__(self):
        self._indptr = self._indices = self._positions = None

    def __call__(self, a: sp.csr_matrix, values: np.ndarray) -> sp.csr_matrix:
        a = a.tocsr()
        if self._indptr is None or not (np.array_equal(a.indptr, self._indptr)
                                        and np.array_equal(a.indices, self._indices)):
            rows = np.repeat(np.arange(a.shape[0]), np.diff(a.indptr))
            positions = np.flatnonzero(a.indices == rows)
            self._indptr, self._indices = a.indptr.copy(), a.indices.copy()
            self._positions = positions if np.array_equal(rows[positions], np.arange(a.shape[0])) else None
        if self._positions is None:
            return a + sp.diags(values)
        a.data[self._positions] += values
        return a


class DiagonalBlockAdd:
    """Add 3x3 blocks to the diagonal blocks (vertex ``i``: rows and columns ``3 i .. 3 i + 2``)
    of CSR matrices that share one pattern, in place.

    The positions of the diagonal blocks' entries are found once per pattern; the matrix
    must hold every entry of those blocks (the Hessians of :mod:`heml_gym.forces.hessian`
    do).
    """

    def __init__(self):
        self._indptr = self._indices = self._positions = None

    def __call__(self, a: sp.csr_matrix, vertices: np.ndarray, blocks: np.ndarray) -> sp.csr_matrix:
        """``a`` with ``blocks (k, 3, 3)`` added to the diagonal blocks of ``vertices (k,)``."""
        a = a.tocsr()
        if self._indptr is None or not (np.array_equal(a.indptr, self._indptr)
                                        and np.array_equal(a.indices, self._indices)):
            if not a.has_sorted_indices:
                a.sort_indices()
            rows = np.repeat(np.arange(a.shape[0]), np.diff(a.indptr))
            positions = np.flatnonzero(a.indices // 3 == rows // 3)
            if len(positions) != 3 * a.shape[0]:
                raise ValueError("the matrix does not hold every entry of its 3x3 diagonal blocks")
            self._indptr, self._indices = a.indptr.copy(), a.indices.copy()
            self._positions = positions.reshape(-1, 3, 3)
        np.add.at(a.data, self._positions[np.asarray(vertices, dtype=np.int64)], blocks)
        return a


class NotPositiveDefinite(ValueError):
    """The matrix given to :class:`EnvelopeCholesky` is not symmetric positive definite."""


class EnvelopeLayout:
    """Where the lower factor of a sparse symmetric matrix lives in envelope storage.

    ``inverse[i]``: the position of row ``i`` in the factor's order (reverse Cuthill-McKee
    or the natural order, whichever has the smaller envelope); ``first[r]``: the first
    stored column of factor row ``r``; ``ptr``: the offsets of the rows in the values
    array of length ``size``. Used by :class:`EnvelopeCholesky` and by solvers that
    assemble their matrices straight into envelope storage (scalar Laplacians of
    :class:`heml_gym.solvers.QuasiNewtonSolver`).
    """

    def __init__(self, inverse: np.ndarray, first: np.ndarray):
        n = len(first)
        self.inverse = np.ascontiguousarray(inverse, dtype=np.int64)
        self.first = np.ascontiguousarray(first, dtype=np.int64)
        self.ptr = np.concatenate([[0], np.cumsum(np.arange(n) - self.first + 1)]).astype(np.int64)
        self.size = int(self.ptr[-1])

    @classmethod
    def of(cls, a: sp.csr_matrix) -> "EnvelopeLayout":
        """The layout of the symmetric pattern of ``a`` (CSR) after the better ordering."""
        a = a.tocsr()
        n = a.shape[0]
        rows = np.repeat(np.arange(n), np.diff(a.indptr))
        cols = a.indices.astype(np.int64)

        def candidate(order):
            inverse = np.empty(n, dtype=np.int64)
            inverse[order] = np.arange(n)
            first = np.arange(n, dtype=np.int64)
            np.minimum.at(first, inverse[rows], inverse[cols])
            return inverse, first, int(np.sum(np.arange(n) - first + 1))

        natural = candidate(np.arange(n))
        rcm = candidate(reverse_cuthill_mckee(a, symmetric_mode=True).astype(np.int64))
        inverse, first, _ = min(natural, rcm, key=lambda c: c[-1])
        return cls(inverse, first)

    def positions(self, rows: np.ndarray, cols: np.ndarray, upper: str | int = "mirror") -> np.ndarray:
        """Index in the values array of each entry ``(rows[k], cols[k])`` (original
        numbering) of the lower factor. An entry above the diagonal in the factor's order
        maps to its mirror (``upper="mirror"``) or to the given integer (e.g. -1: skip)."""
        r, c = self.inverse[np.asarray(rows, dtype=np.int64)], self.inverse[np.asarray(cols, dtype=np.int64)]
        if upper == "mirror":
            r, c = np.maximum(r, c), np.minimum(r, c)
            if np.any(c < self.first[r]):
                raise ValueError("an entry lies outside the envelope of the analysed pattern")
            return (self.ptr[r] + c - self.first[r]).astype(np.int64)
        return np.where(c <= r, self.ptr[r] + c - self.first[r], int(upper)).astype(np.int64)


class EnvelopeCholesky:
    """``A = P^T L L^T P`` for a sparse symmetric positive definite ``A`` (CSR).

    The symmetric ordering ``P`` is reverse Cuthill-McKee or the given order, whichever has
    the smaller envelope; ``L`` is stored row by row from each row's first nonzero to the
    diagonal (Cholesky fills in only inside that envelope). The pattern is analysed once:
    :meth:`factor` with a matrix of the same pattern only scatters and factorises.

    On the 1,440-dof system of a LapGym-size slab (15 x 15 x 1 cells) this factorises in
    about 2 ms and solves in about 0.06 ms on one core, against 5.8 and 0.17 ms for
    SuperLU's LU (measured alone; ``benchmarks/speed/simulation_speed.py`` times the whole step). Its cost grows with the square of
    the bandwidth, so it suits meshes with a short dimension (slabs, flaps, lobes); for
    bulky 3D meshes a nested-dissection factorisation has less fill.
    """

    def __init__(self, a: sp.csr_matrix):
        self._analyse(a.tocsr())
        self.factor(a)

    def _analyse(self, a):
        n = a.shape[0]
        self._indptr, self._indices = a.indptr, a.indices
        layout = EnvelopeLayout.of(a)
        self.layout = layout
        self._inverse, self._first, self._ptr = layout.inverse, layout.first, layout.ptr
        rows = np.repeat(np.arange(n), np.diff(a.indptr))
        self._target = layout.positions(rows, a.indices.astype(np.int64), upper=-1)
        self._values = np.zeros(layout.size)
        self._b = np.empty(n)
        self._x = np.empty(n)
        self.envelope_size = layout.size

    def factor(self, a: sp.csr_matrix) -> None:
        """Factorise ``a`` (same pattern as the analysed matrix, else analysed afresh).

        Raises :class:`NotPositiveDefinite` naming the failing pivot.
        """
        a = a.tocsr()
        if not (a.indptr is self._indptr and a.indices is self._indices) and not (
                np.array_equal(a.indptr, self._indptr) and np.array_equal(a.indices, self._indices)):
            self._analyse(a)
        scatter_into_envelope(np.ascontiguousarray(a.data, dtype=np.float64), self._target, self._values)
        bad = envelope_cholesky(self._first, self._ptr, self._values)
        if bad >= 0:
            raise NotPositiveDefinite(f"pivot {bad} of {a.shape[0]} is not positive")

    def kernel_args(self):
        """``(first, ptr, values, inverse)``: the factor for
        :func:`heml_gym.kernels_cholesky.envelope_precondition` inside other kernels."""
        return self._first, self._ptr, self._values, self._inverse

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` (a new array)."""
        x = np.empty(len(b))
        envelope_precondition(self._first, self._ptr, self._values, self._inverse,
                              np.ascontiguousarray(b, dtype=np.float64), x, self._b, self._x)
        return x

    def pcg(self, a: sp.csr_matrix, b: np.ndarray, rtol: float, max_iter: int):
        """Solve ``a x = b`` by conjugate gradients preconditioned with this factorisation
        (of an earlier matrix), in one Numba call. Returns ``(x, iterations, converged)``
        as :func:`pcg`."""
        a = a.tocsr()
        x = np.empty(a.shape[0])
        iterations, converged = pcg_envelope(
            a.indptr, a.indices, np.ascontiguousarray(a.data, dtype=np.float64),
            np.ascontiguousarray(b, dtype=np.float64), self._first, self._ptr, self._values,
            self._inverse, float(rtol), int(max_iter), x)
        return x, int(iterations), bool(converged)


class LaggedFactorPCG:
    """Solve SPD systems by CG preconditioned with an earlier system's factorisation.

    ``rtol``: CG stops at ``|r| <= rtol |b|``. ``max_iter``: past this many CG
    iterations the current matrix is factorised afresh and used directly. ``key``
    (e.g. the free-dof mask and the time step) forces a new factorisation when it changes.
    ``factorization``: ``"cholesky"`` (:class:`EnvelopeCholesky`, CG in one Numba call;
    a matrix found not positive definite gives a NaN solution) or ``"lu"`` (SuperLU, CG
    in Python).
    Counters: ``factorizations``, ``last_iterations``.
    """

    def __init__(self, rtol: float = 1e-8, max_iter: int = 20, factorization: str = "cholesky"):
        if factorization not in ("cholesky", "lu"):
            raise ValueError(f"factorization must be 'cholesky' or 'lu', got {factorization!r}")
        self.rtol = float(rtol)
        self.max_iter = int(max_iter)
        self.factorization = factorization
        self._lu = None
        self._cholesky = None
        self._key = None
        self.factorizations = 0
        self.last_iterations = 0

    def reset(self) -> None:
        """Forget the factorisation (the next solve factorises)."""
        self._lu, self._key = None, None

    def _factor(self, a, key):
        """Factorise ``a``; False when the Cholesky factorisation finds it indefinite."""
        self._lu, self._key = None, None
        if self.factorization == "cholesky":
            try:
                if self._cholesky is None:
                    self._cholesky = EnvelopeCholesky(a)
                else:
                    self._cholesky.factor(a)  # reuses the analysis of the pattern
            except NotPositiveDefinite:
                return False
            self._lu = self._cholesky
        else:
            self._lu = spla.splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        self._key = key
        self.factorizations += 1
        return True

    def solve(self, a: sp.csr_matrix, b: np.ndarray, key=None) -> np.ndarray:
        """``a^-1 b`` to ``rtol``. With the Cholesky factorisation, a matrix found not
        positive definite gives NaNs (Newton then takes the projected Hessian)."""
        if self._lu is None or key != self._key:
            self.last_iterations = 0
            if not self._factor(a, key):
                return np.full_like(b, np.nan)
            return self._lu.solve(b)
        if isinstance(self._lu, EnvelopeCholesky):
            x, iterations, converged = self._lu.pcg(a, b, self.rtol, self.max_iter)
        else:
            x, iterations, converged = pcg(a, b, self._lu.solve, self.rtol, self.max_iter)
        self.last_iterations = iterations
        if converged:
            return x
        if not self._factor(a, key):
            return np.full_like(b, np.nan)
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
