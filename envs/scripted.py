"""Scripted baseline for the retraction tasks: grasp the free edge, fold the tissue back.

The policy reads only the state observation (gripper position, grasp flag). It closes
the gripper where it starts (next to the free edge); once holding tissue it moves the
gripper along a circular arc about the attached edge (the hinge), keeping its distance
to the hinge so the tissue is folded rather than stretched, up to ``max_angle``.
"""

from __future__ import annotations

import math

import numpy as np


class FoldBackPolicy:
    """Grasp, then fold the tissue about the hinge line ``x = hinge[0], z = hinge[1]``.

    ``direction`` is +1 when the tissue extends from the hinge towards +x, -1 towards -x.
    ``step_angle``: radians added to the arc angle per step; ``max_angle``: where to stop
    (past vertical, so the tissue lies back over its attachment); ``max_speed`` and
    ``control_dt`` convert a displacement (m) into a velocity command.
    """

    def __init__(self, hinge=(0.0, 0.008), step_angle=0.06, max_angle=1.9, max_speed=0.05,
                 control_dt=0.1, direction=1.0):
        self.hinge = np.asarray(hinge, dtype=np.float64)
        self.direction = 1.0 if direction >= 0 else -1.0  # -1: the tissue extends towards -x
        self.step_angle = float(step_angle)
        self.max_angle = float(max_angle)
        self.scale = 1.0 / (max_speed * control_dt)
        self.radius = None

    def reset(self):
        self.radius = None

    def __call__(self, obs) -> np.ndarray:
        state = obs["state"] if isinstance(obs, dict) else obs
        gripper, grasping = np.asarray(state[0:3], dtype=np.float64), state[3] > 0.5
        if not grasping:
            self.radius = None
            return np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32)
        sign = self.direction
        rel = np.array([sign * (gripper[0] - self.hinge[0]), gripper[2] - self.hinge[1]])
        if self.radius is None:
            self.radius = float(np.hypot(*rel))
        angle = min(math.atan2(rel[1], rel[0]) + self.step_angle, self.max_angle)
        target = self.radius * np.array([math.cos(angle), math.sin(angle)])
        move = np.array([self.hinge[0] + sign * target[0] - gripper[0], 0.0,
                         self.hinge[1] + target[1] - gripper[2]]) * self.scale
        return np.concatenate([np.clip(move, -1.0, 1.0), [1.0]]).astype(np.float32)


def scripted_policy(scene_name: str) -> FoldBackPolicy:
    """The scripted baseline of a scene family ("TissueRetraction" or "OrganRetraction")."""
    from . import organ_retraction, tissue_retraction

    if scene_name == "TissueRetraction":  # fold the flap back over its attached edge
        return FoldBackPolicy(hinge=tissue_retraction.HINGE, direction=1.0, max_angle=1.9)
    if scene_name == "OrganRetraction":  # lift the lobe's thin edge about its attachment
        return FoldBackPolicy(hinge=organ_retraction.HINGE, direction=-1.0, max_angle=0.8)
    raise ValueError(f"no scripted policy for scene {scene_name!r}")


def run_episodes(env, policy, episodes: int, seed: int = 0) -> dict:
    """Roll ``policy`` out for ``episodes`` seeded episodes; success rate and means."""
    successes, exposures, strains, lengths = [], [], [], []
    for k in range(episodes):
        obs, info = env.reset(seed=seed + k)
        policy.reset()
        done = False
        steps = 0
        max_strain = 0.0
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            done = terminated or truncated
            steps += 1
            max_strain = max(max_strain, info["max_strain"])
        successes.append(bool(info["is_success"]))
        exposures.append(info["exposure"])
        strains.append(max_strain)
        lengths.append(steps)
    return {"episodes": episodes, "success_rate": float(np.mean(successes)),
            "mean_final_exposure": float(np.mean(exposures)), "mean_max_strain": float(np.mean(strains)),
            "mean_length": float(np.mean(lengths))}
