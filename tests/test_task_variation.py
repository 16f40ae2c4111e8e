"""Per-episode adhesion (``Scene.adhesion``) and jaws that hold only the part of the grasp
patch between them (``TaskSettings.jaw_length``): the held sets against ones selected
independently from the mesh, and the held tissue's motion."""

from __future__ import annotations

import numpy as np
import pytest

from heml_gym.envs.core import TaskSettings
from heml_gym.envs.scene import Scene
from heml_gym.envs.spec import SpecError
from heml_gym.envs.tissue_retraction import FLAP_SIZE, TissueRetractionEnv, tissue_scene

LX, LY, LZ = FLAP_SIZE
UNDERSIDE = {"low": [None, None, 0.0], "high": [None, None, 0.0]}
CLOSE, OPEN = np.array([0, 0, 0, 1.0], dtype=np.float32), np.array([0, 0, 0, -1.0], dtype=np.float32)
LIFT_BACK = np.array([-0.6, 0.0, 1.0, 1.0], dtype=np.float32)


def adhered_scene(low: float, high: float) -> Scene:
    return tissue_scene().updated({"adhesion": {"region": UNDERSIDE, "width": [low, high]}})


def test_adhesion_holds_the_underside_within_the_drawn_width_for_the_whole_episode():
    env = TissueRetractionEnv(scene=adhered_scene(0.025, 0.025))
    _, info = env.reset(seed=3)
    task = env.task
    rest = task.scene.mesh.vertices
    expected = np.flatnonzero((rest[:, 2] == 0.0) & (rest[:, 0] > 0.0) & (rest[:, 0] <= 0.025 + 1e-12))
    assert info["adhesion_width"] == 0.025 and len(expected) > 0
    np.testing.assert_array_equal(np.flatnonzero(task.adhered[0]), expected)
    env.step(CLOSE)
    assert task.grasping[0] and not np.any(task.held[0] & task.adhered[0])
    for _ in range(12):
        env.step(LIFT_BACK)
    assert task.lift[0] > 0.1  # the flap folds ...
    free_underside = (rest[:, 2] == 0.0) & (rest[:, 0] > 0.04) & (rest[:, 0] < 0.1)
    assert task.x[0][free_underside, 2].max() > 0.005  # ... off its support beyond the band
    np.testing.assert_array_equal(task.x[0][expected], rest[expected])  # the band stays stuck
    env.step(OPEN)  # letting go of the flap does not free the band
    assert not task.grasping[0]
    for _ in range(3):
        env.step(OPEN)
    np.testing.assert_array_equal(task.x[0][expected], rest[expected])
    np.testing.assert_array_equal(np.flatnonzero(task.control.kinematic[0]), expected)


def test_adhesion_width_is_drawn_per_episode_and_leaves_the_other_draws_alone():
    plain, stuck = TissueRetractionEnv(), TissueRetractionEnv(scene=adhered_scene(0.0, 0.03))
    widths = []
    for seed in range(12):
        _, a = plain.reset(seed=seed)
        _, b = stuck.reset(seed=seed)
        widths.append(b["adhesion_width"])
        assert a["young_modulus"] == b["young_modulus"]
        np.testing.assert_array_equal(plain.task.target, stuck.task.target)
        np.testing.assert_array_equal(plain.task.gripper, stuck.task.gripper)
        rest = stuck.task.scene.mesh.vertices
        n_expected = np.count_nonzero((rest[:, 2] == 0.0) & (rest[:, 0] > 0.0) & (rest[:, 0] <= widths[-1] + 1e-9))
        assert stuck.task.adhered[0].sum() == n_expected
    assert min(widths) >= 0.0 and max(widths) <= 0.03 and np.ptp(widths) > 0.01
    _, again = stuck.reset(seed=5)
    assert again["adhesion_width"] == widths[5]
    assert "adhesion_width" not in plain.reset(seed=0)[1]


def test_adhesion_round_trips_as_data_and_bad_widths_are_refused():
    scene = adhered_scene(0.0, 0.02)
    assert Scene.from_dict(scene.to_dict()) == scene
    assert scene.to_dict()["adhesion"]["width"] == [0.0, 0.02]
    with pytest.raises(SpecError, match="scene.adhesion.width: must be"):
        adhered_scene(0.02, 0.01)
    with pytest.raises(SpecError, match="scene.adhesion.width: must be"):
        adhered_scene(-0.01, 0.01)
    with pytest.raises(SpecError, match="scene.adhesion.region selects no free vertex"):
        TissueRetractionEnv(scene=tissue_scene().updated(
            {"adhesion": {"region": {"low": [0.0, None, None], "high": [0.0, None, None]}, "width": [0.0, 0.01]}}))


def _close_at(env, y: float, z: float = LZ + 0.004) -> np.ndarray:
    env.reset(seed=0)
    env.task.gripper[0] = (LX, y, z)
    env.step(CLOSE)
    return np.flatnonzero(env.task.held[0])


@pytest.mark.parametrize("y", [0.03, 0.061, 0.114])
def test_jaws_of_a_given_length_hold_the_grasp_line_between_them(y):
    env = TissueRetractionEnv(settings={"jaw_length": 0.03})
    rest = env.task.scene.mesh.vertices
    line = np.flatnonzero(np.isclose(rest[:, 0], LX) & np.isclose(rest[:, 2], LZ))
    within = line[np.abs(rest[line, 1] - y) <= 0.015 + 1e-12]
    np.testing.assert_array_equal(_close_at(env, y), within)
    assert 2 <= len(within) <= 4  # a 30 mm jaw on a line of 10 mm cells
    # without a jaw length, the jaws hold the whole line, wherever along it they close
    np.testing.assert_array_equal(_close_at(TissueRetractionEnv(), y), line)


def test_jaws_out_of_reach_hold_nothing_and_a_bad_jaw_length_is_refused():
    env = TissueRetractionEnv(settings={"jaw_length": 0.03})
    assert _close_at(env, 0.06, z=LZ + 0.03).size == 0
    with pytest.raises(SpecError, match="TaskSettings.jaw_length"):
        TaskSettings(jaw_length=-0.01)
