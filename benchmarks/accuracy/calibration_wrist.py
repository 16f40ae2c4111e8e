"""Calibration of the flap held by jaws with a footprint on a free wrist: do its tracked points then give E?

The flap's jaws hold a line, and next to a held line the tissue stretches more on every
finer mesh (benchmarks/accuracy/flap_grasp_line.py), so the flap's tracked points have no
mesh-converged truth and E fitted to them comes out low by however much finer the
observer is (calibration_mesh.py). Jaws with a footprint that turn freely about their
axis (a free wrist, :mod:`heml_gym.calibration.wrist`) hold a patch instead: the 10 mm of
tissue next to the line the flap's jaws take, held rigidly where it is when they close,
moved with the gripper, and turned about the jaws' axis (the edge's direction) through
the patch's middle to where the tissue's torque on it vanishes.

The same study as calibration_mesh.py's linear one with that grasp: the tissue of
calibration.py (E 5.5 kPa, nu 0.43) driven along the same scripted retraction and hold
(the gripper's path and the jaws' closing recorded by the flap env, seed 1), observed on
24 x 24 x 4 cells in 0.025 s steps by the calibration's replay (Newton on each backward
Euler sub-step, the wrist's angle an unknown of it); the observer is checked against the
same tissue on 36 x 36 x 6 cells and in 0.0125 s steps (noise-free tracked points and
force). 10 tracked points with 0.5 mm noise, the jaws' force with 0.01 N noise; fitted
(E and nu from points, E from force) on models from the default 12 x 12 x 2 cells up to the
observed mesh itself, in 0.05 s steps.

Writes docs/benchmarks/calibration_wrist.{json,md}.

    python benchmarks/accuracy/calibration_wrist.py       # ~40 min on one core
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time

import numba
import numpy as np

from heml_gym.benchmarks.accuracy.calibration import FORCE_NOISE, POINT_NOISE, SEED, TRUTH, observe
from heml_gym.benchmarks.accuracy.calibration_mesh import ENV, MODELS, fit_models, fit_table
from heml_gym.benchmarks.common import machine_info, store_and_report

#: the patch the jaws hold: every vertex within this distance (m, at rest) of the line the flap's jaws take
REACH = 0.01
OBSERVED = {"scene": {"tissue": {"cells": [24, 24, 4]}}, "physics": {"max_dt": 0.025}}
OBSERVED_LABEL = "24 x 24 x 4 cells, 0.025 s steps"
CHECKS = [("0.0125 s steps", {"scene": {"tissue": {"cells": [24, 24, 4]}}, "physics": {"max_dt": 0.0125}}),
          ("36 x 36 x 6 cells", {"scene": {"tissue": {"cells": [36, 36, 6]}}, "physics": {"max_dt": 0.025}})]


def replayed(kwargs: dict, obs) -> dict:
    """The truth's tissue on the flap model ``kwargs`` (env keyword arguments), its jaws on
    a free wrist, driven by ``obs``'s gripper path and grasp: noise-free tracked points at
    ``obs.rest_points`` (m, (T + 1, K, 3)), the jaws' force (N, (T + 1, 3); 0 at the
    start), the wrist's angle at the end (rad) and the patch's vertex count."""
    import gymnasium as gym

    from heml_gym.envs.observations import on_a_free_wrist

    t0 = time.perf_counter()
    seen, result, log = on_a_free_wrist(gym.make(ENV, **kwargs), obs, REACH)
    return {"points": seen.points, "force": seen.force, "angle": float(result.tape[-1]["angle"]),
            "patch": int(log.wrist[-1].sum()), "wall_s": time.perf_counter() - t0}


def measure() -> dict:
    numba.set_num_threads(1)
    path = observe(ENV, OBSERVED, SEED, 0.0, 0.0)  # the gripper's path, the grasp, the tracked points' rest places
    path = dataclasses.replace(path, depth=None, intrinsics=None, camera_pose=None)  # (the env's own grasp's images)
    truth = replayed(OBSERVED, path)
    print(f"observer: wrist at {truth['angle']:.3f} rad, patch of {truth['patch']} vertices, {truth['wall_s']:.0f} s",
          flush=True)
    checks = []
    for label, kwargs in CHECKS:
        finer = replayed(kwargs, path)
        gap = np.linalg.norm(truth["points"] - finer["points"], axis=-1)
        checks.append({"finer": label, "points_max_m": float(gap.max()),
                       "points_rms_m": float(np.sqrt((gap ** 2).mean())),
                       "force_max_N": float(np.linalg.norm(truth["force"] - finer["force"], axis=1).max()),
                       "force_peak_N": float(np.linalg.norm(finer["force"], axis=1).max()),
                       "angle": finer["angle"], "wall_s": finer["wall_s"]})
        print(f"observer vs {label}: points {1e3 * checks[-1]['points_max_m']:.3f} mm at most, force "
              f"{checks[-1]['force_max_N']:.4f} N; wrist {finer['angle']:.3f} rad", flush=True)
    rng = np.random.default_rng(SEED)
    points = truth["points"] + rng.normal(0.0, POINT_NOISE, truth["points"].shape)
    force = truth["force"] + rng.normal(0.0, FORCE_NOISE, truth["force"].shape)
    force[0] = 0.0
    obs = dataclasses.replace(copy.deepcopy(path), points=points, force=force,
                              meta={**path.meta, "made_by": "benchmarks/accuracy/calibration_wrist.py (a replay)",
                                    "point_noise_m": POINT_NOISE, "force_noise_N": FORCE_NOISE})
    study = {"machine": machine_info(), "env": ENV, "observed_on": OBSERVED_LABEL, "wrist_angle": truth["angle"],
             "patch_vertices": truth["patch"], "observe_s": truth["wall_s"], "converged_check": checks,
             "results": fit_models(obs, MODELS, ENV, wrist_reach=REACH)}
    return {"env": ENV, "truth": TRUTH, "seed": SEED, "point_noise_m": POINT_NOISE, "force_noise_N": FORCE_NOISE,
            "wrist_reach_m": REACH, "machine": study["machine"], "study": study}


def report(data: dict) -> str:
    study = data["study"]
    m = study["machine"]
    checks = "; ".join(f"{c['finer']}: {1e3 * c['points_max_m']:.2f} mm ({1e3 * c['points_rms_m']:.2f} mm RMS) and "
                       f"{c['force_max_N']:.3f} N" for c in study["converged_check"])
    return (f"Generated by `benchmarks/accuracy/calibration_wrist.py` on {m['cpu']} ({m['vector_isa']}), one thread, "
            f"{m['date']}. `{data['env']}`'s scene, its jaws holding the {1e3 * data['wrist_reach_m']:g} mm of tissue "
            f"next to the line they take ({study['patch_vertices']} vertices on the observed mesh) on a free wrist "
            f"(it ends the hold turned by {study['wrist_angle']:.2f} rad). Truth E "
            f"{data['truth']['young_modulus']:,.0f} Pa, nu {data['truth']['poisson_ratio']}, along the scripted "
            f"retraction and hold (seed {data['seed']}; points: 10 tracked, {data['point_noise_m'] * 1e3:g} mm noise; "
            f"force: {data['force_noise_N']:g} N noise), observed on {study['observed_on']} by the calibration's "
            f"replay. In finer models the same tissue's noise-free tracked points and jaws' force move by at most "
            f"{checks} (the force peaks at {study['converged_check'][0]['force_peak_N']:.2f} N). Method: the "
            f"script's docstring.\n\n" + fit_table(study) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rewrite the table from the stored JSON")
    args = ap.parse_args(argv)
    store_and_report("calibration_wrist", None if args.from_json else measure(), report, envs=[ENV])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
