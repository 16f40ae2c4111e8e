"""HEML: the P1 hyperelastic force field written on the mesh edges.

``C = F^T F`` of a P1 tet is linear in its six squared edge lengths ``s_k``:
``C = sum_k s_k A_k`` with constant ``A_k = Dm^-T E_k Dm^-1``, where ``E_k`` places
``s_k`` in the Gram matrix ``G = Ds^T Ds`` (``G_aa = s_0a``,
``G_ab = (s_0a + s_0b - s_ab) / 2``). Hence ``I1 = a . s`` and ``I2 = s^T Q s / 2`` with
``a_k = tr A_k`` and ``Q_kl = a_k a_l - tr(A_k A_l)`` precomputed per tet, and ``J`` is
the signed volume ratio. The force is a set of edge forces plus one volume term; see
:mod:`heml_gym.forces.kernels_heml`.
"""

from __future__ import annotations

import numpy as np

from ..mesh import EDGE_PAIRS
from . import kernels_heml
from .base import ForceField

# Upper-triangle (k <= l) index pairs of a 6x6 symmetric matrix, row by row: 21 entries.
Q_UPPER = np.array([(k, l) for k in range(6) for l in range(k, 6)], dtype=np.int64)


def gram_coefficients() -> np.ndarray:
    """``(6, 3, 3)`` matrices ``E_k`` with ``G = Ds^T Ds = sum_k s_k E_k``."""
    e = np.zeros((6, 3, 3))
    for k, (a, b) in enumerate(EDGE_PAIRS):
        if a == 0:  # s_0b sits on the diagonal G_bb and in half of each G_bc
            i = b - 1
            e[k, i, i] = 1.0
            for j in range(3):
                if j != i:
                    e[k, i, j] += 0.5
                    e[k, j, i] += 0.5
        else:  # s_ab enters G_ab with -1/2
            e[k, a - 1, b - 1] = e[k, b - 1, a - 1] = -0.5
    return e


def edge_tensors(rest_edges: np.ndarray) -> np.ndarray:
    """``A_k`` per tet, ``(m, 6, 3, 3)``, from rest edge matrices ``Dm`` ``(m, 3, 3)``."""
    dm_inv = np.linalg.inv(rest_edges)
    return np.einsum("tia,kab,tbj->tkij", dm_inv.transpose(0, 2, 1), gram_coefficients(), dm_inv)


def heml_coefficients(vertices: np.ndarray, tets: np.ndarray, with_q: bool):
    """Per-tet HEML constants: ``coef (m, 8) = (V0, 1/(6 V0), a_0..a_5)`` and ``q (m, 21)``.

    ``q`` holds the upper triangle of ``Q``; it is ``(1, 21)`` zeros when not needed.
    """
    x = vertices[tets]
    dm = (x[:, 1:, :] - x[:, :1, :]).transpose(0, 2, 1)  # columns X_a - X_0
    det = np.linalg.det(dm)
    a_mats = edge_tensors(dm)
    a = np.einsum("tkii->tk", a_mats)
    coef = np.empty((len(tets), 8))
    coef[:, 0] = det / 6.0
    coef[:, 1] = 1.0 / det
    coef[:, 2:] = a
    if with_q:
        tr_aa = np.einsum("tkij,tlji->tkl", a_mats, a_mats)
        q_full = a[:, :, None] * a[:, None, :] - tr_aa
        q = np.ascontiguousarray(q_full[:, Q_UPPER[:, 0], Q_UPPER[:, 1]])
    else:
        q = np.zeros((1, 21))
    return coef, q


def assembled_edge_weights(mesh, tet_edge_weights: np.ndarray):
    """Sum per-tet edge weights ``(m, 6)`` onto the mesh's unique edges.

    Returns ``(edges (e, 2), weights (e,))`` with the edges as in :attr:`TetMesh.edges`.
    """
    n = mesh.n_vertices
    edges = np.ascontiguousarray(mesh.edges)
    pairs = np.sort(mesh.tets[:, EDGE_PAIRS].reshape(-1, 2), axis=1)
    idx = np.searchsorted(edges[:, 0] * n + edges[:, 1], pairs[:, 0] * n + pairs[:, 1])
    weights = np.bincount(idx, weights=tet_edge_weights.reshape(-1), minlength=len(edges))
    return edges, weights


