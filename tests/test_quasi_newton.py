"""The quasi-Newton (L-BFGS) backward Euler solver and the kernels it adds, against
independent computations: Newton's solution of the same potential, scipy's linear
algebra, the general energy and force kernels, equilibrium, and the initial Hessian's
meaning (the P1 Laplacian is the Hessian of |F|^2 V0 / 2)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.forces.kernels_heml import (constant_psi1_energy_and_forces_chunk, constant_psi1_forces_chunk,
                                          heml_energy_chunk)
from heml_gym.kernels_cholesky import envelope_cholesky, envelope_solve, envelope_solve_pair
from heml_gym.kernel_data import world_law
from heml_gym.linear_solvers import EnvelopeLayout

MESH = hg.box_mesh((0.06, 0.03, 0.008), (4, 2, 1))
FIXED = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.0))
HELD = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.06))
DENSITY, GRAVITY = 950.0, (0.0, 0.0, -9.81)


def model(materials, supports=(), damping=5.0, fixed=FIXED, mesh=MESH):
    return hg.Model(mesh, materials, density=DENSITY, gravity=GRAVITY, fixed=fixed, damping=damping,
                    supports=supports)


def test_fused_energy_and_forces_equal_the_separate_kernels():
    mesh = hg.box_mesh((0.03, 0.02, 0.01), (3, 2, 2))
    field = hg.HemlForce(mesh, M.NeoHookean(E=7e3, nu=0.45))
    rest = field.rest
    x = mesh.vertices + np.random.default_rng(0).normal(scale=6e-4, size=mesh.vertices.shape)
    f_fused, f_alone = np.zeros_like(x), np.zeros_like(x)
    energy = constant_psi1_energy_and_forces_chunk(x, rest.tets, rest.inv_det, rest.coef_t[0], field.spring_weights,
                                                   field.psi1, field.law_id, field.params, f_fused, 0, mesh.n_tets)
    constant_psi1_forces_chunk(x, rest.tets, rest.inv_det, field.spring_weights, field.law_id, field.params,
                               f_alone, 0, mesh.n_tets)
    # the general energy kernel: per tet, with math.log and I1 from the edge coefficients
    reference = heml_energy_chunk(x, *field.kernel_args(), 0, mesh.n_tets)
    assert energy == pytest.approx(reference, rel=1e-12)
    np.testing.assert_allclose(f_fused, f_alone, rtol=0, atol=1e-14 * np.abs(f_alone).max())
    # an inverted tet (vertex 0 of tet 0 mirrored through its opposite face): the law is
    # undefined there, and the energy says so
    x_bad = x.copy()
    t = mesh.tets[0]
    normal = np.cross(x[t[2]] - x[t[1]], x[t[3]] - x[t[1]])
    normal /= np.linalg.norm(normal)
    x_bad[t[0]] = x[t[0]] - 2.0 * ((x[t[0]] - x[t[1]]) @ normal) * normal
    assert hg.kinematics.volume_ratios(mesh, x_bad)[0] < 0
    assert np.isinf(constant_psi1_energy_and_forces_chunk(
        x_bad, rest.tets, rest.inv_det, rest.coef_t[0], field.spring_weights, field.psi1, field.law_id,
        field.params, np.zeros_like(x), 0, mesh.n_tets))


def test_an_initial_hessian_too_ill_conditioned_for_single_precision_is_factorised_in_double():
    """Two vertices joined by one edge (Laplacian weight 1 m) with a mass term of 1e-9 of
    it: ``A = [[1 + 1e-9, -1], [-1, 1 + 1e-9]]`` is positive definite, but stored in
    single precision its diagonal rounds to 1 and it is singular, so the single-precision
    factorisation breaks down (checked). The kernel then factorises in double precision
    and rounds: the factor has a positive diagonal (``L L^T`` is a valid initial Hessian)
    and reproduces ``A`` to single precision's rounding."""
    from heml_gym.solvers import kernels_quasi_newton as kq

    a = np.array([[1.0 + 1e-9, -1.0], [-1.0, 1.0 + 1e-9]])
    layout = EnvelopeLayout.of(sp.csr_matrix(a))
    single = np.zeros(layout.size, dtype=np.float32)
    pos = layout.positions(np.array([0, 1, 1]), np.array([0, 0, 1]))
    single[pos] = a[[0, 1, 1], [0, 0, 1]]
    assert envelope_cholesky(layout.first, layout.ptr, single) >= 0  # single precision breaks down
    values = np.zeros((1, 2, 3, layout.size), dtype=np.float32)
    status = np.empty(1, dtype=np.int64)
    zero = np.zeros(1, dtype=np.int64)
    edge_i, edge_j = np.array([0]), np.array([1])
    kq.factor_jobs(zero, zero, zero, values, layout.first, layout.ptr, layout.positions(np.arange(2), np.arange(2)),
                   layout.positions(edge_i, edge_j), edge_i, edge_j, np.array([1.0]), np.ones(2), np.full(2, 1e-9),
                   np.array([1.0]), np.array([1.0]), np.zeros((1, 2), dtype=bool), np.zeros((1, 2, 3, 2)), status)
    assert status[0] == -1
    factor = np.zeros((2, 2))
    for r in range(2):
        factor[r, layout.first[r]:r + 1] = values[0, 0, 0, layout.ptr[r]:layout.ptr[r + 1]]
    assert np.all(np.diag(factor) > 0)
    perm = np.empty(2, dtype=np.int64)
    perm[layout.inverse] = np.arange(2)
    np.testing.assert_allclose(factor @ factor.T, a[np.ix_(perm, perm)], rtol=0, atol=1e-6)


