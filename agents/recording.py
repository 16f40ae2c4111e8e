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
                  episode's last frame.
``episode``       sequence: episode index (0-based).
``episode_step``  sequence: env steps since the episode's reset (0 on the reset frame).
                  Simulated time within the episode is ``episode_step * control_dt``.

Entities
--------
``world``                     static view coordinates (right-handed, z up).
``world/tissue``              :class:`rerun.Mesh3D`: the tissue surface, flat-shaded (each
                              surface triangle with its own three vertices and its face
                              normal, so a flat slab does not look creased; m), coloured by
                              the strain of the most strained mesh edge at each vertex (a
                              local view; pale pink at rest to red at
                              ``settings.damage_strain``); the triangles are logged once,
                              statically.
``world/attachment``          static :class:`rerun.Points3D`: the fixed tissue vertices.
``world/support``             static :class:`rerun.Mesh3D`: what the tissue rests on.
``world/gripper``             :class:`rerun.Boxes3D`: the jaws, grey when open, green when
                              closed on tissue.
``world/held``                :class:`rerun.Points3D`: the tissue vertices the jaws hold
                              (empty when none).
``world/grasp_force``         :class:`rerun.Arrows3D`: the force of the tissue on the
                              gripper, drawn from the gripper; the tissue's weight draws an
                              arrow ``FORCE_ARROW_FRACTION`` of the scene's size long.
``world/target``              :class:`rerun.Points3D`: the target (tumour) as a sphere of
                              the target radius, labelled with its exposure.
``world/camera``              the task camera: :class:`rerun.Transform3D` (its pose) and
                              :class:`rerun.Pinhole` (``CAMERA_SIZE`` pixels), per episode;
                              ``world/camera/image`` (:class:`rerun.Image`) and
                              ``world/camera/depth`` (:class:`rerun.DepthImage`, m) per frame.
``plots/reward_terms/<term>`` :class:`rerun.Scalars`: each shaping term of the step's
                              ``info`` (``exposure``, ``lift``, ``grasp``, ``strain``,
                              ``effort``); ``plots/return/total`` and ``plots/return/success``
                              apart; on step frames only (no reward at reset).
``plots/exposure/exposure``   exposure of the target (0..1), every frame;
``plots/exposure/success_threshold``  ``settings.success_exposure``, every frame.
``plots/strain/max_strain``   largest gauge strain (``info["max_strain"]``), every frame;
``plots/strain/damage_threshold``  ``settings.damage_strain``, every frame.
``plots/grasp_force``         magnitude of the grasp force (N), every frame.
``plots/outcome``             one marker at each episode's last frame: 1 success, 0 time-out,
                              -1 torn or diverged.
``log/episodes``              :class:`rerun.TextLog`: one line at each episode's start (seed,
                              Young's modulus) and one at its end (outcome, steps, return).

