"""Cost-constrained training: a Lagrange multiplier on the episode's tissue damage.

With a ``constraint`` section in a run config (``budget``: the damage an episode may do,
strain x s, the sum of ``info["cost"]``), the learner maximises ``reward - lambda cost``
per step, and after each rollout the multiplier follows the constraint's violation by
dual ascent, ``lambda <- max(0, lambda + multiplier_lr (J_c - budget))``, ``J_c`` the mean
damage of the episodes that ended during the rollout: it grows while episodes do more
damage than the budget and relaxes to 0 when they do less. This is the Lagrangian
relaxation of PPO-Lagrangian (Ray, Achiam and Amodei 2019, "Benchmarking Safe Exploration
in Deep Reinforcement Learning") in its reward-penalty form, on SB3's PPO or SAC as they
are (no separate cost critic). The multiplier's history goes to ``constraint.json`` in
the run folder and to tensorboard (``constraint/multiplier``, ``constraint/episode_cost``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnvWrapper

__all__ = ["CostPenalty", "MultiplierUpdate"]


class CostPenalty(VecEnvWrapper):
    """Rewards minus ``multiplier x info["cost"]``; keeps each ended episode's damage."""

    def __init__(self, venv, multiplier: float = 0.0):
        super().__init__(venv)
        self.multiplier = float(multiplier)
        self._episode_cost = np.zeros(self.num_envs)
        self.ended_costs: list[float] = []

    def reset(self):
        self._episode_cost[:] = 0.0
        return self.venv.reset()

    def step_wait(self):
        obs, reward, done, infos = self.venv.step_wait()
        cost = np.array([float(info.get("cost", 0.0)) for info in infos])
        self._episode_cost += cost
        for i in np.flatnonzero(done):
            infos[i]["episode_cost"] = float(self._episode_cost[i])
            self.ended_costs.append(float(self._episode_cost[i]))
            self._episode_cost[i] = 0.0
        return obs, (reward - self.multiplier * cost).astype(np.float32), done, infos


class MultiplierUpdate(BaseCallback):
    """After each rollout, ``lambda <- max(0, lambda + lr (J_c - budget))`` on ``penalty``
    (a :class:`CostPenalty`); the history is written to ``path`` (JSON)."""

    def __init__(self, penalty: CostPenalty, budget: float, lr: float, path: str | Path):
        super().__init__()
        self.penalty, self.budget, self.lr, self.path = penalty, float(budget), float(lr), Path(path)
        self.history: list[dict] = []

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        ended = self.penalty.ended_costs
        if not ended:
            return
        j_c = float(np.mean(ended))
        self.penalty.ended_costs = []
        self.penalty.multiplier = max(0.0, self.penalty.multiplier + self.lr * (j_c - self.budget))
        self.history.append({"timesteps": int(self.num_timesteps), "episode_cost": j_c, "episodes": len(ended),
                             "multiplier": self.penalty.multiplier})
        self.logger.record("constraint/episode_cost", j_c)
        self.logger.record("constraint/multiplier", self.penalty.multiplier)
        self.path.write_text(json.dumps({"budget": self.budget, "multiplier_lr": self.lr,
                                         "history": self.history}, indent=1))
