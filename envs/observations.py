"""Observation files: what a robot and its sensors saw of a retraction, for calibration.

An observation is an ``.npz`` file with, at the env's control steps ``k = 0..T`` (entry 0:
the start, before the first step):

=============== ============ =====================================================
field           shape        meaning
=============== ============ =====================================================
``t``           (T+1,)       time, s: ``k * control_dt`` (uniform, from 0)
``gripper``     (T+1, 3)     the gripper's position, m (world frame of the scene)
``grasp``       (T+1,)       bool: the jaws closed after step ``k``
``points``      (T+1, K, 3)  optional: tracked material points, m ...
``rest_points`` (K, 3)       ... and where each lies on the tissue at rest, m
``force``       (T+1, 3)     optional: the force the tissue pulls the jaws with, N,
                             the mean over step ``k`` (entry 0: 0)
``env_id``      ()           str, optional: the env (and so the scene) observed
``adhesion_width`` ()        float, optional: how far out the underside was stuck, m
``meta``        ()           str, optional: JSON, anything else (how it was made)
=============== ============ =====================================================

``depth`` (T+1, H, W) m along the optical axis (``DEPTH_FAR`` = 10 m or more: nothing
seen), with ``intrinsics`` (3, 3) ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]`` (pixels; pixel
``(i, j)``'s centre at ``(j + 0.5, i + 0.5)``) and ``camera_pose`` (4, 4) camera to world
(rotation columns: image right, image down, forward; translation: the eye, m), a depth
camera's view: fitted against the model's rendered tissue depth
(:class:`~heml_gym.envs.depth_loss.DepthTerm`). :func:`record` makes such a file from a simulated episode
(``heml-gym observe``); :func:`calibration_problem` turns one and a scene into what
:func:`heml_gym.calibration.fit` takes.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from heml_gym.calibration import (DEFAULT_FORCE_SCALE, DEFAULT_POINT_SCALE, ControlLog, Observed, Replay,
                                  ReplayResult, embed_points)
from heml_gym.mesh import box_regions, check_region_grid

__all__ = ["Observation", "ObservationError", "load_observation", "save_observation", "record", "control_log",
           "on_a_free_wrist", "calibration_problem", "FIT_PARAMETERS", "LAW_CONSTANTS", "physics_from_fit",
           "fit_parameter", "region_names", "keep_observed", "QUANTITIES"]

#: Constants a calibration can fit: name -> (unit, bounds).
#: m: a depth image's value where the camera saw nothing
DEPTH_FAR = 10.0
#: ``c01_fraction`` (MooneyRivlin: the share of the shear modulus in ``c01``) and ``b``
#: (Demiray: how fast the tissue stiffens) are constants of one law (:data:`LAW_CONSTANTS`).
FIT_PARAMETERS = {"young_modulus": ("Pa", (200.0, 200e3)), "poisson_ratio": ("", (0.0, 0.495)),
                  "density": ("kg/m^3", (100.0, 10000.0)), "damping": ("1/s", (0.0, 200.0)),
                  "c01_fraction": ("", (0.0, 1.0)), "b": ("", (0.05, 50.0))}
#: The fittable constants of one law only (its ``material_options``), and their defaults.
LAW_CONSTANTS = {"c01_fraction": ("MooneyRivlin", 0.25), "b": ("Demiray", 2.0)}


def region_names(count: int) -> list[str]:
    """The names of Young's modulus in each of ``count`` regions (``young_modulus_0``, ...)."""
    return [f"young_modulus_{k}" for k in range(count)]


def fit_parameter(name: str) -> tuple[str, tuple[float, float]]:
    """``(unit, bounds)`` of a fittable constant, a region's modulus (``young_modulus_k``) included."""
    if name.startswith("young_modulus_") and name[len("young_modulus_"):].isdigit():
        return FIT_PARAMETERS["young_modulus"]
    return FIT_PARAMETERS[name]


class ObservationError(ValueError):
    """A malformed, non-finite, mis-shaped or inconsistent observation file."""