def test_envelope_layout_factor_and_pair_solve_match_scipy():
    mesh = hg.box_mesh((0.03, 0.02, 0.01), (4, 3, 2))
    n = mesh.n_vertices
    e = mesh.edges
    w = np.random.default_rng(1).uniform(0.5, 2.0, len(e))
    lap = sp.coo_matrix((np.r_[-w, -w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    a = (lap - sp.diags(np.asarray(lap.sum(axis=1)).ravel()) + sp.diags(np.full(n, 0.3))).tocsr()
    layout = EnvelopeLayout.of(a)
    values = np.zeros(layout.size)
    rows, cols = a.nonzero()
    lower = layout.positions(rows, cols, upper=-1)
    keep = lower >= 0
    np.add.at(values, lower[keep], np.asarray(a[rows[keep], cols[keep]]).ravel())
    assert envelope_cholesky(layout.first, layout.ptr, values) == -1
    b0, b1 = np.random.default_rng(2).standard_normal((2, n))
    perm = np.empty(n, dtype=np.int64)
    perm[layout.inverse] = np.arange(n)
    y0, y1, y_single = np.empty(n), np.empty(n), np.empty(n)
    envelope_solve_pair(layout.first, layout.ptr, values, b0[perm], b1[perm], y0, y1)
    envelope_solve(layout.first, layout.ptr, values, b1[perm], y_single)
    exact0, exact1 = sla.solve(a.toarray(), b0), sla.solve(a.toarray(), b1)
    np.testing.assert_allclose(y0[layout.inverse], exact0, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(y1[layout.inverse], exact1, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(y1, y_single, rtol=1e-13, atol=1e-15)
    # mirror positions: (i, j) and (j, i) are one stored entry
    np.testing.assert_array_equal(layout.positions(e[:, 0], e[:, 1]), layout.positions(e[:, 1], e[:, 0]))


def test_initial_hessian_laplacian_is_the_hessian_of_the_i1_energy():
    """The solver's Laplacian makes ``x^T L x = sum V0 |F|^2`` over the axes (so ``mu L`` is
    Neo-Hookean's ``I1`` stiffness): checked on a random linear map, where ``F`` is that
    map in every tet, and a rigid translation costs nothing."""
    mesh = hg.box_mesh((0.03, 0.02, 0.01), (3, 2, 2))
    solver = hg.QuasiNewtonSolver(model(M.NeoHookean(E=5e3, nu=0.3), mesh=mesh, fixed=None))
    n = mesh.n_vertices
    lap = solver.laplacian()
    f_map = np.random.default_rng(3).standard_normal((3, 3))
    x = mesh.vertices @ f_map.T
    quadratic = sum(x[:, a] @ (lap @ x[:, a]) for a in range(3))
    assert quadratic == pytest.approx(mesh.volumes.sum() * np.sum(f_map ** 2), rel=1e-12)
    assert np.abs(lap @ np.ones(n)).max() < 1e-12 * lap.diagonal().max()  # rigid translation: no force


@pytest.mark.parametrize("supports", [(), (hg.PlaneSupport(height=-0.004),)])
def test_the_initial_hessian_steers_lbfgs_but_never_changes_the_solution(supports):
    """Refreshing the initial Hessian on every contact change or never, or weighting its
    Laplacian by half or twice ``lambda + mu``: the same steps when solved tightly (the
    factor only steers L-BFGS)."""
    materials = [M.NeoHookean(E=E, nu=0.45) for E in (2e3, 4e3)]
    results = []
    for settings in ({"contact_refresh": 0}, {"contact_refresh": 10 ** 6}, {"hessian_scale": 0.5},
                     {"hessian_scale": 2.0}):
        m = model(materials, supports=supports)
        solver = hg.QuasiNewtonSolver(m, newton_tol=1e-9, max_iter=2000, **settings)
        state, control = m.state(), m.control()
        for s in range(2):
            control.attach(s, HELD, state.x[s])
        xs = []
        for k in range(6):
            for s in range(2):
                control.drive(s, HELD, MESH.vertices[HELD] + [0.0, 0.0, -0.002 * (k + 1) * (s + 1)])
            stats = solver.step(state, state, control, 0.05)
            assert stats.converged.all() and not stats.diverged.any()
            xs.append(state.x.copy())
        results.append(np.array(xs))
    for other in results[1:]:
        assert np.abs(results[0] - other).max() < 1e-7


@pytest.mark.parametrize("scheme", ["backward_euler", "bdf2"])
def test_hanging_body_reaction_balances_its_weight(scheme):
    """A body hanging from its fixed and held ends comes to rest: the constraint forces on
    them carry its weight (the step-mean reaction at rest is the static one), under
    either time scheme."""
    m = model(M.NeoHookean(E=3e3, nu=0.4))
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-8, max_iter=1000, scheme=scheme)
    state, control = m.state(), m.control()
    control.attach(0, HELD, state.x[0])
    for _ in range(80):
        stats = solver.step(state, state, control, 0.1)
        assert stats.converged.all()
    assert np.abs(state.v).max() < 1e-6
    weight = m.mass.sum() * np.asarray(GRAVITY)
    np.testing.assert_allclose(stats.reaction[0].sum(axis=0), -weight, rtol=1e-6, atol=1e-9)
    assert np.abs(stats.reaction[0][~(m.fixed | control.kinematic[0])]).max() == 0.0


def test_slab_dropped_on_a_support_comes_to_rest_on_it():
    """A free slab falls 1 mm onto a plane and comes to rest: its bottom on the plane (the
    penalty's few micrometres projected away), nothing inside, nothing moving."""
    mesh = hg.box_mesh((0.02, 0.02, 0.004), (2, 2, 1))
    plane = hg.PlaneSupport(height=0.0)
    m = hg.Model(mesh, M.NeoHookean(E=5e3, nu=0.3), density=DENSITY, gravity=GRAVITY, damping=5.0,
                 supports=[plane])
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-6, max_iter=2000)
    state, control = m.state(), m.control()
    state.x[0, :, 2] += 0.001
    for _ in range(80):
        stats = solver.step(state, state, control, 0.1)
        assert stats.converged.all() and not stats.diverged.any()
    assert np.abs(state.v).max() < 1e-6
    bottom = np.isclose(mesh.vertices[:, 2], 0.0)
    np.testing.assert_allclose(state.x[0, bottom, 2], 0.0, atol=1e-12)  # projected onto the plane
    assert np.all(state.x[0, ~bottom, 2] > 0.003)


def test_grasp_jump_that_inverts_the_predictor_still_starts():
    """Driving the top layer 1 cm down in one step inverts the plain predictor; the linear
    response of the free vertices gives a valid start and the step converges."""
    mesh = hg.box_mesh((0.02, 0.02, 0.02), 4)
    bottom = np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.0))
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.02))
    m = hg.Model(mesh, M.NeoHookean(E=5e3, nu=0.45), density=DENSITY, fixed=bottom)
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-6, max_iter=500)
    state, control = m.state(), m.control()
    control.attach(0, top, state.x[0])
    control.drive(0, top, mesh.vertices[top] - [0.0, 0.0, 0.01])
    stats = solver.step(state, state, control, 0.1)
    assert stats.converged.all() and not stats.diverged.any()
    assert hg.kinematics.volume_ratios(mesh, state.x[0]).min() > 0
    np.testing.assert_allclose(state.x[0, top, 2], 0.01, atol=1e-12)


