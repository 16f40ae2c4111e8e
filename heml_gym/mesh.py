"""Tetrahedral meshes: validation, topology, structured boxes and file I/O.

Coordinates are in metres. A tetrahedron ``(i0, i1, i2, i3)`` is *positively oriented*
when ``det[x1 - x0, x2 - x0, x3 - x0] > 0``; every force field in heml_gym assumes
positively oriented rest tets, which :class:`TetMesh` guarantees (it raises on inverted
tets unless asked to re-orient them).
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

__all__ = ["TetMesh", "box_mesh", "load_mesh", "save_mesh", "EDGE_PAIRS", "MeshQualityWarning", "tet_quality",
           "box_regions", "check_region_grid"]

#: The six local edges of a tet, in the order used by every kernel: (a, b) local indices.
EDGE_PAIRS = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)], dtype=np.int64)

#: The four local faces, each opposite the vertex of the same index, wound outward for
#: a positively oriented tet.
FACE_LOCAL = np.array([(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)], dtype=np.int64)

# A tet whose |signed volume| is below this fraction of (mean edge length)^3 is degenerate.
_DEGENERATE_RELATIVE_VOLUME = 1e-12
#: Shape quality ``6 sqrt(2) V / L_rms^3`` (1 for a regular tet, 0 for a flat one) below
#: which a tet is refused as a sliver: its stiffness and critical time step are off by
#: orders of magnitude (gmsh's organs here have at least 0.2, boxes 0.5).
MIN_QUALITY = 1e-4
#: Below this quality a mesh is accepted with a :class:`MeshQualityWarning`.
WARN_QUALITY = 1e-2


class MeshQualityWarning(UserWarning):
    """A mesh that works but will simulate badly (near-slivers, coincident vertices)."""


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tet in m^3 (positive when positively oriented)."""
    x = vertices[tets]
    d = x[:, 1:, :] - x[:, :1, :]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def tet_quality(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Shape quality of each tet, ``6 sqrt(2) |V| / L_rms^3``: 1 for a regular tet, near 0
    for a sliver (``L_rms`` the root-mean-square edge length)."""
    x = vertices[tets]
    lengths2 = ((x[:, EDGE_PAIRS[:, 1]] - x[:, EDGE_PAIRS[:, 0]]) ** 2).sum(axis=2)
    l_rms = np.sqrt(lengths2.mean(axis=1))
    return 6.0 * np.sqrt(2.0) * np.abs(signed_volumes(vertices, tets)) / l_rms ** 3


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated tetrahedral mesh.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
        Rest positions in metres (stored as float64).
    tets : (m, 4) array_like of int
        Vertex indices of each tetrahedron (stored as int64).
    reorient : bool, default False
        If False, an inverted tet (negative signed volume) raises ``ValueError``; if True
        it is re-oriented by swapping its last two vertices.

    Raises
    ------
    ValueError
        On non-finite coordinates, out-of-range or repeated indices, zero-volume tets,
        slivers (shape quality below :data:`MIN_QUALITY`, see :func:`tet_quality`), two
        tets on the same four vertices, vertices no tet uses, or (unless ``reorient``)
        inverted tets. The message names the offending tet or vertex.

    Warns
    -----
    MeshQualityWarning
        For tets of quality below :data:`WARN_QUALITY`, and for distinct vertices at the
        same position (a crack, unless the mesh meant one).
    """

    vertices: np.ndarray
    tets: np.ndarray
    reorient: bool = field(default=False, repr=False)

    def __post_init__(self) -> None:
        v = np.array(self.vertices, dtype=np.float64, copy=True)
        t = np.array(self.tets, copy=True)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must have shape (n, 3), got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 4:
            raise ValueError(f"tets must have shape (m, 4), got {t.shape}")
        if len(t) == 0:
            raise ValueError("mesh has no tetrahedra")
        if not np.issubdtype(t.dtype, np.integer):
            if not np.all(np.equal(np.mod(t, 1), 0)):
                raise ValueError("tets must hold integer vertex indices")
        t = t.astype(np.int64)
        bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
        if bad.size:
            raise ValueError(f"vertex {bad[0]} has non-finite coordinates {v[bad[0]]}")
        n = len(v)
        out = np.flatnonzero(((t < 0) | (t >= n)).any(axis=1))
        if out.size:
            raise ValueError(
                f"tet {out[0]} {t[out[0]].tolist()} has a vertex index outside [0, {n})"
            )
        st = np.sort(t, axis=1)
        rep = np.flatnonzero((st[:, 1:] == st[:, :-1]).any(axis=1))
        if rep.size:
            raise ValueError(f"tet {rep[0]} {t[rep[0]].tolist()} repeats a vertex index")
        vol = signed_volumes(v, t)
        x = v[t]
        edge_len = np.linalg.norm(x[:, EDGE_PAIRS[:, 1]] - x[:, EDGE_PAIRS[:, 0]], axis=2)
        scale = edge_len.mean(axis=1) ** 3
        degenerate = np.flatnonzero(np.abs(vol) <= _DEGENERATE_RELATIVE_VOLUME * scale)
        if degenerate.size:
            k = degenerate[0]
            raise ValueError(
                f"tet {k} {t[k].tolist()} has zero volume ({vol[k]:.3e} m^3): degenerate element"
            )
        quality = tet_quality(v, t)
        worst = int(np.argmin(quality))
        if quality[worst] < MIN_QUALITY:
            raise ValueError(
                f"tet {worst} {t[worst].tolist()} is a sliver (shape quality {quality[worst]:.2e}, "
                f"at least {MIN_QUALITY:g} needed; a regular tet has 1): re-mesh it"
            )
        if quality[worst] < WARN_QUALITY:
            import warnings

            warnings.warn(f"{int((quality < WARN_QUALITY).sum())} tets of shape quality below {WARN_QUALITY:g} "
                          f"(worst: tet {worst}, {quality[worst]:.2e}): expect a tiny explicit time step and "
                          "poor accuracy there", MeshQualityWarning, stacklevel=3)
        used = np.zeros(n, dtype=bool)
        used[t.ravel()] = True
        if not used.all():
            k = int(np.flatnonzero(~used)[0])
            raise ValueError(f"vertex {k} belongs to no tet ({int((~used).sum())} such vertices): remove them "
                             "(heml_gym.load_mesh drops them when it reads a file)")
        keys, counts = np.unique(st, axis=0, return_counts=True)
        if np.any(counts > 1):
            dup = keys[np.argmax(counts > 1)]
            raise ValueError(f"two tets share the vertices {dup.tolist()}: a duplicated element")
        _, first, counts = np.unique(v, axis=0, return_index=True, return_counts=True)
        if np.any(counts > 1):
            import warnings

            warnings.warn(f"{int((counts > 1).sum())} vertex positions are shared by several vertices (e.g. "
                          f"vertex {int(first[np.argmax(counts > 1)])}): the mesh is cut there (a crack)",
                          MeshQualityWarning, stacklevel=3)
        inverted = np.flatnonzero(vol < 0)
        if inverted.size:
            if not self.reorient:
                k = inverted[0]
                raise ValueError(
                    f"tet {k} {t[k].tolist()} is inverted (signed volume {vol[k]:.3e} m^3; "
                    f"{inverted.size} inverted tets in all): pass reorient=True to flip them"
                )
            t[inverted, 2], t[inverted, 3] = t[inverted, 3].copy(), t[inverted, 2].copy()
        v.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "tets", t)

    # ------------------------------------------------------------------ sizes
    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    # --------------------------------------------------------------- geometry
    @cached_property
    def volumes(self) -> np.ndarray:
        """Rest volume of each tet in m^3 (all positive)."""
        return signed_volumes(self.vertices, self.tets)

    @property
    def total_volume(self) -> float:
        """Rest volume of the whole mesh in m^3."""
        return float(self.volumes.sum())

    @cached_property
    def rest_edge_inverses(self) -> np.ndarray:
        """``Dm^-1`` of every tet, ``(m, 3, 3)`` (1/m), ``Dm = [X1-X0, X2-X0, X3-X0]``.

        Computed once per mesh; every force field, Hessian and strain measure reads it
        from here.
        """
        x = self.vertices[self.tets]
        dm = (x[:, 1:, :] - x[:, :1, :]).transpose(0, 2, 1)  # columns X_a - X_0
        out = np.ascontiguousarray(np.linalg.inv(dm))
        out.setflags(write=False)
        return out

    @cached_property
    def vertex_volumes(self) -> np.ndarray:
        """A quarter of the volume of each incident tet, summed per vertex (m^3)."""
        out = np.zeros(self.n_vertices)
        np.add.at(out, self.tets.ravel(), np.repeat(self.volumes / 4.0, 4))
        return out

    @cached_property
    def edges(self) -> np.ndarray:
        """Unique edges ``(e, 2)``, each sorted ``(i < j)``, in lexicographic order."""
        e = np.sort(self.tets[:, EDGE_PAIRS].reshape(-1, 2), axis=1)
        return np.unique(e, axis=0)

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Boundary triangles ``(f, 3)``, wound so their normals point out of the body."""
        faces = self.tets[:, FACE_LOCAL].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[counts[inverse.ravel()] == 1]

    @cached_property
    def surface_vertices(self) -> np.ndarray:
        """Sorted indices of the vertices on the boundary surface."""
        return np.unique(self.boundary_faces)

    def edge_lengths(self, x: np.ndarray | None = None) -> np.ndarray:
        """Length of each edge of :attr:`edges` in metres, at ``x`` (default: rest)."""
        x = self.vertices if x is None else x
        return np.linalg.norm(x[self.edges[:, 1]] - x[self.edges[:, 0]], axis=1)

    @property
    def min_edge_length(self) -> float:
        """Shortest rest edge, in metres."""
        return float(self.edge_lengths().min())

    @cached_property
    def min_height(self) -> float:
        """Smallest tet altitude (3 V / largest face area) at rest, in metres.

        This is the element size that bounds the explicit critical time step.
        """
        x = self.vertices[self.tets]
        areas = np.stack(
            [
                0.5 * np.linalg.norm(
                    np.cross(x[:, f[1]] - x[:, f[0]], x[:, f[2]] - x[:, f[0]]), axis=1
                )
                for f in FACE_LOCAL
            ],
            axis=1,
        )
        return float((3.0 * self.volumes / areas.max(axis=1)).min())

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo, hi)`` of the rest shape, in metres."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def __repr__(self) -> str:
        return f"TetMesh(n_vertices={self.n_vertices}, n_tets={self.n_tets})"


# Kuhn (Freudenthal) split of a cube into 6 tets sharing the main diagonal 000-111: one
# tet per ordering of the three axes. All cells use the same split, so faces conform.
def _kuhn_tets() -> np.ndarray:
    import itertools

    tets = []
    for perm in itertools.permutations(range(3)):
        corner = [0, 0, 0]
        path = [tuple(corner)]
        for axis in perm:
            corner[axis] = 1
            path.append(tuple(corner))
        tets.append([c[0] + 2 * c[1] + 4 * c[2] for c in path])
    return np.array(tets, dtype=np.int64)


_KUHN = _kuhn_tets()


def box_mesh(
    size: tuple[float, float, float] = (1.0, 1.0, 1.0),
    cells: tuple[int, int, int] | int = 4,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    mirrored: bool = False,
) -> TetMesh:
    """Structured box ``[origin, origin + size]`` (metres) on a hex grid, 6 tets per cell.

    Parameters
    ----------
    size : (3,) float
        Edge lengths of the box along x, y, z in metres.
    cells : int or (3,) int
        Number of hex cells along each axis (an int applies to all three).
    origin : (3,) float
        Position of the minimum corner in metres.
    mirrored : bool
        False: every cell is split the same way (its tets share the diagonal from its
        minimum corner). True: a cell with an odd index along an axis is split as the
        mirror image along that axis, so the diagonals alternate from cell to cell (the
        faces still conform); the mesh then has the box's mirror symmetries.
    """
    size = np.asarray(size, dtype=np.float64)
    cells_arr = np.broadcast_to(np.asarray(cells, dtype=np.int64), (3,))
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise ValueError(f"size must be three positive lengths in metres, got {size}")
    if np.any(cells_arr < 1):
        raise ValueError(f"cells must be >= 1 along each axis, got {cells_arr}")
    nx, ny, nz = (int(c) for c in cells_arr)
    axes = [np.linspace(0.0, s, c + 1) for s, c in zip(size, (nx, ny, nz))]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1) + np.asarray(origin)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    fi, fj, fk = ((i & 1, j & 1, k & 1) if mirrored else (0, 0, 0))  # flip the odd cells
    corners = np.stack(
        [vid(i + ((c & 1) ^ fi), j + (((c >> 1) & 1) ^ fj), k + (((c >> 2) & 1) ^ fk)) for c in range(8)],
        axis=1,
    )
    tets = corners[:, _KUHN].reshape(-1, 4)
    return TetMesh(vertices, tets, reorient=True)


# ---------------------------------------------------------------------------- file I/O
_TET_CELL_TYPES = ("tetra",)


def check_region_grid(grid, argument: str = "grid") -> tuple[int, int, int]:
    """``grid`` as three integers >= 1 (boxes along x, y, z), or a one-line error naming
    ``argument``."""
    try:
        values = tuple(grid)
    except TypeError:
        values = ()
    if len(values) != 3 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 1 <= v <= 64
                                   for v in values):
        raise ValueError(f"{argument}: must be three integers from 1 to 64 (boxes along x, y, z), got {grid!r}")
    return tuple(int(v) for v in values)


def box_regions(mesh: TetMesh, grid) -> np.ndarray:
    """Each tet's region, ``(m,)`` int: the box holding its centroid in a grid of
    ``nx x ny x nz`` equal boxes over the mesh's rest bounding box (index
    ``ix + nx (iy + ny iz)``). A definition by place, not by vertex: the same regions on
    any mesh of one body."""
    nx, ny, nz = check_region_grid(grid)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    centres = mesh.vertices[mesh.tets].mean(axis=1)
    span = np.where(hi > lo, hi - lo, 1.0)
    cells = np.array([nx, ny, nz])
    index = np.clip(np.floor((centres - lo) / span * cells).astype(np.int64), 0, cells - 1)
    return index[:, 0] + nx * (index[:, 1] + ny * index[:, 2])


def load_mesh(path: str | Path, reorient: bool = True) -> TetMesh:
    """Read a tetrahedral mesh with meshio (.msh, .vtu, .vtk, .mesh, .xdmf, ...).

    All ``tetra`` cell blocks are concatenated; other cells (triangles, lines) are
    ignored. Coordinates are taken as metres. Vertices used by no tet are dropped.
    Inverted tets are re-oriented unless ``reorient=False``.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If meshio cannot read the file, or it holds no linear tetrahedra.
    """
    import meshio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    # meshio lists ANSYS before gmsh for ".msh"; try gmsh first (the common case).
    formats = ["gmsh", "ansys"] if path.suffix.lower() == ".msh" else [None]
    errors = []
    for fmt in formats:
        # meshio prints its read errors and calls sys.exit(1) when no reader accepts the
        # file, so SystemExit is caught here and the printed reason is kept instead.
        chatter = io.StringIO()
        try:
            with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
                m = meshio.read(path, file_format=fmt)
            break
        except (Exception, SystemExit) as exc:  # meshio raises many kinds of errors
            said = " ".join(chatter.getvalue().split())
            reason = said if isinstance(exc, SystemExit) and said else f"{exc}"
            errors.append(f"as {fmt or 'detected format'}: {reason}")
    else:
        raise ValueError(f"cannot read mesh file {path} ({'; '.join(errors)})")
    blocks = [c.data for c in m.cells if c.type in _TET_CELL_TYPES]
    if not blocks:
        kinds = sorted({c.type for c in m.cells}) or ["none"]
        raise ValueError(
            f"mesh file {path} has no linear tetrahedra (cell types found: {', '.join(kinds)})"
        )
    tets = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(m.points, dtype=np.float64)
    if points.shape[1] == 2:
        raise ValueError(f"mesh file {path} is two-dimensional; tetrahedra need 3D points")
    used = np.unique(tets)
    if len(used) != len(points):
        remap = -np.ones(len(points), dtype=np.int64)
        remap[used] = np.arange(len(used))
        points, tets = points[used], remap[tets]
    return TetMesh(points[:, :3], tets, reorient=reorient)


def save_mesh(mesh: TetMesh, path: str | Path, **kwargs) -> Path:
    """Write ``mesh`` with meshio; the format follows the file extension.

    Extra keyword arguments go to :func:`meshio.write` (e.g. ``file_format=``). A
    ``.msh`` file is written in gmsh 4.1 format unless ``file_format`` says otherwise
    (meshio's own default for ``.msh`` is ANSYS). Returns the path written.
    """
    import meshio

    path = Path(path)
    if path.suffix.lower() == ".msh":
        kwargs.setdefault("file_format", "gmsh")
    out = meshio.Mesh(np.asarray(mesh.vertices), [("tetra", np.asarray(mesh.tets))])
    try:
        meshio.write(path, out, **kwargs)
    except Exception as exc:
        raise ValueError(f"cannot write mesh file {path}: {exc}") from exc
    return path
