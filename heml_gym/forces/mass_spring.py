"""Mass-spring baseline: linear springs on the mesh edges (not continuum mechanics)."""

from __future__ import annotations

import numpy as np

from . import kernels_mass_spring
from .base import ForceField
from .heml import assembled_edge_weights
from .hessian import HessianCache, spring_hessian

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
    has_hessian = True

    def __init__(self, mesh, material, _shared=None):
        super().__init__(mesh, material)
        if _shared is None:
            edges = np.ascontiguousarray(mesh.edges)
            rest_length = np.ascontiguousarray(mesh.edge_lengths())
            # total volume of the tets around each edge
            _, edge_volume = assembled_edge_weights(mesh, np.repeat(mesh.volumes[:, None], 6, axis=1))
            _shared = (edges, rest_length, SPRING_CALIBRATION * edge_volume / rest_length**2, [None])
        self._shared = _shared
        self.edges, self.rest_length, unit_stiffness, _ = _shared
        self.stiffness = material.young_modulus * unit_stiffness  # N/m

    def with_material(self, material) -> "MassSpringForce":
        """The same springs with the stiffness of ``material`` (edges, rest lengths and
        the Hessian pattern shared)."""
        return MassSpringForce(self.mesh, material, _shared=self._shared)

    @property
    def hessian_cache(self) -> HessianCache:
        """The Hessian's pattern and block positions, shared by the fields of one mesh
        (built on first use)."""
        if self._shared[3][0] is None:
            self._shared[3][0] = HessianCache(self.mesh.n_vertices, self.edges, self.edges)
        return self._shared[3][0]

    @property
    def n_elements(self) -> int:
        return len(self.edges)

    def _args(self):
        return self.edges, self.stiffness, self.rest_length

    def _energy_serial(self, x):
        return kernels_mass_spring.spring_energy_chunk(x, *self._args(), 0, self.n_elements)

    def _energy_parallel(self, x, n_chunks):
        return kernels_mass_spring.spring_energy_parallel(x, *self._args(), n_chunks)

    def _add_forces_serial(self, x, f):
        kernels_mass_spring.spring_forces_chunk(x, *self._args(), f, 0, self.n_elements)

    def _add_forces_parallel(self, x, buf):
        kernels_mass_spring.spring_forces_parallel(x, *self._args(), buf)

    def hessian(self, x, project=True):
        """Stiffness matrix ``d2W/dx2`` (N/m) at ``x``: a ``3n x 3n`` scipy CSR matrix.

        Per edge ``k [(1 - L/l)(I - n n^T) + n n^T]``; ``project=True`` clamps
        ``1 - L/l`` at 0 (a compressed spring's transverse part), which makes it PSD.
        """
        return spring_hessian(self, x, project)
