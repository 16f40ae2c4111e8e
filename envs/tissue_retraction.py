"""TissueRetraction-v1: lift a fat flap off a tumour.

## Description

A flap of fat tissue (120 x 120 x 8 mm, the size of LapGym's tissue-retraction slab)
lies on an organ; its edge at ``x = 0`` is attached, and its underside is stuck to the
organ 0-20 mm further out (drawn per episode, see Starting State). Under it, hidden from
a camera above, sits a tumour (a sphere of radius 8 mm, in the organ). The agent moves a
gripper, closes it on the flap's free edge, and retracts the flap to expose the tumour
without over-straining the tissue. The tissue is Neo-Hookean HEML (E drawn in 4-8 kPa per
episode, nu = 0.45, 950 kg/m^3) under gravity, resting on the organ: a rigid,
frictionless plane at z = 0 (``Scene.support``). It is integrated by backward Euler in
0.05 s steps, each solved by L-BFGS to 3e-3 of the flap's weight
(:class:`heml_gym.QuasiNewtonSolver`; any law, field and integrator with ``physics=``).
The mesh is 12 x 12 x 2 hex cells of 6 tets (1,728 tets): with this integrator the
cheapest model whose grasp force and exposure stay within 5 % of a fine one along the
scripted retraction and its 2 s hold (docs/studies/scene_convergence.md); the one-layer
12 x 12 x 1 mesh of earlier versions is 10 % off in the hold once the underside is stuck.

## Action Space

``Box(-1, 1, (4,), float32)``: gripper velocity along x, y, z in units of
``max_speed`` (0.05 m/s), and a grasp command (> 0 closes, < -0.5 opens, in between the
jaws stay as they are: ``settings.release_command``). The jaws clamp the
free edge along its top line (``Scene.grasp``: the vertices at x = 120 mm,
z = 8 mm, the same line of tissue on every mesh, free to rotate about it): closing with
that line within ``grasp_reach`` (12 mm) holds all of it, opening releases it. Held tissue
cannot be pressed below where it rests. Out-of-range actions are clipped; non-finite ones
raise ``ValueError``. Each step simulates ``control_dt`` = 0.1 s.

## Observation Space

``obs_mode="state"``: ``Box(24,)`` float32, clipped to its bounds:

| index | meaning | min | max | unit |
|---|---|---|---|---|
| 0-2 | gripper position | -0.5 | 0.5 | m |
| 3 | grasping (0 or 1) | 0 | 1 | - |
| 4-6 | grasp force (force of the tissue on the gripper, mean over the step) | -20 | 20 | N |
| 7-9 | target (tumour centre) position | -0.5 | 0.5 | m |
| 10-21 | four tracked tissue points (free-edge corners and middle, flap centre) | -0.5 | 0.5 | m |
| 22 | largest gauge strain of the tissue (over 15 mm, see below) | 0 | 5 | - |
| 23 | exposure of the target | 0 | 1 | - |

``obs_mode="pointcloud"``: ``Dict(state=<the above>, points=Box(64, 3))``: 64 fixed
tissue surface vertices (m). ``obs_mode="rgb"``, ``"depth"`` or ``"rgbd"``: the task
camera's images (``camera={"size": [H, W], ...}``: :class:`~heml_gym.envs.camera.ImageSpec`).

## Rewards

The sum of (each reported in ``info`` under its name, weights in ``RewardWeights``):
``reward_exposure`` = 10 x (change of exposure this step); ``reward_lift`` = 20 x (change
of lift progress this step), a potential-based shaping term (Ng et al. 1999) that pays
for folding the free edge (x = 120 mm) back about the attached edge's top line, 1 at
90 degrees (``info["lift"]``); ``reward_grasp`` = 0.5 the
first time a grasp holds tissue; ``reward_strain`` = -5 x (largest gauge strain - 0.5, if
positive); ``reward_stretch`` = -5 x (change of the largest gauge strain this step), a
potential-based shaping term that charges stretching the tissue (and pays it back as the
strain falls), so that folding beats pulling; ``reward_effort`` = -0.01 x |velocity command|^2; ``reward_success`` = 5 on
success; with a hold time, ``reward_hold`` = 1 per second the success condition has held
before success. Exposure is the fraction of the tumour's camera-facing surface samples (256
points) that the deformed tissue surface does not hide, by ray casting. Tissue strain is
measured over a 15 mm gauge (:mod:`heml_gym.envs.strain_gauges`): the largest
``|l / L - 1|`` of segments between material points 15 mm apart on the flap's mid-plane,
not of the mesh's edges, whose strain next to the grasp grows without bound as the mesh
is refined.

## Starting State

Tissue at rest on the organ; tumour centre uniform in x 50-90 mm, y 35-85 mm, 20 mm below
the flap's underside (its top 12 mm below); gripper uniform in x 108-114 mm, y 40-80 mm,
z 9-11 mm (just above the free edge); tissue E uniform in 4-8 kPa; the flap's underside
stuck to the organ from the attached edge out to a width uniform in 0-20 mm
(``Scene.adhesion``: those vertices are held where they rest, so the flap folds about a
line up to 20 mm further out than the attached edge). ``reset(seed=...)`` fixes all of them;
``reset(options={"young_modulus": E, "gripper": [x, y, z], "adhesion_width": w})`` sets
any of E (Pa), the gripper's start (m, inside the workspace) and the stuck width (m)
instead (a replay of a recorded episode starts this way).

## Episode End

Terminated on success (exposure >= 0.8 with gauge strain below 0.5, held continuously
for ``settings.hold_time`` seconds of simulated time: 2 s at the default difficulty 1, 0
(at once) at difficulty 0; the time held so far is ``info["hold_time"]``, not observed),
when the tissue tears (gauge strain >= 1.0), or on a physics failure: a simulation that
diverged (``info["simulation_diverged"]``) or a step whose solve did not converge, under
any integrator, after the quasi-Newton solver's Newton fallback and its shorter sub-steps
(``info["solver_converged"]`` False); the reward is then 0 and the observation stays
finite. Truncated after 100 steps (10 s). ``info["substep_refinement"]``
says when the solver had to re-take a step in shorter sub-steps (strongly compressed
tissue), ``info["solver_fallback"]`` when the quasi-Newton solver took it again by
Newton's method (its fallback), ``info["newton_iterations"]`` what an implicit step cost.

Harm, as Safety-Gymnasium reports it (a cost beside the reward; the reward does not
include it): ``info["cost"]`` is ``control_dt * max(0, gauge strain - safe_strain)``
(strain x s) per step, ``info["damage"]`` its sum over the episode so far.
``settings.safe_strain`` is 0.18 by default: the lower end (mean - 1 SD) of the ultimate
local strain of human liver capsule in tension, 0.47 +- 0.29 (Brunon, Bruyere-Garnier and
Coret, J Biomech 43(11), 2010). The jaws hold tissue kinematically: there is no squeeze
force to cost.
``info`` has the same keys at reset (every reward term 0) and at every step, including
the episode's draws ``young_modulus`` (Pa) and, with adhesion, ``adhesion_width`` (m).

## Arguments

``obs_mode`` ("state" | "pointcloud" | "rgb" | "depth" | "rgbd"), ``camera`` (the image
observations' settings), ``render_mode`` ("rgb_array" | "human"),
``settings`` (:class:`~heml_gym.envs.core.TaskSettings` or a mapping of its fields),
``weights`` (:class:`~heml_gym.envs.core.RewardWeights` or a mapping), ``cells`` (mesh
cells along x, y, z), ``scene`` (a :class:`~heml_gym.envs.scene.Scene`, a mapping of
changes to this scene, or a scene YAML path: ``configs/scenes/tissue_retraction.yaml``),
``physics`` (a mapping of :class:`~heml_gym.envs.scene.PhysicsSpec` fields: ``material``,
``young_modulus``, ``poisson``, ``field``, ``integrator``, ``safety``, ``max_dt``, ...; or
``fit``: a ``heml-gym calibrate`` folder or its fit.json, whose law, Poisson ratio and E,
drawn within two standard errors of the fitted value, the tissue then has).
``difficulty`` (:mod:`heml_gym.envs.difficulty`; the scripted baseline's success rate
and episode length on each level are measured in docs/studies/envs.md):

| difficulty | task | scripted success | scripted episode, median steps |
|---|---|---|---|
| 0 | success as soon as the target is exposed below damage strain | 100 % | 23 |
| 1 (default) | hold the target exposed, below damage strain, for 2 s (``settings.hold_time``) | 100 % | 43 |
| 2 | as 1, with tissue E drawn from half the scene's lowest to 1.5x its highest, and the target region moved halfway towards the hinge (x 25-45 mm) | 100 % | 48 |

(20 seeded episodes each, ``python benchmarks/learning/task_difficulty.py``.)

## Version History

v1 (2026-11-26): the task described here, unchanged since 2026-11-25 18:19 UTC, when it
was still registered as v0: difficulty 1 (hold 2 s) by default; a 12 x 12 x 2 flap
stepped by the quasi-Newton solver; the underside stuck 0-20 mm out from the attached
edge, drawn per episode. Registered with ``max_episode_steps`` 100. The quasi-Newton
initial Hessian's weight (``physics.hessian_scale`` 1.25, 2026-11-26) changes iterations,
not the task (the scripted fold's exposure, episode lengths and success identical on 5
seeds, grasp force within 0.32 %).

v0 (retired 2026-11-26): named five tasks over time: an 8 x 8 x 1 flap by explicit
sub-steps, success at first exposure; since the convergence redesign a line clamp,
gravity on a support plane, gauge strain and step-mean grasp force; since 2026-11-24
difficulty 1 and a 12 x 12 x 1 quasi-Newton flap with a free underside; since
2026-11-25 18:19 the v1 task. ``FORMER_TASK`` restores the 2026-11-24 scene. A result
quoted for v0 is on the task of its date (docs/benchmarks/index.md says which).
"""