def test_unconverged_step_is_reported_not_hidden():
    m = model(M.NeoHookean(E=3e3, nu=0.45))
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-10, max_iter=1, refinements=(), fallback=())
    state, control = m.state(), m.control()
    stats = solver.step(state, state, control, 0.1)
    assert not stats.converged[0] and not stats.diverged[0] and not stats.fallback[0]
    assert stats.newton_iterations[0] == 1 and stats.residual[0] > stats.tolerance[0]
    assert "L-BFGS stopped" in stats.messages[0]
    # refined: the step is taken again in 4, then 16 shorter steps, and still reported
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-10, max_iter=1, fallback=())
    state = m.state()
    stats = solver.step(state, state, control, 0.1)
    assert not stats.converged[0] and stats.refinement[0] == 16
    assert stats.newton_iterations[0] == 1 + 4 + 16 and "refined 16x" in stats.messages[0]
    # and by the Newton fallback, held to one iteration below an unreachable tolerance
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-16, max_iter=1, refinements=(), fallback=(1, 2), max_newton=1)
    state = m.state()
    stats = solver.step(state, state, control, 0.1)
    assert not stats.converged[0] and not stats.diverged[0] and stats.fallback[0]
    assert stats.newton_iterations[0] == 1 + 1 + 2 and "Newton (the fallback) stopped" in stats.messages[0]


