"""The mass-tensor StVK force field equals HEML-StVK and textbook FEM to rounding."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import heml_gym
from heml_gym import FemForce, HemlForce, MassTensorForce, TetMesh, box_mesh
from heml_gym.materials import NeoHookean, StVenantKirchhoff

SIZE = (0.1, 0.08, 0.06)
MATERIAL = StVenantKirchhoff(E=3000.0, nu=0.45)  # Pa


def regular_box():
    return box_mesh(SIZE, (3, 3, 2))


def perturbed_box(seed=0):
    """Box whose interior vertices are moved by ~15% of the cell size (m)."""
    cells = np.array([4, 4, 3])
    base = box_mesh(SIZE, tuple(cells))
    h = np.asarray(SIZE) / cells
    v = base.vertices.copy()
    interior = np.setdiff1d(np.arange(base.n_vertices), base.surface_vertices)
    rng = np.random.default_rng(1000 + seed)
    v[interior] += 0.15 * h * rng.uniform(-1.0, 1.0, (len(interior), 3))
    return TetMesh(v, base.tets, reorient=True)


MESHES = {"regular": regular_box, "perturbed": perturbed_box}


def affine_deformation(mesh, seed):
    """x = R (A X) + t plus small noise (m), R a random rotation, A = I + 0.3 random."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    A = np.eye(3) + 0.3 * rng.uniform(-1.0, 1.0, (3, 3))
    X = mesh.vertices
    c = X.mean(axis=0)
    t = 0.05 * rng.uniform(-1.0, 1.0, 3)
    x = (X - c) @ A.T @ R.T + c + t
    return x + 2e-3 * rng.standard_normal(X.shape)


def volume_deformation(mesh, jac, seed):
    """Anisotropic stretch/compression with volume ratio ``jac``, rotated, plus noise (m)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.7, 1.3, 3)
    a *= (jac / np.prod(a)) ** (1.0 / 3.0)
    R = Rotation.random(random_state=seed + 50).as_matrix()
    X = mesh.vertices
    c = X.mean(axis=0)
    x = ((X - c) * a) @ R.T + c
    return x + 1e-3 * rng.standard_normal(X.shape)


def assert_same(mt, ref, x):
    f_mt, f_ref = mt.forces(x), ref.forces(x)
    scale = np.abs(f_ref).max()
    assert scale > 0
    assert np.abs(f_mt - f_ref).max() <= 1e-10 * scale
    w_mt, w_ref = mt.energy(x), ref.energy(x)
    assert abs(w_ref) > 0
    assert abs(w_mt - w_ref) <= 1e-10 * abs(w_ref)


@pytest.mark.parametrize("mesh_name", sorted(MESHES))
@pytest.mark.parametrize("seed", range(6))
def test_matches_heml_and_fem_affine(mesh_name, seed):
    mesh = MESHES[mesh_name]()
    mt = MassTensorForce(mesh, MATERIAL)
    x = affine_deformation(mesh, seed)
    assert_same(mt, HemlForce(mesh, MATERIAL), x)
    assert_same(mt, FemForce(mesh, MATERIAL), x)


@pytest.mark.parametrize("mesh_name", sorted(MESHES))
@pytest.mark.parametrize("jac", [0.3, 0.5, 0.8, 1.5, 2.2, 3.0])
def test_matches_heml_and_fem_volume_change(mesh_name, jac):
    mesh = MESHES[mesh_name]()
    mt = MassTensorForce(mesh, MATERIAL)
    x = volume_deformation(mesh, jac, seed=int(10 * jac))
    assert_same(mt, HemlForce(mesh, MATERIAL), x)
    assert_same(mt, FemForce(mesh, MATERIAL), x)


@pytest.mark.parametrize("mesh_name", sorted(MESHES))
@pytest.mark.parametrize("seed", range(2))
def test_forces_are_minus_energy_gradient(mesh_name, seed):
    mesh = MESHES[mesh_name]()
    mt = MassTensorForce(mesh, MATERIAL)
    x = affine_deformation(mesh, seed + 100)
    f = mt.forces(x)
    h = 1e-7  # m
    grad = np.empty_like(x)
    for i in range(mesh.n_vertices):
        for a in range(3):
            xp = x.copy()
            xm = x.copy()
            xp[i, a] += h
            xm[i, a] -= h
            grad[i, a] = (mt.energy(xp) - mt.energy(xm)) / (2.0 * h)
    assert np.abs(f + grad).max() <= 1e-6 * np.abs(f).max()


@pytest.mark.parametrize("mesh_name", sorted(MESHES))
def test_zero_at_rest(mesh_name):
    mesh = MESHES[mesh_name]()
    mt = MassTensorForce(mesh, MATERIAL)
    assert np.all(mt.forces(mesh.vertices) == 0.0)
    assert mt.energy(mesh.vertices) == 0.0


def test_tensor_symmetries_and_memory():
    mesh = perturbed_box()
    mt = MassTensorForce(mesh, MATERIAL)
    m = mesh.n_tets
    K = mt.K.reshape(m, 4, 4, 3, 3)
    C = mt.C.reshape(m, 4, 4, 4, 3)
    D = mt.D.reshape(m, 4, 4, 4, 4)
    tol = 1e-12 * np.abs(K).max()
    assert np.abs(K - K.transpose(0, 2, 1, 4, 3)).max() <= tol  # K_kj = K_jk^T
    assert np.abs(C - C.transpose(0, 2, 1, 3, 4)).max() <= 1e-12 * np.abs(C).max()  # C_jkl = C_kjl
    dtol = 1e-12 * np.abs(D).max()
    assert np.abs(D - D.transpose(0, 2, 1, 3, 4)).max() <= dtol  # j <-> k
    assert np.abs(D - D.transpose(0, 1, 2, 4, 3)).max() <= dtol  # l <-> m
    assert np.abs(D - D.transpose(0, 3, 4, 1, 2)).max() <= dtol  # (j, k) <-> (l, m)
    assert mt.memory_bytes == m * (144 + 192 + 256) * 8


def test_rejects_other_laws():
    mesh = regular_box()
    with pytest.raises(TypeError, match="StVenantKirchhoff"):
        MassTensorForce(mesh, NeoHookean(E=3000.0, nu=0.45))


def test_exported():
    assert heml_gym.MassTensorForce is MassTensorForce
    assert "MassTensorForce" in heml_gym.__all__
