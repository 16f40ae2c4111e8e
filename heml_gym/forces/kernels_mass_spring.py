"""Numba kernels of the mass-spring baseline: one linear spring per mesh edge."""

from __future__ import annotations

import math

import numba as nb
from numba import prange

from .kernels_heml import reduce_chunks


@nb.njit(cache=True)
def spring_forces_chunk(x, edges, stiffness, rest_length, f, lo, hi):
    """Add ``f_i = k (|x_j - x_i| - L) (x_j - x_i) / |x_j - x_i|`` (N) of springs ``lo..hi-1``."""
    for e in range(lo, hi):
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


@nb.njit(cache=True, parallel=True)
def spring_forces_parallel(x, edges, stiffness, rest_length, buf):
    """Spring forces, one chunk of springs per thread, summed into ``buf[0]`` (zero on entry)."""
    n_chunks = buf.shape[0]
    m = edges.shape[0]
    for c in prange(n_chunks):
        spring_forces_chunk(x, edges, stiffness, rest_length, buf[c], c * m // n_chunks, (c + 1) * m // n_chunks)
    reduce_chunks(buf)


@nb.njit(cache=True)
def spring_energy_chunk(x, edges, stiffness, rest_length, lo, hi):
    """Spring energy (J) of springs ``lo..hi-1``: ``sum k (|x_j - x_i| - L)^2 / 2``."""
    total = 0.0
    for e in range(lo, hi):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz) - rest_length[e]
        total += 0.5 * stiffness[e] * d * d
    return total


@nb.njit(cache=True, parallel=True)
def spring_energy_parallel(x, edges, stiffness, rest_length, n_chunks):
    """Total spring energy (J), one chunk of springs per thread."""
    m = edges.shape[0]
    total = 0.0
    for c in prange(n_chunks):
        total += spring_energy_chunk(x, edges, stiffness, rest_length, c * m // n_chunks, (c + 1) * m // n_chunks)
    return total
