"""Stable-Baselines3 VecEnv over the batched retraction task (one Numba call for N envs).

SB3 expects same-step auto-reset: when an env's episode ends, the returned observation
is already the first of its next episode, and ``infos[i]["terminal_observation"]`` holds
the last one (with ``infos[i]["TimeLimit.truncated"]`` set on truncation, so that value
bootstrapping is right). This adapter provides exactly that on top of the vector env's
public batch interface (``reset_envs``, ``step_envs``, ``observations``), with no
copy of the task logic. Actions are checked there: a non-finite or misshapen action
raises ``ValueError`` instead of reaching the physics.
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv


class RetractionSb3VecEnv(VecEnv):
    """SB3 ``VecEnv`` view of a :class:`~heml_gym.envs.retraction_env.RetractionVectorEnv`.

    ``vector_env`` is used for its task, spaces and observation builder; its own
    (next-step) auto-reset is bypassed.
    """

    def __init__(self, vector_env):
        self.venv = vector_env
        super().__init__(vector_env.num_envs, vector_env.single_observation_space,
                         vector_env.single_action_space)
        self._actions = None
        self._seeds = [None] * self.num_envs

    def seed(self, seed=None):
        self._seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        return self._seeds

    def reset(self):
        self.venv.reset_envs(np.arange(self.num_envs), self._seeds)
        self._seeds = [None] * self.num_envs
        return self.venv.observations()

    def step_async(self, actions):
        self._actions = actions

    def step_wait(self):
        reward, terminated, truncated, info = self.venv.step_envs(self._actions)
        obs = self.venv.observations()
        done = terminated | truncated
        infos = [{k: (v[i].item() if isinstance(v, np.ndarray) else v) for k, v in info.items()}
                 for i in range(self.num_envs)]
        if done.any():
            ended = np.flatnonzero(done)
            for i in ended:
                infos[i]["terminal_observation"] = _index(obs, i)
                infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            self.venv.reset_envs(ended)
            obs = self.venv.observations()
        return obs, reward.astype(np.float32), done, infos

    def close(self):
        self.venv.close()

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.venv, attr_name) for _ in self._indices(indices)]

    def set_attr(self, attr_name, value, indices=None):
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        return [getattr(self.venv, method_name)(*args, **kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False for _ in self._indices(indices)]

    def _indices(self, indices):
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else indices


def _index(obs, i):
    if isinstance(obs, dict):
        return {k: v[i].copy() for k, v in obs.items()}
    return obs[i].copy()
