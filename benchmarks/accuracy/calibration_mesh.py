"""Calibration's model error: how the fitted model's mesh sets the error of the fitted E.

benchmarks/accuracy/calibration.py fits the default model to a tissue observed on a
finer one. Its E comes out low from tracked points (the default mesh is stiffer than the
finer one, so a softer E makes it deform alike). This measures that error against the
fitted model's mesh, on the flap: the tissue of calibration.py (E 5.5 kPa, nu 0.43)
observed along the same scripted retraction and hold on 24 x 24 x 4 cells stepped in
0.025 s (10 tracked points with 0.5 mm noise; the jaws' force with 0.01 N noise), then
fitted (E and nu from points, E from force) on models from the default 12 x 12 x 2 up to
the observed mesh itself stepped in 0.05 s (the time step's share of the error alone).

The quadratic study (``--part quadratic``) does the same with a converged observer: the
tissue observed on 10-node (quadratic) tets on 12 x 12 x 2 cells (the nodes of 24 x 24 x
4) stepped in 0.025 s by Newton (how far its noise-free tracked points and force are from
those of the same tissue in half the step, and on 16 x 16 x 3 quadratic cells, is stored
as ``converged_check``), fitted on
quadratic tets on 6 x 6 x 1 cells (the default's 507 nodes; in 0.05 and 0.025 s steps), 8 x
8 x 1 cells and the observed mesh itself in 0.05 s steps (the time step's share of the error
alone), and, for comparison, on the default linear model.

The flap's held line has no fine-mesh limit (benchmarks/accuracy/flap_grasp_line.py), so
neither study's observer is converged next to the jaws. The lobe study (``--part lobe``)
does the same on OrganRetraction, whose jaws hold a 6 x 40 mm patch (which has a limit):
observed on a 5 mm lobe in 0.025 s steps (checked against 0.0125 s steps and a 4 mm
lobe), fitted on the default 10 mm lobe, 8, 7 and 6 mm, in 0.05 s steps. The finer lobe
study (``--part lobe_fine``): observed on a 4 mm lobe in 0.025 s steps (not checked against
a finer one), fitted on a 5 mm lobe in 0.05 s steps.

Writes docs/benchmarks/calibration_mesh.{json,md}.

    python benchmarks/accuracy/calibration_mesh.py                  # every part, ~90 min on one core
    python benchmarks/accuracy/calibration_mesh.py --part lobe       # one part; the others' stored rows kept
"""

from __future__ import annotations

import argparse
import copy
import json
import time

import numba
import numpy as np

from heml_gym.benchmarks.accuracy.calibration import (FORCE_NOISE, POINT_NOISE, SEED, STEPS, TRUTH, fit_case,
                                                      fitted_constants, observe, truth_env)
from heml_gym.benchmarks.common import RESULTS, machine_info, markdown_table, store_and_report

ENV = "heml_gym/TissueRetraction-v1"
OBSERVED = {"scene": {"tissue": {"cells": [24, 24, 4]}}, "physics": {"max_dt": 0.025}}
OBSERVED_LABEL = "24 x 24 x 4 cells, 0.025 s steps"
#: the fitted models (label, env keyword arguments, what is fitted from): coarsest first
MODELS = [("12 x 12 x 2 cells, 0.05 s steps (the default)", {}, ("points", "force")),
          ("16 x 16 x 2 cells, 0.05 s steps", {"scene": {"tissue": {"cells": [16, 16, 2]}}}, ("points", "force")),
          ("18 x 18 x 3 cells, 0.05 s steps", {"scene": {"tissue": {"cells": [18, 18, 3]}}}, ("points", "force")),
          ("24 x 24 x 4 cells, 0.05 s steps (the observed mesh)", {"scene": {"tissue": {"cells": [24, 24, 4]}}},
           ("points",))]
FITS = {"points": ("young_modulus", "poisson_ratio"), "force": ("young_modulus",)}

QUADRATIC = {"field": "quadratic", "integrator": "implicit"}
#: the quadratic study's observer, and the finer one that checks it is converged
QUADRATIC_OBSERVED = {"cells": [12, 12, 2], "physics": {**QUADRATIC, "max_dt": 0.025}}
QUADRATIC_OBSERVED_LABEL = "quadratic tets, 12 x 12 x 2 cells, 0.025 s steps"
QUADRATIC_CHECKS = [("0.0125 s steps", {"cells": [12, 12, 2], "physics": {**QUADRATIC, "max_dt": 0.0125}}),
                    ("16 x 16 x 3 cells", {"cells": [16, 16, 3], "physics": {**QUADRATIC, "max_dt": 0.025}})]
QUADRATIC_MODELS = [
    ("12 x 12 x 2 cells, 0.05 s steps (the default)", {}, ("points", "force")),
    ("quadratic tets, 6 x 6 x 1 cells (the default's nodes), 0.05 s steps",
     {"cells": [6, 6, 1], "physics": QUADRATIC}, ("points", "force")),
    ("quadratic tets, 6 x 6 x 1 cells, 0.025 s steps", {"cells": [6, 6, 1], "physics": {**QUADRATIC, "max_dt": 0.025}},
     ("points", "force")),
    ("quadratic tets, 8 x 8 x 1 cells, 0.05 s steps", {"cells": [8, 8, 1], "physics": QUADRATIC}, ("points", "force")),
    ("quadratic tets, 12 x 12 x 2 cells, 0.05 s steps (the observed mesh)", {"cells": [12, 12, 2], "physics": QUADRATIC},
     ("points",))]


