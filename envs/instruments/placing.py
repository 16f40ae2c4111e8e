"""Where an instrument may be put: a checked position inside its workspace."""

from __future__ import annotations

import numpy as np

from ..spec import SpecError


def checked_position(position, low: np.ndarray, high: np.ndarray, what: str) -> np.ndarray:
    """``position`` (m) as a ``(3,)`` float array, or a one-line :class:`SpecError` naming
    ``what`` when it is not 3 finite coordinates inside ``low``..``high`` (m)."""
    p = np.asarray(position, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise SpecError(f"{what}: must be 3 finite coordinates (m), got {position!r}")
    if np.any(p < low - 1e-12) or np.any(p > high + 1e-12):
        raise SpecError(f"{what}: {p.tolist()} lies outside the workspace {list(low)}..{list(high)} m")
    return p
