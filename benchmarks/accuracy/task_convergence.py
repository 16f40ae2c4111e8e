"""Convergence of the newer tasks' default meshes along their scripted solutions.

The rule of docs/studies/scene_convergence.md, for BimanualRetraction, TissueManipulation,
PushRetraction and GallbladderDissection: per seed, the scripted expert runs on the default mesh and its actions
are recorded; the same actions are replayed on a mesh twice as fine each way (8x the
cells), solved to a tighter tolerance in shorter steps (0.025 s, 1e-4 of the weight), the
seed fixing E, the target or goal and the starts on both. Errors over the default's
episode:

* force: ``max_t |F(t) - F_ref(t)| / max_t F_ref(t)``, F the instruments' summed force
  (N, the step mean: the graspers' grasp force, a paddle's push), as for the retraction tasks;
* BimanualRetraction, PushRetraction, GallbladderDissection: exposure (the dissection's:
  the lesser of its two ducts'), ``max_t |e(t) - e_ref(t)|`` (a fraction) with half a step of
  timing tolerance, as scene_convergence.py measures it;
* TissueManipulation: the marked point, ``max_t |p(t) - p_ref(t)|`` over the largest distance
  it travels from its start on the fine mesh (a fraction of the motion).

Within 5 % when both errors are <= 0.05 on the worst seed; the owner allows a jaw-length
setting up to 8 % in force, stated with the figure.

Writes docs/benchmarks/task_convergence.{json,md}.

    python benchmarks/accuracy/task_convergence.py [--seeds 0,1,2] [--envs ID,...] [--from-json]

``--envs`` measures only those tasks and keeps the stored rows of the others.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from tqdm import tqdm

from heml_gym.benchmarks.common import RESULTS, machine_info, markdown_table, store_and_report

#: task -> (its size argument, the default, twice as fine each way)
TASKS = {"heml_gym/BimanualRetraction-v0": ("cells", (12, 24, 2), (24, 48, 4)),
         "heml_gym/TissueManipulation-v0": ("cells", (12, 12, 2), (24, 24, 4)),
         "heml_gym/PushRetraction-v0": ("mesh_size", 0.010, 0.005),
         "heml_gym/GallbladderDissection-v0": ("mesh_size", 0.005, 0.0025)}
FINE_PHYSICS = {"max_dt": 0.025, "newton_tol": 1e-4, "max_newton": 500}
TOLERANCE = 0.05


def rollout(env_id: str, seed: int, size, physics=None, actions=None) -> dict:
    """The scripted expert's episode (``actions`` None: recorded), or ``actions`` replayed
    (termination ignored) on the mesh of ``size`` (the task's size argument): per step the
    instruments' summed force, exposure or marked point."""
    import gymnasium as gym

    from heml_gym.envs.scripted import scripted_policy

    env = gym.make(env_id, **{TASKS[env_id][0]: size}, physics=physics, max_episode_steps=None).unwrapped
    obs, _ = env.reset(seed=seed)
    policy = scripted_policy(env.scene) if actions is None else None
    taken, force, progress = [], [], []
    steps = len(actions) if actions is not None else env.task.settings.max_steps
    for k in range(steps):
        a = policy(obs) if policy is not None else actions[k]
        obs, _, terminated, _, info = env.step(a)
        taken.append(np.asarray(a))
        force.append(float(np.linalg.norm(np.sum([g.force[0] for g in env.task.instruments], axis=0))))
        progress.append(info["exposure"] if "exposure" in info else np.asarray(obs["achieved_goal"], dtype=float))
        if not info["solver_converged"]:
            raise RuntimeError(f"{env_id} seed {seed} on {size}: a step did not converge (step {k})")
        if policy is not None and terminated:
            break
    return {"actions": np.array(taken), "force": np.array(force), "progress": np.array(progress)}


def measure(seeds, envs) -> dict:
    results = {"machine": machine_info(), "seeds": list(seeds), "fine_physics": FINE_PHYSICS, "results": {}}
    with tqdm(total=len(envs) * len(seeds), desc="seeds") as bar:
        for env_id in envs:
            _, default, fine = TASKS[env_id]
            rows = []
            for seed in seeds:
                run = rollout(env_id, seed, default)
                ref = rollout(env_id, seed, fine, FINE_PHYSICS, actions=run["actions"])
                force = float(np.max(np.abs(run["force"] - ref["force"])) / max(ref["force"].max(), 1e-12))
                if run["progress"].ndim == 1:  # exposure, with half a step of timing tolerance (scene_convergence's)
                    from heml_gym.benchmarks.accuracy.scene_convergence import tolerant_exposure_error

                    progress = tolerant_exposure_error(run["progress"], ref["progress"])
                    travel = None
                else:  # the marked point (m), over how far it travels
                    travel = float(np.max(np.linalg.norm(ref["progress"] - ref["progress"][0], axis=1)))
                    progress = float(np.max(np.linalg.norm(run["progress"] - ref["progress"], axis=1)) / travel)
                rows.append({"seed": seed, "steps": len(run["actions"]), "force_error": force,
                             "progress_error": progress, "travel_m": travel,
                             "peak_force_n": float(ref["force"].max()), "hold_force_n": float(run["force"][-1]),
                             "hold_force_ref_n": float(ref["force"][-1])})
                bar.update()
            results["results"][env_id] = {"default_cells": _size(default), "fine_cells": _size(fine), "seeds": rows,
                                          "machine": results["machine"]}
    return results


def _size(size):
    """A mesh size as stored: cells as a list, an element size (m) as a number."""
    return list(size) if isinstance(size, (tuple, list)) else float(size)


def _shown(size) -> str:
    return " x ".join(map(str, size)) + " cells" if isinstance(size, list) else f"{size * 1e3:g} mm elements"


def report(data: dict) -> str:
    rows = []
    for env_id, t in data["results"].items():
        worst_f = max(r["force_error"] for r in t["seeds"])
        worst_p = max(r["progress_error"] for r in t["seeds"])
        what = "marked point / its travel" if "Manipulation" in env_id else "exposure"
        verdict = "within 5 %" if max(worst_f, worst_p) <= TOLERANCE else (
            "within the 8 % allowed a jaw-length setting" if max(worst_f, worst_p) <= 0.08 else "outside 8 %")
        rows.append([f"`{env_id}`", _shown(t["default_cells"]), _shown(t["fine_cells"]),
                     f"{100 * worst_f:.1f} %", f"{what}: {100 * worst_p:.1f} %", verdict])
    m = data["machine"]
    seeds = data["seeds"]
    return ("Each task's scripted solution on its default mesh, its actions replayed on a mesh twice as fine each way, "
            "solved in 0.025 s steps to 1e-4 of the weight; worst of seeds "
            f"{', '.join(map(str, seeds))} ({m['cpu']}, {m['date']}; `python benchmarks/accuracy/task_convergence.py`). "
            "Force: the instruments' summed force's largest gap over its peak (a paddle's push; the graspers' grasp). "
            "Rows measured in a later run than the header's name their machine and date below the table.\n\n"
            + markdown_table(["task", "default mesh", "fine mesh", "force error", "progress error", "verdict"], rows)
            + "".join(f"\n`{env_id}`: {t['machine']['cpu']}, {t['machine']['date']}.\n"
                      for env_id, t in data["results"].items()
                      if "machine" in t and t["machine"]["date"] != m["date"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--envs", default=",".join(TASKS), help="comma-separated task ids (the others' rows are kept)")
    ap.add_argument("--from-json", action="store_true", help="only rewrite the table from the stored result")
    args = ap.parse_args(argv)
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: comma-separated integers, got {args.seeds!r}")
    envs = [e for e in args.envs.split(",") if e]
    unknown = [e for e in envs if e not in TASKS]
    if unknown or not envs:
        ap.error(f"--envs: give ids among {', '.join(TASKS)}, got {args.envs!r}")
    data = None
    if not args.from_json:
        data = measure(seeds, envs)
        stored = RESULTS / "task_convergence.json"
        if set(envs) != set(TASKS) and stored.is_file():  # keep the other tasks' rows, each with its machine
            old = json.loads(stored.read_text())
            for env_id, row in old["results"].items():
                if env_id not in envs:
                    row.setdefault("machine", old["machine"])
                    data["results"][env_id] = row
            data["results"] = {e: data["results"][e] for e in TASKS if e in data["results"]}
    store_and_report("task_convergence", data, report, envs=list(TASKS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