LOBE = "heml_gym/OrganRetraction-v2"
#: the lobe study's observer (a 5 mm lobe, its jaws' 2.5 mm elements as the default's),
#: the finer ones that check it, and the fitted models
LOBE_OBSERVED = {"mesh_size": 0.005, "physics": {"max_dt": 0.025}}
LOBE_OBSERVED_LABEL = "a 5 mm lobe, 0.025 s steps"
LOBE_CHECKS = [("0.0125 s steps", {"mesh_size": 0.005, "physics": {"max_dt": 0.0125}}),
               ("a 4 mm lobe", {"mesh_size": 0.004, "physics": {"max_dt": 0.025}})]
LOBE_MODELS = [("10 mm, 0.05 s steps (the default)", {}, ("points", "force")),
               ("8 mm, 0.05 s steps", {"mesh_size": 0.008}, ("points", "force")),
               ("7 mm, 0.05 s steps", {"mesh_size": 0.007}, ("points", "force")),
               ("6 mm, 0.05 s steps", {"mesh_size": 0.006}, ("points", "force"))]


#: a finer lobe study: observed on a 4 mm lobe, fitted on a 5 mm one (no finer check: a
#: 3 mm lobe's observation alone would take an hour on one core)
LOBE_FINE_OBSERVED = {"mesh_size": 0.004, "physics": {"max_dt": 0.025}}
LOBE_FINE_OBSERVED_LABEL = "a 4 mm lobe, 0.025 s steps"
LOBE_FINE_MODELS = [("5 mm, 0.05 s steps", {"mesh_size": 0.005}, ("points", "force"))]


def fit_models(obs, models, env_id: str = ENV, wrist_reach: float | None = None) -> list[dict]:
    """Fit each of ``models`` (label, env keyword arguments, what it is fitted from) to
    ``obs`` of ``env_id`` (``wrist_reach``: its jaws on a free wrist, see ``fit_case``); a
    model that cannot follow the observed control (its own steps diverge, its replay does
    not converge) is a row with the ``error``."""
    from heml_gym.calibration import ReplayError
    from heml_gym.envs.observations import ObservationError

    rows = []
    for label, kwargs, uses in models:
        for use in uses:
            names = FITS[use]
            try:
                _, result, wall = fit_case(env_id, copy.deepcopy(obs), names, use, kwargs, wrist_reach)
            except (ObservationError, ReplayError) as exc:
                rows.append({"fitted_model": label, "observed": use, "error": str(exc)})
                print(f"{label}, {use}: {exc}", flush=True)
                break
            row = {"fitted_model": label, "observed": use, "converged": result.converged, "wall_s": wall,
                   "iterations": len(result.history), **fitted_constants(result, names)}
            rows.append(row)
            print(f"{label}, {use}: E {row['young_modulus']:.0f} ({100 * row['young_modulus_error']:+.1f} %), "
                  f"{wall:.0f} s", flush=True)
    return rows


def measure_linear() -> dict:
    numba.set_num_threads(1)
    obs = observe(ENV, OBSERVED, SEED, POINT_NOISE, FORCE_NOISE)
    return {"machine": machine_info(), "observed_on": OBSERVED_LABEL, "results": fit_models(obs, MODELS)}


def tracked(kwargs: dict, rest_points: np.ndarray, env_id: str = ENV) -> tuple[np.ndarray, np.ndarray]:
    """The truth's tissue on the model ``kwargs`` of ``env_id`` along :func:`observe`'s retraction,
    noise-free: the positions (m) of the material points at ``rest_points`` (interpolated
    in the model's tets, so models of different meshes compare the same points) and the
    jaws' force (N), at every control step."""
    from heml_gym.calibration import embed_points

    env, policy = truth_env(env_id, kwargs)
    task = env.unwrapped.task
    B = embed_points(task.scene.mesh, rest_points)
    obs, _ = env.reset(seed=SEED)
    points, force = [B @ task.x[0]], [np.zeros(3)]
    for _ in range(STEPS):
        obs, *_ = env.step(policy(obs))
        points.append(B @ task.x[0])
        force.append(task.grasp_force[0].copy())
    return np.array(points), np.array(force)


def measure_quadratic() -> dict:
    """The quadratic study: its observer checked against a finer one (noise-free points and
    force), then the fits."""
    return _checked_study(ENV, QUADRATIC_OBSERVED, QUADRATIC_OBSERVED_LABEL, QUADRATIC_CHECKS, QUADRATIC_MODELS)


def measure_lobe() -> dict:
    """The lobe study: observed on a 5 mm lobe, fitted on the default 10 mm one and finer."""
    return _checked_study(LOBE, LOBE_OBSERVED, LOBE_OBSERVED_LABEL, LOBE_CHECKS, LOBE_MODELS)


