"""Shared interface of the force fields: arrays in, arrays out, SI units."""

from __future__ import annotations

import numba
import numpy as np

from ..materials import Material
from ..mesh import TetMesh


class ForceField:
    """Elastic force field of a tet mesh.

    Positions are ``(n, 3)`` float64 arrays in metres, energies in joules, forces in
    newtons. ``forces(x)`` is ``-dW/dx``: the force the tissue exerts on its vertices.

    What a solver needs is public: :meth:`forces`, :meth:`energy`, :meth:`hessian` (when
    :attr:`has_hessian`), :meth:`with_material` (the same mesh with another material,
    sharing every material-independent precomputation: that is how a batch of worlds
    holds one field per world at the cost of one) and :meth:`kernel_threads`.

    Subclasses provide serial kernels (``_add_forces_serial``, ``_energy_serial``) and
    parallel ones (``_add_forces_parallel``, ``_energy_parallel``).
    The parallel kernels are race-free: elements are split into one contiguous chunk per
    Numba thread, each chunk adds into its own buffer, the buffers are summed. Meshes
    smaller than :attr:`parallel_min_elements` use the serial kernels, since waking the
    threads costs more than it saves there.
    """

    #: Short name used in tables and charts.
    name = "force field"
    #: Below this many elements the serial kernels are used whatever the thread count.
    parallel_min_elements = 20_000
    #: Whether :meth:`hessian` is available (the implicit and static solvers need it).
    has_hessian = False

    def __init__(self, mesh: TetMesh, material: Material):
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a heml_gym.TetMesh, got {type(mesh).__name__}")
        if not isinstance(material, Material):
            raise TypeError(f"material must be a heml_gym.materials.Material, got {type(material).__name__}")
        self.mesh = mesh
        self.material = material
        self._buf = np.zeros((0, 0, 3))

    def with_material(self, material: Material) -> "ForceField":
        """The same field on the same mesh with another ``material``.

        The default builds a new field; subclasses share their material-independent
        precomputation (rest-shape coefficients, Hessian pattern) with the new one.
        """
        return type(self)(self.mesh, material)

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    @property
    def n_elements(self) -> int:
        """Number of elements the kernels loop over (tets; springs for mass-spring)."""
        return self.mesh.n_tets

    def check_positions(self, x) -> np.ndarray:
        """``x`` as a C-contiguous float64 ``(n, 3)`` array; ``ValueError`` if the shape is wrong."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.mesh.n_vertices, 3):
            raise ValueError(f"positions must have shape ({self.mesh.n_vertices}, 3), got {x.shape}")
        return x

    def kernel_threads(self) -> int:
        """Chunks the kernels use: the Numba thread count, or 1 for small meshes."""
        threads = numba.get_num_threads()
        return threads if self.n_elements >= self.parallel_min_elements else 1

    def energy(self, x) -> float:
        """Elastic energy in joules at positions ``x`` (m)."""
        x = self.check_positions(x)
        threads = self.kernel_threads()
        if threads == 1:
            return float(self._energy_serial(x))
        return float(self._energy_parallel(x, threads))

    def forces(self, x, out: np.ndarray | None = None) -> np.ndarray:
        """Elastic forces ``-dW/dx`` in newtons at positions ``x`` (m), shape ``(n, 3)``.

        If ``out`` (a C-contiguous float64 ``(n, 3)`` array) is given the forces are
        written there and it is returned.
        """
        x = self.check_positions(x)
        if out is None:
            out = np.zeros_like(x)
        else:
            if out.shape != x.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
                raise ValueError(f"out must be a C-contiguous float64 array of shape {x.shape}")
            out.fill(0.0)
        threads = self.kernel_threads()
        if threads == 1:
            self._add_forces_serial(x, out)
            return out
        shape = (threads, self.mesh.n_vertices, 3)
        if self._buf.shape != shape:
            self._buf = np.zeros(shape)
        else:
            self._buf.fill(0.0)
        self._add_forces_parallel(x, self._buf)
        out[...] = self._buf[0]
        return out

    def add_forces(self, x, f) -> None:
        """Add the elastic forces (N) at positions ``x`` (m) into ``f``, on one thread and
        without checking either array: for callers that pass arrays of their own kind
        (the operation counter runs the kernel in Python on counting floats). Use
        :meth:`forces` otherwise."""
        self._add_forces_serial(x, f)

    def hessian(self, x, project: bool = True):
        """Stiffness matrix ``d2W/dx2`` (N/m) at ``x``, a ``3n x 3n`` scipy CSR matrix.

        Only fields with :attr:`has_hessian`; the others raise ``NotImplementedError``.
        """
        raise NotImplementedError(f"{type(self).__name__} has no Hessian: use an explicit solver")

    # kernels, per subclass ---------------------------------------------------
    def _energy_serial(self, x):  # pragma: no cover - abstract
        raise NotImplementedError

    def _energy_parallel(self, x, n_chunks):  # pragma: no cover - abstract
        raise NotImplementedError

    def _add_forces_serial(self, x, f):  # pragma: no cover - abstract
        raise NotImplementedError

    def _add_forces_parallel(self, x, buf):  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.mesh!r}, {self.material!r})"