from __future__ import annotations

import math

from .retraction_env import RetractionEnv, RetractionVectorEnv
from .scene import (AdhesionSpec, CameraSpec, FoldSpec, GripperSpec, PhysicsSpec, RegionSpec, Scene, SupportSpec,
                    TargetSpec, TissueSpec)

FLAP_SIZE = (0.12, 0.12, 0.008)
DEFAULT_CELLS = (12, 12, 2)
STIFFNESS_RANGE = (4e3, 8e3)  # Pa: E drawn per episode
HINGE = (0.0, FLAP_SIZE[2])  # m: (x, z) of the attached edge's top line, the fold hinge
#: the flap's underside (a scene region), stuck to the organ over a width drawn per episode,
#: 0-20 mm out from the attached edge (the default since 2026-11-25)
UNDERSIDE = {"low": [None, None, 0.0], "high": [None, None, 0.0]}
ADHESION_WIDTH = (0.0, 0.02)  # m
#: per-episode variation that is not a default (changes to the scene, as
#: configs/experiments/quick_jaws_adhesion.yaml; docs/studies/envs.md): 40 mm jaws; with the default's adhesion
JAWS_AND_ADHESION = {"gripper": {"jaw_length": 0.04}, "adhesion": {"region": UNDERSIDE, "width": list(ADHESION_WIDTH)}}
#: the scene before 2026-11-25 (changes to the default scene): one layer of cells and the
#: underside free (a seed draws the same target place, stiffness and gripper start as then:
#: the adhesion width is drawn after them)
FORMER_TASK = {"tissue": {"cells": [12, 12, 1]}, "adhesion": None}


