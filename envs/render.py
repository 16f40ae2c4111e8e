"""A small CPU software rasteriser, so that ``render_mode="rgb_array"`` works without a GPU.

Units are metres; positions are float64 ``(..., 3)`` in the world frame.

Camera convention (a pinhole camera, as in OpenCV): the camera frame has ``x`` to the
right of the image, ``y`` down the image and ``z`` forward along the optical axis, and
``R = look_at(eye, target, up)`` maps world to camera coordinates,
``p_cam = R @ (p - eye)``; its rows are the camera axes written in the world frame.
``fov_y`` is the full vertical field of view in degrees, pixels are square, and pixel
``(row i, column j)`` has its centre at image coordinates ``(u, v) = (j + 0.5, i + 0.5)``
with the principal point at the image centre::

    u = width / 2 + f * x_cam / z_cam,   v = height / 2 + f * y_cam / z_cam,
    f = (height / 2) / tan(fov_y / 2)   (pixels)

Rasterisation: every triangle is drawn with one colour (flat shading) lit by a
headlight, a directional light along the optical axis:
``shade = ambient + (1 - ambient) |n . z_cam|`` with ``n`` the unit face normal, so a
face square to the view is drawn in its full colour, one seen edge-on in ``ambient``
times it, and both sides are lit alike (the flap's underside shows when it is lifted).
Pixels are covered when their centre is inside the projected triangle or on its edge
(edge functions evaluated at pixel centres, within the triangle's bounding box, in a
Numba kernel that also projects and shades), and a z-buffer in
``1/z_cam`` (interpolated linearly in screen space, which is exact under perspective)
keeps the nearest surface; on equal depth the triangle drawn first stays. Near-plane
handling is by discarding: a triangle with any vertex at ``z_cam <= near`` (behind the
camera or closer than ``near`` metres) is not drawn at all, rather than clipped. Worlds
here keep the camera well away from the tissue, so nothing visible is lost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

__all__ = ["Camera", "look_at", "rasterize", "icosphere", "box", "compose"]


def look_at(eye, target, up) -> np.ndarray:
    """World-to-camera rotation ``R`` (3, 3) of a camera at ``eye`` looking at ``target`` (m).

    Rows: ``x`` (image right) = normalise(forward x up), ``y`` (image down) =
    forward x right, ``z`` = forward = normalise(target - eye); so ``up`` (any vector
    not parallel to the view direction) points to the top of the image.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    fwd = np.asarray(target, dtype=np.float64).reshape(3) - eye
    nf = np.linalg.norm(fwd)
    if not nf > 0:
        raise ValueError("target must differ from eye")
    fwd = fwd / nf
    right = np.cross(fwd, np.asarray(up, dtype=np.float64).reshape(3))
    nr = np.linalg.norm(right)
    if not nr > 1e-9:
        raise ValueError("up must not be parallel to the view direction")
    right = right / nr
    down = np.cross(fwd, right)
    return np.stack([right, down, fwd])


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: centre ``eye`` (3,) (m), world-to-camera ``rotation`` (3, 3), ``fov_y`` (deg).

    ``near`` (m): triangles with a vertex closer than this along the optical axis (or
    behind the camera) are not drawn. Build one with :meth:`looking_at`.
    """

    eye: np.ndarray
    rotation: np.ndarray
    fov_y: float = 45.0
    near: float = 1e-3

    @classmethod
    def looking_at(cls, eye, target, up=(0.0, 1.0, 0.0), fov_y: float = 45.0,
                   near: float = 1e-3) -> "Camera":
        """Camera at ``eye`` looking at ``target`` (m) with ``up`` towards the image top."""
        if not 0.0 < fov_y < 180.0:
            raise ValueError(f"fov_y must be in (0, 180) degrees, got {fov_y}")
        if not near > 0.0:
            raise ValueError(f"near must be positive (m), got {near}")
        eye = np.array(eye, dtype=np.float64).reshape(3)
        return cls(eye, look_at(eye, target, up), float(fov_y), float(near))

    def focal_px(self, height: int) -> float:
        """Focal length in pixels for an image ``height`` pixels high."""
        return 0.5 * height / math.tan(math.radians(0.5 * self.fov_y))

    def project(self, points, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates ``(u, v)`` (n, 2) (pixels) and depths ``z_cam`` (n,) (m) of ``points`` (n, 3)."""
        p = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.eye) @ self.rotation.T
        f = self.focal_px(height)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([0.5 * width + f * p[:, 0] / p[:, 2],
                           0.5 * height + f * p[:, 1] / p[:, 2]], axis=1)
        return uv, p[:, 2]


