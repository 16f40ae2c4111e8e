"""Mass-spring baseline: linear springs on the mesh edges (not continuum mechanics)."""

from __future__ import annotations

import numpy as np

from ..mesh import EDGE_PAIRS
from . import kernels_mass_spring
from .base import ForceField

#: Stiffness calibration: ``k_e = SPRING_CALIBRATION * E * (sum of adjacent tet volumes) / L_e^2``.
#: Averaging ``(n . eps n)^2`` over isotropic edge directions gives 1/5, and each tet's
#: volume is counted on its 6 edges, so 5/6 makes the network store ``E eps^2 V / 2`` under
#: a uniaxial strain ``eps`` with the lateral directions held. A spring network still has
#: no Poisson effect of its own choosing and no resistance to inversion.
SPRING_CALIBRATION = 5.0 / 6.0


class MassSpringForce(ForceField):
    """Linear springs on every mesh edge, ``W = sum_e k_e (l_e - L_e)^2 / 2``.

    Stiffness ``k_e = (5/6) E V_e / L_e^2`` (N/m), with ``E`` the material's small-strain
    Young's modulus (Pa), ``V_e`` the total rest volume of the tets around edge ``e`` (m^3)
    and ``L_e`` its rest length (m). Only ``E`` of the material is used: the law, the
    Poisson ratio and large-strain behaviour are not represented.
    """

    name = "mass-spring"

    def __init__(self, mesh, material):
        super().__init__(mesh, material)
        self.edges = np.ascontiguousarray(mesh.edges)
        self.rest_length = np.ascontiguousarray(mesh.edge_lengths())
        # total volume of the tets around each edge
        tet_edges = np.sort(mesh.tets[:, EDGE_PAIRS].reshape(-1, 2), axis=1)
        n = mesh.n_vertices
        keys = self.edges[:, 0] * n + self.edges[:, 1]
        idx = np.searchsorted(keys, tet_edges[:, 0] * n + tet_edges[:, 1])
        edge_volume = np.bincount(idx, weights=np.repeat(mesh.volumes, 6), minlength=len(keys))
        self.stiffness = SPRING_CALIBRATION * material.young_modulus * edge_volume / self.rest_length**2

    @property
    def n_elements(self) -> int:
        return len(self.edges)

    def _args(self):
        return self.edges, self.stiffness, self.rest_length

    def _energy_range(self, x, lo, hi):
        return kernels_mass_spring.spring_energy_chunk(x, *self._args(), lo, hi)

    def _energy_parallel(self, x, n_chunks):
        return kernels_mass_spring.spring_energy_parallel(x, *self._args(), n_chunks)

    def _add_forces_range(self, x, f, lo, hi):
        kernels_mass_spring.spring_forces_chunk(x, *self._args(), f, lo, hi)

    def _add_forces_parallel(self, x, buf):
        kernels_mass_spring.spring_forces_parallel(x, *self._args(), buf)
