"""Checks the env tests share."""

from __future__ import annotations

import numpy as np


def assert_random_steps_stay_finite(env, steps: int, seed: int) -> None:
    """``steps`` uniformly random actions (grasps, releases, pulls) from ``reset(seed)``:
    finite observations in the observation space, finite rewards and ``info``, every step
    converged and none diverged, and the tissue really deformed (some vertex moved > 1 mm)."""
    task = env.unwrapped.task
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    moved = 0.0
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        assert np.all(np.isfinite(obs)) and np.isfinite(reward) and env.observation_space.contains(obs)
        assert all(np.isfinite(v) for v in info.values())
        assert not info["simulation_diverged"] and info["solver_converged"]
        moved = max(moved, float(np.abs(task.x[0] - task.scene.mesh.vertices).max()))
        if terminated or truncated:
            obs, _ = env.reset()
    assert moved > 1e-3
