"""Numba kernels of the mass-spring baseline: one linear spring per mesh edge."""

from __future__ import annotations

import math

import numba as nb
from numba import prange

from .kernels_heml import reduce_chunks


@nb.njit(cache=True, parallel=True)
def spring_forces(x, edges, stiffness, rest_length, buf):
    """Add ``f_i = k (|x_j - x_i| - L) (x_j - x_i) / |x_j - x_i|`` (N) into ``buf[0]``."""
    n_chunks = buf.shape[0]
    m = edges.shape[0]
    for c in prange(n_chunks):
        f = buf[c]
        for e in range(c * m // n_chunks, (c + 1) * m // n_chunks):
            i = edges[e, 0]
            j = edges[e, 1]
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            w = stiffness[e] * (length - rest_length[e]) / length
            dx *= w
            dy *= w
            dz *= w
            f[i, 0] += dx
            f[i, 1] += dy
            f[i, 2] += dz
            f[j, 0] -= dx
            f[j, 1] -= dy
            f[j, 2] -= dz
    reduce_chunks(buf)


@nb.njit(cache=True, parallel=True)
def spring_energy(x, edges, stiffness, rest_length):
    """Total spring energy (J): ``sum k (|x_j - x_i| - L)^2 / 2``."""
    total = 0.0
    for e in prange(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz) - rest_length[e]
        total += 0.5 * stiffness[e] * d * d
    return total
