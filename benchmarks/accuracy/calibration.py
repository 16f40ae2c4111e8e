"""Calibration: is a known tissue recovered from what a tracker, a force sensor or a depth camera saw?

For each env, a tissue the scenes do not default to (E 5.5 kPa, nu 0.43) is observed
(``heml_gym.envs.observations.record``) along the scripted retraction and hold (30 env
steps, 3 s) on a **finer model** than the one fitted, as a real fit faces model error:
the flap on 18 x 18 x 3 cells stepped in 0.025 s, the lobe meshed at 4 mm (2.5 mm at the
jaws) stepped in 0.025 s. The model ``heml-gym calibrate`` fits by default
(``heml_gym.envs.calibration_models``) is then fitted (``heml_gym.calibration.fit``: E and
nu, from the scene's own mean E and nu): the flap's own 12 x 12 x 2 cells, a 7 mm lobe
(the task's lobe: 10 mm), both in 0.05 s steps; as ``heml-gym calibrate`` does, the lobe's
fits of points and of force are then corrected for the 7 mm mesh's stiffness against a 5
mm lobe in 0.025 s steps (``correct_for_mesh``: one replay of the fit on it, one refit of
that replay), a model coarser than the observer (the table gives the fit before the
correction too). The fits are to

* ``points``: 10 tracked points on the upper surface, 0.5 mm Gaussian noise per coordinate;
* ``force``: the jaws' force, 0.01 N noise per component (E only: the force barely
  depends on nu);
* ``points and force``: both (E and nu), each weighed by its own residual, as ``heml-gym
  calibrate`` does when no scale is given (``fit(..., weigh_by_residuals=True)``);

Prediction: the points fit, replayed on another retraction of the same tissue (another
seed: another gripper start and grasp place), against that retraction's noise-free
points (RMS, m). Speed (one thread, same machine): the fit's wall time (its kernels compiled
beforehand: a fresh install compiles them once, ~20 s, then caches them), and one gradient
(the reverse pass) against one cold forward replay of the 3 s trajectory (its Newton solves
not started from a previous replay's, as a fit's are), medians of 3.
* ``depth``: the task camera's 84 x 84 depth image (everything it sees: the jaws in front of
  the tissue too), 1 mm Gaussian noise per pixel (E only), against the fitted model's
  rendered tissue depth (``heml_gym.envs.depth_loss``).

Writes docs/benchmarks/calibration.{json,md}.

    python benchmarks/accuracy/calibration.py     # ~35 min on one core
"""

from __future__ import annotations

import argparse
import time
from types import SimpleNamespace

import numba
import numpy as np

from heml_gym.benchmarks.common import machine_info, markdown_table, store_and_report
from heml_gym.envs.calibration_models import CALIBRATION_MODELS

TRUTH = {"young_modulus": 5500.0, "poisson_ratio": 0.43}
STEPS = 30
CASES = {
    "heml_gym/TissueRetraction-v1": {"fine": {"scene": {"tissue": {"cells": [18, 18, 3]}},
                                              "physics": {"max_dt": 0.025}},
                                     "fine_label": "18 x 18 x 3 cells, 0.025 s steps",
                                     "model_label": "12 x 12 x 2 cells, 0.05 s steps (the task's)"},
    "heml_gym/OrganRetraction-v2": {"fine": {"mesh_size": 0.004, "physics": {"max_dt": 0.025}},
                                    "fine_label": "4 mm mesh, 0.025 s steps",
                                    "model_label": "7 mm mesh, 0.05 s steps (calibrate's; the task's: 10 mm)"},
}
for _env_id, _case in CASES.items():  # (the fitted model: calibrate's default)
    _case["model"] = CALIBRATION_MODELS[_env_id].env_kwargs
