"""The task suite beyond the two retraction tasks: bimanual retraction (two graspers) and
goal-conditioned tissue manipulation. Conformance, the physics each rests on, the
scripted experts on seeds nobody trained on, and the contract for bad input."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import heml_gym.envs as envs
from heml_gym.envs.bimanual_retraction import BimanualRetractionEnv, BimanualRetractionVectorEnv, bimanual_scene
from heml_gym.envs.scripted import run_episodes, scripted_policy
from heml_gym.envs.spec import SpecError
from heml_gym.envs.tissue_manipulation import TissueManipulationEnv, TissueManipulationVectorEnv

HELD_OUT = 31_000  # episode seeds no training, evaluation or stored result uses


@pytest.mark.parametrize("env_class", [BimanualRetractionEnv, TissueManipulationEnv])
@pytest.mark.parametrize("obs_mode", ["state", "pointcloud"])
def test_gymnasium_and_sb3_env_checkers_pass(env_class, obs_mode):
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(env_class(obs_mode=obs_mode), skip_render_check=True)
    sb3_check_env(env_class(obs_mode=obs_mode), warn=True)


@pytest.mark.parametrize("env_id", [envs.BIMANUAL_RETRACTION, envs.TISSUE_MANIPULATION])
def test_scripted_expert_succeeds_on_nine_of_ten_held_out_seeds(env_id):
    env = gym.make(env_id)
    result = run_episodes(env, scripted_policy(env.unwrapped.scene), 10, seed=HELD_OUT)
    assert sum(result["successes"]) >= 9, result


# ------------------------------------------------------------------ bimanual
def test_one_grasper_with_the_tasks_jaws_strains_the_flap_past_damage_where_two_do_not():
    """The task's premise, on three held-out seeds: one grasper's scripted fold at the
    middle of the free edge exceeds the damage strain (so it cannot succeed), the two
    graspers' stays below it and succeeds."""
    scene = bimanual_scene()
    left = scene.graspers["left"]
    mid = scene.tissue.size[1] / 2
    one = dataclasses.replace(left, start_low=(left.start_low[0], mid - 0.005, left.start_low[2]),
                              start_high=(left.start_high[0], mid + 0.005, left.start_high[2]))
    single = dataclasses.replace(scene, gripper=one, graspers={"middle": one})
    damage = BimanualRetractionEnv().task.settings.damage_strain
    for spec, should_succeed in ((scene, True), (single, False)):
        env = BimanualRetractionEnv(scene=spec)
        policy = scripted_policy(spec)
        for seed in range(HELD_OUT, HELD_OUT + 3):
            obs, info = env.reset(seed=seed)
            policy.reset()
            peak, done = 0.0, False
            while not done:
                obs, _, terminated, truncated, info = env.step(policy(obs))
                peak, done = max(peak, info["max_strain"]), terminated or truncated
            assert info["is_success"] == should_succeed, (spec.graspers, seed)
            assert (peak < damage) == should_succeed, peak


def test_two_graspers_are_each_observed_and_reported_by_name():
    env = BimanualRetractionEnv()
    obs, info = env.reset(seed=HELD_OUT)
    assert env.action_space.shape == (8,) and obs.shape == (31,)
    assert env.instruments == ("left", "right")
    t = env.task
    np.testing.assert_allclose(obs[0:3], t.instruments[0].position[0], atol=1e-6)
    np.testing.assert_allclose(obs[7:10], t.instruments[1].position[0], atol=1e-6)
    # close the left jaws only: the left grasps, the right does not, the sum is the left's
    obs, _, _, _, info = env.step(np.array([0, 0, 0, 1, 0, 0, 0, 0], dtype=np.float32))
    assert info["left_grasping"] and not info["right_grasping"] and info["grasping"]
    assert obs[3] == 1.0 and obs[10] == 0.0
    assert info["grasp_force"] == pytest.approx(info["left_grasp_force"] + info["right_grasp_force"])


def test_a_wrong_action_shape_names_the_shape_a_two_grasper_task_takes():
    env = BimanualRetractionEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(8,\)"):
        env.step(np.zeros(4, dtype=np.float32))
    vec = BimanualRetractionVectorEnv(num_envs=2)
    vec.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(2, 8\)"):
        vec.step(np.zeros((2, 4), dtype=np.float32))


@pytest.mark.parametrize("changes, message", [
    ({"graspers": {"left": {"jaw_lenght": 0.03}}}, r"scene\.graspers\.left\.jaw_lenght: unknown field"),
    ({"graspers": {"left": {"jaw_ends": "glued"}}}, r"scene\.graspers\.left\.jaw_ends"),
    ({"graspers": {"left hand": {}}}, r"scene\.graspers: names must be identifiers"),
])
def test_a_bad_instrument_in_a_scene_is_one_line_naming_it(changes, message):
    with pytest.raises(SpecError, match=message) as caught:
        envs.check_env_kwargs(envs.BIMANUAL_RETRACTION, {"scene": changes})
    assert "\n" not in str(caught.value)


