"""``heml-gym observe`` and ``heml-gym calibrate``: record an observation file from a
simulated retraction, and fit a scene's tissue to one.

The fitting itself is :func:`heml_gym.calibration.fit` (physics only); the env layer turns
the observation and the scene into a replay (:mod:`heml_gym.envs.observations`); this
module adds the command line, the progress bar, ``fit.json`` and the chart.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["observe", "calibrate", "physics_overrides"]


def physics_overrides(young_modulus=None, poisson=None, law=None) -> dict:
    """``physics=`` keyword arguments for an env whose tissue is given exactly."""
    physics = {}
    if young_modulus is not None:
        E = float(young_modulus)
        if not (math.isfinite(E) and E > 0):
            raise ValueError(f"--young-modulus: must be a positive number of pascals, got {young_modulus!r}")
        physics["young_modulus"] = [E, E]
    if poisson is not None:
        physics["poisson"] = float(poisson)
    if law is not None:
        physics["material"] = law
    return physics


def parse_json_mapping(text: str | None, argument: str = "--env-kwargs") -> dict:
    """The JSON object in a command-line argument (``{}`` for none), or a one-line error
    naming ``argument``."""
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{argument}: not JSON ({exc.msg})") from None
    if not isinstance(value, dict):
        raise ValueError(f"{argument}: must be a JSON object of gym.make keyword arguments")
    return value


def _make(env_id: str, kwargs: dict, physics: dict | None = None):
    import gymnasium as gym

    from heml_gym.envs import check_env_kwargs, episode_steps

    kwargs = dict(kwargs)
    if physics:
        kwargs["physics"] = {**kwargs.get("physics", {}), **physics}
    check_env_kwargs(env_id, kwargs, "env kwargs")
    return gym.make(env_id, max_episode_steps=episode_steps(kwargs), **kwargs)


def _problem(env_id: str, env_kwargs: dict, law: str | None, observation, fit_names, point_scale: float,
             force_scale: float, wrist_reach: float | None, regions):
    """The env of ``env_id`` (with ``law``, or the scene's) and its calibration problem for
    ``observation``: ``(env, (replay, observed, names, bounds, start))``
    (:func:`heml_gym.envs.observations.calibration_problem`)."""
    from heml_gym.envs.observations import calibration_problem

    env = _make(env_id, env_kwargs, physics_overrides(law=law))
    return env, calibration_problem(env, observation, tuple(fit_names), point_scale, force_scale,
                                    wrist_reach=wrist_reach, regions=regions)


def _check_wrist_reach(wrist_reach: float | None) -> None:
    """``--wrist-reach``: None (the scene's grasp) or a positive distance in metres."""
    if wrist_reach is not None and not (math.isfinite(wrist_reach) and wrist_reach > 0):
        raise ValueError(f"--wrist-reach: must be a positive distance in metres, got {wrist_reach}")


def observe(env_id: str, out: str, seed: int = 0, steps: int = 30, points: int = 10, point_noise: float = 0.0,
            force_noise: float = 0.0, young_modulus=None, poisson=None, law=None, env_kwargs: str | None = None,
            depth: str | None = None, depth_noise: float = 0.0, force: bool = True,
            wrist_reach: float | None = None) -> dict:
    """Record an observation file of ``env_id``'s scripted retraction (the tissue given by
    ``young_modulus`` / ``poisson`` / ``law``, else drawn as the scene draws it); with
    ``wrist_reach`` (m), as the calibration's replay steps it with the jaws holding the
    tissue within that distance of what the scene's jaws take on a free wrist
    (:func:`heml_gym.envs.observations.on_a_free_wrist`). ``seed`` seeds the episode, the
    tracked points' draw and the noise (so each seed's file has noise of its own)."""
    from heml_gym.envs.observations import on_a_free_wrist, record, save_observation
    from heml_gym.envs.scripted import scripted_policy

    for name, value in (("--steps", steps), ("--points", points)):
        if value < (1 if name == "--steps" else 0):
            raise ValueError(f"{name}: must be >= {1 if name == '--steps' else 0}, got {value}")
    if not force and points == 0 and depth is None:
        raise ValueError("--no-force: then observe something else (--points N or --depth HxW)")
    depth_size = None
    if depth is not None:
        try:
            depth_size = tuple(int(v) for v in str(depth).lower().split("x"))
        except ValueError:
            depth_size = ()
        if len(depth_size) != 2 or not all(8 <= v <= 1024 for v in depth_size):
            raise ValueError(f"--depth: the depth image's size as HxW pixels (each 8-1024), e.g. 84x84, got {depth!r}")
    for name, value in (("--point-noise", point_noise), ("--force-noise", force_noise), ("--depth-noise", depth_noise)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name}: must be >= 0, got {value}")
    _check_wrist_reach(wrist_reach)
    if wrist_reach is not None and depth_size is not None:
        raise ValueError("--wrist-reach: not with --depth (the camera renders the env's own grasp)")
    if not str(out).endswith(".npz"):
        raise ValueError(f"--out: an observation file ends in .npz, got {out!r}")
    env = _make(env_id, parse_json_mapping(env_kwargs), physics_overrides(young_modulus, poisson, law))
    if wrist_reach is None:
        obs = record(env, scripted_policy(env.unwrapped.scene), seed=seed, steps=steps, points=points,
                     point_noise=point_noise, force_noise=force_noise, noise_seed=seed, env_id=env_id,
                     depth_size=depth_size, depth_noise=depth_noise)
    else:  # the env records the gripper's path; the replay, the tissue held on the wrist
        path = record(env, scripted_policy(env.unwrapped.scene), seed=seed, steps=steps, points=points, env_id=env_id)
        obs, _, _ = on_a_free_wrist(env, path, wrist_reach, point_noise, force_noise, noise_seed=seed)
    obs.meta["env_kwargs"] = parse_json_mapping(env_kwargs)
    if not force:  # (what a robot without a force sensor logs)
        obs.force = None
    save_observation(obs, out)
    return {"out": str(out), "steps": obs.steps, "points": 0 if obs.points is None else obs.points.shape[1],
            "depth": None if obs.depth is None else list(obs.depth.shape[1:]),
            "truth": obs.meta["truth"], "adhesion_width_m": obs.adhesion_width, "wrist_reach_m": wrist_reach}


def calibrate(env_id: str | None, observation: str, out: str, fit_names=("young_modulus", "poisson_ratio"),
              law: str | None = None, env_kwargs: str | None = None, starts: int = 1,
              point_scale: float | None = None, force_scale: float | None = None, progress: bool = True,
              wrist_reach: float | None = None,
              regions: str | None = None, use: str | None = None, mesh_correction: bool = True,
              jobs: int = 1) -> dict:
    """Fit the tissue of ``env_id``'s scene (default: the observation's env) to
    ``observation``; write ``fit.json`` and ``fit.png`` into ``out``. ``wrist_reach`` (m):
    the jaws hold the tissue within that distance of what the scene's jaws take, on a free
    wrist (:func:`heml_gym.envs.observations.control_log`); ``regions`` (``"NXxNYxNZ"``):
    Young's modulus fitted per box of that grid over the tissue's rest bounding box; ``use``
    (``"points,force"``, ...): the observed quantities fitted (default: the task's calibration
    model's choice, :mod:`heml_gym.envs.calibration_models`, which also names the fitted model
    unless ``env_kwargs`` does); ``mesh_correction``: take the fitted mesh's bias against the
    calibration model's finer reference off the fitted constants
    (:func:`~heml_gym.envs.calibration_models.correct_for_mesh`; the lobe's; the chart and
    recording show the fitted model's own fit); ``jobs``: with ``law="auto"``, the laws
    fitted in that many worker processes at once (:func:`select_law`); else, with ``starts``
    > 1, the starts (:func:`fit_starts_in_parallel`).
    ``point_scale`` (m) and ``force_scale`` (N): the residual scales (the sensors' noise);
    neither given: 1 mm and 0.05 N to start, then each quantity weighed by its own residual
    (:func:`heml_gym.calibration.fit`'s ``weigh_by_residuals``). Returns the fit's record."""
    from heml_gym.calibration import DEFAULT_FORCE_SCALE, DEFAULT_POINT_SCALE, embed_points, fit
    from heml_gym.envs import SAME_STATE_TASK, unknown_env_message
    from heml_gym.envs.calibration_models import calibration_model
    from heml_gym.envs.observations import QUANTITIES, fit_parameter, keep_observed, load_observation
    from heml_gym.mesh import box_regions

    import gymnasium as gym

    obs = load_observation(observation)
    env_id = env_id or SAME_STATE_TASK.get(obs.env_id, obs.env_id)  # (a retired id of the same scene: its successor)
    if env_id is None:
        raise ValueError("ENV: the observation names no env: give one")
    if env_id not in gym.registry:
        raise ValueError(f"ENV: {unknown_env_message(env_id)}")
    model = calibration_model(env_id)
    kwargs = model.env_kwargs if env_kwargs is None else parse_json_mapping(env_kwargs)
    model_label = model.label if env_kwargs is None else "the model of --env-kwargs"
    present = [k for k in QUANTITIES if getattr(obs, k) is not None]
    if use is not None:
        keep_observed(obs, [n.strip() for n in str(use).split(",") if n.strip()], "--use")
    else:
        keep_observed(obs, model.quantities(present), "the calibration model's quantities")
    fitted = [k for k in QUANTITIES if getattr(obs, k) is not None]
    caveats = model.warnings(fitted)
    if starts < 1:
        raise ValueError(f"--starts: must be >= 1, got {starts}")
    if check_jobs(jobs) > 1 and law != "auto" and starts == 1:
        raise ValueError(f"--jobs: runs the laws of --law auto or the starts of --starts N in parallel, got "
                         f"--jobs {jobs} with neither")
    _check_wrist_reach(wrist_reach)
    grid = parse_regions(regions)
    weigh = point_scale is None and force_scale is None
    point_scale = DEFAULT_POINT_SCALE if point_scale is None else point_scale
    force_scale = DEFAULT_FORCE_SCALE if force_scale is None else force_scale
    for name, value in (("--point-scale", point_scale), ("--force-scale", force_scale)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name}: must be a positive number, got {value}")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"--out {out}: exists and is not empty (give a new folder)")
    selection = None
    if law == "auto":
        law, selection = select_law(env_id, obs, tuple(fit_names), kwargs, point_scale, force_scale,
                                    progress, wrist_reach, grid, weigh, jobs)
    env, (replay, observed, names, bounds, start) = _problem(env_id, kwargs, law, obs, fit_names, point_scale,
                                                             force_scale, wrist_reach, grid)
    first = np.array(start, dtype=np.float64)
    start_list = [first]
    rng = np.random.default_rng(0)
    for _ in range(starts - 1):  # further starts: log-uniform within a factor 2 of the first (E), +-0.05 (nu)
        s = first.copy()
        for j, name in enumerate(names):
            lo, hi = bounds[j]
            s[j] = np.clip(s[j] * 2.0 ** rng.uniform(-1, 1) if name.startswith("young_modulus")
                           else s[j] + rng.uniform(-0.05, 0.05), lo, hi)
        start_list.append(s)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc="calibrating", unit="iteration")

    def report(i, loss):
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4g}")

    t0 = time.perf_counter()
    try:
        if jobs > 1 and selection is None and starts > 1:  # (with --law auto, the laws ran in parallel)
            template = StartFitJob(env_id, kwargs, law, obs, tuple(fit_names), point_scale, force_scale, wrist_reach,
                                   grid, first)
            starts_bar = None
            if progress:
                from tqdm import tqdm

                starts_bar = tqdm(total=starts, desc=f"starts ({min(jobs, starts)} at once)", unit="start")
            try:  # (then the best start is polished here: the "calibrating" bar's iterations)
                result = fit_starts_in_parallel(replay, observed, names, bounds, start_list, jobs, template, weigh,
                                                progress=report, bar=starts_bar)
            finally:
                if starts_bar is not None:
                    starts_bar.close()
        else:
            result = fit(replay, observed, names, start_list, bounds, progress=report, weigh_by_residuals=weigh)
    finally:
        if bar is not None:
            bar.close()
    final = replay.run(result.theta)
    values, stds = [float(v) for v in result.theta], [float(v) for v in result.std]
    correction = None  # (the fitted mesh's bias against a finer model, taken off: envs.calibration_models)
    if mesh_correction and model.reference is not None and env_kwargs is None:
        if obs.points is None and obs.force is None:
            correction = {"reference": model.reference_label,
                          "skipped": "depth is not corrected (the fit renders the fitted model's tissue)"}
        else:
            from heml_gym.calibration import ReplayError
            from heml_gym.envs.calibration_models import correct_for_mesh

            if progress:
                print(f"correcting for the mesh: replaying the fit on {model.reference_label} and fitting that "
                      "(a few minutes)", file=sys.stderr, flush=True)
            try:
                done = correct_for_mesh(_make(env_id, model.reference, physics_overrides(law=law)), obs, replay,
                                        fit_names, names, result, bounds, model.reference_label, wrist_reach, grid)
                correction = {"reference": done.reference, "reference_env_kwargs": model.reference,
                              "raw": done.raw, "refit": done.refit, "corrected": done.corrected,
                              "converged": done.converged, "wall_s": done.wall_s}
                values, stds = done.corrected, done.std
            except ReplayError as exc:
                correction = {"reference": model.reference_label, "error": str(exc)}
    out.mkdir(parents=True, exist_ok=True)
    # (a standard error the data do not determine is null, not JSON's non-standard Infinity)
    parameters = {name: {"value": v, "std": sd if math.isfinite(sd) else None, "unit": fit_parameter(name)[0]}
                  for name, v, sd in zip(names, values, stds)}
    region = None if grid is None else box_regions(replay.model.mesh, grid)  # each tet's box
    record = {
        "parameters": parameters,
        "law": env.unwrapped.scene.physics.material,
        "converged": result.converged, "message": result.message, "loss": result.loss,
        "residual_rms": result.residual_rms, "history": result.history, "starts": result.starts,
        "failed_trials": result.failed_trials,
        "loosely_determined": loosely_determined(parameters),
        "by_quantity": {q: {"parameters": dict(zip(names, own["theta"])), "std": dict(zip(names, own["std"]))}
                        for q, own in result.by_quantity.items()},
        "disagreements": disagreements(result.by_quantity, names),
        "law_selection": selection,
        "law_ambiguity": law_ambiguity(selection, names),
        "regions": None if grid is None else _regions_record(replay.model.mesh, grid, region),
        "caveats": caveats,
        "mesh_correction": correction,
        "settings": {"env_id": env_id, "env_kwargs": kwargs, "model": model_label, "observation": str(observation),
                     "fit": names, "bounds": bounds, "point_scale_m": result.scales["point_scale_m"],
                     "force_scale_N": result.scales["force_scale_N"],
                     "scales": "weighed by the residuals" if weigh else "given",
                     "regions": regions,
                     "wrist_reach_m": wrist_reach,
                     "observed": fitted, "in_the_file": present,
                     "steps": obs.steps, "mesh": {"vertices": int(replay.model.n_vertices),
                                                   "tets": int(replay.model.mesh.n_tets)}},
        "wall_s": time.perf_counter() - t0,
    }
    fitted_points = None  # the tracked points where the fitted tissue puts them, (T + 1, K, 3) m
    if obs.points is not None:
        B = embed_points(replay.model.mesh, obs.rest_points)
        fitted_points = np.stack([B @ x for x in final.x])
    _chart(out / "fit.png", result, obs, final, fitted_points, observed.extra)
    colours = None  # (with regions: each vertex by its regions' fitted moduli)
    if grid is not None:
        colours = region_colours(replay.model.mesh, region, [result.theta[names.index(n)] for n in names
                                                             if n.startswith("young_modulus_")])
    record["recording"] = _record(out / "fit.rrd", obs, final, fitted_points, env.unwrapped.task.scene.surface_faces,
                                  colours)
    (out / "fit.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


#: A fitted constant whose standard error is above its limit here (absolute) or above
#: :data:`LOOSE_RELATIVE` of its value (the others) is reported as loosely determined: nu's
#: limit is issue 34's bar for it, Mooney-Rivlin's c01 share a tenth of its range.
LOOSE_ABSOLUTE = {"poisson_ratio": 0.02, "c01_fraction": 0.1}
LOOSE_RELATIVE = 0.10


#: Two observed quantities disagree on a constant when their own estimates differ by more
#: than this many of their combined standard errors and by more than 2 % (nu: 0.01).
DISAGREEMENT_SIGMAS = 3.0


def disagreements(by_quantity: dict, names) -> list[dict]:
    """The constants on which two observed quantities' own estimates
    (:class:`heml_gym.calibration.FitResult`'s ``by_quantity``) disagree beyond their errors
    (:data:`DISAGREEMENT_SIGMAS`): ``[{"constant": name, "estimates": {quantity: value}}]``.
    Noise cannot part them so far; a model error in one of them can (the lobe's force)."""
    import itertools

    found = []
    for j, name in enumerate(names):
        values = {q: own["theta"][j] for q, own in by_quantity.items()}

        def apart(qa, qb):
            gap = abs(values[qa] - values[qb])
            sigma = math.hypot(by_quantity[qa]["std"][j], by_quantity[qb]["std"][j])
            floor = 0.01 if name == "poisson_ratio" else 0.02 * max(abs(values[qa]), abs(values[qb]))
            return gap > DISAGREEMENT_SIGMAS * sigma and gap > floor

        if any(apart(qa, qb) for qa, qb in itertools.combinations(values, 2)):
            found.append({"constant": name, "estimates": values})
    return found


def loosely_determined(parameters: dict) -> list[str]:
    """The names in fit.json's ``parameters`` whose standard error the data leave above
    their limit (:data:`LOOSE_ABSOLUTE`, :data:`LOOSE_RELATIVE`), or undetermined (None)."""
    loose = []
    for name, p in parameters.items():
        std = p["std"]
        limit = LOOSE_ABSOLUTE.get(name, LOOSE_RELATIVE * abs(p["value"]))
        if std is None or std > limit:
            loose.append(name)
    return loose


def parse_regions(regions: str | None) -> tuple[int, int, int] | None:
    """``--regions NXxNYxNZ`` as three integers (None: one E for the whole tissue)."""
    if regions is None:
        return None
    from heml_gym.mesh import check_region_grid

    try:
        grid = tuple(int(v) for v in str(regions).lower().split("x"))
    except ValueError:
        grid = ()
    try:
        return check_region_grid(grid, "--regions")
    except ValueError:
        raise ValueError(f"--regions: boxes along x, y and z as NXxNYxNZ (each 1-64), e.g. 2x1x1, got {regions!r}") \
            from None


def _regions_record(mesh, grid, region) -> dict:
    """fit.json's ``regions``: the grid, the box it cuts (m) and each box's share of the
    tissue's volume (:func:`heml_gym.envs.observations.physics_from_fit` reads them);
    ``region``: each tet's box (:func:`heml_gym.mesh.box_regions`)."""
    volume = np.bincount(region, weights=mesh.volumes, minlength=int(np.prod(grid)))
    return {"grid": list(grid), "box_m": [mesh.vertices.min(axis=0).tolist(), mesh.vertices.max(axis=0).tolist()],
            "volume_fraction": (volume / volume.sum()).tolist()}


def region_colours(mesh, region, moduli) -> np.ndarray:
    """(n, 3) uint8: each vertex coloured by the mean fitted modulus of the regions of the
    tets around it (``region``: each tet's box, :func:`heml_gym.mesh.box_regions`;
    ``moduli``, Pa, one per box), blue the softest region's, red the stiffest's (one colour
    when they are equal)."""
    import matplotlib

    moduli = np.asarray(moduli, dtype=np.float64)
    per_tet = moduli[region]
    total = np.zeros(mesh.n_vertices)
    count = np.zeros(mesh.n_vertices)
    for corner in range(4):
        np.add.at(total, mesh.tets[:, corner], per_tet)
        np.add.at(count, mesh.tets[:, corner], 1.0)
    span = moduli.max() - moduli.min()
    level = (total / np.maximum(count, 1.0) - moduli.min()) / span if span > 0 else np.full(mesh.n_vertices, 0.5)
    return (255 * matplotlib.colormaps["coolwarm"](level)[:, :3]).astype(np.uint8)


def _record(path: Path, obs, final, fitted_points, faces, colours=None) -> str | None:
    """``fit.rrd``: the fitted tissue (its surface mesh; ``colours`` (n, 3) per vertex,
    default the tissue's), the observed and the fitted tracked points, and the observed and
    fitted jaw force, at each control step (timeline ``sim_time``, s). None (and nothing
    written) without the rerun SDK."""
    try:
        import rerun as rr
    except ImportError:
        return None
    from heml_gym.envs import palette

    rec = rr.RecordingStream("heml_gym_calibration")
    rec.set_log_time_enabled(False)
    rec.save(str(path))
    if colours is None:
        colours = np.tile(palette.TISSUE, (final.x.shape[1], 1))
    for k, t in enumerate(obs.t):
        rec.set_time("sim_time", duration=float(t))
        rec.log("world/fitted_tissue", rr.Mesh3D(vertex_positions=final.x[k], triangle_indices=faces,
                                                 vertex_colors=colours))
        if fitted_points is not None:
            rec.log("world/observed_points", rr.Points3D(obs.points[k], radii=0.0015, colors=[[220, 40, 40]]))
            rec.log("world/fitted_points", rr.Points3D(fitted_points[k], radii=0.0015, colors=[[40, 160, 60]]))
        rec.log("world/gripper", rr.Points3D([obs.gripper[k]], radii=0.003, colors=[[60, 60, 60]]))
        if obs.force is not None and k > 0:
            for d, axis in enumerate("xyz"):
                rec.log(f"plots/force/observed_{axis}", rr.Scalars(float(obs.force[k, d])))
                rec.log(f"plots/force/fitted_{axis}", rr.Scalars(float(final.force[k - 1, d])))
    rec.flush()
    return str(path)


@dataclass
class LawFitJob:
    """One law's fit of ``--law auto`` (:func:`select_law`): what a worker process needs."""

    law: str
    env_id: str
    env_kwargs: dict
    part: object  # the observation with half the tracked points (envs.observations.Observation)
    held_points: np.ndarray  # (T, K/2, 3) m, the other half
    held_rest: np.ndarray  # (K/2, 3) m, their rest places
    fit_names: tuple
    point_scale: float
    force_scale: float
    wrist_reach: float | None
    regions: tuple | None
    weigh_by_residuals: bool


def fit_law(job: LawFitJob) -> dict:
    """Fit ``job.law`` to the fitted half of the tracked points (and the force) and predict
    the held-out half: the law's record of :func:`select_law` (``error``: a replay that
    could not be made). A module-level function: ``--jobs`` runs it in worker processes."""
    from heml_gym.calibration import ReplayError, embed_points, fit

    try:
        _, (replay, observed, names, bounds, start) = _problem(
            job.env_id, job.env_kwargs, job.law, job.part, job.fit_names, job.point_scale, job.force_scale,
            job.wrist_reach, job.regions)
        result = fit(replay, observed, names, [start], bounds, weigh_by_residuals=job.weigh_by_residuals)
        predicted = replay.run(result.theta)
    except ReplayError as exc:
        return {"law": job.law, "error": str(exc)}
    B = embed_points(replay.model.mesh, job.held_rest)
    pts = np.stack([B @ x for x in predicted.x])
    squared = ((pts - job.held_points) ** 2).sum(axis=-1).mean(axis=1)  # per observed time, m^2
    return {"law": job.law, "theta": dict(zip(names, map(float, result.theta))),
            "std": dict(zip(names, map(float, result.std))), "converged": result.converged,
            "heldout_rms_m": float(np.sqrt(squared.mean())),
            "heldout_rms_per_time_m": np.sqrt(squared).tolist(), "fit_loss": result.loss}


def _worker_threads(threads: int) -> None:
    """A ``--jobs`` worker's start: its share of the cores for Numba's threads."""
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


def check_jobs(jobs: int) -> int:
    """``--jobs``: a whole number of worker processes, >= 1."""
    if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or jobs < 1:
        raise ValueError(f"--jobs: must be a whole number >= 1 (worker processes), got {jobs!r}")
    return int(jobs)


def run_jobs(fn, work: list, jobs: int, bar=None) -> list:
    """``[fn(w) for w in work]``, in ``jobs`` spawned worker processes when ``jobs`` > 1 (each
    with its share of the cores for Numba's threads); ``bar`` (tqdm) counts each job done.
    ``fn`` and the jobs must pickle (module-level function, dataclasses)."""
    results = [None] * len(work)
    if jobs == 1:
        for i, job in enumerate(work):
            results[i] = fn(job)
            if bar is not None:
                bar.update(1)
        return results
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor, as_completed

    workers = min(jobs, len(work))
    threads = max(1, len(os.sched_getaffinity(0)) // workers)
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_worker_threads, initargs=(threads,)) as pool:
        pending = {pool.submit(fn, job): i for i, job in enumerate(work)}
        for done in as_completed(pending):
            results[pending[done]] = done.result()
            if bar is not None:
                bar.update(1)
    return results


@dataclass
class StartFitJob:
    """One start of a multi-start fit (``--starts N --jobs M``): what a worker process needs."""

    env_id: str
    env_kwargs: dict
    law: str | None
    observation: object  # envs.observations.Observation
    fit_names: tuple
    point_scale: float
    force_scale: float
    wrist_reach: float | None
    regions: tuple | None
    start: np.ndarray


def fit_start(job: StartFitJob):
    """The fit from ``job.start`` alone, at the given residual scales
    (:class:`heml_gym.calibration.FitResult`), or ``{"error": why}`` where its replay cannot
    be followed. A module-level function: ``--jobs`` runs it in worker processes."""
    from heml_gym.calibration import ReplayError, fit

    try:
        _, (replay, observed, names, bounds, _) = _problem(
            job.env_id, job.env_kwargs, job.law, job.observation, job.fit_names, job.point_scale, job.force_scale,
            job.wrist_reach, job.regions)
        return fit(replay, observed, names, [job.start], bounds)
    except ReplayError as exc:
        return {"error": str(exc)}


def fit_starts_in_parallel(replay, observed, names, bounds, start_list, jobs: int, job: StartFitJob,
                           weigh_by_residuals: bool, progress=None, bar=None):
    """:func:`heml_gym.calibration.fit` from each of ``start_list``, the starts in ``jobs``
    worker processes (:func:`fit_start`, ``job`` a template whose ``start`` each takes), then,
    in this process, the best start's fit polished from its optimum (and, with
    ``weigh_by_residuals``, re-weighed as :func:`~heml_gym.calibration.fit` does): the result
    of the serial multi-start up to the fits' tolerance, with every start's record."""
    import dataclasses

    from heml_gym.calibration import ReplayError, fit

    runs = run_jobs(fit_start, [dataclasses.replace(job, start=np.asarray(s, dtype=np.float64)) for s in start_list],
                    jobs, bar)
    fitted = [r for r in runs if not isinstance(r, dict)]
    if not fitted:
        raise ReplayError(runs[0]["error"])
    best = min(fitted, key=lambda r: r.loss)
    result = fit(replay, observed, names, [best.theta], bounds, progress=progress,
                 weigh_by_residuals=weigh_by_residuals)
    starts = [record for r, s in zip(runs, start_list)  # (a start whose replay failed: why)
              for record in ([{"start": np.asarray(s, dtype=np.float64).tolist(), "error": r["error"]}]
                             if isinstance(r, dict) else r.starts)]
    return dataclasses.replace(result, starts=starts, history=best.history + result.history,
                               wall_s=sum(r.wall_s for r in fitted) + result.wall_s,
                               failed_trials=sum(r.failed_trials for r in fitted) + result.failed_trials)


def select_law(env_id: str, obs, fit_names, env_kwargs: dict, point_scale: float, force_scale: float,
               progress: bool = True, wrist_reach: float | None = None, regions=None,
               weigh_by_residuals: bool = False, jobs: int = 1) -> tuple[str, list[dict]]:
    """``--law auto``: fit each law of :mod:`heml_gym.materials` to half the tracked points
    (and the force) and keep the one that predicts the other half best (held-out RMS, m).
    Returns the law's name and every law's record (:func:`fit_law`); each fitted law's
    record holds the 95 % bootstrap interval (over the observed times) of its held-out RMS
    minus the winner's (``difference_ci95_m``, :func:`heml_gym.calibration.paired_rms_interval`)
    and whether that interval reaches 0 (``as_good_as_winner``: the data do not tell it
    from the winner). ``jobs`` > 1: the laws are fitted in that many worker processes at
    once (spawned, each with its share of the cores for Numba's threads), the records the same."""
    import copy

    from heml_gym.calibration import paired_rms_interval
    from heml_gym.envs.observations import LAW_CONSTANTS
    from heml_gym.envs.scene import LAWS

    jobs = check_jobs(jobs)
    if obs.points is None or obs.points.shape[1] < 4:
        raise ValueError("--law auto: needs at least 4 tracked points (half fit, half held out)")
    own = [name for name in fit_names if name in LAW_CONSTANTS]
    if own:
        raise ValueError(f"--law auto: fits the same constants to every law, and {own[0]} is "
                         f"{LAW_CONSTANTS[own[0]][0]}'s only (drop it, or give --law {LAW_CONSTANTS[own[0]][0]})")
    K = obs.points.shape[1]
    train, held = np.arange(0, K, 2), np.arange(1, K, 2)
    part = copy.deepcopy(obs)
    part.points, part.rest_points = obs.points[:, train], obs.rest_points[train]
    laws = list(LAWS)
    work = [LawFitJob(name, env_id, env_kwargs, part, obs.points[:, held], obs.rest_points[held], tuple(fit_names),
                      point_scale, force_scale, wrist_reach, regions, weigh_by_residuals) for name in laws]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(laws), desc="laws" + (f" ({min(jobs, len(laws))} at once)" if jobs > 1 else ""),
                   unit="law")
    try:
        records = run_jobs(fit_law, work, jobs, bar)
    finally:
        if bar is not None:
            bar.close()
    usable = [r for r in records if "heldout_rms_m" in r and r["converged"]]
    if not usable:
        raise ValueError("--law auto: no law could be fitted (see each law's record)")
    winner = min(usable, key=lambda r: r["heldout_rms_m"])
    for r in usable:  # can the data tell this law from the winner? (the winner's own interval is 0 to 0)
        lo, hi = paired_rms_interval(r["heldout_rms_per_time_m"], winner["heldout_rms_per_time_m"])
        r["difference_ci95_m"] = [lo, hi]
        r["as_good_as_winner"] = bool(lo <= 0.0)
    return winner["law"], records


