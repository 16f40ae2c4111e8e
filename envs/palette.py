"""The colours (RGB, 0-255) and the drawn jaws, shared by the task camera
(:mod:`heml_gym.envs.camera`), the ``rgb_array`` render (:mod:`heml_gym.envs.render_scene`)
and the rerun recordings (:mod:`heml_gym.agents.recording`)."""

from __future__ import annotations

import numpy as np

__all__ = ["TISSUE", "STRAINED", "TARGET", "JAWS_OPEN", "JAWS_CLOSED", "SUPPORT", "BACKGROUND", "ATTACHMENT",
           "HELD", "STUCK", "RELEASED", "HOOK_ON", "HOOK_OFF", "PADDLE", "SHAFT", "FORCE", "JAW_HALF_SIZE", "JAW_OFFSET", "unit"]

TISSUE = np.array([235, 170, 150])  # fat: pale pink
STRAINED = np.array([200, 30, 30])  # tissue at the damage threshold
TARGET = np.array([240, 220, 40])  # the tumour
JAWS_OPEN = np.array([150, 150, 160])
JAWS_CLOSED = np.array([40, 200, 90])
SUPPORT = np.array([120, 60, 60])  # the organ underneath
BACKGROUND = np.array([25, 25, 35], dtype=np.uint8)
ATTACHMENT = np.array([110, 110, 120])
HELD = np.array([40, 120, 255])  # the held vertices
STUCK = np.array([140, 90, 60])  # tissue still stuck to what it rests on (adhesion)
RELEASED = np.array([60, 220, 220])  # tissue a hook has freed this episode
HOOK_ON = np.array([255, 90, 20])  # an energised hook
HOOK_OFF = np.array([120, 120, 130])
PADDLE = np.array([70, 110, 170])  # a paddle retractor's blade
SHAFT = np.array([130, 115, 100])  # an instrument's shaft that touches tissue (on a port)
FORCE = np.array([255, 140, 0])  # the grasp force
JAW_HALF_SIZE = (0.003, 0.006, 0.006)  # m: the jaws drawn as a box
JAW_OFFSET = (0.0, 0.0, 0.006)  # m: the box centre above the grasp point


def unit(colour) -> tuple[float, float, float]:
    """``colour`` (0-255) as three floats in [0, 1]."""
    return tuple(float(c) / 255 for c in colour)
