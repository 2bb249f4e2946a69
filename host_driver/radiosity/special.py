"""Clausen's function and the imaginary part of the dilogarithm (Lewin), compiled with numba: the
special functions of the closed-form edge-pair terms (:mod:`.closed_form`).
"""

import math

import numpy as np
from numba import njit

__all__ = ["CL2_ERROR"]

#: absolute error of :func:`_cl2` (tests/test_formfactor.py, against mpmath)
CL2_ERROR = 2.5e-16


def _clausen_series(terms=40):
    """Taylor coefficients of Clausen's function on its two halves, from exact Bernoulli numbers:

    - near 0: ``Cl2(t) = t (1 - ln t + sum_n g_n t^(2n))``, g_n = |B_2n| / (2n (2n+1)!);
    - near pi: ``Cl2(pi - y) = y (ln 2 - sum_n h_n y^(2n))`` (the integral of
      ``ln(2 cos(y/2))``, whose series is ln cos's), h_n = 2^(2n-1) (2^(2n) - 1) |B_2n| /
      (n (2n)! 4^n (2n+1)).

    On |t| <= pi/2 the first falls by 16 per term, on y <= pi/2 the second by 4: 13 and 26 terms
    give Cl2 to within 2.5e-16 absolute (tests/test_formfactor.py, against mpmath)."""
    from fractions import Fraction
    B = [Fraction(1)]
    for m in range(1, 2 * terms + 1):
        B.append(-sum(math.comb(m + 1, k) * B[k] for k in range(m)) / (m + 1))
    g = [float(abs(B[2 * n]) / (2 * n * math.factorial(2 * n + 1))) for n in range(1, 14)]
    h = [float(Fraction(2 ** (2 * n - 1) * (2 ** (2 * n) - 1)) * abs(B[2 * n])
               / (n * math.factorial(2 * n) * 4 ** n * (2 * n + 1))) for n in range(1, 27)]
    return np.array(g), np.array([math.log(2.0)] + [-c for c in h])


_CL2_NEAR0, _CL2_NEARPI = _clausen_series()


@njit(cache=True)
def _horner(x, coefficients):
    total = 0.0
    for k in range(len(coefficients) - 1, -1, -1):
        total = total * x + coefficients[k]
    return total


@njit(cache=True)
def _cl2(theta):
    """Clausen's Cl2(theta) = -int_0^theta ln|2 sin(x/2)| dx, to 2.5e-16 absolute."""
    t = theta - 2 * math.pi * math.floor(theta / (2 * math.pi) + 0.5)     # in [-pi, pi]
    if t == 0.0:
        return 0.0
    sign = 1.0
    if t < 0:
        sign, t = -1.0, -t
    if t <= 0.5 * math.pi:
        u = t * t
        return sign * t * (1.0 - math.log(t) + u * _horner(u, _CL2_NEAR0))
    y = math.pi - t
    return sign * y * _horner(y * y, _CL2_NEARPI)


@njit(cache=True)
def _im_li2(m, a, sa, ca):
    """Im Li2(m e^{ia}) - Cl2(2a)/2 for m >= 0, 0 < a < pi, sa = sin a, ca = cos a (Lewin's
    identity in Clausen functions). The Cl2(2a)/2 terms of the three dilogarithms in ``f`` add up to
    ``d^2 Cl2(2a) / sin a``, the same at the four corners of an edge pair, so they cancel in its
    corner sum and are left out."""
    if m == 0.0:
        return -0.5 * _cl2(2 * a)
    omega = math.atan2(m * sa, 1.0 - m * ca)
    return omega * math.log(m) + 0.5 * (_cl2(2 * omega) - _cl2(2 * omega + 2 * a))


@njit(cache=True)
def _im_li2_inverse_pair(m, s, c):
    """``_im_li2(m, a) + _im_li2(1/m, a)`` for m > 0 with two Clausen values instead of four:
    the angles omega of m and omega' of 1/m satisfy omega + omega' + a = pi (the triangle 0, 1,
    m e^{ia}), so Cl2(2 omega' + 2a) = -Cl2(2 omega) and Cl2(2 omega + 2a) = -Cl2(2 omega').
    s = sin a, c = cos a."""
    omega = math.atan2(m * s, 1.0 - m * c)
    omega_inv = math.atan2(s, m - c)
    return (omega - omega_inv) * math.log(m) + _cl2(2 * omega) + _cl2(2 * omega_inv)
