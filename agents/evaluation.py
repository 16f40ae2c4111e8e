"""Evaluation of a policy on fresh seeded episodes: success rate with its Wilson
interval, final exposure, worst strain, episode length. Shared by the SB3 and RLlib
backends and the CLI (``heml-gym eval``)."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np

import heml_gym.envs  # noqa: F401  (registers the environments)

__all__ = ["ENDINGS", "episode_ending", "evaluate_policy", "wilson_interval"]


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


#: how an episode can end (:func:`episode_ending`)
ENDINGS = ("success", "torn", "critical", "solver", "time", "other")


def episode_ending(info: dict, truncated: bool) -> str:
    """How an episode ended, from its last ``info``: ``success``; ``torn`` (the tissue tore);
    ``critical`` (energy near a critical structure); ``solver`` (the step diverged or did not
    converge); ``time`` (out of steps, ``truncated``); else ``other``."""
    if bool(info.get("is_success", False)):
        return "success"
    if bool(info.get("tissue_torn", False)):
        return "torn"
    if bool(info.get("critical_hit", False)):
        return "critical"
    if bool(info.get("simulation_diverged", False)) or not bool(info.get("solver_converged", True)):
        return "solver"
    return "time" if truncated else "other"


def evaluate_policy(policy, env_id: str, episodes: int = 20, seed: int = 10_000,
                    obs_mode: str = "state", env_kwargs: dict | None = None) -> dict:
    """Success rate (with its 95 % Wilson interval), mean final exposure (of a goal task: the
    final distance to the goal, m) and max strain, and
    the tissue harm: the mean episode ``damage`` (strain x s, the summed ``info["cost"]``)
    and how many episodes did any; the range of the episodes' Young's moduli (Pa); and
    how many episodes ended each way (``endings``: :data:`ENDINGS`).

    ``policy`` maps an observation to an action. Episodes use seeds ``seed, seed+1, ...``;
    the env is ``gym.make(env_id, obs_mode=obs_mode, **env_kwargs)`` (the run's scene,
    physics and settings).
    """
    from heml_gym.envs import episode_steps

    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"--episodes: must be an integer >= 1, got {episodes!r}")
    env = gym.make(env_id, obs_mode=obs_mode, max_episode_steps=episode_steps(env_kwargs), **(env_kwargs or {}))
    successes, exposures, strains, lengths, damages, stiffness = 0, [], [], [], [], []
    endings = dict.fromkeys(ENDINGS, 0)
    for k in range(episodes):
        obs, info = env.reset(seed=seed + k)
        stiffness.append(float(np.asarray(info["young_modulus"]).reshape(-1)[0]))
        if hasattr(policy, "reset"):
            policy.reset()
        done, steps, worst = False, 0, 0.0
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs))
            done = terminated or truncated
            steps += 1
            worst = max(worst, info["max_strain"])
        successes += bool(info["is_success"])
        endings[episode_ending(info, truncated)] += 1
        exposures.append(info.get("exposure", info.get("goal_distance")))
        strains.append(worst)
        lengths.append(steps)
        damages.append(info["damage"])
    env.close()
    lo, hi = wilson_interval(successes, episodes)
    final = "mean_final_exposure" if "exposure" in info else "mean_final_goal_distance"  # (m, of a goal task)
    return {"episodes": episodes, "success_rate": successes / episodes, "success_ci95": [lo, hi],
            final: float(np.mean(exposures)), "mean_max_strain": float(np.mean(strains)),
            "mean_episode_length": float(np.mean(lengths)),
            "mean_damage": float(np.mean(damages)), "episodes_with_damage": int(np.sum(np.array(damages) > 0)),
            "young_modulus_range": [min(stiffness), max(stiffness)], "endings": endings}
