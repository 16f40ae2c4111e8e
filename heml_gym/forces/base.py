"""Shared interface of the force fields: arrays in, arrays out, SI units."""

from __future__ import annotations

import numba
import numpy as np

from ..materials import Material
from ..mesh import TetMesh


class ForceField:
    """Elastic force field of a tet mesh.

    Subclasses implement :meth:`_energy` and :meth:`_add_forces`. Positions are ``(n, 3)``
    float64 arrays in metres, energies in joules, forces in newtons. ``forces(x)`` is
    ``-dW/dx``: the force the tissue exerts on its vertices.

    Forces are accumulated without races: the elements are split into one contiguous
    chunk per Numba thread, each chunk adds into its own buffer, the buffers are summed.
    """

    #: Short name used in tables and charts.
    name = "force field"

    def __init__(self, mesh: TetMesh, material: Material):
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a heml_gym.TetMesh, got {type(mesh).__name__}")
        if not isinstance(material, Material):
            raise TypeError(f"material must be a heml_gym.materials.Material, got {type(material).__name__}")
        self.mesh = mesh
        self.material = material
        self._buf = np.zeros((0, 0, 3))

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    def _positions(self, x) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.mesh.n_vertices, 3):
            raise ValueError(f"positions must have shape ({self.mesh.n_vertices}, 3), got {x.shape}")
        return x

    def _chunk_buffer(self) -> np.ndarray:
        n_chunks = numba.get_num_threads()
        shape = (n_chunks, self.mesh.n_vertices, 3)
        if self._buf.shape != shape:
            self._buf = np.zeros(shape)
        else:
            self._buf.fill(0.0)
        return self._buf

    def energy(self, x) -> float:
        """Elastic energy in joules at positions ``x`` (m)."""
        return float(self._energy(self._positions(x)))

    def forces(self, x, out: np.ndarray | None = None) -> np.ndarray:
        """Elastic forces ``-dW/dx`` in newtons at positions ``x`` (m), shape ``(n, 3)``.

        If ``out`` is given the forces are written there (and returned).
        """
        x = self._positions(x)
        buf = self._chunk_buffer()
        self._add_forces(x, buf)
        if out is None:
            return buf[0].copy()
        out[...] = buf[0]
        return out

    def _energy(self, x: np.ndarray) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def _add_forces(self, x: np.ndarray, buf: np.ndarray) -> None:  # pragma: no cover
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.mesh!r}, {self.material!r})"
