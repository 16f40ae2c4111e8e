"""Gymnasium wrappers of the batched retraction task: one env, and a native vector env.

Both take the scene as data (``scene=``: a :class:`~heml_gym.envs.scene.Scene`, a mapping
of changes to the env's default scene, or the path of a scene YAML file) and
``physics=`` (a mapping of :class:`~heml_gym.envs.scene.PhysicsSpec` fields: the law,
its stiffness range, the force field, the integrator and its step settings), so that
``gym.make(id, physics={"material": "StVenantKirchhoff", "integrator": "implicit"})``
gives a scene the model it needs.

What training and recording use is public: :meth:`RetractionEnv.observe` /
:meth:`RetractionVectorEnv.observations`, :meth:`~RetractionVectorEnv.reset_envs` and
:meth:`~RetractionVectorEnv.step_envs` (the batch without autoreset, for other RL
libraries' adapters), :attr:`geometry` (what does not change: rest mesh, surface,
attachment, camera, thresholds) and :meth:`snapshot` (what a frame shows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from .camera import SEGMENT_IDS, CameraRenderer, ImageSpec
from .core import BatchedRetraction, RewardWeights, TaskSettings, as_settings, settings_with
from .difficulty import apply_difficulty
from .scene import PhysicsSpec, Scene, build_scene
from .spec import SpecError, from_mapping, merge, to_mapping

POINTCLOUD_SIZE = 64  # surface points in obs_mode="pointcloud"
OBS_MODES = ("state", "pointcloud", "rgb", "depth", "rgbd")
IMAGE_MODES = ("rgb", "depth", "rgbd")
POINT_BOUND = 0.5  # m: point-cloud coordinates are clipped to this


def check_actions(actions, shape) -> np.ndarray:
    """``actions`` as a float64 array of ``shape``; ``ValueError`` naming what is wrong if
    the shape differs or a value is not finite."""
    try:
        a = np.asarray(actions, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"action must be numbers of shape {shape}, got {actions!r}") from None
    if a.shape != tuple(shape):
        raise ValueError(f"action must have shape {tuple(shape)}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite, got {a.tolist()}")
    return a


def resolve_scene(default: Scene, scene=None, physics=None) -> Scene:
    """The scene an env runs: ``default``, or ``scene`` (a Scene, a mapping of changes to
    ``default``, or a YAML path), then ``physics`` (a mapping of PhysicsSpec fields)
    merged into its physics. Errors name the field."""
    if scene is None:
        spec = default
    elif isinstance(scene, Scene):
        spec = scene
    elif isinstance(scene, (str, Path)):
        spec = Scene.load(scene)
    elif isinstance(scene, dict):
        spec = default.updated(scene, path="scene")
    else:
        raise SpecError(f"scene: must be a Scene, a mapping of changes or a YAML path, got {type(scene).__name__}")
    if physics is not None:
        if isinstance(physics, PhysicsSpec):
            new = physics
        elif isinstance(physics, dict):
            if "fit" in physics:  # a calibration's fit.json: its law, nu and E (spread by its uncertainty)
                from .observations import physics_from_fit

                fitted = physics_from_fit(physics["fit"])
                clash = sorted(set(fitted) & set(physics))
                if clash:
                    raise SpecError(f"physics.{clash[0]}: given by physics.fit as well; give one of them")
                physics = {**{k: v for k, v in physics.items() if k != "fit"}, **fitted}
            new = from_mapping(PhysicsSpec, merge(to_mapping(spec.physics), physics), "physics")
        else:
            raise SpecError(f"physics: must be a mapping of PhysicsSpec fields, got {type(physics).__name__}")
        spec = spec.updated({"physics": to_mapping(new)})
    return spec


@dataclass(frozen=True)
class SceneGeometry:
    """What does not change in an env: ``name``, ``rest_vertices (n, 3)`` m, ``surface_faces
    (f, 3)``, ``edges (e, 2)``, ``fixed`` (attached vertex indices), ``target_radius`` m,
    ``camera`` (eye, m), ``look_at`` (m), ``settings`` (the TaskSettings), ``physics``
    (the PhysicsSpec), ``weight`` (N, the tissue's), ``workspace`` (``(low, high)`` m, the
    gripper's) and ``support_mesh`` (``(vertices, faces)``: the supports as triangles)."""

    name: str
    rest_vertices: np.ndarray
    surface_faces: np.ndarray
    edges: np.ndarray
    fixed: np.ndarray
    target_radius: float
    camera: np.ndarray
    look_at: np.ndarray
    settings: TaskSettings
    physics: PhysicsSpec
    weight: float
    workspace: tuple
    support_mesh: tuple


@dataclass(frozen=True)
class SceneSnapshot:
    """One env now: ``positions (n, 3)`` m, ``gripper (3,)`` m (the first grasper's),
    ``grasping``, ``held`` (vertex indices held by any grasper), ``grasp_force (3,)`` N (of
    the tissue on the first grasper), ``target (3,)`` m (a goal task's goal),
    ``young_modulus`` Pa, ``step``; every grasper's ``grippers (K, 3)`` m, ``closed (K,)``
    and ``grasp_forces (K, 3)`` N, in action order; the vertices still ``stuck`` (adhesion)
    and those ``released`` by a hook this episode (indices); every hook's tip ``hooks (H,
    3)`` m and whether it is ``energised (H,)``."""

    positions: np.ndarray
    gripper: np.ndarray
    grasping: bool
    held: np.ndarray
    grasp_force: np.ndarray
    target: np.ndarray
    young_modulus: float
    step: int
    grippers: np.ndarray
    closed: np.ndarray
    grasp_forces: np.ndarray
    stuck: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    released: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    hooks: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    energised: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


class _SceneAccess:
    """Observation spaces and builders, geometry and snapshots, shared by both envs."""

    task: BatchedRetraction

    @property
    def instruments(self) -> tuple[str, ...]:
        """The instruments in each world: their names (or kinds, for an unnamed one), in action order."""
        return tuple(g.name or g.kind for g in self.task.instruments)

    def _setup_observations(self, obs_mode: str, camera=None):
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
        self.obs_mode = obs_mode
        low, high = self.task.state_bounds()
        state_space = spaces.Box(low, high, dtype=np.float32)
        self.camera_renderer = None
        if obs_mode in IMAGE_MODES:
            spec = camera if isinstance(camera, ImageSpec) else from_mapping(ImageSpec, camera or {}, "camera")
            self.camera_renderer = CameraRenderer(self.task, spec)
            h, w = spec.size
            parts = {}
            if obs_mode in ("rgb", "rgbd"):
                parts["rgb"] = spaces.Box(0, 255, (h, w, 3), dtype=np.uint8)
            if obs_mode in ("depth", "rgbd"):
                parts["depth"] = spaces.Box(0.0, spec.far, (h, w, 1), dtype=np.float32)
            if spec.segmentation:
                parts["segmentation"] = spaces.Box(0, max(SEGMENT_IDS.values()), (h, w, 1), dtype=np.uint8)
            if spec.state:
                parts["state"] = state_space
            return next(iter(parts.values())) if len(parts) == 1 else spaces.Dict(parts)
        if camera is not None:
            raise ValueError(f"camera= is for obs_mode in {IMAGE_MODES}, not {obs_mode!r}")
        if obs_mode == "state":
            return state_space
        scene = self.task.scene
        surface = np.setdiff1d(scene.mesh.surface_vertices, scene.fixed)
        pick = np.linspace(0, len(surface) - 1, POINTCLOUD_SIZE).round().astype(np.int64)
        self._cloud_vertices = surface[pick]
        cloud_space = spaces.Box(-POINT_BOUND, POINT_BOUND, (POINTCLOUD_SIZE, 3), dtype=np.float32)
        return spaces.Dict({"state": state_space, "points": cloud_space})

    def _new_camera_poses(self, envs) -> None:
        """Envs starting an episode draw their camera jitter (from their own generator)."""
        if self.camera_renderer is not None:
            for i in np.atleast_1d(envs):
                self.camera_renderer.new_pose(int(i), self.task.rngs[int(i)])

    def observations(self):
        """The observation of every env of the batch (leading axis N)."""
        if self.camera_renderer is not None:
            rgb, depth, seg = self.camera_renderer.render()
            parts = {}
            if self.obs_mode in ("rgb", "rgbd"):
                parts["rgb"] = rgb.copy()
            if self.obs_mode in ("depth", "rgbd"):
                parts["depth"] = depth.copy()
            if self.camera_renderer.spec.segmentation:
                parts["segmentation"] = seg.copy()
            if self.camera_renderer.spec.state:
                parts["state"] = self.task.state_observation()
            return next(iter(parts.values())) if len(parts) == 1 else parts
        state = self.task.state_observation()
        if self.obs_mode == "state":
            return state
        cloud = np.clip(np.nan_to_num(self.task.x[:, self._cloud_vertices]), -POINT_BOUND, POINT_BOUND)
        return {"state": state, "points": cloud.astype(np.float32)}

    @property
    def scene(self) -> Scene:
        """The scene this env runs (data: save it with ``env.scene.save(path)``)."""
        return self.task.scene.spec

    @property
    def scene_name(self) -> str:
        return self.task.scene.name

    @property
    def geometry(self) -> SceneGeometry:
        s, t = self.task.scene, self.task
        weight = float(t.model.mass.sum() * np.linalg.norm(t.model.gravity))
        return SceneGeometry(s.name, s.mesh.vertices, s.surface_faces, s.mesh.edges, s.fixed, s.target_radius,
                             s.camera, s.look_at, t.settings, s.physics, weight, (s.workspace_low, s.workspace_high),
                             CameraRenderer.support_mesh(s))

    def camera_view(self, i: int = 0, size=(240, 320)) -> dict:
        """Scene ``i`` seen from its task camera at ``size`` ``(height, width)`` pixels, for
        viewers and recordings: ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32 m,
        ``segmentation`` (H, W) uint8, and the camera: ``eye`` (m), ``rotation`` (world to
        camera, rows the camera axes x right, y down, z forward), ``focal`` (pixels)."""
        size = tuple(int(v) for v in size)
        if getattr(self, "_view_renderer", None) is None or self._view_renderer.spec.size != list(size):
            self._view_renderer = CameraRenderer(self.task, ImageSpec(size=list(size), far=10.0))
        view = self._view_renderer
        if self.camera_renderer is not None:  # the observation camera's pose (jitter included)
            view.eyes[:], view.rots[:] = self.camera_renderer.eyes, self.camera_renderer.rots
        rgb, depth, seg = view.render()
        return {"rgb": rgb[i].copy(), "depth": depth[i, :, :, 0].copy(), "segmentation": seg[i, :, :, 0].copy(),
                "eye": view.eyes[i].copy(), "rotation": view.rots[i].copy(), "focal": view.focal}

    def snapshot(self, i: int = 0) -> SceneSnapshot:
        """Scene ``i`` as it is now (copies)."""
        t = self.task
        held = np.any([g.held[i] for g in t.instruments], axis=0)
        return SceneSnapshot(t.x[i].copy(), t.gripper[i].copy(), bool(t.grasping[i]), np.flatnonzero(held),
                             t.grasp_force[i].copy(), t.target[i].copy(), float(t.young_modulus[i]),
                             int(t.steps[i]), t.grippers[i].copy(), t.grasping_all[i].copy(),
                             np.stack([g.force[i] for g in t.instruments]), np.flatnonzero(t.world.stuck[i]),
                             np.flatnonzero(t.released[i]), t.hook_tips[i].copy(), t.hooks_energised[i].copy())


class _Resolving:
    """How an env class turns its keyword arguments into a scene, and checks them."""

    #: The task's default scene: a function of the size arguments (``cells=``, ``mesh_size=``).
    default_scene = None
    #: The batched task the env runs, and its settings' class.
    task_class = BatchedRetraction
    settings_class = TaskSettings
    weights_class = RewardWeights

    @classmethod
    def resolve(cls, scene=None, physics=None, **size) -> Scene:
        """The scene the env runs for these arguments (validated; no mesh is built)."""
        if cls.default_scene is None:
            if not isinstance(scene, (Scene, str, Path)):
                raise SpecError(f"scene: {cls.__name__} needs a Scene (or a scene YAML path), got {scene!r}")
            return resolve_scene(Scene.load(scene) if not isinstance(scene, Scene) else scene, None, physics)
        default = cls.default_scene()
        spec = resolve_scene(default, scene, None)
        changes = scene_kwargs_changes(**size)
        if changes:
            spec = spec.updated(changes)
        return resolve_scene(spec, None, physics)

    @classmethod
    def check_kwargs(cls, settings=None, weights=None, scene=None, physics=None, camera=None, difficulty=1,
                     **size) -> Scene:
        """Validate the data arguments of the constructor (as ``gym.make`` would pass
        them) without building the scene's mesh; returns the resolved scene."""
        settings = as_settings(settings, cls.settings_class, "settings")
        as_settings(weights, cls.weights_class, "weights")
        if camera is not None:
            as_settings(camera, ImageSpec, "camera")
        return apply_difficulty(difficulty, settings, cls.resolve(scene, physics, **size))[1]


class RetractionEnv(_Resolving, _SceneAccess, gym.Env):
    """Base of the single retraction environments (see the task classes' docstrings).

    ``scene``: a :class:`Scene`, a mapping of changes to the task's default scene, or a
    scene YAML path; ``physics``: a mapping of :class:`PhysicsSpec` fields.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(self, obs_mode: str = "state", render_mode: str | None = None,
                 settings: TaskSettings | dict | None = None, weights: RewardWeights | dict | None = None,
                 scene: Scene | dict | str | None = None, physics: dict | None = None, camera: dict | None = None,
                 difficulty: int = 1, **size):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}")
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
        settings, spec = apply_difficulty(difficulty, as_settings(settings, self.settings_class, "settings"),
                                          self.resolve(scene, physics, **size))
        self.difficulty = difficulty
        self.task = self.task_class(build_scene(spec), 1, settings, weights)
        self.action_space = spaces.Box(-1.0, 1.0, (self.task.action_size,), dtype=np.float32)
        self.observation_space = self._setup_observations(obs_mode, camera)
        self.render_mode = render_mode
        self._renderer = None

    def observe(self):
        """The current observation."""
        obs = self.observations()
        return {k: v[0] for k, v in obs.items()} if isinstance(obs, dict) else obs[0]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        # a given seed seeds the episode directly (as env i of a vector env reset with
        # seed - i); without one, the episode continues from the env's generator
        scene_seed = seed if seed is not None else int(self.np_random.integers(2**63 - 1))
        self.task.reset([0], seeds=[scene_seed])
        if options:
            if not isinstance(options, dict):
                raise ValueError(f"options: must be a dict, got {type(options).__name__}")
            unknown = sorted(set(options) - set(self.task.EPISODE_OPTIONS))
            if unknown:
                allowed = ", ".join(f"{k} ({u})" for k, u in self.task.EPISODE_OPTIONS.items())
                raise ValueError(f"options.{unknown[0]}: not a reset option (allowed: {allowed})")
            self.task.set_episode(0, **options)
        self._new_camera_poses([0])
        return self.observe(), self._info_at_reset()

    def _info_at_reset(self) -> dict[str, Any]:
        return {k: v[0].item() for k, v in self.task.start_info([0]).items()}

    def step(self, action):
        a = check_actions(action, (self.task.action_size,))
        reward, terminated, truncated, info = self.task.step(a[None, :])
        info = {k: (v[0].item() if isinstance(v, np.ndarray) else v) for k, v in info.items()}
        if self.render_mode == "human":
            self.render()
        return self.observe(), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode is None:
            return None
        from .render_scene import SceneRenderer

        if self._renderer is None:
            self._renderer = SceneRenderer(self.task, mode=self.render_mode)
        return self._renderer.render(0)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class RetractionVectorEnv(_Resolving, _SceneAccess, VectorEnv):
    """N retraction envs advanced by one batched Numba call (next-step autoreset).

    Arguments as the single env's, plus ``num_envs`` and ``max_episode_steps`` (the
    episode length, ``settings.max_steps``; ``gym.make_vec`` passes the registered 100
    unless given, and a ``settings.max_steps`` that disagrees with it is an error; the
    caller's settings are not modified).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int = 4, obs_mode: str = "state",
                 settings: TaskSettings | dict | None = None, weights: RewardWeights | dict | None = None,
                 max_episode_steps: int | None = None, render_mode: str | None = None,
                 scene: Scene | dict | str | None = None, physics: dict | None = None, camera: dict | None = None,
                 difficulty: int = 1, **size):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
        asked = settings.get("max_steps") if isinstance(settings, dict) else None
        settings = as_settings(settings, self.settings_class, "settings")
        if max_episode_steps is not None:
            if isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer)):
                raise ValueError(f"max_episode_steps must be an integer >= 1, got {max_episode_steps!r}")
            if asked is None and settings.max_steps != self.settings_class.max_steps:
                asked = settings.max_steps
            if asked is not None and asked != max_episode_steps:
                raise ValueError(f"settings.max_steps={asked} disagrees with max_episode_steps={max_episode_steps} "
                                 "(gym.make_vec passes the registered spec's unless given): give "
                                 f"max_episode_steps={asked} instead")
            settings = settings_with(settings, max_steps=int(max_episode_steps))  # a copy: never the caller's
        settings, spec = apply_difficulty(difficulty, settings, self.resolve(scene, physics, **size))
        self.difficulty = difficulty
        self.num_envs = int(num_envs)
        self.task = self.task_class(build_scene(spec), self.num_envs, settings, weights)
        self.single_action_space = spaces.Box(-1.0, 1.0, (self.task.action_size,), dtype=np.float32)
        self.single_observation_space = self._setup_observations(obs_mode, camera)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.render_mode = render_mode
        self._needs_reset = np.zeros(self.num_envs, dtype=bool)
        self._np_random = None

    # ------------------------------------------------ the batch without autoreset
    def reset_envs(self, envs, seeds=None) -> None:
        """Start new episodes in ``envs`` (indices), seeded by ``seeds`` (one each, or None)."""
        idx = np.atleast_1d(np.asarray(envs, dtype=np.int64))
        if idx.size and (idx.min() < 0 or idx.max() >= self.num_envs):
            raise ValueError(f"envs must lie in [0, {self.num_envs}), got {idx.tolist()}")
        if seeds is not None and len(seeds) != len(idx):
            raise ValueError(f"give one seed per env ({len(idx)}), got {len(seeds)}")
        self.task.reset(idx, seeds)
        self._new_camera_poses(idx)

    def step_envs(self, actions, active=None):
        """Step every env with ``actions (N, action size)`` (checked: shape and finite values), no
        autoreset: ``(reward, terminated, truncated, info)`` as per-env arrays."""
        a = check_actions(actions, (self.num_envs, self.task.action_size))
        return self.task.step(a, active=active)

    # --------------------------------------------------------------- gymnasium
    def reset(self, *, seed=None, options=None):
        if seed is None:
            seeds = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        self._np_random = np.random.default_rng(seed if isinstance(seed, (int, np.integer)) else None)
        self.reset_envs(np.arange(self.num_envs), seeds)
        self._needs_reset[:] = False
        return self.observations(), {}

    def step(self, actions):
        finished = self._needs_reset.copy()
        reward, terminated, truncated, info = self.step_envs(actions, active=~finished)
        if finished.any():  # next-step autoreset: these envs start a new episode now
            idx = np.flatnonzero(finished)
            self.task.reset(idx)
            self._new_camera_poses(idx)
            reward[idx] = 0.0
            terminated[idx] = False
            truncated[idx] = False
            for key, values in self.task.start_info(idx).items():  # their info: the new episode's start
                info[key][idx] = values
        self._needs_reset = terminated | truncated
        return self.observations(), reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .render_scene import SceneRenderer

        renderer = SceneRenderer(self.task, mode="rgb_array")
        return [renderer.render(i) for i in range(self.num_envs)]


def scene_kwargs_changes(**sizes) -> dict:
    """Scene changes from the envs' shorthand size arguments (``cells``, ``mesh_size``:
    fields of the scene's ``tissue``)."""
    changes: dict = {}
    for key, value in sizes.items():
        if key not in ("cells", "mesh_size"):
            raise SpecError(f"{key}: unknown argument (the size arguments are cells and mesh_size)")
        if value is not None:
            changes.setdefault("tissue", {})[key] = list(value) if key == "cells" else value
    return changes

