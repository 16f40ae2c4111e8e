"""PushRetraction-v0: lift a liver lobe with a blunt paddle, without a grasp, to expose what lies beneath it.

## Description

OrganRetraction's liver lobe (145 x 100 x 44 mm, thin towards -x, attached along the
bottom edge of its base at x = 65 mm) lies free on the organs below (a rigid,
frictionless plane at z = 0). Beneath its base third lies a structure to expose (a
sphere of radius 8 mm), hidden from the laparoscope in front of and above the thin edge.
There is no grasper. A paddle retractor (a rigid blade, 40 x 80 x 4 mm) starts level on
the floor in front of the thin edge; the agent slides it under the lobe and lifts, until
the target shows, and holds it there without over-straining the tissue or pressing too
hard on it. Surgeons retract the liver this way with a fan or paddle retractor.
Neo-Hookean HEML tissue (E drawn in 4-8 kPa, nu = 0.45, 1060 kg/m^3) under gravity,
stepped as OrganRetraction (backward Euler, 0.05 s steps, L-BFGS); the paddle is a rigid
tool of the world (:mod:`heml_gym.tools`: frictionless penalty contact on the tissue's
vertices). Mesh: a uniform 10 mm lobe (2,017 tets): no jaws need refining.

## Action Space

``Box(-1, 1, (4,), float32)``: the paddle's velocity along x, y, z in units of its
``max_speed`` (30 mm/s: below what passes the 4 mm blade through tissue in a 0.05 s
solver step) and its tilt rate about y in units of 0.5 rad/s (at most 0.6 rad from level;
positive tilts the blade's normal towards +x). The blade's centre stays in x -130..60 mm,
y -60..60 mm, z -2.5..100 mm (at -2.5 mm its top face is just below the floor's surface).

## Observation Space

``obs_mode="state"``: ``Box(24,)`` float32, clipped to its bounds:

| index | meaning | min | max | unit |
|---|---|---|---|---|
| 0-2 | the paddle's centre | -0.5 | 0.5 | m |
| 3 | its tilt | -pi | pi | rad |
| 4-6 | its push on the tissue (mean over the step) | -20 | 20 | N |
| 7-9 | target position | -0.5 | 0.5 | m |
| 10-21 | four tracked tissue points (thin-edge corners and middle, top centre) | -0.5 | 0.5 | m |
| 22 | largest gauge strain of the tissue (over 15 mm) | 0 | 5 | - |
| 23 | exposure of the target | 0 | 1 | - |

``obs_mode="pointcloud"``, ``"rgb"``, ``"depth"``, ``"rgbd"`` as for OrganRetraction (the
camera draws the paddle's blade; exposure counts what the tissue hides, not the blade).

## Rewards, Episode End, Harm

OrganRetraction's terms and thresholds (exposure, lift, strain, stretch, effort, hold,
success; no grasp bonus), and ``reward_pressure``: minus ``weights.pressure`` (5) times
the contact pressure's excess over the safe pressure, relative to it. **Harm**
(``info["cost"]``, per step): the gauge strain's excess over the safe strain (0.18)
times ``control_dt``, plus the contact pressure's relative excess over
``settings.safe_pressure`` times ``control_dt``. The safe pressure is 4.3 kPa (32 mmHg),
the capillary closing pressure (Landis, Heart 15, 1930, 209-228): above it the tissue
under the blade is starved of blood. ``info["pressure_cost"]`` and ``info["strain_cost"]``
are its two parts. The contact pressure (``info["paddle_contact_pressure"]``, Pa) is the
blade's push over the area of tissue it touches (a mean over the contact: on the mesh's
vertices, the blade's edges are resolved only to the cells, so a peak would not converge).
Success: exposure >= 0.8 with the gauge strain below 0.5, held for 2 s (difficulty 1).

## Starting State

Tissue at rest, free on its support (no adhesion); target centre uniform in x 30..45 mm,
y -20..20 mm, 23 mm below the lobe's flat face (as OrganRetraction's); the paddle's centre
uniform in x -115..-105 mm, y -10..10 mm, at z -2.5 mm, level; E uniform in 4-8 kPa.
``reset(options={"young_modulus": E, "gripper": [x, y, z]})`` sets E and the paddle's start.

## Arguments

As OrganRetraction's (``obs_mode``, ``camera``, ``render_mode``, ``settings`` (a
:class:`PushSettings`: TaskSettings and ``safe_pressure``), ``weights`` (a
:class:`PushWeights`: RewardWeights and ``pressure``), ``mesh_size``, ``scene``
(``configs/scenes/push_retraction.yaml``), ``physics``, ``difficulty``).
``scene={"paddles": {"paddle": {"half_extents": [0.02, 0.03, 0.002]}}}`` changes the blade.

## Scripted expert

Slides the blade in under the lobe to x = -35 mm at floor level, lifts it at 30 mm/s
until the target is exposed (0.85), and holds it there
(:class:`heml_gym.envs.scripted.PushPolicy`; ``heml-gym eval scripted --env
heml_gym/PushRetraction-v0``).

## Version History

v0 (2026-11-28): the task described here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields

import numpy as np

from .core import BatchedRetraction, RewardWeights, TaskSettings, as_settings
from .organ_retraction import DEFAULT_MESH_SIZE, organ_scene
from .retraction_env import RetractionEnv, RetractionVectorEnv
from .scene import GripperSpec, PaddleSpec, Scene
from .spec import SpecError

#: Pa: the capillary closing pressure, 32 mmHg (Landis, Heart 15, 1930, 209-228)
SAFE_PRESSURE = 32 * 133.322
#: the blade's contact penalty in units of the tissue's stiffness: 10 (not the solvers' 100) takes a
#: sixth of the solver iterations along the scripted lift, its push within 7 % of 100's
TOOL_STIFFNESS = 10.0
PADDLE = PaddleSpec(start_low=(-0.115, -0.01, -0.0025), start_high=(-0.105, 0.01, -0.0025),
                    workspace_low=(-0.13, -0.06, -0.0025), workspace_high=(0.06, 0.06, 0.10),
                    half_extents=(0.02, 0.04, 0.002))


@dataclass(frozen=True)
class PushSettings(TaskSettings):
    """TaskSettings and ``safe_pressure`` (Pa): the contact pressure above which the
    paddle harms the tissue (default: 32 mmHg, the capillary closing pressure)."""

    safe_pressure: float = SAFE_PRESSURE

    def __post_init__(self):
        super().__post_init__()
        p = self.safe_pressure
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not (math.isfinite(p) and p > 0):
            raise SpecError(f"PushSettings.safe_pressure: must be a positive number of pascals, got {p!r}")


@dataclass(frozen=True)
class PushWeights(RewardWeights):
    """RewardWeights and ``pressure``: times the contact pressure's excess over the
    safe pressure, relative to it, as a penalty each step."""

    pressure: float = 5.0


class BatchedPushRetraction(BatchedRetraction):
    """N push-retraction episodes: the retraction task with a paddle, whose contact
    pressure above ``settings.safe_pressure`` is harm and a penalty."""

    def __init__(self, scene, n_worlds, settings=None, weights=None, grippers=None):
        super().__init__(scene, n_worlds, as_settings(settings, PushSettings, "settings"), None, grippers)
        self.weights = as_settings(weights, PushWeights, "weights")
        self.paddles = [g for g in self.instruments if g.kind == "paddle"]
        if not self.paddles:
            raise SpecError("scene.paddles: PushRetraction needs at least one paddle")

    def _pressure_excess(self) -> np.ndarray:
        """The contact pressure's relative excess over the safe pressure, per world (the largest over paddles)."""
        pressure = np.max([p.pressure for p in self.paddles], axis=0)
        return np.maximum(0.0, pressure / self.settings.safe_pressure - 1.0)

    def step(self, actions, active=None):
        reward, terminated, truncated, info = super().step(actions, active)
        failed = info["simulation_diverged"] | ~info["solver_converged"]
        excess = np.where(failed, 0.0, self._pressure_excess())
        pressure_cost = self.settings.control_dt * excess
        term = -self.weights.pressure * excess
        self.damage = self.damage + pressure_cost
        info.update(reward_pressure=term, strain_cost=info["cost"], pressure_cost=pressure_cost,
                    cost=info["cost"] + pressure_cost, damage=self.damage.copy())
        return reward + term, terminated, truncated, info

    def start_info(self, worlds) -> dict:
        info = super().start_info(worlds)
        zero = np.zeros(len(np.atleast_1d(worlds)))
        info.update({f"reward_{f.name}": zero.copy() for f in fields(PushWeights)},
                    strain_cost=zero.copy(), pressure_cost=zero.copy())
        return info


