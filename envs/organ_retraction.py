"""OrganRetraction-v2: fold a liver lobe back about its base to expose what lies beneath it.

## Description

A soft liver-like lobe (145 x 100 x 44 mm, meshed with gmsh; thin towards -x) lies on
the organs below (a rigid, frictionless plane at z = 0) and is attached along the bottom
edge of its base (the cut face at x = 65 mm, where it would join the rest of the liver),
about which it can turn; its underside is stuck to the support over a width drawn per
episode, 0-40 mm out from the base, so it turns about a line that far out. Beneath its
base third lies a structure to expose (a sphere of radius 8 mm, e.g. a gallbladder neck),
hidden from a laparoscope placed in front of and above the thin edge (at (-170, 0, 120)
mm, looking under the edge). The agent grasps the lobe near its thin edge, folds it back
and up about its base until the target shows, and holds it there (the scripted fold: 32
steps, median; docs/benchmarks/task_difficulty.md). Neo-Hookean HEML tissue (E drawn
in 4-8 kPa, nu = 0.45, 1060 kg/m^3) under gravity, integrated by backward Euler in
0.05 s steps, each solved by L-BFGS to 3e-3 of the lobe's weight
(:class:`heml_gym.QuasiNewtonSolver`): several times faster than explicit sub-steps
(``physics={"integrator": "explicit"}``, at 0.5 of the critical step), for the same
accuracy. The mesh (10 mm elements, refined to 2.5 mm around the jaws: about 4,400
tets), the cheapest that keeps grasp force and exposure within 5 % of a converged fine
mesh (docs/studies/scene_convergence.md): lifting the lobe peels it off its support, and how
far it peels depends on its bending stiffness, which coarse linear tets overestimate,
and on how compliant the tissue next to the jaws is, which only fine elements there
resolve.

## Action Space, Observation Space, Rewards, Episode End

As for ``TissueRetraction-v1`` (see :mod:`heml_gym.envs.tissue_retraction`): the same
4-D action, 24-D state (the four tracked points are the lobe's thin-edge corners and
middle, and its top centre), the same reward terms and thresholds, strain over the same
15 mm gauge. Closed jaws hold the lobe's top face over their footprint, a 6 x 40 mm patch
centred 25 mm behind the thin edge (x = -55 mm; its outline imprinted on the mesh, so
that it is the same tissue at any mesh size).

## Starting State

Tissue at rest on its support, its underside stuck 0-40 mm out from the base (uniform);
target centre uniform in x 30..45 mm, y -20..20 mm, 23 mm below the lobe's flat face;
gripper uniform in x -58..-52 mm, y -10..10 mm, z 24-27 mm (above the jaws' footprint);
E uniform in 4-8 kPa. ``reset(options=...)`` sets E, the gripper's start and the stuck
width as for TissueRetraction.

## Arguments

``obs_mode``, ``render_mode``, ``settings``, ``weights``, ``scene``, ``physics``, ``difficulty`` as for
TissueRetraction (the default scene: ``configs/scenes/organ_retraction.yaml``);
``mesh_size`` (m, gmsh element size away from the jaws; default 10 mm; it must stay above
the 2.5 mm at the jaws, and ``scene=organ_scene(size, jaw_size=None)`` meshes uniformly).
``scene=organ_scene(grasp="line")`` holds only the 40 mm line through the footprint's
middle (the former default): a line held in 3-D elasticity has no fine-mesh
limit (the edge in front of it droops further on every finer mesh), a patch does
(docs/studies/scene_convergence.md, "Line and patch grasps"). Difficulty levels:

| difficulty | task | scripted success | scripted episode, median steps |
|---|---|---|---|
| 0 | success as soon as the target is exposed below damage strain | 100 % | 12 |
| 1 (default) | hold the target exposed, below damage strain, for 2 s (``settings.hold_time``) | 100 % | 32 |
| 2 | as 1, with E drawn in 2-12 kPa, and the target halfway closer to the base (x 47.5-55 mm), next to where the underside may be stuck | 100 % | 33 |

(20 seeded episodes each, ``python benchmarks/learning/task_difficulty.py``.)

## Version History

v2 (2026-11-26): the task camera's ``up`` is +z (it was +y, so its images were turned 90
degrees: the lobe's thin edge pointed sideways). Camera observations (RGB, depth,
segmentation) show the lobe upright, its thin edge at the bottom; state and point-cloud
observations, dynamics, rewards and success are v1's, so state-observation results
and policies of v1 hold for v2 (stored results say "renamed").

v1 (retired 2026-11-26): v2's task, its camera turned 90 degrees about its axis;
unchanged since 2026-11-25 15:38 UTC, when it was still registered as v0: fold the lobe back about its base (up to 1.2 rad scripted)
to a target beneath its base third; the underside stuck 0-40 mm out from the base,
drawn per episode; jaws holding their 6 x 40 mm footprint; a 10 mm mesh refined to
2.5 mm at the jaws, stepped by the quasi-Newton solver; difficulty 1 (hold 2 s) by
default. Registered with ``max_episode_steps`` 100.

v0 (retired 2026-11-26): named several tasks over time: a 16 mm lobe clamped over its
thick third without gravity (explicit sub-steps); since the convergence redesign a base
hinge, line grasp, gravity on a support plane on a 7 mm mesh; since 2026-11-24
difficulty 1, the quasi-Newton solver, then the 6 x 40 mm jaw footprint on an 8 mm / 2.5
mm mesh and a lift of the thin edge (target at x -35..-10 mm); since 2026-11-25 15:38
the v1 task. ``FORMER_TASK`` restores the lift's target and free underside. A result
quoted for v0 is on the task of its date (docs/benchmarks/index.md says which).
"""

