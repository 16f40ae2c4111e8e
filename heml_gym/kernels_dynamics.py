"""Numba kernels of the time integrators (per-vertex updates; the forces come from a field)."""

from __future__ import annotations

import numba as nb


@nb.njit(cache=True)
def symplectic_euler_update(x, v, f, mass, gravity, ext, alpha, h, fixed, kinematic,
                            kin_from, kin_to, frac, max_speed, reaction):
    """One symplectic Euler sub-step of length ``h`` (s), in place, given elastic forces ``f`` (N) at ``x``.

    Free vertices: ``v += h (f + ext + m g - alpha m v) / m``, then ``x += h v``. Fixed
    vertices keep ``x`` and get ``v = 0``; kinematic ones move to
    ``kin_from + frac (kin_to - kin_from)`` with the velocity that takes them there.
    ``reaction`` receives the constraint force (N) on held vertices (``m a`` minus every
    other force) and 0 elsewhere. Returns the first vertex whose state went non-finite or
    faster than ``max_speed`` (m/s), or -1.
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
        if bad < 0 and not (speed2 <= limit and abs(x[i, 0]) + abs(x[i, 1]) + abs(x[i, 2]) < 1e300):
            bad = i
    return bad
