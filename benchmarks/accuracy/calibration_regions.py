"""Calibration of a Young's modulus that varies over the tissue: one E per half.

The tissue of calibration.py (nu 0.43) with the half of its rest bounding box nearer the
attachment (x low) at 0.7 and the other at 1.3 times 5,500 Pa (3,850 and 7,150 Pa;
``physics.stiffness_regions``), observed along the same scripted retraction and hold
(10 tracked points with 0.5 mm noise, the jaws' force with 0.01 N noise), then fitted with
``heml-gym calibrate --regions 2x1x1``'s problem: each half's E and nu from the points,
each half's E from the force. Cases: the flap observed on its own default mesh (what the
data identify, without model error); the flap observed on 24 x 24 x 4 cells in 0.025 s
steps and fitted on the default and on 18 x 18 x 3 cells (the model error of
calibration_mesh.py, whose flap observer is not converged next to the jaws' line); the
lobe observed on a 5 mm lobe in 0.025 s steps and fitted on a 7 mm one (the model that
meets the 5 % bar for one E); the flap with its jaws holding a 10 mm patch on a free wrist
(``scene.gripper.wrist_reach``, whose tracked points converge with the mesh, unlike the
line grasp's) observed on 24 x 24 x 4 cells in 0.025 s steps and fitted on 18 x 18 x 3
cells. One thread.

Writes docs/benchmarks/calibration_regions.{json,md}.

    python benchmarks/accuracy/calibration_regions.py           # ~30 min on one core
    python benchmarks/accuracy/calibration_regions.py --case 3  # one case; the others' stored rows kept
"""

from __future__ import annotations

import argparse
import copy
import json

import numba

from heml_gym.benchmarks.accuracy.calibration import FORCE_NOISE, POINT_NOISE, SEED, TRUTH, fit_case, observe
from heml_gym.benchmarks.common import RESULTS, machine_info, markdown_table, store_and_report

ENV = "heml_gym/TissueRetraction-v1"
LOBE = "heml_gym/OrganRetraction-v2"
GRID = (2, 1, 1)
RELATIVE = (0.7, 1.3)
REGIONS = {"stiffness_regions": {"grid": list(GRID), "relative": list(RELATIVE)}}
#: (case, env, observer's keyword arguments, [(fitted model, its keyword arguments)])
CASES = [
    ("flap, observed on the default mesh (12 x 12 x 2 cells, 0.05 s steps)", ENV, {},
     [("12 x 12 x 2 cells (the default)", {})]),
    ("flap, observed on 24 x 24 x 4 cells in 0.025 s steps", ENV,
     {"scene": {"tissue": {"cells": [24, 24, 4]}}, "physics": {"max_dt": 0.025}},
     [("12 x 12 x 2 cells (the default)", {}), ("18 x 18 x 3 cells", {"scene": {"tissue": {"cells": [18, 18, 3]}}})]),
    ("lobe, observed on a 5 mm lobe in 0.025 s steps", LOBE, {"mesh_size": 0.005, "physics": {"max_dt": 0.025}},
     [("7 mm lobe", {"mesh_size": 0.007})]),
    ("flap with its jaws on a free wrist (10 mm patch), observed on 24 x 24 x 4 cells in 0.025 s steps", ENV,
     {"scene": {"tissue": {"cells": [24, 24, 4]}, "gripper": {"wrist_reach": 0.01}}, "physics": {"max_dt": 0.025}},
     [("18 x 18 x 3 cells", {"scene": {"tissue": {"cells": [18, 18, 3]}, "gripper": {"wrist_reach": 0.01}}})]),
]
FITS = {"points": ("young_modulus", "poisson_ratio"), "force": ("young_modulus",)}


def _with_regions(kwargs: dict) -> dict:
    kwargs = copy.deepcopy(kwargs)
    kwargs["physics"] = {**kwargs.get("physics", {}), **REGIONS}
    return kwargs


