"""Goal-conditioned tissue manipulation on N worlds: bring a marked tissue point to a goal.

:class:`BatchedManipulation` is a :class:`~heml_gym.envs.task.TissueTask` (the world, its
graspers, the episode's draws) whose task is a goal drawn per episode in the scene's
target region: the marked tissue point (``scene.marker``) is the achieved goal, the
drawn point the desired goal, in Gymnasium-Robotics' ``GoalEnv`` form. The reward is a
function of the two (and nothing else), so that hindsight relabelling (HER) can
recompute it: :meth:`compute_reward`. Units: m, s, N, Pa.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .core import GRASPER_SIZE, POSITION_BOUND, STATE_HIGH, STATE_LOW, TaskSettings, as_settings, bounds_by_unit
from .measures import finite
from .scene import BuiltScene
from .spec import SpecError
from .task import STRAIN_BOUND, TissueTask

REWARD_TYPES = ("sparse", "dense")

#: The ``observation`` entries after the graspers' 7 each: (name, low, high, unit).
MANIPULATION_SPEC = ([(f"tracked_{i}_{a}", -POSITION_BOUND, POSITION_BOUND, "m") for i in range(4) for a in "xyz"]
                     + [("max_strain", 0.0, STRAIN_BOUND, "-")])


@dataclass(frozen=True)
class ManipulationSettings(TaskSettings):
    """TissueRetraction's settings (control step, jaws, strain thresholds, episode length;
    the exposure and hold settings are not used) and the goal's: ``goal_tolerance`` (m):
    success when the marked point is this close to the goal; ``reward_type``: ``"sparse"``
    (-1 per step away from the goal, 0 within tolerance) or ``"dense"`` (minus the
    distance, m); ``max_steps`` 50 (5 s)."""

    max_steps: int = 50
    goal_tolerance: float = 0.005
    reward_type: str = "sparse"

    def __post_init__(self):
        super().__post_init__()
        t = self.goal_tolerance
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (0 < t < math.inf):
            raise SpecError(f"ManipulationSettings.goal_tolerance: must be a positive length in metres, got {t!r}")
        if self.reward_type not in REWARD_TYPES:
            raise SpecError(f"ManipulationSettings.reward_type: must be one of {REWARD_TYPES}, got {self.reward_type!r}")


def goal_reward(achieved: np.ndarray, desired: np.ndarray, tolerance: float, reward_type: str) -> np.ndarray:
    """The reward of ``achieved`` against ``desired`` goals (``(..., 3)`` m, any leading
    shape): sparse ``-(distance > tolerance)``, dense ``-distance``; float32, one per goal."""
    d = np.linalg.norm(np.asarray(achieved, dtype=np.float64) - np.asarray(desired, dtype=np.float64), axis=-1)
    if reward_type == "dense":
        return (-d).astype(np.float32)
    return -(d > tolerance).astype(np.float32)


class BatchedManipulation(TissueTask):
    """N episodes of bringing ``scene.marker`` to a goal drawn in the scene's target region.

    Not terminated on success (``info["is_success"]`` says each step whether the marked
    point is within ``goal_tolerance``); terminated when the tissue tears or the physics
    fails, truncated after ``max_steps``. The cost is the retraction tasks' strain harm."""

    EPISODE_OPTIONS = {**TissueTask.EPISODE_OPTIONS, "goal": "m, (3,)"}

    def __init__(self, scene: BuiltScene, n_worlds: int, settings: ManipulationSettings | None = None,
                 weights=None, grippers: dict | None = None):
        if weights is not None:
            raise SpecError("weights: a manipulation task's reward is the goal distance alone (settings.reward_type), "
                            "it takes no reward weights")
        if scene.marker is None:
            raise SpecError(f"scene.marker: scene {scene.name!r} marks no tissue point to bring to the goal")
        super().__init__(scene, n_worlds, as_settings(settings, ManipulationSettings, "settings"), grippers)
        n, k = self.n, len(self.instruments)
        self.goal = np.zeros((n, 3))
        self.success = np.zeros(n, dtype=bool)
        low, high = (np.array([b for _, b, _, _ in MANIPULATION_SPEC], dtype=np.float32),
                     np.array([b for _, _, b, _ in MANIPULATION_SPEC], dtype=np.float32))
        hook_low, hook_high = bounds_by_unit(self.hook_fields())  # (the hooks' entries last)
        self._state_low = np.concatenate([np.tile(STATE_LOW[:GRASPER_SIZE], k), low, hook_low])
        self._state_high = np.concatenate([np.tile(STATE_HIGH[:GRASPER_SIZE], k), high, hook_high])

    target = property(lambda self: self.goal)  # what the camera draws: the goal

    # ------------------------------------------------------------------ reset
    def _draw(self, i: int, rng: np.random.Generator) -> None:
        self.goal[i] = rng.uniform(self.scene.target_low, self.scene.target_high)

    def set_episode(self, i: int, goal=None, **drawn) -> None:
        """:meth:`TissueTask.set_episode`, and the episode's ``goal`` (m, (3,), inside the workspace)."""
        if goal is not None:
            g = np.asarray(goal, dtype=np.float64)
            if g.shape != (3,) or not np.all(np.isfinite(g)):
                raise SpecError(f"goal: must be 3 finite coordinates (m), got {goal!r}")
            s = self.scene
            if np.any(g < s.workspace_low - 1e-12) or np.any(g > s.workspace_high + 1e-12):
                raise SpecError(f"goal: {g.tolist()} lies outside the workspace "
                                f"{s.workspace_low.tolist()}..{s.workspace_high.tolist()} m")
            self.goal[i] = g
        super().set_episode(i, **drawn)

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray, active: np.ndarray | None = None):
        """Apply ``actions`` (N, action_size) in [-1, 1]; returns reward, terminated,
        truncated and the info (per-world arrays), as the retraction task's."""
        st = self.settings
        out = self.advance(actions, active)
        failed = out.failed
        all_worlds = np.arange(self.n)
        self.max_strain = self.measure_strain(all_worlds)
        achieved = self.achieved_goal()
        distance = np.linalg.norm(achieved - self.goal, axis=1)
        reward = np.where(failed, 0.0, goal_reward(achieved, self.goal, st.goal_tolerance, st.reward_type))
        self.success = (distance <= st.goal_tolerance) & ~failed
        torn = (self.max_strain >= st.tear_strain) & ~failed
        terminated = torn | failed
        truncated = (self.steps >= st.max_steps) & ~terminated
        cost = self.harm(failed)
        info = {"goal_distance": finite(distance, nan=POSITION_BOUND), "max_strain": self.max_strain.copy(),
                **self.instrument_info(), "cost": cost, "damage": self.damage.copy(),
                "is_success": self.success.copy(), "tissue_torn": torn, **self.solver_info(out.stats),
                **self.wrist_info(all_worlds), **self.episode_info(all_worlds)}
        return reward.astype(np.float64), terminated, truncated, info

    def start_info(self, worlds) -> dict:
        """The ``info`` of ``worlds`` at their episodes' start, with :meth:`step`'s keys."""
        worlds = np.atleast_1d(np.asarray(worlds, dtype=np.int64))
        k = len(worlds)
        zero, no = np.zeros(k), np.zeros(k, dtype=bool)
        distance = np.linalg.norm(self.achieved_goal()[worlds] - self.goal[worlds], axis=1)
        return {"goal_distance": distance, "max_strain": self.max_strain[worlds].copy(),
                **self.instrument_info(worlds, start=True), "cost": zero.copy(), "damage": zero.copy(),
                "is_success": no.copy(), "tissue_torn": no.copy(), **self.solver_start_info(k),
                **self.wrist_info(worlds), **self.episode_info(worlds)}

    def compute_reward(self, achieved, desired, info=None) -> np.ndarray:
        """The reward :meth:`step` pays for ``achieved`` against ``desired`` goals (any
        leading shape; HER relabels with it). ``info`` is not read."""
        return goal_reward(achieved, desired, self.settings.goal_tolerance, self.settings.reward_type)

    # ------------------------------------------------------------ observation
    def achieved_goal(self) -> np.ndarray:
        """Where the marked tissue point is, ``(N, 3)`` m (clipped to the observation's bounds)."""
        return np.clip(finite(self.x[:, self.scene.marker], nan=0.0), -POSITION_BOUND, POSITION_BOUND)

    def goal_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the goal observations (m)."""
        return np.full(3, -POSITION_BOUND, dtype=np.float32), np.full(3, POSITION_BOUND, dtype=np.float32)

    def state_observation(self) -> np.ndarray:
        """The ``observation`` part: each grasper's 7 entries, the 4 tracked points (m) and
        the largest gauge strain, ``(N, 7 K + 13)`` float32, clipped to its bounds."""
        tracked = self.x[:, self.scene.tracked].reshape(self.n, -1)
        obs = np.concatenate([*self.instrument_observation(), tracked, self.max_strain[:, None],
                              *self.hook_observation()], axis=1)
        return np.clip(finite(obs, nan=0.0), self._state_low, self._state_high).astype(np.float32)

    def state_fields(self) -> list[tuple[str, str]]:
        """``(name, unit)`` of each ``observation`` entry."""
        return self.instrument_fields() + [(name, unit) for name, _, _, unit in MANIPULATION_SPEC] + self.hook_fields()

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the ``observation`` part."""
        return self._state_low.copy(), self._state_high.copy()


__all__ = ["BatchedManipulation", "ManipulationSettings", "goal_reward", "REWARD_TYPES", "MANIPULATION_SPEC"]
