"""A task with several instruments: the retraction task's batch with two graspers. The
action is each grasper's slice in turn, the observation each one's part, the info each
one's entries; a wrong action shape is a one-line error; one grasper stays bit for bit
the task it was (scripts/golden_trajectories.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from heml_gym.envs import TaskSettings, build_scene
from heml_gym.envs.core import STATE_SIZE, BatchedRetraction
from heml_gym.envs.tissue_retraction import tissue_scene


def two_grasper_task(n=2):
    base = tissue_scene()
    scene = build_scene(dataclasses.replace(base, adhesion=None))
    jaws = dataclasses.replace(base.gripper, jaw_length=0.04, jaw_ends="weighted")
    return BatchedRetraction(scene, n, TaskSettings(), grippers={"left": jaws, "right": jaws})


def test_two_graspers_lift_the_flap_together_each_with_its_own_slice_part_and_info():
    task = two_grasper_task()
    task.reset([0, 1], seeds=[3, 4])
    assert task.action_size == 8
    for w in range(2):  # the same tissue; mirror places on the mirror-symmetric flap
        task.set_episode(w, young_modulus=6e3)
        task.instruments[0].place(w, (0.112, 0.03, 0.01))
        task.instruments[1].place(w, (0.112, 0.09, 0.01))
    lift = np.array([0.0, 0.0, 1.0, 1.0])
    actions = np.array([np.concatenate([lift, lift]), np.concatenate([lift, [0.0, 0.0, 0.0, -1.0]])])
    reward, terminated, truncated, info = task.step(actions)
    # world 0: both close (two first grasps: 2 x the grasp bonus); world 1: only the left one
    assert info["reward_grasp"].tolist() == [2 * task.weights.grasp, task.weights.grasp]
    assert info["left_grasping"].tolist() == [True, True] and info["right_grasping"].tolist() == [True, False]
    assert info["grasping"].tolist() == [True, True]
    for _ in range(4):
        reward, terminated, truncated, info = task.step(actions)
        assert info["solver_converged"].all() and np.all(np.isfinite(reward))
    left, right = info["left_grasp_force"], info["right_grasp_force"]
    assert left[0] == pytest.approx(right[0], rel=1e-3) and left[0] > 0.05  # symmetric: the load shared
    assert right[1] == 0.0 and left[1] > left[0]  # alone, the left jaws carry more of the flap
    np.testing.assert_allclose(info["grasp_force"], left + right)
    obs = task.state_observation()
    low, high = task.state_bounds()
    assert obs.shape == (2, STATE_SIZE + 7) == (2, len(low)) and np.all((low <= obs) & (obs <= high))
    np.testing.assert_allclose(obs[:, 0:3], task.instruments[0].position, atol=1e-6)
    np.testing.assert_allclose(obs[:, 7:10], task.instruments[1].position, atol=1e-6)


def test_a_wrong_action_shape_names_the_shape_a_two_grasper_task_takes():
    task = two_grasper_task()
    task.reset([0, 1], seeds=[0, 1])
    with pytest.raises(ValueError, match=r"actions: must have shape \(2, 8\).*got \(2, 4\)"):
        task.step(np.zeros((2, 4)))


def test_graspers_must_be_named_gripper_specs():
    scene = build_scene(tissue_scene())
    from heml_gym.envs import SpecError

    for bad in ({}, {"left": {"jaw_length": 0.04}}, [tissue_scene().gripper]):
        with pytest.raises(SpecError, match="grippers: must map each grasper's name to its GripperSpec"):
            BatchedRetraction(scene, 1, TaskSettings(), grippers=bad)
    wrist = dataclasses.replace(tissue_scene().gripper, wrist_reach=0.01)
    with pytest.raises(SpecError, match="at most one grasper may be on a free wrist"):
        BatchedRetraction(scene, 1, TaskSettings(), grippers={"left": wrist, "right": wrist})
