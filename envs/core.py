"""The retraction task on N worlds at once: gripper, grasp, observations, reward.

A :class:`~heml_gym.envs.scene.Scene` describes one scene (tissue mesh, physics,
attachment, target placement, camera, gripper start); :class:`BatchedRetraction` runs N
independent copies of it on one :class:`heml_gym.Model` (one material per world, drawn
per episode) stepped by the scene's solver. The single-environment classes (N = 1) and
the vectorised ones share this code. Units: m, s, N, Pa.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from heml_gym import Model
from heml_gym.mesh import box_regions
from heml_gym.solvers import make_solver

from .geometry import fibonacci_sphere, nearest_triangle_distance, visible_fraction, visible_fraction_batch
from .scene import BuiltScene
from .spec import SpecError, from_mapping
from .strain_gauges import StrainGauges

POSITION_BOUND = 0.5  # m: |positions| in observations are clipped to this
FORCE_BOUND = 20.0  # N
STRAIN_BOUND = 5.0

#: The state observation, entry by entry: (name, low, high, unit). The bounds of the
#: observation space and the clipping of every entry come from this table.
STATE_SPEC = (
    [(f"gripper_{a}", -POSITION_BOUND, POSITION_BOUND, "m") for a in "xyz"]
    + [("grasping", 0.0, 1.0, "-")]
    + [(f"grasp_force_{a}", -FORCE_BOUND, FORCE_BOUND, "N") for a in "xyz"]
    + [(f"target_{a}", -POSITION_BOUND, POSITION_BOUND, "m") for a in "xyz"]
    + [(f"tracked_{i}_{a}", -POSITION_BOUND, POSITION_BOUND, "m") for i in range(4) for a in "xyz"]
    + [("max_strain", 0.0, STRAIN_BOUND, "-"), ("exposure", 0.0, 1.0, "-")]
)
#: Names and order of the state-observation entries (see the env docstrings).
STATE_FIELDS = [name for name, *_ in STATE_SPEC]
STATE_SIZE = len(STATE_FIELDS)
STATE_LOW = np.array([lo for _, lo, _, _ in STATE_SPEC], dtype=np.float32)
STATE_HIGH = np.array([hi for _, _, hi, _ in STATE_SPEC], dtype=np.float32)


def _positive(obj, name, value, allow_zero=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (
        value >= 0 if allow_zero else value > 0)
    if not ok:
        raise SpecError(f"{type(obj).__name__}.{name}: must be a finite number {'>=' if allow_zero else '>'} 0, "
                        f"got {value!r}")


#: Weighted jaws (``gripper.jaw_ends: weighted``) hold a vertex with share ``w`` of its row
#: inside them by a spring of ``HOLD_SPRING_SCALE w / (1 - w)`` times the vertex's diagonal
#: rest stiffness: in series with a tissue of that stiffness, a spring of ``w / (1 - w)``
#: times it holds with ``w`` of it, but the diagonal overstates the stiffness a hold
#: meets (the neighbours give way too); a quarter of it brought the flap's hold force on
#: the default mesh closest to the finest mesh's over jaws of 24-56 mm (one seed, four
#: scales tried; docs/benchmarks/jaw_length_weighted.md measures five seeds).
HOLD_SPRING_SCALE = 0.25

@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (each term is reported in ``info`` under its name);
    every weight a finite number >= 0."""

    exposure: float = 10.0  # times the change of exposure (0..1) this step
    lift: float = 20.0  # times the change of lift progress (0..1) this step (shaping; 5 left PPO stalled short of exposure)
    grasp: float = 0.5  # once per episode, when a grasp first holds tissue
    strain: float = 5.0  # times the strain above the damage threshold
    stretch: float = 5.0  # times the rise of the largest gauge strain this step, as a cost (shaping: fold, don't stretch)
    effort: float = 0.01  # times |gripper velocity command|^2
    success: float = 5.0  # once, on success
    hold: float = 1.0  # per second of simulated time the success condition is held before success (hold_time > 0)

    def __post_init__(self):
        for f in fields(self):
            _positive(self, f.name, getattr(self, f.name), allow_zero=True)