def measure(cases) -> dict:
    """The ``cases`` (indices into :data:`CASES`) measured; the other cases' stored rows kept."""
    numba.set_num_threads(1)
    truth = [TRUTH["young_modulus"] * r for r in RELATIVE]
    measured = [CASES[i][0] for i in cases]
    stored = [] if len(cases) == len(CASES) else json.loads((RESULTS / "calibration_regions.json").read_text())["results"]
    rows = []
    for case, env_id, observed, models in CASES:
        if case not in measured:
            rows += [r for r in stored if r["case"] == case]
            continue
        obs = observe(env_id, _with_regions(observed), SEED, POINT_NOISE, FORCE_NOISE, depth_size=None)
        for label, kwargs in models:
            for use, names in FITS.items():
                _, result, wall = fit_case(env_id, copy.deepcopy(obs), names, use, kwargs, regions=GRID)
                row = {"case": case, "env": env_id, "fitted_model": label, "observed": use,
                       "converged": result.converged, "wall_s": wall, "iterations": len(result.history)}
                for k, E in enumerate(truth):
                    row[f"young_modulus_{k}"] = float(result.theta[k])
                    row[f"young_modulus_{k}_std"] = float(result.std[k])
                    row[f"young_modulus_{k}_error"] = float(result.theta[k]) / E - 1.0
                if use == "points":
                    row["poisson_ratio"] = float(result.theta[len(truth)])
                    row["poisson_ratio_error"] = row["poisson_ratio"] - TRUTH["poisson_ratio"]
                rows.append(row)
                print(f"{case} / {label} / {use}: " + ", ".join(
                    f"E{k} {row[f'young_modulus_{k}']:.0f} ({100 * row[f'young_modulus_{k}_error']:+.1f} %)"
                    for k in range(len(truth))) + f", {wall:.0f} s", flush=True)
    return {"machine": machine_info(), "truth": {"young_modulus": truth, "poisson_ratio": TRUTH["poisson_ratio"]},
            "grid": list(GRID), "relative": list(RELATIVE), "seed": SEED, "point_noise_m": POINT_NOISE,
            "force_noise_N": FORCE_NOISE, "results": rows}


def report(data: dict) -> str:
    m = data["machine"]
    truth = data["truth"]["young_modulus"]
    out = (f"Generated by `benchmarks/accuracy/calibration_regions.py` ({m['cpu']}, {m['vector_isa']}, one thread, "
           f"{m['date']}). Truth: E {truth[0]:,.0f} Pa on the half of the tissue's rest box nearer the attachment "
           f"(x low) and {truth[1]:,.0f} Pa on the other, nu {data['truth']['poisson_ratio']}; observed along the "
           f"scripted retraction and hold (seed {data['seed']}; points: 10 tracked, "
           f"{data['point_noise_m'] * 1e3:g} mm noise; force: {data['force_noise_N']:g} N noise); each half's E "
           "fitted (and nu, from points) with `--regions 2x1x1`. Method: the script's docstring.\n\n")
    rows = []
    for r in data["results"]:
        nu = f"{r['poisson_ratio']:.3f} ({r['poisson_ratio_error']:+.3f})" if "poisson_ratio" in r else "not fitted"
        rows.append([r["case"], r["fitted_model"], r["observed"],
                     *(f"{r[f'young_modulus_{k}']:,.0f} ± {r[f'young_modulus_{k}_std']:,.0f} "
                       f"({100 * r[f'young_modulus_{k}_error']:+.1f} %)" for k in range(len(truth))),
                     nu, "yes" if r["converged"] else "NO", f"{r['wall_s']:.0f}"])
    out += markdown_table(["case", "fitted model", "observed", "E near the attachment (Pa), error",
                           "E far from it (Pa), error", "nu, error", "converged", "fit s"], rows) + "\n"
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rewrite the table from the stored JSON")
    ap.add_argument("--case", type=int, choices=range(len(CASES)), default=None,
                    help="measure this case only (0-based; the others' stored rows kept)")
    args = ap.parse_args(argv)
    cases = range(len(CASES)) if args.case is None else [args.case]
    store_and_report("calibration_regions", None if args.from_json else measure(cases), report, envs=[ENV, LOBE])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
