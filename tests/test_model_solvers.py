"""Model / State / Control / solvers: N worlds in one step behave like N independent Simulations."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.mesh import signed_volumes

MESH = hg.box_mesh((0.06, 0.03, 0.008), (4, 2, 1))
FIXED = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.0))
HELD = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.06))
STIFFNESS = [2e3, 3.5e3, 5e3, 2.7e3]  # Pa, one per world
DAMPING, DENSITY, GRAVITY = 5.0, 950.0, (0.0, 0.0, -9.81)


def paths(n_worlds, steps, seed=0, scale=0.002):
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.uniform(-1, 1, (n_worlds, steps, 3)) * scale, axis=1)  # m, per step


def single_run(material, path, dt, integrator, substeps=None, supports=(), mesh=MESH):
    """One world stepped by Simulation, its held vertices driven along ``path``."""
    sim = hg.Simulation(hg.HemlForce(mesh, material), DENSITY, gravity=GRAVITY, fixed=FIXED, damping=DAMPING,
                        integrator=integrator, supports=supports)
    sim.attach(HELD)
    xs, forces = [], []
    for offset in path:
        sim.drive(HELD, mesh.vertices[HELD] + offset)
        sim.step(dt, substeps=substeps)
        xs.append(sim.x.copy())
        forces.append(sim.reaction_forces(HELD).sum(axis=0))
    return np.array(xs), np.array(forces)


def batch_run(materials, scene_paths, dt, integrator, substeps=None, supports=()):
    model = hg.Model(MESH, materials, density=DENSITY, gravity=GRAVITY, fixed=FIXED, damping=DAMPING,
                     supports=supports)
    solver = {"explicit": hg.ExplicitSolver, "implicit": hg.ImplicitSolver,
              "quasi_newton": hg.QuasiNewtonSolver}[integrator](model)
    state, control = model.state(), model.control()
    for s in range(model.n_worlds):
        control.attach(s, HELD, state.x[s])
    xs, forces = [], []
    for k in range(scene_paths.shape[1]):
        for s in range(model.n_worlds):
            control.drive(s, HELD, MESH.vertices[HELD] + scene_paths[s, k])
        kw = {"substeps": substeps} if substeps is not None else {}
        stats = solver.step(state, state, control, dt, **kw)
        assert not stats.diverged.any() and stats.converged.all()
        xs.append(state.x.copy())
        forces.append(stats.reaction[:, HELD].sum(axis=1))
    return np.array(xs), np.array(forces)


@pytest.mark.parametrize("integrator", ["explicit", "implicit", "quasi_newton"])
def test_four_stiffnesses_in_one_batch_equal_four_simulations(integrator):
    """N = 4 worlds with four E (the explicit path vectorised across worlds, the implicit
    ones world by world, each with its own factorisations) against four single
    Simulations, to 1e-10 m over 20 steps."""
    dt = 0.05 if integrator == "explicit" else 1 / 30
    substeps = 40 if integrator == "explicit" else 1
    materials = [M.NeoHookean(E=E, nu=0.45) for E in STIFFNESS]
    p = paths(4, 20, seed=1)
    xs, forces = batch_run(materials, p, dt, integrator, substeps)
    for s, mat in enumerate(materials):
        x_ref, f_ref = single_run(mat, p[s], dt, integrator, substeps)
        assert np.abs(xs[:, s] - x_ref).max() < 1e-10  # m
        np.testing.assert_allclose(forces[:, s], f_ref, rtol=1e-6, atol=1e-9)
        assert np.abs(x_ref[-1] - MESH.vertices).max() > 1e-3  # the worlds really moved
    assert np.abs(xs[-1, 0] - xs[-1, 2]).max() > 1e-4  # and differently


@pytest.mark.parametrize("integrator", ["explicit", "implicit", "quasi_newton"])
def test_mixed_laws_in_one_batch_equal_single_simulations(integrator):
    """Every law of ALL_MATERIALS in one batch (the explicit path is then the general
    HEML kernel, worlds over threads) equals each law simulated alone."""
    materials = [law(E=E, nu=0.4) for law, E in zip(M.ALL_MATERIALS, [3e3, 4e3, 5e3, 3.5e3, 4.5e3])]
    dt, substeps = (0.05, 60) if integrator == "explicit" else (1 / 30, 1)
    p = paths(len(materials), 8, seed=2, scale=0.0015)
    xs, _ = batch_run(materials, p, dt, integrator, substeps)
    for s, mat in enumerate(materials):
        x_ref, _ = single_run(mat, p[s], dt, integrator, substeps)
        assert np.abs(xs[:, s] - x_ref).max() < 1e-10


def test_inactive_and_diverged_worlds_keep_their_state():
    model = hg.Model(MESH, [M.NeoHookean(E=E, nu=0.45) for E in (2e3, 3e3, 4e3)], density=DENSITY,
                     gravity=GRAVITY, fixed=FIXED, damping=DAMPING)
    solver = hg.ExplicitSolver(model)
    state, control = model.state(), model.control()
    state.x[1] *= 1.02  # world 1 starts stretched: it moves
    state.x[2, 5] = np.nan  # world 2 is broken
    before = state.copy()
    stats = solver.step(state, state, control, 0.01, active=[False, True, True])
    assert stats.diverged.tolist() == [False, False, True]
    assert "non-finite" in stats.messages[2]
    np.testing.assert_array_equal(state.x[0], before.x[0])  # inactive: untouched
    np.testing.assert_array_equal(state.x[2], before.x[2])  # diverged: restored
    assert np.abs(state.x[1] - before.x[1]).max() > 0


def test_a_newton_step_from_an_inverted_state_is_flagged_diverged_not_raised():
    """From a state with an inverted element (its ln J law has no energy there, and its
    step matrix is non-finite), driving the held vertices has no feasible Newton start:
    the world is flagged diverged, says why, and keeps its state. (On the 8 mm / 2.5 mm
    lobe at 0.1 s steps such a matrix made SuperLU raise 'failed to factorize matrix'
    out of the step; it is no longer factorised.)"""
    model = hg.Model(MESH, M.NeoHookean(E=3e3, nu=0.45), density=DENSITY, fixed=FIXED)
    solver = hg.ImplicitSolver(model)
    state, control = model.state(), model.control()
    control.attach(0, HELD, state.x[0])
    free = np.setdiff1d(np.arange(MESH.n_vertices), np.union1d(FIXED, HELD))
    bottom = free[MESH.vertices[free, 2] == 0.0][0]
    state.x[0, bottom, 2] += 0.05  # pushed up through the slab (8 mm thick): inverts its elements
    assert (signed_volumes(state.x[0], MESH.tets) <= 0).any()
    control.drive(0, HELD, MESH.vertices[HELD] + [0.0, 0.0, 0.004])
    before = state.copy()
    stats = solver.step(state, state, control, 1 / 30)
    assert stats.diverged.tolist() == [True] and not stats.converged[0]
    assert "no feasible start" in stats.messages[0]
    np.testing.assert_array_equal(state.x, before.x)


def test_state_out_may_differ_from_state_in():
    model = hg.Model(MESH, M.NeoHookean(E=3e3, nu=0.45), n_worlds=2, density=DENSITY, fixed=FIXED)
    solver = hg.ImplicitSolver(model)
    a, control = model.state(), model.control()
    b = model.state()
    b.x += 1.0  # garbage that the step must overwrite
    solver.step(a, b, control, 1 / 30)
    np.testing.assert_array_equal(a.x, np.repeat(MESH.vertices[None], 2, axis=0))  # input untouched
    assert b.x[:, :, 2].min() < -1e-3 and np.abs(b.x - a.x).max() < 0.05  # sagged from rest


def test_per_world_fields_share_the_rest_data():
    model = hg.Model(MESH, [M.NeoHookean(E=2e3, nu=0.45), M.StVenantKirchhoff(E=3e3, nu=0.45)])
    f0, f1 = model.fields
    assert f0.rest is f1.rest  # one precomputation for every world
    assert f1.use_q and not f0.use_q
    # and each field is the law's own: equal to a field built from scratch
    x = MESH.vertices * [1.1, 0.95, 1.0]
    fresh = hg.HemlForce(MESH, M.StVenantKirchhoff(E=3e3, nu=0.45))
    np.testing.assert_array_equal(f1.forces(x), fresh.forces(x))


def test_critical_step_scales_with_stiffness_without_a_new_eigensolve():
    model = hg.Model(MESH, [M.NeoHookean(E=E, nu=0.45) for E in (1e3, 4e3)], density=DENSITY)
    dt1, dt4 = model.critical_dt(0), model.critical_dt(1)
    assert dt4 == pytest.approx(dt1 / 2, rel=1e-12)  # 1/sqrt(E)
    assert model.critical_dt() == dt4
    # against an independent eigensolve at E = 4 kPa
    alone = hg.Simulation(hg.HemlForce(MESH, M.NeoHookean(E=4e3, nu=0.45)), DENSITY, integrator="explicit")
    assert dt4 == pytest.approx(alone.critical_dt(), rel=1e-3)


@pytest.mark.parametrize("bad, match", [
    (dict(material=None), "material is required"),
    (dict(n_worlds=0), "n_worlds"),
    (dict(n_worlds=2.5), "n_worlds"),
    (dict(density=-1.0), "density"),
    (dict(field="springs"), "field must be one of"),
    (dict(fixed=[0, 10_000]), "fixed vertex indices"),
    (dict(gravity=(0, 0)), "gravity"),
])
def test_model_rejects_bad_input_naming_it(bad, match):
    kw = dict(mesh=MESH, material=M.NeoHookean(E=3e3, nu=0.45))
    kw.update(bad)
    with pytest.raises((ValueError, TypeError), match=match):
        hg.Model(**kw)


def test_solvers_reject_a_state_of_the_wrong_size():
    model = hg.Model(MESH, M.NeoHookean(E=3e3, nu=0.45), n_worlds=2)
    other = hg.Model(MESH, M.NeoHookean(E=3e3, nu=0.45), n_worlds=3)
    with pytest.raises(ValueError, match="state_in"):
        hg.ExplicitSolver(model).step(other.state(), other.state(), model.control(), 0.01)
    with pytest.raises(ValueError, match="dt"):
        hg.ImplicitSolver(model).step(model.state(), model.state(), model.control(), 0.0)
    with pytest.raises(ValueError, match="safety"):
        hg.ExplicitSolver(model, safety=1.5)
    with pytest.raises(ValueError, match="no Hessian|newton_tol"):
        hg.ImplicitSolver(model, newton_tol=float("nan"))


def test_static_solver_batch_equals_single_static_solves():
    materials = [M.NeoHookean(E=3e3, nu=0.45), M.StVenantKirchhoff(E=5e3, nu=0.4), M.Demiray(E=4e3, nu=0.45)]
    model = hg.Model(MESH, materials, density=DENSITY, gravity=GRAVITY, fixed=FIXED)
    state, control = model.state(), model.control()
    stats = hg.StaticSolver(model, load_steps=2).solve(state, control)
    assert stats.converged.all()
    for s, mat in enumerate(materials):
        sim = hg.Simulation(hg.HemlForce(MESH, mat), DENSITY, gravity=GRAVITY, fixed=FIXED)
        sim.solve_static(load_steps=2)
        assert np.abs(state.x[s] - sim.x).max() < 1e-9
        # equilibrium: the support reactions carry the weight
        np.testing.assert_allclose(stats.reaction[s].sum(axis=0), -model.mass.sum() * np.asarray(GRAVITY), rtol=1e-6,
                                   atol=1e-9)


@pytest.mark.parametrize("supports", [(), (hg.PlaneSupport(height=-0.004),)])
def test_quasi_newton_reaches_the_newton_solution(supports):
    """L-BFGS and Newton minimise the same incremental potential: solved tightly, their
    steps agree, for four worlds of different stiffness with held vertices driven."""
    materials = [M.NeoHookean(E=E, nu=0.45) for E in STIFFNESS]
    p = paths(4, 5, seed=4, scale=0.001)
    results = []
    for cls, kw in ((hg.ImplicitSolver, {"newton_tol": 1e-8, "contact_stiffness": 1000.0}),
                    (hg.QuasiNewtonSolver, {"newton_tol": 1e-8, "max_iter": 1000, "contact_stiffness": 1000.0})):
        model = hg.Model(MESH, materials, density=DENSITY, gravity=GRAVITY, fixed=FIXED, damping=DAMPING,
                         supports=supports)
        solver = cls(model, **kw)
        state, control = model.state(), model.control()
        for s in range(4):
            control.attach(s, HELD, state.x[s])
        xs = []
        for k in range(p.shape[1]):
            for s in range(4):
                control.drive(s, HELD, MESH.vertices[HELD] + p[s, k])
            stats = solver.step(state, state, control, 1 / 30)
            assert stats.converged.all() and not stats.diverged.any()
            xs.append(state.x.copy())
        results.append(np.array(xs))
    assert np.abs(results[0] - results[1]).max() < 1e-7
    assert np.abs(results[0][-1] - MESH.vertices).max() > 1e-3


def test_one_factory_builds_every_solver_with_one_meaning_per_setting():
    """``make_solver`` is what Simulation and the envs build their solvers with:
    ``max_iterations`` is Newton's cap for "implicit" and L-BFGS's for "quasi_newton"
    (defaults 20 and 50), and the compatibility rules raise errors naming the setting."""
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401
    from heml_gym.solvers import SolverChoiceError, check_solver_choice, make_solver

    model = hg.Model(hg.box_mesh((0.02, 0.02, 0.02), 2), M.NeoHookean(E=5e3, nu=0.45))
    qn = make_solver(model, "quasi_newton", max_iterations=70, newton_tol=2e-3, scheme="bdf2")
    assert isinstance(qn, hg.QuasiNewtonSolver) and (qn.max_iter, qn.newton_tol, qn.scheme) == (70, 2e-3, "bdf2")
    newton = make_solver(model, "implicit", max_iterations=7, linear_solver="direct", refinements=(3,))
    assert isinstance(newton, hg.ImplicitSolver)
    assert (newton.max_newton, newton.linear_solver, newton.refinements) == (7, "direct", (3,))
    assert make_solver(model, "quasi_newton").max_iter == 50 and make_solver(model, "implicit").max_newton == 20
    assert isinstance(make_solver(model, "explicit", safety=0.3), hg.ExplicitSolver)
    for args, argument in ((("rk4",), "integrator"), (("implicit", "heml", "bdf2"), "scheme"),
                           (("quasi_newton", "fem", "bdf2"), "scheme"), (("explicit", "springs"), "field"),
                           (("quasi_newton", "heml", "rk2"), "scheme")):
        with pytest.raises(SolverChoiceError) as err:
            check_solver_choice(*args)
        assert err.value.argument == argument and str(err.value).startswith(argument)
    # the two users build the same solvers from the same settings
    sim = hg.Simulation(hg.HemlForce(model.mesh, M.NeoHookean(E=5e3, nu=0.45)), 1000.0, integrator="quasi_newton")
    assert sim.solver.max_iter == 50 and sim.solver.refinements == (4, 16)
    env = gym.make("heml_gym/TissueRetraction-v1")
    physics = env.unwrapped.scene.physics
    solver = env.unwrapped.task.solver
    assert (solver.max_iter, solver.newton_tol, solver.scheme) == (physics.max_newton, physics.newton_tol,
                                                                 physics.scheme)
    assert solver.hessian_scale == physics.hessian_scale == 1.25  # the flap's scene: a speed setting
    with pytest.raises(SolverChoiceError, match="^hessian_scale"):
        make_solver(model, "implicit", hessian_scale=2.0)
    # an integrator without an initial Hessian does not read the scene's setting
    implicit = gym.make("heml_gym/TissueRetraction-v1", physics={"integrator": "implicit"}).unwrapped.task.solver
    assert isinstance(implicit, hg.ImplicitSolver)
    with pytest.raises(Exception, match="PhysicsSpec.scheme|physics.scheme"):
        gym.make("heml_gym/TissueRetraction-v1", physics={"integrator": "implicit", "scheme": "bdf2"})


@pytest.mark.parametrize("integrator", ["explicit", "implicit", "quasi_newton"])
def test_one_broken_world_in_a_batch_leaves_the_others_as_single_runs(integrator):
    """Three worlds in one batch, the middle one broken (a NaN position): it is flagged
    diverged, says why and keeps its state; the other two step exactly as they do in the
    same batch with the middle world healthy (and, but for the explicit solver, whose
    sub-steps follow the batch's stiffest material, as each does alone)."""
    from heml_gym.solvers import make_solver

    materials = [M.NeoHookean(E=E, nu=0.45) for E in (2e3, 3e3, 4e3)]

    def run(mats, broken=None):
        model = hg.Model(MESH, mats, density=DENSITY, gravity=GRAVITY, fixed=FIXED, damping=DAMPING)
        solver = make_solver(model, integrator)
        state, control = model.state(), model.control()
        if broken is not None:
            state.x[broken, 5] = np.nan
        before = state.copy()
        for _ in range(3):
            stats = solver.step(state, state, control, 1 / 30)
        return state, before, stats

    state, before, stats = run(materials, broken=1)
    assert stats.diverged.tolist() == [False, True, False] and not stats.converged[1]
    assert stats.messages[1] and not stats.messages[0] and not stats.messages[2]  # (why: non-finite, no start)
    np.testing.assert_array_equal(state.x[1], before.x[1])
    healthy, _, healthy_stats = run(materials)
    assert healthy_stats.converged.all() and stats.converged[[0, 2]].all()
    np.testing.assert_array_equal(state.x[[0, 2]], healthy.x[[0, 2]])
    if integrator != "explicit":
        for s in (0, 2):
            np.testing.assert_array_equal(state.x[s], run([materials[s]])[0].x[0])


def test_the_kernel_arrays_follow_every_material_change():
    """``Model.heml_laws()`` (what the kernels read) after any sequence of
    ``set_material`` calls equals the arrays of a model built with the final materials:
    rows updated in place, or rebuilt when a law changes the batch's flags."""
    mesh = hg.box_mesh((0.02, 0.02, 0.01), (2, 2, 1))
    soft, stiff = M.NeoHookean(E=3e3, nu=0.45), M.NeoHookean(E=9e3, nu=0.4)
    demiray = M.Demiray(E=5e3, nu=0.45, b=2.0)
    model = hg.Model(mesh, soft, n_worlds=3)
    first = model.heml_laws()
    for worlds, material, final in ((1, stiff, [soft, stiff, soft]), ([0, 2], stiff, [stiff, stiff, stiff]),
                                    (2, demiray, [stiff, stiff, demiray]), (2, soft, [stiff, stiff, soft])):
        revision = model.material_revision
        model.set_material(worlds, material)
        assert model.material_revision > revision
        fresh = hg.Model(mesh, final).heml_laws()
        laws = model.heml_laws()
        assert (laws.split, laws.use_q) == (fresh.split, fresh.use_q)
        for name in ("law", "params", "weights", "psi1", "q_t"):
            np.testing.assert_array_equal(getattr(laws, name), getattr(fresh, name), err_msg=name)
    assert model.heml_laws() is not first  # Demiray (no constant Psi_1) rebuilt the arrays
    with pytest.raises(TypeError, match="HEML"):
        hg.Model(mesh, soft, field="fem").heml_body()
