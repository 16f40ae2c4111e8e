"""Isotropic compressible hyperelastic laws, as data for the Numba kernels.

Each law is an energy density ``Psi`` (J/m^3 = Pa) written in the invariants of the right
Cauchy-Green tensor ``C = F^T F``: ``I1 = tr C``, ``I2 = ((tr C)^2 - tr C^2) / 2`` and
``J = det F`` (signed, so inverted elements are seen). A material object holds only
numbers: an integer ``law_id`` and a float64 vector ``params`` of its native constants;
the kernels in :mod:`heml_gym.laws` evaluate ``Psi`` and its derivatives from those.

Every law can be built from its native constants or, equivalently at small strain,
from Young's modulus ``E`` (Pa) and Poisson's ratio ``nu``::

    NeoHookean(E=5e3, nu=0.45)
    NeoHookean(mu=1724.1, lam=15517.2)

======================  =====================================================  ==========
law                     Psi(I1, I2, J)                                         J <= 0
======================  =====================================================  ==========
NeoHookean              mu/2 (I1-3) - mu ln J + lam/2 (ln J)^2                 undefined
StVenantKirchhoff       mu tr(E^2) + lam/2 (tr E)^2, E = (C - I)/2             defined
MooneyRivlin            c10 (J^-2/3 I1 - 3) + c01 (J^-4/3 I2 - 3)              undefined
                        + kappa/2 (J-1)^2
Demiray                 a/(2b) (exp(b (J^-2/3 I1 - 3)) - 1) + kappa/2 (J-1)^2  undefined
StableNeoHookean        mu/2 (I1-3) + lam/2 (J-alpha)^2 - mu/2 ln(I1+1) + c,   defined
                        alpha = 1 + 3 mu / (4 lam), c: Psi(I) = 0  (Smith et al. 2018)
======================  =====================================================  ==========

Where a law is undefined (``J <= 0``) its energy is ``+inf`` and its forces are NaN, so
an inverted element cannot go unnoticed.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "Material",
    "NeoHookean",
    "StVenantKirchhoff",
    "MooneyRivlin",
    "Demiray",
    "StableNeoHookean",
    "lame_from_young",
    "ALL_MATERIALS",
]

# Law identifiers shared with the Numba kernels (heml_gym.laws).
NEO_HOOKEAN = 0
ST_VENANT_KIRCHHOFF = 1
MOONEY_RIVLIN = 2
DEMIRAY = 3
STABLE_NEO_HOOKEAN = 4


def lame_from_young(E: float, nu: float) -> tuple[float, float]:
    """Lamé constants ``(mu, lam)`` in Pa from Young's modulus ``E`` (Pa) and ``nu``.

    Raises ``ValueError`` unless ``E > 0`` and ``-1 < nu < 0.5``.
    """
    E, nu = float(E), float(nu)
    if not math.isfinite(E) or E <= 0:
        raise ValueError(f"Young's modulus E must be a positive number of pascals, got {E}")
    if not math.isfinite(nu) or not (-1.0 < nu < 0.5):
        raise ValueError(f"Poisson's ratio nu must lie in (-1, 0.5), got {nu}")
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def _check(name: str, value: float, *, positive: bool = True) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if positive and value <= 0:
        raise ValueError(f"{name} must be > 0, got {value}")
    if not positive and value < 0:
        raise ValueError(f"{name} must be >= 0, got {value}")
    return value


class Material:
    """Base class: an isotropic hyperelastic law and its constants.

    Attributes
    ----------
    law_id : int
        Which energy the kernels evaluate.
    params : (k,) float64 ndarray
        The law's native constants, in the order its kernel reads them.
    shear_modulus, bulk_modulus : float
        Small-strain moduli in Pa (the law linearised at rest).
    young_modulus, poisson_ratio : float
        The same, as ``E`` (Pa) and ``nu``.
    needs_i2 : bool
        Whether ``Psi`` depends on ``I2`` (the kernels then evaluate it).
    defined_when_inverted : bool
        Whether ``Psi`` is finite for ``J <= 0``.
    """

    law_id: int = -1
    needs_i2: bool = False
    #: ``dPsi/dI1`` when it is a constant and ``Psi`` has no ``I2`` term (the I1 part of the
    #: force is then a fixed linear spring network), else None.
    constant_psi1: float | None = None
    defined_when_inverted: bool = False
    params: np.ndarray

    @staticmethod
    def _one_of(native: dict, young: dict, cls_name: str) -> str:
        has_native = any(v is not None for v in native.values())
        has_young = any(v is not None for v in young.values())
        if has_native and has_young:
            raise ValueError(f"{cls_name}: give either E= and nu= or the native constants, not both")
        if has_young:
            missing = [k for k, v in young.items() if v is None]
            if missing:
                raise ValueError(f"{cls_name}: missing {', '.join(missing)}")
            return "young"
        missing = [k for k, v in native.items() if v is None]
        if missing:
            raise ValueError(
                f"{cls_name}: give E= and nu=, or all of {', '.join(native)} (missing {', '.join(missing)})"
            )
        return "native"

    @property
    def shear_modulus(self) -> float:
        raise NotImplementedError

    @property
    def bulk_modulus(self) -> float:
        raise NotImplementedError

    @property
    def young_modulus(self) -> float:
        mu, k = self.shear_modulus, self.bulk_modulus
        return 9.0 * k * mu / (3.0 * k + mu)

    @property
    def poisson_ratio(self) -> float:
        mu, k = self.shear_modulus, self.bulk_modulus
        return (3.0 * k - 2.0 * mu) / (2.0 * (3.0 * k + mu))

    @property
    def lame_lambda(self) -> float:
        """Small-strain Lamé lambda in Pa."""
        return self.bulk_modulus - 2.0 * self.shear_modulus / 3.0

    def wave_speed(self, density: float) -> float:
        """Small-strain P-wave speed ``sqrt((lam + 2 mu) / rho)`` in m/s for ``density`` kg/m^3."""
        return math.sqrt((self.lame_lambda + 2.0 * self.shear_modulus) / density)

    def __repr__(self) -> str:
        names = ", ".join(f"{k}={v:.6g}" for k, v in self._native().items())
        return f"{type(self).__name__}({names})"

    def _native(self) -> dict:
        raise NotImplementedError


class NeoHookean(Material):
    """Compressible Neo-Hookean: ``Psi = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2``.

    Native constants: ``mu`` (Pa, > 0) and ``lam`` (Pa, bulk modulus ``lam + 2 mu/3 > 0``).
    """

    law_id = NEO_HOOKEAN

    def __init__(self, *, E=None, nu=None, mu=None, lam=None):
        if self._one_of({"mu": mu, "lam": lam}, {"E": E, "nu": nu}, "NeoHookean") == "young":
            mu, lam = lame_from_young(E, nu)
        mu = _check("mu", mu)
        lam = float(lam)
        if not math.isfinite(lam) or lam + 2.0 * mu / 3.0 <= 0:
            raise ValueError(f"NeoHookean: bulk modulus lam + 2 mu / 3 must be > 0 (mu={mu}, lam={lam})")
        self.mu, self.lam = mu, lam
        self.constant_psi1 = 0.5 * mu
        self.params = np.array([mu, lam], dtype=np.float64)

    shear_modulus = property(lambda self: self.mu)
    bulk_modulus = property(lambda self: self.lam + 2.0 * self.mu / 3.0)

    def _native(self):
        return {"mu": self.mu, "lam": self.lam}


class StVenantKirchhoff(Material):
    """Saint Venant-Kirchhoff: ``Psi = mu tr(E^2) + lam/2 (tr E)^2``, ``E = (C - I)/2``.

    In invariants: ``tr E = (I1 - 3)/2``, ``tr E^2 = (I1^2 - 2 I2 - 2 I1 + 3)/4``.
    Finite for any ``J`` but softens, then collapses, under strong compression.
    """

    law_id = ST_VENANT_KIRCHHOFF
    needs_i2 = True
    defined_when_inverted = True

    def __init__(self, *, E=None, nu=None, mu=None, lam=None):
        if self._one_of({"mu": mu, "lam": lam}, {"E": E, "nu": nu}, "StVenantKirchhoff") == "young":
            mu, lam = lame_from_young(E, nu)
        mu = _check("mu", mu)
        lam = float(lam)
        if not math.isfinite(lam) or lam + 2.0 * mu / 3.0 <= 0:
            raise ValueError(f"StVenantKirchhoff: bulk modulus lam + 2 mu / 3 must be > 0 (mu={mu}, lam={lam})")
        self.mu, self.lam = mu, lam
        self.params = np.array([mu, lam], dtype=np.float64)

    shear_modulus = property(lambda self: self.mu)
    bulk_modulus = property(lambda self: self.lam + 2.0 * self.mu / 3.0)

    def _native(self):
        return {"mu": self.mu, "lam": self.lam}


class MooneyRivlin(Material):
    """Compressible Mooney-Rivlin on isochoric invariants.

    ``Psi = c10 (J^-2/3 I1 - 3) + c01 (J^-4/3 I2 - 3) + kappa/2 (J - 1)^2``.
    Small strain: shear modulus ``2 (c10 + c01)``, bulk modulus ``kappa``. From ``E, nu``
    the shear modulus is split with ``c01 = c01_fraction * mu / 2`` (default 0.25).
    """

    law_id = MOONEY_RIVLIN
    needs_i2 = True

    def __init__(self, *, E=None, nu=None, c10=None, c01=None, kappa=None, c01_fraction=0.25):
        native = {"c10": c10, "c01": c01, "kappa": kappa}
        if self._one_of(native, {"E": E, "nu": nu}, "MooneyRivlin") == "young":
            mu, lam = lame_from_young(E, nu)
            frac = float(c01_fraction)
            if not 0.0 <= frac <= 1.0:
                raise ValueError(f"MooneyRivlin: c01_fraction must lie in [0, 1], got {frac}")
            c10, c01, kappa = (1.0 - frac) * mu / 2.0, frac * mu / 2.0, lam + 2.0 * mu / 3.0
        c10 = _check("c10", c10, positive=False)
        c01 = _check("c01", c01, positive=False)
        kappa = _check("kappa", kappa)
        if c10 + c01 <= 0:
            raise ValueError(f"MooneyRivlin: c10 + c01 must be > 0 (c10={c10}, c01={c01})")
        self.c10, self.c01, self.kappa = c10, c01, kappa
        self.params = np.array([c10, c01, kappa], dtype=np.float64)

    shear_modulus = property(lambda self: 2.0 * (self.c10 + self.c01))
    bulk_modulus = property(lambda self: self.kappa)

    def _native(self):
        return {"c10": self.c10, "c01": self.c01, "kappa": self.kappa}


class Demiray(Material):
    """Demiray's exponential soft-tissue law (1972), compressible form.

    ``Psi = a/(2b) (exp(b (J^-2/3 I1 - 3)) - 1) + kappa/2 (J - 1)^2``.
    ``a`` (Pa) is the small-strain shear modulus, ``b`` (dimensionless, > 0) sets how fast
    the tissue stiffens, ``kappa`` (Pa) is the bulk modulus. From ``E, nu``: ``a = mu``,
    ``kappa = lam + 2 mu / 3`` and ``b`` as given (default 2).
    """

    law_id = DEMIRAY

    def __init__(self, *, E=None, nu=None, a=None, b=None, kappa=None):
        if E is not None or nu is not None:
            if a is not None or kappa is not None:
                raise ValueError("Demiray: give either E= and nu= (and b=) or a=, b=, kappa=, not both")
            if E is None or nu is None:
                raise ValueError("Demiray: missing " + ("E" if E is None else "nu"))
            mu, lam = lame_from_young(E, nu)
            a, kappa = mu, lam + 2.0 * mu / 3.0
            b = 2.0 if b is None else b
        elif a is None or b is None or kappa is None:
            raise ValueError("Demiray: give E= and nu=, or all of a, b, kappa")
        self.a, self.b, self.kappa = _check("a", a), _check("b", b), _check("kappa", kappa)
        self.params = np.array([self.a, self.b, self.kappa], dtype=np.float64)

    shear_modulus = property(lambda self: self.a)
    bulk_modulus = property(lambda self: self.kappa)

    def _native(self):
        return {"a": self.a, "b": self.b, "kappa": self.kappa}


class StableNeoHookean(Material):
    """Stable Neo-Hookean (Smith, de Goes and Kim 2018), defined for inverted elements.

    ``Psi = mu/2 (I1 - 3) + lam/2 (J - alpha)^2 - mu/2 ln(I1 + 1) + c``,
    ``alpha = 1 + 3 mu / (4 lam)`` (rest is stress-free) and ``c`` makes ``Psi(I) = 0``. Native ``mu, lam`` (Pa) are the
    energy's own; from ``E, nu`` they are ``mu = 4/3 mu_L``, ``lam = lam_L + 5/6 mu_L``
    (Lamé ``mu_L, lam_L``), which matches linear elasticity at small strain.
    """

    law_id = STABLE_NEO_HOOKEAN
    defined_when_inverted = True

    def __init__(self, *, E=None, nu=None, mu=None, lam=None):
        if self._one_of({"mu": mu, "lam": lam}, {"E": E, "nu": nu}, "StableNeoHookean") == "young":
            mu_l, lam_l = lame_from_young(E, nu)
            mu, lam = 4.0 * mu_l / 3.0, lam_l + 5.0 * mu_l / 6.0
        self.mu = _check("mu", mu)
        self.lam = _check("lam", lam)
        self.alpha = 1.0 + 3.0 * self.mu / (4.0 * self.lam)
        # constant that makes Psi(F = I) = 0
        self.rest_offset = 0.5 * self.mu * math.log(4.0) - 0.5 * self.lam * (1.0 - self.alpha) ** 2
        self.params = np.array([self.mu, self.lam, self.alpha, self.rest_offset], dtype=np.float64)

    # Linearised: mu_L = 3/4 mu, lam_L = lam - 5/8 mu.
    shear_modulus = property(lambda self: 0.75 * self.mu)
    bulk_modulus = property(lambda self: self.lam - 0.625 * self.mu + 0.5 * self.mu)

    def _native(self):
        return {"mu": self.mu, "lam": self.lam}


#: Every law, for parametrised tests and benchmarks.
ALL_MATERIALS = (NeoHookean, StVenantKirchhoff, MooneyRivlin, Demiray, StableNeoHookean)
