"""Camera observations: spaces and checkers, depth and segmentation against an independent
ray cast, images that see what the physics does."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import heml_gym.envs  # noqa: F401
from heml_gym.envs.camera import SEGMENT_IDS
from heml_gym.envs.render import box, icosphere
from heml_gym.envs.scripted import scripted_policy

TISSUE, ORGAN = "heml_gym/TissueRetraction-v0", "heml_gym/OrganRetraction-v0"


@pytest.mark.parametrize("env_id", [TISSUE, ORGAN])
@pytest.mark.parametrize("mode", ["rgb", "depth", "rgbd"])
def test_image_modes_pass_both_checkers(env_id, mode):
    from stable_baselines3.common.env_checker import check_env as sb3_check

    kw = {"mesh_size": 0.012} if env_id == ORGAN else {}
    env = gym.make(env_id, obs_mode=mode, **kw)
    check_env(env.unwrapped, skip_render_check=True)
    sb3_check(env.unwrapped, warn=False)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)


def test_sb3_cnn_and_multi_input_policies_take_them_without_wrappers():
    from stable_baselines3 import PPO

    from heml_gym.agents.vec_env import RetractionSb3VecEnv

    for mode, policy, camera in (("rgb", "CnnPolicy", {"size": 64}),
                                 ("rgbd", "MultiInputPolicy", {"size": 64, "state": True})):
        vec = gym.make_vec(TISSUE, num_envs=2, vectorization_mode="vector_entry_point", obs_mode=mode, camera=camera,
                           settings={"max_steps": 8})
        model = PPO(policy, RetractionSb3VecEnv(vec.unwrapped), n_steps=16, batch_size=16, n_epochs=1, device="cpu")
        model.learn(32)
        assert model.num_timesteps >= 32


def _ray_cast(origin, directions, triangles):
    """Nearest hit distance along each ray and the index of the triangle hit (Moller-Trumbore),
    and each hit's smallest barycentric coordinate; ``(inf, -1, 0)`` for a miss."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = b - a, c - a
    best_t = np.full(len(directions), np.inf)
    best_k = np.full(len(directions), -1)
    best_w = np.zeros(len(directions))
    for r, d in enumerate(directions):
        p = np.cross(d, e2)
        det = (e1 * p).sum(axis=1)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - a
        u = (s * p).sum(axis=1) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = (q * e2).sum(axis=1) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        if hit.any():
            k = np.flatnonzero(hit)[np.argmin(t[hit])]
            best_t[r], best_k[r] = t[k], k
            best_w[r] = min(u[k], v[k], 1 - u[k] - v[k])
    return best_t, best_k, best_w


def test_depth_and_segmentation_match_a_ray_cast():
    """At many pixels of a lifted flap, the rendered depth is the ray-cast depth along the
    optical axis within half a millimetre, and the label is the object the ray hits."""
    env = gym.make(TISSUE, obs_mode="rgbd", camera={"segmentation": True}).unwrapped
    obs, _ = env.reset(seed=4)
    policy = scripted_policy(env.scene)
    state = env.task.state_observation()[0]
    for _ in range(14):  # grasp and fold the flap part of the way
        obs, *_ = env.step(policy(state))
        state = env.task.state_observation()[0]
    cam = env.camera_renderer
    t = env.task
    x = t.x[0]
    meshes = [(x[env.task.scene.surface_faces], SEGMENT_IDS["tissue"])]
    sv, sf = icosphere(env.task.scene.target_radius, t.target[0], subdivisions=1)
    meshes.append((sv[sf], SEGMENT_IDS["target"]))
    bv, bf = box(t.gripper[0] + np.array([0.0, 0.0, 0.006]), (0.003, 0.006, 0.006))
    meshes.append((bv[bf], SEGMENT_IDS["instrument"]))
    qv, qf = cam.support
    meshes.append((qv[qf], SEGMENT_IDS["support"]))
    triangles = np.concatenate([m[0] for m in meshes])
    labels = np.concatenate([np.full(len(m[0]), m[1]) for m in meshes])
    h, w = cam.height, cam.width
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, h, 600), rng.integers(0, w, 600)
    rot, eye = cam.rots[0], cam.eyes[0]
    dirs_cam = np.stack([(cols + 0.5 - 0.5 * w) / cam.focal, (rows + 0.5 - 0.5 * h) / cam.focal, np.ones(600)], axis=1)
    dirs = dirs_cam @ rot  # camera -> world (rows of rot are the camera axes)
    t_hit, k_hit, w_hit = _ray_cast(eye, dirs, triangles)
    depth = obs["depth"][rows, cols, 0]
    seg = obs["segmentation"][rows, cols, 0]
    clear = w_hit > 1e-3  # not within a hair of a triangle's edge
    hit = np.isfinite(t_hit) & clear
    assert hit.sum() > 400
    expected_depth = t_hit[hit] * dirs_cam[hit, 2]  # z_cam: distance along the optical axis (dirs_cam z = 1)
    assert np.abs(depth[hit] - np.minimum(expected_depth, cam.spec.far)).max() < 5e-4  # m
    assert np.array_equal(seg[hit], labels[k_hit[hit]])
    assert np.all(seg[~np.isfinite(t_hit)] == SEGMENT_IDS["background"])
    assert len(set(seg[hit].tolist())) >= 3  # tissue, support and the target or the jaws in view


def test_the_image_changes_when_the_gripper_lifts_the_tissue():
    env = gym.make(TISSUE, obs_mode="rgb").unwrapped
    first, _ = env.reset(seed=2)
    policy = scripted_policy(env.scene)
    state = env.task.state_observation()[0]
    for _ in range(12):
        obs, *_ = env.step(policy(state))
        state = env.task.state_observation()[0]
    changed = np.abs(obs.astype(int) - first.astype(int)).sum(axis=2) > 30
    assert changed.mean() > 0.05  # the folded flap moved across a good part of the view


def test_camera_jitter_moves_the_view_per_episode_and_seeds_fix_it():
    env = gym.make(TISSUE, obs_mode="depth", camera={"jitter": 0.01}).unwrapped
    a, _ = env.reset(seed=1)
    b, _ = env.reset(seed=2)
    c, _ = env.reset(seed=1)
    assert not np.array_equal(a, b) and np.array_equal(a, c)
    with pytest.raises(ValueError, match="camera.size"):
        gym.make(TISSUE, obs_mode="rgb", camera={"size": 3})
    with pytest.raises(ValueError, match="camera="):
        gym.make(TISSUE, obs_mode="state", camera={"size": 64})


def test_a_vector_env_renders_every_scene_as_single_envs_do():
    vec = gym.make_vec(TISSUE, num_envs=3, vectorization_mode="vector_entry_point", obs_mode="rgbd")
    obs, _ = vec.reset(seed=30)
    for i in range(3):
        single, _ = gym.make(TISSUE, obs_mode="rgbd").reset(seed=30 + i)
        assert np.array_equal(single["rgb"], obs["rgb"][i])
        np.testing.assert_allclose(single["depth"], obs["depth"][i], atol=1e-6)