The blueprint frames the whole workspace in the 3D view from a fixed eye (no automatic
framing that clips the lifted flap or jumps), shows the task camera's image below it and
the plots beside them, and plays the ``sim_time`` timeline at real time (10 env steps per
simulated second at the default ``control_dt``).
"""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable

import numpy as np

from heml_gym.envs.core import RewardWeights
from heml_gym.envs.palette import (ATTACHMENT, FORCE, HELD, JAW_HALF_SIZE, JAW_OFFSET, JAWS_CLOSED, JAWS_OPEN,
                                   STRAINED, SUPPORT, TARGET, TISSUE)

__all__ = ["record_rollouts", "FORCE_ARROW_FRACTION", "SCALAR_ENTITIES", "REWARD_TERMS", "REWARD_ENTITIES"]

#: the grasp-force arrow is this fraction of the scene's size long at the tissue's weight
FORCE_ARROW_FRACTION = 0.3
#: reward terms of the task (``info["reward_<term>"]``)
REWARD_TERMS = tuple(f.name for f in fields(RewardWeights))
#: the shaping terms (plotted together, apart from the total and the success bonus)
SHAPING_TERMS = tuple(t for t in REWARD_TERMS if t != "success")
#: the entity of each reward series
REWARD_ENTITIES = {**{t: f"plots/reward_terms/{t}" for t in SHAPING_TERMS}, "success": "plots/return/success",
                   "total": "plots/return/total"}
#: every scalar series entity, and whether it is logged on every frame (True) or on step
#: frames only (False: the reward series)
SCALAR_ENTITIES = {
    **{e: False for e in REWARD_ENTITIES.values()},
    "plots/exposure/exposure": True,
    "plots/exposure/success_threshold": True,
    "plots/strain/max_strain": True,
    "plots/strain/damage_threshold": True,
    "plots/grasp_force": True,
}
#: size (height, width, pixels) of the task camera's images in the recording
CAMERA_SIZE = (240, 320)
#: outcome of an episode as the ``plots/outcome`` marker at its last frame
OUTCOME_VALUES = {"success": 1.0, "truncated": 0.0, "unfinished": 0.0, "terminated": -0.5, "torn": -1.0,
                  "diverged": -1.0}




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
    """A 3D view framing the whole workspace from a fixed eye, the task camera's image, the
    plots (shaping terms apart from the total and the success bonus), the episode log;
    playback on ``sim_time`` at real time."""
    low, high = (np.asarray(v, dtype=np.float64) for v in geometry.workspace)
    centre = 0.5 * (low + high)
    extent = float(np.linalg.norm(high - low))
    eye = centre + extent * np.array([0.55, -0.75, 0.5])
    plots = [
        rrb.TimeSeriesView(origin="plots/reward_terms", name="shaping reward terms"),
        rrb.TimeSeriesView(origin="plots/return", name="reward: total and success bonus"),
        rrb.TimeSeriesView(origin="plots/exposure", name="exposure"),
        rrb.TimeSeriesView(origin="plots/strain", name="strain"),
        rrb.TimeSeriesView(origin="plots/grasp_force", name="grasp force (N)"),
        rrb.TimeSeriesView(origin="plots/outcome", name="episode outcome (1 success, -1 torn / diverged)"),
        rrb.TextLogView(origin="log", name="episodes"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="scene",
                                  eye_controls=rrb.EyeControls3D(position=eye, look_target=centre,
                                                                 eye_up=(0.0, 0.0, 1.0))),
                rrb.Spatial2DView(origin="world/camera", name="task camera"),
                row_shares=[3, 2],
            ),
            rrb.Vertical(*plots),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="sim_time", playback_speed=1.0),
        collapse_panels=True,
    )


class _SceneLogger:
    """Logs one scene of a retraction env (its public geometry, snapshots and camera view)."""

    def __init__(self, rr, rec, env):
        self.rr, self.rec, self.env = rr, rec, env
        geometry = env.geometry
        self.geometry = geometry
        self.faces = np.asarray(geometry.surface_faces, dtype=np.int64)
        self.edges = np.asarray(geometry.edges)
        self.rest_length = np.linalg.norm(geometry.rest_vertices[self.edges[:, 1]]
                                          - geometry.rest_vertices[self.edges[:, 0]], axis=1)
        self.n_vertices = len(geometry.rest_vertices)
        extent = float(np.linalg.norm(np.ptp(geometry.rest_vertices, axis=0)))
        #: m of arrow per N: the tissue's weight draws FORCE_ARROW_FRACTION of the scene's size
        self.force_scale = FORCE_ARROW_FRACTION * extent / max(geometry.weight, 1e-9)

    def log_static(self) -> None:
        rr, rec, geo = self.rr, self.rec, self.geometry
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        # flat-shaded: every triangle its own three vertices, so a flat slab does not look creased
        rec.log("world/tissue", rr.Mesh3D.from_fields(
            triangle_indices=np.arange(3 * len(self.faces), dtype=np.uint32).reshape(-1, 3)), static=True)
        rec.log("world/attachment", rr.Points3D(geo.rest_vertices[geo.fixed], radii=0.0015,
                                                colors=ATTACHMENT), static=True)
        sv, sf = geo.support_mesh
        if len(sf):
            rec.log("world/support", rr.Mesh3D(vertex_positions=sv, triangle_indices=sf,
                                               albedo_factor=SUPPORT), static=True)
        st = geo.settings
        styles = {
            **{REWARD_ENTITIES[t]: (t, None) for t in SHAPING_TERMS},
            REWARD_ENTITIES["total"]: ("total", [255, 255, 255]),
            REWARD_ENTITIES["success"]: ("success bonus", [120, 200, 120]),
            "plots/exposure/exposure": ("exposure", TARGET),
            "plots/exposure/success_threshold": (f"success ({st.success_exposure:g})", [120, 200, 120]),
            "plots/strain/max_strain": ("max gauge strain", STRAINED),
            "plots/strain/damage_threshold": (f"damage ({st.damage_strain:g})", [150, 150, 150]),
            "plots/grasp_force": ("grasp force (N)", FORCE),
            "plots/outcome": ("outcome", [200, 200, 200]),
        }
        for entity, (name, colour) in styles.items():
            style = rr.SeriesLines(names=name) if colour is None else rr.SeriesLines(names=name, colors=colour)
            rec.log(entity, style, static=True)
        rec.log("plots/outcome", rr.SeriesPoints(markers="diamond", marker_sizes=6.0), static=True)

    def log_camera_pose(self, view: dict) -> None:
        """The task camera as a pinhole at its pose (the pose can change per episode)."""
        rr, rec = self.rr, self.rec
        h, w = view["rgb"].shape[:2]
        rec.log("world/camera", rr.Transform3D(translation=view["eye"], mat3x3=view["rotation"].T))
        rec.log("world/camera", rr.Pinhole(focal_length=float(view["focal"]), width=w, height=h,
                                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.03))

    def vertex_colours(self, x: np.ndarray) -> np.ndarray:
        """Per-vertex colour: strain of the most strained incident edge, pink to red at
        the damage threshold."""
        e = self.edges
        strain = np.abs(np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1) / self.rest_length - 1.0)
        per_vertex = np.zeros(self.n_vertices)
        np.maximum.at(per_vertex, e[:, 0], strain)
        np.maximum.at(per_vertex, e[:, 1], strain)
        s = np.clip(np.nan_to_num(per_vertex / self.geometry.settings.damage_strain, nan=1.0), 0.0, 1.0)
        return ((1.0 - s)[:, None] * TISSUE + s[:, None] * STRAINED).astype(np.uint8)

    def log_frame(self, snap, info: dict[str, Any], view: dict) -> None:
        rr, rec, geo = self.rr, self.rec, self.geometry
        x = np.nan_to_num(np.asarray(snap.positions, dtype=np.float64))
        tri = x[self.faces]  # (f, 3, 3): unshared vertices, flat normals
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
        colours = self.vertex_colours(x)[self.faces].reshape(-1, 3)
        rec.log("world/tissue", rr.Mesh3D.from_fields(vertex_positions=tri.reshape(-1, 3),
                                                      vertex_normals=np.repeat(normals, 3, axis=0),
                                                      vertex_colors=colours))
        gripper = np.asarray(snap.gripper, dtype=np.float64)
        rec.log("world/gripper", rr.Boxes3D(centers=[gripper + np.array(JAW_OFFSET)],
                                            half_sizes=[np.array(JAW_HALF_SIZE)],
                                            colors=[JAWS_CLOSED if snap.grasping else JAWS_OPEN],
                                            labels=["closed" if snap.grasping else "open"],
                                            fill_mode="solid"))
        held = x[snap.held]
        rec.log("world/held", rr.Points3D(held.reshape(-1, 3), radii=0.002, colors=HELD))
        force = np.nan_to_num(np.asarray(snap.grasp_force, dtype=np.float64))
        rec.log("world/grasp_force", rr.Arrows3D(origins=[gripper], vectors=[force * self.force_scale],
                                                 colors=[FORCE], labels=[f"{np.linalg.norm(force):.3f} N"]))
        exposure = float(info["exposure"])
        rec.log("world/target", rr.Points3D([snap.target], radii=float(geo.target_radius), colors=[TARGET],
                                            labels=[f"exposure {exposure:.0%}"]))
        rec.log("world/camera/image", rr.Image(view["rgb"]))
        rec.log("world/camera/depth", rr.DepthImage(view["depth"], meter=1.0))
        st = geo.settings
        rec.log("plots/exposure/exposure", rr.Scalars(exposure))
        rec.log("plots/exposure/success_threshold", rr.Scalars(float(st.success_exposure)))
        rec.log("plots/strain/max_strain", rr.Scalars(float(info["max_strain"])))
        rec.log("plots/strain/damage_threshold", rr.Scalars(float(st.damage_strain)))
        rec.log("plots/grasp_force", rr.Scalars(float(info["grasp_force"])))

    def log_rewards(self, reward: float, info: dict[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        for term in REWARD_TERMS:
            rec.log(REWARD_ENTITIES[term], rr.Scalars(float(info.get(f"reward_{term}", 0.0))))
        rec.log(REWARD_ENTITIES["total"], rr.Scalars(float(reward)))

    def log_outcome(self, outcome: str) -> None:
        self.rec.log("plots/outcome", self.rr.Scalars(OUTCOME_VALUES.get(outcome, 0.0)))


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
            young = scene_env.snapshot().young_modulus
            rec.log("log/episodes", rr.TextLog(
                f"episode {k} start: seed {episode_seed}, E = {young:.0f} Pa, "
                f"exposure {float(info['exposure']):.2f}", level="INFO"))
            view = scene_env.camera_view(0, CAMERA_SIZE)
            logger.log_camera_pose(view)
            logger.log_frame(scene_env.snapshot(), info, view)
            frame += 1
            steps, ret, done = 0, 0.0, False
            terminated = truncated = False
            while not done:
                obs, reward, terminated, truncated, info = env.step(policy(obs))
                steps += 1
                ret += float(reward)
                done = bool(terminated or truncated)
                set_time(k, steps)
                logger.log_frame(scene_env.snapshot(), info, scene_env.camera_view(0, CAMERA_SIZE))
                logger.log_rewards(reward, info)
                if done:
                    outcome = _outcome(info, terminated, truncated)
                    logger.log_outcome(outcome)
                    rec.log("log/episodes", rr.TextLog(
                        f"episode {k} end: {outcome} after {steps} steps ({steps * dt:.1f} s), "
                        f"return {ret:.3f}, exposure {float(info['exposure']):.2f}, "
                        f"max strain {float(info['max_strain']):.3f}",
                        level="INFO" if outcome == "success" else "WARN"))
                frame += 1
            lengths.append(steps)
            returns.append(ret)
            outcomes.append(_outcome(info, terminated, truncated))
            successes.append(bool(info.get("is_success", False)))
            final_exposure.append(float(info["exposure"]))
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
