"""Numba evaluation of the laws of :mod:`heml_gym.materials` in the invariants of C.

``law_energy(law, p, I1, I2, J)`` returns ``Psi`` (Pa) and ``law_gradient`` returns
``(dPsi/dI1, dPsi/dI2, dPsi/dJ)``. ``law`` is a material's ``law_id`` and ``p`` its
``params``: the law is data, so one compiled kernel serves every law.

Where a law is undefined (``J <= 0`` for the ln J and J^-2/3 laws) the energy is
``+inf`` and the derivatives are NaN.
"""

from __future__ import annotations

import math

import numba as nb

from .fastlog import log_positive

from .materials import (
    DEMIRAY,
    MOONEY_RIVLIN,
    NEO_HOOKEAN,
    ST_VENANT_KIRCHHOFF,
    STABLE_NEO_HOOKEAN,
)

_NAN = math.nan
_TWO_THIRDS = 2.0 / 3.0


@nb.njit(cache=True, inline="always")
def law_energy(law, p, I1, I2, J):
    """Energy density Psi(I1, I2, J) in Pa."""
    if law == NEO_HOOKEAN:
        if J <= 0.0:
            return math.inf
        lnj = math.log(J)
        return 0.5 * p[0] * (I1 - 3.0) - p[0] * lnj + 0.5 * p[1] * lnj * lnj
    elif law == ST_VENANT_KIRCHHOFF:
        tr_e = 0.5 * (I1 - 3.0)
        tr_e2 = 0.25 * (I1 * I1 - 2.0 * I2 - 2.0 * I1 + 3.0)
        return p[0] * tr_e2 + 0.5 * p[1] * tr_e * tr_e
    elif law == MOONEY_RIVLIN:
        if J <= 0.0:
            return math.inf
        j23 = J ** (-_TWO_THIRDS)
        return p[0] * (j23 * I1 - 3.0) + p[1] * (j23 * j23 * I2 - 3.0) + 0.5 * p[2] * (J - 1.0) ** 2
    elif law == DEMIRAY:
        if J <= 0.0:
            return math.inf
        ib1 = J ** (-_TWO_THIRDS) * I1
        return 0.5 * p[0] / p[1] * (math.exp(p[1] * (ib1 - 3.0)) - 1.0) + 0.5 * p[2] * (J - 1.0) ** 2
    elif law == STABLE_NEO_HOOKEAN:
        return 0.5 * p[0] * (I1 - 3.0) + 0.5 * p[1] * (J - p[2]) ** 2 - 0.5 * p[0] * math.log(I1 + 1.0) + p[3]
    return _NAN


@nb.njit(cache=True, inline="always")
def volumetric_gradient_fast(law, p0, p1, J):
    """``dPsi/dJ`` for the laws with constant ``Psi_1`` and no ``I2`` (Neo-Hookean), inline;
    ``p0, p1`` are the law's first two parameters (scalars, so that a loop over worlds
    with per-world parameters vectorises too).

    Only for normal, positive, finite ``J`` (the caller checks): it uses the inlinable
    logarithm so that a loop around it can vectorise.
    """
    if law == NEO_HOOKEAN:
        return (p1 * log_positive(J) - p0) / J
    return _NAN


@nb.njit(cache=True, inline="always")
def volumetric_energy_fast(law, p0, p1, J):
    """The ``J`` part of ``Psi`` (Pa) for the laws with constant ``Psi_1`` and no ``I2``
    (Neo-Hookean: ``-mu ln J + lambda/2 (ln J)^2``), inline; as
    :func:`volumetric_gradient_fast`, only for normal, positive, finite ``J``."""
    if law == NEO_HOOKEAN:
        lnj = log_positive(J)
        return lnj * (0.5 * p1 * lnj - p0)
    return _NAN


