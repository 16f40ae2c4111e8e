"""One backward Euler sub-step's incremental potential, for any force field with a Hessian.

:class:`FieldSubstep` is the sub-step of :mod:`.kernels_quasi_newton` (``begin_substep``,
``potential_and_gradient``, ``end_substep``) written in NumPy over a
:class:`~heml_gym.forces.ForceField`'s ``energy`` / ``forces`` / ``hessian`` instead of
HEML's kernels, for the case the calibration's replay needs (every held vertex held
exactly, no external forces, backward Euler): over the free vertices it minimises

    Phi(y) = c/2 sum_i m_i |y_i - x_hat_i|^2 + W(y) - sum_i m_i g . y_i
             + sum_i k_i/2 min(d_i(y), 0)^2,

``c = 1/h^2 + alpha/h``, ``x_hat = x_n + h v_n / (1 + alpha h)``, ``k_i = kappa c m_i``
(``kappa`` the support penalty in units of a vertex's inertia), ``d_i`` the vertex's
signed distance to the supports; then, as the kernels do, puts the vertices inside a
support onto it (unless that turns a tet inside out), takes their velocity into it away,
and adds the step-mean force on the held vertices (the trapezoidal rule between the
sub-step's start and end) into the reaction. ``tests/test_substep.py`` checks it against
the HEML kernels on a HEML field. Units: m, s, kg, N.
"""

from __future__ import annotations

import math

import numpy as np

from ..forces.base import ForceField
from ..linear_solvers import DiagonalAdd, DiagonalBlockAdd
from ..mesh import signed_volumes
from . import kernels_quasi_newton as kq
from .quasi_newton import incremental_hessian, penalised_hessian

__all__ = ["FieldSubstep", "HemlSubstep"]


