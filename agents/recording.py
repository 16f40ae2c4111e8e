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
``world/tissue``              :class:`rerun.Mesh3D`: every tissue vertex (deformed positions,
                              m) with normals and per-vertex colours by the strain of the
                              most strained mesh edge at the vertex (a local view; pale pink
                              at rest to red at ``settings.damage_strain``); the triangles
                              (the scene's surface faces) are logged once, statically.
``world/attachment``          static :class:`rerun.Points3D`: the fixed tissue vertices.
``world/gripper``             :class:`rerun.Boxes3D`: the jaws, grey when open, green when
                              closed on tissue.
``world/held``                :class:`rerun.Points3D`: the tissue vertices the jaws hold
                              (empty when none).
``world/grasp_force``         :class:`rerun.Arrows3D`: the force of the tissue on the
                              gripper, drawn from the gripper at ``FORCE_ARROW_SCALE`` m/N.
``world/target``              :class:`rerun.Points3D`: the target (tumour) as a sphere of
                              the target radius, labelled with its exposure.
``plots/reward/<term>``       :class:`rerun.Scalars`: each ``reward_*`` term of the step's
                              ``info`` (``exposure``, ``lift``, ``grasp``, ``strain``, ``effort``,
                              ``success``) and ``total``, on step frames only (no reward at reset).
``plots/exposure/exposure``   exposure of the target (0..1), every frame;
``plots/exposure/success_threshold``  ``settings.success_exposure``, every frame.
``plots/strain/max_strain``   largest gauge strain (``info["max_strain"]``), every frame;
``plots/strain/damage_threshold``  ``settings.damage_strain``, every frame.
``plots/grasp_force``         magnitude of the grasp force (N), every frame.
``log/episodes``              :class:`rerun.TextLog`: one line at each episode's start (seed,
                              Young's modulus) and one at its end (outcome, steps, return).

A blueprint puts the 3D view of ``world`` beside a column of time-series views
(reward terms, exposure, strain, grasp force) and the episode log.
"""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable

import numpy as np

from heml_gym.envs.core import RewardWeights
from heml_gym.envs.render_scene import JAWS_CLOSED, JAWS_OPEN, STRAINED, TISSUE, TUMOUR

__all__ = ["record_rollouts", "FORCE_ARROW_SCALE", "SCALAR_ENTITIES", "REWARD_TERMS"]

#: metres of arrow per newton of grasp force in ``world/grasp_force``
FORCE_ARROW_SCALE = 0.2
#: reward terms of the task (``info["reward_<term>"]``), plotted under ``plots/reward/<term>``
REWARD_TERMS = tuple(f.name for f in fields(RewardWeights))
#: every scalar series entity, and whether it is logged on every frame (True) or on step
#: frames only (False: the reward series)
SCALAR_ENTITIES = {
    **{f"plots/reward/{t}": False for t in REWARD_TERMS},
    "plots/reward/total": False,
    "plots/exposure/exposure": True,
    "plots/exposure/success_threshold": True,
    "plots/strain/max_strain": True,
    "plots/strain/damage_threshold": True,
    "plots/grasp_force": True,
}

_ATTACHMENT = np.array([110, 110, 120])
_HELD = np.array([40, 120, 255])
_FORCE = np.array([255, 140, 0])
_JAW_HALF_SIZE = np.array([0.003, 0.006, 0.006])  # m, as in render_scene
_JAW_OFFSET = np.array([0.0, 0.0, 0.006])  # m: box centre above the grasp point


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


def _blueprint(rrb):
    plots = [
        rrb.TimeSeriesView(origin="plots/reward", name="reward terms"),
        rrb.TimeSeriesView(origin="plots/exposure", name="exposure"),
        rrb.TimeSeriesView(origin="plots/strain", name="strain"),
        rrb.TimeSeriesView(origin="plots/grasp_force", name="grasp force (N)"),
        rrb.TextLogView(origin="log", name="episodes"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="scene"),
            rrb.Vertical(*plots),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class _SceneLogger:
    """Logs one scene of a retraction env (its public geometry and snapshots) to a stream."""

    def __init__(self, rr, rec, geometry):
        self.rr, self.rec, self.geometry = rr, rec, geometry
        self.faces = np.asarray(geometry.surface_faces, dtype=np.uint32)
        self.edges = np.asarray(geometry.edges)
        self.rest_length = np.linalg.norm(geometry.rest_vertices[self.edges[:, 1]]
                                          - geometry.rest_vertices[self.edges[:, 0]], axis=1)
        self.n_vertices = len(geometry.rest_vertices)

    def log_static(self) -> None:
        rr, rec, geo = self.rr, self.rec, self.geometry
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world/tissue", rr.Mesh3D.from_fields(triangle_indices=self.faces), static=True)
        rec.log("world/attachment", rr.Points3D(geo.rest_vertices[geo.fixed], radii=0.0015,
                                                colors=_ATTACHMENT), static=True)
        st = geo.settings
        styles = {
            **{f"plots/reward/{t}": (t, None) for t in REWARD_TERMS},
            "plots/reward/total": ("total", [255, 255, 255]),
            "plots/exposure/exposure": ("exposure", TUMOUR),
            "plots/exposure/success_threshold": (f"success ({st.success_exposure:g})", [120, 200, 120]),
            "plots/strain/max_strain": ("max gauge strain", STRAINED),
            "plots/strain/damage_threshold": (f"damage ({st.damage_strain:g})", [150, 150, 150]),
            "plots/grasp_force": ("grasp force (N)", _FORCE),
        }
        for entity, (name, colour) in styles.items():
            style = rr.SeriesLines(names=name) if colour is None else rr.SeriesLines(names=name, colors=colour)
            rec.log(entity, style, static=True)

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

    def vertex_normals(self, x: np.ndarray) -> np.ndarray:
        f = self.faces
        face_n = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])  # area-weighted
        n = np.zeros_like(x)
        for k in range(3):
            np.add.at(n, f[:, k], face_n)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, length, out=np.zeros_like(n), where=length > 0)

    def log_frame(self, snap, info: dict[str, Any]) -> None:
        rr, rec, geo = self.rr, self.rec, self.geometry
        x = np.nan_to_num(np.asarray(snap.positions, dtype=np.float64))
        rec.log("world/tissue", rr.Mesh3D.from_fields(vertex_positions=x, vertex_normals=self.vertex_normals(x),
                                                      vertex_colors=self.vertex_colours(x)))
        gripper = np.asarray(snap.gripper, dtype=np.float64)
        rec.log("world/gripper", rr.Boxes3D(centers=[gripper + _JAW_OFFSET], half_sizes=[_JAW_HALF_SIZE],
                                            colors=[JAWS_CLOSED if snap.grasping else JAWS_OPEN],
                                            labels=["closed" if snap.grasping else "open"],
                                            fill_mode="solid"))
        held = x[snap.held]
        rec.log("world/held", rr.Points3D(held.reshape(-1, 3), radii=0.002, colors=_HELD))
        force = np.nan_to_num(np.asarray(snap.grasp_force, dtype=np.float64))
        rec.log("world/grasp_force", rr.Arrows3D(origins=[gripper], vectors=[force * FORCE_ARROW_SCALE],
                                                 colors=[_FORCE], labels=[f"{np.linalg.norm(force):.3f} N"]))
        exposure = float(info["exposure"])
        rec.log("world/target", rr.Points3D([snap.target], radii=float(geo.target_radius), colors=[TUMOUR],
                                            labels=[f"exposure {exposure:.0%}"]))
        st = geo.settings
        rec.log("plots/exposure/exposure", rr.Scalars(exposure))
        rec.log("plots/exposure/success_threshold", rr.Scalars(float(st.success_exposure)))
        rec.log("plots/strain/max_strain", rr.Scalars(float(info["max_strain"])))
        rec.log("plots/strain/damage_threshold", rr.Scalars(float(st.damage_strain)))
        rec.log("plots/grasp_force", rr.Scalars(float(info["grasp_force"])))

    def log_rewards(self, reward: float, info: dict[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        for term in REWARD_TERMS:
            rec.log(f"plots/reward/{term}", rr.Scalars(float(info.get(f"reward_{term}", 0.0))))
        rec.log("plots/reward/total", rr.Scalars(float(reward)))


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
    blueprint = _blueprint(rrb)
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
    logger = _SceneLogger(rr, rec, geometry)
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
            logger.log_frame(scene_env.snapshot(), info)
            frame += 1
            steps, ret, done = 0, 0.0, False
            terminated = truncated = False
            while not done:
                obs, reward, terminated, truncated, info = env.step(policy(obs))
                steps += 1
                ret += float(reward)
                done = bool(terminated or truncated)
                set_time(k, steps)
                logger.log_frame(scene_env.snapshot(), info)
                logger.log_rewards(reward, info)
                if done:
                    outcome = _outcome(info, terminated, truncated)
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