def push_scene(mesh_size: float = DEFAULT_MESH_SIZE) -> Scene:
    """The free liver lobe (uniform ``mesh_size`` m) with one paddle and no grasper."""
    lobe = organ_scene(mesh_size, jaw_size=None)
    frame = GripperSpec(start_low=PADDLE.start_low, start_high=PADDLE.start_high,
                        workspace_low=PADDLE.workspace_low, workspace_high=PADDLE.workspace_high)
    physics = dataclasses.replace(lobe.physics, tool_stiffness=TOOL_STIFFNESS)
    return dataclasses.replace(lobe, name="PushRetraction", adhesion=None, grasp=None, gripper=frame, graspers={},
                               paddles={"paddle": PADDLE}, physics=physics)


class PushRetractionEnv(RetractionEnv):
    __doc__ = __doc__
    default_scene = staticmethod(push_scene)
    task_class = BatchedPushRetraction
    settings_class = PushSettings
    weights_class = PushWeights

    def __init__(self, obs_mode="state", render_mode=None, settings=None, weights=None, mesh_size=None,
                 scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(obs_mode, render_mode, settings, weights, scene=scene, physics=physics, camera=camera,
                         difficulty=difficulty, mesh_size=mesh_size)


class PushRetractionVectorEnv(RetractionVectorEnv):
    """``num_envs`` PushRetraction scenes in one batched Numba call (see PushRetractionEnv)."""

    default_scene = staticmethod(push_scene)
    task_class = BatchedPushRetraction
    settings_class = PushSettings
    weights_class = PushWeights

    def __init__(self, num_envs=4, obs_mode="state", settings=None, weights=None, max_episode_steps=None,
                 render_mode=None, mesh_size=None, scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(num_envs, obs_mode, settings, weights, max_episode_steps, render_mode, scene=scene,
                         physics=physics, camera=camera, difficulty=difficulty, mesh_size=mesh_size)