class HemlForce(ForceField):
    """Hyper-Elastic Mass-Links force field for any law of :mod:`heml_gym.materials`.

    Exactly P1 finite elements (it agrees with :class:`heml_gym.FemForce` to rounding),
    evaluated as state-dependent edge springs plus one volume term per tet. For a law
    with constant ``dPsi/dI1`` (Neo-Hookean) the spring weights are constants (``split``):
    they are precomputed, and a blocked kernel that vectorises evaluates springs and
    volume term together.
    """

    name = "HEML"

    def __init__(self, mesh, material):
        super().__init__(mesh, material)
        self.use_q = bool(material.needs_i2)
        self.coef, self.q = heml_coefficients(mesh.vertices, mesh.tets, self.use_q)
        # constant-major copies for the force and energy kernels (a block reads each contiguously)
        self.coef_t = np.ascontiguousarray(self.coef.T)
        self.q_t = np.ascontiguousarray(self.q.T)
        # 32-bit vertex indices for the force and energy kernels: less memory traffic (on 1 M
        # tets, 2 threads: 97 against 77 M tets/s with the 64-bit ones)
        small = mesh.n_vertices < np.iinfo(np.int32).max
        self._force_tets = np.ascontiguousarray(mesh.tets, dtype=np.int32 if small else np.int64)
        self._law = np.int64(material.law_id)
        self._params = np.ascontiguousarray(material.params, dtype=np.float64)
        # Constant Psi_1 (Neo-Hookean): the I1 part is a fixed spring network, its weights
        # 2 V0 Psi_1 a_k precomputed; a blocked kernel that vectorises does the rest.
        self.split = material.constant_psi1 is not None and not self.use_q
        if self.split:
            # stored edge-major, (6, m), so a block of tets reads each weight contiguously
            self.spring_weights = np.ascontiguousarray(
                (2.0 * material.constant_psi1 * self.coef[:, 0:1] * self.coef[:, 2:]).T)
            self.inv_det = np.ascontiguousarray(self.coef[:, 1])

    def _args(self):
        """Arguments of the energy and generic force kernels (constant-major per-tet data)."""
        return self._force_tets, self.coef_t, self.q_t, self.use_q, self._law, self._params

    def _energy_serial(self, x):
        return kernels_heml.heml_energy_chunk(x, *self._args(), 0, self.n_elements)

    def _energy_parallel(self, x, n_chunks):
        return kernels_heml.heml_energy_parallel(x, *self._args(), n_chunks)

    def _split_args(self):
        return self._force_tets, self.inv_det, self.spring_weights, self._law, self._params

    def _add_forces_serial(self, x, f):
        if self.split:
            kernels_heml.constant_psi1_forces_chunk(x, *self._split_args(), f, 0, self.mesh.n_tets)
        else:
            kernels_heml.heml_forces_chunk(x, *self._args(), f, 0, self.n_elements)

    def _add_forces_parallel(self, x, buf):
        if self.split:
            kernels_heml.constant_psi1_forces_parallel(x, *self._split_args(), buf)
        else:
            kernels_heml.heml_forces_parallel(x, *self._args(), buf)

    def hessian(self, x, project=True):
        """Stiffness matrix ``d2W/dx2`` (N/m) at ``x``: a ``3n x 3n`` scipy CSR matrix.

        ``forces(x + dx) ~= forces(x) - K dx``. With ``project=True`` each tet's
        contribution is made positive semi-definite (negative eigenvalues of
        ``d2Psi/dF2`` clamped to zero, in closed form); ``project=False`` gives the
        exact Hessian. See :mod:`heml_gym.forces.hessian`.
        """
        from .hessian import heml_hessian

        return heml_hessian(self, x, project)
