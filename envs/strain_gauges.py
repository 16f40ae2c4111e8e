"""Tissue strain over a fixed gauge length, so that it does not depend on the mesh.

The largest strain of the mesh's own edges grows without bound as the mesh is refined
next to a grasp (the strain field of a held line or point is singular), so a damage or
tearing threshold on it would decide a task differently on every mesh. A
:class:`StrainGauges` instead measures the engineering strain ``|l / L - 1|`` of
segments between material points on a lattice of fixed spacing ``L`` (m) inside the
body, each point carried by the tet that contains it at rest (barycentric
interpolation): a strain averaged over ``L``, with a fine-mesh limit. Units: m.
"""

from __future__ import annotations

import itertools

import numba as nb
import numpy as np

from heml_gym.mesh import TetMesh

#: the 13 lattice directions of half the 26-neighbourhood: axes, face and body diagonals
DIRECTIONS = np.array([d for d in itertools.product((-1, 0, 1), repeat=3) if d > (0, 0, 0)])


def locate(mesh: TetMesh, points: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """The tet containing each point of ``points`` (P, 3) at rest, and its barycentric weights.

    Returns ``(tet, weights)``: ``(P,)`` tet indices (-1 for a point outside the mesh) and
    ``(P, 4)`` weights (rows of points outside are 0). Points on a shared face go to
    either tet; ``tol`` is how far below 0 a weight may be and still count as inside.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = mesh.vertices[mesh.tets]  # (m, 4, 3)
    edges = v[:, 1:] - v[:, :1]  # (m, 3, 3): rows are the edge vectors
    inverse = np.linalg.inv(np.transpose(edges, (0, 2, 1)))  # maps x - v0 to (w1, w2, w3)
    tet = np.full(len(points), -1, dtype=np.int64)
    weights = np.zeros((len(points), 4))
    for start in range(0, len(points), 64):  # (64, m, 3) at a time
        p = points[start:start + 64]
        w = np.einsum("mij,pmj->pmi", inverse, p[:, None, :] - v[None, :, 0, :])
        w = np.concatenate([1.0 - w.sum(axis=2, keepdims=True), w], axis=2)  # (64, m, 4)
        worst = w.min(axis=2)
        best = worst.argmax(axis=1)
        found = worst[np.arange(len(p)), best] >= -tol
        rows = np.arange(start, start + len(p))[found]
        tet[rows] = best[found]
        weights[rows] = w[np.flatnonzero(found), best[found]]
    return tet, weights


class StrainGauges:
    """Gauge segments of rest length ``spacing`` (m, or ``sqrt 2``, ``sqrt 3`` times it on the
    diagonals) between the points of a lattice inside ``mesh``.

    The lattice is centred on the mesh's bounding box along each axis (a body thinner than
    ``spacing`` gets one plane of points through its middle). A segment counts when both its
    ends and its midpoint lie inside the mesh at rest.
    """

    def __init__(self, mesh: TetMesh, spacing: float):
        spacing = float(spacing)
        if not (np.isfinite(spacing) and spacing > 0):
            raise ValueError(f"gauge spacing must be a positive length in metres, got {spacing}")
        lo, hi = mesh.bounds()
        counts = np.floor((hi - lo) / spacing + 1e-9).astype(np.int64) + 1
        first = lo + 0.5 * ((hi - lo) - spacing * (counts - 1))
        grid = np.stack(np.meshgrid(*[first[a] + spacing * np.arange(counts[a]) for a in range(3)],
                                    indexing="ij"), axis=-1)  # (cx, cy, cz, 3)
        tet, weights = locate(mesh, grid.reshape(-1, 3))
        inside = (tet >= 0).reshape(tuple(counts))
        index = np.full(tuple(counts), -1, dtype=np.int64)
        index[inside] = np.arange(int(inside.sum()))
        pairs = []
        for d in DIRECTIONS:
            for a in np.argwhere(inside):
                b = a + d
                if np.all(b >= 0) and np.all(b < counts) and inside[tuple(b)]:
                    pairs.append((index[tuple(a)], index[tuple(b)]))
        pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
        self.points = grid.reshape(-1, 3)[inside.reshape(-1)]  # rest positions (m)
        self.corners = mesh.tets[tet[tet >= 0]]  # (P, 4) vertices carrying each point
        self.weights = weights[tet >= 0]  # (P, 4)
        if len(pairs):  # keep segments whose midpoint is inside too
            mid_tet, _ = locate(mesh, 0.5 * (self.points[pairs[:, 0]] + self.points[pairs[:, 1]]))
            pairs = pairs[mid_tet >= 0]
        if len(pairs) == 0:
            raise ValueError(f"no gauge segment of spacing {spacing} m fits inside the mesh")
        self.pairs = pairs
        self.rest_length = np.linalg.norm(self.points[pairs[:, 1]] - self.points[pairs[:, 0]], axis=1)
        self.spacing = spacing

    def positions(self, x: np.ndarray) -> np.ndarray:
        """Current lattice points (..., P, 3) for vertex positions ``x`` (..., n, 3) in m."""
        return np.einsum("...pkd,pk->...pd", x[..., self.corners, :], self.weights)

    def max_strain(self, x: np.ndarray) -> np.ndarray:
        """Largest gauge strain ``|l / L - 1|`` for positions ``x`` (..., n, 3): shape (...)
        (NaN where a position is not finite)."""
        x = np.asarray(x, dtype=np.float64)
        batch = x.reshape(-1, *x.shape[-2:])
        out = np.empty(len(batch))
        _max_strain_kernel(np.ascontiguousarray(batch), self.corners, self.weights, self.pairs, self.rest_length, out)
        return out.reshape(x.shape[:-2])


@nb.njit(cache=True)
def _max_strain_kernel(x, corners, weights, pairs, rest_length, out):
    """``out[s]``: the largest ``|l / L - 1|`` of the gauge segments ``pairs`` in scene
    ``s`` of ``x (N, n, 3)`` (points interpolated from their tet's ``corners`` with
    ``weights``), NaN if any is NaN; the arithmetic, in order, of the NumPy expression
    ``|norm(p_j - p_i) / L - 1|``."""
    n_points = corners.shape[0]
    p = np.empty((n_points, 3))
    for s in range(x.shape[0]):
        for q in range(n_points):
            for d in range(3):
                acc = 0.0
                for k in range(4):
                    acc += x[s, corners[q, k], d] * weights[q, k]
                p[q, d] = acc
        worst = -1.0
        for e in range(pairs.shape[0]):
            i, j = pairs[e, 0], pairs[e, 1]
            dx = p[j, 0] - p[i, 0]
            dy = p[j, 1] - p[i, 1]
            dz = p[j, 2] - p[i, 2]
            strain = abs(np.sqrt(dx * dx + dy * dy + dz * dz) / rest_length[e] - 1.0)
            if np.isnan(strain):
                worst = strain
                break
            if strain > worst:
                worst = strain
        out[s] = worst
