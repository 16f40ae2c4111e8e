"""10-node quadratic tetrahedra (P2 finite elements): a tet mesh that bends when coarse.

Linear (4-node) tets cannot bend without shearing: on the few cells through a flap's
thickness that an interactive scene affords they are several times too stiff in bending
(the cantilever of docs/benchmarks/element_bending.md). The quadratic tet adds a node at
the middle of every edge; its displacement varies quadratically inside the element, so
its strain varies linearly and bending costs what it should.

:class:`QuadraticTetMesh` builds the nodes and elements from a :class:`~heml_gym.TetMesh`
(straight-sided: each edge node at its edge's middle); :class:`QuadraticFemForce` gives
the energy, forces and Hessian of any law of :mod:`heml_gym.materials` on it, with the
arrays and units of the linear fields (positions ``(n, 3)`` in metres, energies in
joules, forces in newtons, stiffness in N/m).

What is not there yet: a :class:`~heml_gym.Model` does not take this field (its masses,
supports, contact and the env scenes assume 4-node tets), so it is stepped with
:func:`heml_gym.solvers.newton.minimize` directly (statics: see
``benchmarks/accuracy/element_bending.py``).
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp

from ..materials import Material
from ..mesh import EDGE_PAIRS, TetMesh
from . import kernels_quadratic as kq

__all__ = ["QuadraticTetMesh", "QuadraticFemForce", "QUADRATURE_POINTS"]

#: Barycentric coordinates of the 4-point quadrature rule (degree 2, weight 1/4 each).
QUADRATURE_POINTS = np.array([[0.5854101966249685, 0.1381966011250105, 0.1381966011250105, 0.1381966011250105],
                              [0.1381966011250105, 0.5854101966249685, 0.1381966011250105, 0.1381966011250105],
                              [0.1381966011250105, 0.1381966011250105, 0.5854101966249685, 0.1381966011250105],
                              [0.1381966011250105, 0.1381966011250105, 0.1381966011250105, 0.5854101966249685]])

#: Share of an element's volume lumped to each corner node and each edge node (the
#: diagonal of the consistent mass matrix, rescaled to the element's mass: HRZ lumping).
#: Row-sum lumping would give the corners negative mass.
CORNER_MASS_SHARE = 1.0 / 36.0
EDGE_MASS_SHARE = 4.0 / 27.0
#: ``int N_a dV / V`` for a straight-sided P2 tet: the consistent weights of a uniform
#: body force (the corners' are negative).
CORNER_LOAD_SHARE = -1.0 / 20.0
EDGE_LOAD_SHARE = 1.0 / 5.0


def shape_gradients_barycentric(bary: np.ndarray) -> np.ndarray:
    """``dN_a / dL_b`` (10, 4) of the P2 shape functions at barycentric point ``bary``.

    Nodes 0-3 are the corners (``N = L (2 L - 1)``), nodes 4-9 the edges of
    :data:`heml_gym.mesh.EDGE_PAIRS` in that order (``N = 4 L_i L_j``).
    """
    d = np.zeros((10, 4))
    for i in range(4):
        d[i, i] = 4.0 * bary[i] - 1.0
    for k, (i, j) in enumerate(EDGE_PAIRS):
        d[4 + k, i] = 4.0 * bary[j]
        d[4 + k, j] = 4.0 * bary[i]
    return d


class QuadraticTetMesh:
    """The 10-node tets of a linear :class:`~heml_gym.TetMesh`: its vertices first (the
    corner nodes keep their indices), then one node at the middle of each of its
    :attr:`~heml_gym.TetMesh.edges`, in that order.

    Attributes
    ----------
    linear : TetMesh
        The 4-node mesh it was built from.
    vertices : (n, 3) float64
        Rest positions of every node (m).
    elements : (m, 10) int64
        Each element's nodes: its 4 corners, then its 6 edge nodes in
        :data:`~heml_gym.mesh.EDGE_PAIRS` order.
    """

    def __init__(self, linear: TetMesh):
        if not isinstance(linear, TetMesh):
            raise TypeError(f"linear must be a heml_gym.TetMesh, got {type(linear).__name__}")
        self.linear = linear
        nv = linear.n_vertices
        edges = linear.edges
        keys = edges[:, 0] * nv + edges[:, 1]
        local = np.sort(linear.tets[:, EDGE_PAIRS], axis=2)  # (m, 6, 2)
        edge_id = np.searchsorted(keys, local[..., 0] * nv + local[..., 1])
        elements = np.concatenate([linear.tets, nv + edge_id], axis=1).astype(np.int64)
        vertices = np.concatenate([linear.vertices, 0.5 * (linear.vertices[edges[:, 0]]
                                                           + linear.vertices[edges[:, 1]])])
        vertices.setflags(write=False)
        elements.setflags(write=False)
        self.vertices = vertices
        self.elements = elements

    @property
    def n_vertices(self) -> int:
        """Number of nodes (corners and edge nodes)."""
        return len(self.vertices)

    @property
    def n_elements(self) -> int:
        return len(self.elements)

    @property
    def volumes(self) -> np.ndarray:
        """Rest volume of each element (m^3)."""
        return self.linear.volumes

    @cached_property
    def quadrature_gradients(self) -> np.ndarray:
        """``grad N_a`` (1/m) at each quadrature point, ``(m, 4, 10, 3)``."""
        dm_inv = self.linear.rest_edge_inverses  # rows: d(L1, L2, L3)/dX
        dl_dx = np.concatenate([-dm_inv.sum(axis=1, keepdims=True), dm_inv], axis=1)  # (m, 4, 3)
        per_point = [np.einsum("ab,tbj->taj", shape_gradients_barycentric(b), dl_dx) for b in QUADRATURE_POINTS]
        out = np.ascontiguousarray(np.stack(per_point, axis=1))
        out.setflags(write=False)
        return out

    @cached_property
    def quadrature_weights(self) -> np.ndarray:
        """Quadrature weight times rest volume (m^3), ``(m, 4)``."""
        out = np.ascontiguousarray(np.repeat(self.volumes[:, None] / 4.0, 4, axis=1))
        out.setflags(write=False)
        return out

    def _per_node(self, corner_share: float, edge_share: float) -> np.ndarray:
        out = np.zeros(self.n_vertices)
        np.add.at(out, self.elements[:, :4].ravel(), np.repeat(corner_share * self.volumes, 4))
        np.add.at(out, self.elements[:, 4:].ravel(), np.repeat(edge_share * self.volumes, 6))
        return out

    @cached_property
    def node_volumes(self) -> np.ndarray:
        """Lumped volume of each node (m^3, all positive; the mass is density times it)."""
        return self._per_node(CORNER_MASS_SHARE, EDGE_MASS_SHARE)

    @cached_property
    def load_volumes(self) -> np.ndarray:
        """``int N_a dV`` per node (m^3): a uniform body force ``b`` (N/m^3) puts
        ``b * load_volumes`` on the nodes (the corners' share is negative)."""
        return self._per_node(CORNER_LOAD_SHARE, EDGE_LOAD_SHARE)

    def __repr__(self) -> str:
        return f"QuadraticTetMesh({self.n_vertices} nodes, {self.n_elements} elements)"


class QuadraticFemForce:
    """Hyperelastic force field of a :class:`QuadraticTetMesh`, for any law.

    Stresses come from each law's textbook formula in ``F`` (as
    :class:`~heml_gym.forces.FemForce`), the tangent from the laws' invariant derivatives;
    four quadrature points per element. Serial kernels only.
    """

    name = "P2 FEM"
    has_hessian = True

    def __init__(self, mesh: QuadraticTetMesh, material: Material):
        if not isinstance(mesh, QuadraticTetMesh):
            raise TypeError(f"mesh must be a QuadraticTetMesh, got {type(mesh).__name__}")
        if not isinstance(material, Material):
            raise TypeError(f"material must be a heml_gym.materials.Material, got {type(material).__name__}")
        self.mesh = mesh
        self.material = material
        self.law_id = np.int64(material.law_id)
        self.params = np.ascontiguousarray(material.params, dtype=np.float64)
        self._pattern = None

    def with_material(self, material: Material) -> "QuadraticFemForce":
        """The same mesh with another ``material`` (sharing the Hessian pattern)."""
        other = type(self)(self.mesh, material)
        other._pattern = self._pattern
        return other

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    def check_positions(self, x) -> np.ndarray:
        """``x`` as a C-contiguous float64 ``(n, 3)`` array; ``ValueError`` if the shape is wrong."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.mesh.n_vertices, 3):
            raise ValueError(f"positions must have shape ({self.mesh.n_vertices}, 3), got {x.shape}")
        return x

    def _args(self):
        m = self.mesh
        return m.elements, m.quadrature_gradients, m.quadrature_weights, self.law_id, self.params

    def energy(self, x) -> float:
        """Elastic energy in joules at node positions ``x`` (m)."""
        return float(kq.quadratic_energy(self.check_positions(x), *self._args()))

    def forces(self, x, out: np.ndarray | None = None) -> np.ndarray:
        """Elastic forces ``-dW/dx`` (N) on every node, shape ``(n, 3)``."""
        x = self.check_positions(x)
        if out is None:
            out = np.zeros_like(x)
        else:
            if out.shape != x.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
                raise ValueError(f"out must be a C-contiguous float64 array of shape {x.shape}")
            out.fill(0.0)
        kq.quadratic_add_forces(x, *self._args(), out)
        return out

    def element_hessians(self, x, project: bool = False) -> np.ndarray:
        """Each element's 30x30 ``d2 W_t/dx2`` (J/m^2), ``(m, 30, 30)``."""
        x = self.check_positions(x)
        out = np.empty((self.mesh.n_elements, 30, 30))
        kq.quadratic_element_hessians(x, *self._args(), bool(project), out)
        return out

    def hessian(self, x, project: bool = True):
        """Stiffness matrix ``d2W/dx2`` (N/m) at ``x``, a ``3n x 3n`` scipy CSR matrix.

        ``project=True`` clamps the negative modes of ``dP/dF`` at every quadrature point
        (positive semi-definite); ``project=False`` gives the exact Hessian.
        """
        ke = self.element_hessians(x, project)
        if self._pattern is None:
            dof = (3 * self.mesh.elements[:, :, None] + np.arange(3)).reshape(-1, 30)  # (m, 30)
            n = 3 * self.mesh.n_vertices
            keys = (dof[:, :, None] * n + dof[:, None, :]).ravel()
            unique, inverse = np.unique(keys, return_inverse=True)
            rows, cols = unique // n, unique % n
            indptr = np.zeros(n + 1, dtype=np.int64)
            np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
            self._pattern = (indptr, cols.astype(np.int64), inverse.ravel(), len(unique))
        indptr, cols, inverse, nnz = self._pattern
        data = np.bincount(inverse, weights=ke.ravel(), minlength=nnz)
        n = 3 * self.mesh.n_vertices
        return sp.csr_matrix((data, cols, indptr), shape=(n, n))

    def __repr__(self) -> str:
        return f"QuadraticFemForce({self.mesh!r}, {self.material!r})"