def test_an_unconverged_first_sub_step_stays_reported_when_the_second_needs_a_retake():
    """Each sub-step's verdict counts: a re-take of the second sub-step does not erase the
    first's failure (before 2026-11-26 it did)."""
    m = model(M.NeoHookean(E=3e3, nu=0.45))
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-10, max_iter=1, refinements=(2,), fallback=())
    state, control = m.state(), m.control()
    stats = solver.step(state, state, control, 0.1, substeps=2)
    assert not stats.converged[0] and stats.newton_iterations[0] == 2 * (1 + 2)


def _pulled_slab(scheme, supports, **solver_args):
    """A cantilever slab under gravity whose free end is held and pulled 8 mm up and
    sideways in one 0.1 s step (on a support plane it rests on, if ``supports``)."""
    plane = [hg.PlaneSupport(height=float(MESH.vertices[:, 2].min()))] if supports else ()
    m = model(M.NeoHookean(E=4e3, nu=0.45), supports=plane)
    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-6, scheme=scheme, **solver_args)
    state, control = m.state(), m.control()
    for _ in range(3):  # settle a little first (BDF2: with a history)
        solver.step(state, state, control, 0.05)
    control.attach(0, HELD, state.x[0])
    control.drive(0, HELD, state.x[0, HELD] + [0.0, 0.004, 0.008])
    stats = solver.step(state, state, control, 0.1, substeps=2)
    return state, stats


@pytest.mark.parametrize("scheme", ["backward_euler", "bdf2"])
@pytest.mark.parametrize("supports", [False, True])
def test_the_newton_fallback_solves_a_step_lbfgs_cannot_as_lbfgs_solves_it_with_room(scheme, supports):
    """L-BFGS held to 2 iterations, without refinements, cannot converge the pull: the
    Newton fallback (the field's analytic Hessian on the same incremental potential) takes
    it, converges, and lands where L-BFGS with 2,000 iterations does (both minimise the same
    potential to 1e-6 of the weight), with the same velocities and grasp force."""
    hard, hard_stats = _pulled_slab(scheme, supports, max_iter=2, refinements=())
    easy, easy_stats = _pulled_slab(scheme, supports, max_iter=2000, fallback=())
    assert hard_stats.fallback[0] and hard_stats.converged[0] and not hard_stats.diverged[0]
    assert not easy_stats.fallback[0] and easy_stats.converged[0]
    moved = np.abs(easy.x[0] - MESH.vertices).max()
    assert np.abs(hard.x[0] - easy.x[0]).max() < 1e-4 * moved
    assert np.abs(hard.v[0] - easy.v[0]).max() < 1e-4 * np.abs(easy.v[0]).max()
    pull, pull_easy = hard_stats.reaction[0, HELD].sum(axis=0), easy_stats.reaction[0, HELD].sum(axis=0)
    assert np.linalg.norm(pull - pull_easy) < 1e-3 * np.linalg.norm(pull_easy)


