"""A Young's modulus that varies over the body (``Model.set_stiffness_map``, the scenes'
``physics.stiffness_regions``, ``heml-gym calibrate --regions``): the mapped HEML field
against an independent FEM of each region on its own, the solvers on it, the calibration's
gradients in each region's modulus against central differences, and recovery of a tissue
whose two halves differ."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import scipy.sparse as sp

import heml_gym as hg
from heml_gym.agents.cli import main
from heml_gym.envs import ORGAN_RETRACTION, TISSUE_RETRACTION
from heml_gym.envs.observations import calibration_problem, record
from heml_gym.envs.scripted import scripted_policy
from heml_gym.materials import Demiray, MooneyRivlin, NeoHookean, StVenantKirchhoff
from heml_gym.mesh import box_regions
from heml_gym.model import rest_max_eigenvalue

from test_calibration import _random_loss_gradient_check

MESH = hg.box_mesh((0.04, 0.03, 0.01), (4, 3, 2))
REGION = box_regions(MESH, (2, 1, 1))  # two halves along x
RELATIVE = np.array([0.7, 2.5])


def _region_fem(mesh, region, law, E, nu, x):
    """Energy (J), forces (N) and exact Hessian (N/m) at ``x`` of each region's tets as a
    separate FEM body (``FemForce``: deformation gradients, not HEML's edges) of modulus
    ``E * RELATIVE[region]``, summed."""
    energy, forces, hessian = 0.0, np.zeros_like(x), 0
    for r, scale in enumerate(RELATIVE):
        tets = mesh.tets[region == r]
        used = np.unique(tets)
        index = np.full(mesh.n_vertices, -1)
        index[used] = np.arange(len(used))
        field = hg.Model(hg.TetMesh(mesh.vertices[used], index[tets]), law(E=E * scale, nu=nu), field="fem").field
        energy += field.energy(x[used])
        forces[used] += field.forces(x[used])
        rows = (3 * used[:, None] + np.arange(3)).ravel()
        pick = sp.csr_matrix((np.ones(rows.size), (np.arange(rows.size), rows)), shape=(rows.size, 3 * mesh.n_vertices))
        hessian = hessian + pick.T @ field.hessian(x[used], project=False) @ pick
    return energy, forces, hessian


@pytest.mark.parametrize("law", [NeoHookean, MooneyRivlin, Demiray, StVenantKirchhoff])
def test_a_mapped_heml_field_is_each_regions_fem_summed(law):
    """Energy, forces and Hessian of a HEML field whose modulus is 0.7 E on one half and
    2.5 E on the other equal those of two FEM bodies of those moduli, to rounding."""
    x = MESH.vertices + 4e-4 * np.random.default_rng(0).standard_normal(MESH.vertices.shape)
    model = hg.Model(MESH, law(E=5e3, nu=0.45), n_worlds=2)
    model.set_stiffness_map(RELATIVE[REGION])
    energy, forces, hessian = _region_fem(MESH, REGION, law, 5e3, 0.45, x)
    for field in model.fields:
        assert field.energy(x) == pytest.approx(energy, rel=1e-12)
        assert np.abs(field.forces(x) - forces).max() < 1e-12 * np.abs(forces).max()
        assert abs(field.hessian(x, project=False) - hessian).max() < 1e-12 * abs(hessian).max()


def test_removing_the_map_restores_the_uniform_body_bit_for_bit():
    x = MESH.vertices + 4e-4 * np.random.default_rng(1).standard_normal(MESH.vertices.shape)
    model = hg.Model(MESH, NeoHookean(E=5e3, nu=0.45))
    before = model.field.forces(x)
    model.set_stiffness_map(RELATIVE[REGION])
    assert not np.array_equal(model.field.forces(x), before)
    model.set_stiffness_map(None)
    assert model.stiffness_map is None and model.field.split
    assert np.array_equal(model.field.forces(x), before)


def _hanging_slab(integrator):
    """Where a slab clamped at x = 0, four times stiffer on its clamped half, hangs after 2 s
    of sagging under gravity (damped: it has come to rest); ``"static"``: its equilibrium."""
    mesh = hg.box_mesh((0.06, 0.02, 0.006), (6, 2, 1))
    model = hg.Model(mesh, NeoHookean(E=2e4, nu=0.4), fixed=mesh.vertices[:, 0] < 1e-9, damping=40.0)
    model.set_stiffness_map(np.array([4.0, 1.0])[box_regions(mesh, (2, 1, 1))])
    state, control = model.state(), model.control()
    if integrator == "static":
        hg.StaticSolver(model).solve(state, control)
        return state.x[0]
    solver = hg.solvers.make_solver(model, integrator, newton_tol=1e-6, max_iterations=200)
    for _ in range(40):
        solver.step(state, state, control, dt=0.05)
    return state.x[0]


def test_every_solver_steps_the_map_and_they_agree():
    """Newton's and the quasi-Newton backward Euler and the explicit solver (its critical
    step from the map's stiffest tet) come to rest where the static solver's equilibrium
    is, within 1 % of the sag; a uniform slab hangs elsewhere (a map that did nothing would
    not be told apart)."""
    rest = _hanging_slab("static")
    mesh = hg.box_mesh((0.06, 0.02, 0.006), (6, 2, 1))
    sag = np.abs(rest - mesh.vertices).max()
    assert sag > 1e-3
    for integrator in ("implicit", "quasi_newton", "explicit"):
        assert np.abs(_hanging_slab(integrator) - rest).max() < 0.01 * sag, integrator
    uniform = hg.Model(mesh, NeoHookean(E=2e4, nu=0.4), fixed=mesh.vertices[:, 0] < 1e-9)
    state = uniform.state()
    hg.StaticSolver(uniform).solve(state, uniform.control())
    assert np.abs(state.x[0] - rest).max() > 0.1 * sag


def test_the_critical_step_with_a_map_is_safe():
    """The explicit stability limit with a map is at most the mapped body's own (Lanczos on
    the mapped field) and within the stiffest tet's factor of it."""
    mesh = hg.box_mesh((0.06, 0.02, 0.006), (6, 2, 1))
    model = hg.Model(mesh, NeoHookean(E=3e3, nu=0.4))
    model.set_stiffness_map(np.array([1.0, 4.0])[box_regions(mesh, (2, 1, 1))])
    true = 2.0 / np.sqrt(rest_max_eigenvalue(model.field, model.mass))
    assert 0.5 * true <= model.critical_dt() <= true * (1 + 1e-6)


