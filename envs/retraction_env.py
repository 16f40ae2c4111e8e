"""Gymnasium wrappers of the batched retraction task: one env, and a native vector env."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from .core import BatchedRetraction, RetractionScene, RewardWeights, TaskSettings

POINTCLOUD_SIZE = 64  # surface points in obs_mode="pointcloud"


def _check_actions(actions: np.ndarray, shape) -> np.ndarray:
    a = np.asarray(actions, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite, got {a}")
    return a


class _ObservationMixin:
    """Observation spaces and builders shared by the single and the vector env."""

    def _setup_observations(self, obs_mode: str, task: BatchedRetraction):
        if obs_mode not in ("state", "pointcloud"):
            raise ValueError(f"obs_mode must be 'state' or 'pointcloud', got {obs_mode!r}")
        self.obs_mode = obs_mode
        low, high = task.state_bounds()
        state_space = spaces.Box(low, high, dtype=np.float32)
        if obs_mode == "state":
            return state_space
        surface = np.setdiff1d(task.scene.mesh.surface_vertices, task.scene.fixed)
        pick = np.linspace(0, len(surface) - 1, POINTCLOUD_SIZE).round().astype(np.int64)
        self._cloud_vertices = surface[pick]
        bound = 0.5
        cloud_space = spaces.Box(-bound, bound, (POINTCLOUD_SIZE, 3), dtype=np.float32)
        return spaces.Dict({"state": state_space, "points": cloud_space})

    def _observations(self, task: BatchedRetraction):
        state = task.state_observation()
        if self.obs_mode == "state":
            return state
        cloud = np.clip(task.sim.x[:, self._cloud_vertices], -0.5, 0.5)
        return {"state": state, "points": np.nan_to_num(cloud).astype(np.float32)}


class RetractionEnv(_ObservationMixin, gym.Env):
    """Base of the single retraction environments (see the task classes' docstrings)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(self, scene: RetractionScene, obs_mode: str = "state", render_mode: str | None = None,
                 settings: TaskSettings | None = None, weights: RewardWeights | None = None):
        self.task = BatchedRetraction(scene, 1, settings, weights)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), dtype=np.float32)
        self.observation_space = self._setup_observations(obs_mode, self.task)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self._renderer = None

    def _obs(self):
        obs = self._observations(self.task)
        return obs[0] if self.obs_mode == "state" else {k: v[0] for k, v in obs.items()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        # a given seed seeds the scene directly (as scene i of a vector env reset with
        # seed - i); without one, the scene continues from the env's generator
        scene_seed = seed if seed is not None else int(self.np_random.integers(2**63 - 1))
        self.task.reset([0], seeds=[scene_seed])
        return self._obs(), self._info_at_reset()

    def _info_at_reset(self) -> dict[str, Any]:
        t = self.task
        return {"exposure": float(t.exposure[0]), "lift": float(t.lift[0]), "max_strain": float(t.max_strain[0]),
                "grasp_force": 0.0, "is_success": False, "young_modulus": float(t.sim.young_modulus[0])}

    def step(self, action):
        a = _check_actions(action, (4,))
        reward, terminated, truncated, info = self.task.step(a[None, :])
        info = {k: (v[0].item() if isinstance(v, np.ndarray) else v) for k, v in info.items()}
        if self.render_mode == "human":
            self.render()
        return self._obs(), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode is None:
            return None
        from .render_scene import SceneRenderer

        if self._renderer is None:
            self._renderer = SceneRenderer(self.task, mode=self.render_mode)
        return self._renderer.render(0)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class RetractionVectorEnv(_ObservationMixin, VectorEnv):
    """N retraction scenes advanced by one batched Numba call (next-step autoreset)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, scene: RetractionScene, num_envs: int = 4, obs_mode: str = "state",
                 settings: TaskSettings | None = None, weights: RewardWeights | None = None,
                 max_episode_steps: int | None = None, render_mode: str | None = None):
        if max_episode_steps is not None:
            settings = settings or TaskSettings()
            settings.max_steps = int(max_episode_steps)
        self.num_envs = int(num_envs)
        self.task = BatchedRetraction(scene, self.num_envs, settings, weights)
        self.single_action_space = spaces.Box(-1.0, 1.0, (4,), dtype=np.float32)
        self.single_observation_space = self._setup_observations(obs_mode, self.task)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.render_mode = render_mode
        self._needs_reset = np.zeros(self.num_envs, dtype=bool)
        self._np_random = None

    def reset(self, *, seed=None, options=None):
        if seed is None:
            seeds = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        self._np_random = np.random.default_rng(seed if isinstance(seed, int) else None)
        self.task.reset(np.arange(self.num_envs), seeds)
        self._needs_reset[:] = False
        return self._observations(self.task), {}

    def step(self, actions):
        a = _check_actions(actions, (self.num_envs, 4))
        finished = self._needs_reset.copy()
        reward, terminated, truncated, info = self.task.step(a, active=~finished)
        if finished.any():  # next-step autoreset: these scenes start a new episode now
            idx = np.flatnonzero(finished)
            self.task.reset(idx)
            reward[idx] = 0.0
            terminated[idx] = False
            truncated[idx] = False
            for key, values in info.items():  # their info describes the new episode's start
                if key.startswith("reward_") or values.dtype == bool:
                    values[idx] = 0
            info["exposure"][idx] = self.task.exposure[idx]
            info["lift"][idx] = self.task.lift[idx]
            info["max_strain"][idx] = self.task.max_strain[idx]
            info["grasp_force"][idx] = 0.0
        self._needs_reset = terminated | truncated
        return self._observations(self.task), reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .render_scene import SceneRenderer

        renderer = SceneRenderer(self.task, mode="rgb_array")
        return [renderer.render(i) for i in range(self.num_envs)]
