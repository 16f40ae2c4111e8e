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

A :class:`~heml_gym.Model` takes the field (``Model(field=QuadraticFemForce(mesh,
material))``): its masses are the lumped node masses, and geometry (surface, contact,
inversion checks) reads the mesh's linear view, 8 tets per element. The solvers that
take any force field step it (``implicit``, ``explicit``, statics); the default
quasi-Newton solver is HEML's own, and the env scenes are built on linear tets.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp

from ..materials import Material
from ..mesh import EDGE_PAIRS, TetMesh
from . import kernels_quadratic as kq
from .base import ForceField

__all__ = ["QuadraticTetMesh", "QuadraticFemForce", "QUADRATURE_POINTS", "CORNER_TETS", "OCTAHEDRON_SPLITS"]

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


#: The 4 corner tets of a 10-node element's split into 8 (local node numbers), oriented
#: as the element; the other 4 fill the inner octahedron of its edge nodes
#: (:data:`OCTAHEDRON_SPLITS`).
CORNER_TETS = np.array([(0, 4, 5, 6), (4, 1, 7, 8), (5, 7, 2, 9), (6, 8, 9, 3)], dtype=np.int64)
#: The inner octahedron cut along each of its three diagonals (edge nodes on opposite
#: edges of the element: 0-1 and 2-3, 0-2 and 1-3, 0-3 and 1-2): 4 tets around the
#: diagonal, oriented as the element. :meth:`QuadraticTetMesh.from_linear` takes the
#: shortest diagonal, the split whose tets are best shaped.
OCTAHEDRON_SPLITS = np.array([[(4, 9, 7, 5), (4, 9, 8, 7), (4, 9, 6, 8), (4, 9, 5, 6)],
                              [(5, 8, 6, 4), (5, 8, 4, 7), (5, 8, 7, 9), (5, 8, 9, 6)],
                              [(6, 7, 4, 5), (6, 7, 5, 9), (6, 7, 9, 8), (6, 7, 8, 4)]], dtype=np.int64)
#: (the pair of local edge nodes that is each split's diagonal)
OCTAHEDRON_DIAGONALS = np.array([(4, 9), (5, 8), (6, 7)], dtype=np.int64)


