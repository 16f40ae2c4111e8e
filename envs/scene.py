"""Retraction scenes as data: a :class:`Scene` dataclass that loads from and saves to YAML.

A scene says where the tissue mesh comes from (box cells, a gmsh organ and its element
size, or any meshio file), its physics (law and the range its stiffness is drawn from,
force field, integrator and step settings), which vertices are attached, grasped,
tracked and measured, where the target, the gripper and the camera are, and what the
tissue rests on. :func:`build_scene` turns it into the arrays the task runs on
(:class:`BuiltScene`). Every field is validated, and errors name it::

    scene = Scene.load("configs/scenes/tissue_retraction.yaml")
    scene = scene.updated({"physics": {"material": "StVenantKirchhoff", "integrator": "implicit"}})
    scene.save("my_scene.yaml")

Units: m, s, kg, Pa, rad.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from dataclasses import field as dataclass_field
from pathlib import Path

import numpy as np

from heml_gym import QuadraticTetMesh, box_mesh, load_mesh, materials, organs
from heml_gym.contact import MeshSupport, PlaneSupport
from heml_gym.mesh import TetMesh, check_region_grid
from heml_gym.model import FORCE_FIELDS
from heml_gym.solvers import SolverChoiceError, check_solver_choice

from .spec import SpecError, from_mapping, invalid, merge, to_mapping

__all__ = ["Scene", "TissueSpec", "PhysicsSpec", "RegionSpec", "FoldSpec", "AdhesionSpec", "TargetSpec",
           "GripperSpec", "HookSpec", "PaddleSpec", "StructureSpec", "CameraSpec", "SupportSpec", "BuiltScene", "build_scene", "LAWS", "ORGANS"]

#: Material laws by class name (``physics.material``).
LAWS = {cls.__name__: cls for cls in materials.ALL_MATERIALS}
#: Procedural organs (``tissue.organ``): name -> mesher in :mod:`heml_gym.organs`.
ORGANS = {"liver_lobe": organs.liver_lobe_mesh, "kidney": organs.kidney_mesh, "uterus": organs.uterus_mesh,
          "fat_flap": organs.fat_flap_mesh, "irregular_cube": organs.irregular_cube_mesh,
          "gallbladder": organs.gallbladder_mesh}

Vec3 = tuple[float, float, float]
OptVec3 = tuple[float | None, float | None, float | None]


def _finite(values) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def _check_start_and_workspace(spec, inside: bool = True) -> None:
    """An instrument spec's ``start_low``..``start_high`` and ``workspace_low``..``workspace_high``
    boxes: finite, low <= high, and (``inside``) the start box inside the workspace."""
    for lo_name, hi_name in (("start_low", "start_high"), ("workspace_low", "workspace_high")):
        lo, hi = getattr(spec, lo_name), getattr(spec, hi_name)
        if not (_finite(lo) and _finite(hi)) or any(a > b for a, b in zip(lo, hi)):
            raise invalid(spec, lo_name, f"{lo_name} {lo} and {hi_name} {hi} must be finite with low <= high")
    if inside and any(a < wl or b > wh for a, b, wl, wh in zip(spec.start_low, spec.start_high, spec.workspace_low,
                                                                spec.workspace_high)):
        raise invalid(spec, "start_low", "the start box must lie inside the workspace")


@dataclass
class TissueSpec:
    """Where the tissue mesh comes from (``kind``), in metres.

    ``"box"``: a ``size`` box at ``origin`` on a ``cells`` hex grid, 6 tets per cell
    (``mirrored``: alternating splits, see :func:`heml_gym.box_mesh`); ``"organ"``: the
    gmsh organ ``organ`` (one of :data:`ORGANS`) meshed at ``mesh_size``, with the mesher's
    other arguments in ``organ_options``; ``"file"``: any tet mesh meshio reads, at ``path``.
    """

    kind: str = "box"
    size: Vec3 | None = None
    cells: tuple[int, int, int] | None = None
    mirrored: bool = True
    origin: Vec3 = (0.0, 0.0, 0.0)
    organ: str | None = None
    mesh_size: float | None = None
    organ_options: dict = field(default_factory=dict)
    path: str | None = None

    def __post_init__(self):
        if self.kind == "box":
            if self.size is None or not _finite(self.size) or min(self.size) <= 0:
                raise invalid(self, "size", f"a box needs three positive lengths in metres, got {self.size}")
            if self.cells is None or min(self.cells) < 1:
                raise invalid(self, "cells", f"a box needs three cell counts >= 1, got {self.cells}")
        elif self.kind == "organ":
            if self.organ not in ORGANS:
                raise invalid(self, "organ", f"must be one of {sorted(ORGANS)}, got {self.organ!r}")
            if self.mesh_size is not None and not (math.isfinite(self.mesh_size) and self.mesh_size > 0):
                raise invalid(self, "mesh_size", f"must be a positive length in metres, got {self.mesh_size}")
        elif self.kind == "file":
            if not self.path:
                raise invalid(self, "path", "a file tissue needs the path of a mesh file")
        else:
            raise invalid(self, "kind", f"must be 'box', 'organ' or 'file', got {self.kind!r}")
        if not _finite(self.origin):
            raise invalid(self, "origin", f"must be three finite numbers, got {self.origin}")

    def key(self) -> str:
        return json.dumps(to_mapping(self), sort_keys=True)


@dataclass
class PhysicsSpec:
    """The model of the tissue and how it is stepped.

    ``material``: a law of :mod:`heml_gym.materials` by class name, built per episode
    from ``E`` drawn uniformly in ``young_modulus`` (Pa), ``poisson`` and
    ``material_options`` (e.g. ``{"b": 2.0}`` for Demiray); ``density`` (kg/m^3),
    ``damping`` (mass-proportional, 1/s), ``gravity`` (m/s^2); ``field``: ``"heml"``,
    ``"fem"``, ``"mass_tensor"`` (StVK only), ``"mass_spring"`` or ``"quadratic"`` (10-node
    tets on the tissue's cells, :class:`heml_gym.QuadraticTetMesh`: they bend on a coarse
    mesh; a node at the middle of every edge, which the scene's regions select as well);
    ``integrator``:
    ``"explicit"`` (sub-steps at ``safety`` times the critical step of the stiffest
    tissue the scene can draw), ``"implicit"`` (backward Euler steps of at most
    ``max_dt`` s, Newton to ``newton_tol`` of the weight in at most ``max_newton``
    iterations) or ``"quasi_newton"`` (the same steps by L-BFGS from a constant
    factorised Hessian, at most ``max_newton`` iterations: on HEML fields
    :class:`heml_gym.QuasiNewtonSolver`, on the others, quadratic tets included, the
    Newton solver's L-BFGS method, ``heml_gym.ImplicitSolver(method="lbfgs")``);
    ``scheme``: the implicit steps' time discretisation, ``"backward_euler"`` or, with
    ``"quasi_newton"`` on HEML, ``"bdf2"`` (second order, the same cost per step);
    ``hessian_scale``: the weight of the quasi-Newton initial Hessian's Laplacian in units
    of ``lambda + mu`` (on other fields, of their rest stiffness; iterations per step, not
    accuracy; the other integrators have no initial Hessian and do not read it, see
    :class:`heml_gym.QuasiNewtonSolver`);
    ``stiffness_regions``: Young's modulus varying over the tissue, ``{"grid": [nx, ny,
    nz], "relative": [...]}``: the tissue's rest bounding box cut into ``nx x ny x nz``
    equal boxes, and each box's E relative to the episode's drawn E (``nx ny nz`` numbers,
    x fastest; a tet is in the box that holds its centre, :func:`heml_gym.mesh.box_regions`);
    empty (the default): uniform. HEML fields only; ``heml-gym calibrate --regions`` fits it.
    ``tool_stiffness``: the contact penalty of rigid tools (paddles, touching shafts) in
    units of the tissue's own stiffness at each vertex (quasi_newton and implicit; the
    force a tool reports is within about its inverse of the exact one: 100, 1 %; 10 costs
    fewer solver iterations and reads about 7-24 % soft, ``docs/studies/instruments.md``).
    """

    material: str = "NeoHookean"
    young_modulus: tuple[float, float] = (4e3, 8e3)
    poisson: float = 0.45
    material_options: dict = field(default_factory=dict)
    density: float = 1000.0
    damping: float = 5.0
    gravity: Vec3 = (0.0, 0.0, -9.81)
    field: str = "heml"
    integrator: str = "explicit"
    safety: float = 0.5
    max_dt: float = 1.0 / 30.0
    newton_tol: float = 1e-3
    max_newton: int = 20
    scheme: str = "backward_euler"
    hessian_scale: float = 1.0
    stiffness_regions: dict = dataclass_field(default_factory=dict)  # (`field` is the force field here)
    tool_stiffness: float = 100.0

    def __post_init__(self):
        if self.material not in LAWS:
            raise invalid(self, "material", f"must be one of {sorted(LAWS)}, got {self.material!r}")
        lo, hi = self.young_modulus
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
            raise invalid(self, "young_modulus", f"must be [low, high] in Pa with 0 < low <= high, got {[lo, hi]}")
        if not (-1.0 < self.poisson < 0.5):
            raise invalid(self, "poisson", f"must lie in (-1, 0.5), got {self.poisson}")
        for E in (lo, hi):
            try:
                self.material_for(E)
            except (TypeError, ValueError) as exc:
                raise invalid(self, "material_options", f"{self.material}: {exc}") from None
        if not (math.isfinite(self.density) and self.density > 0):
            raise invalid(self, "density", f"must be a positive number of kg/m^3, got {self.density}")
        if not (math.isfinite(self.damping) and self.damping >= 0):
            raise invalid(self, "damping", f"must be a number >= 0 (1/s), got {self.damping}")
        if not _finite(self.gravity):
            raise invalid(self, "gravity", f"must be three finite numbers (m/s^2), got {self.gravity}")
        if self.field not in FORCE_FIELDS:
            raise invalid(self, "field", f"must be one of {sorted(FORCE_FIELDS)}, got {self.field!r}")
        if self.field == "mass_tensor" and self.material != "StVenantKirchhoff":
            raise invalid(self, "field", "'mass_tensor' needs material 'StVenantKirchhoff'")
        try:  # which integrator goes with which field and scheme: the solvers' own rules
            check_solver_choice(self.integrator, self.field, self.scheme)
        except SolverChoiceError as exc:
            raise invalid(self, exc.argument, exc.message) from None
        if not (0 < self.safety <= 1):
            raise invalid(self, "safety", f"must lie in (0, 1], got {self.safety}")
        if not (math.isfinite(self.max_dt) and self.max_dt > 0):
            raise invalid(self, "max_dt", f"must be a positive number of seconds, got {self.max_dt}")
        if not (math.isfinite(self.newton_tol) and self.newton_tol > 0):
            raise invalid(self, "newton_tol", f"must be a positive number, got {self.newton_tol}")
        if self.max_newton < 1:
            raise invalid(self, "max_newton", f"must be >= 1, got {self.max_newton}")
        if not (isinstance(self.hessian_scale, (int, float)) and not isinstance(self.hessian_scale, bool)
                and math.isfinite(self.hessian_scale) and self.hessian_scale > 0):
            raise invalid(self, "hessian_scale", f"must be a positive number, got {self.hessian_scale!r}")
        t = self.tool_stiffness
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (math.isfinite(t) and t > 0):
            raise invalid(self, "tool_stiffness", f"must be a positive number, got {t!r}")
        self._check_stiffness_regions()

    def _check_stiffness_regions(self) -> None:
        regions = self.stiffness_regions
        if not regions:
            return
        if not isinstance(regions, dict) or set(regions) != {"grid", "relative"}:
            raise invalid(self, "stiffness_regions", f"must be {{grid: [nx, ny, nz], relative: [nx ny nz numbers]}}, "
                                                     f"got {regions!r}")
        try:
            nx, ny, nz = check_region_grid(regions["grid"], "grid")
        except ValueError as exc:
            raise invalid(self, "stiffness_regions", str(exc)) from None
        relative = regions["relative"]
        if (not isinstance(relative, (list, tuple)) or len(relative) != nx * ny * nz
                or not all(isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and r > 0
                           for r in relative)):
            raise invalid(self, "stiffness_regions", f"relative: must be {nx * ny * nz} positive numbers (one per box, "
                                                     f"x fastest), got {relative!r}")
        if self.field != "heml":
            raise invalid(self, "stiffness_regions", f"a modulus that varies over the tissue needs field 'heml', "
                                                     f"got {self.field!r}")
        self.stiffness_regions = {"grid": [nx, ny, nz], "relative": [float(r) for r in relative]}

    def material_for(self, young_modulus: float) -> materials.Material:
        """The scene's law with Young's modulus ``young_modulus`` (Pa)."""
        return LAWS[self.material](E=young_modulus, nu=self.poisson, **self.material_options)


@dataclass
class RegionSpec:
    """A set of tissue vertices, chosen by their rest positions (m).

    The vertices inside the box ``low``..``high`` (a null bound: unbounded), within
    ``tolerance`` of the ``segment`` ``[a, b]``, or both; ``points``: instead, the vertex
    nearest to each point, in order. ``surface``: only boundary vertices.
    """

    low: OptVec3 | None = None
    high: OptVec3 | None = None
    segment: tuple[Vec3, Vec3] | None = None
    points: list[Vec3] | None = None
    surface: bool = False
    tolerance: float = 1e-7

    def __post_init__(self):
        if self.points is not None and (self.low, self.high, self.segment) != (None, None, None):
            raise invalid(self, "points", "give points alone, or a box and/or a segment")
        if self.points is None and (self.low, self.high, self.segment) == (None, None, None):
            raise invalid(self, "low", "a region needs a box (low, high), a segment or points")
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0):
            raise invalid(self, "tolerance", f"must be a length >= 0 in metres, got {self.tolerance}")

    def select(self, mesh: TetMesh) -> np.ndarray:
        """The region's vertex indices on ``mesh`` (sorted; in the order of ``points``)."""
        v = mesh.vertices
        candidates = mesh.surface_vertices if self.surface else np.arange(mesh.n_vertices)
        if self.points is not None:
            c = v[candidates]
            return np.array([candidates[np.argmin(np.linalg.norm(c - np.asarray(p), axis=1))] for p in self.points],
                            dtype=np.int64)
        keep = np.ones(len(candidates), dtype=bool)
        c = v[candidates]
        tol = self.tolerance
        for axis in range(3):
            if self.low is not None and self.low[axis] is not None:
                keep &= c[:, axis] >= self.low[axis] - tol
            if self.high is not None and self.high[axis] is not None:
                keep &= c[:, axis] <= self.high[axis] + tol
        if self.segment is not None:
            a, b = np.asarray(self.segment[0]), np.asarray(self.segment[1])
            d = b - a
            t = np.clip((c - a) @ d / (d @ d), 0.0, 1.0)
            keep &= np.linalg.norm(a + t[:, None] * d - c, axis=1) <= tol
        return candidates[keep]