@nb.njit(cache=True, inline="always")
def law_gradient(law, p, I1, I2, J):
    """``(dPsi/dI1, dPsi/dI2, dPsi/dJ)`` in Pa."""
    if law == NEO_HOOKEAN:
        if J <= 0.0:
            return _NAN, _NAN, _NAN
        return 0.5 * p[0], 0.0, (p[1] * math.log(J) - p[0]) / J
    elif law == ST_VENANT_KIRCHHOFF:
        return 0.5 * p[0] * (I1 - 1.0) + 0.25 * p[1] * (I1 - 3.0), -0.5 * p[0], 0.0
    elif law == MOONEY_RIVLIN:
        if J <= 0.0:
            return _NAN, _NAN, _NAN
        j23 = J ** (-_TWO_THIRDS)
        j43 = j23 * j23
        d1 = p[0] * j23
        d2 = p[1] * j43
        dj = -_TWO_THIRDS * (d1 * I1 + 2.0 * d2 * I2) / J + p[2] * (J - 1.0)
        return d1, d2, dj
    elif law == DEMIRAY:
        if J <= 0.0:
            return _NAN, _NAN, _NAN
        j23 = J ** (-_TWO_THIRDS)
        g = 0.5 * p[0] * math.exp(p[1] * (j23 * I1 - 3.0))
        d1 = g * j23
        return d1, 0.0, -_TWO_THIRDS * d1 * I1 / J + p[2] * (J - 1.0)
    elif law == STABLE_NEO_HOOKEAN:
        return 0.5 * p[0] * (1.0 - 1.0 / (I1 + 1.0)), 0.0, p[1] * (J - p[2])
    return _NAN, _NAN, _NAN


@nb.njit(cache=True, inline="always")
def law_hessian(law, p, I1, I2, J):
    """Second derivatives ``(Psi_11, Psi_12, Psi_1J, Psi_22, Psi_2J, Psi_JJ)`` in Pa.

    ``Psi_11 = d2Psi/dI1^2``, ``Psi_12 = d2Psi/dI1 dI2``, ``Psi_1J = d2Psi/dI1 dJ``, and so
    on. NaN where the law is undefined (``J <= 0`` for the ln J and J^-2/3 laws).
    """
    if law == NEO_HOOKEAN:
        if J <= 0.0:
            return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN
        # Psi_J = (lam ln J - mu) / J
        return 0.0, 0.0, 0.0, 0.0, 0.0, (p[1] * (1.0 - math.log(J)) + p[0]) / (J * J)
    elif law == ST_VENANT_KIRCHHOFF:
        # Psi_1 = mu/2 (I1 - 1) + lam/4 (I1 - 3), Psi_2 = -mu/2
        return 0.5 * p[0] + 0.25 * p[1], 0.0, 0.0, 0.0, 0.0, 0.0
    elif law == MOONEY_RIVLIN:
        if J <= 0.0:
            return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN
        j23 = J ** (-_TWO_THIRDS)
        j43 = j23 * j23
        d1 = p[0] * j23  # Psi_1
        d2 = p[1] * j43  # Psi_2
        inv_j = 1.0 / J
        d1j = -_TWO_THIRDS * d1 * inv_j
        d2j = -2.0 * _TWO_THIRDS * d2 * inv_j
        djj = ((10.0 / 9.0) * d1 * I1 + (28.0 / 9.0) * d2 * I2) * inv_j * inv_j + p[2]
        return 0.0, 0.0, d1j, 0.0, d2j, djj
    elif law == DEMIRAY:
        if J <= 0.0:
            return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN
        # Psi = a/(2b) (exp(b (Ib - 3)) - 1) + kappa/2 (J-1)^2, Ib = J^-2/3 I1
        j23 = J ** (-_TWO_THIRDS)
        ib = j23 * I1
        g = 0.5 * p[0] * math.exp(p[1] * (ib - 3.0))  # dPsi/dIb; d2Psi/dIb2 = b g
        inv_j = 1.0 / J
        dib_dj = -_TWO_THIRDS * ib * inv_j
        d11 = p[1] * g * j23 * j23
        d1j = g * j23 * (p[1] * dib_dj - _TWO_THIRDS * inv_j)
        djj = p[1] * g * dib_dj * dib_dj + g * (10.0 / 9.0) * ib * inv_j * inv_j + p[2]
        return d11, 0.0, d1j, 0.0, 0.0, djj
    elif law == STABLE_NEO_HOOKEAN:
        r = 1.0 / (I1 + 1.0)
        return 0.5 * p[0] * r * r, 0.0, 0.0, 0.0, 0.0, p[1]
    return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN
