"""GallbladderDissection-v0: free a gallbladder's neck from its bed with a hook, to the critical view of safety.

## Description

A gallbladder (a pear-shaped sac 85 x 32 x 23 mm, meshed with gmsh,
:func:`heml_gym.organs.gallbladder_mesh`) lies in its bed on the liver (a rigid,
frictionless plane at z = 0), its neck at x = 0 held along the bottom edge of its end
(where the cystic duct leaves it: the sac turns about that line). The lower third of its underside, from the neck 20-28 mm towards the fundus (drawn per
episode), is stuck to the bed. Two ducts enter the sac beneath its neck: the cystic duct
analogue (the target, a sphere of radius 4 mm) and the cystic artery analogue (the same
sphere 4 mm further out and 9 mm to its side). The common bile duct runs beneath, across
the neck's end (a cylinder of radius 3 mm at x = -10 mm): a **critical structure**.
A grasper holds the fundus (20 mm weighted jaws on its top) and retracts; an
electrosurgical hook releases the attachment where its tip touches while energised (30 W,
within 6 mm, its L-shaped end; a stuck vertex is freed once it has taken 2.6e5 J/m^2 times its share of
the surface: vaporising a 0.1 mm water-like layer, the loose areolar plane between sac
and bed, which the hook cuts rather than ablates).

Success is modelled on cholecystectomy's **critical view of safety** (Strasberg, Hertl and
Soper, J Am Coll Surg 180(1), 1995, 101-125): the lower third of the sac freed from its
bed (80 % of its stuck area released) and both ducts exposed to the laparoscope (each at
least 0.8, the exposure measure the retraction tasks have), with the tissue below damage
strain, held for 2 s (difficulty 1).

Neo-Hookean HEML tissue (E drawn in 4-8 kPa, an assumption for a distended sac, not
calibrated; nu = 0.45; 1030 kg/m^3) under gravity, stepped as OrganRetraction (backward
Euler, 0.05 s steps, L-BFGS). Mesh: 5 mm elements (1,863 tets).

## Action Space

``Box(-1, 1, (8,), float32)``: the grasper's 4 entries (velocity along x, y, z in units
of 0.05 m/s and a grasp command, as TissueRetraction's), then the hook's (velocity along
x, y, z in the same units and an energy command: above 0 energised).

## Observation Space

``obs_mode="state"``: ``Box(29,)`` float32, clipped to its bounds:

| index | meaning | min | max | unit |
|---|---|---|---|---|
| 0-6 | grasper: position, grasping, grasp force | | | m, -, N |
| 7-9 | cystic duct (target) position | -0.5 | 0.5 | m |
| 10-21 | four tracked points (fundus tip, neck top, body top, body side) | -0.5 | 0.5 | m |
| 22 | largest gauge strain (over 15 mm) | 0 | 5 | - |
| 23 | exposure: the lesser of the two ducts' | 0 | 1 | - |
| 24 | fraction of the lower third's attachment released | 0 | 1 | - |
| 25-27 | hook tip position | -0.5 | 0.5 | m |
| 28 | hook energised (0 or 1) | 0 | 1 | - |

``obs_mode="pointcloud"``, ``"rgb"``, ``"depth"``, ``"rgbd"`` as for OrganRetraction (the
camera draws the jaws and the hook; released attachment shows in recordings).

## Rewards, Episode End, Harm

OrganRetraction's terms on the ducts' lesser exposure, plus ``reward_release`` (10 times
the change of the released fraction), ``reward_collateral`` (minus 0.05 per joule into
tissue that is not attachment) and ``reward_critical`` (minus 20 once, on the critical
structure). **Harm** (``info["cost"]``, per step): the strain cost (gauge strain above
0.18, times ``control_dt``), plus ``settings.collateral_cost`` (0.01) per joule of
collateral energy, plus ``settings.critical_cost`` (10) if the energised hook comes within
5 mm of the common bile duct. That ends the episode (``info["critical_hit"]``).
``info`` also reports ``released_fraction``, ``duct_exposure``, ``artery_exposure`` and the
hook's ``hook_energised``, ``hook_released``, ``hook_released_area``,
``hook_collateral_energy``.

## Starting State

Tissue at rest, its lower third stuck 20-28 mm out from the neck; the cystic duct's centre
uniform in x 14-18 mm, y -7..-3 mm, 5 mm below the bed's surface; jaws uniform in x
70-74 mm, y -3..3 mm, z 23-25 mm (above the fundus); the hook's tip uniform in x 26-30
mm, y -2..2 mm, z 1-3 mm, off; E uniform in 4-8 kPa. The laparoscope looks from (130, 0,
150) mm at the neck.

## Arguments

As OrganRetraction's (``obs_mode``, ``camera``, ``render_mode``, ``settings`` (a
:class:`DissectionSettings`), ``weights`` (a :class:`DissectionWeights`), ``mesh_size``,
``scene`` (``configs/scenes/gallbladder_dissection.yaml``), ``physics``, ``difficulty``).

## Scripted expert

The grasper closes on the fundus and lifts it 12 mm; the hook, energised, sweeps the stuck
strip in two lanes (y = +-4.5 mm, 0.5 mm above the bed, at 5 mm/s) until 97 % of the
lower third is released, then switches off and rises; the grasper then folds the sac back about its neck
until both ducts show (:class:`heml_gym.envs.scripted.DissectionPolicy`; ``heml-gym eval
scripted --env heml_gym/GallbladderDissection-v0``).

## Version History

v0 (2026-11-28): the task described here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from .core import BatchedRetraction, RewardWeights, TaskSettings, as_settings
from .instruments.hook import surface_areas
from .retraction_env import RetractionEnv, RetractionVectorEnv
from .scene import (AdhesionSpec, CameraSpec, FoldSpec, GripperSpec, HookSpec, PhysicsSpec, RegionSpec, Scene,
                    StructureSpec, SupportSpec, TargetSpec, TissueSpec)
from .spec import SpecError

DEFAULT_MESH_SIZE = 0.005  # m
LOWER_THIRD = 0.085 / 3  # m: the sac's lower third, from the neck (x = 0)
#: m: the cystic artery analogue's centre from the cystic duct's (the target)
ARTERY_OFFSET = (0.004, 0.009, 0.0)
#: J/m^2: what frees the attachment: vaporising a 0.1 mm water-like layer (2.26 kJ/g latent
#: heat plus 0.26 kJ/g to heat it from 37 to 100 C, at 1 g/cm^3): the areolar plane, cut
RELEASE_ENERGY = 2.6e5
#: m: the hook frees and heats tissue this close to its tip (its L-shaped end, about 6 mm)
HOOK_REACH = 0.006


@dataclass(frozen=True)
class DissectionSettings(TaskSettings):
    """TaskSettings and the dissection's: ``release_fraction`` (of the lower third's
    attachment, released for the critical view), ``collateral_cost`` (harm per joule into
    tissue that is not attachment), ``critical_cost`` (harm of energy near the critical
    structure; the episode ends). ``max_steps`` 200 (the release takes time)."""

    max_steps: int = 200
    release_fraction: float = 0.8
    collateral_cost: float = 0.01
    critical_cost: float = 10.0

    def __post_init__(self):
        super().__post_init__()
        f = self.release_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f <= 1:
            raise SpecError(f"DissectionSettings.release_fraction: must lie in (0, 1], got {f!r}")
        for name in ("collateral_cost", "critical_cost"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                     and value >= 0):
                raise SpecError(f"DissectionSettings.{name}: must be a finite number >= 0, got {value!r}")


@dataclass(frozen=True)
class DissectionWeights(RewardWeights):
    """RewardWeights and the dissection's: ``release`` (times the change of the released
    fraction), ``collateral`` (per joule of collateral energy, a penalty), ``critical``
    (once, a penalty, when the energised hook comes near the critical structure)."""

    release: float = 10.0
    collateral: float = 0.05
    critical: float = 20.0


class BatchedDissection(BatchedRetraction):
    """N gallbladder dissections: the retraction task on the lesser of two ducts' exposure,
    with the lower third's release in the state and the success, and the hook's harm."""

    EXTRA_STATE = (("released_fraction", "-"),)

    def __init__(self, scene, n_worlds, settings=None, weights=None, grippers=None):
        if not scene.hooks or scene.spec.critical is None or scene.adhesion_vertices is None:
            raise SpecError("scene: a dissection needs a hook (scene.hooks), adhesion (scene.adhesion) and a "
                            "critical structure (scene.critical)")
        self.released_fraction = np.zeros(n_worlds)
        self.duct_exposure, self.artery_exposure = np.zeros(n_worlds), np.zeros(n_worlds)
        super().__init__(scene, n_worlds, as_settings(settings, DissectionSettings, "settings"), None, grippers)
        self.weights = as_settings(weights, DissectionWeights, "weights")
        self.critical = scene.spec.critical
        mesh = scene.mesh
        self._area = surface_areas(mesh.vertices, scene.surface_faces)
        self._lower = mesh.vertices[:, 0] <= scene.hinge[0] + LOWER_THIRD

    # ----------------------------------------------------------- measurements
    def measure_exposure(self, worlds) -> np.ndarray:
        """The lesser of the two ducts' exposures, per world (each kept in
        ``duct_exposure`` and ``artery_exposure``)."""
        worlds = np.atleast_1d(worlds)
        x, duct = self.x[worlds], self.target[worlds]
        self.duct_exposure[worlds] = self._exposure(x, duct)
        self.artery_exposure[worlds] = self._exposure(x, duct + np.asarray(ARTERY_OFFSET))
        return np.minimum(self.duct_exposure[worlds], self.artery_exposure[worlds])

    def measure_released(self, worlds) -> np.ndarray:
        """Fraction of the lower third's attachment (its stuck area at the episode's start)
        released, per world; 1 where none was stuck."""
        worlds = np.atleast_1d(worlds)
        lower = self.stuck_at_start[worlds] & self._lower[None, :]
        stuck = (lower * self._area).sum(axis=1)
        freed = ((lower & ~self.world.stuck[worlds]) * self._area).sum(axis=1)
        return np.where(stuck > 0, freed / np.where(stuck > 0, stuck, 1.0), 1.0)

    def critical_hit(self) -> np.ndarray:
        """Whether an energised hook is within the critical structure's margin, per world."""
        hit = np.zeros(self.n, dtype=bool)
        for h in self.hooks:
            hit |= h.energised & (self.critical.distance(h.position) <= self.critical.margin)
        return hit

    def _measure_start(self, idx: np.ndarray) -> None:
        super()._measure_start(idx)
        self.released_fraction[idx] = self.measure_released(idx)

    def advance(self, actions, active=None):
        out = super().advance(actions, active)
        self.released_fraction = self.measure_released(np.arange(self.n))
        return out

    def _also_needed(self) -> np.ndarray:
        return self.released_fraction >= self.settings.release_fraction

    # ------------------------------------------------------------------- step
    def step(self, actions, active=None):
        before = self.released_fraction.copy()
        reward, terminated, truncated, info = super().step(actions, active)
        st, w = self.settings, self.weights
        failed = info["simulation_diverged"] | ~info["solver_converged"]
        collateral = sum(info[f"{h.name}_collateral_energy"] for h in self.hooks)
        hit = self.critical_hit() & ~failed
        terms = {"reward_release": np.where(failed, 0.0, w.release * (self.released_fraction - before)),
                 "reward_collateral": np.where(failed, 0.0, -w.collateral * collateral),
                 "reward_critical": np.where(hit, -w.critical, 0.0)}
        hook_cost = np.where(failed, 0.0, st.collateral_cost * collateral) + np.where(hit, st.critical_cost, 0.0)
        self.damage = self.damage + hook_cost
        reward = np.where(hit & info["is_success"], reward - w.success, reward)  # no success where it was hit
        info.update(terms, strain_cost=info["cost"], hook_cost=hook_cost, cost=info["cost"] + hook_cost,
                    damage=self.damage.copy(), critical_hit=hit, is_success=info["is_success"] & ~hit,
                    released_fraction=self.released_fraction.copy(), duct_exposure=self.duct_exposure.copy(),
                    artery_exposure=self.artery_exposure.copy())
        truncated = truncated & ~hit
        return reward + sum(terms.values()), terminated | hit, truncated, info

    def start_info(self, worlds) -> dict:
        info = super().start_info(worlds)
        worlds = np.atleast_1d(np.asarray(worlds, dtype=np.int64))
        zero = np.zeros(len(worlds))
        info.update({f"reward_{f.name}": zero.copy() for f in fields(DissectionWeights)},
                    strain_cost=zero.copy(), hook_cost=zero.copy(), critical_hit=np.zeros(len(worlds), dtype=bool),
                    released_fraction=self.released_fraction[worlds].copy(),
                    duct_exposure=self.duct_exposure[worlds].copy(),
                    artery_exposure=self.artery_exposure[worlds].copy())
        return info

    # ------------------------------------------------------------ observation
    def extra_state_observation(self) -> list[np.ndarray]:
        return [self.released_fraction[:, None]]


