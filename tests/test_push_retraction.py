"""PushRetraction: a paddle retractor (no grasp) lifts the liver lobe. Conformance, the
paddle instrument against independent truth (a slab's weight over its area; no vertex
through the blade at its top speed), the scripted expert on seeds nobody trained on, the
pressure harm, and the contract for bad input."""

from __future__ import annotations

import types

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import heml_gym as hg
import heml_gym.envs as envs
from heml_gym import materials as M
from heml_gym.envs.instruments import Paddle
from heml_gym.envs.push_retraction import SAFE_PRESSURE, PushRetractionEnv, PushSettings, push_scene
from heml_gym.envs.scene import PaddleSpec
from heml_gym.envs.scripted import run_episodes, scripted_policy
from heml_gym.envs.spec import SpecError
from heml_gym.world import World

HELD_OUT = 31_000  # episode seeds no training, evaluation or stored result uses


@pytest.mark.parametrize("obs_mode", ["state", "pointcloud"])
def test_gymnasium_and_sb3_env_checkers_pass(obs_mode):
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(PushRetractionEnv(obs_mode=obs_mode), skip_render_check=True)
    sb3_check_env(PushRetractionEnv(obs_mode=obs_mode), warn=True)


def test_scripted_expert_succeeds_on_nine_of_ten_held_out_seeds():
    env = gym.make(envs.PUSH_RETRACTION)
    result = run_episodes(env, scripted_policy(env.unwrapped.scene), 10, seed=HELD_OUT)
    assert sum(result["successes"]) >= 9, result


def test_the_paddle_is_observed_and_reported_by_name_and_holds_nothing():
    env = PushRetractionEnv()
    obs, info = env.reset(seed=HELD_OUT)
    assert env.action_space.shape == (4,) and obs.shape == (24,)
    assert env.instruments == ("paddle",)
    names = [name for name, _ in env.task.state_fields()]
    assert names[:7] == ["paddle_centre_x", "paddle_centre_y", "paddle_centre_z", "paddle_tilt",
                         "paddle_push_force_x", "paddle_push_force_y", "paddle_push_force_z"]
    np.testing.assert_allclose(obs[0:3], env.task.instruments[0].position[0], atol=1e-6)
    obs, _, _, _, info = env.step(np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32))  # tilt at full rate
    assert obs[3] == pytest.approx(0.5 * 0.1)  # rad: angular_speed x control_dt
    assert info["paddle_tilt"] == pytest.approx(0.05) and not info["grasping"] and info["grasp_force"] == 0.0


def _slab_on_paddle(E=5e3):
    """A free 40 x 40 x 8 mm slab (no support) settled on a level 60 x 60 mm paddle."""
    mesh = hg.box_mesh((0.04, 0.04, 0.008), (4, 4, 2))
    scene = types.SimpleNamespace(mesh=mesh, surface_faces=mesh.boundary_faces, fixed=np.zeros(0, dtype=np.int64))
    spec = PaddleSpec(half_extents=(0.03, 0.03, 0.002))
    model = hg.Model(mesh, M.NeoHookean(E=E, nu=0.45), density=1000.0, gravity=(0.0, 0.0, -9.81), damping=5.0,
                     tools=[Paddle.blade(spec)])
    world = World(model, hg.QuasiNewtonSolver(model, newton_tol=1e-8, max_iter=500), substeps=2)
    paddle = Paddle(world, scene, types.SimpleNamespace(control_dt=0.1), spec)
    paddle.place(0, (0.02, 0.02, -0.002))  # its top face at z = 0, under the slab
    for _ in range(40):
        stats = world.step(0.1)
        assert stats.converged.all() and not stats.diverged.any()
        paddle.after_step(stats.reaction, stats.diverged, stats.tool_force)
    return paddle, 1000.0 * 0.04 * 0.04 * 0.008 * 9.81


