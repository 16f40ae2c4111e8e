"""The retraction task on N scenes at once: gripper, grasp, observations, reward.

A :class:`RetractionScene` describes one scene family (tissue mesh, attachment, target
placement, camera, gripper start); :class:`BatchedRetraction` runs N independent copies
of it on one :class:`heml_gym.batch.BatchedSimulation`. The single-environment classes
(N = 1) and the vectorised ones share this code. Units: m, s, N, Pa.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from heml_gym.batch import BatchedSimulation
from heml_gym.mesh import TetMesh

from .geometry import fibonacci_sphere, nearest_triangle_distance, visible_fraction, visible_fraction_batch
from .strain_gauges import StrainGauges

#: Names and order of the state-observation entries (see the env docstrings).
STATE_FIELDS = (
    ["gripper_x", "gripper_y", "gripper_z", "grasping"]
    + ["grasp_force_x", "grasp_force_y", "grasp_force_z"]
    + ["target_x", "target_y", "target_z"]
    + [f"tracked_{i}_{a}" for i in range(4) for a in "xyz"]
    + ["max_strain", "exposure"]
)
STATE_SIZE = len(STATE_FIELDS)
POSITION_BOUND = 0.5  # m: |positions| in observations are clipped to this
FORCE_BOUND = 20.0  # N
STRAIN_BOUND = 5.0


@dataclass
class RewardWeights:
    """Weights of the reward terms (each term is reported in ``info`` under its name)."""

    exposure: float = 10.0  # times the change of exposure (0..1) this step
    lift: float = 5.0  # times the change of lift progress (0..1) this step (shaping)
    grasp: float = 0.5  # once per episode, when a grasp first holds tissue
    strain: float = 5.0  # times the strain above the damage threshold
    effort: float = 0.01  # times |gripper velocity command|^2
    success: float = 5.0  # once, on success


@dataclass
class RetractionScene:
    """One scene family of the retraction task.

    ``mesh``: tissue at rest (m); ``fixed``: its attached vertices; ``tracked``: 4 vertex
    indices reported in the observation; ``camera``: eye position (m), looking at the
    scene; ``target_low``/``target_high``: box the target centre is drawn from (m);
    ``target_radius`` (m); ``gripper_low``/``gripper_high``: box of gripper start
    positions (m); ``workspace_low``/``workspace_high``: the gripper is kept inside;
    ``stiffness_range``: E (Pa) drawn per episode; ``poisson``, ``density`` (kg/m^3),
    ``gravity`` (m/s^2), ``damping`` (1/s); ``floor``: height (m) of the rigid plane the
    tissue rests on (the organ under it), or None.

    Retraction folds the tissue about a hinge line parallel to y through ``(x, z) =
    hinge`` (m): ``fold_direction`` is +1 when the free tissue extends from the hinge
    towards +x, -1 towards -x. ``edge_vertices`` are the free-edge vertices whose fold
    angle about the hinge (rad, from rest, positive lifting the edge up) measures the lift
    progress ``mean(clip(angle / fold_angle, 0, 1))``, a dense shaping signal.

    ``grasp_patch``: the vertices the jaws hold, a fixed piece of tissue (the same
    material on every mesh of the scene, so that the grasp force converges with the
    mesh): closing within ``grasp_reach`` of the patch (its surface triangles, or the mesh
    edges along it for a line, or its vertices) holds all of them. None: the jaws hold
    the nearest surface vertex and every other within ``jaw_radius``.

    ``strain_gauge``: the gauge length (m) that tissue strain is measured over (see
    :mod:`heml_gym.envs.strain_gauges`): the largest strain reported, penalised and
    checked for tearing is that of segments this long between material points, not
    that of the mesh's edges, so that it has a fine-mesh limit. ``safety``: the explicit
    sub-step as a fraction of the critical step, unless the task settings give one.
    """

    name: str
    mesh: TetMesh
    fixed: np.ndarray
    tracked: np.ndarray
    camera: np.ndarray
    target_low: np.ndarray
    target_high: np.ndarray
    target_radius: float
    gripper_low: np.ndarray
    gripper_high: np.ndarray
    workspace_low: np.ndarray
    workspace_high: np.ndarray
    stiffness_range: tuple[float, float] = (2e3, 5e3)
    poisson: float = 0.45
    density: float = 950.0
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    damping: float = 5.0
    floor: float | None = None
    hinge: tuple[float, float] = (0.0, 0.0)
    fold_direction: float = 1.0
    fold_angle: float = np.pi / 2
    edge_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    grasp_patch: np.ndarray | None = None
    strain_gauge: float = 0.015
    safety: float = 0.5
    surface_faces: np.ndarray = field(init=False)

    def __post_init__(self):
        self.surface_faces = self.mesh.boundary_faces
        if self.grasp_patch is not None:
            patch = np.setdiff1d(np.asarray(self.grasp_patch, dtype=np.int64), self.fixed)
            if patch.size == 0:
                raise ValueError(f"scene {self.name!r}: grasp_patch holds no free vertex")
            self.grasp_patch = patch


@dataclass
class TaskSettings:
    """Task constants: control step, gripper, thresholds, episode length."""

    control_dt: float = 0.1  # s simulated per env step
    max_speed: float = 0.05  # m/s of the gripper at action 1
    grasp_reach: float = 0.012  # m: closing grasps tissue only if the grasp patch (or a surface vertex) is this close
    jaw_radius: float = 0.005  # m: the jaws hold every surface vertex this close (at least the nearest)
    damage_strain: float = 0.5  # gauge strain above which the strain penalty applies
    tear_strain: float = 1.0  # gauge strain that ends the episode (tissue torn)
    success_exposure: float = 0.8  # fraction of the target visible for success
    max_steps: int = 100  # steps before truncation
    exposure_samples: int = 256  # points on the target sphere for exposure
    safety: float | None = None  # explicit sub-step safety factor; None: the scene's


class BatchedRetraction:
    """N independent retraction episodes on one scene family."""

    def __init__(self, scene: RetractionScene, n_scenes: int, settings: TaskSettings | None = None,
                 weights: RewardWeights | None = None):
        self.scene = scene
        self.n = int(n_scenes)
        self.settings = settings or TaskSettings()
        self.weights = weights or RewardWeights()
        s = scene
        self.safety = s.safety if self.settings.safety is None else float(self.settings.safety)
        self.sim = BatchedSimulation(s.mesh, self.n, young_modulus=s.stiffness_range[1],
                                     poisson=s.poisson, density=s.density, gravity=s.gravity,
                                     fixed=s.fixed, damping=s.damping, safety=self.safety,
                                     floor=s.floor)
        # sub-steps fixed by the stiffest tissue the scene can draw: the same in every
        # scene and batch, so a scene's trajectory does not depend on its neighbours
        self.substeps = max(1, int(np.ceil(self.settings.control_dt / (
            self.safety * self.sim.critical_dt(s.stiffness_range[1])))))
        self._edges = s.mesh.edges
        self.gauges = StrainGauges(s.mesh, s.strain_gauge)
        surface = np.setdiff1d(s.mesh.surface_vertices, np.flatnonzero(self.sim.fixed))
        self._graspable = surface
        if s.grasp_patch is not None:  # the patch's surface triangles (or its edges), for its reach
            faces = s.surface_faces[np.isin(s.surface_faces, s.grasp_patch).all(axis=1)]
            if len(faces) == 0:  # a line of vertices: its edges, as degenerate triangles
                e = self._edges[np.isin(self._edges, s.grasp_patch).all(axis=1)]
                faces = np.column_stack([e, e[:, 1]])
            self._patch_faces = faces
        self._sphere = fibonacci_sphere(self.settings.exposure_samples)
        self._edge = np.asarray(s.edge_vertices, dtype=np.int64)
        if self._edge.size == 0:
            raise ValueError(f"scene {s.name!r} has no edge_vertices to measure the lift by")
        self._rest_angle = self._fold_angles(s.mesh.vertices[None, self._edge])[0]
        n = self.n
        self.gripper = np.zeros((n, 3))
        self.grasping = np.zeros(n, dtype=bool)
        self.held = np.zeros((n, s.mesh.n_vertices), dtype=bool)
        self.offsets = np.zeros((n, s.mesh.n_vertices, 3))
        self.target = np.zeros((n, 3))
        self.exposure = np.zeros(n)
        self.lift = np.zeros(n)
        self.max_strain = np.zeros(n)
        self.grasp_force = np.zeros((n, 3))
        self.steps = np.zeros(n, dtype=np.int64)
        self.grasped_once = np.zeros(n, dtype=bool)
        self.rngs = [np.random.default_rng() for _ in range(n)]

    # ------------------------------------------------------------------ reset
    def reset(self, scenes, seeds=None) -> None:
        """Start new episodes in ``scenes`` (indices), reseeding them from ``seeds`` if given."""
        s = self.scene
        for k, i in enumerate(np.atleast_1d(scenes)):
            if seeds is not None and seeds[k] is not None:
                self.rngs[i] = np.random.default_rng(seeds[k])
            rng = self.rngs[i]
            self.sim.reset_scene(i)
            self.sim.set_young_modulus(rng.uniform(*s.stiffness_range), scenes=[i])
            self.target[i] = rng.uniform(s.target_low, s.target_high)
            self.gripper[i] = rng.uniform(s.gripper_low, s.gripper_high)
            self.grasping[i] = False
            self.held[i] = False
            self.steps[i] = 0
            self.grasped_once[i] = False
            self.grasp_force[i] = 0.0
        idx = np.atleast_1d(scenes)
        self.exposure[idx] = self._exposure(idx)
        self.lift[idx] = self._lift(idx)
        self.max_strain[idx] = self._max_strain(idx)

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray, active: np.ndarray | None = None):
        """Apply ``actions`` (N, 4) in [-1, 1] to every scene; returns reward, terminated,
        truncated and a dict of per-scene arrays (the info).

        Scenes outside the ``active`` mask (default: all) are not simulated (their results
        are meaningless; the vector env resets them right after)."""
        st, w = self.settings, self.weights
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.n, 4), -1.0, 1.0)
        prev_exposure, prev_lift = self.exposure.copy(), self.lift.copy()
        grasp_bonus = np.zeros(self.n)
        # grasp / release
        for i in range(self.n):
            close = a[i, 3] > 0.0
            if close and not self.grasping[i]:
                picked = self._jaw_vertices(i)
                if picked.size:
                    self.grasping[i] = True
                    self.held[i, picked] = True
                    self.offsets[i, picked] = self.sim.x[i, picked] - self.gripper[i]
                    self.sim.attach(i, picked)
                    if not self.grasped_once[i]:
                        self.grasped_once[i] = True
                        grasp_bonus[i] = w.grasp
            elif not close and self.grasping[i]:
                self.grasping[i] = False
                self.held[i] = False
                self.sim.detach(i)
        # move the gripper, drive the held tissue
        self.gripper = np.clip(self.gripper + a[:, :3] * st.max_speed * st.control_dt,
                               self.scene.workspace_low, self.scene.workspace_high)
        if self.scene.floor is not None:  # held tissue cannot be pressed below where it rests
            rest_z = self.scene.mesh.vertices[:, 2]
            for i in np.flatnonzero(self.grasping):
                held = self.held[i]
                self.gripper[i, 2] = max(self.gripper[i, 2], (rest_z[held] - self.offsets[i, held, 2]).max())
        for i in np.flatnonzero(self.grasping):
            idx = np.flatnonzero(self.held[i])
            self.sim.drive(i, idx, self.gripper[i] + self.offsets[i, idx])
        diverged = self.sim.step(st.control_dt, active=active, substeps=self.substeps)
        self.steps += 1
        # measurements
        held_reaction = np.where(self.held[:, :, None], self.sim.reaction, 0.0).sum(axis=1)
        self.grasp_force = -held_reaction  # force the tissue pulls the gripper with
        all_scenes = np.arange(self.n)
        self.exposure = self._exposure(all_scenes)
        self.lift = self._lift(all_scenes)
        self.max_strain = self._max_strain(all_scenes)
        # reward terms
        terms = {
            "reward_exposure": w.exposure * (self.exposure - prev_exposure),
            "reward_lift": w.lift * (self.lift - prev_lift),
            "reward_grasp": grasp_bonus,
            "reward_strain": -w.strain * np.maximum(0.0, self.max_strain - st.damage_strain),
            "reward_effort": -w.effort * (a[:, :3] ** 2).sum(axis=1),
        }
        success = (self.exposure >= st.success_exposure) & (self.max_strain < st.damage_strain) & ~diverged
        terms["reward_success"] = np.where(success, w.success, 0.0)
        # a diverged scene earns nothing: every term is zeroed, so they still add up
        terms = {k: np.where(diverged, 0.0, v) for k, v in terms.items()}
        reward = sum(terms.values())
        torn = (self.max_strain >= st.tear_strain) & ~diverged
        terminated = success | torn | diverged
        truncated = (self.steps >= st.max_steps) & ~terminated
        info = {
            **terms,
            "exposure": self.exposure.copy(),
            "lift": self.lift.copy(),
            "max_strain": self.max_strain.copy(),
            "grasp_force": np.linalg.norm(self.grasp_force, axis=1),
            "grasping": self.grasping.copy(),
            "is_success": success,
            "tissue_torn": torn,
            "simulation_diverged": diverged,
        }
        return reward, terminated, truncated, info

    def _jaw_vertices(self, i: int) -> np.ndarray:
        """The tissue vertices that closing the gripper of scene ``i`` holds (maybe none)."""
        st, patch = self.settings, self.scene.grasp_patch
        if patch is not None:  # within reach of the patch's surface (or of its vertices)
            x = self.sim.x[i]
            nearest = min(np.linalg.norm(x[patch] - self.gripper[i], axis=1).min(),
                          nearest_triangle_distance(self.gripper[i], x, self._patch_faces))
            return patch if nearest <= st.grasp_reach else patch[:0]
        d = np.linalg.norm(self.sim.x[i, self._graspable] - self.gripper[i], axis=1)
        held = (d <= st.jaw_radius) | (d == d.min())
        return self._graspable[held & (d <= st.grasp_reach)]

    # ----------------------------------------------------------- measurements
    def _exposure(self, scenes) -> np.ndarray:
        """Fraction of the camera-facing target surface samples the tissue does not hide."""
        scenes = np.atleast_1d(scenes)
        r = self.scene.target_radius
        points = self.target[scenes, None, :] + r * self._sphere[None, :, :]
        # only samples facing the camera count; the rest are hidden by the target itself
        if len(scenes) == 1:  # no thread launch for one scene
            return np.array([visible_fraction(points[0], self.scene.camera, self.sim.x[scenes[0]],
                                              self.scene.surface_faces,
                                              sphere_center=self.target[scenes[0]], sphere_radius=r)])
        return visible_fraction_batch(points, self.scene.camera, self.sim.x[scenes],
                                      self.scene.surface_faces,
                                      sphere_center=self.target[scenes], sphere_radius=r)

    def _fold_angles(self, x_edge: np.ndarray) -> np.ndarray:
        """Angle (rad) of each edge vertex about the hinge, 0 along the free direction,
        increasing as the edge lifts; in (-pi/2, 3 pi/2] so that folding back past
        vertical does not wrap."""
        s = self.scene
        dx = s.fold_direction * (x_edge[..., 0] - s.hinge[0])
        dz = x_edge[..., 2] - s.hinge[1]
        angle = np.arctan2(dz, dx)
        return np.where(angle <= -np.pi / 2, angle + 2 * np.pi, angle)

    def _lift(self, scenes) -> np.ndarray:
        """Lift progress in [0, 1]: mean over the edge vertices of their fold angle from
        rest divided by the scene's ``fold_angle``, each clipped to [0, 1]."""
        x_edge = self.sim.x[np.atleast_1d(scenes)][:, self._edge]
        progress = (self._fold_angles(x_edge) - self._rest_angle) / self.scene.fold_angle
        return np.nan_to_num(np.clip(progress, 0.0, 1.0)).mean(axis=1)

    def _max_strain(self, scenes) -> np.ndarray:
        """Largest engineering strain ``|l / L - 1|`` of the tissue's strain gauges, per scene."""
        return self.gauges.max_strain(self.sim.x[np.atleast_1d(scenes)])

    # ------------------------------------------------------------ observation
    def state_observation(self) -> np.ndarray:
        """The state vector of every scene, ``(N, STATE_SIZE)`` float32, clipped to its bounds."""
        tracked = self.sim.x[:, self.scene.tracked].reshape(self.n, -1)
        obs = np.concatenate([
            np.clip(self.gripper, -POSITION_BOUND, POSITION_BOUND),
            self.grasping[:, None].astype(np.float64),
            np.clip(self.grasp_force, -FORCE_BOUND, FORCE_BOUND),
            np.clip(self.target, -POSITION_BOUND, POSITION_BOUND),
            np.clip(tracked, -POSITION_BOUND, POSITION_BOUND),
            np.clip(self.max_strain, 0.0, STRAIN_BOUND)[:, None],
            np.clip(self.exposure, 0.0, 1.0)[:, None],
        ], axis=1)
        return np.nan_to_num(obs, nan=0.0).astype(np.float32)

    @staticmethod
    def state_bounds() -> tuple[np.ndarray, np.ndarray]:
        low = np.array([-POSITION_BOUND] * 3 + [0.0] + [-FORCE_BOUND] * 3 + [-POSITION_BOUND] * 15
                       + [0.0, 0.0], dtype=np.float32)
        high = np.array([POSITION_BOUND] * 3 + [1.0] + [FORCE_BOUND] * 3 + [POSITION_BOUND] * 15
                        + [STRAIN_BOUND, 1.0], dtype=np.float32)
        return low, high