@pytest.mark.parametrize("scheme", ["backward_euler", "bdf2"])
def test_a_step_that_stalls_is_refined_to_the_same_solution_as_short_steps(scheme):
    """A slab falling from rest under gravity, one 0.1 s step with few iterations allowed:
    it is taken again as 4 steps of 0.025 s, which converge, and equals four such steps
    taken directly (BDF2: the refined steps start their own history, as a new solver's)."""
    materials = M.NeoHookean(E=3e3, nu=0.45)
    results = []
    for dt, steps, max_iter in ((0.1, 1, 60), (0.025, 4, 2000)):  # 0.1 s needs ~85, 0.025 s ~50
        m = model(materials)
        solver = hg.QuasiNewtonSolver(m, newton_tol=1e-4, max_iter=max_iter, refinements=(4,), scheme=scheme)
        state, control = m.state(), m.control()
        for _ in range(steps):
            stats = solver.step(state, state, control, dt)
        results.append((state.x.copy(), stats))
    (x_refined, stats_refined), (x_short, _) = results
    assert stats_refined.refinement[0] == 4 and stats_refined.converged[0]
    assert np.abs(x_refined - x_short).max() < 1e-3 * np.abs(x_short - MESH.vertices).max()


def test_factors_are_refreshed_only_when_their_content_changes():
    m = model([M.NeoHookean(E=3e3, nu=0.45)] * 2)
    solver = hg.QuasiNewtonSolver(m, max_iter=500)  # no refinement: it would factorise too
    state, control = m.state(), m.control()
    solver.step(state, state, control, 0.05)
    first = solver.factorizations
    assert first == 2  # one factor per world: no contact, the three axes share it
    solver.step(state, state, control, 0.05)
    assert solver.factorizations == first  # nothing changed
    control.attach(1, HELD, state.x[1])
    solver.step(state, state, control, 0.05)
    assert solver.factorizations == first + 1  # world 1's held set changed
    m.set_material(0, M.NeoHookean(E=6e3, nu=0.45))
    solver.step(state, state, control, 0.05)
    assert solver.factorizations == first + 2  # world 0's material changed
    control.detach(1)
    solver.step(state, state, control, 0.05)
    assert solver.factorizations == first + 2  # released: world 1's previous initial Hessian is kept
    control.attach(1, HELD, state.x[1])
    solver.step(state, state, control, 0.05)
    assert solver.factorizations == first + 2  # grasped again: so is the one with HELD held