def test_a_scene_with_no_grasper_named_is_refused():
    with pytest.raises(SpecError, match=r"graspers: must name at least one grasper"):
        dataclasses.replace(bimanual_scene(), graspers={})


def test_the_camera_draws_every_grasper():
    """Each grasper's jaw box, projected through the pinhole by hand (eye, rotation and
    focal length from ``camera_view``), lands on pixels labelled jaws (3)."""
    from heml_gym.envs.camera import JAW_OFFSET

    env = BimanualRetractionEnv()
    env.reset(seed=HELD_OUT)
    view = env.camera_view(0, size=(240, 320))
    seg = view["segmentation"]
    for g in env.task.instruments:
        p = view["rotation"] @ (g.position[0] + np.asarray(JAW_OFFSET) - view["eye"])
        u, v = 160 + view["focal"] * p[0] / p[2], 120 + view["focal"] * p[1] / p[2]
        window = seg[int(v) - 2:int(v) + 3, int(u) - 2:int(u) + 3]
        assert (window == 3).any(), (g.name, u, v)


# --------------------------------------------------------------- manipulation
def test_the_goal_observation_is_the_marked_vertex_and_the_drawn_goal():
    env = TissueManipulationEnv()
    obs, info = env.reset(seed=HELD_OUT)
    t = env.task
    np.testing.assert_allclose(obs["achieved_goal"], t.x[0, t.scene.marker], atol=1e-6)
    low, high = t.scene.target_low, t.scene.target_high
    assert np.all(obs["desired_goal"] >= low - 1e-6) and np.all(obs["desired_goal"] <= high + 1e-6)
    assert info["goal_distance"] == pytest.approx(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]), abs=1e-6)
    goals = np.array([env.reset(seed=s)[0]["desired_goal"] for s in range(HELD_OUT, HELD_OUT + 8)])
    assert np.all(goals.std(axis=0) > 1e-3)  # drawn per episode


@pytest.mark.parametrize("reward_type", ["sparse", "dense"])
def test_compute_reward_recomputes_every_step_reward_from_the_goals_alone(reward_type):
    """What HER relies on: ``compute_reward(achieved, desired, info)`` on a batch of the
    episode's goals equals the rewards the steps paid; sparse is -1 outside the 5 mm
    tolerance and 0 within, dense minus the distance (m); success is within tolerance."""
    env = gym.make(envs.TISSUE_MANIPULATION, settings={"reward_type": reward_type})
    policy = scripted_policy(env.unwrapped.scene)
    obs, _ = env.reset(seed=HELD_OUT + 1)
    achieved, desired, rewards, success, distance = [], [], [], [], []
    for _ in range(30):
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        achieved.append(obs["achieved_goal"])
        desired.append(obs["desired_goal"])
        rewards.append(reward)
        success.append(info["is_success"])
        distance.append(info["goal_distance"])
    recomputed = env.unwrapped.compute_reward(np.array(achieved), np.array(desired), [{}] * len(rewards))
    np.testing.assert_allclose(recomputed, rewards, atol=1e-6)
    distance = np.array(distance)
    tol = env.unwrapped.task.settings.goal_tolerance
    np.testing.assert_array_equal(np.array(success), distance <= tol)
    assert any(success) and not all(success)  # the stream crossed the tolerance
    expected = -distance if reward_type == "dense" else -(distance > tol).astype(float)
    np.testing.assert_allclose(rewards, expected, atol=1e-6)


def test_a_goal_outside_the_workspace_is_one_line_naming_it():
    env = TissueManipulationEnv()
    with pytest.raises(SpecError, match=r"^goal: .* lies outside the workspace") as caught:
        env.reset(seed=0, options={"goal": [0.5, 0.06, 0.03]})
    assert "\n" not in str(caught.value)
    obs, _ = env.reset(seed=0, options={"goal": [0.07, 0.06, 0.04]})
    np.testing.assert_allclose(obs["desired_goal"], [0.07, 0.06, 0.04], atol=1e-7)