@dataclass
class FoldSpec:
    """How far the tissue is folded back: about the hinge line parallel to y through
    ``(x, z) = hinge`` (m), the free tissue extending towards +x (``direction`` 1) or -x
    (-1). The ``edge`` vertices' fold angle (rad, from rest) over ``angle`` is the lift
    progress, a dense shaping signal."""

    hinge: tuple[float, float] = (0.0, 0.0)
    direction: float = 1.0
    angle: float = math.pi / 2
    edge: RegionSpec = field(default_factory=lambda: RegionSpec(low=(0.0, None, None)))

    def __post_init__(self):
        if self.direction not in (1.0, -1.0):
            raise invalid(self, "direction", f"must be 1 or -1, got {self.direction}")
        if not (math.isfinite(self.angle) and self.angle > 0):
            raise invalid(self, "angle", f"must be a positive angle in radians, got {self.angle}")


@dataclass
class AdhesionSpec:
    """Tissue stuck to what lies beneath it, over a width drawn per episode: the vertices of
    ``region`` (e.g. the underside) within ``d`` of the fold hinge, measured along the fold
    direction, are held where they rest for the whole episode, ``d`` drawn uniformly in
    ``width`` = [low, high] (m). The tissue then folds about a line ``d`` further out. A
    width is resolved to the mesh's vertices: on a mesh of cell ``h`` it moves the held
    set in steps of about ``h``."""

    region: RegionSpec
    width: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        lo, hi = self.width
        if not (_finite(self.width) and 0.0 <= lo <= hi):
            raise invalid(self, "width", f"must be [low, high] in metres with 0 <= low <= high, got {[lo, hi]}")