def test_worlds_stepped_over_threads_equal_worlds_stepped_one_after_another():
    """Five worlds (different stiffness; two grasped and lifted, all sagging onto a
    support) stepped by the parallel kernel, worlds over two threads, are bit for bit
    those of one thread stepping them in turn (the serial kernel): a world's solve uses
    no state of another and no scratch shared between threads."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one Numba thread: the parallel kernel would be compared with the serial one on one thread")
    materials = [M.NeoHookean(E=E, nu=0.45) for E in (2e3, 3e3, 5e3, 8e3, 4e3)]
    runs = []
    old = numba.get_num_threads()
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            m = model(materials, supports=[hg.PlaneSupport(height=-0.004)])
            solver = hg.QuasiNewtonSolver(m)
            state, control = m.state(), m.control()
            for s in (1, 3):
                control.attach(s, HELD, state.x[s])
            steps = []
            for k in range(6):
                for s in (1, 3):
                    control.drive(s, HELD, MESH.vertices[HELD] + [0.0, 0.0, 0.003 * (k + 1)])
                stats = solver.step(state, state, control, 0.05)
                assert stats.converged.all() and not stats.diverged.any()
                steps.append((state.x.copy(), state.v.copy(), stats.reaction.copy(), stats.newton_iterations.copy()))
            runs.append(steps)
    finally:
        numba.set_num_threads(old)
    assert any(np.any(x[:, :, 2] < -0.0039) for x, *_ in runs[0])  # the sagging worlds reach the support
    for one, two in zip(*runs):
        for a, b in zip(one, two):
            np.testing.assert_array_equal(a, b)


def test_a_kept_initial_hessian_steps_as_a_fresh_factorisation_does():
    """Grasp, release, grasp: the steps after the release and the second grasp use the
    kept factors; a solver told to forget its factors before each of those steps
    factorises afresh. The two give the same states to round-off (the wrong kept
    factor, or curvature pairs carried across the change, would not)."""
    m = model(M.NeoHookean(E=3e3, nu=0.45))
    runs = []
    for fresh in (False, True):
        solver = hg.QuasiNewtonSolver(m, newton_tol=1e-5, max_iter=500)
        state, control = m.state(), m.control()
        for k in range(9):
            if k in (3, 6):
                control.attach(0, HELD, state.x[0])
                control.drive(0, HELD, MESH.vertices[HELD] + [0.0, 0.0, 0.002])
            elif k == 5:
                control.detach(0)
            if fresh and k in (5, 6):
                solver.forget(0)
            stats = solver.step(state, state, control, 0.05)
            assert stats.converged.all() and not stats.diverged.any()
        runs.append((state.x.copy(), solver.factorizations))
    (x_kept, n_kept), (x_fresh, n_fresh) = runs
    assert n_kept < n_fresh
    np.testing.assert_allclose(x_kept, x_fresh, rtol=0, atol=1e-12)


def test_reaction_from_the_held_vertices_tets_equals_the_full_force_evaluation():
    """The solver computes the elastic force on held vertices from their own tets only:
    the same as the forces of all tets, on those vertices, for the spring-split and the
    general kernels."""
    from heml_gym.solvers import kernels_quasi_newton as kq

    mesh = hg.box_mesh((0.03, 0.02, 0.01), (4, 3, 2))
    rng = np.random.default_rng(3)
    x = mesh.vertices + rng.normal(0.0, 2e-4, mesh.vertices.shape)
    held = np.zeros(mesh.n_vertices, dtype=bool)
    held[rng.choice(mesh.n_vertices, 7, replace=False)] = True
    for material in (M.NeoHookean(E=4e3, nu=0.45), M.StVenantKirchhoff(E=4e3, nu=0.45)):
        m = hg.Model(mesh, material)
        full = m.fields[0].forces(x)  # the field's own evaluation, every tet
        part = np.zeros_like(x)
        kq.held_forces(x, part, held, m.heml_body(), world_law(m.heml_laws(), 0))
        scale = np.abs(full).max()
        np.testing.assert_allclose(part[held], full[held], rtol=1e-12, atol=1e-12 * scale)


def test_rejects_bad_arguments_naming_them():
    m = model(M.NeoHookean(E=3e3, nu=0.45))
    for kwargs, match in (({"newton_tol": 0.0}, "newton_tol"), ({"max_iter": 0}, "max_iter"),
                          ({"history": 1.5}, "history"), ({"contact_refresh": -1}, "contact_refresh"),
                          ({"contact_stiffness": float("nan")}, "contact_stiffness"), ({"refinements": (1,)}, "refinements"),
                          ({"scheme": "rk4"}, "scheme"), ({"hessian_scale": 0.0}, "hessian_scale"),
                          ({"hessian_scale": float("inf")}, "hessian_scale")):
        with pytest.raises(ValueError, match=match):
            hg.QuasiNewtonSolver(m, **kwargs)
    with pytest.raises(ValueError, match="HEML"):
        hg.QuasiNewtonSolver(hg.Model(MESH, M.NeoHookean(E=3e3, nu=0.45), field="fem"))


def test_step_mean_reaction_matches_the_explicit_solvers():
    """A slab pulled slowly at its end: the quasi-Newton solver's step-mean reaction (the
    trapezoidal rule over its steps) equals the explicit solver's (the impulse of its
    sub-steps over the step) to 0.1 % of the peak once the start transient is over;
    backward Euler's own end-of-step force is half a step of the ramp later (> 1 %)."""
    mesh = hg.box_mesh((0.06, 0.03, 0.008), (6, 3, 1))
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))
    held = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.06))
    forces, end_forces = {}, []
    for name in ("explicit", "quasi_newton"):
        m = hg.Model(mesh, M.NeoHookean(E=3e3, nu=0.4), density=1000.0, gravity=(0, 0, 0), fixed=fixed, damping=20.0)
        solver = hg.ExplicitSolver(m) if name == "explicit" else hg.QuasiNewtonSolver(m, newton_tol=1e-8, max_iter=500)
        state, control = m.state(), m.control()
        control.attach(0, held, state.x[0])
        series = []
        for k in range(1, 21):
            control.drive(0, held, mesh.vertices[held] + [0.0005 * k, 0.0, 0.0])
            kw = {"substeps": solver.substeps(0.05, m.critical_dt())} if name == "explicit" else {}
            stats = solver.step(state, state, control, 0.05, **kw)
            series.append(stats.reaction[0, held, 0].sum())
            if name == "quasi_newton":  # the held tissue's pull at the end of the step
                end_forces.append(-m.field.forces(state.x[0])[held, 0].sum())
        forces[name] = np.array(series)
    peak = np.abs(forces["explicit"]).max()
    assert np.abs(forces["quasi_newton"] - forces["explicit"])[4:].max() < 1e-3 * peak
    assert np.abs(np.array(end_forces) - forces["explicit"])[4:].min() > 1e-2 * peak


