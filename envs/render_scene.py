"""Draw a retraction scene: CPU images (``rgb_array``) or a live rerun stream (``human``)."""

from __future__ import annotations

import itertools
import os
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from .instruments.paddle import tilt_rotation
from .palette import HOOK_OFF, HOOK_ON, JAWS_CLOSED, JAWS_OPEN, PADDLE, SHAFT, STRAINED, TARGET, TISSUE
from .render import Camera, box, compose, icosphere, rasterize

_COUNTER = itertools.count()


class SceneRenderer:
    """Renders world ``i`` of a :class:`~heml_gym.envs.core.BatchedRetraction`.

    ``rgb_array``: a 160 x 120 uint8 image from the task camera, tissue coloured by the
    strain of its surface triangles (pink to red at the damage threshold), the tumour
    yellow, the gripper grey (open) or green (closed). ``human``: the same scene logged
    to a rerun viewer (spawned on first use; needs ``pip install 'heml-gym[viz]'``).
    """

    def __init__(self, task, mode: str = "rgb_array", width: int = 160, height: int = 120):
        self.task, self.mode, self.width, self.height = task, mode, width, height
        scene = task.scene
        self.camera = Camera.looking_at(scene.camera, scene.look_at, up=scene.camera_up, fov_y=scene.camera_fov_y)
        self._faces = scene.surface_faces
        rest = scene.mesh.vertices
        self._rest_edge = np.linalg.norm(rest[self._faces[:, 1]] - rest[self._faces[:, 0]], axis=1)
        self._rr = None

    def _triangles(self, i: int):
        t = self.task
        x = t.x[i]
        f = self._faces
        edge = np.linalg.norm(x[f[:, 1]] - x[f[:, 0]], axis=1)
        strain = np.clip(np.abs(edge / self._rest_edge - 1.0) / t.settings.damage_strain, 0.0, 1.0)
        tissue_colours = ((1 - strain)[:, None] * TISSUE + strain[:, None] * STRAINED).astype(np.uint8)
        sphere = icosphere(t.scene.target_radius, t.target[i], subdivisions=1)
        parts = [(sphere[0], sphere[1], TARGET)]
        for g, position, closed in zip(t.instruments, t.grippers[i], t.grasping_all[i]):  # every grasper's jaws
            if g.kind == "paddle":  # the blade, turned by its tilt
                blade = box(position, g.spec.half_extents, tilt_rotation(g.tilt[i]))
                parts.append((blade[0], blade[1], PADDLE))
                continue
            if getattr(g, "roll_speed", None) is not None:  # along their axis, up the shaft from the grasp point
                centres, halves, frames = g.jaw_boxes()
                jaws = box(centres[i], halves, frames[i])
            else:
                jaws = box(position + np.array([0.0, 0.0, 0.006]), (0.003, 0.006, 0.006))
            parts.append((jaws[0], jaws[1], JAWS_CLOSED if closed else JAWS_OPEN))
            if getattr(g, "shaft_tool", None) is not None:  # a shaft that touches tissue, from its end to its port
                end = g.port.shaft_ends(position)[0]
                _, turn = g.port.shaft_poses(position)
                length = float(np.linalg.norm(g.port.port - end))
                shaft = box(0.5 * (end + g.port.port), (g.spec.shaft_radius, g.spec.shaft_radius, 0.5 * length), turn[0])
                parts.append((shaft[0], shaft[1], SHAFT))
        for tip, on in zip(t.hook_tips[i], t.hooks_energised[i]):  # every hook's tip
            hook = icosphere(0.003, tip, subdivisions=1)
            parts.append((hook[0], hook[1], HOOK_ON if on else HOOK_OFF))
        x_all, faces_all, colours = compose(parts)
        n = len(x_all)
        return (np.concatenate([x_all, x]), np.concatenate([faces_all, f + n]),
                np.concatenate([colours, tissue_colours]))

    def render(self, i: int = 0):
        x, faces, colours = self._triangles(i)
        if self.mode == "rgb_array":
            return rasterize((x, faces), colours, self.camera, self.width, self.height,
                             background=(25, 25, 35))
        if self._rr is None:
            self._rr, self._stream = open_viewer_stream()
        rr, rec = self._rr, self._stream
        rec.set_time("step", sequence=int(self.task.steps[i]))
        rec.log("scene", rr.Mesh3D(vertex_positions=x, triangle_indices=faces,
                                   vertex_colors=_vertex_colours(len(x), faces, colours)))
        return None

    def close(self):
        if self._rr is not None:
            self._stream.flush()
            self._stream.disconnect()
        self._rr = None


def viewer_executable() -> str | None:
    """The rerun viewer installed with rerun-sdk (found without PATH: a venv that is not
    activated works too), or None."""
    import importlib.util
    import shutil

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.submodule_search_locations:
        for folder in spec.submodule_search_locations:
            for name in ("rerun", "rerun.exe"):
                candidate = Path(folder) / name
                if candidate.is_file():
                    return str(candidate)
    return shutil.which("rerun")


def has_display() -> bool:
    """Whether a window can be opened: on Linux, an X11 or Wayland display is set."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def open_viewer_stream():
    """``(rerun module, recording stream)`` for ``render_mode="human"``: a rerun viewer
    spawned from the installed executable; without a display or a viewer, a recording
    file in the temp folder instead, with a warning that says where and what to do."""
    try:
        import rerun as rr
    except ImportError:
        raise ImportError("render_mode='human' needs the rerun SDK: pip install 'heml-gym[viz]' "
                          "(or use render_mode='rgb_array')") from None
    rec = rr.RecordingStream("heml_gym")
    exe = viewer_executable()
    if has_display() and exe is not None:
        rr.spawn(executable_path=exe, recording=rec, connect=True)
        return rr, rec
    path = Path(tempfile.gettempdir()) / f"heml_gym_human_{os.getpid()}_{next(_COUNTER)}.rrd"
    rec.save(str(path))
    why = "no display (DISPLAY and WAYLAND_DISPLAY are unset)" if exe is not None else "no rerun viewer installed"
    warnings.warn(f"render_mode='human' found {why}: the scene is recorded to {path} instead; open it with "
                  f"`rerun {path}` where a display is, or use render_mode='rgb_array' for images", RuntimeWarning,
                  stacklevel=3)
    return rr, rec


def _vertex_colours(n: int, faces: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Per-vertex colours from per-face ones (the last face touching a vertex wins)."""
    out = np.zeros((n, 3), dtype=np.uint8)
    out[faces.ravel()] = np.repeat(colours, 3, axis=0)
    return out