from __future__ import annotations

from .retraction_env import RetractionEnv, RetractionVectorEnv
from .spec import SpecError
from .scene import (AdhesionSpec, CameraSpec, FoldSpec, GripperSpec, PhysicsSpec, RegionSpec, Scene, SupportSpec,
                    TargetSpec, TissueSpec)

DEFAULT_MESH_SIZE = 0.010  # m: element size away from the jaws
DEFAULT_JAW_SIZE = 0.0025  # m: element size around the jaws
BASE_X = 0.065  # m: the lobe is cut off here (its base) and attached along the base's bottom edge
#: m: the jaws hold the lobe along this segment across its top face near the thin edge,
#: imprinted on the mesh, so that it is the same line of tissue at any mesh size
GRASP_LINE = ((-0.055, -0.02, 0.035 - 0.25 * 0.055), (-0.055, 0.02, 0.035 - 0.25 * 0.055))
HINGE = (BASE_X, 0.0)  # m: (x, z) of the line the lobe is lifted about
TIP_X = -0.08  # m: the lobe's thin edge (the tip of its half-ellipsoid), on every mesh
EDGE_BAND = 0.012  # m: surface vertices this close to the thin edge (in x) measure the lift


def _top_z(x: float) -> float:
    """Height (m) of the lobe's flat top face (the cut plane) at ``x`` (m)."""
    return 0.035 + 0.25 * x


#: m: the jaws' footprint for ``grasp="patch"``: 6 mm along x, centred on the grasp line
JAW_WIDTH = 0.006


#: the lobe's flat underside (a scene region: it rests on the support at z = 0), stuck to
#: the support over a width drawn per episode, 0-40 mm out from the base (the default)
UNDERSIDE = {"low": [None, None, 0.0], "high": [None, None, 0.0], "tolerance": 1e-6}
ADHESION_WIDTH = (0.0, 0.04)  # m
#: per-episode variation that is not a default (changes to the scene; docs/studies/envs.md): 20 mm
#: jaws (the middle half of the 40 mm footprint, where they close); with the default's adhesion
JAWS_AND_ADHESION = {"gripper": {"jaw_length": 0.02},
                     "adhesion": {"region": UNDERSIDE, "width": list(ADHESION_WIDTH)}}
#: m: the region of the target's centre, beneath the lobe's base third (the default since
#: 2026-11-25; it was x -35..-10 mm, behind the thin edge, exposed by a 2 cm lift)
TARGET_LOW, TARGET_HIGH = (0.03, -0.02, -0.023), (0.045, 0.02, -0.023)
#: the task before 2026-11-25 (changes to the default scene): the target behind the thin edge,
#: exposed by lifting it 2 cm, and the underside free (a seed draws the same target place,
#: stiffness and gripper start as then: the adhesion width is drawn after them)
FORMER_TASK = {"target": {"low": [-0.035, -0.02, -0.023], "high": [-0.01, 0.02, -0.023]}, "adhesion": None}