def test_a_slab_resting_on_the_paddle_presses_with_its_weight_over_its_area():
    """Independent truth: the whole underside rests on the blade, so the contact pressure
    is the slab's weight over its underside (40 x 40 mm), the push its weight."""
    paddle, weight = _slab_on_paddle()
    assert paddle.force[0, 2] == pytest.approx(weight, rel=0.01)  # its push on the tissue: up
    assert paddle.pressure[0] == pytest.approx(weight / (0.04 * 0.04), rel=0.02)


def test_the_paddle_at_its_top_speed_lets_no_vertex_through_the_blade():
    """Driven up under the lobe and on at full speed (its max_speed, 30 mm/s, in 0.05 s
    solver steps): no tissue vertex ends more than half the blade's thickness inside it
    (a vertex further in would be pushed out through the far face)."""
    env = PushRetractionEnv()
    env.reset(seed=HELD_OUT)
    t = env.task
    paddle = t.instruments[0]
    half = paddle.spec.half_extents[2]
    for k in range(40):
        action = np.array([1.0, 0.0, 0.0, 0.0]) if paddle.position[0, 0] < -0.035 else np.array([0.0, 0.0, 1.0, 0.0])
        _, _, terminated, _, info = env.step(action.astype(np.float32))
        d, _ = t.model.tools.each_distance(t.x[0], t.control.tool_pose[0])
        assert d[paddle.tool].min() > -half, k
        assert info["solver_converged"]
        if terminated:
            break
    assert paddle.position[0, 2] > 0.02  # it lifted the lobe


def test_explicit_sub_steps_lift_the_lobe_on_the_paddle_too():
    """Every integrator steps the paddle: under explicit sub-steps (contact by projection
    onto the blade, as onto a support) the scripted lift raises the lobe, no vertex ends
    inside the blade, and its push carries the lobe's weight share as under L-BFGS."""
    pushes = {}
    for integrator in ("explicit", "quasi_newton"):
        env = PushRetractionEnv(physics={"integrator": integrator})
        obs, _ = env.reset(seed=HELD_OUT)
        policy = scripted_policy(env.scene)
        policy.reset()
        t = env.task
        paddle = t.instruments[0]
        for _ in range(45):
            obs, _, terminated, _, info = env.step(policy(obs))
            assert info["solver_converged"] and not info["simulation_diverged"]
            if terminated:
                break
        d, _ = t.model.tools.each_distance(t.x[0], t.control.tool_pose[0])
        if integrator == "explicit":
            assert d[paddle.tool].min() > -1e-9
        assert paddle.position[0, 2] > 0.02
        pushes[integrator] = info["paddle_push_force"]
    assert pushes["explicit"] == pytest.approx(pushes["quasi_newton"], rel=0.15)


def test_pressure_above_the_safe_value_is_harm_and_below_it_is_not():
    """The same lift read against two safe pressures: below the lift's contact pressure
    every touching step costs, far above it none does; the cost is the strain's plus the
    pressure's, and it adds up to the episode's damage."""
    costs = {}
    for safe in (100.0, 1e9):
        env = PushRetractionEnv(settings={"safe_pressure": safe})
        obs, info = env.reset(seed=HELD_OUT)
        policy = scripted_policy(env.scene)
        policy.reset()
        total, touching = [], []
        for _ in range(40):
            obs, _, terminated, truncated, info = env.step(policy(obs))
            assert info["cost"] == pytest.approx(info["strain_cost"] + info["pressure_cost"])
            total.append(info["cost"])
            touching.append(info["paddle_contact_pressure"] > safe)
            if terminated or truncated:
                break
        assert info["damage"] == pytest.approx(sum(total))
        costs[safe] = (np.array(total), np.array(touching))
    low_total, low_touch = costs[100.0]
    high_total, _ = costs[1e9]
    assert low_touch.any() and np.all((low_total > high_total) == low_touch)
    assert SAFE_PRESSURE == pytest.approx(32 * 133.322)  # 32 mmHg


