"""Numba kernels of the quasi-Newton (L-BFGS) backward Euler solver, one scene per call
of :func:`_lbfgs_scene`, scenes over threads in :func:`lbfgs_steps_parallel`.

Each step minimises the incremental potential of backward Euler over the free vertices,

    Phi(x) = c/2 sum_i m_i |x_i - x_hat_i|^2 + W(x) - sum_i (f_ext,i + m_i g) . x_i
             + sum_i k_i/2 min(d_i(x), 0)^2,       c = 1/h^2 + alpha/h,

by L-BFGS whose initial inverse Hessian is ``P A^-1 P``: ``A = c M + K(X)`` (the rest
stiffness of a reference material, on the non-fixed degrees of freedom) factorised
once per mesh and step length (an envelope Cholesky factor), ``P`` zeroing the held
degrees of freedom. The factor is shared by every scene and never redone when a grasp
starts or ends: the held set is a projection. A backtracking line search on ``Phi``
(Armijo) keeps every iterate finite. Units: m, s, kg, N.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba import prange

from ..forces.kernels_heml import constant_psi1_forces_chunk, heml_energy_chunk, heml_forces_chunk
from ..kernels_cholesky import envelope_precondition
from ..kernels_contact import signed_distances


@nb.njit(cache=True)
def _potential_and_gradient(x, want_gradient, g, f, dist, normal, mass, c, x_hat, load, held, k_contact,
                            tets, coef_t, q_t, use_q, law, p, split, w, inv_det, planes, grids, grid_values,
                            n_supports):
    """``Phi(x)`` (J) and, if ``want_gradient``, its gradient into ``g`` (N; zero on held
    vertices). ``f``, ``dist``, ``normal`` are scratch."""
    n = x.shape[0]
    m = tets.shape[0]
    phi = heml_energy_chunk(x, tets, coef_t, q_t, use_q, law, p, 0, m)
    if not math.isfinite(phi):
        return math.inf
    if n_supports:
        signed_distances(x, planes, grids, grid_values, dist, normal)
    if want_gradient:
        f[:, :] = 0.0
        if split:
            constant_psi1_forces_chunk(x, tets, inv_det, w, law, p, f, 0, m)
        else:
            heml_forces_chunk(x, tets, coef_t, q_t, use_q, law, p, f, 0, m)
    for i in range(n):
        if held[i]:
            if want_gradient:
                g[i, 0] = 0.0
                g[i, 1] = 0.0
                g[i, 2] = 0.0
            continue
        mi = mass[i]
        pen = min(dist[i], 0.0) if n_supports else 0.0
        kc = k_contact * mi
        for d in range(3):
            e = x[i, d] - x_hat[i, d]
            phi += 0.5 * c * mi * e * e - load[i, d] * x[i, d]
            if want_gradient:
                g[i, d] = c * mi * e - f[i, d] - load[i, d] + kc * pen * normal[i, d]
        phi += 0.5 * kc * pen * pen
    return phi


@nb.njit(cache=True, inline="always")
def _dot(a, b):
    total = 0.0
    for i in range(a.shape[0]):
        total += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return total


@nb.njit(cache=True)
def _precondition(g, z, held, dof_index, first, ptr, values, inverse, r, zr, wb, wx):
    """``z = P A^-1 P g`` (``dof_index[i, d]``: the row of vertex ``i``, axis ``d`` in ``A``,
    -1 for fixed vertices)."""
    n = g.shape[0]
    for i in range(n):
        for d in range(3):
            k = dof_index[i, d]
            if k >= 0:
                r[k] = 0.0 if held[i] else g[i, d]
    envelope_precondition(first, ptr, values, inverse, r, zr, wb, wx)
    for i in range(n):
        for d in range(3):
            k = dof_index[i, d]
            z[i, d] = 0.0 if (k < 0 or held[i]) else zr[k]


@nb.njit(cache=True)
def _lbfgs_scene(x, v, mass, gravity, ext, alpha, h, held, tets, coef_t, q_t, use_q, law, p, split, w, inv_det,
                 planes, grids, grid_values, k_contact, dof_index, first, ptr, values, inverse, tol, max_iter,
                 history, out):
    """One backward Euler step of one scene by L-BFGS, in place on ``x, v`` ``(n, 3)``.

    On entry ``x`` holds the held vertices' end positions (and the fixed ones' positions)
    and the rest's start positions; ``v`` the start velocities. ``out`` receives
    ``(iterations, residual (N), converged, feasible)``.
    """
    n = x.shape[0]
    c = 1.0 / (h * h) + alpha / h
    x_n = x.copy()
    x_hat = np.empty((n, 3))
    load = np.empty((n, 3))
    for i in range(n):
        for d in range(3):
            x_hat[i, d] = x[i, d] + h * v[i, d] / (1.0 + alpha * h)
            load[i, d] = ext[i, d] + mass[i] * gravity[d]
    n_supports = planes.shape[0] + grids.shape[0]
    f = np.empty((n, 3))
    g = np.zeros((n, 3))
    g_new = np.zeros((n, 3))
    d_vec = np.empty((n, 3))
    trial = np.empty((n, 3))
    dist = np.full(n, math.inf)
    normal = np.zeros((n, 3))
    nd = first.shape[0]
    r = np.empty(nd)
    zr = np.empty(nd)
    wb = np.empty(nd)
    wx = np.empty(nd)
    s_hist = np.zeros((history, n, 3))
    y_hist = np.zeros((history, n, 3))
    rho = np.zeros(history)
    a_coef = np.zeros(history)
    # start: the explicit predictor for the free vertices, else where they are
    for i in range(n):
        if not held[i]:
            for d in range(3):
                trial[i, d] = x[i, d] + h * v[i, d]
        else:
            for d in range(3):
                trial[i, d] = x[i, d]
    args = (mass, c, x_hat, load, held, k_contact, tets, coef_t, q_t, use_q, law, p, split, w, inv_det, planes,
            grids, grid_values, n_supports)
    phi = _potential_and_gradient(trial, True, g, f, dist, normal, *args)
    if math.isfinite(phi):
        x[:, :] = trial
    else:
        phi = _potential_and_gradient(x, True, g, f, dist, normal, *args)
        if not math.isfinite(phi):
            out[0], out[1], out[2], out[3] = 0.0, math.inf, 0.0, 0.0
            return
    gnorm = math.sqrt(_dot(g, g))
    stored = 0
    newest = -1
    it = 0
    while gnorm > tol and it < max_iter:
        it += 1
        # two-loop recursion: d = -H g
        d_vec[:, :] = g
        k = newest
        for _ in range(stored):
            a_coef[k] = rho[k] * _dot(s_hist[k], d_vec)
            d_vec -= a_coef[k] * y_hist[k]
            k = (k - 1) % history
        _precondition(d_vec, trial, held, dof_index, first, ptr, values, inverse, r, zr, wb, wx)
        d_vec[:, :] = trial
        k = (newest - stored + 1) % history
        for _ in range(stored):
            b = rho[k] * _dot(y_hist[k], d_vec)
            d_vec += (a_coef[k] - b) * s_hist[k]
            k = (k + 1) % history
        d_vec *= -1.0
        slope = _dot(g, d_vec)
        if not slope < 0.0:  # not a descent direction: restart from the constant Hessian
            stored = 0
            _precondition(g, d_vec, held, dof_index, first, ptr, values, inverse, r, zr, wb, wx)
            d_vec *= -1.0
            slope = _dot(g, d_vec)
            if not slope < 0.0:
                break
        step = 1.0
        accepted = False
        for _ in range(40):
            for i in range(n):
                for dd in range(3):
                    trial[i, dd] = x[i, dd] + step * d_vec[i, dd]
            phi_t = _potential_and_gradient(trial, True, g_new, f, dist, normal, *args)
            if math.isfinite(phi_t):
                # Armijo on the potential or, near convergence where its round-off hides the
                # decrease, a smaller residual (as Newton's line search)
                if phi_t <= phi + 1e-4 * step * slope or math.sqrt(_dot(g_new, g_new)) < (1.0 - 1e-4 * step) * gnorm:
                    accepted = True
                    break
            step *= 0.5
        if not accepted:
            break  # no progress possible at this precision: keep the best iterate
        phi = phi_t
        newest = (newest + 1) % history
        sy = 0.0
        for i in range(n):
            for dd in range(3):
                s_hist[newest, i, dd] = trial[i, dd] - x[i, dd]
                y_hist[newest, i, dd] = g_new[i, dd] - g[i, dd]
        sy = _dot(s_hist[newest], y_hist[newest])
        if sy > 1e-300:
            rho[newest] = 1.0 / sy
            stored = min(stored + 1, history)
        else:
            newest = (newest - 1) % history
        x[:, :] = trial
        g[:, :] = g_new
        gnorm = math.sqrt(_dot(g, g))
    # velocities; vertices inside a support (``dist``, ``normal``: at the last gradient's
    # iterate, which is ``x``) go onto it and lose their velocity into it
    for i in range(n):
        inside = n_supports > 0 and not held[i] and dist[i] < 0.0
        if inside:
            for d in range(3):
                x[i, d] -= dist[i] * normal[i, d]
        for d in range(3):
            v[i, d] = (x[i, d] - x_n[i, d]) / h
        if inside:
            vn = min(v[i, 0] * normal[i, 0] + v[i, 1] * normal[i, 1] + v[i, 2] * normal[i, 2], 0.0)
            for d in range(3):
                v[i, d] -= vn * normal[i, d]
    out[0], out[1], out[2], out[3] = float(it), gnorm, 1.0 if gnorm <= tol else 0.0, 1.0


@nb.njit(cache=True, parallel=True)
def lbfgs_steps_parallel(x, v, mass, gravity, ext, alpha, h, held, tets, coef_t, q_t, use_q, laws, params, split,
                         weights, inv_det, planes, grids, grid_values, k_contact, dof_index, first, ptr, values,
                         inverse, tol, max_iter, history, active, out):
    """:func:`_lbfgs_scene` for every active scene (leading axis N), scenes over threads."""
    for s in prange(x.shape[0]):
        if active[s]:
            _lbfgs_scene(x[s], v[s], mass, gravity, ext[s], alpha, h, held[s], tets, coef_t, q_t, use_q, laws[s],
                         params[s], split, weights[s], inv_det, planes, grids, grid_values, k_contact, dof_index,
                         first, ptr, values, inverse, tol[s], max_iter, history, out[s])


@nb.njit(cache=True)
def lbfgs_steps_serial(x, v, mass, gravity, ext, alpha, h, held, tets, coef_t, q_t, use_q, laws, params, split,
                       weights, inv_det, planes, grids, grid_values, k_contact, dof_index, first, ptr, values,
                       inverse, tol, max_iter, history, active, out):
    """:func:`lbfgs_steps_parallel` scene after scene."""
    for s in range(x.shape[0]):
        if active[s]:
            _lbfgs_scene(x[s], v[s], mass, gravity, ext[s], alpha, h, held[s], tets, coef_t, q_t, use_q, laws[s],
                         params[s], split, weights[s], inv_det, planes, grids, grid_values, k_contact, dof_index,
                         first, ptr, values, inverse, tol[s], max_iter, history, out[s])
