"""Free-dof submatrices and the lagged-factor PCG against direct computation."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.linear_solvers import FreeSubmatrix, LaggedFactorPCG, pcg


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


def test_pcg_and_lagged_factor_solve_to_tolerance():
    a0, a1 = stiffness(1.0), stiffness(3.0)
    b = np.random.default_rng(1).standard_normal(a0.shape[0])
    exact = spla.spsolve(a1.tocsc(), b)
    lu = spla.splu(a0.tocsc())
    x, iterations, converged = pcg(a1, b, lu.solve, 1e-10, 100)
    assert converged and 0 < iterations < 100
    assert np.linalg.norm(a1 @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert np.abs(x - exact).max() <= 1e-8 * np.abs(exact).max()

    solver = LaggedFactorPCG(rtol=1e-10, max_iter=50)
    solver.solve(a0, b, key="k")
    assert solver.factorizations == 1
    x = solver.solve(a1, b, key="k")  # reuses the old factorisation
    assert solver.factorizations == 1 and solver.last_iterations > 0
    assert np.abs(x - exact).max() <= 1e-8 * np.abs(exact).max()
    solver.solve(a1, b, key="other")  # a new key refactorises
    assert solver.factorizations == 2
    tight = LaggedFactorPCG(rtol=1e-14, max_iter=1)
    tight.solve(a0, b)
    x = tight.solve(a1, b)  # CG cannot converge in 1 iteration: falls back to a fresh factor
    assert tight.factorizations == 2
    assert np.abs(x - exact).max() <= 1e-8 * np.abs(exact).max()
