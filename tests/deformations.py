"""Test helpers: irregular meshes and random deformations with known J and rotation."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

import heml_gym as hg


def perturbed_box(seed: int = 0, cells=(2, 2, 2), size=(0.1, 0.08, 0.06), amount=0.15) -> hg.TetMesh:
    """A box mesh whose interior vertices are moved by ``amount`` cell sizes: irregular tets."""
    base = hg.box_mesh(size, cells)
    rng = np.random.default_rng(seed)
    v = base.vertices.copy()
    lo, hi = base.bounds()
    interior = np.all((v > lo + 1e-12) & (v < hi - 1e-12), axis=1)
    h = np.asarray(size) / np.asarray(cells)
    v[interior] += amount * h * rng.uniform(-1, 1, (interior.sum(), 3))
    return hg.TetMesh(v, base.tets, reorient=True)


def random_deformation(mesh: hg.TetMesh, seed: int, jacobian: float, noise: float = 0.02) -> np.ndarray:
    """Positions ``R A X + t + noise`` with ``det A = jacobian``, a random rotation ``R``.

    ``A`` is a random stretch-and-shear of determinant ``jacobian``; the noise (relative to
    the mesh size) makes the deformation inhomogeneous while keeping every tet upright.
    """
    rng = np.random.default_rng(seed)
    a = np.eye(3) + 0.25 * rng.uniform(-1, 1, (3, 3))
    a *= (jacobian / np.linalg.det(a)) ** (1.0 / 3.0)
    rot = Rotation.random(random_state=seed).as_matrix()
    scale = np.ptp(mesh.vertices, axis=0).max()
    x = mesh.vertices @ a.T + noise * scale * jacobian ** (1 / 3) * rng.uniform(-1, 1, mesh.vertices.shape)
    return x @ rot.T + rng.uniform(-1, 1, 3) * scale
