"""Sparse stiffness matrices ``K = d2W/dx2`` of the force fields, for implicit integrators.

``K`` is ``3n x 3n`` (dof ``3 i + d``), symmetric, in SI units (N/m), with the sign of
``d2W/dx2``: ``forces(x + dx) ~= forces(x) - K dx``. It is returned as a
:class:`scipy.sparse.csr_matrix` with sorted indices, one dense 3x3 block per pair of
vertices sharing a mesh edge plus the diagonal blocks.

The sparsity pattern (:class:`HessianPattern`) and, per element, the position of each of
its 3x3 blocks in the CSR ``data`` array (a :class:`HessianCache`) are computed once per
mesh and owned by the force field (``field.hessian_cache``, built on first use), so an
assembly is one Numba pass that adds element blocks into ``data``.

``project=True`` makes every element contribution positive semi-definite (the
definiteness fix of a Newton solver); ``project=False`` gives the exact Hessian. For HEML
the fix clamps the negative eigenvalues of ``d2Psi/dF2`` per tet, in closed form (see
:mod:`heml_gym.forces.kernels_hessian`); ``method="eigh"`` clamps those of the 12x12
element matrix with LAPACK instead (a slower reference).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import kernels_hessian as kh

__all__ = [
    "HessianPattern",
    "HessianCache",
    "hessian_pattern",
    "heml_hessian",
    "heml_hessian_data",
    "heml_element_hessians",
    "heml_f_eigensystems",
    "spring_hessian",
]

_NO_ELEMENTS = np.zeros((0, 12, 12))
_NO_DATA = np.zeros(0)
_METHODS = {"analytic": kh.ANALYTIC_PROJECTION, "eigh": kh.EIGH_PROJECTION}


class HessianPattern:
    """CSR pattern of a ``3n x 3n`` matrix with a 3x3 block on each edge and the diagonal.

    Block row ``i`` holds the blocks of ``i`` and its edge neighbours, columns ascending;
    scalar row ``3 i + d`` holds ``3 * deg_i`` entries. Entry ``(3 i + d, 3 j + e)`` lies at
    ``block_start(i, j) + d * row_stride[i] + e`` in ``data``.

    Attributes
    ----------
    n_vertices : int
    shape : (int, int)
    indptr, indices : int32 ndarrays (int64 if the matrix needs it)
    row_stride : (n,) int64, ``3 * deg_i``
    nnz : int
    """

    def __init__(self, n_vertices: int, edges: np.ndarray):
        n = int(n_vertices)
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        diag = np.arange(n, dtype=np.int64)
        rows = np.concatenate([edges[:, 0], edges[:, 1], diag])
        cols = np.concatenate([edges[:, 1], edges[:, 0], diag])
        keys = np.unique(rows * n + cols)  # sorted by (row, col), duplicates dropped
        rows, cols = keys // n, keys % n
        deg = np.bincount(rows, minlength=n).astype(np.int64)
        block_ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(deg, out=block_ptr[1:])
        self.n_vertices = n
        self.shape = (3 * n, 3 * n)
        self.nnz = int(9 * block_ptr[-1])
        self._keys = keys
        self._block_ptr = block_ptr
        self.row_stride = 3 * deg
        # scalar row 3 i + d starts at 9 block_ptr[i] + d * 3 deg_i
        indptr = np.empty(3 * n + 1, dtype=np.int64)
        indptr[:-1] = (9 * block_ptr[:-1, None] + np.arange(3)[None, :] * self.row_stride[:, None]).ravel()
        indptr[-1] = self.nnz
        # columns: for each block row i, d in 0..2: 3 j + e over the row's blocks j
        local = np.arange(len(keys)) - np.repeat(block_ptr[:-1], deg)  # position in its row
        cols3 = (3 * cols[:, None] + np.arange(3)[None, :])  # (blocks, 3)
        indices = np.empty(self.nnz, dtype=np.int64)
        # position of entry (d, e) of block b: 9 bp[i] + d * 3 deg_i + 3 local_b + e
        start = 9 * block_ptr[rows] + 3 * local
        for d in range(3):
            pos = (start + d * self.row_stride[rows])[:, None] + np.arange(3)[None, :]
            indices[pos.ravel()] = cols3.ravel()
        idx_dtype = np.int32 if max(self.nnz, 3 * n) < np.iinfo(np.int32).max else np.int64
        self.indptr = indptr.astype(idx_dtype)
        self.indices = indices.astype(idx_dtype)
        self._block_start = start

    def block_start(self, i, j) -> np.ndarray:
        """Position in ``data`` of entry ``(3 i, 3 j)`` for vertex pairs ``(i, j)`` (arrays).

        Raises ``KeyError`` if a pair is not in the pattern.
        """
        i = np.asarray(i, dtype=np.int64)
        j = np.asarray(j, dtype=np.int64)
        key = i * self.n_vertices + j
        b = np.searchsorted(self._keys, key)
        b = np.minimum(b, len(self._keys) - 1)
        if not np.all(self._keys[b] == key):
            raise KeyError("vertex pair outside the sparsity pattern")
        return self._block_start[b]

    def element_blocks(self, cells: np.ndarray) -> np.ndarray:
        """``(m, k, k)`` block starts for elements of ``k`` vertices (a tet: 4, an edge: 2)."""
        cells = np.asarray(cells, dtype=np.int64)
        return np.ascontiguousarray(self.block_start(cells[:, :, None], cells[:, None, :]))

    @property
    def diagonal(self) -> np.ndarray:
        """``(3n,)`` positions in ``data`` of the diagonal entries ``(k, k)``, e.g. to add a
        lumped mass ``M / dt^2`` in place: ``data[pattern.diagonal] += m / dt**2``."""
        n = self.n_vertices
        start = self.block_start(np.arange(n), np.arange(n))
        d = np.arange(3)
        return (start[:, None] + d[None, :] * self.row_stride[:, None] + d[None, :]).ravel()

    def zeros(self) -> np.ndarray:
        """A zero ``data`` array for this pattern."""
        return np.zeros(self.nnz)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The CSR matrix of ``data`` (not copied; the index arrays are copied)."""
        m = sp.csr_matrix((data, self.indices.copy(), self.indptr.copy()), shape=self.shape)
        m.has_sorted_indices = True
        return m


