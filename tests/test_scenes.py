"""Scenes as data (YAML round trips, validation naming the field) and every law and
integrator inside both environments through ``physics=``."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import heml_gym.envs  # noqa: F401
from heml_gym import materials as M
from heml_gym.envs import Scene, SpecError, build_scene, check_env_kwargs
from heml_gym.envs.organ_retraction import organ_scene
from heml_gym.envs.bimanual_retraction import bimanual_scene
from heml_gym.envs.tissue_manipulation import manipulation_scene
from heml_gym.envs.tissue_retraction import TissueRetractionEnv, tissue_scene

from env_checks import assert_random_steps_stay_finite

ROOT = Path(__file__).resolve().parents[1]
TISSUE, ORGAN = "heml_gym/TissueRetraction-v1", "heml_gym/OrganRetraction-v2"
LAWS = [cls.__name__ for cls in M.ALL_MATERIALS]


@pytest.mark.parametrize("make", [tissue_scene, organ_scene, bimanual_scene, manipulation_scene])
def test_a_scene_survives_a_yaml_round_trip(make, tmp_path):
    scene = make()
    again = Scene.load(scene.save(tmp_path / "scene.yaml"))
    assert again == scene
    a, b = build_scene(scene), build_scene(again)
    for name in ("fixed", "tracked", "edge_vertices", "grasp_patch", "marker"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize("name, make", [("tissue_retraction", tissue_scene), ("organ_retraction", organ_scene),
                                        ("bimanual_retraction", bimanual_scene),
                                        ("tissue_manipulation", manipulation_scene)])
def test_the_shipped_scene_files_are_the_envs_defaults(name, make):
    assert Scene.load(ROOT / "configs" / "scenes" / f"{name}.yaml") == make()


def test_a_scene_file_drives_the_env(tmp_path):
    path = tissue_scene().updated({"tissue": {"cells": [4, 4, 1]}, "physics": {"young_modulus": [5e3, 5e3]}}).save(
        tmp_path / "coarse.yaml")
    env = gym.make(TISSUE, scene=str(path))
    _, info = env.reset(seed=0)
    assert env.unwrapped.task.scene.mesh.n_tets == 4 * 4 * 6 and info["young_modulus"] == 5e3


@pytest.mark.parametrize("kwargs, field", [
    ({"physics": {"integrator": "rk4"}}, "physics.integrator"),
    ({"physics": {"material": "Rubber"}}, "physics.material"),
    ({"physics": {"young_modulus": [8e3, 4e3]}}, "physics.young_modulus"),
    ({"physics": {"poisson": 0.5}}, "physics.poisson"),
    ({"physics": {"field": "mass_tensor"}}, "physics.field"),
    ({"physics": {"material_options": {"b": -1.0}, "material": "Demiray"}}, "physics.material_options"),
    ({"physics": {"safety": 1.5}}, "physics.safety"),
    ({"physics": {"scheme": "rk4"}}, "physics.scheme"),
    ({"physics": {"hessian_scale": 0}}, "physics.hessian_scale"),
    ({"physics": {"scheme": "bdf2", "integrator": "explicit"}}, "physics.scheme"),
    ({"physics": {"materal": "NeoHookean"}}, "physics.materal"),
    ({"physics": "implicit"}, "physics"),
    ({"scene": {"tissue": {"cells": [0, 4, 1]}}}, "scene.tissue.cells"),
    ({"scene": {"target": {"radius": -0.01}}}, "scene.target.radius"),
    ({"scene": {"camera": {"fov_y": 200}}}, "scene.camera.fov_y"),
    ({"scene": {"gripper": {"start_low": [1, 1]}}}, "scene.gripper.start_low"),
    ({"scene": {"support": {"kind": "table"}}}, "scene.support.kind"),
    ({"scene": {"strain_gauge": "long"}}, "scene.strain_gauge"),
    ({"scene": 3}, "scene"),
    ({"settings": {"max_stepz": 5}}, "settings.max_stepz"),
])
def test_bad_scene_and_physics_fields_fail_naming_the_field(kwargs, field):
    with pytest.raises(SpecError, match="^" + field.replace(".", r"\.").replace("[", r"\[")):
        gym.make(TISSUE, **kwargs)
    with pytest.raises(SpecError, match=field.replace(".", r"\.")):  # and before anything is built
        check_env_kwargs(TISSUE, kwargs)


def test_env_kwargs_check_rejects_unknown_and_reserved_arguments():
    with pytest.raises(SpecError, match=r"env\.kwargs\.colour: not an argument"):
        check_env_kwargs(TISSUE, {"colour": "red"})
    with pytest.raises(SpecError, match=r"env\.kwargs\.obs_mode"):
        check_env_kwargs(TISSUE, {"obs_mode": "state"})
    assert check_env_kwargs(ORGAN, {"mesh_size": 0.01}).tissue.mesh_size == 0.01


@pytest.mark.parametrize("env_id", [TISSUE, ORGAN])
@pytest.mark.parametrize("law", LAWS)
@pytest.mark.parametrize("integrator", ["explicit", "implicit", "quasi_newton"])
def test_every_law_and_integrator_runs_in_both_envs(env_id, law, integrator):
    """50 random env steps (grasps, releases, pulls) with finite observations and rewards;
    the organ on a 12 mm mesh to keep the suite short."""
    size = {"mesh_size": 0.012} if env_id == ORGAN else {}
    env = gym.make(env_id, physics={"material": law, "integrator": integrator}, **size)
    task = env.unwrapped.task
    assert type(task.model.materials[0]).__name__ == law
    assert type(task.solver).__name__ == {"explicit": "ExplicitSolver", "implicit": "ImplicitSolver",
                                          "quasi_newton": "QuasiNewtonSolver"}[integrator]
    assert_random_steps_stay_finite(env, 50, seed=0)


def test_a_vector_env_equals_single_envs_for_another_law_and_integrator():
    physics = {"material": "StVenantKirchhoff", "integrator": "implicit"}
    vec = gym.make_vec(TISSUE, num_envs=3, vectorization_mode="vector_entry_point", physics=physics)
    obs, _ = vec.reset(seed=20)
    rng = np.random.default_rng(3)
    actions = rng.uniform(-1, 1, (12, 3, 4)).astype(np.float32)
    actions[:, :, 3] = 1.0  # grasp and pull: the implicit solve has work to do
    trajectory = [obs]
    for a in actions:
        trajectory.append(vec.step(a)[0])
    for i in range(3):
        env = TissueRetractionEnv(physics=physics)
        obs, _ = env.reset(seed=20 + i)
        np.testing.assert_allclose(obs, trajectory[0][i], atol=1e-6)
        for k, a in enumerate(actions):
            obs, _, terminated, truncated, _ = env.step(a[i])
            np.testing.assert_allclose(obs, trajectory[k + 1][i], atol=1e-6)
            if terminated or truncated:
                break


def test_the_organ_vector_env_equals_single_envs_on_its_default_physics():
    """Three lobes stepped together (L-BFGS, scenes over threads) equal three single envs
    (the serial kernel), step for step, through grasps and pulls."""
    from heml_gym.envs.organ_retraction import OrganRetractionEnv

    vec = gym.make_vec(ORGAN, num_envs=3, vectorization_mode="vector_entry_point", mesh_size=0.012)
    obs, _ = vec.reset(seed=40)
    rng = np.random.default_rng(5)
    actions = rng.uniform(-1, 1, (12, 3, 4)).astype(np.float32)
    actions[:, :, 3] = 1.0
    trajectory = [obs]
    for a in actions:
        trajectory.append(vec.step(a)[0])
    for i in range(3):
        env = OrganRetractionEnv(mesh_size=0.012)
        obs, _ = env.reset(seed=40 + i)
        np.testing.assert_allclose(obs, trajectory[0][i], atol=1e-6)
        for k, a in enumerate(actions):
            obs, _, terminated, truncated, _ = env.step(a[i])
            np.testing.assert_allclose(obs, trajectory[k + 1][i], atol=1e-6)
            if terminated or truncated:
                break


def test_bdf2_vector_env_equals_single_envs_and_a_reset_forgets_the_history():
    """BDF2 keeps each scene's state one step back: scenes stepped together in a vector
    env equal single envs, and an episode started again with its seed repeats itself."""
    physics = {"scheme": "bdf2"}
    vec = gym.make_vec(TISSUE, num_envs=2, vectorization_mode="vector_entry_point", physics=physics)
    assert vec.unwrapped.task.solver.scheme == "bdf2"
    obs, _ = vec.reset(seed=30)
    rng = np.random.default_rng(4)
    actions = rng.uniform(-1, 1, (10, 2, 4)).astype(np.float32)
    actions[:, :, 3] = 1.0
    trajectory = [vec.step(a)[0] for a in actions]
    env = TissueRetractionEnv(physics=physics)
    for i in range(2):
        for _ in range(2):  # the second time after an episode on the same solver
            env.reset(seed=30 + i)
            for k, a in enumerate(actions):
                obs, _, terminated, truncated, info = env.step(a[i])
                assert info["solver_converged"]
                np.testing.assert_allclose(obs, trajectory[k][i], atol=1e-9)


def test_physics_changes_reach_the_model():
    env = TissueRetractionEnv(physics={"material": "Demiray", "material_options": {"b": 3.0}, "poisson": 0.4,
                                       "young_modulus": [6e3, 6e3], "field": "fem", "density": 1100.0,
                                       "integrator": "explicit"})
    env.reset(seed=0)
    model = env.task.model
    mat = model.materials[0]
    assert isinstance(mat, M.Demiray) and mat.b == 3.0
    assert mat.young_modulus == pytest.approx(6e3) and mat.poisson_ratio == pytest.approx(0.4)
    assert type(model.field).__name__ == "FemForce" and model.density == 1100.0
    # the caller's default scene is untouched
    assert tissue_scene().physics.material == "NeoHookean"
