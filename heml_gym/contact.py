"""Rigid support surfaces the tissue rests on: a plane, or any closed triangle surface
(an organ) as a signed-distance query.

Supports are frictionless and perfectly inelastic: a free vertex that ends a step inside
one is moved back onto its surface along the normal and loses the velocity component
into it (both solvers; the implicit one also adds a stiff penalty to its incremental
potential so that Newton sees the contact, then projects the same way). Held and fixed
vertices are not touched. Units: m.

    PlaneSupport(height=0.0)                       # the plane z = 0, tissue above it
    PlaneSupport(normal=(1, 0, 0), offset=0.02)    # x >= 0.02
    MeshSupport(organ_mesh.vertices, organ_mesh.boundary_faces)   # outside a closed surface
"""

from __future__ import annotations

import math

import numpy as np

from .kernel_data import SupportArrays
from .kernels_contact import band_distances, inside_by_parity, signed_distances

__all__ = ["Support", "PlaneSupport", "MeshSupport", "Supports"]


class Support:
    """A rigid body the tissue cannot enter (see :class:`PlaneSupport`, :class:`MeshSupport`)."""

    def signed_distance(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (m, negative inside) of ``points (k, 3)`` and the unit outward
        normals ``(k, 3)``."""
        supports = Supports([self])
        return supports.signed_distance(points)


class PlaneSupport(Support):
    """The half-space ``normal . x >= offset`` (m); by default the floor ``z >= height``."""

    def __init__(self, normal=(0.0, 0.0, 1.0), offset: float = 0.0, height: float | None = None):
        n = np.asarray(normal, dtype=np.float64)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
            raise ValueError(f"normal must be three finite numbers, not all zero; got {normal}")
        if height is not None:
            if not np.allclose(n / np.linalg.norm(n), (0.0, 0.0, 1.0)) or offset != 0.0:
                raise ValueError("height= is for the horizontal plane z = height; give normal= and offset= otherwise")
            offset = height
        offset = float(offset)
        if not math.isfinite(offset):
            raise ValueError(f"offset must be a finite number of metres, got {offset}")
        length = float(np.linalg.norm(n))
        self.normal = n / length
        self.offset = offset / length

    def __repr__(self) -> str:
        return f"PlaneSupport(normal={self.normal.tolist()}, offset={self.offset:g})"


class MeshSupport(Support):
    """The outside of a closed triangle surface (m), e.g. an organ's boundary.

    The signed distance is sampled once on a regular grid (exact point-triangle distances
    within ``band`` of the surface, inside / outside by ray parity) and interpolated
    trilinearly at run time, so a query costs the same whatever the surface's size. The
    interpolation is exact where the surface is flat (a linear distance), and within
    ``spacing^2 / (8 R)`` on a surface of curvature radius ``R``.

    Parameters
    ----------
    vertices : (k, 3) float, m
    faces : (f, 3) int, wound outward (as :attr:`heml_gym.TetMesh.boundary_faces`)
    spacing : float, m
        Grid spacing; default: a 64th of the surface's largest extent.
    band : float, m
        Distances are exact within this much of the surface (default 4 spacings) and
        clamped to it further out. A vertex cannot sink deeper than this in one step.
    """

    def __init__(self, vertices, faces, spacing: float | None = None, band: float | None = None):
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
            raise ValueError(f"vertices must be a finite (k, 3) array, got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
            raise ValueError(f"faces must be an (f, 3) array of at least 4 triangles, got shape {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"faces index vertices outside [0, {len(v)})")
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        if np.any(counts != 2):
            raise ValueError("faces must form a closed surface: every edge shared by exactly two triangles "
                             f"({int(np.sum(counts != 2))} edges are not)")
        lo, hi = v.min(axis=0), v.max(axis=0)
        extent = float((hi - lo).max())
        h = extent / 64.0 if spacing is None else float(spacing)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"spacing must be a positive number of metres, got {spacing}")
        band = 4.0 * h if band is None else float(band)
        if not (math.isfinite(band) and band >= h):
            raise ValueError(f"band must be at least the spacing ({h:g} m), got {band}")
        origin = lo - band - h
        dims = np.ceil((hi + band + h - origin) / h).astype(np.int64) + 1
        if np.prod(dims) > 50_000_000:
            raise ValueError(f"a {dims.tolist()} distance grid is too large: give a larger spacing")
        distance = np.full(tuple(dims), band)
        band_distances(v, f, origin, h, dims, band, distance)
        inside = np.zeros(tuple(dims), dtype=np.bool_)
        # columns shifted by irrational fractions of the spacing miss edges and corners
        inside_by_parity(v, f, origin, h, dims, h * (math.sqrt(2) - 1) * 1e-3, h * (math.sqrt(3) - 1) * 1e-3, inside)
        self.vertices, self.faces = v, f
        self.origin, self.spacing, self.band, self.dims = origin, h, band, dims
        self.values = np.where(inside, -distance, distance).ravel()

    def __repr__(self) -> str:
        return f"MeshSupport({len(self.faces)} triangles, grid {self.dims.tolist()} at {self.spacing:g} m)"


class Supports:
    """A set of supports packed for the kernels (see :mod:`heml_gym.kernels_contact`).

    Attributes: ``planes (P, 4)``, ``grids (G, 8)``, ``grid_values`` and ``items`` (the
    support objects).
    """

    def __init__(self, supports=()):
        items = tuple(supports)
        for s in items:
            if not isinstance(s, Support):
                raise TypeError(f"supports must be PlaneSupport or MeshSupport objects, got {type(s).__name__}")
        self.items = items
        planes = [np.append(s.normal, s.offset) for s in items if isinstance(s, PlaneSupport)]
        self.planes = np.array(planes, dtype=np.float64).reshape(-1, 4)
        grids, values, start = [], [], 0
        for s in items:
            if isinstance(s, MeshSupport):
                grids.append([*s.origin, s.spacing, *s.dims, start])
                values.append(s.values)
                start += len(s.values)
        self.grids = np.array(grids, dtype=np.float64).reshape(-1, 8)
        self.grid_values = np.concatenate(values) if values else np.zeros(1)

    def __len__(self) -> int:
        return len(self.items)

    def kernel_args(self, tools=None, tool_pose=None, tool_k=None) -> SupportArrays:
        """``(planes, grids, grid_values)`` for the kernels, with ``tools``
        (:class:`heml_gym.tools.Tools`) posed at ``tool_pose (N, T, 12)`` if any, their
        penalty stiffness ``tool_k (N, n)`` (N/m at each vertex)
        (:class:`~heml_gym.kernel_data.SupportArrays`)."""
        if tools is None or not len(tools):
            return SupportArrays(self.planes, self.grids, self.grid_values)
        return SupportArrays(self.planes, self.grids, self.grid_values, tools.kind, tools.size, tool_pose,
                             tool_k)

    def signed_distance(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Smallest signed distance (m) of each point to the supports (``inf`` when there
        are none) and the unit outward normal of that support, ``((k,), (k, 3))``."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        d = np.empty(len(p))
        n = np.empty((len(p), 3))
        signed_distances(p, self.planes, self.grids, self.grid_values, d, n)
        return d, n
