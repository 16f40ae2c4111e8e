"""The scripted baseline on every difficulty level of both retraction tasks.

For each env and level (:mod:`heml_gym.envs.difficulty`): the scripted fold
(:func:`heml_gym.envs.scripted.scripted_policy`) on ``--episodes`` seeded episodes:
success rate (95 % Wilson interval), median and mean episode length (env steps of
0.1 s), mean largest gauge strain, and mean CPU seconds per episode.

Writes docs/benchmarks/task_difficulty.{json,md}.

    python benchmarks/task_difficulty.py [--episodes 20]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine_info, markdown_table, write_json  # noqa: E402
from heml_gym.envs.organ_retraction import JAWS_AND_ADHESION as ORGAN_JAWS_AND_ADHESION  # noqa: E402
from heml_gym.envs.tissue_retraction import JAWS_AND_ADHESION  # noqa: E402

ENVS = ("heml_gym/TissueRetraction-v0", "heml_gym/OrganRetraction-v0")
ADHESION = JAWS_AND_ADHESION["adhesion"]
#: options that are not defaults yet, at the default level: (env, what, env kwargs: changes to the default scene)
VARIANTS = [
    ("heml_gym/TissueRetraction-v0", "the underside stuck 0-20 mm out from the hinge (scene.adhesion)",
     {"scene": {"adhesion": ADHESION}}),
    ("heml_gym/TissueRetraction-v0", "40 mm jaws: only the part of the edge between them held "
     "(scene.gripper.jaw_length)", {"scene": {"gripper": {"jaw_length": 0.04}}}),
    ("heml_gym/TissueRetraction-v0", "both (configs/quick_jaws_adhesion.yaml)", {"scene": JAWS_AND_ADHESION}),
    ("heml_gym/TissueRetraction-v0", "30 mm jaws", {"scene": {"gripper": {"jaw_length": 0.03}}}),
    ("heml_gym/OrganRetraction-v0", "20 mm jaws: the middle 20 mm of the 40 mm footprint held",
     {"scene": {"gripper": {"jaw_length": 0.02}}}),
    ("heml_gym/OrganRetraction-v0", "the underside stuck to the support 0-60 mm out from the base (scene.adhesion)",
     {"scene": {"adhesion": ORGAN_JAWS_AND_ADHESION["adhesion"]}}),
    ("heml_gym/OrganRetraction-v0", "both (organ_retraction.JAWS_AND_ADHESION)", {"scene": ORGAN_JAWS_AND_ADHESION}),
    ("heml_gym/OrganRetraction-v0", "the target beneath the lobe's base third (x 30-45 mm; level 2: 15-27.5 mm)",
     {"scene": {"target": {"low": [0.03, -0.02, -0.023], "high": [0.045, 0.02, -0.023]}}}),
]


def measure(env_id: str, level: int, episodes: int, variant: str | None = None, kwargs: dict | None = None) -> dict:
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401
    from heml_gym.agents.train import wilson_interval
    from heml_gym.envs.scripted import run_episodes, scripted_policy

    env = gym.make(env_id, difficulty=level, **(kwargs or {}))  # scene: changes to the default scene
    t0 = time.process_time()
    run = run_episodes(env, scripted_policy(env.unwrapped.scene), episodes)
    cpu = (time.process_time() - t0) / episodes
    env.close()
    k = int(np.sum(run["successes"]))
    return {"env": env_id, "difficulty": level, "variant": variant, "episodes": episodes, "success_rate": k / episodes,
            "success_ci95": list(wilson_interval(k, episodes)), "median_length": float(np.median(run["lengths"])),
            "mean_length": run["mean_length"], "lengths": run["lengths"], "mean_max_strain": run["mean_max_strain"],
            "cpu_s_per_episode": cpu}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=20)
    args = ap.parse_args(argv)
    from heml_gym.envs.difficulty import LEVELS

    rows = []
    for env_id in ENVS:
        for level in LEVELS:
            rows.append(measure(env_id, level, args.episodes))
            r = rows[-1]
            print(env_id, level, f"{r['success_rate']:.0%}", r["median_length"], flush=True)
    variants = []
    for env_id, what, kwargs in VARIANTS:
        variants.append(measure(env_id, 1, args.episodes, what, kwargs))
        print(env_id, what, f"{variants[-1]['success_rate']:.0%}", flush=True)
    m = machine_info()
    write_json("task_difficulty.json", {"machine": m, "rows": rows, "variants": variants})

    def cells(r):
        return [f"{r['success_rate']:.0%} ({r['success_ci95'][0]:.0%}-{r['success_ci95'][1]:.0%})",
                f"{r['median_length']:.0f} ({r['mean_length']:.1f})", f"{r['mean_max_strain']:.2f}",
                f"{r['cpu_s_per_episode']:.2f}"]

    measures = ["scripted success (95 % interval)", "episode length: median (mean), steps", "mean max gauge strain",
                "CPU s per episode"]
    table = markdown_table(["env", "difficulty", "task"] + measures,
                           [[r["env"].split("/")[1], r["difficulty"], LEVELS[r["difficulty"]].description] + cells(r)
                            for r in rows])
    options = markdown_table(["env", "option (at difficulty 1)"] + measures,
                             [[r["env"].split("/")[1], r["variant"]] + cells(r) for r in variants])
    text = (f"Generated by `benchmarks/task_difficulty.py` on {m['cpu']}, {m['date']}: the scripted fold on "
            f"{args.episodes} seeded episodes (seeds 0-{args.episodes - 1}) per env and level; 0.1 s per step.\n\n"
            + table + "\nOptions that are not defaults yet: per-episode variation, and the lobe's target placed "
            "deeper (the same scripted fold: it does not know where the tissue is stuck; with jaws shorter than the "
            "grasp region it closes at the region's middle and folds on an arc 0.9 times the grasp's distance from "
            "the hinge):\n\n"
            + options + "\n")
    (RESULTS / "task_difficulty.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
