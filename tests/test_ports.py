"""Instruments on ports: the shaft passes through a fixed point, the action is the port's
tilt and insertion rates (envs/instruments/port.py). Checked against geometry (the angle
the shaft turns, the distance along it), against the Cartesian velocity the port commands
are meant to give (first order in the step), and through the tasks."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import heml_gym.envs as envs
from heml_gym.envs.instruments.port import Port
from heml_gym.envs.scripted import PortCommands, run_episodes, scripted_policy
from heml_gym.envs.spec import SpecError

HELD_OUT = 61_000  # seeds nobody has run
PORT = [0.06, 0.04, 0.15]  # m: above the flap, TissueRetraction's start box below and beside it


def _angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)


def _ports(rng, count):
    for _ in range(count):
        port = rng.uniform(-0.2, 0.2, 3)
        towards = port + rng.normal(size=3) * rng.uniform(0.05, 0.2)
        yield Port(port, towards, angular_speed=rng.uniform(0.2, 2.0), max_tilt=1.2)


def test_a_tilt_command_turns_the_shaft_by_its_angle_about_the_port_and_keeps_the_insertion():
    rng = np.random.default_rng(0)
    for port in _ports(rng, 20):
        depth = rng.uniform(0.02, 0.2)
        for k, normal in ((0, port.e2), (1, port.e1)):  # pitch turns in the plane normal to e2, yaw to e1
            tip = port.port + depth * port.axis
            command = np.zeros((1, 3))
            command[0, k] = rng.choice([-1, 1]) * rng.uniform(0.1, 1)
            steps, dt = 7, 0.1
            for _ in range(steps):
                tip = port.advance(tip, command, 0.05, dt)
            shaft = tip[0] - port.port
            assert np.linalg.norm(shaft) == pytest.approx(depth, rel=1e-12)
            turned = min(abs(command[0, k]) * port.angular_speed * dt * steps, port.max_tilt)  # up to the limit
            assert _angle(shaft, port.axis) == pytest.approx(turned, rel=1e-9)
            assert abs(shaft @ normal) < 1e-12


def test_an_insertion_command_slides_the_tip_along_the_shaft():
    rng = np.random.default_rng(1)
    for port in _ports(rng, 20):
        tip = port.tips(np.array([[rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.05, 0.2)]]))
        rate, speed, dt = rng.uniform(-1, 1), 0.05, 0.1
        moved = port.advance(tip, np.array([[0.0, 0.0, rate]]), speed, dt)
        shaft = (tip - port.port)[0]
        assert _angle(moved[0] - port.port, shaft) < 1e-7
        assert np.linalg.norm(moved - tip) == pytest.approx(abs(rate) * speed * dt, rel=1e-9)


def test_port_commands_give_the_cartesian_velocity_to_first_order_in_the_step():
    """The tip's displacement over dt under commands_for(v) is v dt + O(dt^2): halving dt
    quarters the error."""
    rng = np.random.default_rng(2)
    for port in _ports(rng, 20):
        tip = port.tips(np.array([[rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), rng.uniform(0.08, 0.2)]]))
        velocity = rng.normal(size=(1, 3)) * 0.01  # m/s, small enough that no command is clipped
        command = port.commands_for(tip, velocity, 0.05)
        assert np.all(np.abs(command) < 1)
        errors = [np.linalg.norm(port.advance(tip, command, 0.05, dt) - tip - velocity * dt) for dt in (0.1, 0.05)]
        assert errors[1] < 0.3 * errors[0]
        assert errors[0] < 0.05 * np.linalg.norm(velocity) * 0.1


def test_a_grasper_on_a_port_keeps_its_tip_under_zero_commands_and_names_its_action():
    env = gym.make(envs.TISSUE_RETRACTION, scene={"gripper": {"port": PORT}})
    env.reset(seed=HELD_OUT)
    grasper = env.unwrapped.task.instruments[0]
    assert grasper.ACTION == ("pitch_rate", "yaw_rate", "insertion_rate", "grasp")
    start = grasper.position.copy()
    for _ in range(5):
        env.step(np.array([0.0, 0.0, 0.0, -1.0], dtype=np.float32))
    np.testing.assert_allclose(grasper.position, start, atol=1e-12)


@pytest.mark.parametrize("env_id, scene", [
    (envs.TISSUE_RETRACTION, {"gripper": {"port": PORT}}),
    (envs.TISSUE_RETRACTION, {"gripper": {"port": PORT, "jaw_length": 0.03, "jaw_ends": "weighted", "roll_speed": 1.0}}),
    (envs.BIMANUAL_RETRACTION, {"graspers": {"left": {"port": [0.06, -0.02, 0.16]},
                                             "right": {"port": [0.06, 0.26, 0.16]}}}),
])
def test_the_scripted_expert_succeeds_through_ports(env_id, scene):
    """The expert thinks in Cartesian velocities; through the ports' commands it still
    succeeds on 9 of 10 held-out seeds."""
    env = gym.make(env_id, scene=scene)
    policy = scripted_policy(env.unwrapped.scene)
    assert isinstance(policy, PortCommands)
    result = run_episodes(env, policy, 10, seed=HELD_OUT)
    assert sum(result["successes"]) >= 9, result


@pytest.mark.parametrize("changes, message", [
    ({"port": [0.11, 0.04, 0.01]}, r"scene\.gripper\.port: .* lies inside the start box"),
    ({"port": [0.0, 0.1]}, r"scene\.gripper\.port"),
    ({"port": [0.06, 0.04, 0.15], "max_tilt": 2.0}, r"scene\.gripper\.max_tilt: must be a number in \(0, 1\.5\]"),
    ({"port": [0.06, 0.04, 0.15], "angular_speed": -1}, r"scene\.gripper\.angular_speed"),
])
def test_a_bad_port_is_one_line_naming_it(changes, message):
    with pytest.raises(SpecError, match=message) as caught:
        envs.check_env_kwargs(envs.TISSUE_RETRACTION, {"scene": {"gripper": changes}})
    assert "\n" not in str(caught.value)


def _deepest_in_shaft(task, grasper, radius):
    from heml_gym.envs.instruments.port import SHAFT_HALF_LENGTH
    from heml_gym.tools import Capsule, Tools

    centres, rotations = grasper.port.shaft_poses(grasper.position)
    pose = np.concatenate([centres[0], rotations[0].ravel()])[None]
    return Tools([Capsule(radius, SHAFT_HALF_LENGTH)]).signed_distance(task.x[0], pose)[0].min()


def test_a_shaft_that_touches_tissue_pushes_it_aside_where_one_that_does_not_passes_through():
    """A low port beside the flap: the shaft, slid in and tilted, lies across the flap's
    edge. With ``shaft_radius`` the tissue stays out of it (to the penalty's 0.1 mm) and
    the shaft reports its push; without, it passes 4 mm deep through the tissue."""
    deepest, pushed = {}, {}
    for radius in (0.005, None):
        env = gym.make(envs.TISSUE_RETRACTION, scene={"gripper": {"port": [0.25, 0.06, 0.02], "shaft_radius": radius}})
        env.reset(seed=HELD_OUT)
        task = env.unwrapped.task
        grasper = task.instruments[0]
        deepest[radius], pushed[radius] = 0.0, 0.0
        for _ in range(25):
            _, _, _, _, info = env.step(np.array([0.3, 0.0, 1.0, -1.0], dtype=np.float32))
            assert np.all(info["solver_converged"])
            deepest[radius] = min(deepest[radius], _deepest_in_shaft(task, grasper, 0.005))
            pushed[radius] = max(pushed[radius], float(info.get("shaft_force", 0.0)))
    assert deepest[0.005] > -1e-4 and pushed[0.005] > 0.1  # m, N
    assert deepest[None] < -3e-3 and "shaft_force" not in info


@pytest.mark.parametrize("changes, message", [
    ({"shaft_radius": 0.005}, r"scene\.gripper\.shaft_radius: a shaft that touches tissue needs a port"),
    ({"port": PORT, "shaft_radius": 0.0}, r"scene\.gripper\.shaft_radius: must be a positive length"),
])
def test_a_bad_shaft_is_one_line_naming_it(changes, message):
    with pytest.raises(SpecError, match=message) as caught:
        envs.check_env_kwargs(envs.TISSUE_RETRACTION, {"scene": {"gripper": changes}})
    assert "\n" not in str(caught.value)




def _of_colour(pixels, colour):
    """Which ``pixels (k, 3)`` (uint8) are ``colour`` under any shade (the camera's
    headlight scales it)."""
    shade = pixels.astype(float)
    return np.abs(shade / np.maximum(shade.max(axis=1, keepdims=True), 1) - colour / colour.max()).max(axis=1) < 0.05


def test_the_task_camera_and_render_draw_a_shaft_that_touches_tissue():
    """A grasper on a port above the flap with ``shaft_radius``: points along its shaft
    (between its end behind the jaws and the port), projected into the task camera, fall
    on instrument pixels of the shaft's colour, and ``render()`` draws it; without
    ``shaft_radius`` (a shaft that does not touch) nothing of that colour is drawn."""
    from heml_gym.envs.camera import SEGMENT_IDS
    from heml_gym.envs.palette import SHAFT
    from heml_gym.envs.render import Camera

    drawn = {}
    for radius in (0.004, None):
        env = gym.make(envs.TISSUE_RETRACTION, obs_mode="rgbd", render_mode="rgb_array",
                       scene={"gripper": {"port": PORT, "shaft_radius": radius}})
        env.reset(seed=HELD_OUT)
        renderer, grasper = env.unwrapped.camera_renderer, env.unwrapped.task.instruments[0]
        rgb, seg = renderer.rgb[0], renderer.segmentation[0, ..., 0]
        drawn[radius] = _of_colour(rgb[seg == SEGMENT_IDS["instrument"]], SHAFT).sum()
        frame = env.render()
        drawn[radius, "render"] = _of_colour(frame.reshape(-1, 3), SHAFT).sum()
        if radius is None:
            continue
        end, port = grasper.port.shaft_ends(grasper.position)[0], grasper.port.port
        camera = Camera(renderer.eyes[0], renderer.rots[0], renderer.fov_y)
        uv, _ = camera.project(end + np.linspace(0.1, 0.4, 4)[:, None] * (port - end), renderer.width, renderer.height)
        for u, v in np.round(uv).astype(int):
            window = (slice(max(v - 1, 0), v + 2), slice(max(u - 1, 0), u + 2))
            assert _of_colour(rgb[window][seg[window] == SEGMENT_IDS["instrument"]], SHAFT).any(), (u, v)
    assert drawn[0.004] > 10 and drawn[0.004, "render"] > 10
    assert drawn[None] == 0 and drawn[None, "render"] == 0


#: a grasp region on the flap's top, 40 mm along x by 20 mm along y (5 x 3 vertices, 10 mm
#: apart), and jaws 25 mm long on a port straight above it that roll at 4 rad/s
ROLLING = {"grasp": {"low": [0.08, 0.05, 0.008], "high": [0.12, 0.07, None], "surface": True},
           "gripper": {"port": [0.10, 0.06, 0.15], "jaw_length": 0.025, "roll_speed": 4.0}}


def _rolling_env():
    env = gym.make(envs.TISSUE_RETRACTION, scene=ROLLING)
    env.reset(seed=HELD_OUT)
    grasper = env.unwrapped.task.instruments[0]
    grasper.place(0, (0.10, 0.06, 0.010))
    return env, grasper


def test_jaws_that_roll_take_the_region_along_their_axis_and_a_quarter_turn_takes_it_across():
    """Unrolled, the jaws lie along the region's long axis (x) and take 25 mm of one row
    (3 vertices at one y, 20 mm apart in x); rolled a quarter turn about the shaft (at
    most that far), 25 mm of one column (3 at one x, 20 mm apart in y). The jaws' axis
    stays across the shaft; the action and state name the roll."""
    rest = None
    taken = {}
    for turns in (0, 4):  # 4 steps at 0.4 rad: past a quarter turn, held there
        env, grasper = _rolling_env()
        rest = env.unwrapped.task.scene.mesh.vertices
        assert grasper.ACTION[-1] == "roll_rate" and grasper.OBSERVATION[-1] == ("jaw_roll", "rad")
        for _ in range(turns):
            env.step(np.array([0.0, 0.0, 0.0, -1.0, 1.0], dtype=np.float32))
        obs, _, _, _, _ = env.step(np.array([0.0, 0.0, 0.0, 1.0, 0.0], dtype=np.float32))
        assert obs[7] == pytest.approx(min(turns * 0.4, np.pi / 2), abs=1e-6)  # jaw_roll, after the grasper's 7
        assert abs(grasper.jaw_axes()[0] @ grasper.shaft_directions()[0]) < 1e-12
        taken[turns] = rest[np.flatnonzero(grasper.held[0])]
    row, column = taken[0], taken[4]
    assert len(row) == 3 and np.ptp(row[:, 1]) == 0 and np.ptp(row[:, 0]) == pytest.approx(0.02)
    assert len(column) == 3 and np.ptp(column[:, 0]) == 0 and np.ptp(column[:, 1]) == pytest.approx(0.02)


def test_rolling_while_holding_turns_the_held_tissue_about_the_shaft():
    """Jaws closed on a row, then rolled 0.8 rad: the held vertices (held exactly) turn
    with them about the shaft through the jaws, by that angle, at their distances."""
    env, grasper = _rolling_env()
    env.step(np.array([0.0, 0.0, 0.0, 1.0, 0.0], dtype=np.float32))
    held = np.flatnonzero(grasper.held[0])
    x = env.unwrapped.task.x
    before = x[0, held] - grasper.position[0]
    for _ in range(2):
        env.step(np.array([0.0, 0.0, 0.0, 1.0, 1.0], dtype=np.float32))
    after = x[0, held] - grasper.position[0]
    u = grasper.shaft_directions()[0]
    a = before - np.outer(before @ u, u)
    b = after - np.outer(after @ u, u)
    far = np.linalg.norm(a, axis=1) > 1e-3  # the vertices off the shaft's line
    assert far.sum() >= 2
    turned = np.arctan2(np.cross(a[far], b[far]) @ u, (a[far] * b[far]).sum(axis=1))
    np.testing.assert_allclose(turned, 0.8, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(after, axis=1), np.linalg.norm(before, axis=1), atol=1e-9)


@pytest.mark.parametrize("changes, message", [
    ({"roll_speed": 1.0, "jaw_length": 0.02}, r"scene\.gripper\.roll_speed: jaws that roll about their shaft need a port"),
    ({"port": PORT, "roll_speed": 1.0}, r"scene\.gripper\.roll_speed: jaws that roll about their shaft need a port and a jaw_length"),
    ({"port": PORT, "jaw_length": 0.02, "roll_speed": -1.0}, r"scene\.gripper\.roll_speed: must be a positive angular speed"),
    ({"port": PORT, "jaw_length": 0.02, "roll_speed": 1.0, "wrist_reach": 0.01},
     r"scene\.gripper\.roll_speed: jaws on a free wrist turn with the tissue"),
])
def test_a_bad_roll_is_one_line_naming_it(changes, message):
    with pytest.raises(SpecError, match=message) as caught:
        envs.check_env_kwargs(envs.TISSUE_RETRACTION, {"scene": {"gripper": changes}})
    assert "\n" not in str(caught.value)


def test_a_task_with_rolling_jaws_passes_gymnasiums_env_checker_and_stays_finite():
    from gymnasium.utils.env_checker import check_env

    from env_checks import assert_random_steps_stay_finite

    env = gym.make(envs.TISSUE_RETRACTION, scene=ROLLING)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.action_space.shape == (5,)
    assert_random_steps_stay_finite(env, steps=60, seed=HELD_OUT)


def test_the_task_camera_and_render_draw_jaws_that_roll_along_their_axis():
    """Jaws that roll are drawn along their axis: points 10 mm out along it either side of
    the grasp point, projected into the task camera, fall on instrument pixels of the open
    jaws' colour, unrolled (along x) and rolled a quarter turn (along y); ``render()``
    draws them too."""
    from heml_gym.envs.camera import SEGMENT_IDS
    from heml_gym.envs.palette import JAWS_OPEN
    from heml_gym.envs.render import Camera

    for turns in (0, 4):
        env = gym.make(envs.TISSUE_RETRACTION, obs_mode="rgbd", render_mode="rgb_array", scene=ROLLING)
        env.reset(seed=HELD_OUT)
        grasper = env.unwrapped.task.instruments[0]
        grasper.place(0, (0.10, 0.06, 0.02))  # above the flap: nothing hides the jaws
        for _ in range(turns):
            env.step(np.array([0.0, 0.0, 0.0, -1.0, 1.0], dtype=np.float32))
        env.step(np.zeros(5, dtype=np.float32))
        renderer = env.unwrapped.camera_renderer
        rgb, seg = renderer.rgb[0], renderer.segmentation[0, ..., 0]
        axis = grasper.jaw_axes()[0]
        assert abs(axis[0 if turns == 0 else 1]) > 0.99  # along x unrolled, along y a quarter turn on
        camera = Camera(renderer.eyes[0], renderer.rots[0], renderer.fov_y)
        ends = grasper.position[0] - 0.003 * grasper.shaft_directions()[0] + np.outer([-0.01, 0.01], axis)
        uv, _ = camera.project(ends, renderer.width, renderer.height)
        for u, v in np.round(uv).astype(int):
            window = (slice(max(v - 1, 0), v + 2), slice(max(u - 1, 0), u + 2))
            assert _of_colour(rgb[window][seg[window] == SEGMENT_IDS["instrument"]], JAWS_OPEN).any(), (turns, u, v)
        assert _of_colour(env.render().reshape(-1, 3), JAWS_OPEN).sum() > 10
