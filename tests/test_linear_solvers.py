"""Free-dof submatrices and the lagged-factor PCG against direct computation."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import heml_gym as hg
from heml_gym import materials as M
import pytest

from heml_gym.linear_solvers import (DiagonalAdd, EnvelopeCholesky, FreeSubmatrix, LaggedFactorPCG,
                                    NotPositiveDefinite, pcg)


def stiffness(scale=1.0):
    mesh = hg.box_mesh((0.03, 0.02, 0.02), (3, 2, 2))
    field = hg.HemlForce(mesh, M.NeoHookean(E=10e3, nu=0.4))
    x = mesh.vertices * np.array([1.0 + 0.1 * scale, 1.0, 1.0 - 0.05 * scale])
    mass = np.repeat(1000.0 * mesh.vertex_volumes, 3)
    return (field.hessian(x) + sp.diags(mass / (1 / 30) ** 2)).tocsr()


def test_free_submatrix_equals_fancy_indexing():
    a = stiffness()
    rng = np.random.default_rng(0)
    free = rng.random(a.shape[0]) > 0.3
    sub = FreeSubmatrix()
    for scale in (1.0, 2.0):  # second call reuses the analysis with new values
        a = stiffness(scale)
        expected = a[free][:, free].toarray()
        np.testing.assert_array_equal(sub(a, free).toarray(), expected)
    free2 = ~free
    np.testing.assert_array_equal(sub(a, free2).toarray(), a[free2][:, free2].toarray())


@pytest.mark.parametrize("factorization", ["cholesky", "lu"])
def test_pcg_and_lagged_factor_solve_to_tolerance(factorization):
    a0, a1 = stiffness(1.0), stiffness(3.0)
    b = np.random.default_rng(1).standard_normal(a0.shape[0])
    exact = spla.spsolve(a1.tocsc(), b)
    lu = spla.splu(a0.tocsc())
    x, iterations, converged = pcg(a1, b, lu.solve, 1e-10, 100)
    assert converged and 0 < iterations < 100
    assert np.linalg.norm(a1 @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert np.abs(x - exact).max() <= 1e-8 * np.abs(exact).max()

    solver = LaggedFactorPCG(rtol=1e-10, max_iter=50, factorization=factorization)
    solver.solve(a0, b, key="k")
    assert solver.factorizations == 1
    x = solver.solve(a1, b, key="k")  # reuses the old factorisation
    assert solver.factorizations == 1 and solver.last_iterations > 0
    assert np.abs(x - exact).max() <= 1e-8 * np.abs(exact).max()
    solver.solve(a1, b, key="other")  # a new key refactorises
    assert solver.factorizations == 2
    tight = LaggedFactorPCG(rtol=1e-14, max_iter=1, factorization=factorization)
    tight.solve(a0, b)
    x = tight.solve(a1, b)  # CG cannot converge in 1 iteration: falls back to a fresh factor
    assert tight.factorizations == 2
    assert np.abs(x - exact).max() <= 1e-8 * np.abs(exact).max()


def test_envelope_cholesky_solves_and_reuses_its_analysis():
    a0, a1 = stiffness(1.0), stiffness(3.0)
    b = np.random.default_rng(2).standard_normal(a0.shape[0])
    chol = EnvelopeCholesky(a0)
    np.testing.assert_allclose(chol.solve(b), spla.spsolve(a0.tocsc(), b), rtol=1e-10, atol=0)
    first = chol._first
    chol.factor(a1)  # same pattern: new values, same analysis
    assert chol._first is first
    b_before = np.array(b)  # (a copy taken before the solve)
    x = chol.solve(b)
    assert np.linalg.norm(a1 @ x - b) <= 1e-12 * np.linalg.norm(b)
    np.testing.assert_array_equal(b, b_before)  # solve leaves b alone


def test_envelope_cholesky_orders_to_a_small_envelope():
    a = stiffness()
    n = a.shape[0]
    shuffle = np.random.default_rng(3).permutation(n)
    scrambled = a[shuffle][:, shuffle].tocsr()
    natural_envelope = int(np.sum(np.arange(n) - np.minimum.reduceat(
        np.minimum(scrambled.indices, np.repeat(np.arange(n), np.diff(scrambled.indptr))),
        scrambled.indptr[:-1]) + 1))
    chol = EnvelopeCholesky(scrambled)
    assert chol.envelope_size < 0.6 * natural_envelope  # reverse Cuthill-McKee was taken
    b = np.random.default_rng(4).standard_normal(n)
    x = chol.solve(b)
    assert np.linalg.norm(scrambled @ x - b) <= 1e-12 * np.linalg.norm(b)


def test_envelope_cholesky_rejects_indefinite_matrices():
    a = stiffness()
    indefinite = (a - sp.diags(np.full(a.shape[0], 2.0 * a.diagonal().max()))).tocsr()
    with pytest.raises(NotPositiveDefinite, match="pivot"):
        EnvelopeCholesky(indefinite)
    solver = LaggedFactorPCG(factorization="cholesky")
    assert np.all(np.isnan(solver.solve(indefinite, np.ones(a.shape[0]))))  # Newton then projects
    assert solver.factorizations == 0
    # a positive definite factor kept, then an indefinite system: CG meets negative
    # curvature, the refactorisation fails, the answer is NaN again (not a wrong solve)
    solver.solve(a, np.ones(a.shape[0]), key="k")
    assert solver.factorizations == 1
    assert np.all(np.isnan(solver.solve(indefinite, np.ones(a.shape[0]), key="k")))
    with pytest.raises(ValueError, match="factorization"):
        LaggedFactorPCG(factorization="qr")


def test_diagonal_add_matches_sparse_sum():
    add = DiagonalAdd()
    values = np.random.default_rng(5).random(stiffness().shape[0])
    for scale in (1.0, 2.0):
        a = stiffness(scale)
        expected = (a + sp.diags(values)).toarray()
        np.testing.assert_array_equal(add(a.copy(), values).toarray(), expected)
    no_diagonal = sp.csr_matrix(np.array([[0.0, 1.0], [1.0, 0.0]]))
    np.testing.assert_array_equal(add(no_diagonal, np.array([2.0, 3.0])).toarray(), [[2.0, 1.0], [1.0, 3.0]])
