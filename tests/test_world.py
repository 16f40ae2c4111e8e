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