def dissection_scene(mesh_size: float = DEFAULT_MESH_SIZE) -> Scene:
    """The gallbladder in its bed (``mesh_size`` m), a grasper on its fundus and a hook."""
    grasper = GripperSpec(start_low=(0.070, -0.003, 0.023), start_high=(0.074, 0.003, 0.025),
                          workspace_low=(-0.05, -0.06, 0.0), workspace_high=(0.15, 0.06, 0.12),
                          jaw_length=0.02, jaw_ends="weighted")
    hook = HookSpec(start_low=(0.026, -0.002, 0.001), start_high=(0.030, 0.002, 0.003),
                    workspace_low=(-0.04, -0.05, 0.0), workspace_high=(0.12, 0.05, 0.08),
                    reach=HOOK_REACH, release_energy=RELEASE_ENERGY)
    return Scene(
        name="GallbladderDissection",
        tissue=TissueSpec(kind="organ", organ="gallbladder", mesh_size=mesh_size),
        physics=PhysicsSpec(material="NeoHookean", young_modulus=(4e3, 8e3), poisson=0.45, density=1030.0,
                            damping=5.0, gravity=(0.0, 0.0, -9.81), field="heml", integrator="quasi_newton",
                            max_dt=0.05, newton_tol=3e-3, max_newton=100, safety=0.5),
        attachment=RegionSpec(low=(0.0, None, 0.0), high=(0.0, None, 0.0)),  # the bottom edge of the neck
        grasp=RegionSpec(low=(0.064, -0.012, 0.014), high=(0.080, 0.012, None), surface=True),  # the fundus's top
        tracked=RegionSpec(points=[(0.085, 0.0, 0.007), (0.003, 0.0, 0.015), (0.05, 0.0, 0.023),
                                   (0.05, 0.016, 0.007)], surface=True),
        fold=FoldSpec(hinge=(0.0, 0.0), direction=1.0, angle=1.2,
                      edge=RegionSpec(low=(0.078, None, None), surface=True, tolerance=0.0)),
        target=TargetSpec(low=(0.014, -0.007, -0.005), high=(0.018, -0.003, -0.005), radius=0.004),
        gripper=grasper,
        camera=CameraSpec(eye=(0.13, 0.0, 0.15), look_at=(0.015, 0.0, 0.0), up=(0.0, 0.0, 1.0)),
        support=SupportSpec(kind="plane", normal=(0.0, 0.0, 1.0), offset=0.0),
        strain_gauge=0.015,
        adhesion=AdhesionSpec(region=RegionSpec(low=(None, None, 0.0), high=(None, None, 0.0), tolerance=1e-6),
                              width=(0.020, 0.028)),
        graspers={"grasper": grasper},
        hooks={"hook": hook},
        critical=StructureSpec(start=(-0.010, -0.03, -0.004), end=(-0.010, 0.03, -0.004), radius=0.003, margin=0.005),
    )


class GallbladderDissectionEnv(RetractionEnv):
    __doc__ = __doc__
    default_scene = staticmethod(dissection_scene)
    task_class = BatchedDissection
    settings_class = DissectionSettings
    weights_class = DissectionWeights

    def __init__(self, obs_mode="state", render_mode=None, settings=None, weights=None, mesh_size=None,
                 scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(obs_mode, render_mode, settings, weights, scene=scene, physics=physics, camera=camera,
                         difficulty=difficulty, mesh_size=mesh_size)


class GallbladderDissectionVectorEnv(RetractionVectorEnv):
    """``num_envs`` GallbladderDissection scenes in one batched Numba call (see GallbladderDissectionEnv)."""

    default_scene = staticmethod(dissection_scene)
    task_class = BatchedDissection
    settings_class = DissectionSettings
    weights_class = DissectionWeights

    def __init__(self, num_envs=4, obs_mode="state", settings=None, weights=None, max_episode_steps=None,
                 render_mode=None, mesh_size=None, scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(num_envs, obs_mode, settings, weights, max_episode_steps, render_mode, scene=scene,
                         physics=physics, camera=camera, difficulty=difficulty, mesh_size=mesh_size)
