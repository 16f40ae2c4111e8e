"""Ray and segment casts against triangles in plain numpy (Moller-Trumbore), the
independent reference the camera and exposure tests compare the envs' own kernels with."""

from __future__ import annotations

import numpy as np


def _crossings(origin, direction, triangles):
    """Every triangle ``(t, 3, 3)`` against the line ``origin + s direction``: the
    parameter ``s``, the barycentric ``u, v`` of the crossing, and whether the line is
    not parallel to the triangle's plane."""
    a = triangles[:, 0]
    e1, e2 = triangles[:, 1] - a, triangles[:, 2] - a
    p = np.cross(direction, e2)
    det = (e1 * p).sum(axis=1)
    ok = np.abs(det) > 1e-20
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    r = origin - a
    u = (r * p).sum(axis=1) * inv
    q = np.cross(r, e1)
    v = (q @ direction) * inv
    s = (q * e2).sum(axis=1) * inv
    return s, u, v, ok & (u >= 0) & (v >= 0) & (u + v <= 1)


def first_hits(origin, directions, triangles):
    """Per ray from ``origin`` along ``directions`` (k, 3): the nearest hit's distance in
    units of the direction's length, the index of the triangle hit, and the hit's smallest
    barycentric coordinate (how far inside the triangle); ``(inf, -1, 0)`` for a miss."""
    best_t = np.full(len(directions), np.inf)
    best_k = np.full(len(directions), -1)
    best_w = np.zeros(len(directions))
    for r, d in enumerate(directions):
        s, u, v, inside = _crossings(origin, d, triangles)
        hit = inside & (s > 1e-9)
        if hit.any():
            k = np.flatnonzero(hit)[np.argmin(s[hit])]
            best_t[r], best_k[r] = s[k], k
            best_w[r] = min(u[k], v[k], 1 - u[k] - v[k])
    return best_t, best_k, best_w


def segments_blocked(eye, points, triangles):
    """Per point (k, 3): does a triangle cross the segment from ``eye`` to it (strictly
    between its ends)?"""
    blocked = np.zeros(len(points), dtype=bool)
    for i, p in enumerate(points):
        s, _, _, inside = _crossings(eye, p - eye, triangles)
        blocked[i] = np.any(inside & (s > 1e-9) & (s < 1 - 1e-9))
    return blocked