#: The law studies' pairing (calibration_laws and law_identification by default): observed on
#: a mesh one step finer than the task's own, in 0.025 s steps, and fitted on the task's own
TASK_MODEL_CASES = {
    "heml_gym/TissueRetraction-v1": CASES["heml_gym/TissueRetraction-v1"],
    "heml_gym/OrganRetraction-v2": {"fine": {"mesh_size": 0.007, "physics": {"max_dt": 0.025}},
                                    "fine_label": "7 mm mesh, 0.025 s steps",
                                    "model_label": "10 mm mesh, 0.05 s steps (the task's)", "model": {}},
}
SEED, PREDICT_SEED = 1, 7
POINT_NOISE, FORCE_NOISE, DEPTH_NOISE = 5e-4, 0.01, 1e-3
DEPTH_SIZE = (84, 84)


def truth_env(env_id: str, kwargs: dict, law: str | None = None):
    """``(env, policy)``: the env ``env_id`` (keyword arguments ``kwargs``) with the truth's
    tissue (of ``law``, default the scene's), and the scripted retraction for its scene."""
    import gymnasium as gym

    from heml_gym.envs.scripted import scripted_policy

    physics = {**kwargs.get("physics", {}), "young_modulus": [TRUTH["young_modulus"]] * 2,
               "poisson": TRUTH["poisson_ratio"], **({"material": law} if law else {})}
    env = gym.make(env_id, **{**kwargs, "physics": physics})
    return env, scripted_policy(env.unwrapped.scene)


def observe(env_id: str, kwargs: dict, seed: int, point_noise: float, force_noise: float, depth_noise: float = 0.0,
            law: str | None = None, stretch: float = 1.0, depth_size=DEPTH_SIZE):
    """The truth's tissue (of ``law``, default the scene's) observed along the scripted
    retraction, its fold's arc ``stretch`` times the grasp's distance from the hinge."""
    from heml_gym.envs.observations import record

    env, policy = truth_env(env_id, kwargs, law)
    policy.radius_scale *= stretch
    return record(env, policy, seed=seed, steps=STEPS, points=10, point_noise=point_noise, force_noise=force_noise,
                  noise_seed=seed, env_id=env_id, depth_size=depth_size, depth_noise=depth_noise)


def fit_case(env_id: str, obs, names, use, model: dict | None = None, wrist_reach: float | None = None,
             regions=None):
    """Fit ``names`` to the ``use`` part of ``obs`` (the rest dropped) on the env's default
    model, or on ``model`` (the env's keyword arguments: a finer mesh, another step);
    ``wrist_reach`` (m): the jaws hold a patch on a free wrist
    (:func:`heml_gym.envs.observations.control_log`); ``regions`` ``(nx, ny, nz)``: E per box
    of that grid (``heml-gym calibrate --regions``)."""
    import gymnasium as gym

    from heml_gym.calibration import fit
    from heml_gym.envs.observations import calibration_problem, keep_observed

    keep_observed(obs, use.split(" and "), "use")
    replay, observed, names, bounds, start = calibration_problem(gym.make(env_id, **(model or {})), obs, names,
                                                                 wrist_reach=wrist_reach, regions=regions)
    warm_up = replay.run(start)
    replay.gradient(start, warm_up, np.zeros_like(warm_up.x))  # compiles the kernels
    replay.forget()  # (the fit's first replay starts cold, as a user's does)
    t0 = time.perf_counter()
    result = fit(replay, observed, names, [start], bounds, weigh_by_residuals=use == "points and force")
    return replay, result, time.perf_counter() - t0


def with_law(kwargs: dict, law: str | None) -> dict:
    """``gym.make`` keyword arguments ``kwargs`` with ``law`` merged into their physics
    (None: ``kwargs`` as they are)."""
    return kwargs if not law else {**kwargs, "physics": {**kwargs.get("physics", {}), "material": law}}


