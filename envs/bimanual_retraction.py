"""BimanualRetraction-v0: fold back a wide, soft flap with two graspers.

## Description

A flap of soft fat (120 x 240 x 8 mm: the TissueRetraction flap, twice as wide) lies on
an organ, attached along its edge at ``x = 0``, its underside stuck 0-20 mm further out
(drawn per episode). A tumour (a sphere of radius 8 mm) sits under the middle of its
free half, hidden from a camera above. Two graspers, ``left`` and ``right``, each with
40 mm jaws (a sixth of the free edge), must fold the flap back to expose the tumour and
hold it there without over-straining the tissue. The tissue is Neo-Hookean HEML with E
drawn in 3.5-5 kPa per episode (soft fat: breast adipose tissue measures 3.25 +- 0.91 kPa,
Samani, Zubovits and Plewes, Phys Med Biol 52(6), 2007, 1565-1576), nu = 0.45,
950 kg/m^3, under gravity on a rigid, frictionless plane at z = 0; stepped as
TissueRetraction (backward Euler, 0.05 s steps, L-BFGS). Mesh: 12 x 24 x 2 hex cells of 6
tets (3,456 tets), the flap's cell size. Along the scripted solution (3 seeds) its summed
grasp force stays within 6.5 % of a mesh twice as fine each way (24 x 48 x 4, solved in
0.025 s steps to 1e-4 of the weight) and its exposure within 0.012: inside the 8 % allowed a
jaw-length setting, not the 5 % rule (``docs/benchmarks/task_convergence.md``).

**Why two.** One grasper cannot do it. On 10 held-out seeds, one pair of the task's
40 mm jaws at the middle of the free edge, running the flap's scripted fold, strains the
tissue at the jaws' ends beyond the damage strain (peak gauge strain 0.51-0.64; 80 mm
jaws 0.54-0.67): 0 of 10 succeed. The two graspers at the quarter points share the load
(peak 0.27-0.37) and succeed on 10 of 10 (``docs/benchmarks/bimanual_task.md``,
``python benchmarks/accuracy/bimanual_task.py``). On a mesh twice as fine one grasper
strains the tissue more and two about the same (``docs/benchmarks/bimanual_feasibility_fine.md``).

## Action Space

``Box(-1, 1, (8,), float32)``: the ``left`` grasper's 4 entries, then the ``right``'s.
Each is TissueRetraction's: velocity along x, y, z in units of ``max_speed`` (0.05 m/s)
and a grasp command (> 0 closes, < -0.5 opens, in between the jaws stay as they are).
The jaws close on the free edge's top line (x = 120 mm, z = 8 mm) within ``grasp_reach``
(12 mm) and hold the 40 mm of it between them, their ends weighted
(``GripperSpec.jaw_ends: weighted``: a vertex partly inside the jaws by a spring that
holds its share). Tissue held by one grasper is not taken by the other. Each grasper
moves in the whole workspace (x -50..200 mm, y -50..290 mm, z 0..150 mm).

## Observation Space

``obs_mode="state"``: ``Box(31,)`` float32, clipped to its bounds:

| index | meaning | min | max | unit |
|---|---|---|---|---|
| 0-2 | left grasper position | -0.5 | 0.5 | m |
| 3 | left grasping (0 or 1) | 0 | 1 | - |
| 4-6 | left grasp force (of the tissue on the jaws, mean over the step) | -20 | 20 | N |
| 7-13 | the same for the right grasper | | | |
| 14-16 | target (tumour centre) position | -0.5 | 0.5 | m |
| 17-28 | four tracked tissue points (free-edge corners and middle, flap centre) | -0.5 | 0.5 | m |
| 29 | largest gauge strain of the tissue (over 15 mm) | 0 | 5 | - |
| 30 | exposure of the target | 0 | 1 | - |

``obs_mode="pointcloud"``, ``"rgb"``, ``"depth"``, ``"rgbd"`` as for TissueRetraction
(the camera draws both graspers).

## Rewards, Episode End, Harm

TissueRetraction's terms, thresholds and harm (``info["cost"]``, ``info["damage"]``),
with each grasper paid its first grasp once. Success: exposure >= 0.8 with the gauge
strain below 0.5, held for 2 s (difficulty 1). ``info`` reports each grasper under its
name (``left_grasp_force``, ``left_grasping``, ``right_...``), ``grasp_force`` (their
magnitudes summed, N) and ``grasping`` (either holds tissue).

## Starting State

Tissue at rest; tumour centre uniform in x 60-80 mm, y 100-140 mm, 20 mm below the
flap's underside; ``left`` jaws uniform in x 108-114 mm, y 50-70 mm, z 9-11 mm, ``right``
the same at y 170-190 mm; E uniform in 3.5-5 kPa; the underside stuck 0-20 mm out.
``reset(options={"young_modulus": E, "gripper": [x, y, z], "adhesion_width": w})`` sets E,
the left grasper's start and the stuck width.

## Arguments

As TissueRetraction's (``obs_mode``, ``camera``, ``render_mode``, ``settings``,
``weights``, ``cells``, ``scene`` (``configs/scenes/bimanual_retraction.yaml``),
``physics``, ``difficulty``). ``scene={"graspers": {"left": {"jaw_length": 0.06}}}``
changes one grasper.

## Scripted expert

Each grasper moves to its quarter point of the free edge (the middle of its start box
in y), closes, and runs TissueRetraction's fold on its own part of the observation
(``heml_gym.envs.scripted.scripted_policy``; ``heml-gym eval scripted --env
heml_gym/BimanualRetraction-v0``).

## Version History

v0 (2026-11-28): the task described here.
"""