@nb.njit(cache=True, inline="always")
def draw_triangles(x, faces, colours, ox, oy, oz, seg_id, eye, rot, focal, cx, cy, near, ambient, image,
                   inv_depth, seg):
    """Draw triangles ``faces`` of ``x + (ox, oy, oz)`` (m) with per-face ``colours`` (f, 3)
    in [0, 1] (one row: every face that colour) into ``image`` (H, W, 3) uint8, keeping
    the nearest surface in ``inv_depth`` (H, W) (``1/z_cam``, 0 = empty) and writing
    ``seg_id`` into ``seg`` (H, W) where drawn (``seg`` may be empty: not written).
    A triangle that crosses the near plane (``z_cam = near``) is clipped to its part in
    front of it (a triangle or a quadrilateral): a large one, such as a support plane
    reaching behind the camera, is drawn where it is seen, not dropped."""
    one_colour = colours.shape[0] == 1
    cam = np.empty((3, 3))  # rows: vertices in camera coordinates
    poly = np.empty((4, 3))  # the clipped polygon
    for t in range(faces.shape[0]):
        n_front = 0
        for c in range(3):
            vi = faces[t, c]
            wx = x[vi, 0] + ox - eye[0]
            wy = x[vi, 1] + oy - eye[1]
            wz = x[vi, 2] + oz - eye[2]
            for r in range(3):
                cam[c, r] = rot[r, 0] * wx + rot[r, 1] * wy + rot[r, 2] * wz
            if cam[c, 2] > near:
                n_front += 1
        if n_front == 0:
            continue
        # flat headlight shading
        e1x = cam[1, 0] - cam[0, 0]
        e1y = cam[1, 1] - cam[0, 1]
        e1z = cam[1, 2] - cam[0, 2]
        e2x = cam[2, 0] - cam[0, 0]
        e2y = cam[2, 1] - cam[0, 1]
        e2z = cam[2, 2] - cam[0, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        if not (nn > 0.0):
            continue  # degenerate triangle (or not finite)
        shade = ambient + (1.0 - ambient) * abs(nz) / nn  # |n . optical axis|
        k = 0 if one_colour else t
        cr = min(255, int(colours[k, 0] * shade * 255.0 + 0.5))
        cg = min(255, int(colours[k, 1] * shade * 255.0 + 0.5))
        cb = min(255, int(colours[k, 2] * shade * 255.0 + 0.5))
        if n_front == 3:
            _fill_triangle(cam[0], cam[1], cam[2], cr, cg, cb, seg_id, focal, cx, cy, image, inv_depth, seg)
            continue
        # clip to z > near (Sutherland-Hodgman against one plane: 3 or 4 vertices)
        m = 0
        for c in range(3):
            d = (c + 1) % 3
            zc = cam[c, 2]
            zd = cam[d, 2]
            if zc > near:
                poly[m] = cam[c]
                m += 1
            if (zc > near) != (zd > near):
                f = (near - zc) / (zd - zc)
                for r in range(3):
                    poly[m, r] = cam[c, r] + f * (cam[d, r] - cam[c, r])
                poly[m, 2] = near  # exactly on the plane, not a hair behind it
                m += 1
        for q in range(1, m - 1):  # a fan: one or two triangles
            _fill_triangle(poly[0], poly[q], poly[q + 1], cr, cg, cb, seg_id, focal, cx, cy, image, inv_depth, seg)


@nb.njit(cache=True)
def _fill_triangle(p0, p1, p2, cr, cg, cb, seg_id, focal, cx, cy, image, inv_depth, seg):
    """Rasterise one triangle given in camera coordinates (every ``z > 0``, m): the
    pixels whose centres it covers get the colour ``(cr, cg, cb)`` and ``seg_id`` where
    it is nearer than what is there (``inv_depth``: ``1/z``, interpolated linearly in
    screen space, as perspective-correct depth is)."""
    height = image.shape[0]
    width = image.shape[1]
    write_seg = seg.shape[0] == height
    iz0 = 1.0 / p0[2]
    iz1 = 1.0 / p1[2]
    iz2 = 1.0 / p2[2]
    u0 = cx + focal * p0[0] * iz0
    v0 = cy + focal * p0[1] * iz0
    u1 = cx + focal * p1[0] * iz1
    v1 = cy + focal * p1[1] * iz1
    u2 = cx + focal * p2[0] * iz2
    v2 = cy + focal * p2[1] * iz2
    area = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    if not (abs(area) > 1e-12):
        return  # edge-on or not finite
    if area < 0.0:  # make the winding positive: swap vertices 1 and 2
        u1, u2 = u2, u1
        v1, v2 = v2, v1
        iz1, iz2 = iz2, iz1
        area = -area
    # pixel-centre bounding box, clamped in floating point before any int conversion
    jlo = max(0.0, math.ceil(min(u0, u1, u2) - 0.5))
    jhi = min(width - 1.0, math.floor(max(u0, u1, u2) - 0.5))
    ilo = max(0.0, math.ceil(min(v0, v1, v2) - 0.5))
    ihi = min(height - 1.0, math.floor(max(v0, v1, v2) - 0.5))
    if jlo > jhi or ilo > ihi:
        return
    j0 = int(jlo)
    j1 = int(jhi)
    i0 = int(ilo)
    i1 = int(ihi)
    # edge functions w_k(u, v) = A_k u + B_k v + C_k, w_k >= 0 inside, sum = area
    a0 = v1 - v2
    b0 = u2 - u1
    c0 = u1 * v2 - u2 * v1
    a1 = v2 - v0
    b1 = u0 - u2
    c1 = u2 * v0 - u0 * v2
    a2 = v0 - v1
    b2 = u1 - u0
    c2 = u0 * v1 - u1 * v0
    inv_area = 1.0 / area
    for i in range(i0, i1 + 1):
        vc = i + 0.5
        for j in range(j0, j1 + 1):
            uc = j + 0.5
            w0 = a0 * uc + b0 * vc + c0
            w1 = a1 * uc + b1 * vc + c1
            w2 = a2 * uc + b2 * vc + c2
            if w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0:
                iz = (w0 * iz0 + w1 * iz1 + w2 * iz2) * inv_area
                if iz > inv_depth[i, j]:
                    inv_depth[i, j] = iz
                    image[i, j, 0] = cr
                    image[i, j, 1] = cg
                    image[i, j, 2] = cb
                    if write_seg:
                        seg[i, j] = seg_id


_NO_SEG = np.zeros((0, 0), dtype=np.uint8)


@nb.njit(cache=True)
def _rasterize_kernel(x, faces, colours, eye, rot, focal, cx, cy, near, ambient, image, inv_depth, seg):
    """Draw triangles ``faces`` of ``x`` with per-face ``colours`` (f, 3) in [0, 1] into ``image``.

    ``image`` (H, W, 3) uint8 holds the background and ``inv_depth`` (H, W) zeros on
    entry (``1/z_cam`` of the nearest surface so far, 0 = empty).
    """
    draw_triangles(x, faces, colours, 0.0, 0.0, 0.0, np.uint8(1), eye, rot, focal, cx, cy, near, ambient, image,
                   inv_depth, seg)


def _unit_colour(c) -> np.ndarray:
    """Colour array in [0, 1] as float64: integer dtypes (uint8, Python ints) are 0-255, floats 0-1."""
    c = np.asarray(c)
    if c.dtype.kind in "iu":
        return c.astype(np.float64) / 255.0
    return c.astype(np.float64)


def _colours01(colours, n_faces: int) -> np.ndarray:
    """Per-face colours as float64 (f, 3) in [0, 1] from integer (0-255) or float (0-1) input."""
    c = _unit_colour(colours)
    if c.shape == (3,):
        c = np.broadcast_to(c, (n_faces, 3))
    if c.shape != (n_faces, 3):
        raise ValueError(f"colours must have shape (3,) or ({n_faces}, 3), got {c.shape}")
    return np.ascontiguousarray(np.clip(c, 0.0, 1.0))


def rasterize(mesh, colours, camera: Camera, width: int = 160, height: int = 120,
              background=(0, 0, 0), ambient: float = 0.25,
              return_depth: bool = False):
    """Render triangles to an RGB image ``(height, width, 3)`` uint8 (see the module docstring).

    ``mesh`` is either ``tri_vertices`` (T, 3, 3) (m) or a pair ``(x (n, 3), faces (f, 3))``.
    ``colours`` are per face, (f, 3), or one (3,) colour for all: integer dtypes (uint8,
    Python ints) are 0-255, floats 0-1; ``background`` is one colour, read the same way.
    ``ambient`` in [0, 1] is the shade of a face seen edge-on (1 = no lighting). With ``return_depth`` also returns the depth
    image ``z_cam`` (m), ``inf`` where nothing was drawn.
    """
    if isinstance(mesh, tuple):
        x, faces = mesh
        x = np.ascontiguousarray(x, dtype=np.float64)
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if x.ndim != 2 or x.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"(x, faces) must have shapes (n, 3), (f, 3); got {x.shape}, {faces.shape}")
    else:
        tri = np.asarray(mesh, dtype=np.float64)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3):
            raise ValueError(f"tri_vertices must have shape (T, 3, 3), got {tri.shape}")
        x = np.ascontiguousarray(tri.reshape(-1, 3))
        faces = np.arange(x.shape[0], dtype=np.int64).reshape(-1, 3)
    width = int(width)
    height = int(height)
    if width < 1 or height < 1:
        raise ValueError(f"width and height must be positive, got {width} x {height}")
    col = _colours01(colours, faces.shape[0])
    bg = np.clip(np.rint(_unit_colour(background) * 255.0), 0, 255).astype(np.uint8).reshape(3)
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[...] = bg
    inv_depth = np.zeros((height, width))
    _rasterize_kernel(x, faces, col, np.ascontiguousarray(camera.eye, dtype=np.float64),
                      np.ascontiguousarray(camera.rotation, dtype=np.float64),
                      camera.focal_px(height), 0.5 * width, 0.5 * height, float(camera.near),
                      float(ambient), image, inv_depth, _NO_SEG)
    if return_depth:
        with np.errstate(divide="ignore"):
            return image, np.where(inv_depth > 0.0, 1.0 / inv_depth, np.inf)
    return image


