"""10-node quadratic tets: derivatives, patch tests, lumping and bending against beam theory."""

from math import factorial

import numpy as np
import pytest

import heml_gym as hg
from heml_gym.benchmarks.accuracy.speed_accuracy import newton_equilibrium
from heml_gym.forces.quadratic import QUADRATURE_POINTS, QuadraticFemForce, QuadraticTetMesh
from heml_gym.materials import ALL_MATERIALS, NeoHookean
from heml_gym.mesh import EDGE_PAIRS


def small_mesh():
    return QuadraticTetMesh.from_linear(hg.box_mesh((0.03, 0.02, 0.01), (2, 1, 1), mirrored=True))


def psi(material, F):
    """Psi(F) (Pa) from the linear FEM field on one tet deformed affinely by F."""
    tet = hg.TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float), np.array([[0, 1, 2, 3]]))
    return hg.FemForce(tet, material).energy(tet.vertices @ F.T) / tet.total_volume


def test_mesh_nodes_are_edge_middles_shared_between_elements():
    mesh = small_mesh()
    lin = mesh.linear
    assert mesh.n_vertices == lin.n_vertices + len(lin.edges)
    assert np.array_equal(mesh.elements[:, :4], lin.tets)
    for k, (i, j) in enumerate(EDGE_PAIRS):
        mid = 0.5 * (lin.vertices[lin.tets[:, i]] + lin.vertices[lin.tets[:, j]])
        assert np.allclose(mesh.vertices[mesh.elements[:, 4 + k]], mid)
    # each edge node is one node however many elements share the edge
    assert len(np.unique(mesh.elements[:, 4:])) == len(lin.edges)


def test_the_linear_view_splits_every_element_into_8_positive_tets():
    """On an unstructured mesh: each element's 8 tets are positively oriented, fill it
    (volumes sum to its volume) and cut its inner octahedron along the shortest diagonal."""
    from heml_gym.forces.quadratic import OCTAHEDRON_DIAGONALS
    from heml_gym.mesh import signed_volumes

    lin = hg.organs.irregular_cube_mesh()
    mesh = QuadraticTetMesh.from_linear(lin)
    sub = signed_volumes(mesh.vertices, mesh.tets).reshape(-1, 8)
    assert np.all(sub > 0)
    assert np.allclose(sub.sum(axis=1), lin.volumes, rtol=1e-12)
    inner = mesh.tets.reshape(-1, 8, 4)[:, 4:]  # the octahedron's 4 tets share its diagonal
    for element, tets in zip(mesh.elements, inner):
        a, b = np.intersect1d(np.intersect1d(tets[0], tets[1]), np.intersect1d(tets[2], tets[3]))
        length = np.linalg.norm(mesh.vertices[a] - mesh.vertices[b])
        candidates = mesh.vertices[element[OCTAHEDRON_DIAGONALS]]  # (3, 2, 3)
        assert length <= np.linalg.norm(candidates[:, 1] - candidates[:, 0], axis=1).min() * (1 + 1e-12)


@pytest.mark.parametrize("law", ALL_MATERIALS, ids=lambda c: c.__name__)
def test_forces_and_hessian_are_the_energy_derivatives(law):
    mesh = small_mesh()
    field = QuadraticFemForce(mesh, law(E=5e3, nu=0.4))
    rng = np.random.default_rng(3)
    for _ in range(3):
        x = mesh.vertices + rng.normal(scale=1e-3, size=mesh.vertices.shape)
        d = rng.normal(size=x.shape)
        h = 1e-7
        slope = (field.energy(x + h * d) - field.energy(x - h * d)) / (2 * h)
        assert -np.sum(field.forces(x) * d) == pytest.approx(slope, rel=1e-5)
        dforce = (field.forces(x + h * d) - field.forces(x - h * d)).ravel() / (2 * h)
        hd = field.hessian(x, project=False) @ d.ravel()
        assert np.abs(hd + dforce).max() <= 1e-5 * np.abs(dforce).max()


