r"""``exp``, ``log`` and the normal CDF written out in arithmetic, so that the compiler can
vectorise the loops that call them (numba calls the C library's scalar ``exp``/``log``/
``erfc`` otherwise, one element at a time, and a loop with such a call stays scalar).

The algorithms and coefficients are fdlibm's (``e_exp.c``, ``e_log.c``; Sun Microsystems,
freely redistributable), the ones behind most C libraries' ``exp`` and ``log``: error
below 1 ulp, checked against ``math.exp``/``math.log`` in ``tests/unit/test_vecmath.py``.
Only the ranges the filter needs are handled (see each function); the reinterpretation
of a double's bits, which fdlibm does with a union, is an LLVM ``bitcast`` here.

- :math:`e^x = 2^k\, e^r`, :math:`k = \operatorname{round}(x / \ln 2)`,
  :math:`r = x - k \ln 2` (in two parts), :math:`e^r = 1 + r + r c / (2 - c)` with
  :math:`c = r - r^2 (P_1 + r^2 P_2 + \dots + r^8 P_5)`.
- :math:`\Phi(u)` from one Chebyshev series of :math:`\ln(\operatorname{erfc}(x)/t) + x^2`
  in :math:`t = 2 / (2 + x)` (the form of Numerical Recipes' ``Erf``; coefficients fitted
  here with 40-digit arithmetic): within 4e-16 of scipy's ``ndtr``, tested.
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


# Chebyshev coefficients c_0..c_30 of f(y) = ln(erfc(x) / t) + x^2 on y = 2t - 1 in (-1, 1],
# t = 2 / (2 + x) (computed with 40-digit arithmetic, mpmath; the terms after c_30 are
# below 1e-18): erfc(x) = t exp(-x^2 + f(y)) for every x >= 0 in one smooth series.
_ERFC_CHEB = (
    -1.3026537197817094342,
    0.6419697923564902603,
    0.019476473204185836312,
    -0.0095615147868086316419,
    -0.0009465953444820368663,
    0.00036683949785276145187,
    0.000042523324806907771645,
    -0.000020278578112534243154,
    -1.6242900046470255135e-6,
    1.3036558355805232018e-6,
    1.5626441722066143178e-8,
    -8.5238095914926542525e-8,
    6.5290544390988514964e-9,
    5.0593434955514689418e-9,
    -9.9136415649303308674e-10,
    -2.2736512229318358557e-10,
    9.646791102015526802e-11,
    2.3940380830391147447e-12,
    -6.8860275264975533984e-12,
    8.9448792730907257168e-13,
    3.1309213993429580783e-13,
    -1.1270822361367252366e-13,
    3.8109052551892320492e-16,
    7.1060976136092369884e-15,
    -1.5230282014571043049e-15,
    -9.4574945712912339405e-17,
    1.2102371892242789863e-16,
    -2.8166630877471769121e-17,
    5.0030055594458419927e-20,
    2.3281042579529258832e-18,
    -8.4460776825090125433e-19,
)
_SQRT1_2 = 0.7071067811865476


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def ndtr(u):
    """The standard normal CDF :math:`\\Phi(u) = \\tfrac12 \\operatorname{erfc}(-u/\\sqrt2)`: within
    2e-16 of it everywhere, the lower tail to 1e-14 relative (tested against scipy).

    :math:`\\tfrac12 \\operatorname{erfc}(x)` for :math:`x = |u| / \\sqrt 2` from the series
    above (Clenshaw's recurrence), then :math:`\\Phi = ` that for :math:`u < 0`, one minus it
    otherwise."""
    x = abs(u) * _SQRT1_2
    t = 2.0 / (2.0 + x)
    y = 2.0 * t - 1.0
    y2 = 2.0 * y
    # Clenshaw's recurrence written out (a loop here would keep the caller's loop scalar)
    d1, d2 = _ERFC_CHEB[30], 0.0
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[29], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[28], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[27], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[26], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[25], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[24], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[23], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[22], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[21], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[20], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[19], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[18], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[17], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[16], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[15], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[14], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[13], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[12], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[11], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[10], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[9], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[8], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[7], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[6], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[5], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[4], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[3], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[2], d1
    d1, d2 = y2 * d1 - d2 + _ERFC_CHEB[1], d1
    f = y * d1 - d2 + 0.5 * _ERFC_CHEB[0]
    half_erfc = 0.5 * t * exp_nonpositive(f - x * x)
    return half_erfc if u < 0.0 else 1.0 - half_erfc
