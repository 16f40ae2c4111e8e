"""Scene-convergence checks beyond the main study: OrganRetraction, and TissueRetraction designs.

The main study (``benchmarks/scene_convergence.py``, docs/scene_convergence.md) checks the
5 % rule for TissueRetraction as shipped. This script reuses its replay protocol (the
scripted policy's actions recorded on the default model, replayed on every model; errors
over the default's episode against a fine reference) for two follow-ups:

* ``organ``: ``heml_gym/OrganRetraction-v0`` on gmsh meshes of 16 (default), 12 and 10 mm
  against 7 mm, seeds 0 and 1;
* ``designs``: TissueRetraction with other scene designs, on the worst seed of the main
  study (2), against 24x24x3: today's 5 mm jaw; a 12 mm jaw (a patch grasp); a 12 mm jaw
  with gravity, the flap resting on the organ (plane z = 0) and E 20-30 kPa (LapGym's
  slab: 27 kPa).

Writes docs/benchmarks/convergence_checks.{json,md}.

    python benchmarks/convergence_checks.py [organ] [designs]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import scene_convergence as sc  # noqa: E402
from common import RESULTS, machine_info, markdown_table, write_json  # noqa: E402
from heml_gym.envs import scripted  # noqa: E402
from heml_gym.envs.core import TaskSettings  # noqa: E402
from heml_gym.envs.organ_retraction import OrganRetractionEnv  # noqa: E402
from heml_gym.envs.retraction_env import RetractionEnv  # noqa: E402
from heml_gym.envs.tissue_retraction import tissue_scene  # noqa: E402

ORGAN_SIZES = (0.016, 0.012, 0.010)  # m; the first is the default
ORGAN_REFERENCE = 0.007
ORGAN_SEEDS = (0, 1)
ORGAN_STEPS = 30
TISSUE_MESHES = ((8, 8, 1), (12, 12, 1), (12, 12, 2), (16, 16, 2))
TISSUE_REFERENCE = (24, 24, 3)
TISSUE_SEED = 2
#: name -> (jaw radius m, gravity m/s^2, resting on the plane z = 0, E range Pa)
DESIGNS = {
    "today's scene (5 mm jaw)": (0.005, 0.0, False, (2e3, 5e3)),
    "12 mm jaw (a patch)": (0.012, 0.0, False, (2e3, 5e3)),
    "12 mm jaw, gravity, on the organ, E 20-30 kPa": (0.012, 9.81, True, (20e3, 30e3)),
}


def replay(env, seed: int, actions: np.ndarray) -> dict:
    """Per-step exposure, grasp force (N), largest edge strain, held vertices, outcomes."""
    env.reset(seed=seed)
    rec = {k: [] for k in ("exposure", "grasp_force", "max_strain", "held", "success", "torn", "diverged")}
    start = time.perf_counter()
    for a in actions:
        _, _, _, _, info = env.step(a)
        rec["exposure"].append(float(info["exposure"]))
        rec["grasp_force"].append(float(info["grasp_force"]))
        rec["max_strain"].append(float(info["max_strain"]))
        rec["held"].append(int(env.task.held[0].sum()))
        rec["success"].append(bool(info["is_success"]))
        rec["torn"].append(bool(info["tissue_torn"]))
        rec["diverged"].append(bool(info["simulation_diverged"]))
    rec["ms_per_step"] = 1e3 * (time.perf_counter() - start) / len(actions)
    rec["n_tets"] = env.task.scene.mesh.n_tets
    rec["substeps"] = env.task.substeps
    return rec


def record(env, policy, seed: int, steps: int) -> tuple[np.ndarray, int]:
    """The policy's actions over ``steps`` steps from ``reset(seed)`` and its episode length."""
    obs, _ = env.reset(seed=seed)
    policy.reset()
    actions, episode = [], None
    for k in range(steps):
        a = policy(obs)
        actions.append(a)
        obs, _, terminated, truncated, _ = env.step(a)
        if episode is None and (terminated or truncated):
            episode = k + 1
    return np.array(actions), episode or steps


def row(label: str, run: dict, ref: dict, window: int, **extra) -> dict:
    e = sc.errors(run, ref, window)
    return {"model": label, **extra, "n_tets": run["n_tets"], "ms_per_step": run["ms_per_step"],
            "held": max(run["held"]), "held_reference": max(ref["held"]), "window": window,
            "force_err": e["force_rel_err"], "force_err_mean": e["force_rel_err_mean"],
            "exposure_err": e["exposure_abs_err"], "exposure_err_mean": e["exposure_abs_err_mean"],
            "peak_strain": e["peak_strain"], "peak_strain_reference": float(max(ref["max_strain"][:window]))}