def test_regions_are_places_not_vertices():
    """The same 2 x 2 x 1 boxes on a coarse and a fine mesh of one slab hold a quarter of
    its volume each, and every tet's centre lies in its own box."""
    for cells in ((4, 4, 1), (9, 7, 2)):
        mesh = hg.box_mesh((0.08, 0.06, 0.01), cells)
        region = box_regions(mesh, (2, 2, 1))
        share = np.bincount(region, weights=mesh.volumes) / mesh.volumes.sum()
        assert share == pytest.approx([0.25] * 4, abs=0.07)
        centre = mesh.vertices[mesh.tets].mean(axis=1)
        assert np.all((centre[:, 0] >= 0.04) == (region % 2 == 1))
        assert np.all((centre[:, 1] >= 0.03) == (region >= 2))


@pytest.mark.slow
def test_law_auto_fits_every_law_per_region(tmp_path, capsys):
    """`--law auto --regions 2x1x1` on a uniform 5,000 Pa flap (a small one: 6 x 6 x 1
    cells, 8 steps, noise-free points and force): every law is fitted with E per half, and
    the kept law puts both halves within 3 % of the truth."""
    small = json.dumps({"scene": {"tissue": {"cells": [6, 6, 1]}}})
    obs = tmp_path / "obs.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(obs), "--steps", "8", "--points", "8", "--seed", "3",
                 "--young-modulus", "5000", "--env-kwargs", small]) == 0
    out = tmp_path / "fit"
    assert main(["calibrate", "-", str(obs), "--out", str(out), "--regions", "2x1x1", "--law", "auto",
                 "--env-kwargs", small, "--no-progress"]) == 0
    capsys.readouterr()
    record = json.loads((out / "fit.json").read_text())
    assert len(record["law_selection"]) == 5
    for r in record["law_selection"]:
        assert set(r["theta"]) == {"young_modulus_0", "young_modulus_1", "poisson_ratio"}
    assert record["regions"]["grid"] == [2, 1, 1]
    for name in ("young_modulus_0", "young_modulus_1"):
        assert record["parameters"][name]["value"] == pytest.approx(5000.0, rel=0.03)


def test_a_region_fit_colours_the_recorded_tissue_by_its_moduli():
    """fit.rrd's tissue colours: on a slab whose left half is fitted soft and right half
    stiff, vertices left of the middle are bluer than red, right of it redder than blue,
    and with equal moduli every vertex has one colour."""
    from heml_gym.agents.calibrate import region_colours

    mesh = hg.box_mesh((0.08, 0.06, 0.01), (8, 6, 1))
    colours = region_colours(mesh, box_regions(mesh, (2, 1, 1)), [3000.0, 7500.0]).astype(int)
    x = mesh.vertices[:, 0]
    left, right = x < 0.04 - 1e-9, x > 0.04 + 1e-9
    assert np.all(colours[left, 2] > colours[left, 0]) and np.all(colours[right, 0] > colours[right, 2])
    same = region_colours(mesh, box_regions(mesh, (2, 1, 1)), [5000.0, 5000.0])
    assert np.all(same == same[0])


