r"""``exp`` and ``log`` written out in arithmetic, so that the compiler can vectorise the
loops that call them (numba calls the C library's scalar ``exp``/``log`` otherwise, one
element at a time, and a loop with such a call stays scalar).

The algorithms and coefficients are fdlibm's (``e_exp.c``, ``e_log.c``; Sun Microsystems,
freely redistributable), the ones behind most C libraries' ``exp`` and ``log``: error
below 1 ulp, checked against ``math.exp``/``math.log`` in ``tests/unit/test_vecmath.py``.
Only the ranges the filter needs are handled (see each function); the reinterpretation
of a double's bits, which fdlibm does with a union, is an LLVM ``bitcast`` here.

- :math:`e^x = 2^k\, e^r`, :math:`k = \operatorname{round}(x / \ln 2)`,
  :math:`r = x - k \ln 2` (in two parts), :math:`e^r = 1 + r + r c / (2 - c)` with
  :math:`c = r - r^2 (P_1 + r^2 P_2 + \dots + r^8 P_5)`.
- :math:`\ln x = k \ln 2 + \ln m`, :math:`m \in [\sqrt2/2, \sqrt2)`, :math:`f = m - 1`,
  :math:`s = f / (2 + f)`, :math:`\ln m = f - f^2/2 + s (f^2/2 + R(s^2))` with
  :math:`R(z) = L_1 z + \dots + L_7 z^7`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic


@intrinsic
def _bits(typingctx, x):
    """The IEEE bits of a float64, as int64."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _double(typingctx, i):
    """The float64 whose IEEE bits are the int64 ``i``."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_P1 = 1.66666666666666019037e-01
_P2 = -2.77777777770155933842e-03
_P3 = 6.61375632143793436117e-05
_P4 = -1.65339022054652515390e-06
_P5 = 4.13813679705723846039e-08
_EXP_FLOOR = -745.5  # exp of anything below is 0 in float64 (the smallest subnormal is e^-744.4)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def exp_nonpositive(x):
    """:math:`e^x` for :math:`x \\le 0` (also ``-inf``: 0); below 1 ulp from ``math.exp``."""
    x = max(x, _EXP_FLOOR)
    k = math.floor(x * _INV_LN2 + 0.5)
    hi = x - k * _LN2_HI
    lo = k * _LN2_LO
    r = hi - lo
    t = r * r
    c = r - t * (_P1 + t * (_P2 + t * (_P3 + t * (_P4 + t * _P5))))
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    # 2^k as two factors, each a normal number down to k = -1076
    k1 = np.int64(k) // 2
    k2 = np.int64(k) - k1
    return y * _double((k1 + 1023) << 52) * _double((k2 + 1023) << 52)


_LG1 = 6.666666666666735130e-01
_LG2 = 3.999999999940941908e-01
_LG3 = 2.857142874366239149e-01
_LG4 = 2.222219843214978396e-01
_LG5 = 1.818357216161805012e-01
_LG6 = 1.531383769920937332e-01
_LG7 = 1.479819860511658591e-01
_SQRT_HALF_HIGH = 0x3FE6A09E  # the high word of sqrt(2)/2


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def log_normal(x):
    """:math:`\\ln x` for a normal (not subnormal) finite :math:`x > 0`; below 1 ulp from
    ``math.log``. Other arguments give meaningless numbers: the filter's ``det S`` is at
    least ``det R > 0``."""
    bits = _bits(x)
    high = (bits >> 32) + (0x3FF00000 - _SQRT_HALF_HIGH)
    k = (high >> 20) - 0x3FF
    high = (high & 0x000FFFFF) + _SQRT_HALF_HIGH
    m = _double((high << 32) | (bits & 0xFFFFFFFF))
    f = m - 1.0
    half_f2 = 0.5 * f * f
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    r = z * (_LG1 + w * (_LG3 + w * (_LG5 + w * _LG7))) + w * (_LG2 + w * (_LG4 + w * _LG6))
    dk = np.float64(k)
    return s * (half_f2 + r) + dk * _LN2_LO - half_f2 + f + dk * _LN2_HI
