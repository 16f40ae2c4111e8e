"""Tissue calibration: replay what drove a scene, and fit its material to what was observed.

:mod:`~heml_gym.calibration.replay` replays a :class:`ControlLog` by backward Euler and
gives exact gradients of a loss on the trajectory (positions, gripper force) in the
material's constants by the adjoint method; :mod:`~heml_gym.calibration.fitting` fits
those constants to observed points and forces. The physics only: no gymnasium, torch or
SB3 (the envs turn an observation file and a scene into a log: ``heml_gym.envs.observations``).
"""

from .fitting import (DEFAULT_FORCE_SCALE, DEFAULT_POINT_SCALE, FitResult, Observed, embed_points, fit, loss_terms,
                      paired_rms_interval)
from .replay import ControlLog, Replay, ReplayError, ReplayResult

__all__ = ["ControlLog", "Replay", "ReplayError", "ReplayResult", "Observed", "FitResult", "embed_points", "fit",
           "loss_terms", "DEFAULT_POINT_SCALE", "DEFAULT_FORCE_SCALE", "paired_rms_interval"]