def test_count_report_adds_a_calls_report_as_the_numpy_expressions_do():
    """The compiled bookkeeping of one L-BFGS call equals the NumPy it replaced: iterations
    added for the worlds run only, the largest residual (NaN kept), converged and feasible
    cleared by a world run that did not converge / had no feasible start (NaN flags too)."""
    rng = np.random.default_rng(3)
    for trial in range(50):
        n = 7
        run = rng.random(n) < 0.6
        out = np.column_stack([rng.integers(0, 40, n).astype(float), rng.exponential(1.0, n),
                               rng.random(n).round(), rng.random(n).round()])
        out[rng.random((n, 4)) < 0.1] = np.nan
        out[:, 0] = np.nan_to_num(out[:, 0])  # the kernel always reports a count
        iterations = rng.integers(0, 50, n)
        residual = rng.exponential(1.0, n)
        residual[rng.random(n) < 0.1] = np.nan
        converged, feasible = rng.random(n) < 0.7, rng.random(n) < 0.8
        expected = (iterations + np.where(run, out[:, 0], 0).astype(np.int64),
                    np.maximum(residual, np.where(run, out[:, 1], 0.0)),
                    converged & (~run | (out[:, 2] > 0.5)), feasible & (~run | (out[:, 3] > 0.5)))
        hg.solvers.kernels_quasi_newton.count_report(run, out, iterations, residual, converged, feasible)
        for got, want in zip((iterations, residual, converged, feasible), expected):
            np.testing.assert_array_equal(got, want)


def test_suspect_worlds_include_every_world_divergence_flags():
    """The compiled pre-check may flag more worlds than :meth:`divergence` does, never fewer:
    NaN or infinite positions or velocities, and speeds at, just above and just below the
    limit (the last not flagged by either)."""
    model = hg.Model(hg.box_mesh((0.02, 0.02, 0.01), (2, 2, 1)), M.NeoHookean(E=1e4, nu=0.4), n_worlds=8)
    solver = hg.QuasiNewtonSolver(model, max_speed=2.0)
    x = np.repeat(model.mesh.vertices[None], 8, axis=0)
    v = np.zeros_like(x)
    x[1, 3, 0] = np.nan
    x[2, 0, 2] = np.inf
    v[3, 5, 1] = -np.inf
    v[4, 2] = [0.0, 2.0, 0.0]  # at the limit: not too fast
    v[5, 2] = [0.0, np.nextafter(2.0, 3.0), 0.0]
    v[6, 4] = [1.2, 1.6, 1e-4]  # |v| 2.5e-9 m/s above 2
    v[7, 1] = [1.0, 1.0, 1.0]  # well below
    flagged = solver.suspect_worlds(x, v, np.arange(8))
    verdicts = [bool(solver.divergence(x[s], v[s])[0]) for s in range(8)]
    assert verdicts == [False, True, True, True, False, True, True, False]
    assert set(np.flatnonzero(verdicts)) <= set(flagged.tolist())
    assert 0 not in flagged and 7 not in flagged
    np.testing.assert_array_equal(solver.suspect_worlds(x, v, np.array([0, 7, 2])), [2])


def test_force_scales_equal_the_per_world_force_scale():
    model = hg.Model(hg.box_mesh((0.02, 0.02, 0.01), (2, 2, 1)), M.NeoHookean(E=1e4, nu=0.4), n_worlds=3)
    solver = hg.QuasiNewtonSolver(model)
    control = model.control()
    assert solver.force_scales(control).tolist() == [solver.force_scale(s, control) for s in range(3)]
    control.external_forces[1, 4] = [0.3, -0.2, 0.1]
    assert solver.force_scales(control).tolist() == [solver.force_scale(s, control) for s in range(3)]
    weightless = hg.Model(model.mesh, M.NeoHookean(E=1e4, nu=0.4), n_worlds=3, gravity=np.zeros(3))
    solver = hg.QuasiNewtonSolver(weightless)
    control = weightless.control()
    control.external_forces[2, 0, 2] = 0.5
    scales = solver.force_scales(control)
    assert scales.tolist() == [solver.force_scale(s, control) for s in range(3)]
    assert scales[0] == pytest.approx(1e4 * weightless.mesh.min_edge_length ** 2) and scales[2] == 0.5