def flap_physics(young_modulus=STIFFNESS_RANGE) -> PhysicsSpec:
    """The fat flaps' physics (Neo-Hookean HEML fat under gravity, backward Euler by L-BFGS
    in 0.05 s steps), with E drawn in ``young_modulus`` (Pa, low and high)."""
    return PhysicsSpec(material="NeoHookean", young_modulus=tuple(young_modulus), poisson=0.45, density=950.0,
                       damping=5.0, gravity=(0.0, 0.0, -9.81), field="heml", integrator="quasi_newton",
                       max_dt=0.05, newton_tol=3e-3, max_newton=100, safety=0.75, hessian_scale=1.25)


def flap_regions(size) -> dict:
    """The regions of a box flap of ``size`` (m) attached along ``x = 0``: the attachment,
    the grasp (the free edge's top line), the tracked points (free-edge corners and middle,
    the centre) and the fold about the attached edge's top line (Scene fields)."""
    lx, ly, lz = size
    return {"attachment": RegionSpec(low=(0.0, None, None), high=(0.0, None, None)),
            "grasp": RegionSpec(low=(lx, None, lz), high=(lx, None, lz)),
            "tracked": RegionSpec(points=[(lx, 0.0, lz), (lx, ly / 2, lz), (lx, ly, lz), (lx / 2, ly / 2, lz)]),
            "fold": FoldSpec(hinge=(0.0, lz), direction=1.0, angle=math.pi / 2,
                             edge=RegionSpec(low=(lx, None, None), high=(lx, None, None)))}


