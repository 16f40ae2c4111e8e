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
from raycast import first_hits

TISSUE, ORGAN = "heml_gym/TissueRetraction-v1", "heml_gym/OrganRetraction-v2"


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
                           max_episode_steps=8)
        model = PPO(policy, RetractionSb3VecEnv(vec.unwrapped), n_steps=16, batch_size=16, n_epochs=1, device="cpu")
        model.learn(32)
        assert model.num_timesteps >= 32


def _pinhole_rays(spec, rest_vertices, height, width):
    """Every pixel's ray (unit-free directions with z_cam = 1, and world directions) of a
    pinhole camera built from the scene's own camera data (eye, look_at or the rest
    tissue's centre, up, vertical field of view): image x to the right, y down."""
    eye = np.asarray(spec.eye, dtype=float)
    target = np.asarray(spec.look_at, dtype=float) if spec.look_at is not None else rest_vertices.mean(axis=0)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, spec.up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    focal = 0.5 * height / np.tan(np.radians(0.5 * spec.fov_y))
    rows, cols = np.mgrid[0:height, 0:width]
    rows, cols = rows.ravel(), cols.ravel()
    cam = np.stack([(cols + 0.5 - 0.5 * width) / focal, (rows + 0.5 - 0.5 * height) / focal,
                    np.ones(rows.size)], axis=1)
    world = cam[:, :1] * right + cam[:, 1:2] * down + cam[:, 2:] * forward
    return eye, rows, cols, cam, world


@pytest.mark.parametrize("env_id", [TISSUE, ORGAN])
def test_depth_segmentation_and_colour_match_an_independent_pinhole_ray_cast(env_id):
    """Once the scripted fold has exposed the target, every pixel of a 40 x 56 image
    (non-square: rows and columns cannot be swapped unnoticed) is checked against a ray
    cast of the scene's own camera data (not the renderer's pose or focal length): the
    depth along the optical axis to 1 micrometre, the label of the object hit (the support
    lies behind everything: the target below the organ's surface shows wherever the
    tissue does not cover it, as exposure counts it), the background where a ray hits
    nothing (the supports fill both tasks' views), and the tissue, the target and the
    support all in view. Colour: each object's pixels are shaded versions of its own colour (its hue
    kept), the background one flat colour. (Before 2026-11-26 the support plane hid the
    target in every camera image, and a support triangle reaching behind the camera was
    dropped whole.)"""
    kw = {"mesh_size": 0.012} if env_id == ORGAN else {}
    env = gym.make(env_id, obs_mode="rgbd", camera={"segmentation": True, "size": [40, 56]}, **kw).unwrapped
    obs, _ = env.reset(seed=4)
    policy = scripted_policy(env.scene)
    state = env.task.state_observation()[0]
    for _ in range(60):  # fold until the target shows
        obs, _, terminated, truncated, info = env.step(policy(state))
        state = env.task.state_observation()[0]
        if info["exposure"] > 0.6 or terminated or truncated:
            break
    assert info["exposure"] > 0.6
    t = env.task
    x = t.x[0]
    meshes = [(x[t.scene.surface_faces], SEGMENT_IDS["tissue"])]
    sv, sf = icosphere(t.scene.target_radius, t.target[0], subdivisions=1)
    meshes.append((sv[sf], SEGMENT_IDS["target"]))
    bv, bf = box(t.gripper[0] + np.array([0.0, 0.0, 0.006]), (0.003, 0.006, 0.006))
    meshes.append((bv[bf], SEGMENT_IDS["instrument"]))
    qv, qf = env.camera_renderer.support
    triangles = np.concatenate([m[0] for m in meshes])
    labels = np.concatenate([np.full(len(m[0]), m[1]) for m in meshes])
    eye, rows, cols, cam, world = _pinhole_rays(t.scene.spec.camera, t.scene.mesh.vertices, 40, 56)
    t_hit, k_hit, w_hit = first_hits(eye, world, triangles)
    # the support lies behind everything: a ray sees it only where it hits nothing else
    s_hit, _, s_w = first_hits(eye, world, qv[qf])
    on_support = ~np.isfinite(t_hit) & np.isfinite(s_hit)
    t_hit[on_support], w_hit[on_support] = s_hit[on_support], s_w[on_support]
    labels = np.append(labels, SEGMENT_IDS["support"])
    k_hit[on_support] = len(labels) - 1
    depth = obs["depth"][rows, cols, 0]
    seg = obs["segmentation"][rows, cols, 0]
    rgb = obs["rgb"][rows, cols].astype(float)
    clear = w_hit > 1e-3  # not within a hair of a triangle's edge
    hit = np.isfinite(t_hit) & clear
    miss = ~np.isfinite(t_hit)
    assert hit.sum() > 0.2 * rows.size  # (hundreds of pixels checked)
    far = env.camera_renderer.spec.far
    np.testing.assert_allclose(depth[hit], np.minimum(t_hit[hit] * cam[hit, 2], far), rtol=0, atol=1e-6)  # m
    assert np.array_equal(seg[hit], labels[k_hit[hit]])
    assert np.all(seg[miss] == SEGMENT_IDS["background"])
    seen = set(labels[k_hit[hit]].tolist())
    assert {SEGMENT_IDS[k] for k in ("tissue", "target", "support")} <= seen
    assert len({tuple(c) for c in rgb[miss]}) <= 1  # background (where seen): one flat colour
    for name in ("tissue", "target", "support"):
        own = rgb[hit & (seg == SEGMENT_IDS[name])]
        if len(own) < 3:
            continue
        brightest = own[np.argmax(own.sum(axis=1))]
        direction = brightest / np.linalg.norm(brightest)
        cosines = own @ direction / np.maximum(np.linalg.norm(own, axis=1), 1e-9)
        assert np.median(cosines) > 0.98, name  # shading scales a colour, it does not change its hue


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


def test_the_lobe_camera_is_upright():
    """The lobe and its camera are mirror-symmetric about the plane y = 0 (the camera sits
    on it), so an upright image (world +z up) shows the lobe and jaws symmetric about the
    image's vertical centre line; an image turned 90 degrees (OrganRetraction-v1) is
    symmetric about the horizontal one instead. The floor fills the bottom row, below the
    lobe's thin edge."""
    env = gym.make(ORGAN, obs_mode="rgb", camera={"size": [64, 64], "segmentation": True})
    obs, _ = env.reset(seed=0, options={"gripper": [-0.055, 0.0, 0.025]})
    labels = obs["segmentation"][..., 0]
    lobe = (labels == SEGMENT_IDS["tissue"]) | (labels == SEGMENT_IDS["instrument"])

    def overlap(a, b):
        return (a & b).sum() / (a | b).sum()

    assert overlap(lobe, lobe[:, ::-1]) > 0.97 > overlap(lobe, lobe[::-1]) + 0.05
    assert (labels[-1] == SEGMENT_IDS["support"]).all()


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


def test_a_vector_env_renders_every_env_as_single_envs_do():
    vec = gym.make_vec(TISSUE, num_envs=3, vectorization_mode="vector_entry_point", obs_mode="rgbd")
    obs, _ = vec.reset(seed=30)
    for i in range(3):
        single, _ = gym.make(TISSUE, obs_mode="rgbd").reset(seed=30 + i)
        assert np.array_equal(single["rgb"], obs["rgb"][i])
        np.testing.assert_allclose(single["depth"], obs["depth"][i], atol=1e-6)
