"""Pictures of the two newer tasks for docs/tasks.md: BimanualRetraction's task camera at the
start and once both graspers' scripted folds have exposed the tumour; TissueManipulation's
camera at the start and once the scripted expert has brought the marked point to its goal
(the goal drawn as a yellow sphere of the 5 mm tolerance). Writes docs/img/new_tasks.png.

    python benchmarks/report/new_task_pictures.py
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym.benchmarks.common import IMAGES, parse_arguments
from heml_gym.envs.scripted import scripted_policy

SIZE = (300, 400)  # pixels


def views(env_id: str, done, seed: int = 3, settle: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """The task camera's image at reset and at the first step where ``done(info)`` holds,
    ``settle`` steps later."""
    env = gym.make(env_id).unwrapped
    obs, _ = env.reset(seed=seed)
    start = env.camera_view(0, SIZE)["rgb"]
    policy = scripted_policy(env.scene)
    reached = None
    for k in range(env.task.settings.max_steps):
        obs, _, terminated, truncated, info = env.step(policy(obs))
        if reached is None and done(info):
            reached = k
        if terminated or truncated or (reached is not None and k >= reached + settle):
            break
    return start, env.camera_view(0, SIZE)["rgb"], info


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(8, 6.4))
    start, end, info = views("heml_gym/BimanualRetraction-v0", lambda i: i["exposure"] >= 0.8)
    axes[0, 0].imshow(start)
    axes[0, 0].set_title("BimanualRetraction: two graspers, one wide soft flap\nstart: the tumour hidden",
                         fontsize=8, loc="left")
    axes[0, 1].imshow(end)
    axes[0, 1].set_title(f"folded back together: {info['exposure']:.0%} exposed, "
                         f"peak gauge strain {info['max_strain']:.2f}", fontsize=8, loc="left")
    start, end, info = views("heml_gym/TissueManipulation-v0", lambda i: i["is_success"], settle=3)
    axes[1, 0].imshow(start)
    axes[1, 0].set_title("TissueManipulation: bring the free edge's middle to the goal\nstart: the goal "
                         "(yellow) above the flap", fontsize=8, loc="left")
    axes[1, 1].imshow(end)
    axes[1, 1].set_title(f"reached: {info['goal_distance'] * 1e3:.1f} mm from the goal", fontsize=8, loc="left")
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / "new_tasks.png", dpi=100)
    print(IMAGES / "new_tasks.png")
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