class HessianCache:
    """What a Hessian assembly precomputes once per mesh (shared by the fields of every
    material on it): the sparsity pattern and each element's block positions in it."""

    def __init__(self, n_vertices: int, cells: np.ndarray, edges: np.ndarray):
        self.pattern = HessianPattern(n_vertices, edges)
        self.blk = self.pattern.element_blocks(cells)


def hessian_pattern(force) -> HessianPattern:
    """The sparsity pattern of ``force.hessian`` (HEML, the fields that share HEML's
    energy, mass-spring): the field's own, built once per mesh."""
    return force.hessian_cache.pattern


def _mode(project: bool, method: str) -> int:
    if not project:
        return kh.NO_PROJECTION
    try:
        return _METHODS[method]
    except KeyError:
        raise ValueError(f"method must be one of {sorted(_METHODS)}, got {method!r}") from None


def heml_hessian_data(force, x, project: bool = True, method: str = "analytic",
                      out: np.ndarray | None = None) -> np.ndarray:
    """The CSR ``data`` of the HEML stiffness matrix (pattern: :func:`hessian_pattern`),
    written into ``out`` if given (overwritten): no allocation, no scipy object.

    After a projected assembly ``force.n_clamped`` holds the number of negative F-space
    modes that were clamped.
    """
    if len(force.params) > 4:  # the kernels read at most 4 law parameters
        raise ValueError(f"law with {len(force.params)} parameters: at most 4 supported")
    hd = force.hessian_cache
    x = force.check_positions(x)
    mode = _mode(project, method)
    if out is None:
        out = hd.pattern.zeros()
    else:
        out.fill(0.0)
    m = force.mesh
    if mode == kh.NO_PROJECTION and force.split:  # Neo-Hookean: fixed springs + volume term
        kh.heml_split_hessian_kernel(x, m.tets, force.inv_det, force.spring_weights, force.law_id,
                                     force.params, hd.blk, hd.pattern.row_stride, out)
        force.n_clamped = 0
        return out
    force.n_clamped = kh.heml_hessian_kernel(
        x, m.tets, force.coef, force.q, force.use_q, force.law_id, force.params, m.rest_edge_inverses,
        mode, hd.blk, hd.pattern.row_stride, out, _NO_ELEMENTS)
    return out


def heml_hessian(force, x, project: bool = True, method: str = "analytic") -> sp.csr_matrix:
    """Stiffness matrix ``d2W/dx2`` (N/m, ``3n x 3n`` CSR) of a :class:`HemlForce` at ``x``.

    ``project=True`` clamps, per tet, the negative eigenvalues of ``d2Psi/dF2``
    (``method="analytic"``, closed form) or of the 12x12 element matrix
    (``method="eigh"``); either way the result is positive semi-definite and equals the
    exact Hessian wherever the element Hessians already are. Elements whose law is
    undefined (``J <= 0`` for ln J laws) give NaN entries.
    """
    data = heml_hessian_data(force, x, project, method)
    return force.hessian_cache.pattern.matrix(data)


def heml_element_hessians(force, x, project: bool = True, method: str = "analytic") -> np.ndarray:
    """Per-tet Hessians ``(m, 12, 12)`` (J/m^2; local dof ``3 a + d``)."""
    hd = force.hessian_cache
    x = force.check_positions(x)
    m = force.mesh
    out = np.empty((m.n_tets, 12, 12))
    kh.heml_hessian_kernel(x, m.tets, force.coef, force.q, force.use_q, force.law_id,
                           force.params, m.rest_edge_inverses, _mode(project, method), hd.blk,
                           hd.pattern.row_stride, _NO_DATA, out)
    return out


def heml_f_eigensystems(force, x):
    """Per tet the 9 eigenvalues of ``d2Psi/dF2`` (Pa) and their mode gradients.

    Returns ``lam (m, 9)`` and ``b (m, 9, 12)`` with ``K_T = V0 sum_k lam_k b_k b_k^T``.
    """
    x = force.check_positions(x)
    m = force.mesh
    lam = np.empty((m.n_tets, 9))
    b = np.empty((m.n_tets, 9, 12))
    kh.heml_f_eigensystems(x, m.tets, force.coef, force.q, force.use_q, force.law_id,
                           force.params, m.rest_edge_inverses, lam, b)
    return lam, b


def spring_hessian(force, x, project: bool = True) -> sp.csr_matrix:
    """Stiffness matrix (N/m) of a :class:`MassSpringForce`: per edge
    ``k [(1 - L/l)(I - n n^T) + n n^T]``, with ``1 - L/l`` clamped at 0 if ``project``
    (then PSD: a compressed spring keeps only its axial stiffness)."""
    hd = force.hessian_cache
    x = force.check_positions(x)
    data = hd.pattern.zeros()
    kh.spring_hessian_assemble(x, force.edges, force.stiffness, force.rest_length, bool(project),
                               hd.blk, hd.pattern.row_stride, data)
    return hd.pattern.matrix(data)
