"""Numba kernels of the elastic stiffness matrix ``K = d2W/dx2`` (HEML and mass-spring).

HEML element Hessian (edge form)
--------------------------------
Per tet ``W_T = V0 Psi(I1(s), I2(s), J(x))`` with the six squared edge lengths ``s_k``
(edge order of :data:`heml_gym.mesh.EDGE_PAIRS`), ``I1 = a . s``, ``I2 = s^T Q s / 2`` and
``J = det(Ds) / (6 V0)``. With ``g_1 = dI1/dx = sum_k a_k ds_k/dx``,
``g_2 = dI2/dx = sum_k (Qs)_k ds_k/dx`` and ``g_J = dJ/dx`` (12-vectors;
``ds_k/dx_a = -2 e_k``, ``ds_k/dx_b = 2 e_k`` for edge ``k = (a, b)``, ``e_k = x_b - x_a``)::

    K_T / V0 = sum_{i,j in (1,2,J)} Psi_ij g_i g_j^T          (law curvature, rank <= 3)
             + Psi_2 sum_kl Q_kl ds_k/dx ds_l/dx^T             (I2 laws only)
             + sum_k 2 Psi'_k [[I, -I], [-I, I]]_(a_k, b_k)    (4x4 edge Laplacian x I3)
             + Psi_J d2J/dx2                                   (linear in x)

with ``Psi'_k = Psi_1 a_k + Psi_2 (Qs)_k`` (the edge weights of the force kernel, over
2 V0). ``d2 det(Ds)`` has zero diagonal blocks and skew off-diagonal blocks ``[v]_x``
(``[v]_x w = v x w``): with ``d_i = x_i - x_0``, block (1,2) = ``-[d3]_x``, (1,3) =
``[d2]_x``, (2,3) = ``-[d1]_x``, (0,1) = ``[d2 - d3]_x``, (0,2) = ``[d3 - d1]_x``,
(0,3) = ``[d1 - d2]_x`` and block (b, a) = block (a, b)^T.

Definiteness fix (analytic, per tet)
------------------------------------
``K_T = V0 B^T H_F B`` where ``B = dF/dx`` (9 x 12, onto) and ``H_F = d2Psi/dF2``, so
``K_T`` is PSD iff ``H_F`` is. For an isotropic ``Psi(I1, I2, J)`` at ``F = U S V^T``
(``U, V`` rotations, ``S = diag(s1, s2, s3)`` with ``s3 < 0`` when inverted), ``H_F`` has
the closed-form eigensystem of Smith, de Goes and Kim 2019 ("Analytic eigensystems for
isotropic distortion energies"); in invariants (no division, so repeated singular
values need no special case), for each pair ``(i, j)`` with third index ``k``:

* twist ``U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2``:
  ``2 Psi_1 + 2 Psi_2 (s_k^2 + s_i s_j) + Psi_J s_k``
* flip ``U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2``:
  ``2 Psi_1 + 2 Psi_2 (s_k^2 - s_i s_j) - Psi_J s_k``
* three scaling modes ``U diag(z) V^T``, ``z`` the eigenvectors of the 3x3
  ``d2Psi/ds_i ds_j``.

The fix subtracts ``V0 lambda b b^T`` for every negative mode ``lambda`` (``b = B^T vec``
of the unit mode): ``K_T`` becomes ``V0 B^T (H_F)_+ B``, PSD, and is left untouched where
it already was PSD. ``F = Ds Dm^-1``; its signed SVD comes from a scalar cyclic Jacobi
eigen-decomposition of ``C = F^T F`` (about 3 sweeps to rounding) and Gram-Schmidt on
``F V``; the 3x3 scaling block is eigen-decomposed only when it is not safely positive
definite. ``project=2`` instead clamps the eigenvalues of the 12x12 ``K_T`` (LAPACK
``eigh``): the slow reference.

Assembly adds the 12x12 element blocks into a CSR ``data`` array by precomputed
positions (see :mod:`heml_gym.forces.hessian`); it is serial, hence race-free.

Performance note: helpers that take arrays and run once per tet are compiled without
Numba's reference counting (``_nrt=False``, a speed-only option: they allocate nothing);
otherwise every call increfs / decrefs its array arguments atomically, which cost more
than the element arithmetic. For the same reason the laws (inlined, several returns) are
evaluated in a helper that takes no arrays (:func:`_law_derivatives`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..laws import law_gradient, law_hessian
from .kernels_heml import edge_cofactors, tet_edges

try:  # Numba's private switch to compile a function without reference counting
    from numba.core.options import DefaultOptions as _DefaultOptions

    _NO_NRT = {"_nrt": False} if hasattr(_DefaultOptions, "_nrt") else {}
except ImportError:  # pragma: no cover - other Numba versions: slower, still correct
    _NO_NRT = {}

# local vertices of the six edges (EDGE_PAIRS)
_EA = np.array([0, 0, 0, 1, 1, 2], dtype=np.int64)
_EB = np.array([1, 2, 3, 2, 3, 3], dtype=np.int64)
# index into the 21 stored upper-triangle entries of Q for each (k, l)
_QIDX = np.zeros((6, 6), dtype=np.int64)
_n = 0
for _k in range(6):
    for _l in range(_k, 6):
        _QIDX[_k, _l] = _n
        _QIDX[_l, _k] = _n
        _n += 1
del _n, _k, _l
# (i, j, k) index triples of the twist / flip pairs
_PAIRS = np.array([(0, 1, 2), (0, 2, 1), (1, 2, 0)], dtype=np.int64)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)

NO_PROJECTION = 0
ANALYTIC_PROJECTION = 1
EIGH_PROJECTION = 2


@nb.njit(cache=True)
def _work():
    # ev(6,3) sv(6) qsv(6) g3(3,12) w3(3,12) qg(6,12) U(3,3) W(3,3) Z(3,3) sig(3) lam(9)
    # b(12) gm(3,3)
    return (np.empty((6, 3)), np.empty(6), np.empty(6), np.empty((3, 12)), np.empty((3, 12)),
            np.empty((6, 12)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
            np.empty(3), np.empty(9), np.empty(12), np.empty((3, 3)))


@nb.njit(cache=True, inline="always")
def _add_skew(ke, a, b, s, vx, vy, vz):
    """Block (a, b) += s [v]_x and block (b, a) += s [v]_x^T."""
    ra = 3 * a
    rb = 3 * b
    ke[ra, rb + 1] -= s * vz
    ke[ra, rb + 2] += s * vy
    ke[ra + 1, rb] += s * vz
    ke[ra + 1, rb + 2] -= s * vx
    ke[ra + 2, rb] -= s * vy
    ke[ra + 2, rb + 1] += s * vx
    ke[rb + 1, ra] -= s * vz
    ke[rb + 2, ra] += s * vy
    ke[rb, ra + 1] += s * vz
    ke[rb + 2, ra + 1] -= s * vx
    ke[rb, ra + 2] -= s * vy
    ke[rb + 1, ra + 2] += s * vx


@nb.njit(cache=True, inline="always")
def _add_det_hessian(ke, s, d1x, d1y, d1z, d2x, d2y, d2z, d3x, d3y, d3z):
    """``ke += s d2 det(Ds) / dx2`` for the edges ``d_i = x_i - x_0``: zero diagonal blocks,
    skew off-diagonal blocks (see the module docstring)."""
    _add_skew(ke, 1, 2, -s, d3x, d3y, d3z)
    _add_skew(ke, 1, 3, s, d2x, d2y, d2z)
    _add_skew(ke, 2, 3, -s, d1x, d1y, d1z)
    _add_skew(ke, 0, 1, s, d2x - d3x, d2y - d3y, d2z - d3z)
    _add_skew(ke, 0, 2, s, d3x - d1x, d3y - d1y, d3z - d1z)
    _add_skew(ke, 0, 3, s, d1x - d2x, d1y - d2y, d1z - d2z)


@nb.njit(cache=True, inline="always")
def _add_edge_spring(ke, k, wk):
    """``ke += wk [[I, -I], [-I, I]]`` on the vertices of edge ``k`` (a linear spring, N/m)."""
    ra = 3 * _EA[k]
    rb = 3 * _EB[k]
    for d in range(3):
        ke[ra + d, ra + d] += wk
        ke[rb + d, rb + d] += wk
        ke[ra + d, rb + d] -= wk
        ke[rb + d, ra + d] -= wk


@nb.njit(cache=True)
def _law_derivatives(law, p, i_1, i_2, jac):
    """First and second derivatives of the law; ``p`` is a tuple of 4 parameters.

    The laws are inlined (several returns): kept in a function without array arguments so
    that Numba does not add reference counting of the caller's arrays around them.
    """
    ps1, ps2, psj = law_gradient(law, p, i_1, i_2, jac)
    h11, h12, h1j, h22, h2j, hjj = law_hessian(law, p, i_1, i_2, jac)
    return ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj


@nb.njit(cache=True, **_NO_NRT)
def heml_element_hessian(x, tets, coef, q, use_q, law, p, t, ke, ev, sv, qsv, g3, w3, qg):
    """Exact Hessian ``d2 W_T / dx2`` (12 x 12, J/m^2) of tet ``t`` into ``ke``.

    ``p`` is the law's parameters as a 4-tuple (:func:`_pad4`). Leaves the edge vectors
    in ``ev`` (rows 0..2 are the columns of ``Ds``) and returns
    ``(Psi_1, Psi_2, Psi_J, Psi_11, Psi_12, Psi_1J, Psi_22, Psi_2J, Psi_JJ)``.
    """
    for k in range(6):
        ia = tets[t, _EA[k]]
        ib = tets[t, _EB[k]]
        ex = x[ib, 0] - x[ia, 0]
        ey = x[ib, 1] - x[ia, 1]
        ez = x[ib, 2] - x[ia, 2]
        ev[k, 0] = ex
        ev[k, 1] = ey
        ev[k, 2] = ez
        sv[k] = ex * ex + ey * ey + ez * ez
    v0 = coef[t, 0]
    inv_det = coef[t, 1]
    i_1 = 0.0
    for k in range(6):
        i_1 += coef[t, 2 + k] * sv[k]
    i_2 = 0.0
    if use_q:
        for k in range(6):
            acc = 0.0
            for l in range(6):
                acc += q[t, _QIDX[k, l]] * sv[l]
            qsv[k] = acc
            i_2 += 0.5 * sv[k] * acc
    else:
        for k in range(6):
            qsv[k] = 0.0
    d1x, d1y, d1z = ev[0, 0], ev[0, 1], ev[0, 2]
    d2x, d2y, d2z = ev[1, 0], ev[1, 1], ev[1, 2]
    d3x, d3y, d3z = ev[2, 0], ev[2, 1], ev[2, 2]
    # d det / d d_i: c1 = d2 x d3, c2 = d3 x d1, c3 = d1 x d2
    c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(d1x, d1y, d1z, d2x, d2y, d2z, d3x, d3y, d3z)
    jac = (d1x * c1x + d1y * c1y + d1z * c1z) * inv_det
    ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj = _law_derivatives(law, p, i_1, i_2, jac)

    # gradients of the invariants: g3[0] = dI1/dx, g3[1] = dI2/dx, g3[2] = dJ/dx
    for r in range(12):
        g3[0, r] = 0.0
        g3[1, r] = 0.0
    for k in range(6):
        ra = 3 * _EA[k]
        rb = 3 * _EB[k]
        ak = 2.0 * coef[t, 2 + k]
        qk = 2.0 * qsv[k]
        for d in range(3):
            e = ev[k, d]
            g3[0, ra + d] -= ak * e
            g3[0, rb + d] += ak * e
            g3[1, ra + d] -= qk * e
            g3[1, rb + d] += qk * e
    g3[2, 3] = c1x * inv_det
    g3[2, 4] = c1y * inv_det
    g3[2, 5] = c1z * inv_det
    g3[2, 6] = c2x * inv_det
    g3[2, 7] = c2y * inv_det
    g3[2, 8] = c2z * inv_det
    g3[2, 9] = c3x * inv_det
    g3[2, 10] = c3y * inv_det
    g3[2, 11] = c3z * inv_det
    g3[2, 0] = -(g3[2, 3] + g3[2, 6] + g3[2, 9])
    g3[2, 1] = -(g3[2, 4] + g3[2, 7] + g3[2, 10])
    g3[2, 2] = -(g3[2, 5] + g3[2, 8] + g3[2, 11])

    # law curvature: sum_ij V0 Psi_ij g_i g_j^T
    h00 = v0 * h11
    h01 = v0 * h12
    h02 = v0 * h1j
    h11v = v0 * h22
    h12v = v0 * h2j
    h22v = v0 * hjj
    act0 = h00 != 0.0 or h01 != 0.0 or h02 != 0.0
    act1 = use_q and (h01 != 0.0 or h11v != 0.0 or h12v != 0.0)
    for c in range(12):
        w3[0, c] = h00 * g3[0, c] + h01 * g3[1, c] + h02 * g3[2, c]
        w3[1, c] = h01 * g3[0, c] + h11v * g3[1, c] + h12v * g3[2, c]
        w3[2, c] = h02 * g3[0, c] + h12v * g3[1, c] + h22v * g3[2, c]
    for r in range(12):
        gr = g3[2, r]
        for c in range(12):
            ke[r, c] = gr * w3[2, c]
    if act0:
        for r in range(12):
            gr = g3[0, r]
            for c in range(12):
                ke[r, c] += gr * w3[0, c]
    if act1:
        for r in range(12):
            gr = g3[1, r]
            for c in range(12):
                ke[r, c] += gr * w3[1, c]

    # Psi_2 sum_kl Q_kl ds_k ds_l^T
    if use_q and ps2 != 0.0:
        for k in range(6):
            for c in range(12):
                qg[k, c] = 0.0
        for k in range(6):
            for l in range(6):
                ql = 2.0 * q[t, _QIDX[k, l]]
                ra = 3 * _EA[l]
                rb = 3 * _EB[l]
                for d in range(3):
                    v = ql * ev[l, d]
                    qg[k, ra + d] -= v
                    qg[k, rb + d] += v
        cq = 2.0 * v0 * ps2
        for k in range(6):
            ra = 3 * _EA[k]
            rb = 3 * _EB[k]
            for d in range(3):
                v = cq * ev[k, d]
                for c in range(12):
                    ke[ra + d, c] -= v * qg[k, c]
                    ke[rb + d, c] += v * qg[k, c]

    # edge Laplacian: sum_k V0 Psi'_k d2 s_k, d2 s_k = 2 [[I, -I], [-I, I]]
    for k in range(6):
        _add_edge_spring(ke, k, 2.0 * v0 * (ps1 * coef[t, 2 + k] + ps2 * qsv[k]))

    # V0 Psi_J d2J = Psi_J / 6 d2 det(Ds)
    _add_det_hessian(ke, v0 * inv_det * psj, d1x, d1y, d1z, d2x, d2y, d2z, d3x, d3y, d3z)
    return ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj


# ------------------------------------------------------------------ analytic eigensystem
@nb.njit(cache=True, inline="always")
def _jacobi_rotation(app, aqq, apq, apr, aqr, vp0, vp1, vp2, vq0, vq1, vq2):
    """Rotate the plane (p, q) so that ``a_pq`` vanishes (``r``: the third index).

    Returns the new ``a_pp, a_qq, a_pr, a_qr`` and eigenvector columns ``v_p, v_q``.
    """
    if apq == 0.0:
        return app, aqq, apr, aqr, vp0, vp1, vp2, vq0, vq1, vq2
    # t = tan(angle), the smaller root of t^2 + 2 theta t - 1 = 0, theta = d / (2 a_pq)
    d = aqq - app
    r = math.sqrt(d * d + 4.0 * apq * apq)
    t = 2.0 * apq / (d + r) if d >= 0.0 else 2.0 * apq / (d - r)
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    return (app - t * apq, aqq + t * apq, c * apr - s * aqr, s * apr + c * aqr,
            c * vp0 - s * vq0, c * vp1 - s * vq1, c * vp2 - s * vq2,
            s * vp0 + c * vq0, s * vp1 + c * vq1, s * vp2 + c * vq2)


@nb.njit(cache=True)
def eig3(a00, a01, a02, a11, a12, a22):
    """Eigen-decomposition of a symmetric 3x3 (cyclic Jacobi, on scalars).

    Returns ``(w0, w1, w2, v00, v01, v02, v10, v11, v12, v20, v21, v22)``: the eigenvalues
    (unsorted) and the rotation ``V`` (row by row) whose column ``i`` belongs to ``w_i``.
    Converges to rounding (``|off-diagonal| <= 3e-17 |diagonal|``) in about 3 sweeps.
    """
    # columns of V: c0 = (c00, c01, c02), ...
    c00, c01, c02 = 1.0, 0.0, 0.0
    c10, c11, c12 = 0.0, 1.0, 0.0
    c20, c21, c22 = 0.0, 0.0, 1.0
    for _sweep in range(12):
        off = a01 * a01 + a02 * a02 + a12 * a12
        dia = a00 * a00 + a11 * a11 + a22 * a22
        if not off > 1e-33 * dia:  # converged (or zero / NaN)
            break
        a00, a11, a02, a12, c00, c01, c02, c10, c11, c12 = _jacobi_rotation(
            a00, a11, a01, a02, a12, c00, c01, c02, c10, c11, c12)
        a01 = 0.0
        a00, a22, a01, a12, c00, c01, c02, c20, c21, c22 = _jacobi_rotation(
            a00, a22, a02, a01, a12, c00, c01, c02, c20, c21, c22)
        a02 = 0.0
        a11, a22, a01, a02, c10, c11, c12, c20, c21, c22 = _jacobi_rotation(
            a11, a22, a12, a01, a02, c10, c11, c12, c20, c21, c22)
        a12 = 0.0
    return a00, a11, a22, c00, c10, c20, c01, c11, c21, c02, c12, c22


@nb.njit(cache=True)
def signed_svd3(f00, f01, f02, f10, f11, f12, f20, f21, f22):
    """``F = U diag(s) V^T`` with rotations ``U, V``, ``s0 >= s1 >= |s2|``, ``s2 < 0`` iff
    ``det F < 0``.

    ``V`` and ``s^2`` from :func:`eig3` of ``F^T F``, ``U`` by Gram-Schmidt on ``F V``.
    Returns ``(s0, s1, s2, U row by row, V row by row)``.
    """
    w0, w1, w2, v00, v01, v02, v10, v11, v12, v20, v21, v22 = eig3(
        f00 * f00 + f10 * f10 + f20 * f20, f00 * f01 + f10 * f11 + f20 * f21,
        f00 * f02 + f10 * f12 + f20 * f22, f01 * f01 + f11 * f11 + f21 * f21,
        f01 * f02 + f11 * f12 + f21 * f22, f02 * f02 + f12 * f12 + f22 * f22)
    # sort descending, swapping columns (a swap flips det V: fixed below)
    if w1 > w0:
        w0, w1 = w1, w0
        v00, v01 = v01, v00
        v10, v11 = v11, v10
        v20, v21 = v21, v20
    if w2 > w1:
        w1, w2 = w2, w1
        v01, v02 = v02, v01
        v11, v12 = v12, v11
        v21, v22 = v22, v21
    if w1 > w0:
        w0, w1 = w1, w0
        v00, v01 = v01, v00
        v10, v11 = v11, v10
        v20, v21 = v21, v20
    det_v = (v00 * (v11 * v22 - v12 * v21) - v01 * (v10 * v22 - v12 * v20)
             + v02 * (v10 * v21 - v11 * v20))
    if det_v < 0.0:
        v02, v12, v22 = -v02, -v12, -v22
    # columns f_i = F v_i
    f1x = f00 * v00 + f01 * v10 + f02 * v20
    f1y = f10 * v00 + f11 * v10 + f12 * v20
    f1z = f20 * v00 + f21 * v10 + f22 * v20
    f2x = f00 * v01 + f01 * v11 + f02 * v21
    f2y = f10 * v01 + f11 * v11 + f12 * v21
    f2z = f20 * v01 + f21 * v11 + f22 * v21
    f3x = f00 * v02 + f01 * v12 + f02 * v22
    f3y = f10 * v02 + f11 * v12 + f12 * v22
    f3z = f20 * v02 + f21 * v12 + f22 * v22
    n1 = math.sqrt(f1x * f1x + f1y * f1y + f1z * f1z)
    if n1 > 1e-300:
        inv = 1.0 / n1
        u1x, u1y, u1z = f1x * inv, f1y * inv, f1z * inv
    else:
        u1x, u1y, u1z = 1.0, 0.0, 0.0
    dot = u1x * f2x + u1y * f2y + u1z * f2z
    g2x = f2x - dot * u1x
    g2y = f2y - dot * u1y
    g2z = f2z - dot * u1z
    n2 = math.sqrt(g2x * g2x + g2y * g2y + g2z * g2z)
    if n2 > 1e-13 * n1 and n2 > 1e-300:
        inv = 1.0 / n2
        u2x, u2y, u2z = g2x * inv, g2y * inv, g2z * inv
    else:  # rank <= 1: any unit vector orthogonal to u1
        ax, ay, az = abs(u1x), abs(u1y), abs(u1z)
        if ax <= ay and ax <= az:
            u2x, u2y, u2z = 0.0, -u1z, u1y
        elif ay <= az:
            u2x, u2y, u2z = u1z, 0.0, -u1x
        else:
            u2x, u2y, u2z = -u1y, u1x, 0.0
        inv = 1.0 / math.sqrt(u2x * u2x + u2y * u2y + u2z * u2z)
        u2x, u2y, u2z = u2x * inv, u2y * inv, u2z * inv
    u3x = u1y * u2z - u1z * u2y
    u3y = u1z * u2x - u1x * u2z
    u3z = u1x * u2y - u1y * u2x
    s1 = u2x * f2x + u2y * f2y + u2z * f2z
    s2 = u3x * f3x + u3y * f3y + u3z * f3z
    return (n1, s1, s2,
            u1x, u2x, u3x, u1y, u2y, u3y, u1z, u2z, u3z,
            v00, v01, v02, v10, v11, v12, v20, v21, v22)


@nb.njit(cache=True, **_NO_NRT)
def element_f_eigensystem(ev, dmi, t, ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj,
                          U, W, Z, sig, lam, full):
    """The 9 eigenvalues ``lam`` of ``d2Psi/dF2`` (Pa) of one tet, analytically.

    ``ev[0:3]`` are the columns of ``Ds``, ``dmi[t]`` is ``Dm^-1``. Order of ``lam``: twist
    and flip of the pairs (0,1), (0,2), (1,2) interleaved (``lam[2m]`` twist,
    ``lam[2m+1]`` flip), then the three scaling modes. Leaves ``U``, ``sig``, ``Z`` (scaling
    eigenvectors, columns) and ``W = V^T Dm^-T`` for :func:`mode_gradient`.

    Unless ``full``, if the 3x3 scaling block is safely positive definite its
    eigen-decomposition is skipped: ``lam[6:9]`` are then its Cholesky pivots (positive, not its eigenvalues),
    and the function returns False (True when ``lam[6:9]`` are the eigenvalues).
    """
    # F = Ds Dm^-1, F[r, c] = sum_i ev[i, r] dmi[t, i, c]
    f = signed_svd3(
        ev[0, 0] * dmi[t, 0, 0] + ev[1, 0] * dmi[t, 1, 0] + ev[2, 0] * dmi[t, 2, 0],
        ev[0, 0] * dmi[t, 0, 1] + ev[1, 0] * dmi[t, 1, 1] + ev[2, 0] * dmi[t, 2, 1],
        ev[0, 0] * dmi[t, 0, 2] + ev[1, 0] * dmi[t, 1, 2] + ev[2, 0] * dmi[t, 2, 2],
        ev[0, 1] * dmi[t, 0, 0] + ev[1, 1] * dmi[t, 1, 0] + ev[2, 1] * dmi[t, 2, 0],
        ev[0, 1] * dmi[t, 0, 1] + ev[1, 1] * dmi[t, 1, 1] + ev[2, 1] * dmi[t, 2, 1],
        ev[0, 1] * dmi[t, 0, 2] + ev[1, 1] * dmi[t, 1, 2] + ev[2, 1] * dmi[t, 2, 2],
        ev[0, 2] * dmi[t, 0, 0] + ev[1, 2] * dmi[t, 1, 0] + ev[2, 2] * dmi[t, 2, 0],
        ev[0, 2] * dmi[t, 0, 1] + ev[1, 2] * dmi[t, 1, 1] + ev[2, 2] * dmi[t, 2, 1],
        ev[0, 2] * dmi[t, 0, 2] + ev[1, 2] * dmi[t, 1, 2] + ev[2, 2] * dmi[t, 2, 2])
    s0, s1, s2 = f[0], f[1], f[2]
    sig[0] = s0
    sig[1] = s1
    sig[2] = s2
    for r in range(3):
        for c in range(3):
            U[r, c] = f[3 + 3 * r + c]
    # W = V^T Dm^-T: W[i, c] = sum_r V[r, i] dmi[t, c, r]
    for i in range(3):
        vi0 = f[12 + i]
        vi1 = f[15 + i]
        vi2 = f[18 + i]
        for c in range(3):
            W[i, c] = vi0 * dmi[t, c, 0] + vi1 * dmi[t, c, 1] + vi2 * dmi[t, c, 2]
    # twist / flip pairs (0,1 | 2), (0,2 | 1), (1,2 | 0)
    c1 = 2.0 * ps1
    lam[0] = c1 + 2.0 * ps2 * (s2 * s2 + s0 * s1) + psj * s2
    lam[1] = c1 + 2.0 * ps2 * (s2 * s2 - s0 * s1) - psj * s2
    lam[2] = c1 + 2.0 * ps2 * (s1 * s1 + s0 * s2) + psj * s1
    lam[3] = c1 + 2.0 * ps2 * (s1 * s1 - s0 * s2) - psj * s1
    lam[4] = c1 + 2.0 * ps2 * (s0 * s0 + s1 * s2) + psj * s0
    lam[5] = c1 + 2.0 * ps2 * (s0 * s0 - s1 * s2) - psj * s0
    # scaling block d2Psi / dsig_i dsig_j = g^T H3 g + Psi_1 d2I1 + Psi_2 d2I2 + Psi_J d2J
    # with g the gradients of (I1, I2, J) in the singular values
    g10, g11, g12 = 2.0 * s0, 2.0 * s1, 2.0 * s2
    g20 = 2.0 * s0 * (s1 * s1 + s2 * s2)
    g21 = 2.0 * s1 * (s0 * s0 + s2 * s2)
    g22 = 2.0 * s2 * (s0 * s0 + s1 * s1)
    gj0, gj1, gj2 = s1 * s2, s0 * s2, s0 * s1
    w10 = h11 * g10 + h12 * g20 + h1j * gj0
    w11 = h11 * g11 + h12 * g21 + h1j * gj1
    w12 = h11 * g12 + h12 * g22 + h1j * gj2
    w20 = h12 * g10 + h22 * g20 + h2j * gj0
    w21 = h12 * g11 + h22 * g21 + h2j * gj1
    w22 = h12 * g12 + h22 * g22 + h2j * gj2
    wj0 = h1j * g10 + h2j * g20 + hjj * gj0
    wj1 = h1j * g11 + h2j * g21 + hjj * gj1
    wj2 = h1j * g12 + h2j * g22 + hjj * gj2
    b00 = g10 * w10 + g20 * w20 + gj0 * wj0 + c1 + 2.0 * ps2 * (s1 * s1 + s2 * s2)
    b01 = g10 * w11 + g20 * w21 + gj0 * wj1 + 4.0 * ps2 * s0 * s1 + psj * s2
    b02 = g10 * w12 + g20 * w22 + gj0 * wj2 + 4.0 * ps2 * s0 * s2 + psj * s1
    b11 = g11 * w11 + g21 * w21 + gj1 * wj1 + c1 + 2.0 * ps2 * (s0 * s0 + s2 * s2)
    b12 = g11 * w12 + g21 * w22 + gj1 * wj2 + 4.0 * ps2 * s1 * s2 + psj * s0
    b22 = g12 * w12 + g22 * w22 + gj2 * wj2 + c1 + 2.0 * ps2 * (s0 * s0 + s1 * s1)
    # positive definite (leading minors, with a margin for rounding): no scaling mode to
    # clamp, and its eigenvectors are not needed (lam[6:9] then only flag "positive")
    m2 = b00 * b11 - b01 * b01
    m3 = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    scale = abs(b00) + abs(b11) + abs(b22)
    if not full and b00 > 1e-8 * scale and m2 > 1e-8 * scale * scale and m3 > 1e-8 * scale * scale * scale:
        lam[6] = b00
        lam[7] = m2 / b00
        lam[8] = m3 / m2
        for r in range(3):
            for c in range(3):
                Z[r, c] = 1.0 if r == c else 0.0
        return False
    z = eig3(b00, b01, b02, b11, b12, b22)
    lam[6] = z[0]
    lam[7] = z[1]
    lam[8] = z[2]
    for r in range(3):
        for c in range(3):
            Z[r, c] = z[3 + 3 * r + c]
    return True


@nb.njit(cache=True, **_NO_NRT)
def mode_gradient(mode, U, W, Z, gm, b):
    """``b = dF/dx^T vec(M)`` (12) for unit F-space mode ``mode`` (0..8, order of ``lam``)."""
    if mode < 6:
        m = mode // 2
        i = _PAIRS[m, 0]
        j = _PAIRS[m, 1]
        sgn = -1.0 if mode % 2 == 0 else 1.0  # twist: skew, flip: symmetric
        for r in range(3):
            for c in range(3):
                gm[r, c] = _INV_SQRT2 * (U[r, i] * W[j, c] + sgn * U[r, j] * W[i, c])
    else:
        zc = mode - 6
        for r in range(3):
            for c in range(3):
                gm[r, c] = (Z[0, zc] * U[r, 0] * W[0, c] + Z[1, zc] * U[r, 1] * W[1, c]
                            + Z[2, zc] * U[r, 2] * W[2, c])
    for r in range(3):
        b[3 + r] = gm[r, 0]
        b[6 + r] = gm[r, 1]
        b[9 + r] = gm[r, 2]
        b[r] = -(gm[r, 0] + gm[r, 1] + gm[r, 2])


@nb.njit(cache=True, **_NO_NRT)
def project_analytic(ke, ev, dmi, t, v0, d, U, W, Z, sig, lam, gm, b):
    """Clamp the negative modes of ``d2Psi/dF2`` in ``ke``; returns how many were clamped.

    ``d`` is the tuple returned by :func:`heml_element_hessian`; a non-finite one (law
    undefined) leaves ``ke`` as it is.
    """
    ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj = d
    n_neg = 0
    finite = (math.isfinite(psj) and math.isfinite(hjj) and math.isfinite(ps1)
              and math.isfinite(h11) and math.isfinite(h1j))
    if finite:
        element_f_eigensystem(ev, dmi, t, ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj,
                              U, W, Z, sig, lam, False)
    for mode in range(9 if finite else 0):
        if lam[mode] < 0.0:
            n_neg += 1
            mode_gradient(mode, U, W, Z, gm, b)
            c = -v0 * lam[mode]
            for r in range(12):
                br = c * b[r]
                for cc in range(12):
                    ke[r, cc] += br * b[cc]
    return n_neg


@nb.njit(cache=True)
def project_eigh(ke):
    """Clamp the negative eigenvalues of the symmetric 12x12 ``ke`` to zero (LAPACK eigh)."""
    finite = True
    for r in range(12):
        for c in range(12):
            if not math.isfinite(ke[r, c]):
                finite = False
    if finite:
        w, vec = np.linalg.eigh(ke)
        if w[0] < 0.0:
            for r in range(12):
                for c in range(12):
                    acc = 0.0
                    for m in range(12):
                        if w[m] > 0.0:
                            acc += vec[r, m] * w[m] * vec[c, m]
                    ke[r, c] = acc


@nb.njit(cache=True)
def _pad4(p):
    """The law parameters as four scalars (zero-padded)."""
    p0 = p[0] if p.shape[0] > 0 else 0.0
    p1 = p[1] if p.shape[0] > 1 else 0.0
    p2 = p[2] if p.shape[0] > 2 else 0.0
    p3 = p[3] if p.shape[0] > 3 else 0.0
    return p0, p1, p2, p3


@nb.njit(cache=True)
def heml_hessian_kernel(x, tets, coef, q, use_q, law, params, dm_inv, project,
                        blk, row_stride, data, out):
    """Every tet's 12x12 Hessian ``d2 W_T/dx2`` (J/m^2), projected per ``project``.

    If ``out`` has one row per tet the element matrices are stored there (local dof
    ``3 a + d``); otherwise they are added into the CSR ``data`` (zero on entry), where
    ``blk[t, a, b]`` is the position of entry ``(3 i_a, 3 i_b)`` and entry
    ``(3 i_a + d, 3 i_b + e)`` sits at ``blk[t, a, b] + d * row_stride[i_a] + e``.
    Returns the number of negative F-space modes clamped (analytic projection).
    ``params`` holds at most 4 law parameters.
    """
    p = _pad4(params)
    ke = np.empty((12, 12))
    ev, sv, qsv, g3, w3, qg, U, W, Z, sig, lam, b, gm = _work()
    store = out.shape[0] == tets.shape[0]
    n_neg = 0
    for t in range(tets.shape[0]):
        d = heml_element_hessian(x, tets, coef, q, use_q, law, p, t, ke, ev, sv, qsv, g3, w3, qg)
        if project == ANALYTIC_PROJECTION:
            n_neg += project_analytic(ke, ev, dm_inv, t, coef[t, 0], d, U, W, Z, sig, lam, gm, b)
        elif project == EIGH_PROJECTION:
            project_eigh(ke)
        if store:
            for r in range(12):
                for c in range(12):
                    out[t, r, c] = ke[r, c]
        else:
            add_element_blocks(ke, t, tets, blk, row_stride, data)
    return n_neg


@nb.njit(cache=True, **_NO_NRT)
def add_element_blocks(ke, t, tets, blk, row_stride, data):
    """Add tet ``t``'s 12x12 matrix ``ke`` into the CSR ``data`` (positions: ``blk``,
    ``row_stride`` as in :func:`heml_hessian_kernel`)."""
    for a in range(4):
        rs = np.uint64(row_stride[tets[t, a]])
        for bb in range(4):
            base = np.uint64(blk[t, a, bb])
            for dd in range(3):
                row = base + np.uint64(dd) * rs  # unsigned: no wrap-around checks
                kr = 3 * a + dd
                kc = 3 * bb
                data[row] += ke[kr, kc]
                data[row + np.uint64(1)] += ke[kr, kc + 1]
                data[row + np.uint64(2)] += ke[kr, kc + 2]


@nb.njit(cache=True)
def heml_split_hessian_kernel(x, tets, inv_det, w, law, params, blk, row_stride, data):
    """Exact Hessian of a law with constant ``Psi_1`` (Neo-Hookean) added into the CSR
    ``data`` (zero on entry): per tet the fixed edge springs ``w[k, t] = 2 V0 Psi_1 a_k``
    (N/m) as ``w [[I, -I], [-I, I]]``, plus the volume term
    ``Psi_JJ g g^T / (36 V0) + Psi_J d2 det(Ds) / 6`` with ``g = d det(Ds) / dx`` (the
    cross products of the edges). The same matrix as :func:`heml_hessian_kernel` without
    projection, for a fraction of the work (no invariant gradients, no ``Q``)."""
    p = _pad4(params)
    ke = np.empty((12, 12))
    g = np.empty(12)
    for t in range(tets.shape[0]):
        ax, ay, az, bx, by, bz, cx, cy, cz = tet_edges(x, tets, t)
        c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = edge_cofactors(ax, ay, az, bx, by, bz, cx, cy, cz)
        idet = inv_det[t]
        jac = (ax * c1x + ay * c1y + az * c1z) * idet
        psj, hjj = _volumetric_derivatives(law, p, jac)
        g[3] = c1x
        g[4] = c1y
        g[5] = c1z
        g[6] = c2x
        g[7] = c2y
        g[8] = c2z
        g[9] = c3x
        g[10] = c3y
        g[11] = c3z
        g[0] = -(c1x + c2x + c3x)
        g[1] = -(c1y + c2y + c3y)
        g[2] = -(c1z + c2z + c3z)
        curvature = hjj * idet / 6.0  # Psi_JJ / (36 V0)
        for r in range(12):
            for c in range(12):
                ke[r, c] = curvature * g[r] * g[c]
        _add_det_hessian(ke, psj / 6.0, ax, ay, az, bx, by, bz, cx, cy, cz)  # Psi_J d2 det / 6
        for k in range(6):  # fixed springs on the six edges
            _add_edge_spring(ke, k, w[k, t])
        add_element_blocks(ke, t, tets, blk, row_stride, data)


@nb.njit(cache=True)
def _volumetric_derivatives(law, p, jac):
    """``(Psi_J, Psi_JJ)`` of a law whose only ``J`` coupling is volumetric (Pa)."""
    ps1, ps2, psj = law_gradient(law, p, 0.0, 0.0, jac)
    h11, h12, h1j, h22, h2j, hjj = law_hessian(law, p, 0.0, 0.0, jac)
    return psj, hjj


@nb.njit(cache=True)
def heml_f_eigensystems(x, tets, coef, q, use_q, law, params, dm_inv, lam_out, b_out):
    """Per tet the 9 F-space eigenvalues (Pa) and their mode gradients ``b`` (12 each).

    ``K_T = V0 sum_m lam_m b_m b_m^T`` exactly; for tests of the analytic eigensystem.
    """
    p = _pad4(params)
    ke = np.empty((12, 12))
    ev, sv, qsv, g3, w3, qg, U, W, Z, sig, lam, b, gm = _work()
    for t in range(tets.shape[0]):
        ps1, ps2, psj, h11, h12, h1j, h22, h2j, hjj = heml_element_hessian(
            x, tets, coef, q, use_q, law, p, t, ke, ev, sv, qsv, g3, w3, qg)
        element_f_eigensystem(ev, dm_inv, t, ps1, ps2, psj, h11, h12, h1j, h22,
                              h2j, hjj, U, W, Z, sig, lam, True)
        for m in range(9):
            lam_out[t, m] = lam[m]
            mode_gradient(m, U, W, Z, gm, b)
            for r in range(12):
                b_out[t, m, r] = b[r]


# ------------------------------------------------------------------------ mass-spring
@nb.njit(cache=True)
def spring_hessian_assemble(x, edges, stiffness, rest_length, project, blk, row_stride, data):
    """Add ``k [r (I - n n^T) + n n^T]``, ``r = 1 - L/l`` (clamped at 0 if ``project``),
    as ``[[K, -K], [-K, K]]`` per edge into the CSR ``data`` (zero on entry)."""
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        r = 1.0 - rest_length[e] / length
        if project and r < 0.0:
            r = 0.0
        k = stiffness[e]
        inv = 1.0 / length
        n0, n1, n2 = dx * inv, dy * inv, dz * inv
        c = k * (1.0 - r)
        kr = k * r
        k00 = kr + c * n0 * n0
        k11 = kr + c * n1 * n1
        k22 = kr + c * n2 * n2
        k01 = c * n0 * n1
        k02 = c * n0 * n2
        k12 = c * n1 * n2
        for a in range(2):
            rs = row_stride[edges[e, a]]
            for bb in range(2):
                sgn = 1.0 if a == bb else -1.0
                base = blk[e, a, bb]
                data[base] += sgn * k00
                data[base + 1] += sgn * k01
                data[base + 2] += sgn * k02
                data[base + rs] += sgn * k01
                data[base + rs + 1] += sgn * k11
                data[base + rs + 2] += sgn * k12
                data[base + 2 * rs] += sgn * k02
                data[base + 2 * rs + 1] += sgn * k12
                data[base + 2 * rs + 2] += sgn * k22