def organ_checks() -> list[dict]:
    rows = []
    settings = TaskSettings(safety=0.5)
    for seed in tqdm(ORGAN_SEEDS, desc="organ seeds"):
        actions, window = record(OrganRetractionEnv(settings=settings),
                                 scripted.scripted_policy("OrganRetraction"), seed, ORGAN_STEPS)
        ref = replay(OrganRetractionEnv(settings=settings, mesh_size=ORGAN_REFERENCE), seed, actions)
        for size in ORGAN_SIZES:
            run = replay(OrganRetractionEnv(settings=settings, mesh_size=size), seed, actions)
            rows.append(row(f"{1e3 * size:g} mm", run, ref, window, seed=seed, mesh_size_m=size))
    return rows


class DesignedTissueEnv(RetractionEnv):
    """TissueRetraction with another gravity, support plane and E range (a design check)."""

    def __init__(self, cells, settings, gravity: float, on_plane: bool, stiffness_range):
        scene = tissue_scene(cells)
        scene.gravity = (0.0, 0.0, -gravity)
        scene.floor = 0.0 if on_plane else None
        scene.stiffness_range = stiffness_range
        super().__init__(scene, "state", None, settings, None)


def design_checks() -> list[dict]:
    rows = []
    for name, (jaw, gravity, on_plane, e_range) in tqdm(DESIGNS.items(), desc="designs"):
        settings = TaskSettings(safety=0.5)
        settings.jaw_radius = jaw
        settings.grasp_reach = max(settings.grasp_reach, jaw)

        def env(cells):
            return DesignedTissueEnv(cells, settings, gravity, on_plane, e_range)

        actions, window = record(env(sc.DEFAULT[0]), scripted.scripted_policy("TissueRetraction"),
                                 TISSUE_SEED, sc.STEPS)
        ref = replay(env(TISSUE_REFERENCE), TISSUE_SEED, actions)
        for cells in TISSUE_MESHES:
            run = replay(env(cells), TISSUE_SEED, actions)
            rows.append(row("x".join(map(str, cells)), run, ref, window, design=name, seed=TISSUE_SEED))
    return rows


def table(rows: list[dict], first: str) -> str:
    return markdown_table(
        [first, "model", "tets", "ms/step", "held (model / ref.)", "force err max (mean)",
         "exposure err max (mean)", "peak strain (model / ref.)"],
        [[r.get("design", r.get("seed")), r["model"], r["n_tets"], f"{r['ms_per_step']:.1f}",
          f"{r['held']} / {r['held_reference']}",
          f"{100 * r['force_err']:.1f} % ({100 * r['force_err_mean']:.1f} %)",
          f"{r['exposure_err']:.2f} ({r['exposure_err_mean']:.3f})",
          f"{r['peak_strain']:.2f} / {r['peak_strain_reference']:.2f}"] for r in rows])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checks", nargs="*", help="organ and/or designs (default: both)")
    args = ap.parse_args(argv)
    args.checks = args.checks or ["organ", "designs"]
    unknown = set(args.checks) - {"organ", "designs"}
    if unknown:
        ap.error(f"unknown checks {sorted(unknown)}: choose from organ, designs")
    numba.set_num_threads(1)
    start = time.perf_counter()
    results = {}
    if "organ" in args.checks:
        results["organ"] = organ_checks()
    if "designs" in args.checks:
        results["designs"] = design_checks()
    wall = time.perf_counter() - start
    write_json("convergence_checks.json", {"machine": machine_info(), "wall_s": wall, **results})
    md = (f"Generated by `benchmarks/convergence_checks.py` in {wall:.0f} s (one thread); see "
          "docs/scene_convergence.md.\n")
    if "organ" in results:
        md += (f"\n**OrganRetraction.** Reference: {1e3 * ORGAN_REFERENCE:g} mm mesh, safety 0.5; the "
               f"scripted lift recorded on the 16 mm default ({ORGAN_STEPS} steps).\n\n"
               + table(results["organ"], "seed") + "\n")
    if "designs" in results:
        md += (f"\n**TissueRetraction designs (seed {TISSUE_SEED}).** Reference: "
               f"{'x'.join(map(str, TISSUE_REFERENCE))}, safety 0.5, same design.\n\n"
               + table(results["designs"], "design") + "\n")
    (RESULTS / "convergence_checks.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