# ---------------------------------------------------------------------------- BDF2
def _released_cantilever(scheme_or_explicit: str, h: float, duration: float = 0.2):
    """A slab clamped at x = 0, held bent (its free end 1 mm up) and released at t = 0
    under gravity, with light damping: positions (m) after ``duration`` s in steps of
    ``h`` (the explicit solver: sub-steps at 0.05 of its critical step)."""
    mesh = hg.box_mesh((0.06, 0.03, 0.008), (6, 3, 1))
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))
    m = hg.Model(mesh, M.NeoHookean(E=30e3, nu=0.4), density=1000.0, gravity=GRAVITY, fixed=fixed, damping=1.0)
    state = m.state()
    state.x[0, :, 2] += 0.001 * (mesh.vertices[:, 0] / 0.06) ** 2
    control = m.control()
    steps = round(duration / h)
    if scheme_or_explicit == "explicit":
        solver = hg.ExplicitSolver(m, safety=0.05)
        for _ in range(steps):
            solver.step(state, state, control, h, substeps=solver.substeps(h, m.critical_dt()))
    else:
        solver = hg.QuasiNewtonSolver(m, newton_tol=1e-10, max_iter=2000, scheme=scheme_or_explicit)
        for _ in range(steps):
            assert solver.step(state, state, control, h).converged.all()
    return state.x[0].copy()


def test_bdf2_is_second_order_in_the_step_and_backward_euler_first():
    """Against an independent reference (the explicit solver at 0.05 of its critical step,
    itself 1e-4 m from BDF2 at a 16th of the step), halving the step divides backward
    Euler's error by about 2 (1.7 measured: not yet asymptotic) and BDF2's by about 4
    (3.7), and BDF2 is several times closer than backward Euler at the same step."""
    reference = _released_cantilever("explicit", 0.005)
    error = {(s, h): np.abs(_released_cantilever(s, h) - reference).max()
             for s in ("backward_euler", "bdf2") for h in (0.01, 0.005)}
    be_ratio = error["backward_euler", 0.01] / error["backward_euler", 0.005]
    bdf2_ratio = error["bdf2", 0.01] / error["bdf2", 0.005]
    assert 1.3 < be_ratio < 2.5, error
    assert bdf2_ratio > 3.0, error
    assert error["bdf2", 0.005] < 0.3 * error["backward_euler", 0.005], error


def test_bdf2_forget_restarts_a_world_as_a_new_solver_would():
    """After :meth:`forget`, a world put back to its start is stepped exactly as by a new
    solver (its state one step back is not carried over); a world that keeps it is
    stepped differently from the same state in a new solver (which expands the state one
    step back about its start)."""
    m = model(M.NeoHookean(E=3e3, nu=0.4))

    def run(solver, state):
        control = m.control()
        for _ in range(5):
            assert solver.step(state, state, control, 0.05).converged.all()

    solver = hg.QuasiNewtonSolver(m, scheme="bdf2")
    first = m.state()
    run(solver, first)
    solver.forget([0])
    again = m.state()
    run(solver, again)
    np.testing.assert_array_equal(again.x, first.x)
    copy = m.state()
    copy.x[:], copy.v[:] = again.x, again.v
    run(solver, again)  # its state one step back kept
    run(hg.QuasiNewtonSolver(m, scheme="bdf2"), copy)
    assert np.abs(again.x - copy.x).max() > 1e-9


def test_forget_restarts_a_world_that_took_the_newton_fallback_as_a_new_solver_would():
    """The fallback keeps a lagged factorisation per world (its inexact solves start from
    it); :meth:`forget` drops it with the rest, so that an episode restarted after steps the
    fallback took is stepped exactly as by a new solver."""
    m = model(M.NeoHookean(E=4e3, nu=0.45))

    def run(solver):
        state, control = m.state(), m.control()
        control.attach(0, HELD, state.x[0])
        for k in range(4):
            control.drive(0, HELD, MESH.vertices[HELD] + [0.0, 0.002 * (k + 1), 0.004 * (k + 1)])
            stats = solver.step(state, state, control, 0.1, substeps=2)
            assert stats.fallback[0] and stats.converged[0]
        return state.x.copy()

    solver = hg.QuasiNewtonSolver(m, newton_tol=1e-6, max_iter=2, refinements=())
    run(solver)
    solver.forget([0])
    np.testing.assert_array_equal(run(solver), run(hg.QuasiNewtonSolver(m, newton_tol=1e-6, max_iter=2,
                                                                        refinements=())))
