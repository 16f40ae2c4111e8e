"""Fitting a tissue to depth images: the tissue's rendered depth against the observed.

A depth camera (stereo, RGB-D) sees the tissue's surface. :class:`DepthTerm` compares,
at every observed time and pixel, the depth (m along the optical axis) at which the
pixel's ray meets the *model's* tissue surface with the observed depth there, and gives
the loss's derivative in the tissue's vertex positions: the ray meets the plane of the
triangle it hits at depth ``s = (n . c0) / (n . d)`` (``c0..c2`` the triangle's corners
in camera coordinates, ``n = (c1 - c0) x (c2 - c0)``, ``d`` the ray with ``d_z = 1``),
whose derivative in each corner is exact (which triangle a ray hits is held fixed: the
loss is smooth between silhouette changes). Pixels where the model's tissue is not hit,
or where nothing was observed (the far depth), do not count; the residual
``(s - depth) / scale`` is weighed by the pseudo-Huber function (quadratic within
``huber`` scales, linear beyond), so pixels where something else lies in front of the
tissue (the jaws) or the model's silhouette is off do not dominate. The loss is the sum
over counted pixels over the number of pixels observed (fixed), so it does not jump when a
pixel enters or leaves the model's silhouette more than that pixel's own term.

Camera: ``intrinsics`` ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]`` (pixels; pixel ``(i, j)``'s
centre at ``(j + 0.5, i + 0.5)``), ``camera_pose`` (4, 4) camera to world, its rotation's
columns the camera's x (image right), y (image down) and z (forward) axes in the world,
its translation the eye (m): the conventions of :mod:`heml_gym.envs.camera`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["DepthTerm", "render_tissue_depth", "camera_of"]

NEAR = 1e-3  # m: triangles with a corner closer to the camera are not drawn (the tissue is far in front)


@nb.njit(cache=True)
def _tissue_depth(x, faces, eye, rot, focal, cx, cy, depth, triangle):
    """Z-buffer ``faces`` of ``x`` (m) seen from ``eye`` / ``rot`` (world to camera):
    ``depth`` (H, W) m along the optical axis (``inf`` where no triangle), ``triangle``
    (H, W) the index of the face hit (-1 where none)."""
    height, width = depth.shape
    for i in range(height):
        for j in range(width):
            depth[i, j] = np.inf
            triangle[i, j] = -1
    c = np.empty((3, 3))
    u = np.empty(3)
    v = np.empty(3)
    for t in range(faces.shape[0]):
        ok = True
        for k in range(3):
            p = faces[t, k]
            for r in range(3):
                c[k, r] = rot[r, 0] * (x[p, 0] - eye[0]) + rot[r, 1] * (x[p, 1] - eye[1]) + rot[r, 2] * (x[p, 2] - eye[2])
            if c[k, 2] <= NEAR:
                ok = False
            else:
                u[k] = focal * c[k, 0] / c[k, 2] + cx
                v[k] = focal * c[k, 1] / c[k, 2] + cy
        if not ok:
            continue
        area = (u[1] - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (v[1] - v[0])
        if abs(area) < 1e-12:
            continue
        i0 = max(0, int(math.floor(min(v[0], v[1], v[2]) - 0.5)))
        i1 = min(height - 1, int(math.ceil(max(v[0], v[1], v[2]) - 0.5)))
        j0 = max(0, int(math.floor(min(u[0], u[1], u[2]) - 0.5)))
        j1 = min(width - 1, int(math.ceil(max(u[0], u[1], u[2]) - 0.5)))
        for i in range(i0, i1 + 1):
            py = i + 0.5
            for j in range(j0, j1 + 1):
                px = j + 0.5
                l1 = ((px - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (py - v[0])) / area
                l2 = ((u[1] - u[0]) * (py - v[0]) - (px - u[0]) * (v[1] - v[0])) / area
                l0 = 1.0 - l1 - l2
                if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                    continue
                z = 1.0 / (l0 / c[0, 2] + l1 / c[1, 2] + l2 / c[2, 2])
                if z < depth[i, j]:
                    depth[i, j] = z
                    triangle[i, j] = t


@nb.njit(cache=True)
def _depth_gradient(x, faces, eye, rot, focal, cx, cy, triangle, weight, x_bar):
    """``x_bar += sum over pixels of weight[i, j] * d s_ij / d x``: each drawn pixel's ray
    depth on the plane of its triangle, differentiated in the triangle's corners (exact
    for the plane; the triangle a pixel hits held fixed)."""
    height, width = triangle.shape
    c = np.empty((3, 3))
    for i in range(height):
        for j in range(width):
            t = triangle[i, j]
            w = weight[i, j]
            if t < 0 or w == 0.0:
                continue
            for k in range(3):
                p = faces[t, k]
                for r in range(3):
                    c[k, r] = rot[r, 0] * (x[p, 0] - eye[0]) + rot[r, 1] * (x[p, 1] - eye[1]) \
                        + rot[r, 2] * (x[p, 2] - eye[2])
            d0, d1, d2 = (j + 0.5 - cx) / focal, (i + 0.5 - cy) / focal, 1.0
            e1 = c[1] - c[0]
            e2 = c[2] - c[0]
            n = np.cross(e1, e2)
            nd = n[0] * d0 + n[1] * d1 + n[2] * d2
            if abs(nd) < 1e-300:
                continue
            s = (n[0] * c[0, 0] + n[1] * c[0, 1] + n[2] * c[0, 2]) / nd
            q = np.array([c[0, 0] - s * d0, c[0, 1] - s * d1, c[0, 2] - s * d2])
            g1 = np.cross(e2, q) / nd
            g2 = np.cross(q, e1) / nd
            g0 = n / nd - g1 - g2
            for k, g in ((0, g0), (1, g1), (2, g2)):
                p = faces[t, k]
                for col in range(3):  # camera to world: R^T g
                    x_bar[p, col] += w * (rot[0, col] * g[0] + rot[1, col] * g[1] + rot[2, col] * g[2])


def camera_of(intrinsics: np.ndarray, camera_pose: np.ndarray) -> tuple:
    """``(eye, rot, focal, cx, cy)`` of an observation's camera (see the module docstring)."""
    K = np.asarray(intrinsics, dtype=np.float64)
    pose = np.asarray(camera_pose, dtype=np.float64)
    rot = np.ascontiguousarray(pose[:3, :3].T)
    return np.ascontiguousarray(pose[:3, 3]), rot, float(K[0, 0]), float(K[0, 2]), float(K[1, 2])


