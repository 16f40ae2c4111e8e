"""The control: what the user drives each step, for N worlds at once."""

from __future__ import annotations

import numpy as np

__all__ = ["Control"]


class Control:
    """Held (kinematic) vertices, where they go, and external forces, per world.

    Attributes
    ----------
    kinematic : (N, n) bool
        Vertices held by a gripper: they follow :attr:`targets` exactly.
    targets : (N, n, 3) float, m
        Where the kinematic vertices are at the end of the next step; they move there
        along a straight line at constant speed during the step.
    external_forces : (N, n, 3) float, N
        Applied to every vertex every step (a tip load, a probe).
    """

    def __init__(self, n_worlds: int, n_vertices: int):
        self.kinematic = np.zeros((n_worlds, n_vertices), dtype=bool)
        self.targets = np.zeros((n_worlds, n_vertices, 3))
        self.external_forces = np.zeros((n_worlds, n_vertices, 3))

    @property
    def n_worlds(self) -> int:
        return self.kinematic.shape[0]

    def indices(self, vertices) -> np.ndarray:
        """Vertex indices from indices or an ``(n,)`` bool mask, checked against ``[0, n)``."""
        n = self.kinematic.shape[1]
        arr = np.asarray(vertices)
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise ValueError(f"vertex mask must have shape ({n},), got {arr.shape}")
            return np.flatnonzero(arr)
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"vertices must be integer indices or a bool mask, got {arr.dtype}")
        idx = arr.astype(np.int64).ravel()
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise ValueError(f"vertex indices must lie in [0, {n})")
        return idx

    def attach(self, world: int, vertices, positions) -> None:
        """Hold ``vertices`` of ``world`` where they are (``positions``: their current
        positions, m, ``(k, 3)`` or the world's whole ``(n, 3)`` array)."""
        idx = self.indices(vertices)
        positions = np.asarray(positions, dtype=np.float64)
        here = positions[idx] if positions.shape == (self.kinematic.shape[1], 3) else positions.reshape(len(idx), 3)
        self.kinematic[world, idx] = True
        self.targets[world, idx] = here

    def drive(self, world: int, vertices, targets) -> None:
        """Kinematic ``vertices`` of ``world`` reach ``targets`` (m, ``(k, 3)``) at the end of
        the next step."""
        idx = self.indices(vertices)
        targets = np.asarray(targets, dtype=np.float64).reshape(len(idx), 3)
        if not np.all(self.kinematic[world, idx]):
            raise ValueError("drive() needs attached (kinematic) vertices: attach them first")
        if not np.all(np.isfinite(targets)):
            raise ValueError("kinematic targets must be finite")
        self.targets[world, idx] = targets

    def detach(self, world: int, vertices=None) -> None:
        """Release the kinematic vertices of ``world`` (all, or ``vertices``); they keep
        their velocity."""
        if vertices is None:
            self.kinematic[world] = False
        else:
            self.kinematic[world, self.indices(vertices)] = False

    def clear(self, world: int) -> None:
        """Nothing held and no external force in ``world``."""
        self.kinematic[world] = False
        self.external_forces[world] = 0.0

    def __repr__(self) -> str:
        return f"Control({self.n_worlds} worlds, {int(self.kinematic.sum())} held vertices)"
