"""Nonlinear mass-tensor force field (Cotin, Picinbono, Delingette) for Saint Venant-Kirchhoff.

Units: rest and current positions in m, Lamé constants in Pa, energies in J, forces in N.

With the P1 shape-function gradients ``D_j = grad N_j`` (``D_1..D_3`` the rows of
``Dm^-1``, ``Dm = [X_1 - X_0, X_2 - X_0, X_3 - X_0]``; ``D_0 = -(D_1 + D_2 + D_3)``), the
displacement gradient of a tet is ``grad u = sum_j u_j D_j^T`` with ``u_j = x_j - X_j``,
and ``Psi = mu tr(E^2) + lam/2 (tr E)^2`` with ``E = (grad u + grad u^T + grad u^T grad u)/2``
expands, times the rest volume ``V0``, into a quartic polynomial in the ``u_j``:

    W = sum_jk u_j^T K_jk u_k + sum_jkl (u_j . u_k)(C_jkl . u_l)
        + sum_jklm D_jklm (u_j . u_k)(u_l . u_m)

    K_jk   = V0 [ lam/2 D_j D_k^T + mu/2 D_k D_j^T + mu/2 (D_j . D_k) I ]
    C_jkl  = V0 [ lam/2 (D_j . D_k) D_l + mu/2 ((D_l . D_k) D_j + (D_l . D_j) D_k) ]
    D_jklm = V0 [ lam/8 (D_j . D_k)(D_l . D_m)
                  + mu/8 ((D_j . D_m)(D_k . D_l) + (D_j . D_l)(D_k . D_m)) ]

The ``mu`` part of ``D`` is the textbook ``mu/4 (D_j . D_m)(D_k . D_l)`` symmetrised
under ``j <-> k`` (which leaves ``W`` unchanged, ``u_j . u_k`` being symmetric), so that
``D`` has the symmetries the force formula relies on; see
:mod:`heml_gym.forces.kernels_mass_tensor` for the force and the storage layout.

This is the same physics as :class:`heml_gym.HemlForce` with a
:class:`~heml_gym.materials.StVenantKirchhoff` material (identical to rounding), in a
different arithmetic: 592 precomputed numbers per tet and several thousand
multiply-adds per tet and force evaluation.
"""

from __future__ import annotations

import numpy as np

from ..materials import StVenantKirchhoff
from . import kernels_mass_tensor
from .base import ForceField
from .heml import SameEnergyAsHeml


def shape_gradients(mesh) -> np.ndarray:
    """P1 shape-function gradients ``D_j = grad N_j`` (1/m) per tet, shape ``(m, 4, 3)``."""
    grads = np.empty((mesh.n_tets, 4, 3))
    grads[:, 1:, :] = mesh.rest_edge_inverses  # row j - 1 of Dm^-1 is grad N_j
    grads[:, 0, :] = -grads[:, 1:, :].sum(axis=1)
    return grads


def mass_tensors(grads: np.ndarray, volumes: np.ndarray, mu: float, lam: float):
    """Full per-tet StVK mass tensors ``K (m, 4, 4, 3, 3)``, ``C (m, 4, 4, 4, 3)``, ``D (m, 4, 4, 4, 4)``.

    ``grads`` ``(m, 4, 3)`` in 1/m, ``volumes`` ``(m,)`` in m^3, ``mu, lam`` in Pa.
    """
    g = grads
    v = volumes
    dots = np.einsum("tja,tka->tjk", g, g)  # D_j . D_k
    eye = np.eye(3)
    K = (0.5 * lam * np.einsum("tja,tkb->tjkab", g, g)
         + 0.5 * mu * np.einsum("tka,tjb->tjkab", g, g)
         + 0.5 * mu * dots[:, :, :, None, None] * eye)
    K *= v[:, None, None, None, None]
    C = (0.5 * lam * np.einsum("tjk,tla->tjkla", dots, g)
         + 0.5 * mu * (np.einsum("tlk,tja->tjkla", dots, g) + np.einsum("tlj,tka->tjkla", dots, g)))
    C *= v[:, None, None, None, None]
    D = (0.125 * lam * np.einsum("tjk,tlm->tjklm", dots, dots)
         + 0.125 * mu * (np.einsum("tjm,tkl->tjklm", dots, dots) + np.einsum("tjl,tkm->tjklm", dots, dots)))
    D *= v[:, None, None, None, None]
    return K, C, D


class MassTensorForce(SameEnergyAsHeml, ForceField):
    """Nonlinear (StVK) mass-tensor force field with full per-tet tensors.

    Accepts only :class:`heml_gym.materials.StVenantKirchhoff`. Energies and forces equal
    those of :class:`heml_gym.HemlForce` and :class:`heml_gym.FemForce` on the same mesh
    and material to rounding.

    Attributes
    ----------
    K, C, D : ndarray
        Per-tet tensors, ``(m, 144)``, ``(m, 192)``, ``(m, 256)`` float64 (layout in
        :mod:`heml_gym.forces.kernels_mass_tensor`).
    memory_bytes : int
        Bytes of the precomputed tensors (``592 * 8`` per tet).
    """

    name = "Mass-Tensor"

    def __init__(self, mesh, material):
        if not isinstance(material, StVenantKirchhoff):
            raise TypeError(
                "MassTensorForce needs a heml_gym.materials.StVenantKirchhoff material, "
                f"got {type(material).__name__}"
            )
        super().__init__(mesh, material)
        m = mesh.n_tets
        grads = shape_gradients(mesh)
        K, C, D = mass_tensors(grads, mesh.volumes, material.mu, material.lam)
        self.K = np.ascontiguousarray(K.reshape(m, 144))
        self.C = np.ascontiguousarray(C.reshape(m, 192))
        self.D = np.ascontiguousarray(D.reshape(m, 256))
        self.memory_bytes = int(self.K.nbytes + self.C.nbytes + self.D.nbytes)
        self._u = np.empty((mesh.n_vertices, 3))

    def _displacements(self, x):
        kernels_mass_tensor.displacements(x, self.mesh.vertices, self._u)
        return self._u

    def _energy_serial(self, x):
        u = self._displacements(x)
        return kernels_mass_tensor.mass_tensor_energy_chunk(u, self.mesh.tets, self.K, self.C, self.D, 0, self.n_elements)

    def _energy_parallel(self, x, n_chunks):
        u = self._displacements(x)
        return kernels_mass_tensor.mass_tensor_energy_parallel(u, self.mesh.tets, self.K, self.C, self.D, n_chunks)

    def _add_forces_serial(self, x, f):
        u = self._displacements(x)
        kernels_mass_tensor.mass_tensor_forces_chunk(u, self.mesh.tets, self.K, self.C, self.D, f, 0, self.n_elements)

    def _add_forces_parallel(self, x, buf):
        m = self.mesh
        kernels_mass_tensor.mass_tensor_forces_parallel(x, m.vertices, m.tets, self.K, self.C, self.D, self._u, buf)

