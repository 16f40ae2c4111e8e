"""TissueManipulation-v0: grasp a flap and bring a marked point of it to a goal.

## Description

Goal-conditioned tissue manipulation (LapGym's tissue manipulation, in
Gymnasium-Robotics' ``GoalEnv`` form). The TissueRetraction flap (120 x 120 x 8 mm of
fat, attached along its edge at ``x = 0``, its underside free) lies on an organ. A point
of the tissue is marked: the middle of its free edge's top line (x = 120 mm, y = 60 mm,
z = 8 mm). Each episode draws a goal in the space above the flap; the agent grasps the
free edge with 40 mm jaws (weighted ends) and brings the marked point within 5 mm of the
goal, and keeps it there, without over-straining the tissue. Tissue and physics are
TissueRetraction's: Neo-Hookean HEML, E drawn in 4-8 kPa per episode, nu = 0.45,
950 kg/m^3, under gravity on a rigid, frictionless plane at z = 0, backward Euler in
0.05 s steps solved by L-BFGS; 12 x 12 x 2 hex cells of 6 tets (1,728 tets).

**Mesh convergence, a stated exception.** The marked point, which success is judged on,
is held by the jaws: along the scripted solution it is where a mesh twice as fine each way
puts it (0.0 % of its travel, 3 seeds). The grasp force is not converged: up to 76 % above
that finer mesh's, on a goal that folds the flap back on itself, where linear tets are too
stiff in bending (``docs/benchmarks/task_convergence.md``; a cantilever on coarse cells
sags 80 % short, ``docs/benchmarks/element_bending.md``). Read ``info["grasp_force"]`` as
this model's, not the tissue's.

## Action Space

``Box(-1, 1, (4,), float32)``: TissueRetraction's: jaw velocity along x, y, z in units of
``max_speed`` (0.05 m/s) and a grasp command (> 0 closes, < -0.5 opens). Closed within
``grasp_reach`` (12 mm) of the free edge's top line, the jaws hold the 40 mm of it
between them, their ends weighted (``GripperSpec.jaw_ends: weighted``).

## Observation Space

``Dict(observation, achieved_goal, desired_goal)`` (``obs_mode="state"``):

| key | index | meaning | min | max | unit |
|---|---|---|---|---|---|
| observation | 0-2 | jaw position | -0.5 | 0.5 | m |
| observation | 3 | grasping (0 or 1) | 0 | 1 | - |
| observation | 4-6 | grasp force (of the tissue on the jaws) | -20 | 20 | N |
| observation | 7-18 | four tracked tissue points (free-edge corners and middle, flap centre) | -0.5 | 0.5 | m |
| observation | 19 | largest gauge strain of the tissue (over 15 mm) | 0 | 5 | - |
| achieved_goal | 0-2 | the marked point | -0.5 | 0.5 | m |
| desired_goal | 0-2 | the goal | -0.5 | 0.5 | m |

``obs_mode="pointcloud"`` adds ``points`` (64 tissue surface vertices, m); ``"rgb"``,
``"depth"``, ``"rgbd"`` add the camera's images (``rgb``, ``depth``), the goal drawn as
a 5 mm sphere.

## Rewards

``settings.reward_type="sparse"`` (default): -1 each step the marked point is more than
``goal_tolerance`` (5 mm) from the goal, 0 within it; ``"dense"``: minus the distance
(m). ``env.unwrapped.compute_reward(achieved_goal, desired_goal, info)`` gives the same
for any batch of goals (what SB3's ``HerReplayBuffer`` relabels with).

## Starting State

Tissue at rest; jaws open, uniform in x 108-114 mm, y 55-65 mm, z 9-11 mm (within reach
of the edge, the marked point between the jaws); goal uniform in x 50-100 mm, y 45-75 mm,
z 20-60 mm (within 113 mm of the attached edge's top line: every goal can be reached
without stretching the flap); E uniform in 4-8 kPa.
``reset(options={"goal": [x, y, z], "young_modulus": E, "gripper": [x, y, z]})`` sets any
of them (a goal must lie inside the workspace, x -50..200 mm, y -50..170 mm, z 0..150 mm).

## Episode End

Reaching the goal does not end the episode (``GoalEnv``'s convention:
``info["is_success"]`` says each step whether the marked point is within tolerance).
Terminated when the tissue tears (gauge strain >= 1.0) or the physics fails (as
TissueRetraction; the reward is then 0). Truncated after 50 steps (5 s).

## Harm

TissueRetraction's: ``info["cost"]`` is ``control_dt * max(0, gauge strain - 0.18)``
(strain x s) per step, ``info["damage"]`` its sum over the episode. ``info`` also has
``goal_distance`` (m), ``max_strain``, ``grasp_force`` (N), ``grasping``, the solver's
counters and ``young_modulus``.

## Arguments

``obs_mode``, ``camera``, ``render_mode``, ``cells``, ``scene``
(``configs/scenes/tissue_manipulation.yaml``), ``physics`` as for TissueRetraction;
``settings``: :class:`~heml_gym.envs.manipulation.ManipulationSettings` or a mapping of
its fields (``goal_tolerance``, ``reward_type``, ``max_steps``, the jaws' and strain
settings).

## Scripted expert

Close the jaws where they start, then move them by the marked point's offset from the
goal each step (:class:`heml_gym.envs.scripted.ReachGoalPolicy`; ``heml-gym eval scripted
--env heml_gym/TissueManipulation-v0``).

## Version History

v0 (2026-11-28): the task described here.
"""

