"""Numba kernels for a few tets at a time: the tets around a set of vertices (the held
vertices' reaction needs no others), and jaws on a free wrist in the quasi-Newton solver.

A free wrist: the jaws hold a patch of tissue rigidly, but turn freely about their axis
(unit ``a``) through a pivot ``p``: the patch's vertices are at ``y_i = p + R(theta) r_i``
(``r_i`` their arms at angle 0). The wrist is massless (the patch's inertia and weight are
the jaws', as for any held vertex), so in each sub-step the angle minimises the elastic
energy of the tets around the patch with the free vertices where they are: the angle is
eliminated, a 1-D minimisation (:func:`settle`: a safeguarded secant-Newton on ``dPhi/ds``,
``s = L theta`` with ``L`` the patch's RMS radius about the axis, so that ``dPhi/ds`` is a
force in N) inside each evaluation of the sub-step's potential. By the envelope theorem the
reduced potential's gradient on the free vertices is the potential's own at that angle, so
L-BFGS, its line search and its initial Hessian (the patch held, as any held vertex) are
unchanged. The end of each sub-step is the stationary point of the potential over the free
vertices and the angle together, the one the calibration's replay finds by Newton on both
(:class:`heml_gym.calibration.wrist.WristSubstep`). Units: m, rad, N, J.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from ..forces.kernels_heml import (constant_psi1_energy_and_forces_chunk, constant_psi1_forces_chunk,
                                   heml_energy_chunk, heml_forces_chunk)


class TetSubset(NamedTuple):
    """Some tets of a HEML body and their rest data (the layouts of
    :class:`~heml_gym.kernel_data.HemlBody` and :class:`~heml_gym.kernel_data.WorldLaw`)."""

    tets: np.ndarray  #: (k, 4) int64
    coef_t: np.ndarray  #: (9, k)
    q_t: np.ndarray  #: (21, k) when the law reads I2, else (21, 1)
    weights: np.ndarray  #: (6, k) when the law is split, else (6, 1)
    inv_det: np.ndarray  #: (k,)


class Wrist(NamedTuple):
    """Jaws on a free wrist (leading axis: the worlds' N, or none for one world); see
    :class:`heml_gym.Control` (``turns``, ``arms``, ``wrist_axis``, ``pivot``,
    ``pivot_target``, ``wrist_angle``, ``wrist_stiffness``). The solver advances ``pivot``,
    ``angle`` and ``stiffness`` in place."""

    turns: np.ndarray  #: (n,) bool: the patch
    arms: np.ndarray  #: (n, 3) m: each patch vertex from the pivot, at angle 0
    axis: np.ndarray  #: (3,) unit
    pivot: np.ndarray  #: (3,) m, now
    target: np.ndarray  #: (3,) m, the pivot at the end of the step
    angle: np.ndarray  #: (1,) rad, now
    stiffness: np.ndarray  #: (1,) N/m: the latest d^2 Phi / ds^2, 0 when unknown


@nb.njit(cache=True, inline="always")
def world_wrist(wrist, s):
    """World ``s``'s :class:`Wrist` of the stacked bundle."""
    return Wrist(wrist.turns[s], wrist.arms[s], wrist.axis[s], wrist.pivot[s], wrist.target[s],
                 wrist.angle[s:s + 1], wrist.stiffness[s:s + 1])


@nb.njit(cache=True)
def tets_touching(mask, body, law):
    """The :class:`TetSubset` of ``body``'s tets with a vertex in ``mask`` ((n,) bool, or
    empty: no tets, nothing scanned), for ``law`` (:class:`~heml_gym.kernel_data.WorldLaw`)."""
    tets, coef_t, q_t, w, inv_det = body.tets, body.coef_t, law.q_t, law.weights, body.inv_det
    vt_ptr, vt_tets = body.vt_ptr, body.vt_tets
    m = tets.shape[0]
    touches = np.zeros(m if mask.shape[0] else 0, dtype=np.bool_)
    k = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            for j in range(vt_ptr[i], vt_ptr[i + 1]):
                t = vt_tets[j]
                if not touches[t]:
                    touches[t] = True
                    k += 1
    sub_tets = np.empty((k, 4), dtype=tets.dtype)
    sub_inv_det = np.empty(k)
    sub_w = np.zeros((w.shape[0], k if law.split else 1))
    sub_coef = np.empty((coef_t.shape[0], k))
    sub_q = np.zeros((q_t.shape[0], k if law.use_q else 1))
    r = 0
    for t in range(m if k else 0):
        if touches[t]:
            for a in range(4):
                sub_tets[r, a] = tets[t, a]
            sub_inv_det[r] = inv_det[t]
            for a in range(coef_t.shape[0]):
                sub_coef[a, r] = coef_t[a, t]
            if law.split:
                for a in range(w.shape[0]):
                    sub_w[a, r] = w[a, t]
            if law.use_q:
                for a in range(q_t.shape[0]):
                    sub_q[a, r] = q_t[a, t]
            r += 1
    return TetSubset(sub_tets, sub_coef, sub_q, sub_w, sub_inv_det)


@nb.njit(cache=True)
def subset_forces(x, f, sub, law):
    """``f`` = the HEML forces (N) at ``x`` of the tets of ``sub`` (:class:`TetSubset`): exact
    on every vertex of ``mask`` it was taken for, partial or zero elsewhere."""
    f[:, :] = 0.0
    k = sub.tets.shape[0]
    if law.split:
        constant_psi1_forces_chunk(x, sub.tets, sub.inv_det, sub.weights, law.law, law.params, f, 0, k)
    else:
        heml_forces_chunk(x, sub.tets, sub.coef_t, sub.q_t, law.use_q, law.law, law.params, f, 0, k)


@nb.njit(cache=True)
def subset_energy(x, sub, law):
    """The elastic energy (J) at ``x`` of the tets of ``sub``; ``inf`` where one is inverted."""
    return heml_energy_chunk(x, sub.tets, sub.coef_t, sub.q_t, law.use_q, law.law, law.params, 0,
                             sub.tets.shape[0])


# ------------------------------------------------------------------------ the wrist
@nb.njit(cache=True)
def radius(wrist):
    """``L`` (m): the root-mean-square distance of the patch's vertices from the axis."""
    a = wrist.axis
    total, count = 0.0, 0
    for i in range(wrist.turns.shape[0]):
        if wrist.turns[i]:
            r = wrist.arms[i]
            along = r[0] * a[0] + r[1] * a[1] + r[2] * a[2]
            total += r[0] * r[0] + r[1] * r[1] + r[2] * r[2] - along * along
            count += 1
    return max(math.sqrt(total / max(count, 1)), 1e-4)


@nb.njit(cache=True)
def place(x, wrist, angle):
    """Put the patch's vertices of ``x`` at ``pivot + R(angle) arms`` (Rodrigues)."""
    a, p = wrist.axis, wrist.pivot
    c, s = math.cos(angle), math.sin(angle)
    for i in range(wrist.turns.shape[0]):
        if wrist.turns[i]:
            r = wrist.arms[i]
            along = (r[0] * a[0] + r[1] * a[1] + r[2] * a[2]) * (1.0 - c)
            x[i, 0] = p[0] + r[0] * c + (a[1] * r[2] - a[2] * r[1]) * s + a[0] * along
            x[i, 1] = p[1] + r[1] * c + (a[2] * r[0] - a[0] * r[2]) * s + a[1] * along
            x[i, 2] = p[2] + r[2] * c + (a[0] * r[1] - a[1] * r[0]) * s + a[2] * along


@nb.njit(cache=True)
def _torque_force(x, f, wrist, scale):
    """``dPhi/ds`` (N): minus the elastic torque about the axis on the patch, over ``scale``."""
    a, p = wrist.axis, wrist.pivot
    total = 0.0
    for i in range(wrist.turns.shape[0]):
        if wrist.turns[i]:
            rx, ry, rz = x[i, 0] - p[0], x[i, 1] - p[1], x[i, 2] - p[2]
            total -= (f[i, 0] * (a[1] * rz - a[2] * ry) + f[i, 1] * (a[2] * rx - a[0] * rz)
                      + f[i, 2] * (a[0] * ry - a[1] * rx))
    return total / scale


@nb.njit(cache=True)
def _energy_and_slope(x, wrist, angle, sub, law, f, scale):
    """The energy (J) of ``sub`` with the patch at ``angle`` (placed in ``x``) and
    ``dPhi/ds`` (N); ``(inf, 0)`` where a tet inverts. A law with a constant ``Psi_1``
    (Neo-Hookean) takes both in one pass."""
    place(x, wrist, angle)
    if law.split:
        f[:, :] = 0.0
        phi = constant_psi1_energy_and_forces_chunk(x, sub.tets, sub.inv_det, sub.coef_t[0], sub.weights, law.psi1,
                                                    law.law, law.params, f, 0, sub.tets.shape[0])
        if not math.isfinite(phi):
            return math.inf, 0.0
        return phi, _torque_force(x, f, wrist, scale)
    phi = subset_energy(x, sub, law)
    if not math.isfinite(phi):
        return math.inf, 0.0
    subset_forces(x, f, sub, law)
    return phi, _torque_force(x, f, wrist, scale)


@nb.njit(cache=True)
def settle(x, wrist, sub, law, f, scale, tol, max_iter):
    """Turn the patch of ``x`` (in place) to the angle that minimises the energy of ``sub``
    (:class:`TetSubset`, the tets around the patch) with the other vertices where they
    are, from ``wrist.angle[0]``; ``wrist.angle`` and ``wrist.stiffness`` updated. ``f``:
    scratch (n, 3). ``scale``: :func:`radius` (m); ``tol``: ``|dPhi/ds|`` (N) to reach.
    Returns ``|dPhi/ds|`` at the end (N; ``inf`` when the patch inverts a tet at every angle
    tried: the potential is then infinite there, which the line search needs to know)."""
    s = wrist.angle[0] * scale
    phi, g = _energy_and_slope(x, wrist, s / scale, sub, law, f, scale)
    if not math.isfinite(phi):
        return math.inf
    k = wrist.stiffness[0]
    if not (k > 0.0 and math.isfinite(k)):  # no estimate yet: a finite difference
        ds = 1e-6 * scale
        _, g2 = _energy_and_slope(x, wrist, (s + ds) / scale, sub, law, f, scale)
        k = (g2 - g) / ds
        place(x, wrist, s / scale)
    for _ in range(max_iter):
        if abs(g) <= tol:
            break
        if not (k > 0.0 and math.isfinite(k)):
            k = abs(g) / (0.05 * scale)  # (not convex here: a cautious step of 0.05 rad)
        ds = -g / k
        limit = 0.3 * scale  # at most 0.3 rad per try
        if abs(ds) > limit:
            ds = math.copysign(limit, ds)
        accepted = False
        phi_t, g_t = math.inf, 0.0
        for _ in range(30):
            phi_t, g_t = _energy_and_slope(x, wrist, (s + ds) / scale, sub, law, f, scale)
            if math.isfinite(phi_t) and (phi_t <= phi + 1e-4 * ds * g or abs(g_t) < abs(g)):
                accepted = True
                break
            ds *= 0.5
        if not accepted:
            place(x, wrist, s / scale)
            break
        k_new = (g_t - g) / ds
        if k_new > 0.0 and math.isfinite(k_new):
            k = k_new
        s += ds
        phi, g = phi_t, g_t
    wrist.angle[0] = s / scale
    wrist.stiffness[0] = k if (k > 0.0 and math.isfinite(k)) else 0.0
    return abs(g)


@nb.njit(cache=True)
def begin_wrist(x, x_n, v_n, jump, h, fraction, wrist):
    """A sub-step's start for the wrist, after :func:`~.kernels_quasi_newton.begin_substep`:
    the pivot moves a ``fraction`` of the way to its target, the patch goes to the pivot at
    the current angle, and its ``jump`` beyond its own predictor is set. Returns whether
    any held vertex jumps."""
    for d in range(3):
        wrist.pivot[d] += (wrist.target[d] - wrist.pivot[d]) * fraction
    place(x, wrist, wrist.angle[0])
    any_jump = False
    for i in range(x.shape[0]):
        for d in range(3):
            if wrist.turns[i]:
                jump[i, d] = x[i, d] - x_n[i, d] - h * v_n[i, d]
            any_jump = any_jump or jump[i, d] != 0.0
    return any_jump