def test_the_defaults_keep_the_scripted_lift_below_the_safe_pressure_on_average():
    """The task has a harmless solution: along the expert's lift most steps stay below the
    safe pressure (it costs only where the blade first meets the lobe, if at all)."""
    env = gym.make(envs.PUSH_RETRACTION)
    policy = scripted_policy(env.unwrapped.scene)
    obs, info = env.reset(seed=HELD_OUT + 1)
    policy.reset()
    pressures = []
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        pressures.append(info["paddle_contact_pressure"])
        done = terminated or truncated
    assert info["is_success"]
    assert np.median([p for p in pressures if p > 0]) < SAFE_PRESSURE


@pytest.mark.parametrize("changes, message", [
    ({"paddles": {"paddle": {"half_extents": [0.02, 0.0, 0.002]}}}, "half_extents"),
    ({"paddles": {"paddle": {"max_tilt": 2.0}}}, "max_tilt"),
    ({"paddles": None}, "graspers"),
    ({"physics": {"tool_stiffness": -1.0}}, "tool_stiffness"),
    ({"paddles": {"paddle": {"max_speed": 0.0}}}, "max_speed"),
])
def test_bad_paddles_are_one_line_naming_the_field(changes, message):
    with pytest.raises(SpecError, match=message) as err:
        PushRetractionEnv(scene=changes)
    assert "\n" not in str(err.value)


def test_bad_push_settings_are_one_line():
    with pytest.raises(SpecError, match="safe_pressure"):
        PushSettings(safe_pressure=0.0)
    with pytest.raises(SpecError, match="pressure"):
        PushRetractionEnv(weights={"pressure": -1.0})


def test_the_shipped_scene_file_is_the_envs_default():
    from heml_gym.envs.scene import Scene

    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    assert Scene.load(root / "configs" / "scenes" / "push_retraction.yaml") == push_scene()


def test_the_task_camera_draws_the_blade_across_its_width():
    """Once the lobe is lifted, the blade's two ends, projected into the task camera, fall
    on instrument pixels drawn in the paddle's colour (a single marker at its centre would
    cover neither); ``render()`` draws the blade too."""
    from heml_gym.envs.camera import SEGMENT_IDS
    from heml_gym.envs.palette import PADDLE
    from heml_gym.envs.render import Camera

    env = PushRetractionEnv(obs_mode="rgbd", render_mode="rgb_array")
    env.reset(seed=HELD_OUT)
    policy = scripted_policy(env.scene)
    policy.reset()
    info = {"exposure": 0.0}
    while info["exposure"] < 0.8:  # the lobe lifted off the target: the blade is in view beneath it
        _, _, _, _, info = env.step(policy(env.task.state_observation()[0]))
    renderer = env.camera_renderer
    rgb, seg = renderer.rgb[0], renderer.segmentation[0, ..., 0]
    paddle = env.task.instruments[0]
    camera = Camera(renderer.eyes[0], renderer.rots[0], renderer.fov_y)
    hy = paddle.spec.half_extents[1]
    ends = paddle.position[0] + np.array([[0.0, -0.8 * hy, 0.0], [0.0, 0.8 * hy, 0.0]])
    uv, _ = camera.project(ends, renderer.width, renderer.height)
    for u, v in np.round(uv).astype(int):
        window = (slice(max(v - 2, 0), v + 3), slice(max(u - 2, 0), u + 3))
        assert (seg[window] == SEGMENT_IDS["instrument"]).any(), (u, v)
        shade = rgb[window][seg[window] == SEGMENT_IDS["instrument"]].astype(float)
        hue = shade / np.maximum(shade.max(axis=1, keepdims=True), 1)
        assert np.abs(hue - PADDLE / PADDLE.max()).max(axis=1).min() < 0.05
    frame = env.render()  # render() draws the blade as a box too
    blue = np.abs(frame.astype(float) / np.maximum(frame.max(axis=2, keepdims=True), 1)
                  - PADDLE / PADDLE.max()).max(axis=2) < 0.05
    assert blue.sum() > 20