class FieldSubstep:
    """A backward Euler sub-step of length ``h`` (s) from ``x, v`` (m, m/s; ``(n, 3)``) on
    ``field``, the ``kinematic`` vertices (``(n,)`` bool; and the ``fixed`` ones) moved a
    ``fraction`` of the way to their ``targets`` (m): :meth:`begin` moves them in ``x``;
    :meth:`potential`, :meth:`gradient` and :meth:`hessian` are the sub-step's incremental
    potential (J), its gradient (N, zero on held rows) and Hessian (CSR, ``3n x 3n``);
    :meth:`finish` turns the minimiser into the sub-step's end state.

    Parameters besides those: ``mass`` (n,) kg, ``alpha`` (1/s) mass damping,
    ``gravity`` (3,) m/s^2, ``supports`` (:class:`~heml_gym.contact.Supports`),
    ``kappa`` the support penalty in units of a vertex's inertia ``c m_i``, ``tets`` the
    mesh's tets (for the inside-out check of the support projection).
    """

    def __init__(self, field: ForceField, mass: np.ndarray, alpha: float, gravity: np.ndarray, fixed: np.ndarray,
                 supports, kappa: float, tets: np.ndarray, h: float, kinematic: np.ndarray, targets: np.ndarray,
                 fraction: float, add_diagonal: DiagonalAdd | None = None,
                 add_blocks: DiagonalBlockAdd | None = None):
        self.field, self.mass, self.alpha = field, mass, float(alpha)
        self.gravity, self.supports, self.tets = gravity, supports, tets
        self.h = float(h)
        self.c = 1.0 / self.h ** 2 + self.alpha / self.h
        self.k_contact = float(kappa) * self.c  # 1/s^2, times a vertex's mass
        self.held = np.asarray(kinematic, dtype=bool) | fixed
        self.moving = np.asarray(kinematic, dtype=bool) & ~fixed
        self.targets, self.fraction = targets, float(fraction)
        self.load = mass[:, None] * gravity[None, :]  # N
        self._add_diagonal = add_diagonal or DiagonalAdd()
        self._add_blocks = add_blocks or DiagonalBlockAdd()
        self.x_n = self.v_n = self.x_hat = None

    # ------------------------------------------------------------------ start
    def begin(self, x: np.ndarray, v: np.ndarray, r_prev: np.ndarray | None = None) -> None:
        """Record the start ``x_n, v_n`` and the inertial target ``x_hat``; move the held
        vertices along their path in ``x``. With ``r_prev`` (a control step's first
        sub-step) put the start's quasi-static holding force into it (N, held rows; 0
        elsewhere)."""
        self.x_n, self.v_n = x.copy(), v.copy()
        self.x_hat = self.x_n + self.h * self.v_n / (1.0 + self.alpha * self.h)
        if r_prev is not None:
            r_prev[:] = 0.0
            held = self.held
            r_prev[held] = -(self.field.forces(x)[held] + self.load[held] - self.alpha * self.mass[held, None] * v[held])
        m = self.moving
        x[m] = x[m] + (self.targets[m] - x[m]) * self.fraction

    # -------------------------------------------------------------- potential
    def contact(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(d, normal)``: each vertex's signed distance to the supports (m; ``inf``
        without supports) and the support's outward normal at ``y``."""
        if not len(self.supports):
            return np.full(len(y), math.inf), np.zeros_like(y)
        return self.supports.signed_distance(y)

    def _penetration(self, y):
        d, normal = self.contact(y)
        return np.where(self.held, 0.0, np.minimum(d, 0.0)), normal

    def potential(self, y: np.ndarray) -> float:
        """``Phi(y)`` (J); ``inf`` where the field's energy is not finite (inverted elements)."""
        y = y.reshape(-1, 3)
        w = self.field.energy(y)
        if not math.isfinite(w):
            return math.inf
        free = ~self.held
        e = y[free] - self.x_hat[free]
        m = self.mass[free]
        phi = w + 0.5 * self.c * float(m @ (e * e).sum(axis=1)) - float((self.load[free] * y[free]).sum())
        if len(self.supports):
            pen, _ = self._penetration(y)
            phi += 0.5 * self.k_contact * float(self.mass @ (pen * pen))
        return phi

    def gradient(self, y: np.ndarray) -> np.ndarray:
        """``grad Phi(y)`` (N), ``(n, 3)``, zero on the held rows."""
        y = y.reshape(-1, 3)
        g = self.c * self.mass[:, None] * (y - self.x_hat) - self.field.forces(y) - self.load
        if len(self.supports):
            pen, normal = self._penetration(y)
            g += (self.k_contact * self.mass * pen)[:, None] * normal
        g[self.held] = 0.0
        return g

    def hessian(self, y: np.ndarray, project: bool = False):
        """The Hessian (CSR, ``3n x 3n``) of ``Phi`` at ``y``: the field's (per element made
        positive semi-definite if ``project``), ``c M``, and the support penalty
        ``k_contact m_i n n^T`` of the free vertices inside a support."""
        y = y.reshape(-1, 3)
        pen, normal = self._penetration(y)
        return penalised_hessian(self.field, self.mass, y, self.c, project, self._add_diagonal, self._add_blocks,
                                 np.flatnonzero(pen < 0.0), normal, self.k_contact)

    # ------------------------------------------------------------------- end
    def finish(self, x: np.ndarray, v: np.ndarray, reaction: np.ndarray, r_prev: np.ndarray) -> dict:
        """From the minimiser ``x`` (changed in place) to the sub-step's end: the free
        vertices inside a support go onto it unless a tet of theirs would turn inside
        out, and lose their velocity into it; ``v = (x - x_n) / h``; the step-mean force
        on the held vertices, ``(r_prev + r_end) / 2`` with ``r_end = m (v - v_n)/h - f(x)
        - m g + alpha m v``, is added into ``reaction`` and ``r_end`` kept in ``r_prev``.
        Returns what the adjoint needs: ``inside`` (free vertices inside a support at the
        minimiser), ``projected`` (those moved onto it), ``stopped`` (those whose velocity
        into it was taken away), ``normal`` (the supports' normals there)."""
        d, normal = self.contact(x)
        held = self.held
        inside = ~held & (d < 0.0)
        projected = np.zeros_like(inside)
        if inside.any():
            trial = x.copy()
            trial[inside] -= d[inside, None] * normal[inside]
            touched = np.isin(self.tets, np.flatnonzero(inside)).any(axis=1)
            if np.all(signed_volumes(trial, self.tets[touched]) > 0.0):
                projected = inside & np.any(trial != x, axis=1)
                x[:] = trial
        v[:] = (x - self.x_n) / self.h
        stopped = inside & (np.einsum("ij,ij->i", v, normal) < 0.0)
        if stopped.any():
            vn = np.einsum("ij,ij->i", v[stopped], normal[stopped])
            v[stopped] -= vn[:, None] * normal[stopped]
        r_end = np.zeros_like(x)
        if held.any():
            m = self.mass[held, None]
            r_end[held] = (m * (v[held] - self.v_n[held]) / self.h - self.field.forces(x)[held] - self.load[held]
                           + self.alpha * m * v[held])
        reaction += 0.5 * (r_prev + r_end)
        r_prev[:] = r_end
        return dict(inside=inside, projected=projected, stopped=stopped, normal=normal)