@dataclass
class Observation:
    """An observation (see the module docstring for the fields and units)."""

    t: np.ndarray
    gripper: np.ndarray
    grasp: np.ndarray
    points: np.ndarray | None = None
    rest_points: np.ndarray | None = None
    force: np.ndarray | None = None
    depth: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    camera_pose: np.ndarray | None = None
    env_id: str | None = None
    adhesion_width: float | None = None
    meta: dict = field(default_factory=dict)
    source: str = "observation"

    def __post_init__(self):
        where = self.source

        def bad(name, why):
            return ObservationError(f"{where}: field '{name}': {why}")

        def array(name, value, ndim, dtype=np.float64):
            a = np.asarray(value)
            if a.ndim != ndim:
                raise bad(name, f"must have {ndim} dimensions, got shape {a.shape}")
            if dtype is bool:
                if a.dtype != bool and not np.isin(a, (0, 1)).all():
                    raise bad(name, "must be booleans (0 or 1)")
                return a.astype(bool)
            if not np.issubdtype(a.dtype, np.number):
                raise bad(name, f"must be numbers, got {a.dtype}")
            a = a.astype(np.float64)
            if not np.all(np.isfinite(a)):
                raise bad(name, "must be finite (NaN or inf found)")
            return a

        self.t = array("t", self.t, 1)
        T1 = self.t.shape[0]
        if T1 < 2:
            raise bad("t", f"needs at least 2 entries (the start and one step), got {T1}")
        if self.t[0] != 0.0 or np.any(np.diff(self.t) <= 0):
            raise bad("t", "must start at 0 and increase")
        self.gripper = array("gripper", self.gripper, 2)
        if self.gripper.shape != (T1, 3):
            raise bad("gripper", f"must have shape ({T1}, 3) (one position per t), got {self.gripper.shape}")
        self.grasp = array("grasp", self.grasp, 1, bool)
        if self.grasp.shape != (T1,):
            raise bad("grasp", f"must have shape ({T1},), got {self.grasp.shape}")
        if (self.points is None) != (self.rest_points is None):
            raise bad("points" if self.points is None else "rest_points", "points and rest_points go together")
        if self.points is not None:
            self.points = array("points", self.points, 3)
            self.rest_points = array("rest_points", self.rest_points, 2)
            K = self.rest_points.shape[0]
            if self.rest_points.shape != (K, 3) or K < 1:
                raise bad("rest_points", f"must have shape (K, 3), K >= 1, got {self.rest_points.shape}")
            if self.points.shape != (T1, K, 3):
                raise bad("points", f"must have shape ({T1}, {K}, 3) (T+1 times, K points), got {self.points.shape}")
        if self.force is not None:
            self.force = array("force", self.force, 2)
            if self.force.shape != (T1, 3):
                raise bad("force", f"must have shape ({T1}, 3), got {self.force.shape}")
        if self.depth is not None:
            self.depth = array("depth", self.depth, 3)
            if self.depth.shape[0] != T1:
                raise bad("depth", f"must have {T1} images, got {self.depth.shape[0]}")
            for name, shape in (("intrinsics", (3, 3)), ("camera_pose", (4, 4))):
                value = getattr(self, name)
                if value is None:
                    raise bad(name, "depth needs it")
                value = array(name, value, 2)
                if value.shape != shape:
                    raise bad(name, f"must have shape {shape}, got {value.shape}")
                setattr(self, name, value)
            if np.any(self.depth <= 0.0):
                raise bad("depth", "must be positive distances in metres along the optical axis")
            if not np.any(self.depth < DEPTH_FAR):
                raise bad("depth", f"nothing seen: every pixel is at {DEPTH_FAR:g} m or more (depth in metres? "
                                   "millimetres would read as 1000 times too far)")
            k, (height, width) = self.intrinsics, self.depth.shape[1:]
            f = k[0, 0]
            square = f > 0 and abs(k[1, 1] - f) <= 1e-9 * f
            form = k[0, 1] == 0 and k[1, 0] == 0 and k[2, 0] == 0 and k[2, 1] == 0 and k[2, 2] == 1
            if not (square and form and 0 < k[0, 2] < width and 0 < k[1, 2] < height):
                raise bad("intrinsics", f"must be [[f, 0, cx], [0, f, cy], [0, 0, 1]] with f > 0 (square pixels) "
                                        f"and the principal point inside the {height} x {width} image, got "
                                        f"{np.round(k, 6).tolist()}")
            rotation = self.camera_pose[:3, :3]
            rigid = (np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) and np.linalg.det(rotation) > 0
                     and np.array_equal(self.camera_pose[3], [0.0, 0.0, 0.0, 1.0]))
            if not rigid:
                raise bad("camera_pose", "must be a rigid camera-to-world transform: a rotation (orthonormal, "
                                         "det +1) and the eye, bottom row [0, 0, 0, 1]")
        if self.points is None and self.force is None and self.depth is None:
            raise ObservationError(f"{where}: nothing observed: give points (with rest_points), force or depth")
        if self.adhesion_width is not None:
            w = float(self.adhesion_width)
            if not (math.isfinite(w) and w >= 0):
                raise bad("adhesion_width", f"must be a distance >= 0 (m), got {self.adhesion_width!r}")
            self.adhesion_width = w

    @property
    def steps(self) -> int:
        return self.t.shape[0] - 1


