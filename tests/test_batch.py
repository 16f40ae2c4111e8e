"""BatchedSimulation: N scenes in one call behave like N independent Simulations."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym.batch import BatchedSimulation
from heml_gym.materials import NeoHookean

MESH = hg.box_mesh((0.06, 0.03, 0.008), (4, 2, 1))
FIXED = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.0))
HELD = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.06))
STIFFNESS = [2e3, 3.5e3, 5e3, 2.7e3, 4.1e3, 2.2e3, 4.9e3, 3.3e3, 2.9e3]  # Pa, one per scene
DAMPING, DENSITY, GRAVITY = 5.0, 950.0, (0.0, 0.0, -9.81)


def reference(E, path, dt, substeps):
    """One scene stepped by Simulation (explicit), its held vertices driven along ``path``."""
    sim = hg.Simulation(hg.HemlForce(MESH, NeoHookean(E=E, nu=0.45)), DENSITY, gravity=GRAVITY,
                        fixed=FIXED, damping=DAMPING, integrator="explicit")
    sim.attach(HELD)
    xs, reactions = [], []
    for offset in path:
        sim.drive(HELD, MESH.vertices[HELD] + offset)
        sim.step(dt, substeps=substeps)
        xs.append(sim.x.copy())
        reactions.append(sim.reaction_forces(HELD).sum(axis=0))
    return np.array(xs), np.array(reactions)


@pytest.mark.parametrize("n_scenes", [2, len(STIFFNESS)])
def test_batched_scenes_equal_independent_simulations(n_scenes):
    dt, substeps = 0.05, 40
    rng = np.random.default_rng(n_scenes)
    paths = np.cumsum(rng.uniform(-1, 1, (n_scenes, 6, 3)) * 0.002, axis=1)  # m, per step
    batch = BatchedSimulation(MESH, n_scenes, young_modulus=STIFFNESS[:n_scenes], poisson=0.45,
                              density=DENSITY, gravity=GRAVITY, fixed=FIXED, damping=DAMPING)
    for s in range(n_scenes):
        batch.attach(s, HELD)
    xs, reactions = [], []
    for k in range(paths.shape[1]):
        for s in range(n_scenes):
            batch.drive(s, HELD, MESH.vertices[HELD] + paths[s, k])
        assert not batch.step(dt, substeps=substeps).any()
        xs.append(batch.x.copy())
        reactions.append(batch.reaction[:, HELD].sum(axis=1))
    xs, reactions = np.array(xs), np.array(reactions)
    for s in range(n_scenes):
        x_ref, r_ref = reference(STIFFNESS[s], paths[s], dt, substeps)
        assert np.abs(xs[:, s] - x_ref).max() < 1e-12  # m
        np.testing.assert_allclose(reactions[:, s], r_ref, rtol=1e-8, atol=1e-12)
        assert np.abs(x_ref[-1] - MESH.vertices).max() > 1e-3  # the scenes really moved


def test_inactive_and_diverged_scenes_keep_their_state():
    batch = BatchedSimulation(MESH, 3, young_modulus=[2e3, 3e3, 4e3], poisson=0.45, density=DENSITY,
                              gravity=GRAVITY, fixed=FIXED, damping=DAMPING)
    for s in range(3):
        batch.attach(s, HELD)
        batch.drive(s, HELD, MESH.vertices[HELD] + [0.0, 0.0, 0.004])
    batch.targets[2, HELD[0]] = [0.06, 0.0, -0.2]  # through the slab in one step: inverts tets
    before = batch.x.copy()
    diverged = batch.step(0.05, active=np.array([True, False, True]), substeps=30)
    assert diverged.tolist() == [False, False, True]
    np.testing.assert_array_equal(batch.x[1], before[1])  # inactive: not advanced
    np.testing.assert_array_equal(batch.x[2], before[2])  # diverged: rolled back
    assert np.abs(batch.x[0] - before[0]).max() > 1e-3 and np.all(np.isfinite(batch.x))


def test_floor_holds_the_tissue_up_in_both_kernels():
    """Held vertices pushed 5 mm below the support plane z = 0: the free vertices stay on or
    above it, and the batched kernel agrees with the one-scene kernel."""
    def run(n_scenes):
        batch = BatchedSimulation(MESH, n_scenes, young_modulus=STIFFNESS[:n_scenes], poisson=0.45,
                                  density=DENSITY, gravity=GRAVITY, fixed=FIXED, damping=DAMPING, floor=0.0)
        for s in range(n_scenes):
            batch.attach(s, HELD)
        for k in range(1, 6):
            for s in range(n_scenes):
                batch.drive(s, HELD, MESH.vertices[HELD] - [0.0, 0.0, 0.001 * k])
            assert not batch.step(0.05, substeps=40).any()
        return batch

    many = run(3)
    free = np.setdiff1d(np.arange(MESH.n_vertices), np.concatenate([FIXED, HELD]))
    assert many.x[:, free, 2].min() >= 0.0
    assert np.isclose(many.x[:, free, 2], 0.0).sum() > 0  # some rest on the plane
    np.testing.assert_allclose(many.x[0, HELD, 2], MESH.vertices[HELD, 2] - 0.005)  # held: driven through
    for s in range(3):
        one = BatchedSimulation(MESH, 1, young_modulus=STIFFNESS[s], poisson=0.45, density=DENSITY,
                                gravity=GRAVITY, fixed=FIXED, damping=DAMPING, floor=0.0)
        one.attach(0, HELD)
        for k in range(1, 6):
            one.drive(0, HELD, MESH.vertices[HELD] - [0.0, 0.0, 0.001 * k])
            one.step(0.05, substeps=40)
        assert np.abs(one.x[0] - many.x[s]).max() < 1e-12