@pytest.mark.parametrize("env_id, grid", [(TISSUE_RETRACTION, (2, 1, 1)), (ORGAN_RETRACTION, (1, 2, 1))])
def test_adjoint_gradients_in_each_regions_modulus(env_id, grid):
    """d/dE of each region and d/dnu of a loss on positions and jaw force, on both envs'
    scenes replaying their scripted retraction, against central differences."""
    env = gym.make(env_id, physics={"young_modulus": [5e3, 5e3]})
    obs = record(env, scripted_policy(env.unwrapped.scene), seed=2, steps=8, points=4)
    replay, _, names, _, _ = calibration_problem(gym.make(env_id), obs, ("young_modulus", "poisson_ratio"),
                                                 regions=grid)
    assert names == ["young_modulus_0", "young_modulus_1", "poisson_ratio"]
    _random_loss_gradient_check(replay, (4.5e3, 6e3, 0.44), (0.5, 0.5, 1e-5), np.random.default_rng(3))


@pytest.mark.slow
def test_two_halves_are_recovered_from_the_command_line_and_trained_on(tmp_path, capsys):
    """A flap whose halves are 3,000 and 7,500 Pa, observed (10 points and the jaws'
    force, noise-free, same mesh) and calibrated with --regions 2x1x1: each half within
    1 %; an env built from the fit draws E around their mean with the halves' ratio."""
    obs = tmp_path / "obs.npz"
    regions = {"physics": {"stiffness_regions": {"grid": [2, 1, 1], "relative": [0.6, 1.5]}}}
    assert main(["observe", TISSUE_RETRACTION, "--out", str(obs), "--young-modulus", "5000", "--steps", "20",
                 "--env-kwargs", json.dumps(regions)]) == 0
    out = tmp_path / "fit"
    assert main(["calibrate", "-", str(obs), "--out", str(out), "--regions", "2x1x1", "--no-progress"]) == 0
    record_ = json.loads((out / "fit.json").read_text())
    fitted = [record_["parameters"][f"young_modulus_{k}"]["value"] for k in range(2)]
    assert fitted == pytest.approx([3000.0, 7500.0], rel=0.01)
    assert record_["regions"]["grid"] == [2, 1, 1]
    env = gym.make(TISSUE_RETRACTION, physics={"fit": str(out / "fit.json")})
    env.reset(seed=0)
    model = env.unwrapped.task.model
    assert model.young_modulus[0] == pytest.approx(5250.0, rel=0.02)
    assert model.stiffness_map.max() / model.stiffness_map.min() == pytest.approx(2.5, rel=0.01)
    assert np.isfinite(env.step(env.action_space.sample())[1])


@pytest.mark.parametrize("physics, says", [
    ({"stiffness_regions": {"grid": [2, 1], "relative": [1, 1]}}, "grid: must be three integers"),
    ({"stiffness_regions": {"grid": [2, 1, 1], "relative": [1.0]}}, "relative: must be 2 positive numbers"),
    ({"stiffness_regions": {"grid": [2, 1, 1], "relative": [1.0, -1.0]}}, "relative: must be 2 positive numbers"),
    ({"stiffness_regions": {"relative": [1.0]}}, "must be {grid"),
    ({"stiffness_regions": {"grid": [2, 1, 1], "relative": [1, 2]}, "field": "fem",
      "integrator": "implicit"}, "needs field 'heml'")])
def test_bad_stiffness_regions_are_one_line_errors(physics, says):
    with pytest.raises(ValueError, match="physics.stiffness_regions") as info:
        gym.make(TISSUE_RETRACTION, physics=physics)
    assert says in str(info.value) and "\n" not in str(info.value)


def test_bad_maps_and_regions_are_one_line_errors(tmp_path, capsys):
    model = hg.Model(MESH, NeoHookean(E=5e3, nu=0.45))
    for bad in (np.ones(3), -np.ones(MESH.n_tets), np.full(MESH.n_tets, np.nan)):
        with pytest.raises(ValueError, match="relative stiffness"):
            model.set_stiffness_map(bad)
    with pytest.raises(ValueError, match="HEML force fields only"):
        hg.Model(MESH, NeoHookean(E=5e3, nu=0.45), field="fem").set_stiffness_map(np.ones(MESH.n_tets))
    obs = tmp_path / "obs.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(obs), "--steps", "3"]) == 0
    capsys.readouterr()
    for argv, says in ((["--regions", "2x1"], "--regions: boxes along x, y and z"),
                       (["--regions", "1x1x40"], "holds no tet's centre"),
                       (["--regions", "2x1x1", "--fit", "poisson_ratio"], "regions: fit young_modulus")):
        out = tmp_path / "never"
        assert main(["calibrate", "-", str(obs), "--out", str(out), "--no-progress", *argv]) == 2
        err = capsys.readouterr().err
        assert says in err and err.count("\n") == 1, err
        assert not out.exists()
