"""Textbook F-based P1 finite elements: the independent cross-check of HEML."""

from __future__ import annotations

import numpy as np

from . import kernels_fem
from .base import ForceField
from .heml import SameEnergyAsHeml


class FemForce(SameEnergyAsHeml, ForceField):
    """P1 FEM with ``F = Ds Dm^-1``, ``P = dPsi/dF`` and ``f = -V0 P Dm^-T`` per tet.

    Stresses come from each law's textbook formula in ``F`` (see
    :mod:`heml_gym.forces.kernels_fem`), not from the invariant derivatives HEML uses.
    """

    name = "F-FEM"

    def __init__(self, mesh, material):
        super().__init__(mesh, material)
        self.dm_inv = mesh.rest_edge_inverses
        self.vol = np.ascontiguousarray(mesh.volumes)
        self.law_id = np.int64(material.law_id)
        self.params = np.ascontiguousarray(material.params, dtype=np.float64)

    def _args(self):
        return self.mesh.tets, self.dm_inv, self.vol, self.law_id, self.params

    def _energy_serial(self, x):
        return kernels_fem.fem_energy_chunk(x, *self._args(), 0, self.n_elements)

    def _energy_parallel(self, x, n_chunks):
        return kernels_fem.fem_energy_parallel(x, *self._args(), n_chunks)

    def _add_forces_serial(self, x, f):
        kernels_fem.fem_forces_chunk(x, *self._args(), f, 0, self.n_elements)

    def _add_forces_parallel(self, x, buf):
        kernels_fem.fem_forces_parallel(x, *self._args(), buf)