def load_observation(path) -> Observation:
    """Read and check an observation file (one-line :class:`ObservationError` naming the field)."""
    path = Path(path)
    if not path.is_file():
        raise ObservationError(f"{path}: not found")
    try:
        data = np.load(path, allow_pickle=False)
        fields_ = {k: data[k] for k in data.files}
    except Exception as exc:  # a damaged or foreign file
        raise ObservationError(f"{path}: not a readable .npz observation ({type(exc).__name__}: {exc})") from None
    known = {f.name for f in dataclasses.fields(Observation)} - {"source"}
    unknown = sorted(set(fields_) - known)
    if unknown:
        raise ObservationError(f"{path}: field '{unknown[0]}': not an observation field (known: {', '.join(sorted(known))})")
    for name in ("t", "gripper", "grasp"):
        if name not in fields_:
            raise ObservationError(f"{path}: field '{name}': missing")
    kwargs = dict(fields_)
    for name in ("env_id", "meta"):
        if name in kwargs:
            kwargs[name] = str(kwargs[name])
    if "meta" in kwargs:
        try:
            kwargs["meta"] = json.loads(kwargs["meta"])
        except json.JSONDecodeError:
            raise ObservationError(f"{path}: field 'meta': not JSON") from None
    if "adhesion_width" in kwargs:
        kwargs["adhesion_width"] = float(np.asarray(kwargs["adhesion_width"]).reshape(-1)[0])
    return Observation(**kwargs, source=str(path))


def save_observation(obs: Observation, path) -> Path:
    """Write ``obs`` as an ``.npz`` observation file."""
    path = Path(path)
    data = {"t": obs.t, "gripper": obs.gripper, "grasp": obs.grasp}
    for name in ("points", "rest_points", "force", "depth", "intrinsics", "camera_pose"):
        if getattr(obs, name) is not None:
            data[name] = getattr(obs, name)
    if obs.env_id is not None:
        data["env_id"] = np.array(obs.env_id)
    if obs.adhesion_width is not None:
        data["adhesion_width"] = np.array(obs.adhesion_width)
    data["meta"] = np.array(json.dumps(obs.meta))
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        np.savez_compressed(fh, **data)
    return path


