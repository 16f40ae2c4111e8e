"""An inlinable natural logarithm, so that kernel loops calling it can vectorise.

``math.log`` compiles to a call into the C library, which no loop around it can
vectorise. :func:`log_positive` evaluates the same function inline: ``x = 2^k m`` with
``m`` in ``[sqrt(1/2), sqrt(2))`` and ``ln m = 2 atanh(s)``, ``s = (m - 1)/(m + 1)``,
by its series to ``s^19`` (truncation below 3e-17 relative). Measured against
``math.log``: at most 2 units in the last place.

It is only valid for positive, normal, finite ``x``; callers check that and take
``math.log`` otherwise. Every operation has a packed AVX2 form (a logical shift for the
exponent, the 2^52 "magic number" for the integer-to-float conversion), so the loops
around it vectorise on AVX2-only CPUs too, not only with AVX-512. With ``NUMBA_DISABLE_JIT=1`` (the operation counter) it is
``math.log``.
"""

from __future__ import annotations

import math

import numba as nb
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["log_positive", "SMALLEST_NORMAL"]

_LN2_HI = 6.93147180369123816490e-01  # ln 2 split so that k * _LN2_HI is exact
_LN2_LO = 1.90821492927058770002e-10
_SQRT2 = 1.4142135623730951
#: Smallest positive normal float64: the lower limit of :func:`log_positive`.
SMALLEST_NORMAL = 2.2250738585072014e-308


@intrinsic
def _float_bits(typingctx, x):
    """The IEEE-754 bits of a float64, as an int64."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _bits_float(typingctx, b):
    """The float64 whose IEEE-754 bits are the int64 ``b``."""
    if not isinstance(b, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


@intrinsic
def _shift_right_logical(typingctx, b, n):
    """``b >> n`` for int64 ``b`` as a logical shift (zeros in): AVX2 has a packed
    logical 64-bit shift but no arithmetic one, so a loop using this one vectorises
    on every x86-64 CPU, not only on AVX-512 ones."""
    if not (isinstance(b, types.Integer) and isinstance(n, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        amount = builder.zext(args[1], ir.IntType(64)) if args[1].type.width < 64 else args[1]
        return builder.lshr(args[0], amount)

    return types.int64(types.int64, n), codegen


#: 2^52: ``_bits_float(_MAGIC_BITS | e) - _MAGIC`` is ``e`` as a float64 for ``0 <= e < 2^52``
_MAGIC = 4503599627370496.0
_MAGIC_BITS = 0x4330000000000000


@nb.njit(cache=True, inline="always")
def _log_positive(x):
    bits = _float_bits(x)
    # the biased exponent (x is positive: no sign bit), and that integer as a float by the
    # 2^52 "magic number" instead of an int64 -> float64 conversion (no packed AVX2 form)
    e = _bits_float(_shift_right_logical(bits, 52) | _MAGIC_BITS) - _MAGIC
    m = _bits_float((bits & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000)  # in [1, 2)
    big = m > _SQRT2  # branch-free: a select, not a jump
    m = m * 0.5 if big else m
    kf = e - (1022.0 if big else 1023.0)
    s = (m - 1.0) / (m + 1.0)
    z = s * s
    p = 1.0 / 19.0
    p = p * z + 1.0 / 17.0
    p = p * z + 1.0 / 15.0
    p = p * z + 1.0 / 13.0
    p = p * z + 1.0 / 11.0
    p = p * z + 1.0 / 9.0
    p = p * z + 1.0 / 7.0
    p = p * z + 1.0 / 5.0
    p = p * z + 1.0 / 3.0
    return kf * _LN2_HI + (kf * _LN2_LO + 2.0 * s + 2.0 * s * z * p)


if nb.config.DISABLE_JIT:  # pragma: no cover - the operation counter's plain-Python mode

    def log_positive(x):
        return math.log(x)

else:
    log_positive = _log_positive
