"""Camera observations: RGB, depth and segmentation of N worlds in one parallel Numba call.

The task camera (the scene's ``camera``: the one the target's exposure is measured from)
sees the tissue surface, the target, the instruments (jaws, a paddle's blade, a hook's tip,
a shaft that touches tissue) and the support. Every world is
drawn by :func:`render_worlds` (z-buffered triangles, flat headlight shading: the
rasteriser of :mod:`heml_gym.envs.render`), worlds over threads, no GPU and no OpenGL.

* RGB: ``(H, W, 3)`` uint8;
* depth: ``(H, W, 1)`` float32, metres along the camera's optical axis (``z`` in the
  camera frame, not the distance to the eye), ``far`` where nothing is seen;
* segmentation: ``(H, W, 1)`` uint8, :data:`SEGMENT_IDS` (background, tissue, target,
  instrument, support).

``jitter`` (m) moves each world's camera eye by a uniform offset in
``[-jitter, jitter]^3`` per episode (the same look-at point), for sim-to-real
robustness. Units: m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np
from numba import prange

from .palette import (BACKGROUND, HOOK_OFF, HOOK_ON, JAW_HALF_SIZE, JAW_OFFSET, JAWS_CLOSED, JAWS_OPEN, PADDLE, SHAFT,
                      SUPPORT, TARGET, TISSUE, unit)
from .render import box, draw_triangles, icosphere, look_at
from .spec import invalid

__all__ = ["ImageSpec", "CameraRenderer", "SEGMENT_IDS", "render_worlds"]

#: Segmentation labels.
SEGMENT_IDS = {"background": 0, "tissue": 1, "target": 2, "instrument": 3, "support": 4}
#: m: the half size of the cubes that draw jaws that roll (along their axis) and shafts
JAW_TILE = 0.003



@dataclass
class ImageSpec:
    """The image observations' settings (``camera=`` of the envs, a mapping of these
    fields; where the camera is, is the scene's :class:`~heml_gym.envs.scene.CameraSpec`):
    ``size`` ``[height, width]`` in pixels (or one number: square), ``segmentation`` (add
    a segmentation image), ``state`` (add the state vector), ``jitter`` (m, camera eye
    offset per episode), ``far`` (m, the depth of the background and the depth bound)."""

    size: list[int] | int = 84
    segmentation: bool = False
    state: bool = False
    jitter: float = 0.0
    far: float = 1.0

    def __post_init__(self):
        size = [self.size, self.size] if isinstance(self.size, int) else list(self.size)
        if len(size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and 8 <= v <= 1024 for v in size):
            raise invalid(self, "size", f"must be [height, width] (or one number), each 8-1024 pixels, got {self.size}")
        self.size = size
        if not (math.isfinite(self.jitter) and self.jitter >= 0):
            raise invalid(self, "jitter", f"must be a length >= 0 in metres, got {self.jitter}")
        if not (math.isfinite(self.far) and self.far > 0):
            raise invalid(self, "far", f"must be a positive length in metres, got {self.far}")


class SceneMeshes(NamedTuple):
    """What every world draws, as triangles and colours (``(1, 3)`` rows in [0, 1]): the
    tissue's surface ``faces`` (over each world's vertices), the target sphere and the jaw
    box templates (placed per world), the support, and the background colour ``(3,)``
    uint8."""

    faces: np.ndarray
    tissue_colour: np.ndarray
    sphere_v: np.ndarray
    sphere_f: np.ndarray
    target_colour: np.ndarray
    box_v: np.ndarray
    box_f: np.ndarray
    support_v: np.ndarray
    support_f: np.ndarray
    support_colour: np.ndarray
    background: np.ndarray


class WorldPoses(NamedTuple):
    """Per world (leading axis N): the tissue's vertices ``x`` (m), the target's place (m),
    the K instrument boxes' places ``grippers (N, K, 3)`` (m), their colours ``(N, K, 3)``
    and their sizes ``box_scales (N, K, 3)`` (times the jaws' box, along x, y, z), the
    camera's eye (m) and its world-to-camera rotation ``rots (N, 3, 3)``."""

    x: np.ndarray
    targets: np.ndarray
    grippers: np.ndarray
    jaw_colours: np.ndarray
    box_scales: np.ndarray
    eyes: np.ndarray
    rots: np.ndarray


class Lens(NamedTuple):
    """The pinhole: ``focal`` length and principal point ``cx, cy`` (pixels), ``near`` and
    ``far`` (m), and the ``ambient`` share of the headlight shading."""

    focal: float
    cx: float
    cy: float
    near: float
    far: float
    ambient: float


class Images(NamedTuple):
    """The outputs: ``rgb (N, H, W, 3)`` uint8, ``depth (N, H, W, 1)`` float32 (m along the
    optical axis, ``far`` where empty), ``seg (N, H, W)`` uint8."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray


@nb.njit(cache=True, inline="always")
def _render_one(s, poses, meshes, lens, images):
    x, targets, grippers, jaw_colours, box_scales, eyes, rots = poses
    faces, tissue_colour, sphere_v, sphere_f, target_colour, box_v, box_f, support_v, support_f, support_colour, \
        background = meshes
    focal, cx, cy, near, far, ambient = lens
    image = images.rgb[s]
    labels = images.seg[s]
    depth = images.depth
    height, width = image.shape[0], image.shape[1]
    inv = np.zeros((height, width))
    for i in range(height):
        for j in range(width):
            image[i, j, 0] = background[0]
            image[i, j, 1] = background[1]
            image[i, j, 2] = background[2]
            labels[i, j] = 0
    eye, rot = eyes[s], rots[s]
    # the support first, into a depth buffer of its own: it lies behind everything else
    # (the target sits below the organ's surface, and exposure counts what the tissue hides,
    # so the image shows the target wherever the tissue does not cover it)
    inv_support = np.zeros((height, width))
    draw_triangles(support_v, support_f, support_colour, 0.0, 0.0, 0.0, np.uint8(4), eye, rot, focal, cx, cy, near,
                   ambient, image, inv_support, labels)
    draw_triangles(x[s], faces, tissue_colour, 0.0, 0.0, 0.0, np.uint8(1), eye, rot, focal, cx, cy, near, ambient,
                   image, inv, labels)
    draw_triangles(sphere_v, sphere_f, target_colour, targets[s, 0], targets[s, 1], targets[s, 2], np.uint8(2), eye,
                   rot, focal, cx, cy, near, ambient, image, inv, labels)
    for k in range(grippers.shape[1]):  # every instrument's box (jaws, a hook's tip, a part of a blade)
        draw_triangles(box_v * box_scales[s, k], box_f, jaw_colours[s, k:k + 1], grippers[s, k, 0], grippers[s, k, 1],
                       grippers[s, k, 2], np.uint8(3), eye, rot, focal, cx, cy, near, ambient, image, inv, labels)
    for i in range(height):
        for j in range(width):
            z = far
            if inv[i, j] > 0.0:
                z = 1.0 / inv[i, j]
            elif inv_support[i, j] > 0.0:
                z = 1.0 / inv_support[i, j]
            depth[s, i, j, 0] = min(z, far)


@nb.njit(cache=True, parallel=True)
def render_worlds(poses, meshes, lens, images):
    """Draw every world ``s`` (tissue ``poses.x[s]`` over ``meshes.faces``, the target
    sphere at ``poses.targets[s]``, a jaw box at each of ``poses.grippers[s]`` in
    ``poses.jaw_colours[s]``, the support) from its camera (``poses.eyes[s]``,
    ``poses.rots[s]``) through ``lens`` into ``images`` (:class:`WorldPoses`,
    :class:`SceneMeshes`, :class:`Lens`, :class:`Images`), worlds over threads."""
    for s in prange(poses.x.shape[0]):
        _render_one(s, poses, meshes, lens, images)


@nb.njit(cache=True)
def render_worlds_serial(poses, meshes, lens, images):
    """:func:`render_worlds` world after world (one world: no thread launch)."""
    for s in range(poses.x.shape[0]):
        _render_one(s, poses, meshes, lens, images)


def _row(colour) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(colour, dtype=np.float64).reshape(1, 3))


class CameraRenderer:
    """Camera images of every world of a :class:`~heml_gym.envs.core.BatchedRetraction`.

    ``spec``: :class:`ImageSpec`. :meth:`render` fills :attr:`rgb`, :attr:`depth` and
    :attr:`segmentation` (arrays with a leading world axis) and returns them;
    :meth:`new_pose` draws world ``i``'s camera jitter (called at each reset).
    """

    def __init__(self, task, spec: ImageSpec):
        self.task, self.spec = task, spec
        scene = task.scene
        n = task.n
        self.height, self.width = spec.size
        self.base_eye = np.asarray(scene.camera, dtype=np.float64)
        self.look_at = np.asarray(scene.look_at, dtype=np.float64)
        self.up = np.asarray(scene.camera_up, dtype=np.float64)
        self.fov_y = float(scene.camera_fov_y)
        self.near = 1e-3
        self.focal = 0.5 * self.height / math.tan(math.radians(0.5 * self.fov_y))
        self.eyes = np.repeat(self.base_eye[None], n, axis=0)
        self.rots = np.repeat(look_at(self.base_eye, self.look_at, self.up)[None], n, axis=0)
        self.faces = np.ascontiguousarray(scene.surface_faces, dtype=np.int64)
        sv, sf = icosphere(scene.target_radius, subdivisions=1)
        self.sphere = (np.ascontiguousarray(sv), np.ascontiguousarray(sf))
        bv, bf = box(JAW_OFFSET, JAW_HALF_SIZE)
        self.box = (np.ascontiguousarray(bv), np.ascontiguousarray(bf))
        self.support = self.support_mesh(scene)
        self.meshes = SceneMeshes(self.faces, _row(unit(TISSUE)), *self.sphere, _row(unit(TARGET)), *self.box,
                                  *self.support, _row(unit(SUPPORT)), BACKGROUND)
        self.lens = Lens(float(self.focal), 0.5 * self.width, 0.5 * self.height, self.near, float(spec.far), 0.25)
        self.rgb = np.zeros((n, self.height, self.width, 3), dtype=np.uint8)
        self.depth = np.zeros((n, self.height, self.width, 1), dtype=np.float32)
        self.segmentation = np.zeros((n, self.height, self.width, 1), dtype=np.uint8)

    @staticmethod
    def support_mesh(scene):
        """The support as triangles: a plane as a square 1 m across under the tissue, a mesh
        support as its surface; none: no triangles."""
        from heml_gym.contact import MeshSupport, PlaneSupport

        verts, faces = [], []
        for sup in scene.supports:
            offset = sum(len(v) for v in verts)
            if isinstance(sup, PlaneSupport):
                n = sup.normal
                centre = scene.mesh.vertices.mean(axis=0)
                centre = centre - (n @ centre - sup.offset) * n
                a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
                a /= np.linalg.norm(a)
                b = np.cross(n, a)
                corners = [centre + 0.5 * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
                verts.append(np.array(corners))
                faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + offset)
            elif isinstance(sup, MeshSupport):
                verts.append(sup.vertices)
                faces.append(sup.faces + offset)
        if not verts:
            return np.zeros((1, 3)), np.zeros((0, 3), dtype=np.int64)
        return np.ascontiguousarray(np.concatenate(verts)), np.ascontiguousarray(np.concatenate(faces), dtype=np.int64)

    def new_pose(self, i: int, rng: np.random.Generator) -> None:
        """World ``i``'s camera for a new episode: the scene's, its eye moved by the jitter."""
        eye = self.base_eye + (rng.uniform(-1.0, 1.0, 3) * self.spec.jitter if self.spec.jitter else 0.0)
        self.eyes[i] = eye
        self.rots[i] = look_at(eye, self.look_at, self.up)

    def instrument_boxes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every instrument of every world as boxes: places ``(N, B, 3)`` (m), scales ``(N,
        B, 3)`` of the jaw box (each drawn its scaled ``JAW_OFFSET`` above its place) and
        colours ``(N, B, 3)`` in [0, 1]. Jaws are one box at the grasp point, grey when
        open and green when closed (jaws that roll: cubes along their axis); a paddle's
        blade is flat boxes tiling its face; a shaft that touches tissue cubes from its end
        to its port; a hook's tip the jaw box, orange when energised."""
        t = self.task
        closed = np.where(t.grasping_all[:, :, None], np.array(unit(JAWS_CLOSED)), np.array(unit(JAWS_OPEN)))
        places, scales, colours = [], [], []

        def add(centres, half, colour):  # boxes centred on ``centres`` (N, k, 3), of half sizes ``half`` (m)
            scale = np.broadcast_to(np.asarray(half, dtype=np.float64) / np.asarray(JAW_HALF_SIZE), centres.shape)
            places.append(centres - scale * np.asarray(JAW_OFFSET))
            scales.append(scale)
            colours.append(np.broadcast_to(colour, centres.shape))

        for k, g in enumerate(t.instruments):
            if g.kind == "paddle":
                add(*g.blade_tiles(), np.array(unit(PADDLE)))
            elif getattr(g, "roll_speed", None) is not None:
                add(g.jaw_tiles(JAW_TILE), JAW_TILE, closed[:, k:k + 1])
            else:
                places.append(t.grippers[:, k:k + 1])
                scales.append(np.ones((t.n, 1, 3)))
                colours.append(closed[:, k:k + 1])
        for g in t.instruments:
            shaft = g.shaft_tiles() if g.kind == "grasper" else None
            if shaft is not None:
                add(*shaft, np.array(unit(SHAFT)))
        if getattr(t, "hooks", None):
            places.append(t.hook_tips)
            scales.append(np.ones_like(t.hook_tips))
            colours.append(np.where(t.hooks_energised[:, :, None], np.array(unit(HOOK_ON)), np.array(unit(HOOK_OFF))))
        if not places:  # (nothing to draw)
            return np.zeros((t.n, 0, 3)), np.zeros((t.n, 0, 3)), np.zeros((t.n, 0, 3))
        return np.concatenate(places, axis=1), np.concatenate(scales, axis=1), np.concatenate(colours, axis=1)

    def render(self):
        """``(rgb, depth, segmentation)`` of every world (arrays owned by the renderer)."""
        t = self.task
        places, scales, jaw = self.instrument_boxes()
        kernel = render_worlds if t.n > 1 and nb.get_num_threads() > 1 else render_worlds_serial
        poses = WorldPoses(np.ascontiguousarray(t.x), np.ascontiguousarray(t.target), np.ascontiguousarray(places),
                           np.ascontiguousarray(jaw), np.ascontiguousarray(scales, dtype=np.float64), self.eyes,
                           self.rots)
        kernel(poses, self.meshes, self.lens, Images(self.rgb, self.depth, self.segmentation[..., 0]))
        return self.rgb, self.depth, self.segmentation