@dataclass
class TargetSpec:
    """The structure to expose: a sphere of ``radius`` (m) whose centre is drawn
    uniformly in the box ``low``..``high`` (m) per episode."""

    low: Vec3 = (0.0, 0.0, 0.0)
    high: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 0.008

    def __post_init__(self):
        if not (_finite(self.low) and _finite(self.high)) or any(a > b for a, b in zip(self.low, self.high)):
            raise invalid(self, "low", f"low {self.low} and high {self.high} must be finite with low <= high")
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise invalid(self, "radius", f"must be a positive length in metres, got {self.radius}")


@dataclass
class StructureSpec:
    """A critical structure that must not be harmed (a duct, a vessel): the cylinder of
    ``radius`` (m) about the segment ``start``..``end`` (m). An energised instrument within
    ``margin`` (m) of its surface harms it."""

    start: Vec3 = (0.0, 0.0, 0.0)
    end: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 0.003
    margin: float = 0.005

    def __post_init__(self):
        if not (_finite(self.start) and _finite(self.end)) or tuple(self.start) == tuple(self.end):
            raise invalid(self, "start", f"start {self.start} and end {self.end} must be distinct finite points")
        for name in ("radius", "margin"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                     and value > 0):
                raise invalid(self, name, f"must be a positive length in metres, got {value!r}")

    def distance(self, points) -> np.ndarray:
        """Distance (m) of ``points (k, 3)`` to the structure's surface (negative inside)."""
        a, b = np.asarray(self.start, dtype=np.float64), np.asarray(self.end, dtype=np.float64)
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        t = np.clip((p - a) @ (b - a) / float((b - a) @ (b - a)), 0.0, 1.0)
        return np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1) - self.radius


