"""Tissue harm: ``info["cost"]`` and ``info["damage"]`` against the gauge strain computed
here, independently of the env (the gauges' lattice points carried by this test's own
barycentric embedding of the rest mesh)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from heml_gym.calibration import embed_points
from heml_gym.envs import ORGAN_RETRACTION, TISSUE_RETRACTION, TaskSettings
from heml_gym.envs.scripted import scripted_policy


def independent_cost(env, dt, safe):
    """``dt * max(0, max gauge strain - safe)`` from the state: the lattice points by this
    test's own embedding, their segments' engineering strain ``|l / L - 1|``."""
    task = env.unwrapped.task
    gauges = task.gauges
    B = embed_points(task.scene.mesh, gauges.points)
    p = B @ task.x[0]
    a, b = gauges.pairs[:, 0], gauges.pairs[:, 1]
    rest = np.linalg.norm(gauges.points[b] - gauges.points[a], axis=1)
    strain = np.abs(np.linalg.norm(p[b] - p[a], axis=1) / rest - 1.0).max()
    return dt * max(0.0, strain - safe), strain


@pytest.mark.parametrize("env_id", [TISSUE_RETRACTION, ORGAN_RETRACTION])
def test_no_cost_at_rest_and_along_the_scripted_fold_it_is_the_strains_excess(env_id):
    env = gym.make(env_id)
    st = TaskSettings()
    _, info = env.reset(seed=3)
    assert info["cost"] == 0.0 and info["damage"] == 0.0
    for _ in range(5):  # at rest: the tissue lies on its support, far below the safe strain
        *_, info = env.step(np.zeros(4, dtype=np.float32))
        assert info["cost"] == 0.0 and info["damage"] == 0.0
    policy = scripted_policy(env.unwrapped.scene)
    obs, _ = env.reset(seed=3)
    total, done = 0.0, False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        done = terminated or truncated
        expected, strain = independent_cost(env, st.control_dt, st.safe_strain)
        assert info["cost"] == pytest.approx(expected, abs=1e-9)
        total += expected
        assert info["damage"] == pytest.approx(total, abs=1e-9)
    assert info["is_success"]


def test_a_tearing_pull_costs_and_tears():
    env = gym.make(TISSUE_RETRACTION)
    st = TaskSettings()
    env.reset(seed=5)
    env.step(np.array([0, 0, 0, 1.0], dtype=np.float32))  # close on the edge
    costs, done, info = [], False, {}
    while not done:
        *_, terminated, truncated, info = env.step(np.array([1.0, 0, 1.0, 1.0], dtype=np.float32))  # away and up
        done = terminated or truncated
        expected, _ = independent_cost(env, st.control_dt, st.safe_strain)
        assert info["cost"] == pytest.approx(expected, abs=1e-9)
        costs.append(info["cost"])
    assert info["tissue_torn"] and max(costs) > 0.0 and info["damage"] > 0.0


def test_the_safe_strain_is_a_setting_and_checked():
    env = gym.make(TISSUE_RETRACTION, settings={"safe_strain": 0.0})
    env.reset(seed=0)
    *_, info = env.step(np.zeros(4, dtype=np.float32))
    assert info["cost"] > 0.0  # any strain at all (the tissue sags under its weight) costs
    for bad in (-0.1, float("inf"), "low", float("nan"), True):
        with pytest.raises(ValueError, match="safe_strain"):
            TaskSettings(safe_strain=bad)
