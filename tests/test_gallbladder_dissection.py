"""GallbladderDissection: a grasper retracts the fundus, a hook frees the neck from its bed,
to the critical view of safety. Conformance, the scripted expert on seeds nobody trained
on, the critical structure (energy near it is charged and ends the episode), the release
measure against an independent count, the sac's mesh, and the contract for bad input."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import heml_gym.envs as envs
from heml_gym.envs.gallbladder_dissection import (LOWER_THIRD, DissectionSettings, GallbladderDissectionEnv,
                                                  dissection_scene)
from heml_gym.envs.instruments.hook import surface_areas
from heml_gym.envs.scene import StructureSpec
from heml_gym.envs.scripted import run_episodes, scripted_policy
from heml_gym.envs.spec import SpecError
from heml_gym.organs import gallbladder_mesh

HELD_OUT = 31_000  # episode seeds no training, evaluation or stored result uses
HOOK = slice(4, 8)  # the hook's entries in the action


@pytest.mark.parametrize("obs_mode", ["state", "pointcloud"])
def test_gymnasium_and_sb3_env_checkers_pass(obs_mode):
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(GallbladderDissectionEnv(obs_mode=obs_mode), skip_render_check=True)
    sb3_check_env(GallbladderDissectionEnv(obs_mode=obs_mode), warn=True)


def test_scripted_expert_succeeds_on_nine_of_ten_held_out_seeds():
    env = gym.make(envs.GALLBLADDER_DISSECTION)
    result = run_episodes(env, scripted_policy(env.unwrapped.scene), 10, seed=HELD_OUT)
    assert sum(result["successes"]) >= 9, result


def test_the_sac_lies_in_its_bed_with_its_neck_at_the_origin():
    mesh = gallbladder_mesh()
    v = mesh.vertices
    assert v[:, 0].min() == pytest.approx(0.0, abs=1e-9) and v[:, 0].max() == pytest.approx(0.085, abs=1e-4)
    assert v[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    a, b, c, d = (v[mesh.tets[:, k]] for k in range(4))
    assert np.all(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) > 0)  # every tet positively oriented
    underside = v[np.abs(v[:, 2]) < 1e-9]
    assert underside[:, 0].min() < 0.002 and underside[:, 0].max() > 0.07  # it rests in its bed from neck to fundus
    with pytest.raises(ValueError, match="bed_depth"):
        gallbladder_mesh(bed_depth=0.02)


def _sweep(env, seed, hook_y=0.0, steps=60):
    """Energise the hook and sweep it along the stuck strip (the grasper idle)."""
    obs, info = env.reset(seed=seed)
    for _ in range(steps):
        tip = env.task.hooks[0].position[0]
        action = np.zeros(8, dtype=np.float32)
        action[HOOK] = [-0.1 if tip[0] > 0.004 else 0.0, np.clip((hook_y - tip[1]) * 200, -1, 1),
                        np.clip((0.0005 - tip[2]) * 200, -1, 1), 1.0]
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    return obs, info


def test_the_released_fraction_is_the_freed_share_of_the_lower_thirds_stuck_area():
    """Independent count: from the world's own stuck set and the rest mesh's triangle areas."""
    env = GallbladderDissectionEnv()
    obs, info = _sweep(env, HELD_OUT)
    t = env.task
    mesh = t.scene.mesh
    area = surface_areas(mesh.vertices, mesh.boundary_faces)
    lower = t.stuck_at_start[0] & (mesh.vertices[:, 0] <= LOWER_THIRD)
    freed = lower & ~t.world.stuck[0]
    expected = area[freed].sum() / area[lower].sum()
    assert 0.2 < expected < 1.0  # the sweep freed part of it
    assert info["released_fraction"] == pytest.approx(expected)
    assert obs[24] == pytest.approx(expected, abs=1e-6)
    assert info["hook_released_area"] >= area[freed].sum() * (1 - 1e-9)  # (it may free beyond the lower third)
    assert not info["is_success"]  # freed, but the ducts are still hidden


def test_energy_near_the_critical_structure_is_charged_and_ends_the_episode():
    env = GallbladderDissectionEnv()
    env.reset(seed=HELD_OUT)
    critical = env.scene.critical
    steps = 0
    while True:  # drive the hook, energised, towards the common bile duct
        tip = env.task.hooks[0].position[0]
        goal = np.array(critical.start) * 0.5 + np.array(critical.end) * 0.5 + [0.0, 0.0, 0.004]
        action = np.zeros(8, dtype=np.float32)
        action[HOOK] = [*np.clip((goal - tip) * 20, -1, 1), 1.0]
        _, reward, terminated, truncated, info = env.step(action)
        steps += 1
        near = critical.distance(env.task.hooks[0].position[0][None])[0] <= critical.margin
        assert info["critical_hit"] == near
        if terminated or truncated:
            break
    assert info["critical_hit"] and terminated and not truncated and steps < 60
    settings = DissectionSettings()
    assert info["hook_cost"] >= settings.critical_cost and info["cost"] >= settings.critical_cost
    assert info["reward_critical"] == -env.task.weights.critical and not info["is_success"]


def test_the_same_path_switched_off_near_the_critical_structure_costs_nothing_there():
    env = GallbladderDissectionEnv()
    env.reset(seed=HELD_OUT)
    critical = env.scene.critical
    for _ in range(40):
        tip = env.task.hooks[0].position[0]
        goal = np.array(critical.start) * 0.5 + np.array(critical.end) * 0.5 + [0.0, 0.0, 0.004]
        action = np.zeros(8, dtype=np.float32)
        action[HOOK] = [*np.clip((goal - tip) * 20, -1, 1), -1.0]
        _, _, terminated, _, info = env.step(action)
        assert not info["critical_hit"] and not terminated and info["hook_cost"] == 0.0


def test_the_structures_distance_is_to_its_cylinder():
    s = StructureSpec(start=(0.0, -0.03, 0.0), end=(0.0, 0.03, 0.0), radius=0.003, margin=0.005)
    points = np.array([[0.01, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.001]])
    np.testing.assert_allclose(s.distance(points), [0.007, 0.02 - 0.003, -0.002], atol=1e-12)


@pytest.mark.parametrize("changes, message", [
    ({"critical": {"radius": -1.0}}, "radius"),
    ({"critical": {"start": [0.0, 0.0, 0.0], "end": [0.0, 0.0, 0.0]}}, "start"),
    ({"critical": None}, "critical"),
    ({"hooks": None}, "hook"),
])
def test_bad_dissection_scenes_are_one_line_naming_the_field(changes, message):
    with pytest.raises(SpecError, match=message) as err:
        GallbladderDissectionEnv(scene=changes)
    assert "\n" not in str(err.value)


def test_bad_dissection_settings_are_one_line():
    for kwargs, name in (({"release_fraction": 0.0}, "release_fraction"), ({"critical_cost": -1.0}, "critical_cost")):
        with pytest.raises(SpecError, match=name):
            DissectionSettings(**kwargs)


def test_the_shipped_scene_file_is_the_envs_default():
    from pathlib import Path

    from heml_gym.envs.scene import Scene

    root = Path(__file__).resolve().parents[1]
    assert Scene.load(root / "configs" / "scenes" / "gallbladder_dissection.yaml") == dissection_scene()


def test_the_grasper_is_reported_by_name_and_in_the_sums_the_tools_read():
    env = GallbladderDissectionEnv()
    _, info = env.reset(seed=HELD_OUT)
    assert env.instruments == ("grasper",) and env.task.hooks[0].name == "hook"
    action = np.zeros(8, dtype=np.float32)
    action[3] = 1.0  # close the jaws on the fundus
    _, _, _, _, info = env.step(action)
    assert info["grasper_grasping"] and info["grasping"]
    assert info["grasp_force"] == pytest.approx(info["grasper_grasp_force"]) and info["grasp_force"] > 0


def test_an_evaluation_counts_how_its_episodes_end():
    """A policy that drives the energised hook to the common bile duct ends every episode
    there; one that does nothing runs out of time; their counts say so."""
    from heml_gym.agents.evaluation import evaluate_policy

    critical = dissection_scene().critical
    goal = np.array(critical.start) * 0.5 + np.array(critical.end) * 0.5 + [0.0, 0.0, 0.004]

    def to_the_duct(obs):
        action = np.zeros(8, dtype=np.float32)
        action[HOOK] = [*np.clip((goal - obs[25:28]) * 20, -1, 1), 1.0]  # the hook's tip is state 25-27
        return action

    kwargs = {"settings": {"max_steps": 60}}
    hit = evaluate_policy(to_the_duct, "heml_gym/GallbladderDissection-v0", 3, seed=HELD_OUT, env_kwargs=kwargs)
    assert hit["endings"]["critical"] == 3 and sum(hit["endings"].values()) == 3
    idle = evaluate_policy(lambda obs: np.zeros(8, dtype=np.float32), "heml_gym/GallbladderDissection-v0", 2,
                           seed=HELD_OUT, env_kwargs={"settings": {"max_steps": 5}})
    assert idle["endings"]["time"] == 2 and sum(idle["endings"].values()) == 2