@dataclass
class GripperSpec:
    """The gripper starts uniformly in ``start_low``..``start_high`` and is kept inside
    ``workspace_low``..``workspace_high`` (m). ``jaw_length`` (m): closed jaws hold only the
    part of the scene's grasp region within half of it of them, measured along the
    region's long axis (at least its nearest vertex), so where along the region they close
    matters; null: all of the region within reach. ``jaw_ends``: ``"vertex"`` holds every
    vertex within the jaws exactly (the held length steps with the mesh's rows);
    ``"weighted"`` holds each vertex by its share of the region inside the jaws (its row's
    span along the axis, from midway to the previous row to midway to the next): a whole
    share exactly, a part ``w`` by a spring of ``w / (1 - w)`` times the tissue's own
    stiffness at the vertex (so that, in series with the tissue, it holds with ``w`` of
    it), a vertex with no share not at all. ``wrist_reach`` (m): jaws with a footprint on
    a free wrist: closed, they hold every vertex within this distance (at rest) of those
    they take (not fixed or stuck), rigidly, where it is, and the patch turns about the
    jaws' axis (the taken vertices' longest direction at rest) through its middle to
    where the tissue's torque on it vanishes (:meth:`heml_gym.Control.turn`; the
    ``quasi_newton`` integrator only, exact jaw ends); null: the jaws hold what they take,
    rigidly. ``port`` (m): the shaft passes through this point (a trocar in the body
    wall), outside the start box, and the grasper's action is then ``(pitch_rate,
    yaw_rate, insertion_rate, grasp)``: tilts about the port in units of ``angular_speed``
    (rad/s), at most ``max_tilt`` (rad) from the line to the middle of the start box
    (:class:`~heml_gym.envs.instruments.port.Port`); null: velocities along x, y, z.
    ``shaft_radius`` (m; a port only): the shaft, from the port to ``SHAFT_GAP`` behind the
    jaws, is a rigid capsule the tissue cannot enter (:mod:`heml_gym.tools`; its push in
    ``info`` as ``shaft_force``); null: it passes through the tissue. ``roll_speed``
    (rad/s; a port and ``jaw_length`` only): the jaws roll about the shaft at this rate
    for a roll command of 1, at most a quarter turn either way from the grasp region's
    axis; the action gains a fifth entry ``roll_rate`` (after ``grasp``), the state an
    entry ``jaw_roll`` (rad); closing, the jaws take the region's vertices within
    ``jaw_length / 2`` along their axis and ``settings.jaw_radius`` across it; rolling
    while they hold turns the held tissue with them (Grasper); null: the jaws lie along
    the grasp region's axis."""

    start_low: Vec3 = (0.0, 0.0, 0.0)
    start_high: Vec3 = (0.0, 0.0, 0.0)
    workspace_low: Vec3 = (-1.0, -1.0, -1.0)
    workspace_high: Vec3 = (1.0, 1.0, 1.0)
    jaw_length: float | None = None
    jaw_ends: str = "vertex"
    wrist_reach: float | None = None
    port: Vec3 | None = None
    angular_speed: float = 0.5
    max_tilt: float = 1.2
    shaft_radius: float | None = None
    roll_speed: float | None = None

    def __post_init__(self):
        if self.jaw_ends not in ("vertex", "weighted"):
            raise invalid(self, "jaw_ends", f"must be 'vertex' or 'weighted', got {self.jaw_ends!r}")
        r = self.wrist_reach
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r)
                              or r <= 0):
            raise invalid(self, "wrist_reach", f"must be a positive length in metres or null, got {r!r}")
        if r is not None and self.jaw_ends == "weighted":
            raise invalid(self, "wrist_reach", "a free wrist holds its patch exactly: give jaw_ends 'vertex'")
        j = self.jaw_length
        if j is not None and (isinstance(j, bool) or not isinstance(j, (int, float)) or not math.isfinite(j)
                              or j <= 0):
            raise invalid(self, "jaw_length", f"must be a positive length in metres or null, got {j!r}")
        _check_start_and_workspace(self)
        for name, high in (("angular_speed", math.inf), ("max_tilt", 1.5)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= high:
                raise invalid(self, name, f"must be a number in (0, {high:g}], got {value!r}")
        r = self.shaft_radius
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r)
                              or r <= 0):
            raise invalid(self, "shaft_radius", f"must be a positive length in metres or null, got {r!r}")
        if r is not None and self.port is None:
            raise invalid(self, "shaft_radius", "a shaft that touches tissue needs a port (give port)")
        w = self.roll_speed
        if w is not None and (isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w)
                              or w <= 0):
            raise invalid(self, "roll_speed", f"must be a positive angular speed in rad/s or null, got {w!r}")
        if w is not None and (self.port is None or self.jaw_length is None):
            raise invalid(self, "roll_speed", "jaws that roll about their shaft need a port and a jaw_length")
        if w is not None and self.wrist_reach is not None:
            raise invalid(self, "roll_speed", "jaws on a free wrist turn with the tissue: give roll_speed or "
                                              "wrist_reach, not both")
        if self.port is not None:
            if not isinstance(self.port, (list, tuple)) or len(self.port) != 3 or not _finite(self.port):
                raise invalid(self, "port", f"must be three finite coordinates in metres or null, got {self.port!r}")
            if all(lo <= p <= hi for p, lo, hi in zip(self.port, self.start_low, self.start_high)):
                raise invalid(self, "port", f"{list(self.port)} lies inside the start box: the shaft would have "
                                            "no direction")


