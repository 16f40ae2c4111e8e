"""A free wrist: jaws that hold a patch of tissue rigidly but turn freely about their axis.

Jaws that hold a line of vertices (the flap's edge) make the tissue next to the line
stretch more on every finer mesh (a line held in a solid is a singular boundary
condition: docs/benchmarks/flap_grasp_line.md). Jaws with a footprint hold a patch; held
rigidly they also fix its orientation, which a real gripper's passive (or compliant) wrist
does not: the patch turns until the torque on it about the jaws' axis vanishes. That
angle is one more unknown of each backward Euler sub-step.

The held patch's vertices ``W`` are at ``y_i = p + R(theta) (q_i - p)``: ``q_i`` their
path without the turn (the log's targets), ``p`` a point on the jaws' axis (unit vector
``a``; ``R`` the rotation about it). :class:`WristSubstep` minimises a sub-step's
incremental potential over the free vertices and ``s = L theta`` together (``L`` (m) the
patch's radius about the axis, so that ``dPhi/ds`` is a force, N, like the free
vertices' residuals). The wrist is massless: the patch's inertia and weight are the
jaws' (as for any held vertex), so ``dPhi/dtheta = -sum_W f_i . (a x (y_i - p))``, minus
the elastic torque about the axis. Units: m, rad, N, N m.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..control import rotation

__all__ = ["rotation", "WristSubstep"]


class WristSubstep:
    """A sub-step (:class:`~heml_gym.solvers.substep.FieldSubstep` or ``HemlSubstep``,
    begun) with its ``wrist`` vertices ((n,) bool, held by it) turned about ``axis`` through
    ``point`` (m) from their unturned places ``path`` ((n, 3) m; the wrist rows are read):
    its potential, gradient and Hessian over ``u = [y (3n), s]``, ``s = scale * angle``
    (``scale``, m). ``forces(y)``: the elastic forces (N, (n, 3)) at ``y``; ``mass`` (n,)
    kg, the sub-step's lumped masses (to take ``c M`` out of the held rows' Hessian)."""

    def __init__(self, step, wrist: np.ndarray, axis: np.ndarray, point: np.ndarray, path: np.ndarray,
                 scale: float, forces, mass: np.ndarray):
        self.step, self.scale = step, float(scale)
        self.axis, self.point = np.array(axis, dtype=np.float64), np.array(point, dtype=np.float64)
        self.rows = np.flatnonzero(wrist)
        self.arm0 = path[self.rows] - self.point  # (k, 3) m, unturned
        self.forces, self.mass = forces, mass
        self.n = len(wrist)
        self.free = np.append(np.repeat(~step.held, 3), True)  # (3n + 1,)
        self.dofs = np.repeat(3 * self.rows, 3) + np.tile(np.arange(3), len(self.rows))

    # ------------------------------------------------------------------ geometry
    def angle(self, u: np.ndarray) -> float:
        """The wrist angle (rad) of ``u``."""
        return float(u[-1]) / self.scale

    def arms(self, angle: float) -> np.ndarray:
        """``y_i - p`` (m, (k, 3)) of the wrist rows at ``angle``."""
        return self.arm0 @ rotation(self.axis, angle).T

    def positions(self, u: np.ndarray) -> np.ndarray:
        """``y`` (n, 3) m: ``u``'s vertices with the wrist rows turned to its angle."""
        y = np.array(u[:-1], dtype=np.float64).reshape(self.n, 3)
        y[self.rows] = self.point + self.arms(self.angle(u))
        return y

    def extend(self, y: np.ndarray, angle: float) -> np.ndarray:
        """``u`` (3n + 1,) from positions ``y`` (n, 3) and an ``angle`` (rad)."""
        return np.append(np.asarray(y, dtype=np.float64).reshape(-1), self.scale * angle)

    def lever(self, y: np.ndarray) -> np.ndarray:
        """``dy_i/ds = a x (y_i - p) / L`` of the wrist rows (dimensionless, (k, 3))."""
        return np.cross(self.axis, y[self.rows] - self.point) / self.scale

    # ------------------------------------------------------------------ the potential
    def potential(self, u: np.ndarray) -> float:
        return self.step.potential(self.positions(u))

    def gradient(self, u: np.ndarray) -> np.ndarray:
        """``dPhi/du``: the sub-step's gradient (zero on held rows), then ``dPhi/ds`` (N)."""
        y = self.positions(u)
        g = self.step.gradient(y).reshape(-1)
        torque_force = -float(np.sum(self.forces(y)[self.rows] * self.lever(y)))
        return np.append(g, torque_force)

    def hessian(self, u: np.ndarray, project: bool = False) -> sp.csr_matrix:
        """``d^2 Phi/du^2`` (CSR, (3n + 1)^2): the sub-step's Hessian, bordered by the
        coupling ``d^2 Phi/dy ds = H_yW lever`` and ``d^2 Phi/ds^2 = lever^T H_WW lever -
        sum_W f_i . a x (a x (y_i - p)) / L^2`` (``H`` elastic; where ``project`` the
        curvature term is dropped when negative, as a per-element projection would)."""
        y = self.positions(u)
        hess = self.step.hessian(y, project).tocsr()
        lever = np.zeros((self.n, 3))
        lever[self.rows] = self.lever(y)
        column = hess @ lever.reshape(-1)
        rigid = float(lever.reshape(-1) @ column) - self.step.c * float(self.mass[self.rows] @ (lever[self.rows] ** 2).sum(1))
        arms = y[self.rows] - self.point
        curvature = -float(np.sum(self.forces(y)[self.rows] * np.cross(self.axis, np.cross(self.axis, arms)))) \
            / self.scale ** 2
        if project:
            curvature = max(curvature, 0.0)
        # the coupling's rows: the dofs the wrist's dofs couple to (the pattern is symmetric)
        rows = np.unique(np.concatenate([hess.indices[hess.indptr[d]:hess.indptr[d + 1]] for d in self.dofs]))
        border = sp.csr_matrix((column[rows], (rows, np.zeros(len(rows), dtype=np.int64))), shape=(3 * self.n, 1))
        corner = sp.csr_matrix(np.array([[rigid + curvature]]))
        return sp.bmat([[hess, border], [border.T, corner]], format="csr")