def render_tissue_depth(x: np.ndarray, faces: np.ndarray, intrinsics, camera_pose, size) -> tuple:
    """``(depth (H, W) m, triangle (H, W))`` of the tissue surface ``faces`` of ``x`` (m)
    seen by the camera; ``inf`` / -1 where the tissue is not seen."""
    eye, rot, focal, cx, cy = camera_of(intrinsics, camera_pose)
    depth = np.empty(tuple(size))
    triangle = np.empty(tuple(size), dtype=np.int64)
    _tissue_depth(np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64), eye, rot,
                  focal, cx, cy, depth, triangle)
    return depth, triangle


class DepthTerm:
    """A depth-image term of a calibration loss (``heml_gym.calibration.Observed(extra=)``).

    Parameters
    ----------
    depth : (T + 1, H, W) float
        The observed depth (m along the optical axis) at the control steps ``0..T``;
        ``far`` or more (or non-finite) where nothing was seen.
    intrinsics, camera_pose : (3, 3), (4, 4)
        The camera (module docstring).
    faces : (f, 3) int
        The model's tissue surface triangles.
    scale : float
        m: a residual of one scale weighs as a point off by one ``point_scale`` does.
    huber : float
        Residuals (in scales) beyond this count linearly.
    far : float
        m: observed depths at or beyond it are "nothing seen".
    """

    name = "depth_m"

    def __init__(self, depth, intrinsics, camera_pose, faces, scale: float = 1e-3, huber: float = 3.0,
                 far: float = 10.0):
        self.depth = np.asarray(depth, dtype=np.float64)
        self.intrinsics, self.camera_pose = np.asarray(intrinsics), np.asarray(camera_pose)
        self.camera = camera_of(intrinsics, camera_pose)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.scale, self.huber, self.far = float(scale), float(huber), float(far)
        self.seen = np.isfinite(self.depth) & (self.depth < self.far)
        self.count = max(int(self.seen.sum()), 1)

    def _frame(self, x_t: np.ndarray, t: int):
        eye, rot, focal, cx, cy = self.camera
        depth = np.empty(self.depth.shape[1:])
        triangle = np.empty(self.depth.shape[1:], dtype=np.int64)
        _tissue_depth(np.ascontiguousarray(x_t), self.faces, eye, rot, focal, cx, cy, depth, triangle)
        counted = self.seen[t] & (triangle >= 0)
        r = np.zeros(depth.shape)
        r[counted] = (depth[counted] - self.depth[t][counted]) / self.scale
        return r, counted, triangle

    def __call__(self, x: np.ndarray):
        """``(loss, residuals, x_bar)`` of the positions ``x`` (T + 1, n, 3) m; the residuals
        (one per pixel and time, 0 where the pixel does not count) are the robust ones,
        ``sign(r) sqrt(2 rho(r))``."""
        eye, rot, focal, cx, cy = self.camera
        x_bar = np.zeros_like(x)
        loss, residuals = 0.0, []
        for t in range(x.shape[0]):
            r, counted, triangle = self._frame(x[t], t)
            root = np.sqrt(1.0 + (r / self.huber) ** 2)
            rho = np.where(counted, self.huber ** 2 * (root - 1.0), 0.0)
            loss += float(rho.sum())
            # the robust residual sign(r) sqrt(2 rho): r near 0, ~sqrt(2 huber |r|) far out (the
            # Gauss-Newton curvature and variance of the loss the fit minimises, not of outliers)
            residuals.append((np.sign(r) * np.sqrt(2.0 * rho)).reshape(-1))
            weight = np.where(counted, r / root, 0.0) / (self.count * self.scale)  # d loss / d s
            _depth_gradient(np.ascontiguousarray(x[t]), self.faces, eye, rot, focal, cx, cy, triangle, weight,
                            x_bar[t])
        return loss / self.count, np.concatenate(residuals), x_bar

    def residual_image(self, x_t: np.ndarray, t: int) -> np.ndarray:
        """(H, W) m: the model's tissue depth minus the observed at time ``t`` for positions
        ``x_t`` (n, 3); NaN where the pixel does not count."""
        r, counted, _ = self._frame(np.asarray(x_t, dtype=np.float64), t)
        return np.where(counted, r * self.scale, np.nan)

    def rms(self, x: np.ndarray) -> float:
        """RMS (m) of the depth residuals over the counted pixels of ``x`` (T + 1, n, 3)."""
        total, n = 0.0, 0
        for t in range(x.shape[0]):
            r, counted, _ = self._frame(x[t], t)
            total += float((r[counted] ** 2).sum())
            n += int(counted.sum())
        return math.sqrt(total / max(n, 1)) * self.scale
