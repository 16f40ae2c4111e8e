"""An animated rollout for the README: the shipped (pretrained) ONNX policy of each task
solving one seeded episode (seed 0), as the task camera (the view its exposure is measured
from) sees it, TissueRetraction and OrganRetraction side by side, one frame per env step
(0.1 s of tissue, so it plays in real time), the shorter episode's last frame held until
the longer one ends, and the end held about 1 s. Writes docs/img/rollout.gif.

    python benchmarks/report/rollout_gif.py
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym.agents.export import exported_policy
from heml_gym.benchmarks.common import parse_arguments, IMAGES

ENVS = {"heml_gym/TissueRetraction-v1": "TissueRetraction: fat flap",
        "heml_gym/OrganRetraction-v2": "OrganRetraction: liver lobe"}
SEED = 0
SIZE = (180, 240)  # pixels per panel (height, width)
STEP_MS = 100  # one env step (control_dt 0.1 s): real time
HOLD_MS = 1000  # the last frame


def episode(env_id: str, seed: int = SEED) -> tuple[list[np.ndarray], list[dict], bool]:
    """The task camera's image at reset and after every step of the pretrained policy's
    episode, the info of each (the reset's too), and whether the episode succeeded."""
    env = gym.make(env_id).unwrapped
    policy = exported_policy("pretrained", env_id, env_id)
    state, info = env.reset(seed=seed)
    frames, infos = [env.camera_view(0, SIZE)["rgb"]], [info]
    terminated = truncated = False
    while not (terminated or truncated):
        state, _, terminated, truncated, info = env.step(policy(state))
        frames.append(env.camera_view(0, SIZE)["rgb"])
        infos.append(info)
    env.close()
    return frames, infos, bool(infos[-1].get("is_success", False))


def panel(rgb: np.ndarray, title: str, info: dict, step: int, done: bool, success: bool):
    """One task's image with its name, the time and the exposure written on it."""
    from PIL import Image, ImageDraw, ImageFont

    img = Image.fromarray(rgb)
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default(size=12)
    status = f"t {step * STEP_MS / 1000:4.1f} s   exposed {info.get('exposure', 0.0):4.0%}"
    if done:
        status += "   success" if success else "   (ended)"
    for y, text in ((3, title), (SIZE[0] - 17, status)):
        box = draw.textbbox((5, y), text, font=font)
        draw.rectangle((box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2), fill=(0, 0, 0))
        draw.text((5, y), text, fill=(255, 255, 255), font=font)
    return img


def main() -> int:
    from PIL import Image

    runs = []
    for env_id, title in ENVS.items():
        frames, infos, success = episode(env_id)
        print(f"{env_id}: seed {SEED}, {len(frames) - 1} steps, exposure {infos[-1]['exposure']:.2f}, "
              f"success {success}")
        runs.append((title, frames, infos, success))
    n = max(len(frames) for _, frames, _, _ in runs)
    movie = []
    for k in range(n):
        sheet = Image.new("RGB", (SIZE[1] * len(runs) + 4 * (len(runs) - 1), SIZE[0]), (255, 255, 255))
        for j, (title, frames, infos, success) in enumerate(runs):
            i = min(k, len(frames) - 1)
            sheet.paste(panel(frames[i], title, infos[i], i, i == len(frames) - 1, success), (j * (SIZE[1] + 4), 0))
        movie.append(sheet)
    # one palette for the whole movie (from a few frames spread over it): no flicker, small file
    sample = Image.new("RGB", (movie[0].width, movie[0].height * 4))
    for m, k in enumerate(np.linspace(0, n - 1, 4).astype(int)):
        sample.paste(movie[k], (0, m * movie[0].height))
    palette = sample.quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    movie = [frame.quantize(palette=palette, dither=Image.Dither.NONE) for frame in movie]
    IMAGES.mkdir(parents=True, exist_ok=True)
    out = IMAGES / "rollout.gif"
    movie[0].save(out, save_all=True, append_images=movie[1:], duration=[STEP_MS] * (n - 1) + [HOLD_MS],
                  loop=0, optimize=True)
    print(f"{out}: {out.stat().st_size} bytes, {n} frames, {((n - 1) * STEP_MS + HOLD_MS) / 1000:.1f} s")
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
