"""Numba kernels of the textbook F-based P1 finite-element force field.

Per tet: ``F = Ds Dm^-1``, first Piola-Kirchhoff stress ``P = dPsi/dF`` from each law's
textbook formula (written here in F, independently of the invariant derivatives that
HEML uses), and nodal forces ``[f1 f2 f3] = -V0 P Dm^-T``, ``f0 = -(f1 + f2 + f3)``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba import prange

from ..materials import (
    DEMIRAY,
    MOONEY_RIVLIN,
    NEO_HOOKEAN,
    ST_VENANT_KIRCHHOFF,
    STABLE_NEO_HOOKEAN,
)
from .kernels_heml import reduce_chunks


@nb.njit(cache=True, inline="always")
def deformation_gradient(x, tets, dm_inv, t, F):
    """Write ``F = Ds Dm^-1`` of tet ``t`` into the 3x3 array ``F``."""
    i0 = tets[t, 0]
    for r in range(3):
        d1 = x[tets[t, 1], r] - x[i0, r]
        d2 = x[tets[t, 2], r] - x[i0, r]
        d3 = x[tets[t, 3], r] - x[i0, r]
        for c in range(3):
            F[r, c] = d1 * dm_inv[t, 0, c] + d2 * dm_inv[t, 1, c] + d3 * dm_inv[t, 2, c]


@nb.njit(cache=True, inline="always")
def cofactor(F, K):
    """Write the cofactor matrix ``cof F = det(F) F^-T`` into ``K``; return ``det F``."""
    K[0, 0] = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    K[0, 1] = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    K[0, 2] = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    K[1, 0] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    K[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    K[1, 2] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    K[2, 0] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    K[2, 1] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    K[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    return F[0, 0] * K[0, 0] + F[0, 1] * K[0, 1] + F[0, 2] * K[0, 2]


@nb.njit(cache=True, inline="always")
def right_cauchy_green(F, C):
    """Write ``C = F^T F`` into ``C``."""
    for i in range(3):
        for j in range(3):
            C[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]


@nb.njit(cache=True)
def energy_density(law, p, F, K, C):
    """Textbook ``Psi(F)`` in Pa (``K``, ``C`` are 3x3 scratch arrays)."""
    jac = cofactor(F, K)
    right_cauchy_green(F, C)
    i1 = C[0, 0] + C[1, 1] + C[2, 2]
    if law == NEO_HOOKEAN:
        if jac <= 0.0:
            return math.inf
        lnj = math.log(jac)
        return 0.5 * p[0] * (i1 - 3.0) - p[0] * lnj + 0.5 * p[1] * lnj * lnj
    if law == ST_VENANT_KIRCHHOFF:
        ee = 0.0  # E : E with E = (C - I) / 2
        for i in range(3):
            for j in range(3):
                e = 0.5 * (C[i, j] - (1.0 if i == j else 0.0))
                ee += e * e
        tr_e = 0.5 * (i1 - 3.0)
        return p[0] * ee + 0.5 * p[1] * tr_e * tr_e
    if law == STABLE_NEO_HOOKEAN:
        return 0.5 * p[0] * (i1 - 3.0) + 0.5 * p[1] * (jac - p[2]) ** 2 - 0.5 * p[0] * math.log(i1 + 1.0) + p[3]
    if jac <= 0.0:
        return math.inf
    j23 = jac ** (-2.0 / 3.0)
    vol = 0.5 * p[2] * (jac - 1.0) ** 2
    if law == MOONEY_RIVLIN:
        cc = 0.0
        for i in range(3):
            for j in range(3):
                cc += C[i, j] * C[j, i]
        i2 = 0.5 * (i1 * i1 - cc)
        return p[0] * (j23 * i1 - 3.0) + p[1] * (j23 * j23 * i2 - 3.0) + vol
    if law == DEMIRAY:
        return 0.5 * p[0] / p[1] * (math.exp(p[1] * (j23 * i1 - 3.0)) - 1.0) + vol
    return math.nan


@nb.njit(cache=True)
def first_piola(law, p, F, K, C, P):
    """Write the textbook first Piola-Kirchhoff stress ``P = dPsi/dF`` (Pa) into ``P``."""
    jac = cofactor(F, K)  # K = J F^-T
    right_cauchy_green(F, C)
    i1 = C[0, 0] + C[1, 1] + C[2, 2]
    if law == NEO_HOOKEAN:
        # P = mu (F - F^-T) + lam ln J F^-T
        if jac <= 0.0:
            P[:, :] = math.nan
            return
        lnj = math.log(jac)
        for i in range(3):
            for j in range(3):
                P[i, j] = p[0] * F[i, j] + (p[1] * lnj - p[0]) * K[i, j] / jac
    elif law == ST_VENANT_KIRCHHOFF:
        # P = F S, S = lam tr(E) I + 2 mu E
        tr_e = 0.5 * (i1 - 3.0)
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    s_kj = p[0] * (C[k, j] - (1.0 if k == j else 0.0))
                    if k == j:
                        s_kj += p[1] * tr_e
                    acc += F[i, k] * s_kj
                P[i, j] = acc
    elif law == STABLE_NEO_HOOKEAN:
        # P = mu (1 - 1/(I1 + 1)) F + lam (J - alpha) cof F
        a = p[0] * (1.0 - 1.0 / (i1 + 1.0))
        b = p[1] * (jac - p[2])
        for i in range(3):
            for j in range(3):
                P[i, j] = a * F[i, j] + b * K[i, j]
    elif law == MOONEY_RIVLIN or law == DEMIRAY:
        if jac <= 0.0:
            P[:, :] = math.nan
            return
        j23 = jac ** (-2.0 / 3.0)
        vol = p[2] * (jac - 1.0)  # times cof F = J F^-T
        if law == MOONEY_RIVLIN:
            # P = 2 c10 J^-2/3 (F - I1/3 F^-T) + 2 c01 J^-4/3 (I1 F - F C - 2/3 I2 F^-T)
            cc = 0.0
            for i in range(3):
                for j in range(3):
                    cc += C[i, j] * C[j, i]
            i2 = 0.5 * (i1 * i1 - cc)
            a = 2.0 * p[0] * j23
            b = 2.0 * p[1] * j23 * j23
            for i in range(3):
                for j in range(3):
                    fc = F[i, 0] * C[0, j] + F[i, 1] * C[1, j] + F[i, 2] * C[2, j]
                    finv_t = K[i, j] / jac
                    P[i, j] = (a * (F[i, j] - i1 / 3.0 * finv_t)
                               + b * (i1 * F[i, j] - fc - 2.0 / 3.0 * i2 * finv_t)
                               + vol * K[i, j])
        else:
            # P = a exp(b (J^-2/3 I1 - 3)) J^-2/3 (F - I1/3 F^-T) + kappa (J - 1) cof F
            g = p[0] * math.exp(p[1] * (j23 * i1 - 3.0)) * j23
            for i in range(3):
                for j in range(3):
                    P[i, j] = g * (F[i, j] - i1 / 3.0 * K[i, j] / jac) + vol * K[i, j]
    else:
        P[:, :] = math.nan


@nb.njit(cache=True)
def fem_forces_chunk(x, tets, dm_inv, vol, law, p, f, lo, hi):
    """Add the F-based FEM forces (N) of tets ``lo..hi-1`` at positions ``x`` (m) into ``f``."""
    F = np.empty((3, 3))
    K = np.empty((3, 3))
    C = np.empty((3, 3))
    P = np.empty((3, 3))
    for t in range(lo, hi):
        deformation_gradient(x, tets, dm_inv, t, F)
        first_piola(law, p, F, K, C, P)
        # H = -V0 P Dm^-T: column a is the force on local vertex a + 1
        for r in range(3):
            h0 = 0.0
            for a in range(3):
                h = -vol[t] * (P[r, 0] * dm_inv[t, a, 0] + P[r, 1] * dm_inv[t, a, 1]
                               + P[r, 2] * dm_inv[t, a, 2])
                f[tets[t, a + 1], r] += h
                h0 += h
            f[tets[t, 0], r] -= h0


@nb.njit(cache=True, parallel=True)
def fem_forces_parallel(x, tets, dm_inv, vol, law, p, buf):
    """FEM forces, one chunk of tets per thread, summed into ``buf[0]`` (zero on entry)."""
    n_chunks = buf.shape[0]
    m = tets.shape[0]
    for c in prange(n_chunks):
        fem_forces_chunk(x, tets, dm_inv, vol, law, p, buf[c], c * m // n_chunks, (c + 1) * m // n_chunks)
    reduce_chunks(buf)


@nb.njit(cache=True)
def fem_energy_chunk(x, tets, dm_inv, vol, law, p, lo, hi):
    """Elastic energy (J) of tets ``lo..hi-1``: sum of ``V0 Psi(F)``."""
    F = np.empty((3, 3))
    K = np.empty((3, 3))
    C = np.empty((3, 3))
    total = 0.0
    for t in range(lo, hi):
        deformation_gradient(x, tets, dm_inv, t, F)
        total += vol[t] * energy_density(law, p, F, K, C)
    return total


@nb.njit(cache=True, parallel=True)
def fem_energy_parallel(x, tets, dm_inv, vol, law, p, n_chunks):
    """Total elastic energy (J), one chunk of tets per thread."""
    m = tets.shape[0]
    total = 0.0
    for c in prange(n_chunks):
        total += fem_energy_chunk(x, tets, dm_inv, vol, law, p, c * m // n_chunks, (c + 1) * m // n_chunks)
    return total
