"""Goal-conditioned observations for the envs, in Gymnasium-Robotics' ``GoalEnv`` form.

A task with a goal (:class:`~heml_gym.envs.manipulation.BatchedManipulation`) is observed
as ``Dict(observation, achieved_goal, desired_goal)``: ``observation`` the task's state
vector, the goals 3-D points (m). Point-cloud and camera modes add their parts beside
them (``points``, ``rgb``, ``depth``, ``segmentation``), so SB3's ``MultiInputPolicy``
and ``HerReplayBuffer`` take every mode. ``compute_reward(achieved_goal, desired_goal,
info)`` is vectorised over any leading shape, as HER calls it.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


class GoalObservations:
    """Mixin for an env class whose ``task`` has a goal: wraps the observation of
    :meth:`_setup_observations` / :meth:`observations` into the ``GoalEnv`` dict."""

    def _setup_observations(self, obs_mode: str, camera=None):
        inner = super()._setup_observations(obs_mode, camera)
        low, high = self.task.state_bounds()
        goal_low, goal_high = self.task.goal_bounds()
        goal = spaces.Box(goal_low, goal_high, dtype=np.float32)
        parts = {"observation": spaces.Box(low, high, dtype=np.float32)}
        for key, space in self._extra_parts(inner, obs_mode):
            parts[key] = space
        parts["achieved_goal"], parts["desired_goal"] = goal, goal
        return spaces.Dict(parts)

    @staticmethod
    def _extra_parts(inner, obs_mode: str):
        """The mode's parts beside the state (the state itself goes under ``observation``)."""
        if isinstance(inner, spaces.Dict) or isinstance(inner, dict):
            return [(k, v) for k, v in inner.items() if k != "state"]
        if obs_mode == "state":
            return []
        return [("depth" if obs_mode == "depth" else "rgb", inner)]

    def observations(self):
        """Every env's observation (leading axis N): the ``GoalEnv`` dict."""
        inner = super().observations()
        if isinstance(inner, dict):  # the mode's parts, the state among them when the mode has it
            obs = {k: v for k, v in inner.items() if k != "state"}
            state = inner.get("state")
        elif self.obs_mode == "state":  # the state itself: not computed twice
            obs, state = {}, inner
        else:
            obs, state = dict(self._extra_parts(inner, self.obs_mode)), None
        obs["observation"] = self.task.state_observation() if state is None else state
        obs["achieved_goal"] = self.task.achieved_goal().astype(np.float32)
        obs["desired_goal"] = self.task.goal.astype(np.float32)
        return obs

    def compute_reward(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """The reward the env pays for ``achieved_goal`` against ``desired_goal`` (arrays of
        3-D points, m, any leading shape; ``info`` is not read): what HER relabels with."""
        return self.task.compute_reward(achieved_goal, desired_goal, info)

    def compute_terminated(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """Reaching the goal does not end an episode (``GoalEnv``'s convention): all False."""
        return np.zeros(np.shape(achieved_goal)[:-1], dtype=bool)

    def compute_truncated(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """The goal never truncates an episode (the time limit does): all False."""
        return np.zeros(np.shape(achieved_goal)[:-1], dtype=bool)