def fit_as_calibrate(env_id: str, obs, names, use: str, model: dict | None = None, law: str | None = None):
    """Fit ``names`` to the ``use`` part of ``obs`` as ``heml-gym calibrate`` does by
    default: on ``model`` (the env's keyword arguments; default its calibration model,
    ``heml_gym.envs.calibration_models``), with ``law`` given, then, where that model has a
    finer reference and points or force are fitted, corrected for its mesh
    (``correct_for_mesh``). Returns ``(replay, result, raw, wall_s)``: ``result`` has the
    corrected ``theta`` and ``std`` (the fit's ``converged`` and correction's together),
    ``raw`` is the fit before the correction (None: not corrected)."""
    import gymnasium as gym

    from heml_gym.envs.calibration_models import correct_for_mesh
    from heml_gym.envs.observations import fit_parameter

    calibration = CALIBRATION_MODELS[env_id]
    model = calibration.env_kwargs if model is None else model
    replay, result, wall = fit_case(env_id, obs, names, use, with_law(model, law))
    if calibration.reference is None or use == "depth":
        return replay, result, None, wall
    t0 = time.perf_counter()
    done = correct_for_mesh(gym.make(env_id, **with_law(calibration.reference, law)), obs, replay, names, names,
                            result, [fit_parameter(n)[1] for n in names], calibration.reference_label)
    corrected = SimpleNamespace(theta=done.corrected, std=done.std, message=result.message,
                                converged=result.converged and done.converged, residual_rms=result.residual_rms,
                                refit=done.refit, reference=done.reference, correction_converged=done.converged)
    return replay, corrected, result, wall + time.perf_counter() - t0


def fitted_constants(result, names) -> dict:
    """Each fitted constant of ``result`` (a :func:`heml_gym.calibration.fit` result of
    ``names``), its standard error (``NAME_std``) and its error against :data:`TRUTH`
    (E relative, nu absolute)."""
    row = {}
    for j, name in enumerate(names):
        row[name] = float(result.theta[j])
        row[f"{name}_std"] = float(result.std[j])
    row["young_modulus_error"] = row["young_modulus"] / TRUTH["young_modulus"] - 1.0
    if "poisson_ratio" in names:
        row["poisson_ratio_error"] = row["poisson_ratio"] - TRUTH["poisson_ratio"]
    return row


def measure() -> dict:
    import copy

    import gymnasium as gym

    from heml_gym.calibration import embed_points
    from heml_gym.envs.observations import calibration_problem

    numba.set_num_threads(1)
    rows, timing = [], []
    for env_id, case in CASES.items():
        obs = observe(env_id, case["fine"], SEED, POINT_NOISE, FORCE_NOISE, DEPTH_NOISE)
        for use, names in (("points", ("young_modulus", "poisson_ratio")), ("force", ("young_modulus",)),
                           ("points and force", ("young_modulus", "poisson_ratio")), ("depth", ("young_modulus",))):
            used = copy.deepcopy(obs)
            # as heml-gym calibrate: on the calibration model, the lobe's points and force corrected for its mesh
            replay, fitted, raw, wall = fit_as_calibrate(env_id, used, names, use, model=case["model"])
            result = fitted if raw is None else raw  # the fitted model's own fit
            row = {"env": env_id, "observed": use, "fine_model": case["fine_label"], "fitted_model": case["model_label"],
                   "fit": list(names), "converged": result.converged, "message": result.message,
                   "iterations": len(result.history), "wall_s": wall, "residual_rms": result.residual_rms,
                   "failed_trials": result.failed_trials}
            own = fitted_constants(result, names)
            row.update(own)
            if raw is not None:
                row.update({f"raw_{k}": v for k, v in own.items()},
                           mesh_reference=fitted.reference, refit=fitted.refit,
                           refit_converged=fitted.correction_converged)
                row.update(fitted_constants(fitted, names))
            if use == "points":  # prediction of another retraction of the same tissue, by the fitted model's fit
                other = observe(env_id, case["fine"], PREDICT_SEED, 0.0, 0.0)
                other.force = None
                replay2, *_ = calibration_problem(gym.make(env_id, **case["model"]), other, names)
                predicted = replay2.run(result.theta)
                B = embed_points(replay2.model.mesh, other.rest_points)
                pts = np.stack([B @ x for x in predicted.x])
                row["prediction_rms_m"] = float(np.sqrt(((pts - other.points) ** 2).sum(axis=-1).mean()))
                # speed: one forward replay and one gradient, medians of 3
                forward, backward = [], []
                theta = result.theta
                for _ in range(3):
                    replay.forget()  # a cold forward replay (a fit's replays start from the previous one's)
                    t0 = time.perf_counter()
                    r = replay.run(theta)
                    t1 = time.perf_counter()
                    replay.gradient(theta, r, np.ones_like(r.x), np.ones_like(r.force))
                    forward.append(t1 - t0)
                    backward.append(time.perf_counter() - t1)
                timing.append({"env": env_id, "forward_s": float(np.median(forward)),
                               "gradient_s": float(np.median(backward)),
                               "gradient_over_forward": float(np.median(backward) / np.median(forward)),
                               "vertices": int(replay.model.n_vertices)})
            rows.append(row)
            print(f"{env_id} {use}: " + ", ".join(f"{n} {row[n]:.5g} ± {row[n + '_std']:.2g}" for n in names)
                  + f" ({wall:.0f} s)", flush=True)
    return {"machine": machine_info(), "truth": TRUTH, "steps": STEPS, "seed": SEED, "predict_seed": PREDICT_SEED,
            "point_noise_m": POINT_NOISE, "force_noise_N": FORCE_NOISE, "depth_noise_m": DEPTH_NOISE,
            "depth_size": list(DEPTH_SIZE), "results": rows, "timing": timing}


