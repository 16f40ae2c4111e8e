"""Procedural organ and test meshes, tetrahedralised with gmsh (OpenCASCADE kernel).

Every function returns a :class:`~heml_gym.mesh.TetMesh` in metres, positively oriented,
with no unused vertices. Meshing is headless, single-threaded and seeded, so two calls
with the same arguments return identical arrays (on the same gmsh build).

gmsh is an optional dependency: ``pip install 'heml-gym[mesh]'``.
"""

from __future__ import annotations

import threading
from typing import Callable

import numpy as np

from .mesh import TetMesh

__all__ = [
    "gmsh_solid_mesh",
    "kidney_mesh",
    "uterus_mesh",
    "liver_lobe_mesh",
    "fat_flap_mesh",
    "irregular_cube_mesh",
]


def _import_gmsh():
    try:
        import gmsh
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "procedural meshes need gmsh: pip install 'heml-gym[mesh]'"
        ) from exc
    return gmsh


def gmsh_solid_mesh(build_fn: Callable[[object], None], mesh_size: float, refine=()) -> TetMesh:
    """Tetrahedralise the OCC solid(s) that ``build_fn(gmsh)`` adds to a fresh model.

    ``build_fn`` receives the ``gmsh`` module and adds entities through
    ``gmsh.model.occ`` (it need not synchronise). All 3D entities are meshed with
    linear tets of target edge length ``mesh_size`` (metres) except inside the boxes of
    ``refine``: each ``(low, high, size, transition)`` asks for edges of ``size`` (m)
    inside the axis-aligned box ``low``-``high`` (m; ``None`` coordinates are unbounded),
    growing linearly to ``mesh_size`` over ``transition`` (m) outside it. Node tags are
    remapped to ``0..n-1`` and nodes used by no tet are dropped.
    """
    mesh_size = _positive_length("mesh_size", mesh_size)
    boxes = [_refinement_box(k, box) for k, box in enumerate(refine)]
    for k, box in enumerate(boxes):
        if box[2] >= mesh_size:
            raise ValueError(f"refine[{k}]: size {box[2]} m must be below mesh_size {mesh_size} m (a box "
                             "refines the mesh; it cannot coarsen it)")
    smallest = min([mesh_size] + [b[2] for b in boxes])
    gmsh = _import_gmsh()
    # gmsh installs a SIGINT handler when interruptible, which Python allows only on the
    # main thread: a Ray trial or any worker thread meshing an organ would fail.
    on_main_thread = threading.current_thread() is threading.main_thread()
    gmsh.initialize(readConfigFiles=False, interruptible=on_main_thread)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay surfaces
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay volumes
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.ElementOrder", 1)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeMin", smallest)
        gmsh.option.setNumber("Mesh.MeshSizeMax", mesh_size)
        gmsh.model.add("heml_gym_solid")
        build_fn(gmsh)
        gmsh.model.occ.synchronize()
        if boxes:
            _size_field(gmsh, boxes, mesh_size)
        if not gmsh.model.getEntities(3):
            raise ValueError("build_fn created no 3D entity to mesh")
        gmsh.model.mesh.generate(3)
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        _, elem_nodes = gmsh.model.mesh.getElementsByType(4)
    finally:
        gmsh.finalize()
    node_tags = np.asarray(node_tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    tet_tags = np.asarray(elem_nodes, dtype=np.int64).reshape(-1, 4)
    if len(tet_tags) == 0:
        raise ValueError("gmsh produced no tetrahedra")
    # Keep only nodes used by a tet, in increasing-tag order, and renumber them 0..n-1.
    used = np.unique(tet_tags)
    tag_to_row = np.full(node_tags.max() + 1, -1, dtype=np.int64)
    tag_to_row[node_tags] = np.arange(len(node_tags))
    rows = tag_to_row[used]
    if np.any(rows < 0):
        raise ValueError("gmsh returned a tet referencing an unknown node")
    index = np.full(node_tags.max() + 1, -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    return TetMesh(coords[rows], index[tet_tags], reorient=True)


def _positive_length(name: str, value) -> float:
    """``value`` as a positive, finite length in metres, else a ValueError naming ``name``."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive length in metres, got {value!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive length in metres, got {value}")
    return value


def _refinement_box(k: int, box) -> tuple:
    """Validate ``refine[k]`` = ``(low, high, size, transition)`` (metres)."""
    try:
        low, high, size, transition = box
        low, high = [[None if c is None else float(c) for c in corner] for corner in (low, high)]
        size, transition = float(size), float(transition)
    except (TypeError, ValueError):
        raise ValueError(f"refine[{k}] must be (low, high, size, transition) in metres, got {box!r}") from None
    if len(low) != 3 or len(high) != 3:
        raise ValueError(f"refine[{k}]: low and high must have 3 coordinates, got {low}, {high}")
    if not (np.isfinite(size) and size > 0 and np.isfinite(transition) and transition >= 0):
        raise ValueError(f"refine[{k}]: size must be > 0 and transition >= 0 metres, got {size}, {transition}")
    for a, b in zip(low, high):
        if a is not None and b is not None and not a <= b:
            raise ValueError(f"refine[{k}]: low must not exceed high, got {low}, {high}")
    return low, high, size, transition


def _size_field(gmsh, boxes, mesh_size: float) -> None:
    """The smallest of one gmsh Box size field per refinement box, as the background mesh."""
    field = gmsh.model.mesh.field
    tags = []
    for low, high, size, transition in boxes:
        tag = field.add("Box")
        field.setNumber(tag, "VIn", size)
        field.setNumber(tag, "VOut", mesh_size)
        for axis, lo, hi in zip("XYZ", low, high):
            field.setNumber(tag, f"{axis}Min", -1e3 if lo is None else lo)
            field.setNumber(tag, f"{axis}Max", 1e3 if hi is None else hi)
        field.setNumber(tag, "Thickness", transition)
        tags.append(tag)
    smallest = field.add("Min")
    field.setNumbers(smallest, "FieldsList", tags)
    field.setAsBackgroundMesh(smallest)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)


def _ellipsoid(gmsh, centre, semi_axes) -> int:
    """Add an OCC ellipsoid (a dilated unit sphere) and return its volume tag.

    The sphere is first turned so that its poles lie on the longest semi-axis: with the
    poles on a short axis the dilated (B-spline) surface is badly parametrised and
    gmsh's surface mesher intermittently fails and over-refines it.
    """
    occ = gmsh.model.occ
    tag = occ.addSphere(*centre, 1.0)
    longest = int(np.argmax(semi_axes))
    if longest != 2:  # OCC sphere poles are on z; turn them onto x (about y) or y (about x)
        axis = (0.0, 1.0, 0.0) if longest == 0 else (1.0, 0.0, 0.0)
        occ.rotate([(3, tag)], *centre, *axis, np.pi / 2)
    occ.dilate([(3, tag)], *centre, *semi_axes)
    return tag


def kidney_mesh(mesh_size: float = 0.007) -> TetMesh:
    """Kidney-like bean, centred at the origin, long axis along x (metres).

    An ellipsoid with semi-axes (0.055, 0.03, 0.0225) m (0.11 x 0.06 x 0.045 m) with a
    hilum notch: an ellipsoid of semi-axes (0.022, 0.016, 0.03) m centred on the -y
    side at y = -0.034 m is cut away. Volume ~1.48e-4 m^3 (~95 % of the full ellipsoid).
    At the default ``mesh_size`` (m): about 630 nodes and 2,400 tets, the scale of the
    HEML seed's kidney (~800 nodes, ~2,000 tets); meshing takes ~0.3 s.
    """

    def build(gmsh):
        body = _ellipsoid(gmsh, (0.0, 0.0, 0.0), (0.055, 0.03, 0.0225))
        notch = _ellipsoid(gmsh, (0.0, -0.034, 0.0), (0.022, 0.016, 0.03))
        gmsh.model.occ.cut([(3, body)], [(3, notch)])

    return gmsh_solid_mesh(build, mesh_size)


def uterus_mesh(mesh_size: float = 0.0035) -> TetMesh:
    """Pear-shaped uterus, fundus up along +z, cervix down along -z (metres).

    An ellipsoid body with semi-axes (0.025, 0.02, 0.04) m (0.05 wide x 0.04 thick x
    0.08 long) centred at the origin, fused with a cone neck (cervix) of radii
    0.016 m -> 0.011 m running from z = -0.02 m down to z = -0.06 m. At the default
    ``mesh_size``: about 2,400 nodes and 10,800 tets (the seed's uterus scale, ~11,000
    tets); meshing takes ~0.5 s.
    """

    def build(gmsh):
        occ = gmsh.model.occ
        body = _ellipsoid(gmsh, (0.0, 0.0, 0.0), (0.025, 0.02, 0.04))
        neck = occ.addCone(0.0, 0.0, -0.02, 0.0, 0.0, -0.04, 0.016, 0.011)
        occ.fuse([(3, body)], [(3, neck)])

    return gmsh_solid_mesh(build, mesh_size)


def liver_lobe_mesh(mesh_size: float = 0.0085, lines=(), base_x: float | None = None, edge_size: float | None = None,
                    edge_band: float = 0.03, refine=()) -> TetMesh:
    """Flattened, wedge-like liver lobe (metres).

    A half-ellipsoid of semi-axes (0.08, 0.05, 0.05) m (0.16 x 0.10 x 0.05 m overall)
    keeps its z >= 0 half (flat inferior face at z = 0), and is then cut by the plane
    z = 0.035 + 0.25 x so that it thins towards -x (the left, sharp edge).
    At the default ``mesh_size``: about 820 nodes and 3,100 tets; meshing takes ~0.3 s.

    ``lines``: straight segments ``((x0, y0, z0), (x1, y1, z1))`` (m) lying on the lobe's
    faces, imprinted on them, so that every mesh has nodes along them and the nodes on
    a segment are the same line of tissue at any ``mesh_size`` (an attachment or a grasp,
    say). Parts of a segment outside the lobe are ignored. ``base_x`` (m): cut the lobe
    off at the plane x = ``base_x`` (its base, where it would join the rest of the liver).
    ``edge_size`` (m): finer elements within ``edge_band`` (m) of the thin edge (x <=
    -0.08 + ``edge_band``), growing to ``mesh_size`` over the next ``edge_band``: the thin
    part bends most, and coarse linear tets there are too stiff in bending. ``refine``: more
    refinement boxes, as for :func:`gmsh_solid_mesh`.
    """
    refine = tuple(refine)
    if edge_size is not None:
        edge_size, edge_band = _positive_length("edge_size", edge_size), _positive_length("edge_band", edge_band)
        if edge_size >= float(mesh_size):
            raise ValueError(f"edge_size must be below mesh_size ({mesh_size} m), got {edge_size} m")
        refine += (((None, None, None), (-0.08 + edge_band, None, None), edge_size, edge_band),)

    def build(gmsh):
        occ = gmsh.model.occ
        lobe = _ellipsoid(gmsh, (0.0, 0.0, 0.0), (0.08, 0.05, 0.05))
        big = 1.0
        below = occ.addBox(-big / 2, -big / 2, -big, big, big, big)  # z < 0
        # Half-space above the tilted plane z = 0.035 + 0.25 x: a box rotated about y.
        above = occ.addBox(-big / 2, -big / 2, 0.0, big, big, big)
        occ.rotate([(3, above)], 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -np.arctan(0.25))
        occ.translate([(3, above)], 0.0, 0.0, 0.035)
        tools = [(3, below), (3, above)]
        if base_x is not None:
            tools.append((3, occ.addBox(base_x, -big / 2, -big / 2, big, big, big)))
        body, _ = occ.cut([(3, lobe)], tools)
        segments = [(1, occ.addLine(occ.addPoint(*a), occ.addPoint(*b))) for a, b in lines]
        if segments:
            occ.fragment(body, segments)

    return gmsh_solid_mesh(build, mesh_size, refine)


def gallbladder_mesh(mesh_size: float = 0.005, length: float = 0.085, radius: float = 0.016,
                     neck_radius: float = 0.008, bed_depth: float = 0.009) -> TetMesh:
    """A gallbladder lying in its bed: a pear-shaped sac along +x, its neck at x = 0 (metres).

    The body is an ellipsoid of semi-axes (0.4 ``length``, ``radius``, ``radius``) whose far
    end, the fundus, reaches x = ``length``; a cone narrowing from 0.8 ``radius`` to
    ``neck_radius`` joins it to the neck, cut off at x = 0 (where the cystic duct leaves).
    The sac sinks ``bed_depth`` into its bed: everything below that depth is cut away, so
    it lies on a flat underside at z = 0 from neck to fundus, its axis at z = ``radius`` -
    ``bed_depth``. At the defaults (85 mm long, 32 mm wide, 23 mm high): about 500 nodes
    and 1,700 tets.
    """
    length, radius = _positive_length("length", length), _positive_length("radius", radius)
    neck_radius, bed_depth = _positive_length("neck_radius", neck_radius), _positive_length("bed_depth", bed_depth)
    if not (neck_radius < radius and radius - neck_radius < bed_depth < radius):
        raise ValueError(f"need neck_radius ({neck_radius}) < radius ({radius}) m and bed_depth ({bed_depth} m) "
                         "between their difference and radius (the neck then rests in the bed too)")
    axis_z = radius - bed_depth

    def build(gmsh):
        occ = gmsh.model.occ
        body = _ellipsoid(gmsh, (0.6 * length, 0.0, axis_z), (0.4 * length, radius, radius))
        neck = occ.addCone(-0.01 * length, 0.0, axis_z, 0.45 * length, 0.0, 0.0, neck_radius, 0.8 * radius)
        sac, _ = occ.fuse([(3, body)], [(3, neck)])
        big = 1.0
        below = occ.addBox(-big / 2, -big / 2, -big, big, big, big)  # z < 0: the bed
        behind = occ.addBox(-big, -big / 2, -big / 2, big, big, big)  # x < 0: beyond the neck
        occ.cut(sac, [(3, below), (3, behind)])

    return gmsh_solid_mesh(build, mesh_size)


def fat_flap_mesh(
    size: tuple[float, float, float] = (0.12, 0.12, 0.008),
    mesh_size: float = 0.012,
    layers: int = 2,
) -> TetMesh:
    """Thin slab ``[0, size]`` in metres (a fat flap), unstructured in plane.

    ``size`` is (length, width, thickness) along x, y, z. The top view is an
    unstructured gmsh triangulation of edge ``mesh_size`` (m), extruded into ``layers``
    layers of prisms through the thickness, each split into 3 tets. (A free Delaunay
    tetrahedralisation of a slab thinner than its element size leaves near-flat
    slivers, altitude ~1e-4 edge, that would wreck the explicit time step.) At the
    defaults: about 430 nodes and 1,450 tets (~0.02 s).
    """
    sx, sy, sz = (float(s) for s in size)
    if not all(np.isfinite(s) and s > 0 for s in (sx, sy, sz)):
        raise ValueError(f"size must be three positive lengths in metres, got {size}")
    if int(layers) != layers or layers < 1:
        raise ValueError(f"layers must be a positive integer, got {layers}")

    def build(gmsh):
        occ = gmsh.model.occ
        rect = occ.addRectangle(0.0, 0.0, 0.0, sx, sy)
        occ.extrude([(2, rect)], 0.0, 0.0, sz, numElements=[int(layers)], recombine=False)

    return gmsh_solid_mesh(build, mesh_size)


def irregular_cube_mesh(size: float = 0.1, mesh_size: float | None = None) -> TetMesh:
    """Unstructured cube ``[0, size]^3`` in metres (the seed's "Irreg. Cube").

    ``mesh_size`` (metres) defaults to ``0.26 * size``: 4 edge divisions, about 150
    nodes and 400 tets whatever the ``size`` (~0.02 s).
    """
    size = float(size)
    if not np.isfinite(size) or size <= 0:
        raise ValueError(f"size must be a positive length in metres, got {size}")
    if mesh_size is None:
        mesh_size = 0.26 * size

    def build(gmsh):
        gmsh.model.occ.addBox(0.0, 0.0, 0.0, size, size, size)

    return gmsh_solid_mesh(build, mesh_size)