from __future__ import annotations

from .retraction_env import RetractionEnv, RetractionVectorEnv
from .scene import AdhesionSpec, CameraSpec, GripperSpec, RegionSpec, Scene, SupportSpec, TargetSpec, TissueSpec
from .tissue_retraction import ADHESION_WIDTH, flap_physics, flap_regions

FLAP_SIZE = (0.12, 0.24, 0.008)  # m
DEFAULT_CELLS = (12, 24, 2)
STIFFNESS_RANGE = (3.5e3, 5e3)  # Pa: E drawn per episode
JAW_LENGTH = 0.04  # m


def _grasper(y_low: float, y_high: float) -> GripperSpec:
    """A grasper with 40 mm weighted jaws starting over the free edge between ``y_low`` and ``y_high`` (m)."""
    lx, ly, lz = FLAP_SIZE
    return GripperSpec(start_low=(lx - 0.012, y_low, lz + 0.001), start_high=(lx - 0.006, y_high, lz + 0.003),
                       workspace_low=(-0.05, -0.05, 0.0), workspace_high=(0.20, ly + 0.05, 0.15),
                       jaw_length=JAW_LENGTH, jaw_ends="weighted")


def bimanual_scene(cells=DEFAULT_CELLS) -> Scene:
    """The wide-flap scene with two graspers (``cells``: its hex grid, 6 tets per cell)."""
    lx, ly, lz = FLAP_SIZE
    left, right = _grasper(0.05, 0.07), _grasper(0.17, 0.19)
    return Scene(
        name="BimanualRetraction",
        tissue=TissueSpec(kind="box", size=FLAP_SIZE, cells=tuple(int(c) for c in cells)),
        physics=flap_physics(STIFFNESS_RANGE),
        **flap_regions(FLAP_SIZE),
        target=TargetSpec(low=(0.06, 0.10, -0.02), high=(0.08, 0.14, -0.02), radius=0.008),
        gripper=left,
        camera=CameraSpec(eye=(0.06, ly / 2, 0.35)),
        support=SupportSpec(kind="plane", normal=(0.0, 0.0, 1.0), offset=0.0),
        strain_gauge=0.015,
        adhesion=AdhesionSpec(region=RegionSpec(low=(None, None, 0.0), high=(None, None, 0.0)), width=ADHESION_WIDTH),
        graspers={"left": left, "right": right},
    )


class BimanualRetractionEnv(RetractionEnv):
    __doc__ = __doc__
    default_scene = staticmethod(bimanual_scene)

    def __init__(self, obs_mode="state", render_mode=None, settings=None, weights=None, cells=None,
                 scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(obs_mode, render_mode, settings, weights, scene=scene, physics=physics, camera=camera,
                         difficulty=difficulty, cells=cells)


class BimanualRetractionVectorEnv(RetractionVectorEnv):
    """``num_envs`` BimanualRetraction scenes in one batched Numba call (see BimanualRetractionEnv)."""

    default_scene = staticmethod(bimanual_scene)

    def __init__(self, num_envs=4, obs_mode="state", settings=None, weights=None, max_episode_steps=None,
                 render_mode=None, cells=None, scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(num_envs, obs_mode, settings, weights, max_episode_steps, render_mode, scene=scene,
                         physics=physics, camera=camera, difficulty=difficulty, cells=cells)