class QuadraticTetMesh(TetMesh):
    """The 10-node tets of a linear :class:`~heml_gym.TetMesh`.

    Its nodes are the linear mesh's vertices (same indices) followed by one node at the
    middle of each of the linear mesh's :attr:`~heml_gym.TetMesh.edges`, in that order.
    As a :class:`~heml_gym.TetMesh` it is the linear view of those nodes (``tets``: each
    element split into 8 tets: :data:`CORNER_TETS` and the inner octahedron cut along its
    shortest diagonal, :data:`OCTAHEDRON_SPLITS`), which is what geometry reads (surface,
    contact, rendering, inversion checks, strain measures), while the force field reads
    :attr:`elements`. :attr:`vertex_volumes` are the elements' lumped node volumes.
    Build it with :meth:`from_linear`.

    Attributes
    ----------
    linear : TetMesh
        The 4-node mesh it was built from.
    elements : (m, 10) int64
        Each element's nodes: its 4 corners, then its 6 edge nodes in
        :data:`~heml_gym.mesh.EDGE_PAIRS` order.
    """

    @classmethod
    def from_linear(cls, linear: TetMesh) -> "QuadraticTetMesh":
        """Straight-sided quadratic tets on the cells of ``linear``."""
        if not isinstance(linear, TetMesh):
            raise TypeError(f"linear must be a heml_gym.TetMesh, got {type(linear).__name__}")
        nv = linear.n_vertices
        edges = linear.edges
        keys = edges[:, 0] * nv + edges[:, 1]
        local = np.sort(linear.tets[:, EDGE_PAIRS], axis=2)  # (m, 6, 2)
        edge_id = np.searchsorted(keys, local[..., 0] * nv + local[..., 1])
        elements = np.concatenate([linear.tets, nv + edge_id], axis=1).astype(np.int64)
        vertices = np.concatenate([linear.vertices, 0.5 * (linear.vertices[edges[:, 0]]
                                                           + linear.vertices[edges[:, 1]])])
        diagonal = vertices[elements[:, OCTAHEDRON_DIAGONALS[:, 1]]] - vertices[elements[:, OCTAHEDRON_DIAGONALS[:, 0]]]
        split = np.argmin(np.einsum("mdk,mdk->md", diagonal, diagonal), axis=1)  # (m,) the shortest
        local = np.concatenate([np.broadcast_to(CORNER_TETS, (len(elements), 4, 4)), OCTAHEDRON_SPLITS[split]], axis=1)
        sub_tets = np.take_along_axis(elements[:, None, :], local.reshape(len(elements), 32)[:, None, :], axis=2)
        mesh = cls(vertices, sub_tets.reshape(-1, 4))
        elements.setflags(write=False)
        object.__setattr__(mesh, "linear", linear)
        object.__setattr__(mesh, "elements", elements)
        return mesh

    @property
    def n_elements(self) -> int:
        """Number of 10-node elements."""
        return len(self.elements)

    @property
    def element_volumes(self) -> np.ndarray:
        """Rest volume of each 10-node element (m^3)."""
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
        out = np.ascontiguousarray(np.repeat(self.element_volumes[:, None] / 4.0, 4, axis=1))
        out.setflags(write=False)
        return out

    def _per_node(self, corner_share: float, edge_share: float) -> np.ndarray:
        out = np.zeros(self.n_vertices)
        np.add.at(out, self.elements[:, :4].ravel(), np.repeat(corner_share * self.element_volumes, 4))
        np.add.at(out, self.elements[:, 4:].ravel(), np.repeat(edge_share * self.element_volumes, 6))
        return out

    @cached_property
    def vertex_volumes(self) -> np.ndarray:
        """Lumped volume of each node (m^3, all positive; the mass is density times it):
        the diagonal of the elements' consistent mass, rescaled to their volume."""
        return self._per_node(CORNER_MASS_SHARE, EDGE_MASS_SHARE)

    @cached_property
    def load_volumes(self) -> np.ndarray:
        """``int N_a dV`` per node (m^3): a uniform body force ``b`` (N/m^3) puts
        ``b * load_volumes`` on the nodes (the corners' share is negative)."""
        return self._per_node(CORNER_LOAD_SHARE, EDGE_LOAD_SHARE)

    @cached_property
    def hessian_pattern(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The CSR pattern of a ``3n x 3n`` matrix coupling every pair of nodes of an
        element: ``(indptr, indices, position)``, ``position`` the place in the CSR data of
        each entry of the elements' 30 x 30 matrices, flattened (entries that meet add up).
        Derived from the elements alone, so every material's field shares it."""
        dof = (3 * self.elements[:, :, None] + np.arange(3)).reshape(-1, 30)  # (m, 30)
        n = 3 * self.n_vertices
        unique, position = np.unique((dof[:, :, None] * n + dof[:, None, :]).ravel(), return_inverse=True)
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(unique // n, minlength=n), out=indptr[1:])
        return indptr, (unique % n).astype(np.int64), position.ravel()

    def __repr__(self) -> str:
        return f"QuadraticTetMesh(n_vertices={self.n_vertices}, n_elements={self.n_elements})"


class QuadraticFemForce(ForceField):
    """Hyperelastic force field of a :class:`QuadraticTetMesh`, for any law.

    Stresses come from each law's textbook formula in ``F`` (as
    :class:`~heml_gym.forces.FemForce`), the tangent from the laws' invariant derivatives;
    four quadrature points per element. Serial kernels only.
    """

    name = "P2 FEM"
    has_hessian = True

    def __init__(self, mesh: QuadraticTetMesh, material: Material):
        if not isinstance(mesh, QuadraticTetMesh) or not hasattr(mesh, "elements"):
            raise TypeError(f"mesh must be a QuadraticTetMesh built by QuadraticTetMesh.from_linear, got "
                            f"{type(mesh).__name__}")
        super().__init__(mesh, material)
        self.law_id = np.int64(material.law_id)
        self.params = np.ascontiguousarray(material.params, dtype=np.float64)

    @property
    def n_elements(self) -> int:
        return self.mesh.n_elements

    def kernel_threads(self) -> int:
        return 1  # serial kernels only

    def _args(self):
        m = self.mesh
        return m.elements, m.quadrature_gradients, m.quadrature_weights, self.law_id, self.params

    def _energy_serial(self, x):
        return kq.quadratic_energy(x, *self._args())

    def _add_forces_serial(self, x, f):
        kq.quadratic_add_forces(x, *self._args(), f)
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
        indptr, cols, position = self.mesh.hessian_pattern
        data = np.bincount(position, weights=self.element_hessians(x, project).ravel(), minlength=len(cols))
        n = 3 * self.mesh.n_vertices
        return sp.csr_matrix((data, cols, indptr), shape=(n, n))

    def __repr__(self) -> str:
        return f"QuadraticFemForce({self.mesh!r}, {self.material!r})"