# ----------------------------------------------------------------------------- primitives


def icosphere(radius: float, center=(0.0, 0.0, 0.0), subdivisions: int = 1):
    """Triangulated sphere of ``radius`` (m) at ``center`` (m): ``(vertices (v, 3), faces (f, 3))``.

    An icosahedron whose triangles are split in four ``subdivisions`` times, new
    vertices pushed onto the sphere: ``f = 20 * 4**subdivisions`` faces (20, 80, 320,
    1280), counter-clockwise seen from outside (outward normals).
    """
    subdivisions = int(subdivisions)
    if subdivisions < 0:
        raise ValueError(f"subdivisions must be >= 0, got {subdivisions}")
    p = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0),
             (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
             (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    verts = [np.array(v, dtype=np.float64) / math.sqrt(1.0 + p * p) for v in verts]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
             (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
             (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
             (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def midpoint(a, b):
            key = (a, b) if a < b else (b, a)
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    v = np.asarray(center, dtype=np.float64).reshape(3) + float(radius) * np.array(verts)
    return v, np.array(faces, dtype=np.int64)


def box(center, half_sizes, rotation=None):
    """Closed box of ``half_sizes`` (3,) (m) at ``center`` (3,) (m): ``(vertices (8, 3), faces (12, 3))``.

    Axis-aligned unless ``rotation`` (3, 3), the box-to-world rotation, is given.
    Faces are counter-clockwise seen from outside (outward normals).
    """
    h = np.asarray(half_sizes, dtype=np.float64).reshape(3)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                       dtype=np.float64) * h
    if rotation is not None:
        corners = corners @ np.asarray(rotation, dtype=np.float64).reshape(3, 3).T
    v = corners + np.asarray(center, dtype=np.float64).reshape(3)
    # corner index = 4 * (x > 0) + 2 * (y > 0) + (z > 0)
    faces = np.array([[0, 1, 3], [0, 3, 2],   # -x
                      [4, 6, 7], [4, 7, 5],   # +x
                      [0, 4, 5], [0, 5, 1],   # -y
                      [2, 3, 7], [2, 7, 6],   # +y
                      [0, 2, 6], [0, 6, 4],   # -z
                      [1, 5, 7], [1, 7, 3]],  # +z
                     dtype=np.int64)
    return v, faces


def compose(meshes):
    """Concatenate ``[(x (n, 3), faces (f, 3), colour), ...]`` into one ``(x, faces, colours)``.

    ``colour`` is one (3,) colour or per-face (f, 3), integer (0-255) or float (0-1).
    Returns ``x`` (sum n, 3) float64, ``faces`` (sum f, 3) int64 (re-indexed) and
    ``colours`` (sum f, 3) uint8, ready for :func:`rasterize` ``((x, faces), colours)``.
    """
    xs, fs, cs = [], [], []
    offset = 0
    for x, faces, colour in meshes:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        xs.append(x)
        fs.append(faces + offset)
        cs.append(np.rint(_colours01(colour, faces.shape[0]) * 255.0).astype(np.uint8))
        offset += x.shape[0]
    if not xs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
    return np.concatenate(xs), np.concatenate(fs), np.concatenate(cs)
