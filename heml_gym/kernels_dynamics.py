"""Numba kernels of the time integrators (per-vertex updates; the forces come from a field)."""

from __future__ import annotations

import math

import numba as nb

from .forces.kernels_heml import constant_psi1_forces_chunk


@nb.njit(cache=True)
def symplectic_euler_update(x, v, f, mass, gravity, ext, alpha, h, fixed, kinematic,
                            kin_from, kin_to, frac, max_speed, reaction, floor_z=-math.inf):
    """One symplectic Euler sub-step of length ``h`` (s), in place, given elastic forces ``f`` (N) at ``x``.

    Free vertices: ``v += h (f + ext + m g - alpha m v) / m``, then ``x += h v``. Fixed
    vertices keep ``x`` and get ``v = 0``; kinematic ones move to
    ``kin_from + frac (kin_to - kin_from)`` with the velocity that takes them there.
    ``reaction`` receives the constraint force (N) on held vertices (``m a`` minus every
    other force) and 0 elsewhere. A free vertex that ends below the plane
    ``z = floor_z`` (m; a rigid, frictionless support) is put back on it and loses its
    downward velocity. Returns the first vertex whose state went non-finite or faster than
    ``max_speed`` (m/s), or -1.
    """
    bad = -1
    limit = max_speed * max_speed
    for i in range(x.shape[0]):
        m = mass[i]
        speed2 = 0.0
        if fixed[i]:
            for d in range(3):
                reaction[i, d] = -(f[i, d] + ext[i, d] + m * gravity[d] - alpha * m * v[i, d]) + m * (0.0 - v[i, d]) / h
                v[i, d] = 0.0
        elif kinematic[i]:
            for d in range(3):
                target = kin_from[i, d] + frac * (kin_to[i, d] - kin_from[i, d])
                vn = (target - x[i, d]) / h
                total = f[i, d] + ext[i, d] + m * gravity[d] - alpha * m * v[i, d]
                reaction[i, d] = m * (vn - v[i, d]) / h - total
                v[i, d] = vn
                x[i, d] = target
                speed2 += vn * vn
        else:
            for d in range(3):
                total = f[i, d] + ext[i, d] + m * gravity[d] - alpha * m * v[i, d]
                vn = v[i, d] + h * total / m
                v[i, d] = vn
                x[i, d] += h * vn
                reaction[i, d] = 0.0
                speed2 += vn * vn
            if x[i, 2] < floor_z:  # resting on the support
                x[i, 2] = floor_z
                v[i, 2] = max(v[i, 2], 0.0)
        if bad < 0 and not (speed2 <= limit and abs(x[i, 0]) + abs(x[i, 1]) + abs(x[i, 2]) < 1e300):
            bad = i
    return bad


@nb.njit(cache=True)
def explicit_substeps_constant_psi1(x, v, f, reaction, sub_reaction, mass, gravity, ext, alpha, h,
                                    n_sub, fixed, kinematic, kin_from, kin_to, max_speed,
                                    tets, inv_det, w, law, p, floor_z=-math.inf):
    """``n_sub`` symplectic Euler sub-steps of a constant-``Psi_1`` HEML body in one call.

    The force kernel is :func:`~heml_gym.forces.kernels_heml.constant_psi1_forces_chunk`
    (arguments ``tets, inv_det, w, law, p``); the rest as
    :func:`symplectic_euler_update`. ``reaction`` receives the constraint forces (N)
    averaged over the sub-steps, ``sub_reaction`` (scratch, same shape) those of each one.
    Returns ``(sub-steps done, first bad vertex or -1)``.
    """
    m = tets.shape[0]
    reaction[:, :] = 0.0
    for k in range(1, n_sub + 1):
        f[:, :] = 0.0
        constant_psi1_forces_chunk(x, tets, inv_det, w, law, p, f, 0, m)
        bad = symplectic_euler_update(x, v, f, mass, gravity, ext, alpha, h, fixed, kinematic,
                                      kin_from, kin_to, k / n_sub, max_speed, sub_reaction, floor_z)
        if bad >= 0:
            return k, bad
        for i in range(x.shape[0]):
            if fixed[i] or kinematic[i]:
                for d in range(3):
                    reaction[i, d] += sub_reaction[i, d] / n_sub
    return n_sub, -1
