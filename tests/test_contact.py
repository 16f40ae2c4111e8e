"""Rigid supports: signed distances against geometry, and contact in both solvers."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.contact import Supports

SLAB = hg.box_mesh((0.06, 0.03, 0.008), (4, 2, 1), origin=(0.0, 0.0, 0.003))  # 3 mm above z = 0
#: a box whose top face is the plane z = 0, much larger than the slab
BLOCK = hg.box_mesh((0.2, 0.2, 0.05), 2, origin=(-0.07, -0.085, -0.05))
DENSITY, GRAVITY, DAMPING = 950.0, (0.0, 0.0, -9.81), 2.0


def icosphere(radius: float, subdivisions: int):
    """A closed triangle surface approximating a sphere (outward winding)."""
    t = (1 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, dtype=float) / np.linalg.norm(p) for p in v]
    for _ in range(subdivisions):
        cache, new_f = {}, []

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new_f += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = new_f
    return radius * np.array(verts), np.array(f)


def test_plane_distance_and_normal():
    plane = hg.PlaneSupport(normal=(0, 0, 2.0), offset=0.02)  # z >= 0.01
    d, n = plane.signed_distance([[0.3, -1.0, 0.0], [0.0, 0.0, 0.05]])
    np.testing.assert_allclose(d, [-0.01, 0.04])
    np.testing.assert_allclose(n, [[0, 0, 1], [0, 0, 1]])
    with pytest.raises(ValueError, match="normal"):
        hg.PlaneSupport(normal=(0, 0, 0))


def test_mesh_distance_matches_a_sphere():
    """The sampled distance of a triangulated sphere against the sphere's own (the
    error allowed: the polygon's chord error plus the trilinear interpolation's)."""
    radius = 0.05
    v, f = icosphere(radius, 4)
    support = hg.MeshSupport(v, f, spacing=0.002)
    rng = np.random.default_rng(0)
    directions = rng.standard_normal((2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    depth = rng.uniform(-0.006, 0.006, 2000)  # within the band of 8 mm
    points = directions * (radius + depth)[:, None]
    d, n = support.signed_distance(points)
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).max()
    chord = radius - np.sqrt(radius ** 2 - (edge / 2) ** 2 * 4 / 3)  # sagitta over a triangle
    assert np.abs(d - depth).max() < chord + 0.002 ** 2 / (8 * radius) * 4
    assert np.all(np.sign(d[np.abs(depth) > 0.002]) == np.sign(depth[np.abs(depth) > 0.002]))
    cosine = (n * directions).sum(axis=1)
    assert cosine.min() > 0.98  # the normal points out, radially
    # far inside and far outside keep their sign (the band clamps the magnitude)
    d_in, _ = support.signed_distance([[0.0, 0.0, 0.0]])
    d_out, _ = support.signed_distance([[0.0, 0.0, 0.2]])
    assert d_in[0] < 0 and d_out[0] == np.inf


def test_mesh_support_rejects_an_open_surface():
    v, f = icosphere(0.05, 1)
    with pytest.raises(ValueError, match="closed surface"):
        hg.MeshSupport(v, f[:-1])


def drop(support, integrator, n_worlds=1, steps=12, dt=1 / 30, newton_tol=1e-3):
    """Slabs of different E dropped onto ``support``; their positions per step."""
    materials = [M.NeoHookean(E=E, nu=0.45) for E in (3e3, 5e3, 4e3, 6e3)[:n_worlds]]
    model = hg.Model(SLAB, materials, density=DENSITY, gravity=GRAVITY, damping=DAMPING, supports=[support])
    solver = hg.ExplicitSolver(model) if integrator == "explicit" else hg.ImplicitSolver(model, newton_tol=newton_tol)
    state, control = model.state(), model.control()
    kw = {"substeps": 200} if integrator == "explicit" else {}
    xs = []
    for _ in range(steps):
        stats = solver.step(state, state, control, dt, **kw)
        assert not stats.diverged.any()
        xs.append(state.x.copy())
    return np.array(xs), state


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_a_slab_comes_to_rest_on_a_plane(integrator):
    xs, state = drop(hg.PlaneSupport(height=0.0), integrator, steps=20)
    tol = 1e-12 if integrator == "explicit" else 1e-9
    assert xs[:, :, :, 2].min() >= -tol  # never below the plane
    bottom = np.isclose(SLAB.vertices[:, 2], 0.003)
    np.testing.assert_allclose(state.x[0, bottom, 2], 0.0, atol=2e-4)  # it landed and stays
    on_plane = state.x[0, :, 2] <= 1e-12
    assert on_plane.sum() >= 4 and np.all(state.v[0, on_plane, 2] >= -1e-9)  # no velocity into it


@pytest.mark.parametrize("integrator", [pytest.param("explicit", marks=pytest.mark.slow), "implicit"])
def test_a_closed_mesh_support_acts_like_its_flat_top(integrator):
    """On a box's flat top the sampled distance is exact (linear), so a slab dropped on
    the box behaves as on the plane z = 0: to rounding."""
    block = hg.MeshSupport(BLOCK.vertices, BLOCK.boundary_faces)
    n = 4 if integrator == "explicit" else 1  # 4: the kernel vectorised across worlds
    # Newton solved tightly, so that the two runs' rounding differences stay small
    on_mesh, _ = drop(block, integrator, n_worlds=n, newton_tol=1e-11)
    on_plane, _ = drop(hg.PlaneSupport(height=0.0), integrator, n_worlds=n, newton_tol=1e-11)
    assert np.abs(on_mesh - on_plane).max() < 1e-9
    assert np.abs(on_mesh[-1] - SLAB.vertices).max() > 2e-3  # it really fell onto it


@pytest.mark.parametrize("integrator", [pytest.param("explicit", marks=pytest.mark.slow), "implicit"])
def test_a_batch_on_a_mesh_support_equals_single_worlds(integrator):
    """Four slabs of different E on a sphere (curved contact), in one batch, against
    each simulated alone."""
    v, f = icosphere(0.08, 3)
    sphere = hg.MeshSupport(v + [0.03, 0.015, -0.08], f, spacing=0.003)
    batch, _ = drop(sphere, integrator, n_worlds=4, steps=8)
    for s, E in enumerate((3e3, 5e3, 4e3, 6e3)):
        model = hg.Model(SLAB, M.NeoHookean(E=E, nu=0.45), density=DENSITY, gravity=GRAVITY, damping=DAMPING,
                         supports=[sphere])
        sim = hg.Simulation(hg.HemlForce(SLAB, M.NeoHookean(E=E, nu=0.45)), DENSITY, gravity=GRAVITY,
                            damping=DAMPING, integrator=integrator, supports=[sphere])
        assert model.n_worlds == 1
        for k in range(8):
            sim.step(1 / 30, substeps=200 if integrator == "explicit" else None)
            assert np.abs(batch[k, s] - sim.x).max() < 1e-10
        # resting on the sphere: no vertex inside it
        d, _ = Supports([sphere]).signed_distance(sim.x)
        assert d.min() > -1e-4
