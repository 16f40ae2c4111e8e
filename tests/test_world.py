"""heml_gym.World: the physics a task stands on (model, solver, state, control, adhesion,
hold springs), checked against independent truth."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym.world import HOLD_SPRING_SCALE, World

SLAB = hg.box_mesh((0.06, 0.04, 0.008), (6, 4, 1))


def physics(integrator="quasi_newton"):
    from heml_gym.envs import PhysicsSpec

    return PhysicsSpec(material="NeoHookean", young_modulus=(4e3, 6e3), density=950.0, damping=0.0,
                       integrator=integrator, max_dt=0.05)


def test_hold_springs_are_the_share_over_its_rest_times_the_tissues_own_stiffness():
    """A vertex held with share w gets HOLD_SPRING_SCALE w / (1 - w) times its mean diagonal
    rest stiffness, here measured by central differences of the elastic forces."""
    world = World.from_physics(SLAB, physics(), 2, 0.1, fixed=np.flatnonzero(SLAB.vertices[:, 0] == 0))
    field = world.model.fields[1]
    X = SLAB.vertices
    v, h = 17, 1e-7
    diagonal = []
    for axis in range(3):
        d = np.zeros_like(X)
        d[v, axis] = h
        diagonal.append(-(field.forces(X + d)[v, axis] - field.forces(X - d)[v, axis]) / (2 * h))
    share = np.array([1.0, 0.5, 0.25])
    k = world.hold_stiffness(1, np.array([v, v, v]), share)
    assert k[0] == 0.0  # a whole share is held exactly
    expected = HOLD_SPRING_SCALE * np.mean(diagonal) * share[1:] / (1 - share[1:])
    np.testing.assert_allclose(k[1:], expected, rtol=1e-5)


@pytest.mark.parametrize("integrator", ["quasi_newton", "explicit"])
def test_stuck_tissue_stays_where_it_rests_and_falls_once_released(integrator):
    """Under gravity, with nothing fixed, the stuck vertices stay put and the rest sag;
    unstuck, the whole slab falls freely (its centre of mass by g t^2 / 2 within damping)."""
    world = World.from_physics(SLAB, physics(integrator), 1, 0.05)
    stuck = np.flatnonzero(SLAB.vertices[:, 0] <= 0.01)
    world.reset(0)
    world.stick(0, stuck)
    for _ in range(4):
        stats = world.step(0.05)
        assert stats.converged.all() and not stats.diverged.any()
    np.testing.assert_array_equal(world.x[0, stuck], SLAB.vertices[stuck])
    assert world.x[0, :, 2].min() < -1e-4  # the free end sags
    world.unstick(0)
    assert not world.stuck.any() and not world.control.kinematic.any()
    z0 = world.x[0, :, 2].mean()
    v0 = world.state.v[0, :, 2].mean()
    t = 0.1
    for _ in range(2):
        world.step(0.05)
    fall = z0 + v0 * t - 0.5 * 9.81 * t ** 2
    assert world.x[0, :, 2].mean() == pytest.approx(fall, abs=0.15 * 0.5 * 9.81 * t ** 2 + 1e-4)


def test_two_graspers_on_one_world_share_a_symmetric_load_and_never_take_each_others_tissue():
    """Instruments compose on one world: two graspers with 40 mm weighted jaws close on the
    flap's free edge at mirror places (y = 30 and 90 mm on the mirror-symmetric 120 mm
    flap) and lift it together. By symmetry they hold mirror sets of vertices and feel the
    same force; a third closing on held tissue takes nothing."""
    import dataclasses

    from heml_gym.envs import TaskSettings, build_scene
    from heml_gym.envs.instruments import Grasper
    from heml_gym.envs.tissue_retraction import tissue_scene

    base = tissue_scene()
    scene = build_scene(dataclasses.replace(base, adhesion=None))
    settings = TaskSettings()
    world = World.from_physics(scene.mesh, scene.physics, 1, settings.control_dt, fixed=scene.fixed,
                               supports=scene.supports)
    world.reset(0)
    jaws = dataclasses.replace(base.gripper, jaw_length=0.04, jaw_ends="weighted")
    graspers = [Grasper(world, scene, settings, name=f"g{k}", spec=jaws) for k in range(3)]
    for g, y in zip(graspers, (0.03, 0.09, 0.03)):
        g.place(0, (0.112, y, 0.01))
    close_and_lift = np.array([[0.0, 0.0, 1.0, 1.0]])
    for _ in range(6):
        for g in graspers[:2]:
            g.grasp(close_and_lift)
        for g in graspers[:2]:
            g.move(close_and_lift)
        stats = world.step(settings.control_dt)
        assert stats.converged.all()
        for g in graspers[:2]:
            g.after_step(stats.reaction, ~stats.converged)
    left, right = (np.flatnonzero(g.held[0]) for g in graspers[:2])
    assert left.size and right.size and not np.intersect1d(left, right).size
    X = scene.mesh.vertices
    mirror = np.array([0.12, 0.12, 0.0]) * [0, 1, 0] + X * [1, -1, 1]  # y -> 120 mm - y
    assert np.allclose(np.sort(mirror[left][:, 1]), np.sort(X[right][:, 1]))
    f_left, f_right = (np.linalg.norm(g.force[0]) for g in graspers[:2])
    assert f_left > 0.05 and f_left == pytest.approx(f_right, rel=1e-3)
    graspers[2].position[0] = graspers[0].position[0]  # right where the first grasper holds the tissue
    assert graspers[2]._reached_vertices(0)[0].size  # within reach of it
    graspers[2].grasp(close_and_lift)
    assert not graspers[2].held.any() and not graspers[2].grasping[0]
