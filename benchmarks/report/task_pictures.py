"""Pictures of the two tasks for the README: each env's task camera (the view its exposure
is measured from) at the start of an episode and once the scripted fold has exposed the
target. Writes docs/img/tasks.png.

    python benchmarks/report/task_pictures.py
"""

from __future__ import annotations


import gymnasium as gym
import numpy as np
import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym.benchmarks.common import parse_arguments, IMAGES
from heml_gym.envs.scripted import scripted_policy

ENVS = {"heml_gym/TissueRetraction-v1": "TissueRetraction: fold the fat flap back off the tumour",
        "heml_gym/OrganRetraction-v2": "OrganRetraction: fold the liver lobe back off the tumour"}
SIZE = (300, 400)  # pixels


def views(env_id: str, seed: int = 3) -> tuple[np.ndarray, np.ndarray, float]:
    """The task camera's image at reset and at the first step with exposure >= 0.8."""
    env = gym.make(env_id).unwrapped
    state, _ = env.reset(seed=seed)
    start = env.camera_view(0, SIZE)["rgb"]
    policy = scripted_policy(env.scene)
    info = {"exposure": 0.0}
    for _ in range(env.task.settings.max_steps):
        state, _, terminated, truncated, info = env.step(policy(state))
        if info["exposure"] >= 0.8 or terminated or truncated:
            break
    return start, env.camera_view(0, SIZE)["rgb"], float(info["exposure"])


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(8, 6.4))
    for row, (env_id, title) in zip(axes, ENVS.items()):
        start, exposed, exposure = views(env_id)
        row[0].imshow(start)
        row[0].set_title(f"{title}\nstart: the tumour (yellow) hidden", fontsize=8, loc="left")
        row[1].imshow(exposed)
        row[1].set_title(f"held back: {exposure:.0%} of the tumour exposed", fontsize=8, loc="left")
        for ax in row:
            ax.set_axis_off()
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / "tasks.png", dpi=100)
    print(IMAGES / "tasks.png")
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