class HemlSubstep:
    """:class:`FieldSubstep`'s interface over the HEML kernels of the quasi-Newton solver
    (:func:`~.kernels_quasi_newton.begin_substep`, ``potential_and_gradient``,
    ``end_substep``): the same sub-step, computed as :class:`~.QuasiNewtonSolver` computes
    it. ``body`` (:class:`~heml_gym.kernel_data.HemlBody`, its masses and damping the
    sub-step's), ``law`` (:class:`~heml_gym.kernel_data.WorldLaw`), ``supports``
    (:class:`~heml_gym.kernel_data.SupportArrays`); the rest as :class:`FieldSubstep`'s."""

    def __init__(self, field: ForceField, body, law, supports, kappa: float, h: float, kinematic: np.ndarray,
                 targets: np.ndarray, fraction: float, add_diagonal: DiagonalAdd | None = None,
                 add_blocks: DiagonalBlockAdd | None = None):
        n = len(kinematic)
        self.field, self.body, self.law, self.supports = field, body, law, supports
        self.kappa, self.h, self.fraction, self.targets = float(kappa), float(h), float(fraction), targets
        self.holds = kq.Holds(np.asarray(kinematic, dtype=bool), np.zeros(n), np.zeros((n, 3)))
        self.n_supports = supports.planes.shape[0] + supports.grids.shape[0]
        self._history = kq.Bdf2History(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(1))
        self._add_diagonal = add_diagonal or DiagonalAdd()
        self._add_blocks = add_blocks or DiagonalBlockAdd()
        self._g, self._dist, self._normal = np.zeros((n, 3)), np.full(n, math.inf), np.zeros((n, 3))
        self.c = self.k_contact = self.held = self.x_n = self.v_n = self.x_hat = None

    def begin(self, x: np.ndarray, v: np.ndarray, r_prev: np.ndarray | None = None) -> None:
        """As :meth:`FieldSubstep.begin`."""
        n = x.shape[0]
        self._sub = kq.Substep(self.h, self.fraction, 1, r_prev is not None, 0, self.kappa)
        self.work = kq.substep_work(n, 1)
        r = np.zeros((n, 3)) if r_prev is None else r_prev
        self.c, _ = kq.begin_substep(x, v, self.targets, self.holds, np.zeros((n, 3)), self.body, self.law,
                                     self._sub, self._history, r, self.work)
        self.k_contact = self.kappa * self.c
        self.held = self.work.held.copy()
        self.x_n, self.v_n, self.x_hat = self.work.x_n, self.work.v_n, self.work.x_hat
        self.args = (self.body, self.law, self.supports, self.c, self.work.x_hat, self.work.load, self.held,
                     self.k_contact, self.holds)

    def potential(self, y: np.ndarray) -> float:
        """As :meth:`FieldSubstep.potential`: ``inf`` where a tet is turned inside out
        (HEML's energy stays finite there, but its exact Hessian does not, and Newton's
        larger steps than the envs' L-BFGS can otherwise end in such a minimum)."""
        if not np.all(signed_volumes(y.reshape(-1, 3), self.field.mesh.tets) > 0.0):
            return math.inf
        return kq.potential_and_gradient(y.reshape(-1, 3), False, self._g, self.work.f, self._dist, self._normal,
                                         *self.args)

    def gradient(self, y: np.ndarray) -> np.ndarray:
        """As :meth:`FieldSubstep.gradient`."""
        kq.potential_and_gradient(y.reshape(-1, 3), True, self._g, self.work.f, self._dist, self._normal,
                                  *self.args)
        return self._g.copy()

    def hessian(self, y: np.ndarray, project: bool = False):
        """As :meth:`FieldSubstep.hessian`."""
        return incremental_hessian(self.field, self.body.mass, y.reshape(-1, 3), self.c, self.k_contact, self.held,
                                   self.args, project, self._add_diagonal, self._add_blocks)

    def finish(self, x: np.ndarray, v: np.ndarray, reaction: np.ndarray, r_prev: np.ndarray) -> dict:
        """As :meth:`FieldSubstep.finish`."""
        dist, normal = np.full(len(x), math.inf), np.zeros_like(x)
        kq.potential_and_gradient(x, True, self._g, self.work.f, dist, normal, *self.args)  # work.f: f(x)
        inside = (dist < 0.0) & ~self.held if self.n_supports else np.zeros(len(x), dtype=bool)
        x_before = x.copy()
        kq.end_substep(x, v, self.work, dist, normal, self.n_supports, True, reaction, r_prev, self.body, self.law,
                       self._sub, self._history, self.holds)
        projected = inside & np.any(x != x_before, axis=1)
        v_pre = (x - self.x_n) / self.h
        stopped = inside & (np.einsum("ij,ij->i", v_pre, normal) < 0.0)  # (end_substep's test)
        return dict(inside=inside, projected=projected, stopped=stopped, normal=normal)