@pytest.mark.parametrize("law", ALL_MATERIALS, ids=lambda c: c.__name__)
def test_affine_deformation_energy_exact_and_interior_nodes_unloaded(law):
    mesh = QuadraticTetMesh.from_linear(hg.box_mesh((0.03, 0.03, 0.03), 3, mirrored=True))
    material = law(E=5e3, nu=0.4)
    A = np.array([[1.1, 0.05, -0.02], [0.03, 0.95, 0.04], [-0.01, 0.02, 1.05]])
    x = mesh.vertices @ A.T + np.array([0.01, -0.02, 0.03])
    field = QuadraticFemForce(mesh, material)
    assert field.energy(x) == pytest.approx(mesh.linear.total_volume * psi(material, A), rel=1e-10)
    f = field.forces(x)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    interior = np.all((mesh.vertices > lo + 1e-9) & (mesh.vertices < hi - 1e-9), axis=1)
    assert interior.sum() > 0
    scale = np.abs(f).max()
    assert np.abs(f[interior]).max() <= 1e-9 * scale
    assert np.abs(f.sum(axis=0)).max() <= 1e-9 * scale


@pytest.mark.parametrize("law", ALL_MATERIALS, ids=lambda c: c.__name__)
def test_rigid_motion_has_no_energy_and_no_forces(law):
    mesh = small_mesh()
    field = QuadraticFemForce(mesh, law(E=5e3, nu=0.4))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    x = mesh.vertices @ R.T + 0.05
    assert abs(field.energy(x)) <= 1e-12 * 5e3 * mesh.linear.total_volume
    assert np.abs(field.forces(x)).max() <= 1e-9 * 5e3 * 0.01 ** 2


def test_quadratic_displacement_reproduced_at_the_quadrature_points():
    """Nodes placed on a quadratic map: the element's deformation gradient is the map's
    exact gradient, so the energy is the quadrature of Psi(grad phi) (independently)."""
    mesh = small_mesh()
    material = NeoHookean(E=5e3, nu=0.4)
    Q = np.array([[[0.0, 2.0, 1.0], [2.0, -1.0, 0.0], [1.0, 0.0, 3.0]],
                  [[1.0, 0.0, -2.0], [0.0, 2.0, 1.0], [-2.0, 1.0, 0.0]],
                  [[-1.0, 1.0, 0.0], [1.0, 0.0, 2.0], [0.0, 2.0, 1.0]]])  # phi_i = X_i + X.Q_i.X

    def phi(X):
        return X + np.einsum("nj,ijk,nk->ni", X, Q, X)

    def grad_phi(X):
        return np.eye(3) + 2.0 * np.einsum("ijk,k->ij", Q, X)

    field = QuadraticFemForce(mesh, material)
    expected = 0.0
    corners = mesh.linear.vertices[mesh.linear.tets]  # (m, 4, 3)
    for t, vol in enumerate(mesh.linear.volumes):
        for bary in QUADRATURE_POINTS:
            expected += vol / 4.0 * psi(material, grad_phi(bary @ corners[t]))
    assert field.energy(phi(mesh.vertices)) == pytest.approx(expected, rel=1e-10)


def integral_of_monomial(powers, volume):
    """Exact int over a tet of prod L_i^a_i: 6 V prod a_i! / (sum a + 3)!."""
    return 6.0 * volume * np.prod([factorial(a) for a in powers]) / factorial(sum(powers) + 3)


def test_lumped_masses_follow_the_consistent_diagonal_and_loads_the_shape_integrals():
    mesh = small_mesh()
    V = mesh.linear.total_volume
    assert np.all(mesh.vertex_volumes > 0)
    assert mesh.vertex_volumes.sum() == pytest.approx(V, rel=1e-12)
    assert mesh.load_volumes.sum() == pytest.approx(V, rel=1e-12)
    # one element: consistent-mass diagonal int N_a^2 and load int N_a, by exact monomial integration
    one = QuadraticTetMesh.from_linear(hg.TetMesh(np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 3.0]]), np.array([[0, 1, 2, 3]])))
    v = one.linear.total_volume
    corner_sq = 4 * integral_of_monomial([4, 0, 0, 0], v) - 4 * integral_of_monomial([3, 0, 0, 0], v) \
        + integral_of_monomial([2, 0, 0, 0], v)  # (2L^2 - L)^2
    edge_sq = 16 * integral_of_monomial([2, 2, 0, 0], v)
    total = 4 * corner_sq + 6 * edge_sq
    assert one.vertex_volumes[:4] == pytest.approx(np.full(4, v * corner_sq / total), rel=1e-12)
    assert one.vertex_volumes[4:] == pytest.approx(np.full(6, v * edge_sq / total), rel=1e-12)
    corner_load = 2 * integral_of_monomial([2, 0, 0, 0], v) - integral_of_monomial([1, 0, 0, 0], v)
    edge_load = 4 * integral_of_monomial([1, 1, 0, 0], v)
    assert one.load_volumes[:4] == pytest.approx(np.full(4, corner_load), rel=1e-12)
    assert one.load_volumes[4:] == pytest.approx(np.full(6, edge_load), rel=1e-12)


