"""Record rollouts of a retraction environment to a rerun recording (``.rrd`` file or viewer).

:func:`record_rollouts` plays seeded episodes of a policy in one
:class:`~heml_gym.envs.retraction_env.RetractionEnv` and logs every frame to its own
:class:`rerun.RecordingStream` (never the global one, so several recordings in one
process do not mix). Needs ``pip install 'heml-gym[viz]'`` (rerun-sdk >= 0.41).

Units: positions and lengths in metres (m), time in seconds (s), forces in newtons (N);
strain and exposure are dimensionless (exposure is a fraction in 0..1).

Frames
------
A *frame* is the state after ``reset`` (the reset frame of an episode) or after an env
step, so an episode of ``n`` steps gives ``n + 1`` frames and a recording of episodes
with lengths ``n_k`` gives ``sum(n_k + 1)`` frames (``summary["frames"]``).

Timelines
---------
``step``          sequence: frame index over the whole recording (0, 1, 2, ...; reset frames
                  included), so episodes lie one after another.
``sim_time``      duration (s): ``step * control_dt``, simulated time with episodes laid
                  end to end, each reset frame one ``control_dt`` after the previous
                  episode's last frame (the timeline the blueprint plays).
``episode``       sequence: episode index (0-based).
``episode_step``  sequence: env steps since the episode's reset (0 on the reset frame).
                  Simulated time within the episode is ``episode_step * control_dt``;
                  switch the time panel to it to lay the episodes' plot lines over each
                  other (each episode has its own series, see below).

Entities
--------
``world``                     static view coordinates (right-handed, z up).
``world/tissue``              :class:`rerun.Mesh3D`: the tissue surface, flat-shaded (each
                              surface triangle with its own three vertices and its face
                              normal; m), coloured by the *gauge strain* (the strain
                              ``info["max_strain"]`` is the largest of, see
                              :mod:`heml_gym.envs.strain_gauges`): a vertex shows the largest
                              strain of the gauge segments at its nearest gauge point (and
                              of every gauge point whose nearest surface vertex it is), so
                              the reddest vertex shows the plotted max gauge strain; pale
                              pink (``palette.TISSUE``) at 0, linearly to red
                              (``palette.STRAINED``) at ``settings.damage_strain`` and above
                              (:func:`strain_colours`; the ``legend/strain_scale`` colour
                              bar). The triangles are logged once, statically.
``world/attachment``          static :class:`rerun.Points3D`: the fixed tissue vertices.
``world/support``             static :class:`rerun.Mesh3D`: what the tissue rests on,
                              translucent (``SUPPORT_ALPHA``) so that the target below it
                              stays visible.
``world/critical``            static :class:`rerun.Capsules3D`: a scene's critical structure
                              (``Scene.critical``) and, translucent, its margin.
``world/gripper``             :class:`rerun.Boxes3D`: the jaws, grey when open, green when
                              closed on tissue (no label: the state is in ``status``);
                              jaws that roll turned along their axis.
``world/paddle``              :class:`rerun.Boxes3D`: a paddle retractor's blade, turned by
                              its tilt (scenes with paddles).
``world/shaft``               :class:`rerun.Capsules3D`: each shaft that touches tissue (a
                              grasper on a port with ``shaft_radius``), from its end behind
                              the jaws to its port.
``world/held``                :class:`rerun.Points3D`: the tissue vertices the jaws hold
                              (empty when none).
``world/grasp_force``         :class:`rerun.Arrows3D`: the force of the tissue on the
                              gripper, drawn with its tip on the top of the jaws (so that
                              it stays above the tissue it pulls into), labelled with its
                              magnitude; the tissue's weight draws an arrow
                              ``FORCE_ARROW_FRACTION`` of the scene's size long.
``world/target``              :class:`rerun.Points3D`: the target (tumour) as a sphere of
                              the target radius, labelled with its exposure.
``world/camera``              the task camera in the 3D view: :class:`rerun.Transform3D`
                              (its pose) and :class:`rerun.Pinhole` (``CAMERA_SIZE``
                              pixels), per episode; no image under it (images are 2D only).
``camera/rgb``                :class:`rerun.Image`: the task camera's colour image.
``camera/depth``              :class:`rerun.DepthImage` (m along the optical axis, ``far``
                              = 10 m where nothing is seen), in a 2D view of its own,
                              coloured over the depth range of the first frame.
``camera/segmentation``       :class:`rerun.SegmentationImage` with a static
                              :class:`rerun.AnnotationContext` (``SEGMENT_COLOURS``: the
                              labels of :data:`heml_gym.envs.camera.SEGMENT_IDS`).
``status``                    :class:`rerun.TextDocument` (markdown), every frame: episode,
                              step, success, exposure against its threshold, max gauge
                              strain against the damage strain, the damage so far,
                              hold timer against
                              ``settings.hold_time``, gripper, grasp force, action, reward.
``legend``                    static :class:`rerun.TextDocument`: what the colours mean;
                              ``legend/strain_scale``: the strain colour bar (an image,
                              strain 0 on the left to ``damage_strain`` on the right).
``plots/<group>/<series>/ep<k>``  :class:`rerun.Scalars`, one series per episode ``k`` (so
                              lines are not joined across resets and episodes can be laid
                              over each other on ``episode_step``), see ``SERIES``:
                              ``exposure/exposure``, ``strain/max_strain``,
                              ``success/hold_time`` (s), ``success/success`` (0/1),
                              ``grasp_force/grasp_force`` (N), ``harm/damage`` (the
                              episode's ``info["damage"]`` so far, strain x s) on every
                              frame; ``harm/cost`` (the step's ``info["cost"]``),
                              ``action/<move_x|move_y|move_z|grip>`` (the action the
                              policy returned for the previous frame's observation, as
                              passed to ``env.step``), ``reward/total`` and
                              ``reward/terms/<term>`` (every reward term of the step's
                              ``info``) on step frames only.
``plots/<group>/<threshold>`` constant lines, every frame: ``exposure/success_threshold``
                              (``settings.success_exposure``), ``strain/damage_threshold``
                              (``settings.damage_strain``), ``strain/safe_threshold``
                              (``settings.safe_strain``: harm counts above it),
                              ``success/hold_required``
                              (``settings.hold_time``).
``plots/episode_start``       a marker (value 0) at each episode's reset frame, shown in
                              every plot; ``plots/success/outcome`` one marker at each
                              episode's last frame: 1 success, 0 time-out, -1 torn or
                              diverged.
``log/episodes``              :class:`rerun.TextLog`: one line at each episode's start (seed,
                              Young's modulus) and one at its end (outcome, steps, return).

The blueprint (``BLUEPRINT_VIEWS`` names its views): the 3D scene from a fixed eye that
frames the whole workspace, the task camera's colour, depth and segmentation images side by
side below it; on the right the status text and the strain colour bar, then the plots of
exposure, success (hold timer), strain and, in tabs, grasp force, tissue harm, actions,
rewards and the episode log. Plots have no legends (their titles name the series and colours), the same
height, and linked time axes; the time panel is collapsed and plays ``sim_time`` at real
time.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from heml_gym.envs.camera import SEGMENT_IDS
from heml_gym.envs.core import RewardWeights
from heml_gym.envs.palette import (ATTACHMENT, FORCE, HELD, HOOK_OFF, HOOK_ON, JAW_HALF_SIZE, JAW_OFFSET,
                                   JAWS_CLOSED, JAWS_OPEN, PADDLE, RELEASED, SHAFT, STRAINED, STUCK, SUPPORT, TARGET, TISSUE)

__all__ = ["ACTION_NAMES", "BLUEPRINT_VIEWS", "CAMERA_SIZE", "FORCE_ARROW_FRACTION", "OUTCOME_VALUES", "REWARD_TERMS",
           "SEGMENT_COLOURS", "SERIES", "THRESHOLDS", "record_rollouts", "series_entity", "strain_colours"]

#: the grasp-force arrow is this fraction of the scene's size long at the tissue's weight
FORCE_ARROW_FRACTION = 0.3
#: opacity (0..255) of the support in the 3D view: translucent, so the target below shows
SUPPORT_ALPHA = 70
#: reward terms of the task (``info["reward_<term>"]``)
REWARD_TERMS = tuple(f.name for f in fields(RewardWeights))
#: the action's components (``env.step``'s 4-vector: gripper velocity x, y, z; grip command)
ACTION_NAMES = ("move_x", "move_y", "move_z", "grip")
#: series logged per episode: name -> (entity base, logged on every frame (True) or on step
#: frames only (False)); episode ``k`` logs to :func:`series_entity` (``<base>/ep<k>``)
SERIES = {
    "exposure": ("plots/exposure/exposure", True),
    "goal_distance": ("plots/exposure/goal_distance", True),  # (m; a goal task's, in the exposure view)
    "max_strain": ("plots/strain/max_strain", True),
    "hold_time": ("plots/success/hold_time", True),
    "is_success": ("plots/success/success", True),
    "grasp_force": ("plots/grasp_force/grasp_force", True),
    "damage": ("plots/harm/damage", True),
    "cost": ("plots/harm/cost", False),
    **{f"action_{a}": (f"plots/action/{a}", False) for a in ACTION_NAMES},
    "reward": ("plots/reward/total", False),
    **{f"reward_{t}": (f"plots/reward/terms/{t}", False) for t in REWARD_TERMS},
}
#: constant lines (every frame, one series for the whole recording): entity -> the
#: :class:`~heml_gym.envs.core.TaskSettings` field it shows
THRESHOLDS = {
    "plots/exposure/success_threshold": "success_exposure",
    "plots/strain/damage_threshold": "damage_strain",
    "plots/strain/safe_threshold": "safe_strain",
    "plots/success/hold_required": "hold_time",
}
#: size (height, width, pixels) of the task camera's images in the recording
CAMERA_SIZE = (240, 320)
#: outcome of an episode as the ``plots/success/outcome`` marker at its last frame
OUTCOME_VALUES = {"success": 1.0, "truncated": 0.0, "unfinished": 0.0, "terminated": -0.5, "torn": -1.0,
                  "diverged": -1.0}
#: colour of each segmentation label in ``camera/segmentation``
SEGMENT_COLOURS = {"background": (0, 0, 0), "tissue": tuple(TISSUE), "target": tuple(TARGET),
                   "instrument": tuple(JAWS_CLOSED), "support": (70, 90, 160)}
#: colours of the plotted series (by entity base)
SERIES_COLOURS = {
    "plots/exposure/exposure": TARGET, "plots/strain/max_strain": STRAINED, "plots/success/hold_time": HELD,
    "plots/success/success": JAWS_CLOSED, "plots/grasp_force/grasp_force": FORCE, "plots/reward/total": (255, 255, 255),
    "plots/action/move_x": (230, 80, 80), "plots/action/move_y": (80, 200, 80), "plots/action/move_z": (90, 140, 255),
    "plots/action/grip": (200, 200, 200),
    "plots/exposure/success_threshold": JAWS_CLOSED, "plots/strain/damage_threshold": (150, 150, 150),
    "plots/success/hold_required": (150, 150, 150), "plots/strain/safe_threshold": (240, 200, 80),
    "plots/harm/damage": (255, 140, 40), "plots/harm/cost": STRAINED,
}
#: the blueprint's views: name -> origin
BLUEPRINT_VIEWS = {
    "scene": "world",
    "camera RGB": "camera/rgb",
    "camera depth": "camera/depth",
    "camera segmentation": "camera/segmentation",
    "status": "status",
    "strain colours": "legend/strain_scale",
    "colour legend": "legend",
    "exposure (yellow), success threshold (green)": "plots/exposure",
    "hold timer s (blue) vs needed (grey), success (green)": "plots/success",
    "max gauge strain (red), damage strain (grey), safe strain (amber)": "plots/strain",
    "tissue harm: damage so far (orange), this step's cost (red), strain x s": "plots/harm",
    "grasp force (N)": "plots/grasp_force",
    "action: move x red, y green, z blue; grip grey": "plots/action",
    "reward: total (white) and terms": "plots/reward",
    "episode log": "log",
}


def series_entity(base: str, episode: int) -> str:
    """The entity of series ``base`` (a ``SERIES`` entity base) in episode ``episode``."""
    return f"{base}/ep{episode}"


def strain_colours(strain: np.ndarray, damage_strain: float) -> np.ndarray:
    """``(n, 3)`` uint8: pale pink (``TISSUE``) at strain 0, linearly to red (``STRAINED``)
    at ``damage_strain`` and above (NaN: red)."""
    s = np.clip(np.nan_to_num(np.asarray(strain, dtype=np.float64) / damage_strain, nan=1.0), 0.0, 1.0)
    return np.rint((1.0 - s)[:, None] * TISSUE + s[:, None] * STRAINED).astype(np.uint8)


def _import_rerun():
    try:
        import rerun as rr
        import rerun.blueprint as rrb
    except ImportError as exc:  # tests/test_recording.py hides rerun to check this
        raise ImportError(
            "recording rollouts needs the rerun SDK (rerun-sdk >= 0.41); install it with "
            "pip install 'heml-gym[viz]'"
        ) from exc
    return rr, rrb


def _check_writable(path: Path) -> None:
    """Raise a clear ``OSError`` if ``path`` cannot be written (before anything is logged)."""
    if path.is_dir():
        raise IsADirectoryError(f"cannot write the rerun recording to {str(path)!r}: it is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(
            f"cannot write the rerun recording to {str(path)!r}: directory {str(parent)!r} does not exist")
    try:
        with open(path, "ab"):
            pass
    except OSError as exc:
        raise type(exc)(exc.errno, f"cannot write the rerun recording to {str(path)!r}: {exc.strerror}",
                        str(path)) from exc


def _blueprint(rrb, geometry):
    """The layout (see the module docstring): 3D scene (seen from the task camera's side)
    over the camera images on the left;
    status, colour bar and plots (linked time axes, no legends) on the right."""
    low, high = (np.asarray(v, dtype=np.float64) for v in geometry.workspace)
    centre = 0.5 * (low + high)
    extent = float(np.linalg.norm(high - low))
    # from the task camera's side (what it must see, the 3D view shows too): its azimuth
    # turned 30 degrees aside (a camera looking straight down: from -y, +x) and its
    # elevation kept between 25 and 50 degrees, so the tissue is seen obliquely
    towards_camera = np.asarray(geometry.camera, dtype=np.float64) - centre
    horizontal = float(np.hypot(towards_camera[0], towards_camera[1]))
    if horizontal < 0.2 * abs(towards_camera[2]):
        azimuth = np.arctan2(-0.75, 0.55)
    else:
        azimuth = np.arctan2(towards_camera[1], towards_camera[0]) - np.radians(30.0)
    elevation = np.clip(np.arctan2(towards_camera[2], horizontal), np.radians(25.0), np.radians(50.0))
    direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                          np.sin(elevation)])
    eye = centre + 1.0 * extent * direction
    names = {origin: name for name, origin in BLUEPRINT_VIEWS.items()}
    linked = rrb.TimeAxis(link=rrb.components.LinkAxis.LinkToGlobal)
    no_legend = rrb.PlotLegend(visible=False)

    def plot(origin):
        return rrb.TimeSeriesView(origin=origin, name=names[origin], axis_x=linked, plot_legend=no_legend,
                                  contents=["$origin/**", "/plots/episode_start"])

    images = [rrb.Spatial2DView(origin=o, name=names[o]) for o in ("camera/rgb", "camera/depth",
                                                                    "camera/segmentation")]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name=names["world"],
                                  eye_controls=rrb.EyeControls3D(position=eye, look_target=centre,
                                                                 eye_up=(0.0, 0.0, 1.0))),
                rrb.Horizontal(*images),
                row_shares=[5, 2],
            ),
            rrb.Vertical(
                rrb.Horizontal(rrb.TextDocumentView(origin="status", name=names["status"]),
                               rrb.Spatial2DView(origin="legend/strain_scale", name=names["legend/strain_scale"]),
                               column_shares=[3, 2]),
                plot("plots/exposure"),
                plot("plots/success"),
                plot("plots/strain"),
                rrb.Tabs(plot("plots/grasp_force"), plot("plots/harm"), plot("plots/action"), plot("plots/reward"),
                         rrb.TextLogView(origin="log", name=names["log"]),
                         rrb.TextDocumentView(origin="legend", name=names["legend"])),
                row_shares=[4, 3, 3, 3, 3],
            ),
            column_shares=[11, 9],
        ),
        rrb.TimePanel(timeline="sim_time", playback_speed=1.0, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )



def _quaternion(rotation: np.ndarray) -> list[float]:
    """The unit quaternion ``[x, y, z, w]`` of a ``(3, 3)`` rotation matrix."""
    r = np.asarray(rotation, dtype=np.float64)
    w = 0.5 * np.sqrt(max(0.0, 1.0 + np.trace(r)))
    x = 0.5 * np.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) * np.sign(r[2, 1] - r[1, 2] or 1.0)
    y = 0.5 * np.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) * np.sign(r[0, 2] - r[2, 0] or 1.0)
    z = 0.5 * np.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) * np.sign(r[1, 0] - r[0, 1] or 1.0)
    q = np.array([x, y, z, w])
    return (q / np.linalg.norm(q)).tolist()


def _turn_z_to(rr, direction):
    """The ``rerun.RotationAxisAngle`` that takes +z onto ``direction`` (a capsule's axis)."""
    axis = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    turn = np.cross([0.0, 0.0, 1.0], axis)
    return rr.RotationAxisAngle(axis=turn if np.linalg.norm(turn) > 1e-12 else [1.0, 0.0, 0.0],
                                radians=float(np.arccos(np.clip(axis[2], -1.0, 1.0))))

class _StrainField:
    """Per surface vertex, the gauge strain of :class:`~heml_gym.envs.strain_gauges.StrainGauges`
    ``gauges``: a gauge point's strain is the largest of its segments'; a vertex shows its
    nearest gauge point's (at rest) and that of every gauge point whose nearest surface
    vertex it is, so the largest over the surface equals the gauges' largest strain."""

    def __init__(self, gauges, rest_vertices: np.ndarray, surface_faces: np.ndarray):
        from scipy.spatial import cKDTree

        self.gauges = gauges
        self.n_vertices = len(rest_vertices)
        surface = np.unique(np.asarray(surface_faces).ravel())
        self.surface = surface
        _, self.nearest_point = cKDTree(gauges.points).query(rest_vertices[surface])
        _, nearest_vertex = cKDTree(rest_vertices[surface]).query(gauges.points)
        self.owner = surface[nearest_vertex]  # (P,) the surface vertex each gauge point reports to

    def __call__(self, x: np.ndarray) -> np.ndarray:
        g = self.gauges
        p = g.positions(x)
        seg = np.abs(np.linalg.norm(p[g.pairs[:, 1]] - p[g.pairs[:, 0]], axis=1) / g.rest_length - 1.0)
        seg = np.nan_to_num(seg, nan=np.inf)
        point = np.zeros(len(g.points))
        np.maximum.at(point, g.pairs[:, 0], seg)
        np.maximum.at(point, g.pairs[:, 1], seg)
        out = np.zeros(self.n_vertices)
        out[self.surface] = point[self.nearest_point]
        np.maximum.at(out, self.owner, point)
        return out


class _SceneLogger:
    """Logs one scene of a retraction env (its public geometry, snapshots and camera view)."""

    def __init__(self, rr, rec, env):
        self.rr, self.rec, self.env = rr, rec, env
        geometry = env.geometry
        self.geometry = geometry
        self.settings = geometry.settings
        self.faces = np.asarray(geometry.surface_faces, dtype=np.int64)
        self.strain = _StrainField(env.task.gauges, np.asarray(geometry.rest_vertices), self.faces)
        extent = float(np.linalg.norm(np.ptp(geometry.rest_vertices, axis=0)))
        #: m of arrow per N: the tissue's weight draws FORCE_ARROW_FRACTION of the scene's size
        self.force_scale = FORCE_ARROW_FRACTION * extent / max(geometry.weight, 1e-9)
        self.depth_range = None

    def log_static(self) -> None:
        rr, rec, geo, st = self.rr, self.rec, self.geometry, self.settings
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        # flat-shaded: every triangle its own three vertices, so a flat slab does not look creased
        rec.log("world/tissue", rr.Mesh3D.from_fields(
            triangle_indices=np.arange(3 * len(self.faces), dtype=np.uint32).reshape(-1, 3)), static=True)
        rec.log("world/attachment", rr.Points3D(geo.rest_vertices[geo.fixed], radii=0.0015,
                                                colors=ATTACHMENT), static=True)
        sv, sf = geo.support_mesh
        if len(sf):
            rec.log("world/support", rr.Mesh3D(vertex_positions=sv, triangle_indices=sf,
                                               albedo_factor=[*SUPPORT, SUPPORT_ALPHA]), static=True)
        critical = getattr(self.env.task.scene.spec, "critical", None)
        if critical is not None:  # a structure no energised instrument may come near (drawn with its margin)
            start, end = np.asarray(critical.start, dtype=np.float64), np.asarray(critical.end, dtype=np.float64)
            rotation = _turn_z_to(rr, end - start)
            rec.log("world/critical", rr.Capsules3D(
                lengths=[float(np.linalg.norm(end - start))] * 2, radii=[critical.radius, critical.radius + critical.margin],
                translations=[start, start], rotation_axis_angles=[rotation, rotation],
                colors=[[60, 200, 90], [60, 200, 90, 60]], labels=["critical structure", "its margin"]), static=True)
        rec.log("camera/segmentation", rr.AnnotationContext(
            [rr.AnnotationInfo(id=SEGMENT_IDS[name], label=name, color=colour)
             for name, colour in SEGMENT_COLOURS.items()]), static=True)
        for entity, field in THRESHOLDS.items():
            rec.log(entity, rr.SeriesLines(names=f"{field} ({getattr(st, field):g})",
                                           colors=SERIES_COLOURS[entity], widths=1.0), static=True)
        rec.log("plots/episode_start", rr.SeriesPoints(names="episode start", markers="right", marker_sizes=5.0,
                                                       colors=[200, 200, 255]), static=True)
        rec.log("plots/success/outcome", rr.SeriesPoints(names="outcome (1 success, -1 torn / diverged)",
                                                         markers="diamond", marker_sizes=6.0,
                                                         colors=[255, 255, 255]), static=True)
        rec.log("legend", rr.TextDocument(self._legend(), media_type=rr.MediaType.MARKDOWN), static=True)
        # the colour bar: strain 0 (left) to damage_strain (right), labelled below
        width, height = 200, 24
        bar = strain_colours(np.linspace(0.0, st.damage_strain, width), st.damage_strain)
        rec.log("legend/strain_scale", rr.Image(np.repeat(bar[None], height, axis=0)), static=True)
        ticks = np.array([0.0, 0.5, 1.0])
        rec.log("legend/strain_scale/ticks", rr.Points2D(
            np.stack([ticks * (width - 1), np.full(3, height + 6.0)], axis=1), radii=1.0,
            colors=[200, 200, 200],
            labels=[f"{v * st.damage_strain:g}" + (" damage" if v == 1.0 else "") for v in ticks]), static=True)

    def _depth_range(self, view: dict) -> tuple[float, float]:
        """One depth colour scale for the recording (m): from the nearest corner of the
        workspace (where the gripper and lifted tissue can be) to the farthest of those
        corners and of what the first frame sees."""
        low, high = (np.asarray(v, dtype=np.float64) for v in self.geometry.workspace)
        corners = np.array([[(low, high)[i][0], (low, high)[j][1], (low, high)[k][2]]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        z = (corners - view["eye"]) @ view["rotation"][2]
        depth = view["depth"]
        seen = depth[depth < depth.max()]
        near = float(np.clip(z.min(), 1e-3, None))
        far = max(float(z.max()), float(seen.max()) if seen.size else near + 1e-3)
        return near, far

    def _legend(self) -> str:
        st = self.settings
        return (f"Tissue colour: gauge strain, pale pink 0 to red at the damage strain "
                f"{st.damage_strain:g} (the red line of the strain plot). Yellow sphere: target; "
                f"green jaws: closed, grey: open; blue dots: held tissue; orange arrow: grasp force; "
                f"translucent: support.")

    def start_episode(self, k: int) -> None:
        """Static styles of episode ``k``'s series."""
        rr, rec = self.rr, self.rec
        for name, (base, _) in SERIES.items():
            colour = SERIES_COLOURS.get(base)
            label = f"{name} (episode {k})"
            style = rr.SeriesLines(names=label) if colour is None else rr.SeriesLines(names=label, colors=colour)
            rec.log(series_entity(base, k), style, static=True)
        rec.log("plots/episode_start", rr.Scalars(0.0))

    def log_camera_pose(self, view: dict) -> None:
        """The task camera as a pinhole at its pose (the pose can change per episode)."""
        rr, rec = self.rr, self.rec
        h, w = view["rgb"].shape[:2]
        rec.log("world/camera", rr.Transform3D(translation=view["eye"], mat3x3=view["rotation"].T))
        rec.log("world/camera", rr.Pinhole(focal_length=float(view["focal"]), width=w, height=h,
                                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.03))

    def vertex_colours(self, x: np.ndarray) -> np.ndarray:
        """Per-vertex colour: the gauge strain at the vertex (:class:`_StrainField`)."""
        return strain_colours(self.strain(x), self.settings.damage_strain)

    def log_frame(self, k: int, snap, info: dict[str, Any], view: dict, action=None, reward=None,
                  ret: float = 0.0, episode_step: int = 0) -> None:
        rr, rec, geo, st = self.rr, self.rec, self.geometry, self.settings
        x = np.nan_to_num(np.asarray(snap.positions, dtype=np.float64))
        tri = x[self.faces]  # (f, 3, 3): unshared vertices, flat normals
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
        colours = self.vertex_colours(x)[self.faces].reshape(-1, 3)
        rec.log("world/tissue", rr.Mesh3D.from_fields(vertex_positions=tri.reshape(-1, 3),
                                                      vertex_normals=np.repeat(normals, 3, axis=0),
                                                      vertex_colors=colours))
        grippers = np.asarray(snap.grippers, dtype=np.float64).reshape(-1, 3)  # every instrument's place
        paddles = [k for k, g in enumerate(self.env.task.instruments) if g.kind == "paddle"]
        jaws = [k for k in range(len(grippers)) if k not in paddles]
        centres, halves, turns = grippers[jaws] + np.array(JAW_OFFSET), [np.array(JAW_HALF_SIZE)] * len(jaws), []
        for j, which in enumerate(jaws):  # jaws that roll: along their axis, up the shaft from the grasp point
            g, frame = self.env.task.instruments[which], np.eye(3)
            if getattr(g, "roll_speed", None) is not None:
                box_centres, halves[j], box_frames = g.jaw_boxes()
                centres[j], frame = box_centres[0], box_frames[0]
            turns.append(rr.Quaternion(xyzw=_quaternion(frame)))
        rec.log("world/gripper", rr.Boxes3D(centers=centres, half_sizes=halves, quaternions=turns,
                                            colors=[JAWS_CLOSED if snap.closed[k] else JAWS_OPEN for k in jaws],
                                            fill_mode="solid"))
        if paddles:  # each paddle's blade, turned by its tilt (about y)
            blades = [self.env.task.instruments[k] for k in paddles]
            rec.log("world/paddle", rr.Boxes3D(
                centers=grippers[paddles], half_sizes=[b.spec.half_extents for b in blades],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0.0, 1.0, 0.0], radians=float(b.tilt[0]))
                                      for b in blades], colors=[PADDLE] * len(blades), fill_mode="solid"))
        shafts = [(k, g) for k, g in enumerate(self.env.task.instruments) if getattr(g, "shaft_tool", None) is not None]
        if shafts:  # each shaft that touches tissue, from its end behind the jaws to its port
            ends = [g.port.shaft_ends(grippers[k])[0] for k, g in shafts]
            axes = [g.port.port - end for (_, g), end in zip(shafts, ends)]
            rec.log("world/shaft", rr.Capsules3D(
                lengths=[float(np.linalg.norm(a)) for a in axes], radii=[g.spec.shaft_radius for _, g in shafts],
                translations=ends, rotation_axis_angles=[_turn_z_to(rr, a) for a in axes],
                colors=[SHAFT] * len(shafts)))
        held = x[snap.held]
        rec.log("world/held", rr.Points3D(held.reshape(-1, 3), radii=0.002, colors=HELD))
        if len(snap.stuck) or len(snap.released):  # the adhesion: what remains, and what a hook freed
            rec.log("world/adhesion/stuck", rr.Points3D(x[snap.stuck].reshape(-1, 3), radii=0.0015, colors=STUCK))
            rec.log("world/adhesion/released", rr.Points3D(x[snap.released].reshape(-1, 3), radii=0.0015,
                                                             colors=RELEASED))
        if len(snap.hooks):
            rec.log("world/hook", rr.Points3D(np.asarray(snap.hooks).reshape(-1, 3), radii=0.003,
                                              colors=[HOOK_ON if on else HOOK_OFF for on in snap.energised]))
        forces = np.nan_to_num(np.asarray(snap.grasp_forces, dtype=np.float64)).reshape(-1, 3)
        vectors = forces * self.force_scale
        jaw_tops = grippers + np.array(JAW_OFFSET) + np.array([0.0, 0.0, JAW_HALF_SIZE[2]])
        rec.log("world/grasp_force", rr.Arrows3D(origins=jaw_tops - vectors, vectors=vectors,
                                                 colors=[FORCE] * len(forces),
                                                 labels=[f"{np.linalg.norm(f):.2f} N" for f in forces]))
        exposure = float(info["exposure"]) if "exposure" in info else None  # (a goal task has a goal instead)
        label = (f"target {exposure:.0%} exposed" if exposure is not None
                 else f"goal: marked point {float(info['goal_distance']) * 1e3:.1f} mm away")
        rec.log("world/target", rr.Points3D([snap.target], radii=float(geo.target_radius), colors=[TARGET],
                                            labels=[label]))
        rec.log("camera/rgb", rr.Image(view["rgb"]))
        if self.depth_range is None:
            self.depth_range = self._depth_range(view)
        rec.log("camera/depth", rr.DepthImage(view["depth"], meter=1.0, colormap="viridis",
                                              depth_range=self.depth_range))
        rec.log("camera/segmentation", rr.SegmentationImage(view["segmentation"]))
        # plots
        for entity, field in THRESHOLDS.items():
            rec.log(entity, rr.Scalars(float(getattr(st, field))))
        values = {"max_strain": float(info["max_strain"]), "hold_time": float(info.get("hold_time", 0.0)),
                  "is_success": float(bool(info["is_success"])), "grasp_force": float(info["grasp_force"]),
                  "damage": float(info["damage"])}
        if exposure is not None:
            values["exposure"] = exposure
        else:
            values["goal_distance"] = float(info["goal_distance"])
        if action is not None:
            values["cost"] = float(info["cost"])
            a = np.asarray(action, dtype=np.float64).reshape(-1)
            values.update({f"action_{n}": float(v) for n, v in zip(ACTION_NAMES, a)})  # (the first grasper's)
            values["reward"] = float(reward)
            values.update({f"reward_{t}": float(info.get(f"reward_{t}", 0.0)) for t in REWARD_TERMS})
        for name, value in values.items():
            rec.log(series_entity(SERIES[name][0], k), rr.Scalars(value))
        rec.log("status", rr.TextDocument(self._status(k, episode_step, snap, info, action, reward, ret),
                                          media_type=rr.MediaType.MARKDOWN))

    def _status(self, k, episode_step, snap, info, action, reward, ret) -> str:
        st = self.settings
        strain, hold = float(info["max_strain"]), float(info.get("hold_time", 0.0))

        def ok(good: bool) -> str:
            return "yes" if good else "no"

        lines = [
            (f"**episode {k}, step {episode_step}** ({episode_step * st.control_dt:.1f} s): "
             f"**success: {ok(bool(info['is_success']))}**"),
            self._progress_line(info, ok),
            f"- max gauge strain **{strain:.3f}** (needs < {st.damage_strain:g}: {ok(strain < st.damage_strain)})",
            (f"- tissue harm: damage **{float(info['damage']):.3f}** strain x s so far (strain above the "
             f"safe {st.safe_strain:g}, integrated over time)"),
        ]
        if "hold_time" in info:
            lines.append(f"- held **{hold:.1f} s** of {st.hold_time:g} s")
        closed = ", ".join("closed" if c else "open" for c in snap.closed)
        lines.append(f"- jaws {closed}, holding {len(snap.held)} vertices, force {float(info['grasp_force']):.2f} N")
        if action is not None:  # each instrument's entries by name (a grasper's 4, or 5 when its jaws roll; ...)
            a, parts, start = np.asarray(action, dtype=np.float64).reshape(-1), [], 0
            for instrument in [*self.env.task.instruments, *getattr(self.env.task, "hooks", [])]:
                names = instrument.ACTION
                parts.append(", ".join(f"{n} {v:+.2f}" for n, v in zip(names, a[start:start + len(names)])))
                start += len(names)
            lines.append(f"- action: {'; '.join(parts)}; reward {float(reward):+.3f}, return {ret:+.3f}")
        return "\n".join(lines)

    def _progress_line(self, info, ok) -> str:
        """The status line of the task's progress: the target's exposure, or a goal task's distance."""
        st = self.settings
        if "exposure" in info:
            e = float(info["exposure"])
            return f"- exposure **{e:.0%}** (needs >= {st.success_exposure:.0%}: {ok(e >= st.success_exposure)})"
        d, tol = float(info["goal_distance"]), st.goal_tolerance
        return f"- marked point **{d * 1e3:.1f} mm** from the goal (needs <= {tol * 1e3:g} mm: {ok(d <= tol)})"

    def log_outcome(self, outcome: str) -> None:
        self.rec.log("plots/success/outcome", self.rr.Scalars(OUTCOME_VALUES.get(outcome, 0.0)))


def _progress(info: dict[str, Any]) -> str:
    """The task's progress for the episode log: exposure, or a goal task's distance (mm)."""
    if "exposure" in info:
        return f"exposure {float(info['exposure']):.2f}"
    return f"goal distance {float(info['goal_distance']) * 1e3:.1f} mm"


def _outcome(info: dict[str, Any], terminated: bool, truncated: bool) -> str:
    if info.get("is_success"):
        return "success"
    if info.get("simulation_diverged"):
        return "diverged"
    if info.get("tissue_torn"):
        return "torn"
    if truncated:
        return "truncated"
    return "terminated" if terminated else "unfinished"


def record_rollouts(env, policy: Callable[[Any], Any], path: str | os.PathLike | None = None,
                    episodes: int = 1, seed: int = 0, spawn: bool = False,
                    app_id: str = "heml_gym") -> dict[str, Any]:
    """Play ``episodes`` seeded episodes of ``policy`` in ``env`` and log them to rerun.

    ``env``: one retraction env (a :class:`RetractionEnv`, possibly wrapped: its public
    ``geometry`` and ``snapshot()`` are what is logged). ``policy``: a callable
    ``obs -> action``; its ``reset()`` is called before each episode if it has one (wrap
    SB3 models, e.g. ``lambda obs: model.predict(obs, deterministic=True)[0]``).
    Episode ``k`` is reset with ``seed + k``. ``path``: save the recording to this
    ``.rrd`` file (a clear ``OSError`` is raised before logging if it cannot be written).
    ``spawn``: also open a rerun viewer and stream to it (never in headless runs). At least
    one of ``path`` and ``spawn`` must be given. ``app_id``: the rerun application id.

    Returns ``{"episodes", "frames", "steps", "episode_lengths", "returns",
    "mean_return", "outcomes", "successes", "success_rate", "final_exposure", "path",
    "application_id", "recording_id"}``: ``frames`` counts logged frames (one reset frame
    per episode plus one per step), ``path`` is the ``.rrd`` path as a string or None.
    See the module docstring for the entity layout, timelines and units (m, s, N).
    """
    rr, rrb = _import_rerun()
    episodes = int(episodes)
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if path is None and not spawn:
        raise ValueError("nothing to record to: give path= (an .rrd file) and/or spawn=True (a viewer)")
    from heml_gym.envs.retraction_env import RetractionEnv

    if not isinstance(env.unwrapped, RetractionEnv):
        raise TypeError(f"record_rollouts needs a single retraction env, got {type(env.unwrapped).__name__}")
    scene_env = env.unwrapped
    file_path = None
    if path is not None:
        file_path = Path(os.fspath(path)).expanduser()
        _check_writable(file_path)

    rec = rr.RecordingStream(app_id)  # dedicated stream, not the global one
    rec.set_log_time_enabled(False)  # deterministic timelines only (no wall clock)
    blueprint = _blueprint(rrb, scene_env.geometry)
    try:
        if spawn:
            rec.spawn(connect=False)
            sinks = [rr.GrpcSink()] + ([rr.FileSink(str(file_path))] if file_path is not None else [])
            rec.set_sinks(*sinks)
        else:
            rec.save(str(file_path))
    except RuntimeError as exc:
        raise OSError(f"cannot open the rerun recording sink ({file_path or 'viewer'}): {exc}") from exc
    rec.send_blueprint(blueprint, make_active=True, make_default=True)

    geometry = scene_env.geometry
    logger = _SceneLogger(rr, rec, scene_env)
    logger.log_static()
    dt = float(geometry.settings.control_dt)
    frame = 0
    lengths, returns, outcomes, successes, final_exposure = [], [], [], [], []

    def set_time(episode: int, episode_step: int) -> None:
        rec.set_time("step", sequence=frame)
        rec.set_time("sim_time", duration=frame * dt)
        rec.set_time("episode", sequence=episode)
        rec.set_time("episode_step", sequence=episode_step)

    try:
        for k in range(episodes):
            episode_seed = seed + k
            obs, info = env.reset(seed=episode_seed)
            if hasattr(policy, "reset"):
                policy.reset()
            set_time(k, 0)
            logger.start_episode(k)
            young = scene_env.snapshot().young_modulus
            rec.log("log/episodes", rr.TextLog(
                f"episode {k} start: seed {episode_seed}, E = {young:.0f} Pa, {_progress(info)}", level="INFO"))
            view = scene_env.camera_view(0, CAMERA_SIZE)
            logger.log_camera_pose(view)
            logger.log_frame(k, scene_env.snapshot(), info, view)
            frame += 1
            steps, ret, done = 0, 0.0, False
            terminated = truncated = False
            while not done:
                action = policy(obs)
                obs, reward, terminated, truncated, info = env.step(action)
                steps += 1
                ret += float(reward)
                done = bool(terminated or truncated)
                set_time(k, steps)
                logger.log_frame(k, scene_env.snapshot(), info, scene_env.camera_view(0, CAMERA_SIZE),
                                 action=action, reward=reward, ret=ret, episode_step=steps)
                if done:
                    outcome = _outcome(info, terminated, truncated)
                    logger.log_outcome(outcome)
                    rec.log("log/episodes", rr.TextLog(
                        f"episode {k} end: {outcome} after {steps} steps ({steps * dt:.1f} s), "
                        f"return {ret:.3f}, {_progress(info)}, "
                        f"max strain {float(info['max_strain']):.3f}",
                        level="INFO" if outcome == "success" else "WARN"))
                frame += 1
            lengths.append(steps)
            returns.append(ret)
            outcomes.append(_outcome(info, terminated, truncated))
            successes.append(bool(info.get("is_success", False)))
            final_exposure.append(float(info["exposure"]) if "exposure" in info else None)  # (None: a goal task)
    finally:
        rec.flush()
        if not spawn:
            rec.disconnect()  # closes the file and writes its footer

    return {
        "episodes": episodes,
        "frames": frame,
        "steps": int(sum(lengths)),
        "episode_lengths": lengths,
        "returns": returns,
        "mean_return": float(np.mean(returns)),
        "outcomes": outcomes,
        "successes": successes,
        "success_rate": float(np.mean(successes)),
        "final_exposure": final_exposure,
        "path": None if file_path is None else str(file_path),
        "application_id": rec.get_application_id(),
        "recording_id": rec.get_recording_id(),
    }