def organ_scene(mesh_size: float = DEFAULT_MESH_SIZE, edge_size: float | None = None, grasp: str = "patch",
                jaw_size: float | None = DEFAULT_JAW_SIZE) -> Scene:
    """The liver-lobe scene meshed at ``mesh_size`` metres.

    ``edge_size`` (m): finer elements near the thin edge (see
    :func:`heml_gym.organs.liver_lobe_mesh`); ``jaw_size`` (m): finer elements only around
    the jaws (the box within 5 mm of the grasp line in x, 25 mm of the lobe's midline in y,
    above z = 10 mm; growing to ``mesh_size`` over 6 mm; ``None``: a uniform mesh).
    ``grasp``: ``"patch"`` (the default) holds the jaws' footprint, a ``JAW_WIDTH`` x 40 mm
    rectangle of the top face centred on the grasp line (its edges imprinted on the mesh),
    so that the held tissue cannot turn about the line; ``"line"`` holds only the 40 mm
    grasp line. A line held in 3-D elasticity has no
    fine-mesh limit (the tissue next to it grows ever more compliant as the mesh refines);
    a patch does (docs/studies/scene_convergence.md, "Line and patch grasps").
    """
    if grasp not in ("line", "patch"):
        raise ValueError(f"grasp must be 'line' or 'patch', got {grasp!r}")
    if jaw_size is not None and not (isinstance(jaw_size, (int, float)) and 0 < jaw_size < mesh_size):
        raise ValueError(f"jaw_size must be a length in metres between 0 and mesh_size ({mesh_size}), "
                         f"got {jaw_size!r}")
    (gx, y0, _), (_, y1, _) = GRASP_LINE
    lines = [GRASP_LINE]
    grasp_region = RegionSpec(segment=GRASP_LINE)
    if grasp == "patch":
        x0, x1 = gx - JAW_WIDTH / 2, gx + JAW_WIDTH / 2
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        lines = [((xa, ya, _top_z(xa)), (xb, yb, _top_z(xb)))
                 for (xa, ya), (xb, yb) in zip(corners, corners[1:] + corners[:1])]
        grasp_region = RegionSpec(low=(x0, y0, _top_z(x0) - 0.002), high=(x1, y1, None), surface=True,
                                  tolerance=1e-6)
    options = {"lines": [list(map(list, line)) for line in lines], "base_x": BASE_X}
    if edge_size is not None:
        options["edge_size"] = edge_size
    if jaw_size is not None:
        options["refine"] = [[[gx - 0.005, y0 - 0.005, 0.01], [gx + 0.005, y1 + 0.005, None], jaw_size, 0.006]]
    return Scene(
        name="OrganRetraction",
        tissue=TissueSpec(kind="organ", organ="liver_lobe", mesh_size=mesh_size, organ_options=options),
        physics=PhysicsSpec(material="NeoHookean", young_modulus=(4e3, 8e3), poisson=0.45, density=1060.0,
                            damping=5.0, gravity=(0.0, 0.0, -9.81), field="heml", integrator="quasi_newton",
                            max_dt=0.05, newton_tol=3e-3, max_newton=100, safety=0.5),
        attachment=RegionSpec(low=(BASE_X, None, 0.0), high=(BASE_X, None, 0.0)),
        grasp=grasp_region,
        tracked=RegionSpec(points=[(TIP_X, -0.05, 0.02), (TIP_X, 0.0, 0.02), (TIP_X, 0.05, 0.02),
                                   (0.0, 0.0, 0.0443)], surface=True),
        fold=FoldSpec(hinge=HINGE, direction=-1.0, angle=0.6,
                      edge=RegionSpec(high=(TIP_X + EDGE_BAND - 1e-7, None, None), surface=True, tolerance=0.0)),
        target=TargetSpec(low=TARGET_LOW, high=TARGET_HIGH, radius=0.008),
        gripper=GripperSpec(start_low=(-0.058, -0.01, 0.024), start_high=(-0.052, 0.01, 0.027),
                            workspace_low=(-0.15, -0.10, 0.0), workspace_high=(0.10, 0.10, 0.20)),
        camera=CameraSpec(eye=(-0.17, 0.0, 0.12), up=(0.0, 0.0, 1.0)),  # upright: the support below
        support=SupportSpec(kind="plane", normal=(0.0, 0.0, 1.0), offset=0.0),
        strain_gauge=0.015,
        adhesion=AdhesionSpec(region=RegionSpec(low=(None, None, 0.0), high=(None, None, 0.0), tolerance=1e-6),
                              width=ADHESION_WIDTH),  # UNDERSIDE, as a spec (tuples, as a loaded scene has)
    )


def _check_mesh_size(mesh_size, scene) -> None:
    """``mesh_size`` on the default scene must stay above its element size at the jaws."""
    if (scene is None and isinstance(mesh_size, (int, float)) and not isinstance(mesh_size, bool)
            and 0 < mesh_size <= DEFAULT_JAW_SIZE):
        raise SpecError(f"mesh_size: the default lobe is refined to {DEFAULT_JAW_SIZE} m at the jaws, so mesh_size "
                        f"must be above that, got {mesh_size}; for a finer lobe pass "
                        f"scene=organ_scene({mesh_size}, jaw_size=None) (uniform) or a smaller jaw_size")


class OrganRetractionEnv(RetractionEnv):
    __doc__ = __doc__
    default_scene = staticmethod(organ_scene)

    def __init__(self, obs_mode="state", render_mode=None, settings=None, weights=None, mesh_size=None,
                 scene=None, physics=None, camera=None, difficulty=1):
        _check_mesh_size(mesh_size, scene)
        super().__init__(obs_mode, render_mode, settings, weights, scene=scene, physics=physics, camera=camera,
                         difficulty=difficulty, mesh_size=mesh_size)


class OrganRetractionVectorEnv(RetractionVectorEnv):
    """``num_envs`` OrganRetraction scenes in one batched Numba call (see OrganRetractionEnv)."""

    default_scene = staticmethod(organ_scene)

    def __init__(self, num_envs=4, obs_mode="state", settings=None, weights=None, max_episode_steps=None,
                 render_mode=None, mesh_size=None, scene=None, physics=None, camera=None, difficulty=1):
        _check_mesh_size(mesh_size, scene)
        super().__init__(num_envs, obs_mode, settings, weights, max_episode_steps, render_mode, scene=scene,
                         physics=physics, camera=camera, difficulty=difficulty, mesh_size=mesh_size)