def test_projected_hessian_is_positive_semidefinite_and_exact_at_rest():
    mesh = small_mesh()
    field = QuadraticFemForce(mesh, NeoHookean(E=5e3, nu=0.45))
    rng = np.random.default_rng(5)
    rest = mesh.vertices + 0.01  # moved, not deformed: the tangent is positive semi-definite
    exact, projected = field.hessian(rest, project=False), field.hessian(rest, project=True)
    assert abs(exact - projected).max() <= 1e-9 * abs(exact).max()
    squeezed = mesh.vertices * np.array([1.0, 1.0, 0.3]) + rng.normal(scale=2e-4, size=mesh.vertices.shape)
    lam_exact = np.linalg.eigvalsh(field.hessian(squeezed, project=False).toarray())
    lam = np.linalg.eigvalsh(field.hessian(squeezed, project=True).toarray())
    assert lam_exact.min() < -1e-6 * lam_exact.max()  # the state is one where projecting matters
    assert lam.min() >= -1e-9 * lam.max()


def cantilever_tip_deflection(n, quadratic):
    """Tip deflection (m) of a 100 x 10 x 10 mm steel-stiff cantilever under its weight."""
    length, side, E, nu, rho, g = 0.1, 0.01, 1e7, 0.3, 1000.0, 9.81
    lin = hg.box_mesh((length, side, side), (n, max(n // 10, 1), max(n // 10, 1)))
    if quadratic:
        mesh = QuadraticTetMesh.from_linear(lin)
        field, rest, weights = QuadraticFemForce(mesh, NeoHookean(E=E, nu=nu)), mesh.vertices, mesh.load_volumes
    else:
        field, rest, weights = hg.FemForce(lin, NeoHookean(E=E, nu=nu)), lin.vertices, lin.vertex_volumes
    load = np.zeros_like(rest)
    load[:, 2] = -rho * g * weights
    x, _, _ = newton_equilibrium(field, rest.copy(), rest[:, 0] > 1e-9, load.ravel(), 1e-9 * rho * g * side ** 2 * length ** 2)
    tip = np.flatnonzero(lin.vertices[:, 0] > length - 1e-9)
    q, inertia, shear = rho * g * side ** 2, side ** 4 / 12, E / (2 * (1 + nu))
    timoshenko = q * length ** 4 / (8 * E * inertia) + q * length ** 2 / (2 * 5 / 6 * shear * side ** 2)
    return -float(np.mean(x[tip, 2] - rest[tip, 2])), timoshenko


def test_quadratic_tets_bend_like_a_beam_where_linear_ones_lock():
    """Small deflection (1.5 % of the length): Timoshenko beam theory is the truth. One
    cell through the thickness: quadratic tets within 5 %, linear ones far too stiff."""
    quadratic, truth = cantilever_tip_deflection(10, quadratic=True)
    linear, _ = cantilever_tip_deflection(10, quadratic=False)
    assert quadratic == pytest.approx(truth, rel=0.05)
    assert linear < 0.5 * truth


def test_bad_arguments_are_named():
    with pytest.raises(TypeError, match="linear must be a heml_gym.TetMesh"):
        QuadraticTetMesh.from_linear(np.zeros((4, 3)))
    with pytest.raises(TypeError, match="mesh must be a QuadraticTetMesh"):
        QuadraticFemForce(hg.box_mesh(), NeoHookean(E=1e3, nu=0.3))
    bare = QuadraticTetMesh(small_mesh().vertices, small_mesh().tets)  # not from_linear: no elements
    with pytest.raises(TypeError, match="built by QuadraticTetMesh.from_linear"):
        QuadraticFemForce(bare, NeoHookean(E=1e3, nu=0.3))
    field = QuadraticFemForce(small_mesh(), NeoHookean(E=1e3, nu=0.3))
    with pytest.raises(ValueError, match="positions must have shape"):
        field.forces(np.zeros((3, 3)))


def test_first_bending_frequency_matches_beam_theory():
    """Lumped masses and stiffness together: the cantilever's lowest eigenfrequency on one
    cell through the thickness against Euler-Bernoulli (slender: 10 x 10 x 100 mm)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    length, side, E, rho = 0.1, 0.01, 1e5, 1000.0
    beam = 1.8751 ** 2 * np.sqrt(E * side ** 4 / 12 / (rho * side ** 2 * length ** 4))  # rad/s
    ratios = {}
    for quadratic in (False, True):
        lin = hg.box_mesh((length, side, side), (10, 1, 1))
        mesh = QuadraticTetMesh.from_linear(lin) if quadratic else lin
        field = (QuadraticFemForce if quadratic else hg.FemForce)(mesh, NeoHookean(E=E, nu=0.3))
        free = np.repeat(mesh.vertices[:, 0] > 1e-9, 3)
        k = field.hessian(mesh.vertices, project=False).tocsr()[free][:, free]
        m = sp.diags(np.repeat(rho * mesh.vertex_volumes, 3)[free])
        lam = spla.eigsh(k, k=1, M=m, sigma=0, which="LM", return_eigenvectors=False)[0]
        ratios[quadratic] = np.sqrt(lam) / beam
    assert ratios[True] == pytest.approx(1.0, abs=0.03)
    assert ratios[False] > 1.5  # linear tets: far too stiff


@pytest.mark.parametrize("integrator", ["implicit", "explicit"])
def test_model_steps_quadratic_tets_to_the_static_equilibrium(integrator):
    """A Model on quadratic tets, stepped with damping by the generic solvers, comes to
    rest where the static solver puts it (the lumped node masses carry the weight)."""
    from heml_gym.solvers.factory import make_solver
    from heml_gym.solvers.statics import StaticSolver

    lin = hg.box_mesh((0.1, 0.02, 0.02), (5, 1, 1))
    mesh = QuadraticTetMesh.from_linear(lin)
    model = hg.Model(field=QuadraticFemForce(mesh, NeoHookean(E=50e3, nu=0.45)), density=1000.0,
                     fixed=mesh.vertices[:, 0] < 1e-9, damping=3.0)
    assert model.mass.sum() == pytest.approx(1000.0 * 0.1 * 0.02 * 0.02, rel=1e-12)
    tip = np.flatnonzero(lin.vertices[:, 0] > 0.1 - 1e-9)
    static = model.state()
    assert StaticSolver(model, load_steps=8).solve(static, model.control()).converged.all()
    state, control = model.state(), model.control()
    solver = make_solver(model, integrator, newton_tol=1e-5)
    for _ in range(200):
        stats = solver.step(state, state, control, 0.02)
        assert stats.converged.all()
    sag = np.mean(state.x[0, tip, 2] - mesh.vertices[tip, 2])
    assert sag == pytest.approx(np.mean(static.x[0, tip, 2] - mesh.vertices[tip, 2]), rel=0.01)


def test_an_inverted_quadrature_point_gives_nan_not_an_error():
    """ln J laws are undefined past J = 0: energy +inf, and a Hessian (projected or not)
    holding NaN where the solvers look for a usable step matrix, instead of raising."""
    mesh = small_mesh()
    field = QuadraticFemForce(mesh, NeoHookean(E=5e3, nu=0.45))
    x = mesh.vertices.copy()
    x[mesh.elements[0, 4]] = mesh.vertices[mesh.elements[0, 9]] + 0.02  # an edge node thrown through the element
    assert field.energy(x) == np.inf
    for project in (False, True):
        assert not np.all(np.isfinite(field.hessian(x, project=project).data))
