"""The state: what a step changes, for N worlds at once."""

from __future__ import annotations

import numpy as np

__all__ = ["State"]


class State:
    """Positions ``x`` (m) and velocities ``v`` (m/s) of N worlds, ``(N, n, 3)`` float64 each.

    ``state.x[s]`` is world ``s``. A solver reads one state and writes another (they may
    be the same object): ``solver.step(state_in, state_out, control, dt)``.
    """

    def __init__(self, x, v=None):
        x = np.array(x, dtype=np.float64)
        if x.ndim != 3 or x.shape[2] != 3:
            raise ValueError(f"x must have shape (N, n, 3), got {x.shape}")
        v = np.zeros_like(x) if v is None else np.array(v, dtype=np.float64)
        if v.shape != x.shape:
            raise ValueError(f"v must have the shape of x {x.shape}, got {v.shape}")
        self.x = x
        self.v = v

    @property
    def n_worlds(self) -> int:
        return self.x.shape[0]

    @property
    def n_vertices(self) -> int:
        return self.x.shape[1]

    def copy(self) -> "State":
        return State(self.x.copy(), self.v.copy())

    def assign(self, other: "State", worlds=None) -> None:
        """Copy ``other``'s positions and velocities into this state (all worlds, or ``worlds``)."""
        if worlds is None:
            self.x[...] = other.x
            self.v[...] = other.v
        else:
            self.x[worlds] = other.x[worlds]
            self.v[worlds] = other.v[worlds]

    def __repr__(self) -> str:
        return f"State({self.n_worlds} worlds, {self.n_vertices} vertices)"
