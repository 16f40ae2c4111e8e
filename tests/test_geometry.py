"""Tests of heml_gym.envs.geometry (visibility by ray casting) and heml_gym.envs.render.

Expectations are computed independently of the code under test: line-plane
intersections by hand for occlusion by flat squares, a vectorised numpy Moller-Trumbore
over every (sample, triangle) pair for random scenes, the back-face rule written out in
numpy, and for the rasteriser the pinhole model inverted per pixel centre (a ray cast
onto the plane of the triangle, then a barycentric point-in-triangle test in the world).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from heml_gym.envs.geometry import (
    fibonacci_sphere,
    visible_counts,
    visible_fraction,
    visible_fraction_batch,
)
from heml_gym.envs.render import Camera, box, compose, icosphere, look_at, rasterize

METHODS = ["grid", "brute"]

# ----------------------------------------------------------------------------- helpers


def square(half: float, z: float, cx: float = 0.0, cy: float = 0.0, x_range=None):
    """Horizontal rectangle at height ``z`` as two triangles sharing a diagonal: (x, faces)."""
    x0, x1 = (cx - half, cx + half) if x_range is None else x_range
    x = np.array([[x0, cy - half, z], [x1, cy - half, z], [x1, cy + half, z], [x0, cy + half, z]])
    return x, np.array([[0, 1, 2], [0, 2, 3]])


def numpy_hidden(points, eye, x, faces, eps=1e-9):
    """Reference: hidden[i] when any triangle crosses segment eye->p_i more than eps from both ends."""
    v0, v1, v2 = (x[faces[:, c]] for c in range(3))
    e1, e2 = v1 - v0, v2 - v0
    d = points - eye  # (k, 3) unnormalised directions, t in (0, 1) between the ends
    length = np.linalg.norm(d, axis=1)
    p = np.cross(d[:, None, :], e2[None])  # (k, f, 3)
    det = np.einsum("fj,kfj->kf", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = eye - v0  # (f, 3)
        u = np.einsum("fj,kfj->kf", s, p) * inv
        q = np.cross(s, e1)  # (f, 3)
        v = np.einsum("kj,fj->kf", d, q) * inv
        t = np.einsum("fj,fj->f", e2, q)[None] * inv
        tol = (eps / length)[:, None]
        hit = (np.abs(det) > 1e-14) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > tol) & (t < 1 - tol)
    return hit.any(axis=1)


def random_scene(rng, n_tri=150, k=64):
    """Tumour-like samples near the origin under a layer of random triangles, camera above."""
    points = 0.01 * fibonacci_sphere(k) + rng.normal(0, 1e-3, 3)
    centres = rng.uniform([-0.04, -0.04, 0.012], [0.04, 0.04, 0.03], size=(n_tri, 3))
    x = (centres[:, None, :] + rng.normal(0, 0.006, size=(n_tri, 3, 3))).reshape(-1, 3)
    faces = np.arange(3 * n_tri).reshape(-1, 3)
    return points, x, faces


# ----------------------------------------------------------------------------- fibonacci


@pytest.mark.parametrize("n", [1, 16, 64, 300])
def test_fibonacci_sphere_unit_and_spread(n):
    p = fibonacci_sphere(n)
    assert p.shape == (n, 3) and p.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-14)
    if n == 1:
        return
    spacing = math.sqrt(4 * math.pi / n)  # side of the area each point owns
    dist = np.linalg.norm(p[:, None] - p[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    assert dist.min() > 0.8 * spacing
    # no large hole: every direction of a dense random set has a sample nearby
    probe = np.random.default_rng(0).normal(size=(4000, 3))
    probe /= np.linalg.norm(probe, axis=1, keepdims=True)
    gap = np.linalg.norm(probe[:, None] - p[None], axis=-1).min(axis=1).max()
    assert gap < 1.0 * spacing
    assert np.linalg.norm(p.mean(axis=0)) < 2.0 / n  # balanced


def test_fibonacci_sphere_rejects_empty():
    with pytest.raises(ValueError):
        fibonacci_sphere(0)


# ----------------------------------------------------------------------------- visibility


@pytest.mark.parametrize("method", METHODS)
def test_point_below_square_hidden_beside_and_above_visible(method):
    x, faces = square(0.05, 0.0)
    eye = np.array([0.0, 0.0, 1.0])
    cases = {
        (0.01, 0.02, -0.05): 0,   # under the square
        (0.01, 0.01, -0.05): 0,   # under the shared diagonal: watertight
        (0.0, 0.0, -0.3): 0,      # on the axis, under the middle of the shared diagonal
        (0.2, 0.0, -0.05): 1,     # beside: the segment passes the plane at x = 0.19 > 0.05
        (0.01, 0.02, 0.05): 1,    # above the square
        (0.01, 0.02, 0.0): 1,     # on the square: a hit at the sample itself does not count
        (0.01, 0.02, -1e-10): 1,  # closer to the square than eps = 1e-9 m
        (0.01, 0.02, -1e-6): 0,   # farther than eps
    }
    for p, expected in cases.items():
        assert visible_counts(np.array([p]), eye, x, faces, method=method) == (expected, 1), p
    # a fan of four triangles around a centre vertex: a segment through that vertex
    fan_x = np.array([[0.0, 0.0, 0.0], [-0.05, -0.05, 0.0], [0.05, -0.05, 0.0],
                      [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0]])
    fan = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
    assert visible_counts(np.array([[0.0, 0.0, -0.3]]), eye, fan_x, fan, method=method) == (0, 1)
    assert visible_counts(np.array([[0.0, 0.03, -0.3]]), eye, fan_x, fan, method=method) == (0, 1)
    # occlusion is two-sided: seen from below, a point above is hidden
    below = np.array([0.0, 0.0, -1.0])
    assert visible_counts(np.array([[0.01, 0.02, 0.05]]), below, x, faces, method=method) == (0, 1)
    # the eye side: a triangle beyond the sample (farther from the eye) never hides it
    assert visible_counts(np.array([[0.01, 0.02, 0.5]]), eye, x, faces, method=method) == (1, 1)


@pytest.mark.parametrize("method", METHODS)
def test_hemisphere_half_covered(method):
    p = fibonacci_sphere(400)
    points = 0.01 * p[p[:, 2] > 0]
    eye = np.array([0.0, 0.0, 0.3])
    h = 0.02
    x, faces = square(0.05, h, x_range=(-0.05, 0.0))  # covers x in [-0.05, 0], |y| <= 0.05
    # independent: where the segment crosses the plane z = h
    t = (eye[2] - h) / (eye[2] - points[:, 2])
    xi = eye[0] + t * (points[:, 0] - eye[0])
    yi = eye[1] + t * (points[:, 1] - eye[1])
    hidden = (xi >= -0.05) & (xi <= 0.0) & (np.abs(yi) <= 0.05)
    expected = 1.0 - hidden.mean()
    assert abs(expected - 0.5) < 0.05
    vis, cnt = visible_counts(points, eye, x, faces, method=method)
    assert cnt == len(points)
    assert vis == len(points) - hidden.sum()
    if method == "grid":
        assert visible_fraction(points, eye, x, faces) == pytest.approx(expected, abs=1e-15)


@pytest.mark.parametrize("seed", range(6))
def test_random_scenes_match_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    points, x, faces = random_scene(rng)
    eyes = [np.array([0.0, 0.0, 0.25]),                    # top-down
            np.array([0.15, -0.1, 0.12]),                  # oblique
            rng.uniform([-0.03, -0.03, 0.015], [0.03, 0.03, 0.025]),  # among the triangles
            np.array([0.0, 0.0, 0.0]) + points.mean(axis=0)]         # inside the samples
    for eye in eyes:
        expected = int((~numpy_hidden(points, eye, x, faces)).sum())
        for method in METHODS:
            assert visible_counts(points, eye, x, faces, method=method) == (expected, len(points))


def test_triangle_reaching_towards_the_eye_plane():
    """A vertex almost level with the eye projects far off the grid; the grid must still list it."""
    points = 0.01 * fibonacci_sphere(100)
    eye = np.array([0.0, 0.0, 0.3])
    for dz in [1e-12, 1e-8, 1e-3, -1e-3]:  # depth of the top vertex below the eye (m)
        x = np.array([[-0.03, -0.002, 0.0], [0.002, -0.03, 0.0], [0.5, 0.5, eye[2] - dz]])
        faces = np.array([[0, 1, 2]])
        expected = int((~numpy_hidden(points, eye, x, faces)).sum())
        assert expected < len(points)
        for method in METHODS:
            assert visible_counts(points, eye, x, faces, method=method) == (expected, len(points))


def test_bad_arguments_raise():
    p = np.zeros((4, 3))
    x, faces = square(0.05, 0.1)
    with pytest.raises(ValueError):
        visible_fraction(p, [0, 0, 1], x, faces + 1)  # index 4 of 4 vertices
    with pytest.raises(ValueError):
        visible_fraction(p, [0, 0, 1], x, faces - 1)
    with pytest.raises(ValueError):
        visible_fraction_batch(p[None], [0, 0, 1], x[None], faces + 1)
    with pytest.raises(ValueError):
        visible_counts(p, [0, 0, 1], x, faces, method="bvh")
    with pytest.raises(ValueError):
        visible_fraction(p[:, :2], [0, 0, 1], x, faces)


def test_empty_inputs():
    eye = np.array([0.0, 0.0, 1.0])
    p = np.array([[0.0, 0.0, 0.0]])
    no_faces = np.zeros((0, 3), np.int64)
    assert visible_fraction(p, eye, np.zeros((0, 3)), no_faces) == 1.0
    assert visible_fraction(np.zeros((0, 3)), eye, np.zeros((0, 3)), no_faces) == 0.0
    # degenerate (zero-area) triangles never occlude
    x = np.array([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.2, 0.0, 0.5]])
    assert visible_fraction(p, eye, x, np.array([[0, 1, 2]])) == 1.0


def test_sphere_back_faces_excluded():
    c = np.array([0.01, -0.02, 0.0])
    r = 0.01
    points = c + r * fibonacci_sphere(256)
    eye = np.array([0.0, 0.0, 0.3])
    front = np.einsum("ij,ij->i", points - c, eye - points) > 0  # the rule, written out
    assert 0 < front.sum() < len(points) / 2  # a camera at a finite distance sees under half
    no_x, no_faces = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    assert visible_counts(points, eye, no_x, no_faces) == (len(points), len(points))
    assert visible_counts(points, eye, no_x, no_faces, sphere_center=c, sphere_radius=r) == (
        front.sum(), front.sum())
    # a square over the half x < c_x: exposure = visible front-facing / front-facing
    x, faces = square(0.05, 0.02, x_range=(-0.05, c[0]))
    hidden = numpy_hidden(points, eye, x, faces)
    expected = (front & ~hidden).sum() / front.sum()
    for method in METHODS:
        vis, cnt = visible_counts(points, eye, x, faces, sphere_center=c, method=method)
        assert (vis, cnt) == ((front & ~hidden).sum(), front.sum())
    assert visible_fraction(points, eye, x, faces, sphere_center=c, sphere_radius=r) == \
        pytest.approx(expected, abs=1e-15)
    assert 0.3 < expected < 0.7
    with pytest.raises(ValueError):  # the eye inside the tumour: nothing faces it
        visible_fraction(points, c, x, faces, sphere_center=c, sphere_radius=r)
    with pytest.raises(ValueError):
        visible_fraction(points, eye, x, faces, sphere_radius=r)


def test_batch_equals_single_calls():
    rng = np.random.default_rng(7)
    points0, x0, faces = random_scene(rng)
    n_worlds = 5
    points = points0 + rng.normal(0, 0.004, size=(n_worlds, 1, 3))
    x = x0 + rng.normal(0, 0.003, size=(n_worlds,) + x0.shape)
    eye = np.array([0.02, 0.0, 0.25])
    out = visible_fraction_batch(points, eye, x, faces)
    assert out.shape == (n_worlds,)
    ref = [visible_fraction(points[s], eye, x[s], faces) for s in range(n_worlds)]
    np.testing.assert_array_equal(out, ref)
    assert len(set(ref)) > 1  # the scenes do differ
    centers = points.mean(axis=1)
    out = visible_fraction_batch(points, eye, x, faces, sphere_center=centers, sphere_radius=0.01)
    ref = [visible_fraction(points[s], eye, x[s], faces, sphere_center=centers[s])
           for s in range(n_worlds)]
    np.testing.assert_array_equal(out, ref)


# ----------------------------------------------------------------------------- rasteriser

W, H, FOV = 40, 30, 60.0
RED = np.array([255, 0, 0], np.uint8)
BLUE = np.array([0, 0, 255], np.uint8)
BG = np.array([10, 20, 30], np.uint8)


def top_down_camera(height=1.0):
    return Camera.looking_at((0.0, 0.0, height), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_y=FOV)


def pixel_centres_on_ground(height=1.0):
    """World (X, Y) where each pixel centre's ray meets z = 0, for the top-down camera.

    Independent pinhole model: image right = world +x, image up = world +y,
    f = (H / 2) / tan(fov / 2) pixels, principal point at the image centre.
    """
    f = 0.5 * H / math.tan(math.radians(FOV / 2))
    u = np.arange(W) + 0.5
    v = np.arange(H) + 0.5
    X = (u[None, :] - W / 2) / f * height
    Y = -(v[:, None] - H / 2) / f * height
    return np.broadcast_to(X, (H, W)), np.broadcast_to(Y, (H, W))


def inside_triangle_2d(X, Y, a, b, c):
    """Barycentric point-in-triangle test in the plane (closed triangle)."""
    det = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])
    l1 = ((X - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (Y - a[1])) / det
    l2 = ((b[0] - a[0]) * (Y - a[1]) - (X - a[0]) * (b[1] - a[1])) / det
    return (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)


def dilate(mask):
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= mask[:, :-1]
    out[:, :-1] |= mask[:, 1:]
    return out


def test_look_at_top_down_axes():
    R = look_at((0, 0, 1), (0, 0, 0), (0, 1, 0))
    np.testing.assert_allclose(R, [[1, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        look_at((0, 0, 1), (0, 0, 0), (0, 0, 1))


def test_red_triangle_left_half_matches_point_in_triangle():
    a, b, c = np.array([-0.9, -0.7, 0.0]), np.array([0.02, -0.6, 0.0]), np.array([-0.15, 0.8, 0.0])
    img, depth = rasterize(np.array([[a, b, c]]), RED, top_down_camera(), W, H, background=BG,
                           return_depth=True)
    assert img.dtype == np.uint8 and img.shape == (H, W, 3)
    X, Y = pixel_centres_on_ground()
    expected = inside_triangle_2d(X, Y, a, b, c)
    assert 0.3 < expected.mean() < 0.6 and expected[:, : W // 2].mean() > 2 * expected[:, W // 2:].mean()
    drawn = np.any(img != BG, axis=2)
    # every drawn pixel is red-only, every other is the background
    assert np.all(img[drawn][:, 1:] == 0) and np.all(img[drawn][:, 0] > 0)
    assert np.all(img[~drawn] == BG)
    # same set as the independent test, up to a one-pixel border
    assert np.all(drawn <= dilate(expected))
    assert np.all(expected <= dilate(drawn))
    assert (drawn != expected).sum() <= 0.05 * expected.sum()
    # the plane z = 0 is 1 m in front of a camera at height 1 looking straight down
    np.testing.assert_allclose(depth[drawn], 1.0, rtol=1e-12)
    assert np.all(np.isinf(depth[~drawn]))
    # (x, faces) input gives the same picture
    img2 = rasterize((np.array([a, b, c]), np.array([[0, 1, 2]])), RED, top_down_camera(), W, H,
                     background=BG)
    np.testing.assert_array_equal(img, img2)


@pytest.mark.parametrize("order", ["red_first", "blue_first"])
def test_z_buffer_nearer_blue_wins(order):
    red = [[-4.0, -2.0, 0.0], [4.0, -2.0, 0.0], [0.0, 4.0, 0.0]]      # covers the whole view
    blue = [[-0.2, -0.2, 0.3], [0.2, -0.2, 0.3], [0.0, 0.2, 0.3]]     # 0.3 m nearer the camera
    tris = np.array([red, blue] if order == "red_first" else [blue, red])
    cols = np.array([RED, BLUE] if order == "red_first" else [BLUE, RED])
    img = rasterize(tris, cols, top_down_camera(), W, H, background=BG, ambient=1.0)
    np.testing.assert_array_equal(img[H // 2, W // 2], BLUE)
    np.testing.assert_array_equal(img[1, 1], RED)
    blue_px = np.all(img == BLUE, axis=2)
    red_px = np.all(img == RED, axis=2)
    assert np.all(blue_px | red_px)
    assert 0 < blue_px.sum() < red_px.sum()


def test_triangles_behind_or_through_the_camera_are_not_drawn():
    cam = top_down_camera()
    behind = np.array([[[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0]]])
    img = rasterize(behind, (1.0, 0.0, 0.0), cam, W, H, background=BG)
    assert np.all(img == BG)
    crossing = np.array([[[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 2.0]]])
    assert np.all(rasterize(crossing, (1.0, 0.0, 0.0), cam, W, H, background=BG) == BG)
    assert np.all(rasterize(np.zeros((0, 3, 3)), RED, cam, W, H, background=BG) == BG)


def test_headlight_shading():
    cam = top_down_camera()
    flat = np.array([[[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [0.0, 2.0, 0.0]]])
    # square to the optical axis: full colour everywhere; tilted 60 degrees: 0.2 + 0.8 cos 60
    img = rasterize(flat, (1.0, 1.0, 1.0), cam, W, H, ambient=0.2)
    assert np.all(img[H // 2] == 255)
    k = math.tan(math.radians(60.0))  # a plane through the origin tilted 60 degrees about x
    tilt = np.array([[[-2.0, -0.5, -0.5 * k], [2.0, -0.5, -0.5 * k], [0.0, 0.5, 0.5 * k]]])
    img = rasterize(tilt, (1.0, 1.0, 1.0), cam, W, H, ambient=0.2)
    assert img[H // 2, W // 2, 0] == round(0.6 * 255)
    img = rasterize(tilt, (0, 255, 0), cam, W, H, ambient=1.0)  # no lighting
    np.testing.assert_array_equal(img[H // 2, W // 2], [0, 255, 0])


def test_primitives_and_compose():
    def divergence_volume(v, f):
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        return np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0

    for s in range(3):
        v, f = icosphere(0.02, (0.1, 0.0, -0.1), s)
        assert f.shape == (20 * 4**s, 3)
        np.testing.assert_allclose(np.linalg.norm(v - [0.1, 0.0, -0.1], axis=1), 0.02, rtol=1e-12)
        vol = divergence_volume(v - [0.1, 0.0, -0.1], f)  # > 0: outward orientation
        assert 0.6 * (4 / 3) * math.pi * 0.02**3 < vol < (4 / 3) * math.pi * 0.02**3
    v, f = box((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
    assert v.shape == (8, 3) and f.shape == (12, 3)
    assert divergence_volume(v, f) == pytest.approx(8 * 0.1 * 0.2 * 0.3)
    rot = look_at((0, 0, 0), (1, 1, 0), (0, 0, 1)).T
    v, f = box((0.0, 0.0, 0.0), (0.1, 0.2, 0.3), rotation=rot)
    assert divergence_volume(v, f) == pytest.approx(8 * 0.1 * 0.2 * 0.3)

    sv, sf = icosphere(0.01, (0, 0, 0), 1)
    bv, bf = box((0, 0, 0.05), (0.01, 0.01, 0.01))
    x, faces, cols = compose([(sv, sf, (200, 40, 40)), (bv, bf, np.full((12, 3), 0.5))])
    assert x.shape == (len(sv) + 8, 3) and faces.shape == (len(sf) + 12, 3) and cols.dtype == np.uint8
    np.testing.assert_array_equal(x[faces[len(sf):]], bv[bf])
    np.testing.assert_array_equal(cols[0], [200, 40, 40])
    np.testing.assert_array_equal(cols[-1], [128, 128, 128])
    img = rasterize((x, faces), cols, Camera.looking_at((0, -0.1, 0.2), (0, 0, 0), up=(0, 1, 0)),
                    W, H)
    assert img.shape == (H, W, 3) and img.any()
