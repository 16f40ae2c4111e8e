"""Numba kernels of the nonlinear mass-tensor force field (Saint Venant-Kirchhoff).

Units: positions and displacements in m, tensors ``K`` in N/m, ``C`` in N/m^2, ``D`` in
N/m^3 (J/m^2, J/m^3, J/m^4), energies in J, forces in N.

Per tet ``t`` the precomputation (:mod:`heml_gym.forces.mass_tensor`) stores the full,
unfactored tensors contiguously, local vertex indices ``j, k, l, m, p`` in ``0..3`` and
Cartesian indices ``a, b`` in ``0..2``:

* ``K[t, 36 p + 9 k + 3 a + b]`` = ``(K_pk)_ab``  (144 numbers),
* ``C[t, 48 j + 12 k + 3 l + a]`` = ``(C_jkl)_a``  (192 numbers),
* ``D[t, 64 j + 16 k + 4 l + m]`` = ``D_jklm``      (256 numbers).

With nodal displacements ``u_j = x_j - X_j`` the tet energy is the quartic polynomial

    W = sum_jk u_j^T K_jk u_k + sum_jkl (u_j . u_k)(C_jkl . u_l)
        + sum_jklm D_jklm (u_j . u_k)(u_l . u_m)

and, since ``K_kp = K_pk^T``, ``C_jkl = C_kjl`` and ``D`` is symmetric under
``j <-> k``, ``l <-> m`` and ``(j, k) <-> (l, m)``, the force on local vertex ``p`` is

    f_p = -[ 2 sum_k K_pk u_k + 2 sum_kl u_k (C_pkl . u_l) + sum_jk (u_j . u_k) C_jkp
             + 4 sum_klm D_pklm u_k (u_l . u_m) ].

The force kernel evaluates it in the published per-element form of the mass-tensor
method: the displacement dot products are formed inside the loops, for every ``p``, and
not factored out. The kernels use scalar arithmetic on array elements only (no
allocation inside the kernels), so they also run as plain Python (``NUMBA_DISABLE_JIT=1``)
on object arrays of operation-counting scalars; the displacement work array ``u``
``(n, 3)`` is passed in by the caller and overwritten.

Forces are accumulated race-free as in :mod:`heml_gym.forces.kernels_heml`: tets are
split into ``buf.shape[0]`` contiguous chunks, each adding into its own ``buf[c]``, then
:func:`~heml_gym.forces.kernels_heml.reduce_chunks` sums them into ``buf[0]``.
"""

from __future__ import annotations

import numba as nb
from numba import prange

from .kernels_heml import reduce_chunks


@nb.njit(cache=True)
def displacements(x, rest, u):
    """Write the nodal displacements ``u = x - rest`` (m) into ``u`` ``(n, 3)``."""
    for i in range(x.shape[0]):
        u[i, 0] = x[i, 0] - rest[i, 0]
        u[i, 1] = x[i, 1] - rest[i, 1]
        u[i, 2] = x[i, 2] - rest[i, 2]


@nb.njit(cache=True)
def mass_tensor_forces_chunk(u, tets, K, C, D, f, lo, hi):
    """Add the mass-tensor StVK forces (N) of tets ``lo..hi-1`` into ``f``, from displacements ``u`` (m)."""
    for t in range(lo, hi):
        for p in range(4):
            # linear term: sum_k K_pk u_k
            lx = 0.0
            ly = 0.0
            lz = 0.0
            for k in range(4):
                ik = tets[t, k]
                ukx = u[ik, 0]
                uky = u[ik, 1]
                ukz = u[ik, 2]
                o = 36 * p + 9 * k
                lx += K[t, o] * ukx + K[t, o + 1] * uky + K[t, o + 2] * ukz
                ly += K[t, o + 3] * ukx + K[t, o + 4] * uky + K[t, o + 5] * ukz
                lz += K[t, o + 6] * ukx + K[t, o + 7] * uky + K[t, o + 8] * ukz
            # cubic terms: sum_kl u_k (C_pkl . u_l) and sum_jk (u_j . u_k) C_jkp
            ax = 0.0
            ay = 0.0
            az = 0.0
            bx = 0.0
            by = 0.0
            bz = 0.0
            for j in range(4):
                ij = tets[t, j]
                ujx = u[ij, 0]
                ujy = u[ij, 1]
                ujz = u[ij, 2]
                for k in range(4):
                    ik = tets[t, k]
                    ukx = u[ik, 0]
                    uky = u[ik, 1]
                    ukz = u[ik, 2]
                    # u_j (C_pjk . u_k)
                    o = 48 * p + 12 * j + 3 * k
                    s = C[t, o] * ukx + C[t, o + 1] * uky + C[t, o + 2] * ukz
                    ax += s * ujx
                    ay += s * ujy
                    az += s * ujz
                    # (u_j . u_k) C_jkp
                    d = ujx * ukx + ujy * uky + ujz * ukz
                    o = 48 * j + 12 * k + 3 * p
                    bx += d * C[t, o]
                    by += d * C[t, o + 1]
                    bz += d * C[t, o + 2]
            # quartic term: sum_klm D_pklm u_k (u_l . u_m)
            qx = 0.0
            qy = 0.0
            qz = 0.0
            for k in range(4):
                ik = tets[t, k]
                ukx = u[ik, 0]
                uky = u[ik, 1]
                ukz = u[ik, 2]
                for l in range(4):  # noqa: E741
                    il = tets[t, l]
                    ulx = u[il, 0]
                    uly = u[il, 1]
                    ulz = u[il, 2]
                    for mm in range(4):
                        im = tets[t, mm]
                        d = ulx * u[im, 0] + uly * u[im, 1] + ulz * u[im, 2]
                        w = D[t, 64 * p + 16 * k + 4 * l + mm] * d
                        qx += w * ukx
                        qy += w * uky
                        qz += w * ukz
            ip = tets[t, p]
            f[ip, 0] -= 2.0 * (lx + ax) + bx + 4.0 * qx
            f[ip, 1] -= 2.0 * (ly + ay) + by + 4.0 * qy
            f[ip, 2] -= 2.0 * (lz + az) + bz + 4.0 * qz