from __future__ import annotations

from .goal_env import GoalObservations
from .manipulation import BatchedManipulation, ManipulationSettings
from .retraction_env import RetractionEnv, RetractionVectorEnv
from .scene import CameraSpec, GripperSpec, RegionSpec, Scene, SupportSpec, TargetSpec, TissueSpec
from .tissue_retraction import DEFAULT_CELLS, FLAP_SIZE, flap_physics, flap_regions

GOAL_LOW = (0.05, 0.045, 0.02)  # m
GOAL_HIGH = (0.10, 0.075, 0.06)  # m
JAW_LENGTH = 0.04  # m


def manipulation_scene(cells=DEFAULT_CELLS) -> Scene:
    """The flap with a marked point and a goal region (``cells``: its hex grid, 6 tets per cell)."""
    lx, ly, lz = FLAP_SIZE
    return Scene(
        name="TissueManipulation",
        tissue=TissueSpec(kind="box", size=FLAP_SIZE, cells=tuple(int(c) for c in cells)),
        physics=flap_physics(),
        **flap_regions(FLAP_SIZE),
        target=TargetSpec(low=GOAL_LOW, high=GOAL_HIGH, radius=0.005),
        gripper=GripperSpec(start_low=(0.108, 0.055, 0.009), start_high=(0.114, 0.065, 0.011),
                            workspace_low=(-0.05, -0.05, 0.0), workspace_high=(0.20, 0.17, 0.15),
                            jaw_length=JAW_LENGTH, jaw_ends="weighted"),
        camera=CameraSpec(eye=(0.06, -0.12, 0.22), look_at=(0.07, 0.06, 0.03), up=(0.0, 0.0, 1.0)),
        support=SupportSpec(kind="plane", normal=(0.0, 0.0, 1.0), offset=0.0),
        strain_gauge=0.015,
        marker=RegionSpec(points=[(lx, ly / 2, lz)]),
    )


class TissueManipulationEnv(GoalObservations, RetractionEnv):
    __doc__ = __doc__
    default_scene = staticmethod(manipulation_scene)
    task_class = BatchedManipulation
    settings_class = ManipulationSettings

    def __init__(self, obs_mode="state", render_mode=None, settings=None, cells=None, scene=None, physics=None,
                 camera=None):
        super().__init__(obs_mode, render_mode, settings, None, scene=scene, physics=physics, camera=camera,
                         difficulty=0, cells=cells)


class TissueManipulationVectorEnv(GoalObservations, RetractionVectorEnv):
    """``num_envs`` TissueManipulation scenes in one batched Numba call (see TissueManipulationEnv)."""

    default_scene = staticmethod(manipulation_scene)
    task_class = BatchedManipulation
    settings_class = ManipulationSettings

    def __init__(self, num_envs=4, obs_mode="state", settings=None, max_episode_steps=None, render_mode=None,
                 cells=None, scene=None, physics=None, camera=None):
        super().__init__(num_envs, obs_mode, settings, None, max_episode_steps, render_mode, scene=scene,
                         physics=physics, camera=camera, difficulty=0, cells=cells)
