"""Stiffness matrices (Hessians of the elastic energy): exactness, symmetry, definiteness."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.forces import hessian as H

from deformations import random_deformation

E, NU = 20e3, 0.42
LAWS = M.ALL_MATERIALS
SIZE = 0.02


def irregular_mesh(seed: int = 4) -> hg.TetMesh:
    """Two cells, 12 tets, every vertex moved: irregular tets (some obtuse)."""
    base = hg.box_mesh((SIZE, SIZE, SIZE), (2, 1, 1))
    rng = np.random.default_rng(seed)
    v = base.vertices + 0.12 * (SIZE / 2) * rng.uniform(-1, 1, base.vertices.shape)
    return hg.TetMesh(v, base.tets, reorient=True)


MESH = irregular_mesh()


def fd_stiffness(field, x, rel_step=1e-6):
    """Minus the central-difference Jacobian of the forces: d2W/dx2 (N/m), dense."""
    h = rel_step * SIZE
    n = x.size
    k = np.empty((n, n))
    for i in range(n):
        xp, xm = x.copy().ravel(), x.copy().ravel()
        xp[i] += h
        xm[i] -= h
        k[:, i] = -(field.forces(xp.reshape(-1, 3)) - field.forces(xm.reshape(-1, 3))).ravel() / (2 * h)
    return k


def eigs(k):
    k = k.toarray() if sp.issparse(k) else k
    return np.linalg.eigvalsh(0.5 * (k + k.T))


def min_relative_eig(k):
    w = eigs(k)
    return w[0] / w[-1]


def jacobians(x):
    return hg.mesh.signed_volumes(x, MESH.tets) / MESH.volumes


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_exact_hessian_equals_minus_force_jacobian(law):
    field = hg.HemlForce(MESH, law(E=E, nu=NU))
    for seed, jac in ((1, 0.6), (2, 1.5)):
        x = random_deformation(MESH, seed=seed, jacobian=jac, noise=0.05)
        j = jacobians(x)
        assert 0.4 <= j.min() and j.max() <= 2.2  # J between about 0.5 and 2
        k = field.hessian(x, project=False)
        assert isinstance(k, sp.csr_matrix) and k.shape == (x.size, x.size)
        kd = k.toarray()
        scale = np.abs(kd).max()
        assert np.abs(kd - fd_stiffness(field, x)).max() <= 1e-6 * scale
        assert np.abs(kd - kd.T).max() <= 1e-13 * scale


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_rest_hessian_is_psd_with_six_rigid_modes(law):
    field = hg.HemlForce(MESH, law(E=E, nu=NU))
    k = field.hessian(MESH.vertices, project=False)
    w = eigs(k)
    assert w[0] >= -1e-10 * w[-1]
    assert np.sum(np.abs(w) <= 1e-9 * w[-1]) == 6
    assert w[6] > 1e-6 * w[-1]
    # nothing to fix at rest: the projected Hessian is the exact one
    for method in ("analytic", "eigh"):
        kp = H.heml_hessian(field, MESH.vertices, project=True, method=method)
        assert np.abs((kp - k).toarray()).max() <= 1e-12 * np.abs(k.toarray()).max()


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_analytic_f_eigensystem_reconstructs_element_hessians(law):
    """K_T = V0 sum_m lam_m b_m b_m^T: the closed-form eigenvalues and modes are exact."""
    field = hg.HemlForce(MESH, law(E=E, nu=NU))
    for jac in (0.3, 1.0, 1.8):
        x = random_deformation(MESH, seed=5, jacobian=jac, noise=0.05)
        ke = H.heml_element_hessians(field, x, project=False)
        lam, b = H.heml_f_eigensystems(field, x)
        rebuilt = np.einsum("t,tm,tmr,tmc->trc", field.coef[:, 0], lam, b, b)
        assert np.abs(rebuilt - ke).max() <= 1e-12 * np.abs(ke).max()
        # b_m = B^T q_m with B = dF/dx (9 x 12) and q_m orthonormal F-space modes, so the
        # lam are the eigenvalues of d2Psi/dF2
        for t in range(MESH.n_tets):
            dmi = MESH.rest_edge_inverses[t]
            w = np.vstack([-dmi.sum(axis=0), dmi])  # dF[:, c] / dx_a = w[a, c]
            bt = np.einsum("ac,rs->asrc", w, np.eye(3)).reshape(12, 9)  # B^T, F row-major
            q = np.linalg.lstsq(bt, b[t].T, rcond=None)[0]
            assert np.abs(bt @ q - b[t].T).max() <= 1e-12 * np.abs(b[t]).max()
            assert np.abs(q.T @ q - np.eye(9)).max() <= 1e-10


@pytest.mark.parametrize("method", ["analytic", "eigh"])
@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_projected_hessian_is_psd_and_exact_where_already_psd(law, method):
    field = hg.HemlForce(MESH, law(E=E, nu=NU))
    for seed, jac in ((3, 0.3), (4, 1.0), (6, 2.0)):
        x = random_deformation(MESH, seed=seed, jacobian=jac, noise=0.05)
        assert jacobians(x).min() > 0.5 * jac
        exact = H.heml_element_hessians(field, x, project=False)
        fixed = H.heml_element_hessians(field, x, project=True, method=method)
        scale = np.abs(exact).max()
        for ke, kf in zip(exact, fixed):
            w = eigs(kf)
            assert w[0] >= -1e-10 * w[-1]
            assert np.abs(kf - kf.T).max() <= 1e-12 * scale
            if eigs(ke)[0] >= -1e-12 * w[-1]:  # already PSD: left as it was
                assert np.abs(kf - ke).max() <= 1e-10 * scale
        k = H.heml_hessian(field, x, project=True, method=method)
        assert min_relative_eig(k) >= -1e-10
        # the assembled matrix is the sum of the element matrices
        k_exact = field.hessian(x, project=False)
        k_sum = np.zeros(k.shape)
        for t, tet in enumerate(MESH.tets):
            dof = (3 * tet[:, None] + np.arange(3)).ravel()
            k_sum[np.ix_(dof, dof)] += fixed[t]
        assert np.abs(k.toarray() - k_sum).max() <= 1e-12 * scale
        if jac == 0.3 and law in (M.NeoHookean, M.StVenantKirchhoff):
            # strongly compressed: the exact Hessian is indefinite, so the fix did work
            assert min_relative_eig(k_exact) < -1e-3


def test_default_projection_is_analytic_and_counts_clamped_modes():
    field = hg.HemlForce(MESH, M.NeoHookean(E=E, nu=NU))
    x = random_deformation(MESH, seed=3, jacobian=0.3, noise=0.05)
    k = field.hessian(x)
    assert np.abs((k - H.heml_hessian(field, x, True, "analytic")).toarray()).max() == 0.0
    assert field.n_clamped > 0
    with pytest.raises(ValueError, match="method"):
        H.heml_hessian(field, x, True, "svd")


def test_sparsity_pattern_is_the_edge_graph():
    field = hg.HemlForce(MESH, M.NeoHookean(E=E, nu=NU))
    k = field.hessian(MESH.vertices)
    n, n_edges = MESH.n_vertices, len(MESH.edges)
    assert k.nnz == 9 * (n + 2 * n_edges)
    assert k.has_canonical_format
    blocks = {(int(i) // 3, int(j) // 3) for i, j in zip(*k.nonzero())}
    expected = {(i, i) for i in range(n)}
    expected |= {(int(a), int(b)) for a, b in MESH.edges} | {(int(b), int(a)) for a, b in MESH.edges}
    assert blocks <= expected
    pattern = H.hessian_pattern(field)
    assert pattern.indices.dtype == pattern.indptr.dtype
    far = next((i, j) for i in range(n) for j in range(n) if (i, j) not in expected)
    with pytest.raises(KeyError):
        pattern.block_start([far[0]], [far[1]])


def test_undefined_law_gives_nan_and_stable_neo_hookean_stays_finite():
    mesh = hg.box_mesh((0.01, 0.01, 0.01), 1)
    x = mesh.vertices * np.array([1.0, 1.0, -0.5])  # every tet inverted
    for project in (False, True):
        k = hg.HemlForce(mesh, M.NeoHookean(E=E, nu=NU)).hessian(x, project=project)
        assert np.isnan(k.data).any()
        k = hg.HemlForce(mesh, M.StableNeoHookean(E=E, nu=NU)).hessian(x, project=project)
        assert np.all(np.isfinite(k.data))
        if project:
            assert min_relative_eig(k) >= -1e-10


# ---------------------------------------------------------------------------- mass-spring
def test_mass_spring_hessian():
    field = hg.MassSpringForce(MESH, M.NeoHookean(E=E, nu=NU))
    x = random_deformation(MESH, seed=8, jacobian=0.7, noise=0.05)
    k = field.hessian(x, project=False)
    kd = k.toarray()
    scale = np.abs(kd).max()
    assert np.abs(kd - fd_stiffness(field, x)).max() <= 1e-6 * scale
    assert np.abs(kd - kd.T).max() <= 1e-13 * scale
    # compressed springs make the exact Hessian indefinite; the projection fixes that
    x = MESH.vertices * 0.5
    assert min_relative_eig(field.hessian(x, project=False)) < -1e-3
    assert min_relative_eig(field.hessian(x, project=True)) >= -1e-10
    # stretched springs: nothing to clamp
    x = MESH.vertices * 1.3
    diff = (field.hessian(x, project=True) - field.hessian(x, project=False)).toarray()
    assert np.abs(diff).max() == 0.0
    # at rest: PSD with the 6 rigid modes (and possibly more: springs only)
    w = eigs(field.hessian(MESH.vertices))
    assert w[0] >= -1e-10 * w[-1] and np.sum(np.abs(w) <= 1e-9 * w[-1]) >= 6


def test_data_api_and_diagonal_positions():
    field = hg.HemlForce(MESH, M.MooneyRivlin(E=E, nu=NU))
    x = random_deformation(MESH, seed=9, jacobian=1.2, noise=0.05)
    pattern = H.hessian_pattern(field)
    data = pattern.zeros() + 1.0
    H.heml_hessian_data(field, x, project=True, out=data)  # overwritten, not added to
    k = field.hessian(x)
    assert np.array_equal(data, k.data)
    assert np.array_equal(data[pattern.diagonal], k.diagonal())
    spring = hg.MassSpringForce(MESH, M.NeoHookean(E=E, nu=NU))
    ks = spring.hessian(x)
    assert np.array_equal(ks.data[H.hessian_pattern(spring).diagonal], ks.diagonal())


def test_neo_hookean_split_hessian_equals_the_general_kernel():
    """The exact Neo-Hookean Hessian (fixed springs + volume term) is assembled by its own
    kernel; it must equal the general edge-form kernel's, entry by entry."""
    from heml_gym.forces import kernels_hessian as kh

    field = hg.HemlForce(MESH, M.NeoHookean(E=E, nu=NU))
    assert field.split
    pattern = H.hessian_pattern(field)
    blk = pattern.element_blocks(MESH.tets)
    for seed, jac in ((0, 0.5), (1, 1.0), (2, 2.5)):
        x = random_deformation(MESH, seed, jac)
        general = pattern.zeros()
        kh.heml_hessian_kernel(x, MESH.tets, field.coef, field.q, field.use_q, field.law_id, field.params,
                               MESH.rest_edge_inverses, kh.NO_PROJECTION, blk, pattern.row_stride, general,
                               np.zeros((0, 12, 12)))
        split = field.hessian(x, project=False).data
        assert np.abs(split - general).max() <= 1e-12 * np.abs(general).max()