def report(data: dict) -> str:
    m = data["machine"]
    lines = [f"Generated by `benchmarks/accuracy/calibration.py` on {m['cpu']} ({m['vector_isa']}, one thread), "
             f"{m['date']}. Truth: E {data['truth']['young_modulus']:,.0f} Pa, nu {data['truth']['poisson_ratio']}, "
             f"observed on the finer model along the scripted retraction and hold ({data['steps']} env steps, seed "
             f"{data['seed']}); points: 10 tracked, {data['point_noise_m'] * 1e3:g} mm noise; force: "
             f"{data['force_noise_N']:g} N noise"
             + (f"; depth: {data['depth_size'][0]} x {data['depth_size'][1]} pixels, {data['depth_noise_m'] * 1e3:g} mm "
                "noise" if "depth_size" in data else "") + ". Method: the script's docstring.\n"]
    rows = []
    for r in data["results"]:
        nu = (f"{r['poisson_ratio']:.3f} ± {r['poisson_ratio_std']:.3f} ({r['poisson_ratio_error']:+.3f})"
              if "poisson_ratio" in r else "not fitted")
        rms = ", ".join(f"{k.split('_')[0]} {v * (1e3 if k.endswith('_m') else 1):.2f} "
                        f"{'mm' if k.endswith('_m') else 'N'}" for k, v in r["residual_rms"].items())
        raw = ""
        if "raw_young_modulus" in r:
            raw = f"{r['raw_young_modulus']:,.0f} ({100 * r['raw_young_modulus_error']:+.1f} %)" + (
                f", nu {r['raw_poisson_ratio']:.3f} ({r['raw_poisson_ratio_error']:+.3f})" if "raw_poisson_ratio" in r
                else "")
        rows.append([r["env"].split("/")[-1], r["observed"], r["fine_model"], r["fitted_model"],
                     f"{r['young_modulus']:,.0f} ± {r['young_modulus_std']:,.0f} ({100 * r['young_modulus_error']:+.1f} %)",
                     nu, raw, rms, f"{r['prediction_rms_m'] * 1e3:.2f} mm" if "prediction_rms_m" in r else "",
                     "yes" if r["converged"] else "NO", r["iterations"], f"{r['wall_s']:.0f}"])
    lines.append(markdown_table(["env", "observed", "observed on", "fitted model", "E (Pa), error",
                                 "nu, error", "before the mesh correction", "residual RMS", "prediction RMS (another retraction)", "converged",
                                 "iterations", "fit s"], rows))
    lines.append("\nOne forward replay (3 s) and one gradient (its reverse pass), medians of 3:\n")
    lines.append(markdown_table(["env", "vertices", "forward s", "gradient s", "gradient / forward"],
                                [[t["env"].split("/")[-1], t["vertices"], f"{t['forward_s']:.2f}",
                                  f"{t['gradient_s']:.2f}", f"{t['gradient_over_forward']:.2f}"]
                                 for t in data["timing"]]))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rewrite the table from the stored JSON")
    args = ap.parse_args(argv)
    store_and_report("calibration", None if args.from_json else measure(), report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