@dataclass(frozen=True)
class TaskSettings:
    """Task constants: control step, gripper, thresholds, episode length. Every value is
    checked: the error names the setting and what it allows."""

    control_dt: float = 0.1  # s simulated per env step, in (0, 10]
    max_speed: float = 0.05  # m/s of the gripper at action 1
    grasp_reach: float = 0.012  # m: closing grasps tissue only if the grasp patch (or a surface vertex) is this close
    jaw_radius: float = 0.005  # m: the jaws hold every surface vertex this close (at least the nearest)
    damage_strain: float = 0.5  # gauge strain above which the strain penalty applies
    #: gauge strain above which info["cost"] counts harm: 0.18, the lower end (mean - 1 SD)
    #: of the ultimate local strain of human liver capsule in uniaxial tension, 0.47 +- 0.29
    #: (Brunon, Bruyere-Garnier and Coret, J Biomech 43(11), 2010, 2221-2227)
    safe_strain: float = 0.18
    tear_strain: float = 1.0  # gauge strain that ends the episode (tissue torn)
    success_exposure: float = 0.8  # fraction of the target visible for success
    hold_time: float = 0.0  # s the success condition must hold, continuously, before success (0: at once)
    release_command: float = -0.5  # grasp command below which closed jaws open (> 0 closes), in [-1, 0]
    max_steps: int = 100  # steps before truncation
    exposure_samples: int = 256  # points on the target sphere for exposure

    def __post_init__(self):
        for name in ("control_dt", "max_speed", "grasp_reach", "jaw_radius", "damage_strain", "tear_strain"):
            _positive(self, name, getattr(self, name))
        if self.control_dt > 10.0:
            raise SpecError(f"TaskSettings.control_dt: must be at most 10 s, got {self.control_dt}")
        s = self.safe_strain
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not (0.0 <= s < math.inf):
            raise SpecError(f"TaskSettings.safe_strain: must be a finite number >= 0, got {s!r}")
        if not self.tear_strain > self.damage_strain:
            raise SpecError(f"TaskSettings.tear_strain: must exceed damage_strain ({self.damage_strain}), "
                            f"got {self.tear_strain}")
        if not (isinstance(self.success_exposure, (int, float)) and 0 < self.success_exposure <= 1):
            raise SpecError(f"TaskSettings.success_exposure: must lie in (0, 1], got {self.success_exposure!r}")
        _positive(self, "hold_time", self.hold_time, allow_zero=True)
        r = self.release_command
        if not (isinstance(r, (int, float)) and not isinstance(r, bool) and -1.0 <= r <= 0.0):
            raise SpecError(f"TaskSettings.release_command: must be a number in [-1, 0], got {r!r}")
        for name in ("max_steps", "exposure_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise SpecError(f"TaskSettings.{name}: must be an integer >= 1, got {value!r}")


def as_settings(value, cls, name: str):
    """``value`` (None, a ``cls`` or a mapping of its fields) as a ``cls``; errors name ``name``."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, dict):
        return from_mapping(cls, value, name)
    raise SpecError(f"{name}: must be a {cls.__name__} or a mapping of its fields, got {type(value).__name__}")


class BatchedRetraction:
    """N independent retraction episodes on one scene."""

    def __init__(self, scene: BuiltScene, n_worlds: int, settings: TaskSettings | None = None,
                 weights: RewardWeights | None = None):
        if not isinstance(scene, BuiltScene):
            raise TypeError(f"scene must be a BuiltScene (heml_gym.envs.scene.build_scene), got {type(scene).__name__}")
        self.scene = scene
        self.n = int(n_worlds)
        self.settings = as_settings(settings, TaskSettings, "settings")
        self.weights = as_settings(weights, RewardWeights, "weights")
        s, ph = scene, scene.physics
        E_low, E_high = ph.young_modulus
        self.model = Model(s.mesh, ph.material_for(E_high), n_worlds=self.n, field=ph.field, density=ph.density,
                           fixed=s.fixed, gravity=ph.gravity, damping=ph.damping, supports=s.supports)
        if ph.stiffness_regions:  # E varies over the tissue: each region's share of the drawn E
            relative = np.asarray(ph.stiffness_regions["relative"], dtype=np.float64)
            self.model.set_stiffness_map(relative[box_regions(s.mesh, ph.stiffness_regions["grid"])])
        dt = self.settings.control_dt
        self.solver = make_solver(self.model, ph.integrator, scheme=ph.scheme, safety=ph.safety,
                                  newton_tol=ph.newton_tol, max_iterations=ph.max_newton,
                                  hessian_scale=ph.hessian_scale if ph.integrator == "quasi_newton" else 1.0)
        if s.spec.gripper.wrist_reach is not None and not self.solver.takes_wrist:
            raise SpecError(f"scene.gripper.wrist_reach: jaws on a free wrist are stepped by the quasi_newton "
                            f"integrator, not {ph.integrator}")
        if s.spec.gripper.jaw_ends == "weighted" and not self.solver.takes_hold_springs:
            raise SpecError(f"scene.gripper.jaw_ends: weighted jaws hold their end vertices by springs, which the "
                            f"{ph.integrator} integrator does not step (use quasi_newton or implicit)")
        if ph.integrator == "explicit":
            # sub-steps fixed by the stiffest tissue the scene can draw: the same in every
            # world and batch, so a world's trajectory does not depend on its neighbours
            self.substeps = self.solver.substeps(dt, self.model.critical_dt(material=ph.material_for(E_high)))
        else:
            self.substeps = max(1, math.ceil(dt / ph.max_dt - 1e-9))
        if self.substeps > 1_000_000:
            raise SpecError(f"settings.control_dt: {dt} s needs {self.substeps} explicit sub-steps per env step; "
                            "use a shorter control_dt or the implicit integrator")
        self.state = self.model.state()
        self.control = self.model.control()
        self.reaction = np.zeros((self.n, s.mesh.n_vertices, 3))
        self._edges = s.mesh.edges
        self.gauges = StrainGauges(s.mesh, s.strain_gauge)
        self._graspable = np.setdiff1d(s.mesh.surface_vertices, s.fixed)
        if s.grasp_patch is not None:  # the patch's surface triangles (or its edges), for its reach
            faces = s.surface_faces[np.isin(s.surface_faces, s.grasp_patch).all(axis=1)]
            if len(faces) == 0:  # a line of vertices: its edges, as degenerate triangles
                e = self._edges[np.isin(self._edges, s.grasp_patch).all(axis=1)]
                faces = np.column_stack([e, e[:, 1]])
            self._patch_faces = faces
            rest = s.mesh.vertices[s.grasp_patch]
            # the patch's long axis (unit): ``gripper.jaw_length`` is measured along it
            self._patch_axis = np.linalg.svd(rest - rest.mean(axis=0))[2][0] if len(rest) > 1 else np.zeros(3)
        self._sphere = fibonacci_sphere(self.settings.exposure_samples)
        self._edge = np.asarray(s.edge_vertices, dtype=np.int64)
        self._rest_angle = self._fold_angles(s.mesh.vertices[None, self._edge])[0]
        n = self.n
        self.gripper = np.zeros((n, 3))
        self.grasping = np.zeros(n, dtype=bool)
        self.held = np.zeros((n, s.mesh.n_vertices), dtype=bool)
        #: each held vertex's share held by the jaws (1: whole; weighted jaws' ends: less)
        self.held_share = np.zeros((n, s.mesh.n_vertices))
        self.adhered = np.zeros((n, s.mesh.n_vertices), dtype=bool)
        self.adhesion_width = np.zeros(n)
        self.offsets = np.zeros((n, s.mesh.n_vertices, 3))
        self.pivot_offset = np.zeros((n, 3))  # a free wrist's pivot from the gripper (m)
        self.target = np.zeros((n, 3))
        self.exposure = np.zeros(n)
        self.lift = np.zeros(n)
        self.max_strain = np.zeros(n)
        self.grasp_force = np.zeros((n, 3))
        self.damage = np.zeros(n)  # strain x s: the episode's summed info["cost"]
        self.young_modulus = np.full(n, E_high)
        self.steps = np.zeros(n, dtype=np.int64)
        self.grasped_once = np.zeros(n, dtype=bool)
        # env steps the success condition has held in a row; success once it has held hold_time
        self.held_steps = np.zeros(n, dtype=np.int64)
        self.steps_to_hold = math.ceil(self.settings.hold_time / self.settings.control_dt - 1e-9)
        self.rngs = [np.random.default_rng() for _ in range(n)]

    @property
    def x(self) -> np.ndarray:
        """Tissue vertex positions of every world, ``(N, n, 3)`` m (the state's)."""
        return self.state.x

    # ------------------------------------------------------------------ reset
    def reset(self, worlds, seeds=None) -> None:
        """Start new episodes in ``worlds`` (indices), reseeding them from ``seeds`` if given."""
        s = self.scene
        rest = s.mesh.vertices
        for k, i in enumerate(np.atleast_1d(worlds)):
            if seeds is not None and seeds[k] is not None:
                self.rngs[i] = np.random.default_rng(seeds[k])
            rng = self.rngs[i]
            self.state.x[i] = rest
            self.state.v[i] = 0.0
            self.control.clear(i)
            self.reaction[i] = 0.0
            E = rng.uniform(*s.physics.young_modulus)
            self.young_modulus[i] = E
            self.model.set_material(i, s.physics.material_for(E))
            self.target[i] = rng.uniform(s.target_low, s.target_high)
            self.gripper[i] = rng.uniform(s.gripper_low, s.gripper_high)
            self.grasping[i] = False
            self.held[i] = False
            self.held_share[i] = 0.0
            self.steps[i] = 0
            self.grasped_once[i] = False
            self.held_steps[i] = 0
            self.grasp_force[i] = 0.0
            self.damage[i] = 0.0
            self.adhered[i] = False
            if s.adhesion_vertices is not None:  # drawn last: the other draws stay as without adhesion
                self._stick(i, rng.uniform(*s.spec.adhesion.width))
        idx = np.atleast_1d(worlds)
        self.solver.forget(idx)  # the same seed gives the same episode, whatever came before
        self.exposure[idx] = self.measure_exposure(idx)
        self.lift[idx] = self._lift(idx)
        self.max_strain[idx] = self.measure_strain(idx)

    #: What :meth:`set_episode` can set, with its unit.
    EPISODE_OPTIONS = {"young_modulus": "Pa", "gripper": "m, (3,)", "adhesion_width": "m"}

    def set_episode(self, i: int, young_modulus: float | None = None, gripper=None,
                    adhesion_width: float | None = None) -> None:
        """Set what :meth:`reset` drew for world ``i``'s episode (before its first step): the
        tissue's ``young_modulus`` (Pa), the ``gripper``'s start (m, inside the workspace)
        and how far out the underside is stuck (``adhesion_width``, m; the scene must have
        adhesion). A replay of a recorded episode (an observation file) starts this way."""
        s = self.scene
        if young_modulus is not None:
            E = float(young_modulus)
            if not (math.isfinite(E) and E > 0):
                raise SpecError(f"young_modulus: must be a positive number of pascals, got {young_modulus!r}")
            self.young_modulus[i] = E
            self.model.set_material(i, s.physics.material_for(E))
        if gripper is not None:
            g = np.asarray(gripper, dtype=np.float64)
            if g.shape != (3,) or not np.all(np.isfinite(g)):
                raise SpecError(f"gripper: must be 3 finite coordinates (m), got {gripper!r}")
            if np.any(g < np.asarray(s.workspace_low) - 1e-12) or np.any(g > np.asarray(s.workspace_high) + 1e-12):
                raise SpecError(f"gripper: {g.tolist()} lies outside the workspace "
                                f"{list(s.workspace_low)}..{list(s.workspace_high)} m")
            self.gripper[i] = g
        if adhesion_width is not None:
            if s.adhesion_vertices is None:
                raise SpecError("adhesion_width: this scene has no adhesion (scene.adhesion is null)")
            w = float(adhesion_width)
            if not (math.isfinite(w) and w >= 0):
                raise SpecError(f"adhesion_width: must be a distance >= 0 (m), got {adhesion_width!r}")
            self.control.detach(i, np.flatnonzero(self.adhered[i]))
            self.adhered[i] = False
            self._stick(i, w)
        self.solver.forget(np.array([i]))
        self.exposure[i] = self.measure_exposure([i])[0]
        self.lift[i] = self._lift([i])[0]
        self.max_strain[i] = self.measure_strain([i])[0]

    def _stick(self, i: int, width: float) -> None:
        """Hold world ``i``'s underside where it rests, out to ``width`` (m) from the attachment."""
        s = self.scene
        self.adhesion_width[i] = width
        stuck = s.adhesion_vertices[s.adhesion_distance <= width + 1e-9]
        self.adhered[i, stuck] = True
        self.control.attach(i, stuck, s.mesh.vertices)

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray, active: np.ndarray | None = None):
        """Apply ``actions`` (N, 4) in [-1, 1] to every world; returns reward, terminated,
        truncated and a dict of per-world arrays (the info).

        Worlds outside the ``active`` mask (default: all) are not simulated (their results
        are meaningless; the vector env resets them right after)."""
        st, w = self.settings, self.weights
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.n, 4), -1.0, 1.0)
        prev_exposure, prev_lift, prev_strain = self.exposure.copy(), self.lift.copy(), self.max_strain.copy()
        grasp_bonus = np.zeros(self.n)
        x = self.state.x
        # grasp / release
        for i in range(self.n):
            close = a[i, 3] > 0.0
            release = a[i, 3] < st.release_command  # between it and 0 the jaws stay as they are
            if close and not self.grasping[i]:
                picked, share = self._jaw_vertices(i)
                wrist = self._wrist(i, picked) if picked.size else None
                if wrist is not None:
                    picked, share = wrist[0], np.ones(len(wrist[0]))
                if picked.size:
                    self.grasping[i] = True
                    self.held[i, picked] = True
                    self.held_share[i, picked] = share
                    self.offsets[i, picked] = x[i, picked] - self.gripper[i]
                    self.control.attach(i, picked, x[i], stiffness=self._hold_springs(i, picked, share))
                    if wrist is not None and wrist[2] is not None:
                        self.control.turn(i, picked, wrist[1], wrist[2])
                        self.pivot_offset[i] = wrist[1] - self.gripper[i]
                    if not self.grasped_once[i]:
                        self.grasped_once[i] = True
                        grasp_bonus[i] = w.grasp
            elif release and self.grasping[i]:
                self.grasping[i] = False
                self.control.detach(i, np.flatnonzero(self.held[i]))  # adhered tissue stays stuck
                self.held[i] = False
                self.held_share[i] = 0.0
        # move the gripper, drive the held tissue
        self.gripper = np.clip(self.gripper + a[:, :3] * st.max_speed * st.control_dt,
                               self.scene.workspace_low, self.scene.workspace_high)
        if self.scene.supports:  # held tissue cannot be pressed below where it rests
            rest_z = self.scene.mesh.vertices[:, 2]
            for i in np.flatnonzero(self.grasping):
                held = self.held[i]
                self.gripper[i, 2] = max(self.gripper[i, 2], (rest_z[held] - self.offsets[i, held, 2]).max())
        for i in np.flatnonzero(self.grasping):
            idx = np.flatnonzero(self.held[i])
            self.control.drive(i, idx, self.gripper[i] + self.offsets[i, idx])
            if self.control.turns[i].any():
                self.control.drive_wrist(i, self.gripper[i] + self.pivot_offset[i])
        stats = self.solver.step(self.state, self.state, self.control, st.control_dt, substeps=self.substeps,
                                 active=active)
        for i in np.flatnonzero(self.grasping & self.control.turns.any(axis=1)):  # the patch has turned
            self.offsets[i, self.held[i]] = self.state.x[i, self.held[i]] - self.gripper[i]
        diverged = stats.diverged
        failed = diverged | ~stats.converged
        self.reaction = stats.reaction
        self.steps += 1
        # measurements
        held_reaction = np.where(self.held[:, :, None], stats.reaction, 0.0).sum(axis=1)
        self.grasp_force = np.where(failed[:, None], 0.0, -held_reaction)  # force the tissue pulls the gripper with
        all_worlds = np.arange(self.n)
        self.exposure = self.measure_exposure(all_worlds)
        self.lift = self._lift(all_worlds)
        self.max_strain = self.measure_strain(all_worlds)
        # reward terms
        terms = {
            "reward_exposure": w.exposure * (self.exposure - prev_exposure),
            "reward_lift": w.lift * (self.lift - prev_lift),
            "reward_grasp": grasp_bonus,
            "reward_strain": -w.strain * np.maximum(0.0, self.max_strain - st.damage_strain),
            "reward_stretch": -w.stretch * (self.max_strain - prev_strain),
            "reward_effort": -w.effort * (a[:, :3] ** 2).sum(axis=1),
        }
        # success: the target exposed with the tissue below damage strain, held for hold_time
        # (the condition first met counts as 0 s; each further step in a row adds control_dt)
        meets = (self.exposure >= st.success_exposure) & (self.max_strain < st.damage_strain) & ~failed
        self.held_steps = np.where(meets, self.held_steps + 1, 0)
        success = meets & (self.held_steps > self.steps_to_hold)
        terms["reward_hold"] = np.where(meets & ~success, w.hold * st.control_dt, 0.0)
        terms["reward_success"] = np.where(success, w.success, 0.0)
        # a failed world earns nothing: every term is zeroed, so they still add up
        if failed.any():
            terms = {k: np.where(failed, 0.0, v) for k, v in terms.items()}
        reward = sum(terms.values())
        torn = (self.max_strain >= st.tear_strain) & ~failed
        terminated = success | torn | failed
        truncated = (self.steps >= st.max_steps) & ~terminated
        # harm (Safety-Gymnasium's convention: a per-step cost beside the reward): the time
        # integral of the gauge strain's excess over the safe strain, strain x s
        cost = np.where(failed, 0.0, st.control_dt * np.maximum(0.0, self.max_strain - st.safe_strain))
        self.damage = self.damage + cost
        info = {
            **terms,
            "cost": cost,
            "damage": self.damage.copy(),
            "exposure": self.exposure.copy(),
            "lift": self.lift.copy(),
            "max_strain": self.max_strain.copy(),
            "grasp_force": np.linalg.norm(self.grasp_force, axis=1),
            "grasping": self.grasping.copy(),
            "is_success": success,
            "hold_time": np.maximum(self.held_steps - 1, 0) * st.control_dt,
            "tissue_torn": torn,
            "simulation_diverged": diverged.copy(),
            "solver_converged": stats.converged.copy(),
            "newton_iterations": stats.newton_iterations.copy(),
            "substep_refinement": stats.refinement.copy(),
            "solver_fallback": stats.fallback.copy(),
            **self._wrist_info(all_worlds),
            **self._episode_info(all_worlds),
        }
        return reward, terminated, truncated, info

    def _episode_info(self, worlds) -> dict:
        """What ``info`` says of the episode itself (drawn at its reset): the tissue's
        ``young_modulus`` (Pa) and, with adhesion, its ``adhesion_width`` (m)."""
        info = {"young_modulus": self.young_modulus[worlds].copy()}
        if self.scene.adhesion_vertices is not None:
            info["adhesion_width"] = self.adhesion_width[worlds].copy()
        return info

    def start_info(self, worlds) -> dict:
        """The ``info`` of ``worlds`` (indices) at the start of their episodes (after
        :meth:`reset`), with the keys and dtypes of :meth:`step`'s: every reward term 0,
        nothing held, succeeded, torn or failed, the solver's counters at rest, and the
        episode's measurements and draws. Single envs return it at reset, vector envs
        for the worlds they start afresh."""
        worlds = np.atleast_1d(np.asarray(worlds, dtype=np.int64))
        k = len(worlds)
        zero, no = np.zeros(k), np.zeros(k, dtype=bool)
        return {**{f"reward_{term.name}": zero.copy() for term in fields(RewardWeights)},
                "exposure": self.exposure[worlds].copy(), "lift": self.lift[worlds].copy(),
                "max_strain": self.max_strain[worlds].copy(), "grasp_force": zero.copy(),
                "cost": zero.copy(), "damage": zero.copy(),
                "grasping": self.grasping[worlds].copy(), "is_success": no.copy(), "hold_time": zero.copy(),
                "tissue_torn": no.copy(), "simulation_diverged": no.copy(), "solver_converged": ~no,
                "newton_iterations": np.zeros(k, dtype=np.int64), "substep_refinement": np.ones(k, dtype=np.int64),
                "solver_fallback": no.copy(), **self._wrist_info(worlds), **self._episode_info(worlds)}

    def _wrist_info(self, worlds) -> dict:
        """``wrist_angle`` (rad): how far the jaws on a free wrist have turned since they
        closed (0 when open), where the scene has them."""
        if self.scene.spec.gripper.wrist_reach is None:
            return {}
        turned = self.control.turns[worlds].any(axis=1)
        return {"wrist_angle": np.where(turned, self.control.wrist_angle[worlds], 0.0)}

    def _jaw_vertices(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The tissue vertices that closing the gripper of world ``i`` holds (maybe none),
        and the share of each that the jaws hold (1: whole; below 1: weighted jaws' ends)."""
        picked, share = self._reached_vertices(i)
        keep = ~self.adhered[i, picked]
        return picked[keep], share[keep]

    def wrist_patch(self, i: int, picked: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray | None]:
        """What jaws on a free wrist hold when they close on ``picked`` (vertex indices) in
        world ``i``: the vertices within ``reach`` (m, at rest) of one of them, not fixed or
        stuck (indices, ascending), and the jaws' axis (unit: the longest direction of
        ``picked`` at rest, else of the patch; None when that is a single vertex, which has
        no angle). The scene's wrist (``scene.gripper.wrist_reach``) and the calibration's
        (:func:`heml_gym.envs.observations.control_log`) both take it."""
        rest = self.scene.mesh.vertices
        near = np.zeros(len(rest), dtype=bool)
        for p in rest[picked]:
            near |= np.linalg.norm(rest - p, axis=1) <= reach
        near[picked] = True
        patch = np.flatnonzero(near & ~self.model.fixed & ~self.adhered[i])
        shape = rest[picked] if len(picked) > 1 else rest[patch]
        if len(shape) < 2:
            return patch, None
        return patch, np.linalg.svd(shape - shape.mean(axis=0), full_matrices=False)[2][0]

    def _wrist(self, i: int, picked: np.ndarray):
        """``(patch, pivot, axis)`` of the scene's free wrist closing on ``picked`` in world
        ``i`` (:meth:`wrist_patch`; the pivot: the patch's middle, m), None without one."""
        reach = self.scene.spec.gripper.wrist_reach
        if reach is None:
            return None
        patch, axis = self.wrist_patch(i, picked, reach)
        return patch, self.state.x[i, patch].mean(axis=0), axis

    def _hold_springs(self, i: int, vertices: np.ndarray, share: np.ndarray) -> np.ndarray:
        """The hold stiffness (N/m) of ``vertices`` of world ``i`` held with ``share``: 0 (exact)
        for a whole share, else ``share / (1 - share)`` times :data:`HOLD_SPRING_SCALE` times
        the tissue's own stiffness at the vertex (the mean diagonal of the world's rest
        stiffness matrix there, N/m)."""
        k = np.zeros(len(vertices))
        part = share < 1.0 - 1e-9
        if part.any():
            X = self.scene.mesh.vertices
            diagonal = self.model.fields[i].hessian(X, project=False).diagonal().reshape(-1, 3).mean(axis=1)
            w = share[part]
            k[part] = HOLD_SPRING_SCALE * diagonal[vertices[part]] * w / (1.0 - w)
        return k

    def _reached_vertices(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        st, patch = self.settings, self.scene.grasp_patch
        x = self.state.x[i]
        if patch is not None:  # within reach of the patch's surface (or of its vertices)
            nearest = min(np.linalg.norm(x[patch] - self.gripper[i], axis=1).min(),
                          nearest_triangle_distance(self.gripper[i], x, self._patch_faces))
            if nearest > st.grasp_reach:
                return patch[:0], np.zeros(0)
            gripper = self.scene.spec.gripper
            if gripper.jaw_length is None:
                return patch, np.ones(len(patch))
            if gripper.jaw_ends == "weighted":
                share = self._jaw_shares(i, gripper.jaw_length)
                return patch[share > 0.0], share[share > 0.0]
            # the part of the patch between the jaws: within jaw_length / 2 of them along
            # the patch's long axis (at least the nearest such vertex)
            along = np.abs((x[patch] - self.gripper[i]) @ self._patch_axis)
            picked = patch[(along <= gripper.jaw_length / 2) | (along == along.min())]
            return picked, np.ones(len(picked))
        d = np.linalg.norm(x[self._graspable] - self.gripper[i], axis=1)
        held = (d <= st.jaw_radius) | (d == d.min())
        picked = self._graspable[held & (d <= st.grasp_reach)]
        return picked, np.ones(len(picked))

    def _jaw_shares(self, i: int, jaw_length: float) -> np.ndarray:
        """Each grasp-patch vertex's share (0..1) inside jaws ``jaw_length`` (m) long centred
        on world ``i``'s gripper: the overlap of its row's span along the patch's axis (from
        midway to the previous row to midway to the next; at the patch's ends, as far out as
        in) with the jaws, over the span. Rows: the vertices' rest places along the axis,
        to 1e-6 m."""
        patch = self.scene.grasp_patch
        rest = self.scene.mesh.vertices[patch] @ self._patch_axis
        rows, row_of = np.unique(np.round(rest, 6), return_inverse=True)
        if len(rows) == 1:
            return np.ones(len(patch))
        mids = 0.5 * (rows[1:] + rows[:-1])
        low = np.concatenate([[2 * rows[0] - mids[0]], mids])
        high = np.concatenate([mids, [2 * rows[-1] - mids[-1]]])
        # the jaws' centre along the axis, in the rest frame: the gripper's offset from the
        # patch's current centre, added to the patch's rest centre
        x = self.state.x[i, patch]
        centre = rest.mean() + (self.gripper[i] - x.mean(axis=0)) @ self._patch_axis
        overlap = np.clip(np.minimum(high, centre + jaw_length / 2) - np.maximum(low, centre - jaw_length / 2), 0.0,
                          None)
        share = (overlap / (high - low))[row_of]
        if not (share > 0).any():  # (jaws between two rows' spans cannot be: the spans tile the axis)
            share[np.argmin(np.abs(rest - centre))] = 1.0
        return share

    # ----------------------------------------------------------- measurements
    def measure_exposure(self, worlds) -> np.ndarray:
        """Fraction of the camera-facing target surface samples the tissue does not hide, in
        each of ``worlds`` (indices), from the current state (the observation's exposure)."""
        worlds = np.atleast_1d(worlds)
        r = self.scene.target_radius
        points = self.target[worlds, None, :] + r * self._sphere[None, :, :]
        x = self.state.x
        # only samples facing the camera count; the rest are hidden by the target itself
        if len(worlds) == 1:  # no thread launch for one world
            return np.array([visible_fraction(points[0], self.scene.camera, x[worlds[0]],
                                              self.scene.surface_faces,
                                              sphere_center=self.target[worlds[0]], sphere_radius=r)])
        return visible_fraction_batch(points, self.scene.camera, x[worlds], self.scene.surface_faces,
                                      sphere_center=self.target[worlds], sphere_radius=r)

    def _fold_angles(self, x_edge: np.ndarray) -> np.ndarray:
        """Angle (rad) of each edge vertex about the hinge, 0 along the free direction,
        increasing as the edge lifts; in (-pi/2, 3 pi/2] so that folding back past
        vertical does not wrap."""
        s = self.scene
        dx = s.fold_direction * (x_edge[..., 0] - s.hinge[0])
        dz = x_edge[..., 2] - s.hinge[1]
        angle = np.arctan2(dz, dx)
        return np.where(angle <= -np.pi / 2, angle + 2 * np.pi, angle)

    def _lift(self, worlds) -> np.ndarray:
        """Lift progress in [0, 1]: mean over the edge vertices of their fold angle from
        rest divided by the scene's ``fold_angle``, each clipped to [0, 1]."""
        x_edge = self.state.x[np.atleast_1d(worlds)[:, None], self._edge]  # (no copy of the whole state first)
        progress = (self._fold_angles(x_edge) - self._rest_angle) / self.scene.fold_angle
        return finite(np.clip(progress, 0.0, 1.0), nan=0.0).mean(axis=1)

    def measure_strain(self, worlds) -> np.ndarray:
        """Largest engineering strain ``|l / L - 1|`` of the tissue's strain gauges, per world."""
        worlds = np.atleast_1d(worlds)
        x = self.state.x if np.array_equal(worlds, np.arange(self.n)) else self.state.x[worlds]
        return finite(self.gauges.max_strain(x), nan=STRAIN_BOUND)

    # ------------------------------------------------------------ observation
    def state_observation(self) -> np.ndarray:
        """The state vector of every world, ``(N, STATE_SIZE)`` float32, clipped to its bounds."""
        tracked = self.state.x[:, self.scene.tracked].reshape(self.n, -1)
        obs = np.concatenate([self.gripper, self.grasping[:, None].astype(np.float64), self.grasp_force,
                              self.target, tracked, self.max_strain[:, None], self.exposure[:, None]], axis=1)
        obs = np.clip(finite(obs, nan=0.0), STATE_LOW, STATE_HIGH)
        return obs.astype(np.float32)

    @staticmethod
    def state_bounds() -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the state observation (from :data:`STATE_SPEC`)."""
        return STATE_LOW.copy(), STATE_HIGH.copy()


def finite(values: np.ndarray, nan: float) -> np.ndarray:
    """``np.nan_to_num(values, nan=nan)`` (infinities to the largest finite floats); the
    array itself, without a copy, when every value is finite already (the usual case)."""
    if np.isfinite(values).all():
        return values
    return np.nan_to_num(values, nan=nan)


def settings_with(settings: TaskSettings, **changes) -> TaskSettings:
    """A copy of ``settings`` with ``changes`` (the caller's object is never modified)."""
    return replace(settings, **changes)