def record(env, policy, seed: int = 0, steps: int = 30, points: int = 10, point_noise: float = 0.0,
           force_noise: float = 0.0, noise_seed: int = 0, env_id: str | None = None,
           depth_size: tuple[int, int] | None = None, depth_noise: float = 0.0) -> Observation:
    """Run one episode of the single env ``env`` (``gym.make(...)``) under ``policy``
    (``obs -> action``) for ``steps`` steps and record what a robot would log: the gripper,
    the jaws, ``points`` tracked points on the tissue's upper surface (its free vertices,
    drawn with ``noise_seed``) with Gaussian noise of ``point_noise`` m per coordinate, the
    jaws' force with ``force_noise`` N, and with ``depth_size`` ``(H, W)`` the task
    camera's depth image (everything it sees: tissue, jaws, target, support; 10 m where
    nothing) with Gaussian noise of ``depth_noise`` m, its ``intrinsics`` and
    ``camera_pose``. The truth (law, E, nu, mesh) goes in ``meta``."""
    task = env.unwrapped.task
    scene = task.scene
    obs, _ = env.reset(seed=seed)
    if hasattr(policy, "reset"):
        policy.reset()
    rng = np.random.default_rng(noise_seed)
    X = scene.mesh.vertices
    movable = np.setdiff1d(scene.mesh.surface_vertices, scene.fixed)
    movable = movable[~task.adhered[0, movable]]
    top = movable[X[movable, 2] >= X[:, 2].max() - 1e-6]
    pool = top if top.size >= points else movable
    tracked = rng.choice(pool, size=min(points, pool.size), replace=False) if points else np.zeros(0, dtype=int)
    log = {"gripper": [task.gripper[0].copy()], "grasp": [bool(task.grasping[0])],
           "points": [task.x[0, tracked].copy()], "force": [np.zeros(3)], "depth": []}
    camera = None
    if depth_size is not None:
        view = env.unwrapped.camera_view(0, depth_size)
        height, width = view["depth"].shape
        camera = (np.array([[view["focal"], 0.0, 0.5 * width], [0.0, view["focal"], 0.5 * height], [0.0, 0.0, 1.0]]),
                  np.block([[view["rotation"].T, view["eye"][:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
        log["depth"].append(view["depth"].astype(np.float64))
    worst = 0.0  # the largest gauge strain of the episode
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(policy(obs))
        worst = max(worst, float(info["max_strain"]))
        if info.get("simulation_diverged") or not info.get("solver_converged", True):
            raise ObservationError(f"recording: the simulation failed at step {len(log['force'])}: "
                                   "diverged or unconverged (see the env's info)")
        log["gripper"].append(task.gripper[0].copy())
        log["grasp"].append(bool(task.grasping[0]))
        log["points"].append(task.x[0, tracked].copy())
        log["force"].append(task.grasp_force[0].copy())
        if camera is not None:
            log["depth"].append(env.unwrapped.camera_view(0, depth_size)["depth"].astype(np.float64))
        if terminated or truncated:
            break
    T1 = len(log["force"])
    pts = np.array(log["points"]) + rng.normal(0.0, point_noise, (T1, tracked.size, 3)) if points else None
    force = np.array(log["force"]) + rng.normal(0.0, force_noise, (T1, 3))
    force[0] = 0.0
    depth = None
    if camera is not None:
        depth = np.array(log["depth"])
        seen = depth < DEPTH_FAR
        depth = np.where(seen, depth + rng.normal(0.0, depth_noise, depth.shape), DEPTH_FAR)
    ph = scene.physics
    meta = {"made_by": "heml_gym.envs.observations.record", "seed": seed, "steps": T1 - 1,
            "truth": {"law": ph.material, "young_modulus": float(task.young_modulus[0]),
                      "poisson_ratio": float(ph.poisson), "material_options": ph.material_options},
            "mesh": {"vertices": int(scene.mesh.n_vertices), "tets": int(scene.mesh.n_tets)},
            "max_strain": worst, "point_noise_m": point_noise, "force_noise_N": force_noise,
            **({"depth_noise_m": depth_noise} if camera is not None else {})}
    width = float(task.adhesion_width[0]) if scene.adhesion_vertices is not None else None
    return Observation(t=np.arange(T1) * task.settings.control_dt, gripper=np.array(log["gripper"]),
                       grasp=np.array(log["grasp"]), points=pts, rest_points=X[tracked] if points else None,
                       force=force, env_id=env_id or (env.spec.id if env.spec is not None else None),
                       depth=depth, intrinsics=camera[0] if camera else None,
                       camera_pose=camera[1] if camera else None,
                       adhesion_width=width, meta=meta)


def control_log(env, obs: Observation, young_modulus: float | None = None,
                wrist_reach: float | None = None) -> ControlLog:
    """What drove the tissue in ``obs``, on the scene of the single env ``env``: the env is
    reset to the observed start (gripper, adhesion) and stepped with the actions that move
    its gripper along the observed path and close / open its jaws as observed; each step's
    held vertices and their targets are the log. ``young_modulus`` (Pa): the tissue used
    to find which vertices the jaws take (default: the scene's upper one).

    ``wrist_reach`` (m): jaws with a footprint on a free wrist instead of the scene's grasp:
    every vertex within that distance (at rest) of one the jaws take is held, rigidly,
    where it was when they closed, and the patch turns freely about the jaws' axis (the
    held vertices' longest direction at rest) through its middle
    (:mod:`heml_gym.calibration.wrist`). A replay, not the env's solver, steps such a
    grasp. A scene whose jaws are on a free wrist already (``scene.gripper.wrist_reach``)
    logs its own: the patch, axis and pivot its solver turned."""
    task = env.unwrapped.task
    st = task.settings
    if not np.allclose(np.diff(obs.t), st.control_dt, rtol=0, atol=1e-9):
        raise ObservationError(f"{obs.source}: field 't': steps must be the env's control_dt ({st.control_dt} s)")
    if obs.adhesion_width is None and task.scene.adhesion_vertices is not None:
        raise ObservationError(f"{obs.source}: field 'adhesion_width': missing, and the scene's underside is stuck "
                               "over a width drawn per episode (give it, m)")
    options = {"gripper": obs.gripper[0],
               "young_modulus": young_modulus if young_modulus is not None else task.scene.physics.young_modulus[1]}
    if task.scene.adhesion_vertices is not None:
        options["adhesion_width"] = obs.adhesion_width
    env.reset(seed=0, options=options)
    n = task.scene.mesh.n_vertices
    if wrist_reach is not None and not (isinstance(wrist_reach, (int, float)) and math.isfinite(wrist_reach)
                                        and wrist_reach > 0):
        raise ValueError(f"wrist_reach: must be a positive distance in metres, got {wrist_reach!r}")
    native = task.scene.spec.gripper.wrist_reach is not None
    if native and wrist_reach is not None:
        raise ValueError(f"wrist_reach: the scene's jaws are on a free wrist already (scene.gripper.wrist_reach "
                         f"{task.scene.spec.gripper.wrist_reach} m): give no other")
    kinematic, targets, gripped = [], [], []
    wrist = _WristGrasp(task, wrist_reach) if wrist_reach is not None else _SceneWrist(task) if native else None
    x0 = task.x[0].copy()
    step = st.max_speed * st.control_dt
    for k in range(1, obs.t.shape[0]):
        if wrist is not None:
            wrist.before_step()
        move = (obs.gripper[k] - obs.gripper[k - 1]) / step
        if np.any(np.abs(move) > 1.0 + 1e-6):
            raise ObservationError(f"{obs.source}: field 'gripper': moves {np.abs(move).max() * step:.4g} m in step {k}, "
                                   f"more than the env's {step:.4g} m per step (max_speed x control_dt)")
        grasp = 1.0 if obs.grasp[k] else -1.0
        _, _, terminated, truncated, info = env.step(np.append(np.clip(move, -1, 1), grasp).astype(np.float32))
        if obs.grasp[k] and not task.grasping[0]:
            raise ObservationError(f"{obs.source}: field 'grasp': the jaws close at step {k} where the scene has no "
                                   "tissue within reach of the observed gripper")
        kinematic.append(task.control.kinematic[0].copy())
        targets.append(task.control.targets[0].copy())
        gripped.append(task.held[0].copy())
        if wrist is not None:
            wrist.after_step(kinematic[-1], targets[-1], gripped[-1])
        if np.linalg.norm(task.gripper[0] - obs.gripper[k]) > 1e-6:
            raise ObservationError(f"{obs.source}: field 'gripper': step {k} leaves the scene's workspace or presses "
                                   f"held tissue below its rest (observed {obs.gripper[k].round(5).tolist()}, the "
                                   f"scene allows {task.gripper[0].round(5).tolist()})")
        if (terminated or truncated) and k < obs.t.shape[0] - 1 and info.get("simulation_diverged"):
            raise ObservationError(f"{obs.source}: the env's own solver diverged at step {k} of the observed "
                                   "control (its info's simulation_diverged), before any fitting: this model "
                                   "cannot follow it (a shorter max_dt or another integrator may)")
    turning = {} if wrist is None else wrist.log_fields()
    return ControlLog(np.array(kinematic), np.array(targets), st.control_dt, task.substeps, x0, np.zeros((n, 3)),
                      gripped=np.array(gripped), **turning)


def on_a_free_wrist(env, obs: Observation, wrist_reach: float, point_noise: float = 0.0, force_noise: float = 0.0,
                    noise_seed: int = 0) -> tuple[Observation, ReplayResult, ControlLog]:
    """``obs`` (recorded by :func:`record` on ``env``'s scene) as it would have been with the
    jaws holding the tissue within ``wrist_reach`` (m) of what the scene's jaws take on a
    free wrist (:func:`control_log`): the same gripper path and grasp replayed with the
    recorded tissue (its ``meta["truth"]``) by the calibration's replay (the envs' solvers
    do not step that grasp), the tracked points and the jaws' force replaced by the
    replay's with Gaussian noise of ``point_noise`` m and ``force_noise`` N (drawn with
    ``noise_seed``). Returns the observation, the replay's result and its log."""
    if obs.depth is not None:
        raise ObservationError(f"{obs.source}: field 'depth': a free-wrist observation has no depth images (the "
                               "camera renders the env's own state, whose jaws hold the scene's grasp)")
    truth = obs.meta.get("truth", {})
    if "young_modulus" not in truth or "poisson_ratio" not in truth:
        raise ObservationError(f"{obs.source}: field 'meta': no truth (young_modulus, poisson_ratio) to replay")
    if truth.get("law") not in (None, env.unwrapped.task.scene.physics.material):
        raise ObservationError(f"{obs.source}: the truth's law is {truth['law']}, the env's "
                               f"{env.unwrapped.task.scene.physics.material}: make the env with it")
    replay, *_ = calibration_problem(env, obs, wrist_reach=wrist_reach)
    result = replay.run((float(truth["young_modulus"]), float(truth["poisson_ratio"])))
    rng = np.random.default_rng(noise_seed)
    points = None
    if obs.points is not None:
        B = embed_points(env.unwrapped.task.scene.mesh, obs.rest_points)
        points = np.stack([B @ x for x in result.x])
        points = points + rng.normal(0.0, point_noise, points.shape)
    force = None
    if obs.force is not None:
        force = np.vstack([np.zeros(3), result.force + rng.normal(0.0, force_noise, result.force.shape)])
    meta = {**obs.meta, "made_by": "heml_gym.envs.observations.on_a_free_wrist", "wrist_reach_m": float(wrist_reach),
            "point_noise_m": point_noise, "force_noise_N": force_noise}
    return dataclasses.replace(obs, points=points, force=force, meta=meta), result, replay.log


class _SceneWrist:
    """:func:`control_log` of a scene whose jaws are on a free wrist: the patch each step
    held on it, the jaws' axis and the pivot's path, from the env's control (the
    replay's targets for the patch: its places at angle 0 about the step's last pivot)."""

    def __init__(self, task):
        self.task = task
        self.masks, self.points, self.axis = [], [task.gripper[0].copy()], None

    def before_step(self) -> None:
        self.gripper_start = self.task.gripper[0].copy()

    def after_step(self, kinematic: np.ndarray, targets: np.ndarray, gripped: np.ndarray) -> None:
        control, task = self.task.control, self.task
        turns = control.turns[0].copy()
        self.masks.append(turns)
        if not turns.any():
            self.points.append(task.gripper[0].copy())
            return
        pivot = control.pivot[0].copy()
        if len(self.masks) == 1 or not np.array_equal(turns, self.masks[-2]):  # closed in this step
            self.points[-1] = self.gripper_start + (pivot - task.gripper[0])  # (the pivot moves with the gripper)
        if self.axis is not None and not np.allclose(self.axis, control.wrist_axis[0], atol=1e-12):
            raise ObservationError("the scene's jaws closed on their wrist about another axis in a later grasp; a "
                                   "replay takes one axis")
        self.axis = control.wrist_axis[0].copy()
        targets[turns] = pivot + control.arms[0, turns]
        self.points.append(pivot)

    def log_fields(self) -> dict:
        if self.axis is None:
            return {}
        return dict(wrist=np.array(self.masks), wrist_axis=self.axis, wrist_points=np.array(self.points))


class _WristGrasp:
    """:func:`control_log`'s jaws on a free wrist: the patch within ``reach`` (m) of the
    vertices the scene's jaws take, held where it is when they close and moved with the
    gripper, turning about the jaws' axis through its middle."""

    def __init__(self, task, reach: float):
        self.task, self.reach = task, float(reach)
        self.patch = self.offsets = None
        self.masks, self.points, self.axis = [], [task.gripper[0].copy()], None

    def before_step(self) -> None:
        self.x_start, self.gripper_start = self.task.x[0].copy(), self.task.gripper[0].copy()

    def after_step(self, kinematic: np.ndarray, targets: np.ndarray, gripped: np.ndarray) -> None:
        """Turn the step's recorded grasp (changed in place) into the patch's."""
        task = self.task
        jaws = task.held[0]
        if not jaws.any():
            self.patch = None
            self.masks.append(np.zeros_like(jaws))
            self.points.append(task.gripper[0].copy())
            return
        if self.patch is None:  # the jaws close: the patch, where it is
            if self.axis is None and jaws.sum() < 2:
                raise ObservationError("wrist_reach: the jaws take a single vertex, so their axis is undefined")
            patch, axis = task.wrist_patch(0, np.flatnonzero(jaws), self.reach)
            self.patch = np.zeros(len(jaws), dtype=bool)
            self.patch[patch] = True
            self.offsets = self.x_start[self.patch] - self.gripper_start
            self.middle = self.offsets.mean(axis=0)
            if self.axis is None:  # the jaws' axis: the longest direction of what they take, at rest
                self.axis = axis
            self.points[-1] = self.gripper_start + self.middle
        kinematic[self.patch] = True
        gripped[self.patch] = True
        targets[self.patch] = task.gripper[0] + self.offsets
        self.masks.append(self.patch.copy())
        self.points.append(task.gripper[0] + self.middle)

    def log_fields(self) -> dict:
        if self.axis is None:
            raise ObservationError("wrist_reach: the jaws never close in the observation: nothing turns")
        return dict(wrist=np.array(self.masks), wrist_axis=self.axis, wrist_points=np.array(self.points))


#: The observed quantities an observation can hold.
QUANTITIES = ("points", "force", "depth")


def keep_observed(obs: Observation, quantities, argument: str = "quantities") -> None:
    """Drop from ``obs`` every observed quantity (:data:`QUANTITIES`) not in ``quantities``;
    a one-line ``ValueError`` naming ``argument`` for an unknown name or one ``obs`` lacks."""
    names = list(quantities)
    if not names or any(n not in QUANTITIES for n in names):
        raise ValueError(f"{argument}: comma-separated names among {', '.join(QUANTITIES)}, got {','.join(names)!r}")
    missing = [n for n in names if getattr(obs, n) is None]
    if missing:
        has = [n for n in QUANTITIES if getattr(obs, n) is not None]
        raise ValueError(f"{argument}: the observation has no {missing[0]} (it has {', '.join(has)})")
    if "points" not in names:
        obs.points = obs.rest_points = None
    if "force" not in names:
        obs.force = None
    if "depth" not in names:
        obs.depth = obs.intrinsics = obs.camera_pose = None


def calibration_problem(env, obs: Observation, fit: tuple[str, ...] = ("young_modulus", "poisson_ratio"),
                        point_scale: float = DEFAULT_POINT_SCALE, force_scale: float = DEFAULT_FORCE_SCALE,
                        depth_scale: float = 1e-3,
                        wrist_reach: float | None = None, regions=None):
    """``(replay, observed, names, bounds, start)`` for :func:`heml_gym.calibration.fit`:
    the scene of ``env`` replaying ``obs``, the constants ``fit`` (the others kept at the
    scene's values) with their bounds, and the scene's own values as the start;
    ``wrist_reach`` (m): the jaws hold a patch on a free wrist (see :func:`control_log`);
    ``regions`` ``(nx, ny, nz)``: Young's modulus fitted in each box of that grid over the
    tissue's rest bounding box (:func:`heml_gym.mesh.box_regions`; the names
    ``young_modulus_0``, ... in place of ``young_modulus``; the scene's own
    ``stiffness_regions`` are replaced). Without ``regions`` a scene whose E varies keeps
    its regions' ratios and ``young_modulus`` scales them all."""
    unknown = [name for name in fit if name not in FIT_PARAMETERS]
    if unknown or not fit:
        raise ValueError(f"fit: {unknown[0] if unknown else 'nothing'}: can fit {', '.join(FIT_PARAMETERS)}")
    if len(set(fit)) != len(fit):
        raise ValueError(f"fit: each constant once, got {', '.join(fit)}")
    task = env.unwrapped.task
    ph = task.scene.physics
    for name in fit:
        if name in LAW_CONSTANTS and LAW_CONSTANTS[name][0] != ph.material:
            raise ValueError(f"fit: {name} is a constant of {LAW_CONSTANTS[name][0]}, the scene's law is "
                             f"{ph.material} (choose the law with --law {LAW_CONSTANTS[name][0]})")
    names, region_of = list(fit), None
    if regions is not None:
        grid = check_region_grid(regions, "regions")
        if "young_modulus" not in fit:
            raise ValueError("regions: fit young_modulus with them (it is Young's modulus that varies by region)")
        region_of = box_regions(task.model.mesh, grid)
        empty = np.flatnonzero(np.bincount(region_of, minlength=int(np.prod(grid))) == 0)
        if empty.size:
            raise ValueError(f"regions: box {int(empty[0])} of {'x'.join(map(str, grid))} holds no tet's centre on this "
                             "mesh (use fewer boxes)")
        at, count = names.index("young_modulus"), int(np.prod(grid))
        names[at:at + 1] = region_names(count)
        regional = slice(at, at + count)  # where the regions' moduli are in theta
    log = control_log(env, obs, wrist_reach=wrist_reach)
    E0 = float(np.mean(ph.young_modulus))
    defaults = {"young_modulus": E0, "poisson_ratio": float(ph.poisson), "density": float(ph.density),
                "damping": float(ph.damping)}
    for name, (law, default) in LAW_CONSTANTS.items():
        if law == ph.material:
            defaults[name] = float(ph.material_options.get(name, default))

    for name in names:
        defaults.setdefault(name, E0)  # (a region's modulus starts at the scene's)

    def material_of(theta):
        values = dict(defaults, **dict(zip(names, theta)))
        options = dict(ph.material_options, **{k: values[k] for k in LAW_CONSTANTS if k in fit})
        return dataclasses.replace(ph, poisson=values["poisson_ratio"],
                                   material_options=options).material_for(values["young_modulus"])

    def dynamics_of(theta):
        values = dict(defaults, **dict(zip(names, theta)))
        return values["density"], values["damping"]

    def stiffness_of(theta):  # each tet's region's modulus over the material's (E0)
        return np.asarray(theta[regional], dtype=np.float64)[region_of] / E0

    # the replay's own one-world model: the env's, whose world 0 it re-materialises
    replay = Replay(task.model, log, material_of, contact_stiffness=getattr(task.solver, "contact_stiffness", 1000.0),
                    dynamics_of=dynamics_of if {"density", "damping"} & set(fit) else None,
                    stiffness_of=None if region_of is None else stiffness_of)
    extra = ()
    if obs.depth is not None:
        from .depth_loss import DepthTerm

        term = DepthTerm(obs.depth, obs.intrinsics, obs.camera_pose, task.scene.surface_faces, scale=depth_scale,
                         far=DEPTH_FAR)
        if not np.isfinite(term.residual_image(log.x0, 0)).any():
            raise ObservationError(f"{obs.source}: field 'depth': at the start, the scene's tissue is not seen where "
                                   "the camera saw anything (no pixel in common): check camera_pose, intrinsics and "
                                   "that the depth is in metres")
        extra = (term,)
    observed = Observed(points=obs.points, rest_points=obs.rest_points, force=obs.force,
                        point_scale=point_scale, force_scale=force_scale, extra=extra)
    return replay, observed, names, [fit_parameter(name)[1] for name in names], [defaults[name] for name in names]


def physics_from_fit(path, spread: float = 2.0) -> dict:
    """``physics=`` changes that make a scene's tissue the one a calibration found
    (``heml-gym calibrate``'s ``fit.json``): its law and Poisson ratio, and Young's modulus
    drawn per episode uniformly within ``spread`` standard errors of the fitted value (the
    fit's uncertainty as the spread; at least 1 % of the value; a fit per region: their
    volume-weighted mean drawn within ``spread`` times the largest relative standard error,
    the regions' ratios as ``stiffness_regions``); a fitted density, damping
    or law constant (``c01_fraction``, ``b``) as fitted. ``physics={"fit":
    "DIR/fit.json"}`` in ``gym.make`` does this."""
    from .spec import SpecError

    path = Path(path)
    if path.is_dir():
        path = path / "fit.json"
    try:
        record = json.loads(path.read_text())
        parameters = record["parameters"]
        law = record["law"]
    except FileNotFoundError:
        raise SpecError(f"physics.fit: {path} not found") from None
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise SpecError(f"physics.fit: {path} is not a heml-gym calibrate fit.json ({type(exc).__name__}: {exc})") from None
    if not record.get("converged", False):
        raise SpecError(f"physics.fit: {path} records a fit that did not converge ({record.get('message', '?')})")
    out = {"material": law}
    regions = record.get("regions")
    if regions:  # E per region: its volume-weighted mean drawn, the regions' ratios kept
        try:
            named = region_names(len(regions["volume_fraction"]))
            values = np.array([float(parameters[name]["value"]) for name in named])
            stds = [parameters[name]["std"] for name in named]
            share = np.asarray(regions["volume_fraction"], dtype=np.float64)
            grid = list(regions["grid"])
        except (KeyError, TypeError, ValueError) as exc:
            raise SpecError(f"physics.fit: {path}: its regions do not match its parameters ({exc})") from None
        if any(s is None or not math.isfinite(float(s)) for s in stds):
            raise SpecError(f"physics.fit: {path}: the fit determined no uncertainty for a region's young_modulus "
                            "(the data did not constrain it): nothing to draw the tissue from")
        E = float(share @ values)
        half = max(spread * max(float(s) / v for s, v in zip(stds, values)) * E, 0.01 * E)
        out["young_modulus"] = [max(E - half, 0.5 * E), E + half]
        out["stiffness_regions"] = {"grid": grid, "relative": (values / E).tolist()}
    if "young_modulus" in parameters:
        E, s = float(parameters["young_modulus"]["value"]), parameters["young_modulus"]["std"]
        if s is None or not math.isfinite(float(s)):
            raise SpecError(f"physics.fit: {path}: the fit determined no uncertainty for young_modulus (the data "
                            "did not constrain it): nothing to draw the tissue from")
        half = max(spread * float(s), 0.01 * E)
        out["young_modulus"] = [max(E - half, 0.5 * E), E + half]
    if "poisson_ratio" in parameters:
        out["poisson"] = float(parameters["poisson_ratio"]["value"])
    for name, key in (("density", "density"), ("damping", "damping")):
        if name in parameters:
            out[key] = float(parameters[name]["value"])
    options = {name: float(parameters[name]["value"]) for name in LAW_CONSTANTS if name in parameters}
    if options:
        out["material_options"] = options
    return out