def test_vector_manipulation_matches_single_envs():
    vec = gym.make_vec(envs.TISSUE_MANIPULATION, num_envs=2, vectorization_mode="vector_entry_point")
    assert isinstance(vec.unwrapped, TissueManipulationVectorEnv)
    obs, _ = vec.reset(seed=40)
    actions = np.random.default_rng(0).uniform(-1, 1, (8, 2, 4)).astype(np.float32)
    steps = [vec.step(a) for a in actions]
    for i in range(2):
        env = TissueManipulationEnv()
        single, _ = env.reset(seed=40 + i)
        for key in single:
            np.testing.assert_allclose(single[key], obs[key][i], atol=1e-12)
        for k, a in enumerate(actions):
            single, reward, *_ = env.step(a[i])
            for key in single:
                np.testing.assert_allclose(single[key], steps[k][0][key][i], rtol=1e-9, atol=1e-9)
            assert reward == pytest.approx(steps[k][1][i])


def test_sb3_sac_with_her_trains_on_the_goal_task_and_relabels_with_its_reward(tmp_path):
    """SB3's SAC with ``HerReplayBuffer`` runs on the task's SB3 VecEnv (a few hundred
    steps), and the buffer's relabelled rewards are the env's ``compute_reward`` of the
    relabelled goals. Its ONNX export, run by onnxruntime on the dict observations of an
    episode, acts as SB3's own ``predict``."""
    from stable_baselines3 import SAC, HerReplayBuffer

    from heml_gym.agents.vec_env import RetractionSb3VecEnv

    vec = RetractionSb3VecEnv(gym.make_vec(envs.TISSUE_MANIPULATION, num_envs=2,
                                           vectorization_mode="vector_entry_point").unwrapped)
    model = SAC("MultiInputPolicy", vec, replay_buffer_class=HerReplayBuffer,
                replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
                learning_starts=100, batch_size=64, seed=0, device="cpu")
    model.learn(300)
    sample = model.replay_buffer.sample(256)
    obs = sample.next_observations
    expected = vec.venv.compute_reward(obs["achieved_goal"].numpy(), obs["desired_goal"].numpy(), None)
    np.testing.assert_allclose(sample.rewards.numpy().ravel(), expected, atol=1e-6)
    assert (sample.rewards.numpy() == 0).any() or (expected == 0).sum() == 0

    from heml_gym.agents.export import OnnxPolicy, export_policy

    out = export_policy(model, None, tmp_path / "her.onnx", envs.TISSUE_MANIPULATION)
    policy = OnnxPolicy(out)
    env = TissueManipulationEnv()
    obs, _ = env.reset(seed=HELD_OUT)
    for _ in range(10):
        expected = model.predict(obs, deterministic=True)[0]
        np.testing.assert_allclose(policy(obs), expected, atol=1e-5)
        obs, *_ = env.step(expected)


@pytest.mark.parametrize("kwargs, message", [
    ({"scene": {"paddle": {"size": [0.04, 0.02]}}}, r"scene\.paddle: unknown field \(known: .*graspers"),
    ({"scene": {"graspers": {"left": {"jaws": 0.04}}}}, r"scene\.graspers\.left\.jaws: unknown field"),
    ({"weights": {"exposur": 1.0}}, r"weights\.exposur: unknown field"),
    ({"settings": {"reward_typ": "dense"}}, r"settings\.reward_typ: unknown field"),
    ({"settings": {"reward_type": "shaped"}}, r"settings\.reward_type: must be one of"),
])
def test_a_run_config_naming_an_unknown_instrument_or_term_is_one_line(kwargs, message, tmp_path):
    """A run config's env arguments are checked before anything runs: an instrument kind the
    scenes do not have, a grasper field, a reward term or a setting that does not exist, a
    reward type not offered. One line, naming the key."""
    import yaml

    from heml_gym.agents.config import ConfigError, load_config

    env_id = envs.TISSUE_MANIPULATION if "settings" in kwargs else envs.BIMANUAL_RETRACTION
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump({"env": {"id": env_id, "kwargs": kwargs},
                                      "algorithm": {"name": "PPO", "policy": "MlpPolicy"}}))
    with pytest.raises(ConfigError, match=message) as caught:
        load_config(config)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("obs_mode", ["rgb", "rgbd"])
def test_the_goal_task_in_camera_modes_keeps_its_goals_beside_the_images(obs_mode):
    """Camera observations of the goal task: the images beside ``observation``,
    ``achieved_goal`` and ``desired_goal`` (what HER needs), checked by gymnasium; the goal
    is drawn (target pixels, label 2, in the segmentation)."""
    env = TissueManipulationEnv(obs_mode=obs_mode, camera={"size": [48, 64], "segmentation": True})
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=HELD_OUT)
    assert {"observation", "achieved_goal", "desired_goal", "rgb", "segmentation"} <= set(obs)
    assert obs["rgb"].shape == (48, 64, 3) and (obs["segmentation"] == 2).any()
