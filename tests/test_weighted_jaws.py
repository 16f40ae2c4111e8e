"""Weighted jaws (``scene.gripper.jaw_ends: weighted``): each vertex of the grasp region
held by its share inside the jaws, so that the held length, and the force, follow the
jaws' length instead of stepping with the mesh's rows."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import heml_gym.envs  # noqa: F401
from heml_gym.envs import TISSUE_RETRACTION, SpecError
from heml_gym.envs.scripted import scripted_policy


def _flap(length, ends="weighted", **kwargs):
    return gym.make(TISSUE_RETRACTION, scene={"gripper": {"jaw_length": length, "jaw_ends": ends}}, **kwargs).unwrapped


@pytest.mark.parametrize("length", [0.013, 0.03, 0.047])
def test_the_shares_add_up_to_the_jaws_length(length):
    """The grasp edge's vertices lie in rows ``s`` apart along it: jaws of length ``L``
    closed inside the edge hold shares that add up to ``L / s`` rows, each in [0, 1], at
    most two of them in part (the jaws' two ends)."""
    env = _flap(length)
    env.reset(seed=1)
    task = env.task
    patch = task.scene.grasp_patch
    rows = np.unique(np.round(task.scene.mesh.vertices[patch, 1], 9))
    spacing = (rows[-1] - rows[0]) / (len(rows) - 1)
    env.step(np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32))
    assert task.grasping[0]
    share = task.held_share[0]
    per_row = {}
    for v in np.flatnonzero(share):
        per_row[round(task.scene.mesh.vertices[v, 1], 9)] = share[v]
    values = np.array(list(per_row.values()))
    assert np.all((values > 0) & (values <= 1.0))
    assert np.sum(values < 1.0 - 1e-9) <= 2
    assert values.sum() == pytest.approx(length / spacing, rel=1e-9)
    # held in part: a spring (the solver's hold stiffness), held whole: exactly
    held = np.flatnonzero(task.held[0])
    partial = share[held] < 1.0 - 1e-9
    assert np.all(task.control.hold_stiffness[0, held[partial]] > 0)
    assert np.all(task.control.hold_stiffness[0, held[~partial]] == 0)


def _hold_force(length, ends, seed=0, steps=30):
    """The mean grasp force (N) over env steps 21..30 of the scripted fold, recorded with
    40 mm jaws of the same kind and replayed with ``length``."""
    env = _flap(0.04, ends)
    policy = scripted_policy(env.scene)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    actions = []
    for _ in range(steps):
        actions.append(policy(obs))
        obs, *_ = env.step(actions[-1])
    env = _flap(length, ends)
    env.reset(seed=seed)
    forces = []
    for a in actions:
        *_, info = env.step(a)
        assert info["solver_converged"]
        forces.append(info["grasp_force"])
    return float(np.mean(forces[20:30]))


def test_the_force_follows_the_jaws_length_where_whole_vertices_step():
    """On the default flap, jaws of 30, 33 and 36 mm hold the same three edge vertices when
    only whole vertices count (the same force: a tread of the staircase); weighted, the
    force grows with the length."""
    whole = [_hold_force(L, "vertex") for L in (0.030, 0.033, 0.036)]
    weighted = [_hold_force(L, "weighted") for L in (0.030, 0.033, 0.036)]
    assert whole[0] == whole[1] == whole[2]
    assert weighted[0] < weighted[1] < weighted[2]
    assert weighted[2] - weighted[0] > 0.005  # N


def test_a_bad_jaw_ends_setting_is_refused():
    with pytest.raises(SpecError, match="jaw_ends"):
        _flap(0.03, ends="half")
