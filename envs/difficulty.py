"""Difficulty levels of the retraction tasks: named changes to the task settings and scene.

Level 0 is the first task (success as soon as the target is exposed with the tissue below
damage strain). Level 1, the default since 2026-11-24, asks for what retraction is for:
hold the target exposed, below damage strain, for 2 s of simulated time. Level 2 adds a wider tissue
stiffness range per episode (half the scene's lowest Young's modulus to 1.5 times its
highest) and hides the target deeper under the tissue: its region moves halfway towards
the fold hinge (in x), so the tissue must be folded further back before it is exposed. ``docs/studies/envs.md`` has the scripted baseline's success rate and episode length on
every level (``python benchmarks/learning/task_difficulty.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

from .core import TaskSettings, settings_with
from .scene import Scene
from .spec import SpecError


@dataclass(frozen=True)
class Difficulty:
    """One level: ``hold_time`` (s) the success condition must hold; ``stiffness_spread``
    (low factor, high factor) applied to the scene's Young's modulus range;
    ``target_toward_hinge``: the fraction of the way (in x) the target region moves from
    where the scene puts it towards the fold hinge (0: unchanged)."""

    level: int
    hold_time: float
    stiffness_spread: tuple[float, float]
    description: str
    target_toward_hinge: float = 0.0


LEVELS = {
    0: Difficulty(0, 0.0, (1.0, 1.0), "success as soon as the target is exposed below damage strain"),
    1: Difficulty(1, 2.0, (1.0, 1.0), "hold the target exposed, below damage strain, for 2 s"),
    2: Difficulty(2, 2.0, (0.5, 1.5), "hold for 2 s; tissue E from half the lowest to 1.5x the highest; "
                  "target halfway deeper towards the hinge", target_toward_hinge=0.5),
}


def check_difficulty(level) -> Difficulty:
    """The level ``level`` (an integer key of :data:`LEVELS`); a one-line error otherwise."""
    if isinstance(level, bool) or not isinstance(level, int) or level not in LEVELS:
        raise SpecError(f"difficulty: must be one of {sorted(LEVELS)}, got {level!r}")
    return LEVELS[level]


def apply_difficulty(level, settings: TaskSettings, scene: Scene) -> tuple[TaskSettings, Scene]:
    """``settings`` and ``scene`` at difficulty ``level`` (copies; level 0 changes nothing).
    A hold time the settings give (> 0 s) replaces the level's."""
    d = check_difficulty(level)
    if d.hold_time > 0 and settings.hold_time == 0.0:
        settings = settings_with(settings, hold_time=d.hold_time)
    if d.stiffness_spread != (1.0, 1.0):
        lo, hi = scene.physics.young_modulus
        scene = scene.updated({"physics": {"young_modulus": [lo * d.stiffness_spread[0], hi * d.stiffness_spread[1]]}})
    if d.target_toward_hinge:
        hinge_x, f = scene.fold.hinge[0], d.target_toward_hinge
        low, high = list(scene.target.low), list(scene.target.high)
        low[0], high[0] = sorted((low[0] + f * (hinge_x - low[0]), high[0] + f * (hinge_x - high[0])))
        scene = scene.updated({"target": {"low": low, "high": high}})
    return settings, scene