def measure_lobe_fine() -> dict:
    """The finer lobe study: observed on a 4 mm lobe, fitted on a 5 mm one."""
    return _checked_study(LOBE, LOBE_FINE_OBSERVED, LOBE_FINE_OBSERVED_LABEL, [], LOBE_FINE_MODELS)


def _checked_study(env_id, observed, observed_label, checks_on, models) -> dict:
    """Observe ``env_id`` on ``observed``, check its noise-free tracked points and force
    against the finer ``checks_on``, and fit ``models``."""
    numba.set_num_threads(1)
    t0 = time.perf_counter()
    obs = observe(env_id, observed, SEED, POINT_NOISE, FORCE_NOISE)
    observe_s = time.perf_counter() - t0
    points, force = tracked(observed, obs.rest_points, env_id)
    checks = []
    for label, kwargs in checks_on:
        finer_points, finer_force = tracked(kwargs, obs.rest_points, env_id)
        gap = np.linalg.norm(points - finer_points, axis=-1)
        checks.append({"finer": label, "points_max_m": float(gap.max()),
                       "points_rms_m": float(np.sqrt((gap ** 2).mean())),
                       "force_max_N": float(np.linalg.norm(force - finer_force, axis=1).max()),
                       "force_peak_N": float(np.linalg.norm(finer_force, axis=1).max())})
        print(f"observer vs {label}: points {1e3 * checks[-1]['points_max_m']:.3f} mm at most, force "
              f"{checks[-1]['force_max_N']:.4f} N of {checks[-1]['force_peak_N']:.3f} N", flush=True)
    return {"machine": machine_info(), "env": env_id, "observed_on": observed_label, "observe_s": observe_s,
            "converged_check": checks, "results": fit_models(obs, models, env_id)}


PARTS = ("linear", "quadratic", "lobe", "lobe_fine")


def measure(parts) -> dict:
    """The chosen ``parts`` measured, the others read from the stored JSON."""
    stored = json.loads((RESULTS / "calibration_mesh.json").read_text()) if len(parts) < len(PARTS) else {}
    data = {"env": ENV, "truth": TRUTH, "seed": SEED, "point_noise_m": POINT_NOISE, "force_noise_N": FORCE_NOISE}
    for part, run in (("linear", measure_linear), ("quadratic", measure_quadratic), ("lobe", measure_lobe),
                      ("lobe_fine", measure_lobe_fine)):
        if part in parts or part in stored:
            data[part] = run() if part in parts else stored[part]
    data["machine"] = data[parts[-1]]["machine"]  # (the run that wrote the file; each study has its own)
    return data


def fit_table(study: dict) -> str:
    """The markdown table of a study's fits (its ``results``)."""
    rows = []
    for r in study["results"]:
        if "error" in r:
            rows.append([r["fitted_model"], r["observed"], f"failed: {r['error']}", "", "", ""])
            continue
        nu = (f"{r['poisson_ratio']:.3f} ({r['poisson_ratio_error']:+.3f})" if "poisson_ratio" in r else "not fitted")
        rows.append([r["fitted_model"], r["observed"],
                     f"{r['young_modulus']:,.0f} ± {r['young_modulus_std']:,.0f} ({100 * r['young_modulus_error']:+.1f} %)",
                     nu, "yes" if r["converged"] else "NO", f"{r['wall_s']:.0f}"])
    return markdown_table(["fitted model", "observed", "E (Pa), error", "nu, error", "converged", "fit s"], rows)


def report(data: dict) -> str:
    head = (f"Generated by `benchmarks/accuracy/calibration_mesh.py`. Truth E {data['truth']['young_modulus']:,.0f} Pa, "
            f"nu {data['truth']['poisson_ratio']}, observed along the scripted retraction and hold (seed "
            f"{data['seed']}; points: 10 tracked, {data['point_noise_m'] * 1e3:g} mm noise; force: "
            f"{data['force_noise_N']:g} N noise). Method: the script's docstring.\n\n")
    out = head
    for part in PARTS:
        if part not in data:
            continue
        study = data[part]
        m = study["machine"]
        checks = "; ".join(f"{c['finer']}: {1e3 * c['points_max_m']:.2f} mm and {c['force_max_N']:.3f} N"
                           for c in study.get("converged_check", []))
        out += (f"{study.get('env', data['env']).split('/')[-1]}, observed on {study['observed_on']} ({m['cpu']}, "
                f"{m['vector_isa']}, one thread, {m['date']})"
                + (f". Observed in finer models, the same tissue's noise-free tracked points and jaws' force "
                   f"move by at most {checks} (the force peaks at "
                   f"{study['converged_check'][0]['force_peak_N']:.2f} N)" if checks else "") + ":\n\n")
        out += fit_table(study) + "\n"
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rewrite the table from the stored JSON")
    ap.add_argument("--part", choices=(*PARTS, "all"), default="all",
                    help="measure this study only (the others' stored rows kept)")
    args = ap.parse_args(argv)
    parts = PARTS if args.part == "all" else (args.part,)
    store_and_report("calibration_mesh", None if args.from_json else measure(parts), report, envs=[ENV, LOBE])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
