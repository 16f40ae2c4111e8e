"""Difficulty levels of the retraction tasks: named changes to the task settings and scene.

Level 0 is the task as published (success as soon as the target is exposed with the
tissue below damage strain). Level 1 asks for what retraction is for: hold the target
exposed, below damage strain, for 2 s of simulated time. Level 2 adds a wider tissue
stiffness range per episode (half the scene's lowest Young's modulus to 1.5 times its
highest). ``docs/envs.md`` has the scripted baseline's success rate and episode length on
every level (``python benchmarks/task_difficulty.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

from .core import TaskSettings, settings_with
from .scene import Scene
from .spec import SpecError


@dataclass(frozen=True)
class Difficulty:
    """One level: ``hold_time`` (s) the success condition must hold; ``stiffness_spread``
    (low factor, high factor) applied to the scene's Young's modulus range."""

    level: int
    hold_time: float
    stiffness_spread: tuple[float, float]
    description: str


LEVELS = {
    0: Difficulty(0, 0.0, (1.0, 1.0), "success as soon as the target is exposed below damage strain"),
    1: Difficulty(1, 2.0, (1.0, 1.0), "hold the target exposed, below damage strain, for 2 s"),
    2: Difficulty(2, 2.0, (0.5, 1.5), "hold for 2 s; tissue E from half the lowest to 1.5x the highest"),
}


def check_difficulty(level) -> Difficulty:
    """The level ``level`` (an integer key of :data:`LEVELS`); a one-line error otherwise."""
    if isinstance(level, bool) or not isinstance(level, int) or level not in LEVELS:
        raise SpecError(f"difficulty: must be one of {sorted(LEVELS)}, got {level!r}")
    return LEVELS[level]


def apply_difficulty(level, settings: TaskSettings, scene: Scene) -> tuple[TaskSettings, Scene]:
    """``settings`` and ``scene`` at difficulty ``level`` (copies; level 0 changes nothing).
    A level with a hold time refuses settings that set their own."""
    d = check_difficulty(level)
    if d.hold_time > 0:
        if settings.hold_time not in (0.0, d.hold_time):
            raise SpecError(f"difficulty: level {d.level} sets settings.hold_time to {d.hold_time} s, "
                            f"but settings give {settings.hold_time} s; give one of them")
        settings = settings_with(settings, hold_time=d.hold_time)
    if d.stiffness_spread != (1.0, 1.0):
        lo, hi = scene.physics.young_modulus
        scene = scene.updated({"physics": {"young_modulus": [lo * d.stiffness_spread[0], hi * d.stiffness_spread[1]]}})
    return settings, scene
