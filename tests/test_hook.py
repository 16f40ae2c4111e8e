"""The electrosurgical hook (envs/instruments/hook.py) on a world: it frees stuck tissue
where it touches, after the energy its spec states, counts what it puts into the rest as
collateral, does nothing in air or switched off, and the tissue it frees moves."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

from heml_gym.envs import TaskSettings, build_scene
from heml_gym.envs.instruments import Grasper, Hook
from heml_gym.envs.instruments.hook import surface_areas
from heml_gym.envs.scene import HookSpec
from heml_gym.envs.spec import SpecError
from heml_gym.envs.tissue_retraction import tissue_scene
from heml_gym.world import World

SETTINGS = TaskSettings()


def _world(stuck_to: float = 0.03):
    """The flap (no drawn adhesion), its underside stuck from the hinge to ``stuck_to`` (m)."""
    base = tissue_scene()
    scene = build_scene(dataclasses.replace(base, adhesion=None))
    world = World.from_physics(scene.mesh, scene.physics, 1, SETTINGS.control_dt, fixed=scene.fixed,
                               supports=scene.supports)
    world.reset(0)
    X = scene.mesh.vertices
    underside = np.flatnonzero((X[:, 2] == 0.0) & (X[:, 0] > 0.0) & (X[:, 0] <= stuck_to + 1e-9))
    world.stick(0, underside)
    return base, scene, world, underside


def test_surface_areas_sum_to_the_surface_and_a_vertex_takes_a_third_of_its_triangles():
    base, scene, world, _ = _world()
    area = surface_areas(scene.mesh.vertices, scene.surface_faces)
    size = np.ptp(scene.mesh.vertices, axis=0)
    total = 2 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    assert area.sum() == pytest.approx(total, rel=1e-12)
    assert np.all(area[np.unique(scene.surface_faces)] > 0)


def test_an_energised_hook_frees_the_stuck_vertices_within_reach_once_they_have_taken_their_energy():
    """The tip on the underside's stuck strip: the power is shared equally among the surface
    vertices within reach, so each stuck one is freed after ceil(E_A A_i / (P dt / k))
    steps, k the vertices within reach. Counted against that formula, step by step."""
    base, scene, world, underside = _world()
    spec = HookSpec(start_low=(0.0, 0.0, 0.0), start_high=(0.2, 0.2, 0.1), reach=0.011, power=30.0,
                    release_energy=2e5)
    hook = Hook(world, scene, SETTINGS, spec)
    X = scene.mesh.vertices
    tip = np.array([0.03, 0.06, 0.0])  # on the stuck strip's outer row (x = 10-30 mm stuck)
    hook.place(0, tip)
    surface = np.unique(scene.surface_faces)
    near = surface[np.linalg.norm(X[surface] - tip, axis=1) <= spec.reach]
    bonded = near[np.isin(near, underside)]
    assert bonded.size >= 2 and near.size > bonded.size  # stuck ones, and one beyond the strip
    dt = SETTINGS.control_dt
    steps_to_free = np.ceil(spec.release_energy * hook.area[bonded] / (spec.power * dt / near.size) - 1e-9)
    energise = np.array([[0.0, 0.0, 0.0, 1.0]])
    freed_at = {}
    for step in range(1, int(steps_to_free.max()) + 1):
        hook.act(energise)
        hook.burn(dt)  # (the world is not stepped: the tissue stays where it rests)
        for v in bonded[~world.stuck[0, bonded]]:
            freed_at.setdefault(int(v), step)
        # only the vertices within reach are freed, and they are no longer held
        assert world.stuck[0, underside[~np.isin(underside, near)]].all()
        assert not world.control.kinematic[0, [v for v in freed_at]].any()
    assert [freed_at[int(v)] for v in bonded] == steps_to_free.astype(int).tolist()
    assert hook.released_area[0] == pytest.approx(hook.area[bonded].sum(), rel=1e-12)


def test_collateral_energy_is_the_share_of_the_vertices_that_were_not_stuck_and_air_and_off_cost_nothing():
    base, scene, world, underside = _world()
    spec = HookSpec(start_low=(0.0, 0.0, 0.0), start_high=(0.2, 0.2, 0.1), reach=0.006)
    hook = Hook(world, scene, SETTINGS, spec)
    X = scene.mesh.vertices
    surface = np.unique(scene.surface_faces)
    dt = SETTINGS.control_dt
    for tip, energy in (((0.08, 0.06, 0.008), 1.0), ((0.08, 0.06, 0.05), 1.0), ((0.02, 0.06, 0.0), -1.0)):
        hook.place(0, tip)
        hook.act(np.array([[0.0, 0.0, 0.0, energy]]))
        hook.burn(dt)
        near = surface[np.linalg.norm(X[surface] - np.asarray(tip), axis=1) <= spec.reach]
        if energy > 0 and near.size:  # on the flap's top, nothing stuck: all of it collateral
            assert not np.isin(near, underside).any()
            assert hook.collateral[0] == pytest.approx(spec.power * dt, rel=1e-12)
        else:  # in air, or switched off
            assert hook.collateral[0] == 0.0 and hook.released[0] == 0
    assert world.stuck[0, underside].all()  # nothing was freed


def test_tissue_the_hook_frees_comes_away_when_pulled():
    """The flap grasped at its free edge and lifted while its underside is stuck near the
    hinge; the hook then frees the strip along the fold line: the freed underside lifts off
    the floor, where the still-stuck one in a second run stays on it."""
    lifted = {}
    for cut in (False, True):
        base, scene, world, underside = _world(stuck_to=0.02)
        grasper = Grasper(world, scene, SETTINGS, spec=base.gripper)
        grasper.place(0, (0.112, 0.06, 0.01))
        hook = Hook(world, scene, SETTINGS, HookSpec(start_low=(0.0, 0.0, 0.0), start_high=(0.2, 0.2, 0.1),
                                                     reach=0.012, release_energy=5e3))
        lift = np.array([[-0.4, 0.0, 1.0, 1.0]])
        for step in range(40):
            grasper.grasp(lift)
            grasper.move(lift)
            if cut and step >= 10:  # sweep the hook along the strip, energised
                hook.place(0, (0.015, 0.005 + 0.11 * (step - 10) / 29, 0.0))
                hook.act(np.array([[0.0, 0.0, 0.0, 1.0]]))
                hook.burn(SETTINGS.control_dt)
            stats = world.step(SETTINGS.control_dt)
            assert stats.converged.all()
            grasper.after_step(stats.reaction, ~stats.converged)
        lifted[cut] = world.state.x[0, underside, 2].max()
        if cut:
            assert hook.released_area[0] > 0.5 * hook.area[underside].sum()
    assert lifted[False] == 0.0  # (held where it rests)
    assert lifted[True] > 0.002  # m: freed, it comes away


@pytest.mark.parametrize("changes, message", [
    ({"reach": 0.0}, r"HookSpec\.reach: must be a positive number"),
    ({"power": float("nan")}, r"HookSpec\.power: must be a positive number"),
    ({"port": (0.01, 0.01, 0.01), "start_low": (0.0, 0.0, 0.0), "start_high": (0.1, 0.1, 0.1)},
     r"HookSpec\.port: .* lies inside the start box"),
])
def test_a_bad_hook_is_one_line_naming_it(changes, message):
    with pytest.raises(SpecError, match=message) as caught:
        HookSpec(**changes)
    assert "\n" not in str(caught.value)


HOOK = {"start_low": [0.015, 0.0, 0.0], "start_high": [0.015, 0.0, 0.0], "workspace_low": [-0.05, -0.05, 0.0],
        "workspace_high": [0.2, 0.17, 0.15], "reach": 0.012, "release_energy": 5e3}


def test_a_task_with_a_hook_takes_its_action_observes_it_and_frees_the_stuck_underside():
    """TissueRetraction with a hook in its scene: 4 more action entries, its tip and switch
    at the end of the state, gymnasium's checker passes; swept along the stuck strip,
    energised, it frees it, as ``info`` reports."""
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import heml_gym.envs as envs

    env = gym.make(envs.TISSUE_RETRACTION, scene={"hooks": {"hook": HOOK}})
    assert env.action_space.shape == (8,) and env.observation_space.shape == (24 + 4,)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=5, options={"adhesion_width": 0.02})
    task = env.unwrapped.task
    stuck = task.world.stuck[0].sum()
    assert stuck > 0 and info["hook_released_area"] == 0.0
    np.testing.assert_allclose(obs[-4:], [0.015, 0.0, 0.0, 0.0], atol=1e-7)
    sweep = np.array([0, 0, 0, -1, 0, 0.5, 0, 1], dtype=np.float32)  # grasper idle; hook along +y, energised
    freed = 0
    for _ in range(50):
        obs, _, _, _, info = env.step(sweep)
        freed += int(info["hook_released"])
    assert obs[-1] == 1.0 and freed == stuck - task.world.stuck[0].sum() and freed > 0.8 * stuck
    assert info["hook_released_area"] > 0 and info["hook_collateral_energy"] >= 0


def test_the_scripted_expert_leaves_the_hooks_off_and_still_succeeds():
    import gymnasium as gym

    import heml_gym.envs as envs
    from heml_gym.envs.scripted import HooksIdle, run_episodes, scripted_policy

    env = gym.make(envs.TISSUE_RETRACTION, scene={"hooks": {"hook": HOOK}})
    policy = scripted_policy(env.unwrapped.scene)
    assert isinstance(policy, HooksIdle)
    result = run_episodes(env, policy, 5, seed=62_000)
    assert sum(result["successes"]) >= 4, result


def test_the_task_camera_draws_the_hook_orange_when_energised():
    """A hook above the flap, in view of the task camera: its box is drawn, in the
    instrument's segment, orange while energised and grey while off."""
    import gymnasium as gym

    import heml_gym.envs as envs
    from heml_gym.envs.camera import SEGMENT_IDS
    from heml_gym.envs.palette import HOOK_ON

    above = dict(HOOK, start_low=[0.06, 0.09, 0.03], start_high=[0.06, 0.09, 0.03])
    env = gym.make(envs.TISSUE_RETRACTION, scene={"hooks": {"hook": above}}, obs_mode="rgbd")
    env.reset(seed=1)
    for energy, lit in ((1.0, True), (-1.0, False)):
        env.step(np.array([0, 0, 0, -1, 0, 0, 0, energy], dtype=np.float32))
        rgb, seg = env.unwrapped.camera_renderer.rgb[0], env.unwrapped.camera_renderer.segmentation[0, ..., 0]
        instrument = seg == SEGMENT_IDS["instrument"]
        # the lit box's pixels are shades of its colour: their hue is the colour's
        hue = rgb[instrument].astype(float) / np.maximum(rgb[instrument].max(axis=1, keepdims=True), 1)
        orange = np.abs(hue - np.asarray(HOOK_ON, dtype=float) / max(HOOK_ON)).max(axis=1) < 0.05
        assert orange.any() == lit  # orange pixels while energised only (the grasper's jaws are grey)
        assert instrument.sum() > orange.sum() > 0 if lit else instrument.any()


def test_a_hook_placed_outside_its_workspace_is_one_line_naming_it():
    env = gym.make("heml_gym/GallbladderDissection-v0")
    env.reset(seed=0)
    hook = env.unwrapped.task.hooks[0]
    for bad, message in (((0.0, 0.0, -0.01), r"^hook: \[0\.0, 0\.0, -0\.01\] lies outside the workspace"),
                         ((0.0, np.nan, 0.0), r"^hook: must be 3 finite coordinates")):
        with pytest.raises(SpecError, match=message) as caught:
            hook.place(0, bad)
        assert "\n" not in str(caught.value)
