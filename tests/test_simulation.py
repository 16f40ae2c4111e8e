"""Dynamics: energy behaviour, stability limits, divergence, constraints and statics."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym import materials as M

RHO = 1000.0


def cube_sim(integrator="explicit", nu=0.45, E=5e3, **kw):
    mesh = hg.box_mesh((0.02, 0.02, 0.02), 2)
    return hg.Simulation(hg.HemlForce(mesh, M.NeoHookean(E=E, nu=nu)), RHO, integrator=integrator, **kw)


def squeezed_start(sim, amount=0.15):
    """Initial positions: the cube squeezed along z and bulged in x, y (free vibration)."""
    x = sim.mesh.vertices * np.array([1 + amount / 2, 1 + amount / 2, 1 - amount])
    sim.reset(x=x)


def test_critical_dt_matches_the_spectrum():
    sim = cube_sim()
    mesh = sim.mesh
    n = mesh.n_vertices
    h = 1e-7 * mesh.min_edge_length
    k = np.zeros((3 * n, 3 * n))
    for i in range(3 * n):
        d = np.zeros(3 * n)
        d[i] = h
        k[:, i] = -(sim.field.forces(mesh.vertices + d.reshape(-1, 3))
                    - sim.field.forces(mesh.vertices - d.reshape(-1, 3))).ravel() / (2 * h)
    omega2 = np.linalg.eigvals(k / np.repeat(sim.mass, 3)[:, None]).real.max()
    assert sim.critical_dt() == pytest.approx(2 / np.sqrt(omega2), rel=1e-3)
    # the element-size estimate is of the right order
    assert 0.5 < sim.critical_dt("estimate") / sim.critical_dt() < 2.0


def test_explicit_energy_drift_bounded_below_critical_step():
    sim = cube_sim(gravity=(0, 0, 0))
    squeezed_start(sim)
    dt = 0.5 * sim.critical_dt()
    e0 = sim.total_energy()
    energies = []
    for _ in range(10_000):
        sim.step(dt, substeps=1)
        energies.append(sim.total_energy())
    energies = np.array(energies)
    # symplectic Euler: the energy oscillates (by O(omega dt)) but does not drift
    assert np.all(np.abs(energies - e0) <= 0.25 * e0)
    early, late = energies[:1000].mean(), energies[-1000:].mean()
    assert abs(late - early) <= 0.02 * e0
    # and it really moved: kinetic energy came and went
    assert sim.kinetic_energy() < e0 and max(energies) > 0


def test_explicit_above_critical_step_diverges_and_keeps_state():
    sim = cube_sim(gravity=(0, 0, 0), refinements=())
    squeezed_start(sim, 0.01)
    dt = 1.5 * sim.critical_dt()
    with pytest.raises(hg.SimulationDiverged) as info:
        for _ in range(5000):
            before = (sim.x.copy(), sim.v.copy(), sim.step_count)
            sim.step(dt, substeps=1)
    err = info.value
    assert err.step == before[2]
    assert err.elements.size > 0
    np.testing.assert_array_equal(sim.x, before[0])
    np.testing.assert_array_equal(sim.v, before[1])
    assert np.all(np.isfinite(sim.x))


def test_explicit_auto_substeps_stay_stable_at_frame_rate():
    sim = cube_sim(gravity=(0, 0, 0))
    squeezed_start(sim)
    e0 = sim.total_energy()
    for _ in range(30):
        stats = sim.step(1 / 30)
    assert stats.substeps >= (1 / 30) / sim.critical_dt()
    assert sim.total_energy() <= 1.05 * e0


def test_fixed_and_kinematic_vertices():
    mesh = hg.box_mesh((0.06, 0.02, 0.02), (6, 2, 2))
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0))
    held = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.06))
    sim = hg.Simulation(hg.HemlForce(mesh, M.NeoHookean(E=20e3, nu=0.4)), RHO, fixed=fixed,
                        integrator="explicit", damping=5.0)
    sim.attach(held)
    start = sim.x[held].copy()
    path = lambda t: start + np.array([0.0, 0.0, 0.01 * np.sin(2 * np.pi * t)])  # noqa: E731
    dt = 0.01
    for k in range(1, 51):
        sim.drive(held, path(k * dt))
        sim.step(dt)
        np.testing.assert_array_equal(sim.x[fixed], mesh.vertices[fixed])
        np.testing.assert_allclose(sim.x[held], path(k * dt), rtol=0, atol=1e-15)
    # the gripper feels the tissue: nonzero reaction
    assert np.linalg.norm(sim.reaction_forces(held).sum(axis=0)) > 0
    # release: the vertices now move on their own (fall and spring back)
    sim.detach(held)
    before = sim.x[held].copy()
    for _ in range(5):
        sim.step(dt)
    assert np.abs(sim.x[held] - before).max() > 1e-5
    assert not sim.kinematic.any()


def test_bad_arguments_raise():
    mesh = hg.box_mesh((0.02, 0.02, 0.02), 1)
    field = hg.HemlForce(mesh, M.NeoHookean(E=5e3, nu=0.45))
    with pytest.raises(ValueError, match="density"):
        hg.Simulation(field, -1.0)
    with pytest.raises(ValueError, match="integrator"):
        hg.Simulation(field, RHO, integrator="rk4")
    with pytest.raises(ValueError, match="Damping"):
        hg.Simulation(field, RHO, damping=hg.Damping(alpha=-1.0))
    sim = hg.Simulation(field, RHO, integrator="explicit", fixed=[0])
    with pytest.raises(ValueError, match="dt"):
        sim.step(float("nan"))
    with pytest.raises(ValueError, match="attach"):
        sim.drive([1], [[0, 0, 0]])
    with pytest.raises(ValueError, match="fixed"):
        sim.attach([0])
    sim.attach([1])
    with pytest.raises(ValueError, match="finite"):
        sim.drive([1], [[0, np.nan, 0]])


# ------------------------------------------------------------------------- implicit
def test_implicit_is_finite_and_dissipates_at_100x_critical_step():
    # solved tightly: an exact backward Euler step never gains energy (the default
    # tolerance leaves residual jitter of order newton_tol * E h^2 * h in the settled state)
    sim = cube_sim("implicit", gravity=(0, 0, 0), newton_tol=1e-9)
    squeezed_start(sim, 0.3)
    e0 = sim.total_energy()
    dt = 100 * sim.critical_dt()
    energies = []
    for _ in range(20):
        sim.step(dt)
        energies.append(sim.total_energy())
    assert np.all(np.isfinite(sim.x))
    assert np.all(np.diff(energies) <= 1e-12 * e0)  # backward Euler only loses energy
    assert energies[-1] < 0.05 * e0


@pytest.mark.parametrize("linear_solver", ["pcg", "direct"])
def test_implicit_default_tolerance_tracks_a_tight_solve(linear_solver):
    """The default inexact Newton (1e-3 of the weight, CG to 1e-2 with a lagged Cholesky
    preconditioner) stays on the trajectory of a 1e-10 solve: a sagging flap, 1/30 s steps."""
    mesh = hg.box_mesh((0.06, 0.06, 0.006), (6, 6, 1))
    clamp = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))

    def trajectory(**kw):
        sim = hg.Simulation(hg.HemlForce(mesh, M.NeoHookean(E=20e3, nu=0.43)), RHO, fixed=clamp,
                            linear_solver=linear_solver, **kw)
        out = []
        for _ in range(15):
            sim.step(1 / 30)
            out.append(sim.x.copy())
        return np.array(out)

    loose, tight = trajectory(), trajectory(newton_tol=1e-10)
    sag = -(tight[..., 2] - mesh.vertices[None, :, 2]).min()
    assert sag > 0.01  # a large deflection, not a linear one
    assert np.linalg.norm(loose - tight, axis=2).max() < 1e-3 * sag


def test_static_hanging_body_reaction_balances_weight():
    mesh = hg.box_mesh((0.03, 0.02, 0.05), (3, 2, 5))
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.05))
    sim = hg.Simulation(hg.HemlForce(mesh, M.NeoHookean(E=3e3, nu=0.45)), RHO, fixed=top)
    stats = sim.solve_static(load_steps=2)
    weight = sim.mass.sum() * 9.81
    f = sim.field.forces(sim.x) + sim.mass[:, None] * sim.gravity
    assert np.linalg.norm(f[sim.free]) <= 1e-8 * weight
    assert stats.residual <= 1e-8 * weight
    reaction = sim.reaction_forces(top).sum(axis=0)
    np.testing.assert_allclose(reaction, [0, 0, weight], rtol=0, atol=1e-9 * weight)
    assert sim.x[:, 2].min() < -1e-3  # it really sagged


def cantilever(cells, E=50e3, nu=0.45, law=M.NeoHookean, size=(0.10, 0.02, 0.02)):
    mesh = hg.box_mesh(size, cells)
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))
    sim = hg.Simulation(hg.HemlForce(mesh, law(E=E, nu=nu)), RHO, fixed=fixed)
    return mesh, sim


def test_static_cantilever_residual():
    mesh, sim = cantilever((10, 2, 2))
    sim.solve_static(load_steps=2)
    weight = sim.mass.sum() * 9.81
    f = sim.field.forces(sim.x) + sim.mass[:, None] * sim.gravity
    assert np.linalg.norm(f[sim.free]) <= 1e-8 * weight
    assert sim.x[:, 2].min() < -0.005  # a soft beam: large deflection


def test_stiff_cantilever_matches_timoshenko_beam_theory():
    """Small deflection under self weight: Euler-Bernoulli bending plus Timoshenko shear.

    Linear tets lock in bending and converge as h^2 (we measured 0.67, 0.79, 0.88, 0.93 of
    the theory from 480 to 30,720 tets), so the fine-mesh value is the Richardson
    extrapolation of two meshes, one twice as fine as the other in every direction.
    """
    length, side, E, nu = 0.10, 0.01, 5e8, 0.3
    area, inertia = side * side, side**4 / 12
    q = RHO * 9.81 * area  # N/m
    shear_modulus = E / (2 * (1 + nu))
    kappa = 10 * (1 + nu) / (12 + 11 * nu)  # rectangle
    tip = q * length**4 / (8 * E * inertia) + q * length**2 / (2 * kappa * shear_modulus * area)
    assert tip < 0.01 * side  # the small-deflection regime
    deflections = []
    for cells in [(40, 4, 4), (80, 8, 8)]:
        mesh, sim = cantilever(cells, E=E, nu=nu, size=(length, side, side))
        sim.solve_static()
        end = np.isclose(mesh.vertices[:, 0], length)
        deflections.append(-(sim.x[end, 2] - mesh.vertices[end, 2]).mean())
    coarse, fine = deflections
    assert coarse < fine < tip  # converging from below, as locking elements do
    extrapolated = fine + (fine - coarse) / 3.0
    assert extrapolated == pytest.approx(tip, rel=0.03)


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_heml_and_fem_trajectories_agree(integrator):
    """Same mesh, law and integrator: HEML (fused fast path) and F-FEM (generic path) coincide."""
    mesh = hg.box_mesh((0.04, 0.01, 0.01), (4, 1, 1))
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))
    mat = M.NeoHookean(E=20e3, nu=0.4)
    runs = []
    for field in (hg.HemlForce(mesh, mat), hg.FemForce(mesh, mat)):
        sim = hg.Simulation(field, RHO, fixed=fixed, integrator=integrator, damping=1.0)
        for _ in range(10):
            sim.step(1 / 60)
        runs.append(sim.x.copy())
    moved = np.abs(runs[0] - mesh.vertices).max()
    assert moved > 1e-4
    assert np.abs(runs[0] - runs[1]).max() <= 1e-8 * moved


def test_implicit_newton_keeps_iterating_far_from_convergence():
    """Regression: Newton must not give up after 5 slow iterations (it raised at step 2)."""
    mesh, sim = cantilever((15, 3, 3), E=5e3)
    dt = 100 * sim.critical_dt()
    weight = sim.mass.sum() * 9.81
    for _ in range(3):
        stats = sim.step(dt, substeps=1)
        assert np.all(np.isfinite(sim.x))
    assert stats.residual < weight


def test_implicit_step_with_a_grasp_that_would_invert_the_predictor():
    """Regression: driving the top layer 1 cm down in one step inverts the naive start."""
    mesh = hg.box_mesh((0.02, 0.02, 0.02), 4)
    bottom = np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.0))
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.02))
    sim = hg.Simulation(hg.HemlForce(mesh, M.NeoHookean(E=5e3, nu=0.45)), RHO, fixed=bottom)
    sim.attach(top)
    sim.drive(top, mesh.vertices[top] - [0.0, 0.0, 0.01])
    sim.step(0.1)
    j = hg.kinematics.volume_ratios(mesh, sim.x)
    assert j.min() > 0
    np.testing.assert_allclose(sim.x[top, 2], 0.01, atol=1e-12)