def law_ambiguity(selection: list[dict] | None, names) -> dict | None:
    """``--law auto``'s verdict when the data do not name one law: the laws whose held-out
    RMS is within the 95 % interval of the winner's (:func:`select_law`), and the range of
    each fitted constant across them (a constant's value depends on the law assumed, and
    the data do not fix which). None when only the winner remains (or without a selection)."""
    if not selection:
        return None
    tied = [r for r in selection if r.get("as_good_as_winner")]
    if len(tied) < 2:
        return None
    return {"laws": [r["law"] for r in tied],
            "ranges": {name: [min(r["theta"][name] for r in tied), max(r["theta"][name] for r in tied)]
                       for name in names}}


def _chart(path: Path, result, obs, final, fitted_points, extra=()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 1 + (obs.force is not None) + (obs.points is not None) + len(extra)
    fig, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 3.4), constrained_layout=True)
    axes = np.atleast_1d(axes)
    ax = axes[0]
    ax.semilogy(range(1, len(result.history) + 1), result.history, "o-", ms=3)
    ax.set_xlabel("L-BFGS iteration")
    ax.set_ylabel("loss")
    ax.set_title("fit")
    k = 1
    if obs.force is not None:
        ax = axes[k]
        k += 1
        t = obs.t[1:]
        for d, (name, colour) in enumerate(zip("xyz", ("tab:red", "tab:green", "tab:blue"))):
            ax.plot(t, obs.force[1:, d], ".", color=colour, ms=4, label=f"observed {name}")
            ax.plot(t, final.force[:, d], "-", color=colour, lw=1.2, label=f"fitted {name}")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("force on the jaws (N)")
        ax.legend(fontsize=7, ncol=2, loc="best")
    if obs.points is not None:
        ax = axes[k]
        for j in range(obs.points.shape[1]):
            line, = ax.plot(obs.t, 1e3 * obs.points[:, j, 2], ".", ms=3)
            ax.plot(obs.t, 1e3 * fitted_points[:, j, 2], "-", lw=1, color=line.get_color())
        ax.set_xlabel("time (s)")
        ax.set_ylabel("tracked point height (mm)")
        ax.set_title("dots: observed, lines: fitted", fontsize=9)
        k += 1
    for term in extra:  # a depth camera's: the last frame's residual image
        ax = axes[k]
        k += 1
        last = final.x.shape[0] - 1
        image = 1e3 * term.residual_image(final.x[last], last)
        # the scale of most pixels (the jaws in front of the tissue are off by centimetres)
        limit = max(float(np.nanpercentile(np.abs(image), 95)), 0.1) if np.isfinite(image).any() else 1.0
        shown = ax.imshow(image, cmap="coolwarm", vmin=-limit, vmax=limit)
        fig.colorbar(shown, ax=ax, label="fitted - observed depth (mm)")
        ax.set_title(f"depth at t = {obs.t[last]:.1f} s (blank: not counted)", fontsize=9)
        ax.set_axis_off()
    names = ", ".join(f"{n} {v:.4g} ± {s:.2g}" for n, v, s in zip(result.names, result.theta, result.std))
    fig.suptitle(names, fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)