@nb.njit(cache=True, parallel=True)
def mass_tensor_forces_parallel(x, rest, tets, K, C, D, u, buf):
    """Mass-tensor forces at positions ``x`` (m), one chunk of tets per thread, into ``buf[0]``.

    ``rest`` are the rest positions (m), ``u`` an ``(n, 3)`` work array (overwritten with
    the displacements), ``buf`` ``(n_chunks, n, 3)`` must be zero on entry.
    """
    displacements(x, rest, u)
    n_chunks = buf.shape[0]
    m = tets.shape[0]
    for c in prange(n_chunks):
        mass_tensor_forces_chunk(u, tets, K, C, D, buf[c], c * m // n_chunks, (c + 1) * m // n_chunks)
    reduce_chunks(buf)


@nb.njit(cache=True, inline="always")
def tet_energy(u, tets, K, C, D, t):
    """Mass-tensor StVK energy (J) of tet ``t`` from the displacements ``u`` (m)."""
    w2 = 0.0
    w3 = 0.0
    w4 = 0.0
    for j in range(4):
        ij = tets[t, j]
        ujx = u[ij, 0]
        ujy = u[ij, 1]
        ujz = u[ij, 2]
        for k in range(4):
            ik = tets[t, k]
            ukx = u[ik, 0]
            uky = u[ik, 1]
            ukz = u[ik, 2]
            o = 36 * j + 9 * k
            w2 += (ujx * (K[t, o] * ukx + K[t, o + 1] * uky + K[t, o + 2] * ukz)
                   + ujy * (K[t, o + 3] * ukx + K[t, o + 4] * uky + K[t, o + 5] * ukz)
                   + ujz * (K[t, o + 6] * ukx + K[t, o + 7] * uky + K[t, o + 8] * ukz))
            djk = ujx * ukx + ujy * uky + ujz * ukz
            for l in range(4):  # noqa: E741
                il = tets[t, l]
                ulx = u[il, 0]
                uly = u[il, 1]
                ulz = u[il, 2]
                o = 48 * j + 12 * k + 3 * l
                w3 += djk * (C[t, o] * ulx + C[t, o + 1] * uly + C[t, o + 2] * ulz)
                for mm in range(4):
                    im = tets[t, mm]
                    dlm = ulx * u[im, 0] + uly * u[im, 1] + ulz * u[im, 2]
                    w4 += D[t, 64 * j + 16 * k + 4 * l + mm] * djk * dlm
    return w2 + w3 + w4


@nb.njit(cache=True)
def mass_tensor_energy_chunk(u, tets, K, C, D, lo, hi):
    """Mass-tensor StVK energy (J) of tets ``lo..hi-1`` from the displacements ``u`` (m)."""
    total = 0.0
    for t in range(lo, hi):
        total += tet_energy(u, tets, K, C, D, t)
    return total


@nb.njit(cache=True, parallel=True)
def mass_tensor_energy_parallel(u, tets, K, C, D, n_chunks):
    """Total mass-tensor StVK energy (J), one chunk of tets per thread."""
    m = tets.shape[0]
    total = 0.0
    for c in prange(n_chunks):
        total += mass_tensor_energy_chunk(u, tets, K, C, D, c * m // n_chunks, (c + 1) * m // n_chunks)
    return total