@dataclass
class HookSpec:
    """An electrosurgical hook: its tip starts uniformly in ``start_low``..``start_high`` and
    is kept inside ``workspace_low``..``workspace_high`` (m); ``port`` as a grasper's. While
    energised it delivers ``power`` (W) to the tissue within ``reach`` (m) of its tip,
    shared equally among the surface vertices there; a stuck vertex is released once it
    has taken ``release_energy`` (J/m^2) times its share of the surface. The defaults: 30 W,
    a monopolar hook's usual setting; 2.6e6 J/m^2, what it takes to vaporise a 1 mm layer
    of water-like tissue (2.26 kJ/g latent heat plus 0.26 kJ/g to heat it from 37 to 100
    C, at 1 g/cm^3)."""

    start_low: Vec3 = (0.0, 0.0, 0.0)
    start_high: Vec3 = (0.0, 0.0, 0.0)
    workspace_low: Vec3 = (-1.0, -1.0, -1.0)
    workspace_high: Vec3 = (1.0, 1.0, 1.0)
    port: Vec3 | None = None
    angular_speed: float = 0.5
    max_tilt: float = 1.2
    reach: float = 0.004
    power: float = 30.0
    release_energy: float = 2.6e6

    def __post_init__(self):
        for name in ("reach", "power", "release_energy", "angular_speed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                     and value > 0):
                raise invalid(self, name, f"must be a positive number, got {value!r}")
        if not (isinstance(self.max_tilt, (int, float)) and 0 < self.max_tilt <= 1.5):
            raise invalid(self, "max_tilt", f"must be a number in (0, 1.5], got {self.max_tilt!r}")
        _check_start_and_workspace(self, inside=False)
        if self.port is not None and (not isinstance(self.port, (list, tuple)) or len(self.port) != 3
                                      or not _finite(self.port)):
            raise invalid(self, "port", f"must be three finite coordinates in metres or null, got {self.port!r}")
        if self.port is not None and all(lo <= p <= hi for p, lo, hi in zip(self.port, self.start_low,
                                                                             self.start_high)):
            raise invalid(self, "port", f"{list(self.port)} lies inside the start box: the shaft would have "
                                        "no direction")


@dataclass
class PaddleSpec:
    """A paddle retractor: a rigid blade of ``half_extents`` (m; thin along its local z)
    that pushes tissue and holds nothing. Its centre starts uniformly in
    ``start_low``..``start_high`` and is kept inside ``workspace_low``..``workspace_high``
    (m); it moves at up to ``max_speed`` (m/s) and tilts about its local y (its pitch) at up
    to ``angular_speed`` (rad/s), at most ``max_tilt`` (rad) from level. The default speed,
    30 mm/s, keeps the default 4 mm blade from passing through tissue (a vertex carried more
    than half its thickness per 0.05 s solver step would; :mod:`heml_gym.tools`)."""

    start_low: Vec3 = (0.0, 0.0, 0.0)
    start_high: Vec3 = (0.0, 0.0, 0.0)
    workspace_low: Vec3 = (-1.0, -1.0, -1.0)
    workspace_high: Vec3 = (1.0, 1.0, 1.0)
    half_extents: Vec3 = (0.02, 0.04, 0.002)
    max_speed: float = 0.03
    angular_speed: float = 0.5
    max_tilt: float = 0.6

    def __post_init__(self):
        if not _finite(self.half_extents) or len(self.half_extents) != 3 or min(self.half_extents) <= 0:
            raise invalid(self, "half_extents", f"must be three positive lengths in metres, got {self.half_extents}")
        for name, high in (("max_speed", math.inf), ("angular_speed", math.inf), ("max_tilt", 1.5)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= high:
                raise invalid(self, name, f"must be a number in (0, {high:g}], got {value!r}")
        _check_start_and_workspace(self)


@dataclass
class CameraSpec:
    """The task camera (the target's exposure is seen from it): ``eye`` (m) looking at
    ``look_at`` (m; null: the tissue's centre), ``up``, vertical field of view ``fov_y``
    (degrees)."""

    eye: Vec3 = (0.0, 0.0, 0.3)
    look_at: Vec3 | None = None
    up: Vec3 = (0.0, 1.0, 0.0)
    fov_y: float = 45.0

    def __post_init__(self):
        if not _finite(self.eye):
            raise invalid(self, "eye", f"must be three finite numbers, got {self.eye}")
        if not (0 < self.fov_y < 180):
            raise invalid(self, "fov_y", f"must lie in (0, 180) degrees, got {self.fov_y}")


@dataclass
class SupportSpec:
    """What the tissue rests on: ``"plane"`` (``normal . x >= offset``, m), ``"mesh"``
    (the outside of the closed surface of the ``mesh`` tissue source, distance grid of
    ``spacing`` m) or ``"none"``."""

    kind: str = "plane"
    normal: Vec3 = (0.0, 0.0, 1.0)
    offset: float = 0.0
    mesh: TissueSpec | None = None
    spacing: float | None = None

    def __post_init__(self):
        if self.kind not in ("plane", "mesh", "none"):
            raise invalid(self, "kind", f"must be 'plane', 'mesh' or 'none', got {self.kind!r}")
        if self.kind == "mesh" and self.mesh is None:
            raise invalid(self, "mesh", "a mesh support needs a mesh source (box, organ or file)")
        if self.kind == "plane" and (not _finite(self.normal) or not any(self.normal) or not math.isfinite(self.offset)):
            raise invalid(self, "normal", f"a plane needs a finite non-zero normal and offset, got {self.normal}")


@dataclass
class Scene:
    """A retraction scene (see the module docstring and the env docstrings).

    ``attachment``: the vertices that never move; ``adhesion``: more of them, held for an
    episode over a width drawn per episode (null: none); ``grasp``: the tissue the jaws
    hold (closing within ``grasp_reach`` of it holds all of it, or the part of it within
    ``gripper.jaw_length`` / 2 of the jaws; null: the nearest surface vertex and those within
    ``jaw_radius``); ``tracked``: the 4 points reported in the observation;
    ``strain_gauge``: the length (m) tissue strain is measured over; ``graspers``: several
    graspers by name, in action order (each name prefixes its ``info`` keys; null: one,
    ``gripper``, whose keys carry no name). With ``graspers``, ``gripper`` only frames
    single-grasper tools; ``marker``: one point of the tissue (the vertex nearest to it) that a
    goal-conditioned task brings to its goal, drawn per episode in ``target``'s region;
    ``hooks``: electrosurgical hooks by name (:class:`HookSpec`), after the graspers in the
    action and at the end of the state observation (null: none); ``paddles``: paddle
    retractors by name (:class:`PaddleSpec`), after the graspers and before the hooks in
    the action and the state observation (null: none); ``critical``: a structure that no
    energised instrument may come near (:class:`StructureSpec`; null: none). A scene with paddles may have no
    grasper (``graspers: {}``); ``gripper`` then only frames single-instrument tools.
    """

    name: str
    tissue: TissueSpec
    attachment: RegionSpec
    tracked: RegionSpec
    fold: FoldSpec
    target: TargetSpec
    gripper: GripperSpec
    camera: CameraSpec
    physics: PhysicsSpec = field(default_factory=PhysicsSpec)
    grasp: RegionSpec | None = None
    support: SupportSpec = field(default_factory=lambda: SupportSpec(kind="none"))
    strain_gauge: float = 0.015
    adhesion: AdhesionSpec | None = None
    graspers: dict[str, GripperSpec] | None = None
    marker: RegionSpec | None = None
    hooks: dict[str, HookSpec] | None = None
    paddles: dict[str, PaddleSpec] | None = None
    critical: StructureSpec | None = None

    def __post_init__(self):
        if not self.name:
            raise invalid(self, "name", "must be a non-empty string")
        if self.graspers is not None:
            if not self.graspers and not self.paddles:
                raise invalid(self, "graspers", "must name at least one grasper, or be null (one: gripper); "
                                                "only a scene with paddles may have none")
            for name, spec in self.graspers.items():
                if not (isinstance(name, str) and name.isidentifier()):
                    raise invalid(self, "graspers", f"names must be identifiers (they prefix info keys), got {name!r}")
                if not isinstance(spec, GripperSpec):
                    raise invalid(self, "graspers", f"{name}: must be a GripperSpec or a mapping of its fields")
            if sum(spec.wrist_reach is not None for spec in self.graspers.values()) > 1:
                raise invalid(self, "graspers", "at most one grasper may have jaws on a free wrist (wrist_reach)")
        for name, spec in (self.hooks or {}).items():
            if not (isinstance(name, str) and name.isidentifier()):
                raise invalid(self, "hooks", f"names must be identifiers (they prefix info keys), got {name!r}")
            if not isinstance(spec, HookSpec):
                raise invalid(self, "hooks", f"{name}: must be a HookSpec or a mapping of its fields")
            if name in (self.graspers or {}):
                raise invalid(self, "hooks", f"{name}: a grasper has that name")
        for name, spec in (self.paddles or {}).items():
            if not (isinstance(name, str) and name.isidentifier()):
                raise invalid(self, "paddles", f"names must be identifiers (they prefix info keys), got {name!r}")
            if not isinstance(spec, PaddleSpec):
                raise invalid(self, "paddles", f"{name}: must be a PaddleSpec or a mapping of its fields")
            if name in (self.graspers or {}) or name in (self.hooks or {}):
                raise invalid(self, "paddles", f"{name}: a grasper or hook has that name")
        if self.tracked.points is None or len(self.tracked.points) != 4:
            raise invalid(self, "tracked", "must give exactly 4 points")
        if not (math.isfinite(self.strain_gauge) and self.strain_gauge > 0):
            raise invalid(self, "strain_gauge", f"must be a positive length in metres, got {self.strain_gauge}")
        if self.marker is not None and (self.marker.points is None or len(self.marker.points) != 1):
            raise invalid(self, "marker", "must give exactly one point (points: [[x, y, z]])")

    # ----------------------------------------------------------------- data
    def to_dict(self) -> dict:
        return to_mapping(self)

    @classmethod
    def from_dict(cls, data: dict, path: str = "scene") -> "Scene":
        return from_mapping(cls, data, path)

    def updated(self, changes: dict, path: str = "scene") -> "Scene":
        """A copy with ``changes`` (a nested mapping of fields) merged in, validated."""
        if not isinstance(changes, dict):
            raise SpecError(f"{path}: changes must be a mapping, got {type(changes).__name__}")
        return from_mapping(Scene, merge(self.to_dict(), changes), path)

    def save(self, path: str | Path) -> Path:
        import yaml

        path = Path(path)
        path.write_text(yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Scene":
        import yaml

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"scene file not found: {path}")
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as exc:
            raise SpecError(f"scene file {path} is not valid YAML: {exc}") from None
        return from_mapping(cls, data, "scene")


# ------------------------------------------------------------------ built scenes
class BuiltScene:
    """A :class:`Scene` made concrete: the mesh and the vertex sets (arrays).

    Attributes: ``spec`` (the Scene), ``name``, ``mesh``, ``fixed``, ``tracked``,
    ``grasp_patch`` (or None), ``adhesion_vertices`` and their ``adhesion_distance`` (m)
    from the hinge (or None), ``edge_vertices``, ``surface_faces``, ``supports``
    (:mod:`heml_gym.contact` objects), and as arrays ``camera`` (eye), ``look_at``,
    ``target_low``, ``target_high``, ``gripper_low``, ``gripper_high``,
    ``workspace_low``, ``workspace_high`` (every grasper's); ``graspers`` (name, spec); ``target_radius``, ``hinge``,
    ``fold_direction``, ``fold_angle``, ``strain_gauge``, ``physics``.
    """

    def __init__(self, spec: Scene):
        self.spec = spec
        self.name = spec.name
        self.physics = spec.physics
        self.mesh = _tissue_mesh(spec.tissue, quadratic=spec.physics.field == "quadratic")
        mesh = self.mesh
        self.fixed = spec.attachment.select(mesh)
        if self.fixed.size == 0:
            raise SpecError(f"scene {spec.name!r}: scene.attachment selects no vertex of the mesh")
        self.tracked = spec.tracked.select(mesh)
        self.edge_vertices = spec.fold.edge.select(mesh)
        if self.edge_vertices.size == 0:
            raise SpecError(f"scene {spec.name!r}: scene.fold.edge selects no vertex to measure the lift by")
        self.grasp_patch = None
        if spec.grasp is not None:
            patch = np.setdiff1d(spec.grasp.select(mesh), self.fixed)
            if patch.size == 0:
                raise SpecError(f"scene {spec.name!r}: scene.grasp holds no free vertex")
            self.grasp_patch = patch
        self.adhesion_vertices = self.adhesion_distance = None
        if spec.adhesion is not None:
            candidates = np.setdiff1d(spec.adhesion.region.select(mesh), self.fixed)
            if candidates.size == 0:
                raise SpecError(f"scene {spec.name!r}: scene.adhesion.region selects no free vertex")
            self.adhesion_vertices = candidates
            # m from the hinge line, along the fold direction (where the free tissue lies)
            self.adhesion_distance = spec.fold.direction * (mesh.vertices[candidates, 0] - spec.fold.hinge[0])
        #: the marked vertex (a goal-conditioned task's achieved goal), or None
        self.marker = None if spec.marker is None else int(spec.marker.select(mesh)[0])
        self.surface_faces = mesh.boundary_faces
        self.supports = _supports(spec.support)
        cam = spec.camera
        self.camera = np.asarray(cam.eye, dtype=np.float64)
        self.look_at = np.asarray(cam.look_at if cam.look_at is not None else mesh.vertices.mean(axis=0))
        self.camera_up = np.asarray(cam.up, dtype=np.float64)
        self.camera_fov_y = float(cam.fov_y)
        t, g = spec.target, spec.gripper
        self.target_low, self.target_high = np.asarray(t.low), np.asarray(t.high)
        self.target_radius = float(t.radius)
        self.gripper_low, self.gripper_high = np.asarray(g.start_low), np.asarray(g.start_high)
        #: the graspers, ``[(name, GripperSpec), ...]`` in action order (one, unnamed: ``gripper``)
        self.graspers = [(None, g)] if spec.graspers is None else list(spec.graspers.items())
        #: the electrosurgical hooks, ``[(name, HookSpec), ...]`` in action order (after the graspers)
        self.hooks = list((spec.hooks or {}).items())
        #: the paddle retractors, ``[(name, PaddleSpec), ...]`` in action order (after the graspers)
        self.paddles = list((spec.paddles or {}).items())
        #: where any grasper (or paddle) may go (m): the union of their workspaces
        moving = [s for _, s in self.graspers + self.paddles]
        self.workspace_low = np.min([s.workspace_low for s in moving], axis=0).astype(np.float64)
        self.workspace_high = np.max([s.workspace_high for s in moving], axis=0).astype(np.float64)
        self.hinge = tuple(spec.fold.hinge)
        self.fold_direction = float(spec.fold.direction)
        self.fold_angle = float(spec.fold.angle)
        self.strain_gauge = float(spec.strain_gauge)

    def __repr__(self) -> str:
        return f"BuiltScene({self.name!r}, {self.mesh!r}, {len(self.fixed)} fixed)"


_MESHES: dict[str, TetMesh] = {}
_SUPPORTS: dict[str, object] = {}


def _tissue_mesh(spec: TissueSpec, quadratic: bool = False) -> TetMesh:
    """The mesh of a tissue source (cached: gmsh organs take a second or more); with
    ``quadratic``, its 10-node tets (:class:`heml_gym.QuadraticTetMesh`: a node at the
    middle of every edge, so the scene's regions select those nodes too)."""
    key = spec.key()
    if quadratic:
        if key + "|quadratic" not in _MESHES:
            _MESHES[key + "|quadratic"] = QuadraticTetMesh.from_linear(_tissue_mesh(spec))
        return _MESHES[key + "|quadratic"]
    if key not in _MESHES:
        if spec.kind == "box":
            mesh = box_mesh(spec.size, spec.cells, origin=spec.origin, mirrored=spec.mirrored)
        elif spec.kind == "organ":
            kwargs = dict(spec.organ_options)
            if spec.mesh_size is not None:
                kwargs["mesh_size"] = spec.mesh_size
            if "lines" in kwargs:
                kwargs["lines"] = tuple(tuple(tuple(p) for p in seg) for seg in kwargs["lines"])
            try:
                mesh = ORGANS[spec.organ](**kwargs)
            except TypeError as exc:
                raise SpecError(f"scene.tissue.organ_options: {exc}") from None
            except ValueError as exc:  # an organ option or the mesh size out of range; the message names it
                raise SpecError(f"scene.tissue ({spec.organ}): {exc}") from None
            if any(spec.origin):
                mesh = TetMesh(mesh.vertices + np.asarray(spec.origin), mesh.tets)
        else:
            mesh = load_mesh(spec.path)
            if any(spec.origin):
                mesh = TetMesh(mesh.vertices + np.asarray(spec.origin), mesh.tets)
        _MESHES[key] = mesh
    return _MESHES[key]


def _supports(spec: SupportSpec) -> list:
    if spec.kind == "none":
        return []
    if spec.kind == "plane":
        return [PlaneSupport(normal=spec.normal, offset=spec.offset)]
    key = spec.mesh.key() + f"|{spec.spacing}"
    if key not in _SUPPORTS:
        body = _tissue_mesh(spec.mesh)
        _SUPPORTS[key] = MeshSupport(body.vertices, body.boundary_faces, spacing=spec.spacing)
    return [_SUPPORTS[key]]


def build_scene(spec: Scene) -> BuiltScene:
    """The arrays of ``spec`` (meshes and supports are cached across calls)."""
    if not isinstance(spec, Scene):
        raise TypeError(f"scene must be a heml_gym.envs.Scene, got {type(spec).__name__}")
    return BuiltScene(spec)