def tissue_scene(cells=DEFAULT_CELLS, mirrored: bool = True) -> Scene:
    """The fat-flap scene with a ``cells`` hex grid (6 tets per cell; ``mirrored``: each
    cell split as the mirror image of its neighbours, see :func:`heml_gym.mesh.box_mesh`)."""
    return Scene(
        name="TissueRetraction",
        tissue=TissueSpec(kind="box", size=FLAP_SIZE, cells=tuple(int(c) for c in cells), mirrored=mirrored),
        physics=flap_physics(),
        **flap_regions(FLAP_SIZE),
        target=TargetSpec(low=(0.05, 0.035, -0.02), high=(0.09, 0.085, -0.02), radius=0.008),
        gripper=GripperSpec(start_low=(0.108, 0.04, 0.009), start_high=(0.114, 0.08, 0.011),
                            workspace_low=(-0.05, -0.05, 0.0), workspace_high=(0.20, 0.17, 0.15)),
        camera=CameraSpec(eye=(0.06, 0.06, 0.30)),
        support=SupportSpec(kind="plane", normal=(0.0, 0.0, 1.0), offset=0.0),
        strain_gauge=0.015,
        adhesion=AdhesionSpec(region=RegionSpec(low=(None, None, 0.0), high=(None, None, 0.0)),
                              width=ADHESION_WIDTH),  # UNDERSIDE, as a spec (tuples, as a loaded scene has)
    )


class TissueRetractionEnv(RetractionEnv):
    __doc__ = __doc__
    default_scene = staticmethod(tissue_scene)

    def __init__(self, obs_mode="state", render_mode=None, settings=None, weights=None, cells=None,
                 scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(obs_mode, render_mode, settings, weights, scene=scene, physics=physics, camera=camera,
                         difficulty=difficulty, cells=cells)


class TissueRetractionVectorEnv(RetractionVectorEnv):
    """``num_envs`` TissueRetraction scenes in one batched Numba call (see TissueRetractionEnv)."""

    default_scene = staticmethod(tissue_scene)

    def __init__(self, num_envs=4, obs_mode="state", settings=None, weights=None, max_episode_steps=None,
                 render_mode=None, cells=None, scene=None, physics=None, camera=None, difficulty=1):
        super().__init__(num_envs, obs_mode, settings, weights, max_episode_steps, render_mode, scene=scene,
                         physics=physics, camera=camera, difficulty=difficulty, cells=cells)
