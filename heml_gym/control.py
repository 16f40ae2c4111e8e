"""The control: what the user drives each step, for N worlds at once."""

from __future__ import annotations

import numpy as np

__all__ = ["Control"]


class Control:
    """Held (kinematic) vertices, where they go, and external forces, per world.

    Attributes
    ----------
    kinematic : (N, n) bool
        Vertices held by a gripper: they follow :attr:`targets` exactly, or, where
        :attr:`hold_stiffness` is positive, through a spring.
    targets : (N, n, 3) float, m
        Where the kinematic vertices (or their springs' anchors) are at the end of the next
        step; they move there along a straight line at constant speed during the step.
    hold_stiffness : (N, n) float, N/m
        0: a kinematic vertex is held exactly; positive: it is held by a spring of that
        stiffness to its anchor (a vertex the jaws hold only in part). Every solver
        steps it (the explicit one with a critical step shortened for the springs).
    anchors : (N, n, 3) float, m
        Where each spring's anchor is (the solver moves it towards :attr:`targets`).
    external_forces : (N, n, 3) float, N
        Applied to every vertex every step (a tip load, a probe).
    """

    def __init__(self, n_worlds: int, n_vertices: int):
        self.kinematic = np.zeros((n_worlds, n_vertices), dtype=bool)
        self.targets = np.zeros((n_worlds, n_vertices, 3))
        self.external_forces = np.zeros((n_worlds, n_vertices, 3))
        self.hold_stiffness = np.zeros((n_worlds, n_vertices))
        self.anchors = np.zeros((n_worlds, n_vertices, 3))

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

    def attach(self, world: int, vertices, positions, stiffness=None) -> None:
        """Hold ``vertices`` of ``world`` where they are (``positions``: their current
        positions, m, ``(k, 3)`` or the world's whole ``(n, 3)`` array): exactly, or, with
        ``stiffness`` (N/m, one number or one per vertex; 0: exactly), each by a spring to
        an anchor placed there."""
        idx = self.indices(vertices)
        positions = np.asarray(positions, dtype=np.float64)
        here = positions[idx] if positions.shape == (self.kinematic.shape[1], 3) else positions.reshape(len(idx), 3)
        k = np.zeros(len(idx)) if stiffness is None else np.broadcast_to(np.asarray(stiffness, dtype=np.float64),
                                                                        (len(idx),))
        if not np.all(np.isfinite(k) & (k >= 0.0)):
            raise ValueError("attach: stiffness must be finite and >= 0 N/m (0: held exactly)")
        self.kinematic[world, idx] = True
        self.targets[world, idx] = here
        self.hold_stiffness[world, idx] = k
        self.anchors[world, idx] = here

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
            self.hold_stiffness[world] = 0.0
        else:
            idx = self.indices(vertices)
            self.kinematic[world, idx] = False
            self.hold_stiffness[world, idx] = 0.0

    def clear(self, world: int) -> None:
        """Nothing held and no external force in ``world``."""
        self.kinematic[world] = False
        self.hold_stiffness[world] = 0.0
        self.external_forces[world] = 0.0

    def exactly_held(self) -> np.ndarray:
        """``(N, n)`` bool: the kinematic vertices held exactly (no spring)."""
        return self.kinematic & (self.hold_stiffness == 0.0)

    def spring_held(self) -> np.ndarray:
        """``(N, n)`` bool: the kinematic vertices held by a spring."""
        return self.kinematic & (self.hold_stiffness > 0.0)

    def spring_stiffness(self, fixed) -> np.ndarray:
        """``(N, n)`` N/m: the hold spring of each spring-held vertex that ``fixed`` (the
        model's ``(n,)`` mask) does not pin, 0 elsewhere: what a solver steps."""
        return np.where(self.spring_held() & ~np.asarray(fixed, dtype=bool)[None, :], self.hold_stiffness, 0.0)

    def __repr__(self) -> str:
        return f"Control({self.n_worlds} worlds, {int(self.kinematic.sum())} held vertices)"
