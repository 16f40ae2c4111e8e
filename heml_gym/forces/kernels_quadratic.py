"""Numba kernels of the 10-node quadratic tetrahedron (P2 finite elements).

Per element ``t`` and quadrature point ``q`` (four points, exact for the stiffness of a
straight-sided P2 tet): ``F_q = sum_a x_a (x) grad N_a(q)``, the first Piola-Kirchhoff
stress ``P(F_q)`` from each law's textbook formula in ``F``
(:func:`heml_gym.forces.kernels_fem.first_piola`), nodal forces
``f_a = -sum_q w_q P(F_q) grad N_a(q)`` and energy ``sum_q w_q Psi(F_q)``, where
``w_q`` (m^3) is the quadrature weight times the element's rest volume. The tangent
``dP/dF`` comes from the laws' invariant derivatives (:mod:`heml_gym.laws`), so the
Hessian and the forces are computed by different formulas.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..laws import law_gradient, law_hessian
from .kernels_fem import cofactor, energy_density, first_piola, right_cauchy_green


@nb.njit(cache=True, inline="always")
def quadrature_deformation_gradient(x, elements, grads, t, q, F):
    """Write ``F = sum_a x_a (x) grad N_a`` at quadrature point ``q`` of element ``t``."""
    for r in range(3):
        for c in range(3):
            F[r, c] = 0.0
    for a in range(10):
        n = elements[t, a]
        for r in range(3):
            xr = x[n, r]
            for c in range(3):
                F[r, c] += xr * grads[t, q, a, c]


@nb.njit(cache=True)
def quadratic_energy(x, elements, grads, weights, law, p):
    """Elastic energy (J): ``sum_t sum_q w_tq Psi(F_tq)``."""
    F = np.empty((3, 3))
    K = np.empty((3, 3))
    C = np.empty((3, 3))
    total = 0.0
    for t in range(elements.shape[0]):
        for q in range(4):
            quadrature_deformation_gradient(x, elements, grads, t, q, F)
            total += weights[t, q] * energy_density(law, p, F, K, C)
    return total


@nb.njit(cache=True)
def quadratic_add_forces(x, elements, grads, weights, law, p, f):
    """Add the elastic forces ``-dW/dx`` (N) into ``f`` ``(n, 3)``."""
    F = np.empty((3, 3))
    K = np.empty((3, 3))
    C = np.empty((3, 3))
    P = np.empty((3, 3))
    for t in range(elements.shape[0]):
        for q in range(4):
            quadrature_deformation_gradient(x, elements, grads, t, q, F)
            first_piola(law, p, F, K, C, P)
            w = weights[t, q]
            for a in range(10):
                n = elements[t, a]
                for r in range(3):
                    f[n, r] -= w * (P[r, 0] * grads[t, q, a, 0] + P[r, 1] * grads[t, q, a, 1]
                                    + P[r, 2] * grads[t, q, a, 2])


@nb.njit(cache=True)
def stress_tangent(law, p, F, A):
    """Write ``A[3 i + j, 3 k + l] = dP_ij / dF_kl`` (Pa) into the 9x9 ``A``.

    ``P = 2 Psi_1 F + 2 Psi_2 (I1 F - F C) + Psi_J cof F`` differentiated along each unit
    direction ``D``; ``cof`` is quadratic in ``F``, so its derivative along ``D`` is
    exactly ``cof(F + D) - cof(F) - cof(D)``, and ``cof(D) = 0`` for a unit ``D`` (rank
    one). NaN where the law is undefined.
    """
    K = np.empty((3, 3))
    C = np.empty((3, 3))
    KFD = np.empty((3, 3))
    D = np.zeros((3, 3))
    FD = np.empty((3, 3))
    FC = np.empty((3, 3))
    dC = np.empty((3, 3))
    jac = cofactor(F, K)
    right_cauchy_green(F, C)
    i1 = C[0, 0] + C[1, 1] + C[2, 2]
    cc = 0.0
    for i in range(3):
        for j in range(3):
            cc += C[i, j] * C[j, i]
    i2 = 0.5 * (i1 * i1 - cc)
    ps1, ps2, psj = law_gradient(law, p, i1, i2, jac)
    h11, h12, h1j, h22, h2j, hjj = law_hessian(law, p, i1, i2, jac)
    for i in range(3):
        for j in range(3):
            FC[i, j] = F[i, 0] * C[0, j] + F[i, 1] * C[1, j] + F[i, 2] * C[2, j]
    for k in range(3):
        for m in range(3):
            D[:, :] = 0.0
            D[k, m] = 1.0
            # invariant derivatives along D
            di1 = 2.0 * F[k, m]
            di2 = 2.0 * (i1 * F[k, m] - FC[k, m])
            dj = K[k, m]
            d1 = h11 * di1 + h12 * di2 + h1j * dj
            d2 = h12 * di1 + h22 * di2 + h2j * dj
            dJ = h1j * di1 + h2j * di2 + hjj * dj
            for i in range(3):
                for j in range(3):
                    FD[i, j] = F[i, j] + D[i, j]
            cofactor(FD, KFD)
            for s in range(3):  # dC = D^T F + F^T D
                for j in range(3):
                    dC[s, j] = (D[0, s] * F[0, j] + D[1, s] * F[1, j] + D[2, s] * F[2, j]
                                + F[0, s] * D[0, j] + F[1, s] * D[1, j] + F[2, s] * D[2, j])
            for i in range(3):
                for j in range(3):
                    fdc = F[i, 0] * dC[0, j] + F[i, 1] * dC[1, j] + F[i, 2] * dC[2, j]  # (F dC)_ij
                    dc_d = D[i, 0] * C[0, j] + D[i, 1] * C[1, j] + D[i, 2] * C[2, j]
                    dk = KFD[i, j] - K[i, j]
                    A[3 * i + j, 3 * k + m] = (2.0 * d1 * F[i, j] + 2.0 * ps1 * D[i, j]
                                               + 2.0 * d2 * (i1 * F[i, j] - FC[i, j])
                                               + 2.0 * ps2 * (di1 * F[i, j] + i1 * D[i, j] - dc_d - fdc)
                                               + dJ * K[i, j] + psj * dk)


@nb.njit(cache=True)
def clamp_negative_modes(A):
    """Replace the symmetric 9x9 ``A`` by its positive semi-definite part (eigenvalues
    below zero set to zero); returns how many were clamped. A non-finite ``A`` (an
    inverted quadrature point of a ln J law) is left as it is: the Hessian then holds NaN,
    which the solvers read as no step matrix there."""
    for i in range(9):
        for j in range(9):
            if not np.isfinite(A[i, j]):
                return 0
    S = 0.5 * (A + A.T)
    lam, V = np.linalg.eigh(S)
    clamped = 0
    for e in range(9):
        if lam[e] < 0.0:
            lam[e] = 0.0
            clamped += 1
    for i in range(9):
        for j in range(9):
            acc = 0.0
            for e in range(9):
                acc += V[i, e] * lam[e] * V[j, e]
            A[i, j] = acc
    return clamped


@nb.njit(cache=True)
def quadratic_element_hessians(x, elements, grads, weights, law, p, project, out):
    """Every element's 30x30 Hessian ``d2 W_t / dx2`` (J/m^2, dof ``3 a + i`` for local
    node ``a``) into ``out`` ``(m, 30, 30)``. ``project``: clamp the negative modes of
    ``dP/dF`` at each quadrature point first (a positive semi-definite matrix).
    Returns the number of clamped modes."""
    F = np.empty((3, 3))
    A = np.empty((9, 9))
    T = np.empty((9, 10, 3))
    clamped = 0
    for t in range(elements.shape[0]):
        for r in range(30):
            for c in range(30):
                out[t, r, c] = 0.0
        for q in range(4):
            quadrature_deformation_gradient(x, elements, grads, t, q, F)
            stress_tangent(law, p, F, A)
            if project:
                clamped += clamp_negative_modes(A)
            w = weights[t, q]
            # T[(i, j), b, k] = sum_l A[(i, j), (k, l)] G_b,l
            for ij in range(9):
                for b in range(10):
                    for k in range(3):
                        T[ij, b, k] = (A[ij, 3 * k] * grads[t, q, b, 0] + A[ij, 3 * k + 1] * grads[t, q, b, 1]
                                       + A[ij, 3 * k + 2] * grads[t, q, b, 2])
            for a in range(10):
                for i in range(3):
                    g0 = w * grads[t, q, a, 0]
                    g1 = w * grads[t, q, a, 1]
                    g2 = w * grads[t, q, a, 2]
                    for b in range(10):
                        for k in range(3):
                            out[t, 3 * a + i, 3 * b + k] += (g0 * T[3 * i, b, k] + g1 * T[3 * i + 1, b, k]
                                                             + g2 * T[3 * i + 2, b, k])
    return clamped
