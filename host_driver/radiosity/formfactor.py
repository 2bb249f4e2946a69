"""Unoccluded form factors: exact patch-to-patch, in closed form (compiled with numba).

**The patch factor.** By Stokes' theorem the area-to-area factor is a double contour integral
(Sparrow; Schröder and Hanrahan, SIGGRAPH 1993)::

    A_j F_ji = 1/(4 pi) | sum_{p in edges(j)} sum_{q in edges(i)} (u_p . v_q) int_p int_q ln r^2 ds dt |

and each edge pair has a closed form. For non-parallel edges, with s and t measured from the
points where the two lines come closest (distance d, angle alpha between the unit directions),
the antiderivative ``f`` of ``-ln(s^2 + t^2 - 2 s t cos alpha + d^2) - 2`` is (Narayanaswamy,
Int. J. Heat Mass Transfer 91, 2015, eq. 22b; its derivative checked to 40 digits in the tests)::

    f = (cos(a)/2 (s^2+t^2) - s t) ln R2 + s W_s atan2(W_s, t - s cos a) + t W_t atan2(W_t, s - t cos a)
        + s t + d^2/(2 sin a) [Im Li2(w/p e^{ia}) + Im Li2(p/w e^{ia}) - 2 Im Li2((w-2s)/p e^{i(pi-a)})]
    W_s = sqrt(s^2 sin^2 a + d^2),  w = s + sqrt(s^2 + d^2/sin^2 a),  p = t + sqrt(t^2 + d^2/sin^2 a)

with Im Li2 through Clausen's function (Lewin). Parallel edges (a = 0 or pi) have an elementary
form. The constant -2 integrates to -2 L_p L_q, which cancels in the sum over a closed contour
(sum_p e_p = 0), so it is dropped everywhere. Limits are taken exactly where edges touch
(0 ln 0 = 0; the dilogarithm term vanishes with d): patches sharing an edge or a vertex need no
nudging. Each polygon is first clipped to the half-space in front of the other's plane, so the
integrand's cosines are the clipped ``max(cos, 0)`` ones; coplanar and back-facing pairs give 0.

The result is ``A_j F_ji``, symmetric in (i, j): reciprocity holds by construction, and to the
bit, since every pair is computed in a canonical order (below). :func:`unoccluded_factors`
divides by the receiver's area.

**Far pairs.** The edge-pair terms are of size L^2 ln D while their sum is of size L^4 / D^2, so
the closed form loses about (D / L)^2 digits to cancellation, and it costs about 9 us a pair.
Far pairs use a cubature of the exact point-to-triangle factor (below) over the smaller of the
two triangles instead (by reciprocity ``A_j F_ji = A_i F_ij``, either may be integrated),
wherever a derived bound shows it within ``FAR_TARGET`` (relative): the point factor is analytic
in the receiver point; its Taylor remainder of degree p over a ball of radius rho is at most
``M q^(p+1) / (1 - q)`` (Cauchy, along each line through the centroid, q = rho / R) where M
bounds the kernel on the complex ball of radius R = D / 4 around the receiver's centroid (D =
distance to the shooter): ``M <= 8.17 / D^2`` per unit shooter area. A rule exact to degree p
with positive weights errs by at most twice that, so
``|error of F_ji| <= (2/pi) A_i 8.17 / D^2 q^(p+1) / (1 - q)``. The rules: centroid (degree 1),
Radon's 7 points (degree 5), 5 x 5 and 8 x 8 collapsed Gauss (degrees 8 and 14): the first
whose bound, against the centroid's estimate of the value, looks met is computed, and it is
accepted only where the bound holds against its own value.
The bound is applied only where neither patch needs clipping (otherwise the integrand is not
analytic). ``FAR_TARGET`` is 1e-6, a tenth of the 1e-5 that the factors are held to against
pyviewfactor (issue 17); ``target=0`` selects the closed form for every pair (the reference).

**Grazing pairs.** Where the closed form's corner terms are large against their sum (``CANCELLATION``
times their absolute sum above the target times the value: grazing pairs, whose cosines suppress
the value but not the terms), the pair is recomputed by a cubature over the clipped polygons with
a bound that leaves the cosines out: the point factor is ``h_Q(x) G(x)``, the height of x above
the other's plane times ``G(x) = int_Q h_P(y) / (pi r^4) dy``, whose ratio of sup on a complex ball
to inf on the patch does not depend on the positive weight h_P; a positive rule exact to degree p
then errs relatively by at most ``2 C_k (1 + rho/D)^4 q^p / (1 - q)`` (docs/formfactors.md,
"Grazing pairs", derives it). Where the point factor itself would lose digits (edge-on pairs)
the cubature is a product rule over both polygons of ``h_P h_Q / (pi r^4)`` with the heights
computed directly.

The pair is put in a canonical order (its triangles' coordinates) before either form is chosen,
so ``(i, j)`` and ``(j, i)`` give the same bits: the render computes each unordered pair once
(:class:`PairCache`).

**The point factor.** From a differential receiver at p with unit normal n to a whole shooter
triangle T (Lambert's contour integral; Baum, Rushmeier, Winget 1989)::

    F_{dA -> T} = 1/(2 pi) | sum_k beta_k n . (R_k x R_{k+1}) / |R_k x R_{k+1}| |,  R_k = V_k - p

evaluated on the part of T in front of the receiver's tangent plane.
"""

import math

import numpy as np
from numba import njit, prange

from ... import threads as _threads  # (also chooses the threading layer before any kernel runs)
from ...exact_float import _plane_sign, plane_signs

__all__ = ["point_to_triangles", "triangle_to_points", "exchange_mask", "pair_factors", "samples_in_front", "sample_weights", "pair_sample_weights", "weight_points",
           "centroid_in_front",
           "unoccluded_factors", "PairCache", "form_factor_matrix", "FAR_TARGET", "METHODS"]

#: relative error bound a far-pair cubature must meet to replace the closed form
FAR_TARGET = 1e-6
#: method codes in the statistics of :func:`pair_factors`
METHODS = ("zero", "closed form", "centroid", "7-point", "25-point", "64-point", "subdivided", "edge quadrature",
           "144-point", "unresolved")
#: the closed form is recomputed by the subdivided cubature where this times the sum of the
#: absolute values of its corner terms exceeds the target times its value (about 64 rounding
#: units: the estimated relative error of the sum; docs/formfactors.md "Grazing pairs")
CANCELLATION = 64 * 2.0 ** -53
#: the unit roundoff of float64
_U = 2.0 ** -53
#: absolute error of :func:`_cl2` (tests/test_formfactor.py, against mpmath)
CL2_ERROR = 2.5e-16
#: relative error the contour sum's edge pairs are held to at ``target=0`` (else a tenth of the
#: target): an edge pair whose closed form's derived error bound exceeds its share of this times
#: the value is integrated numerically
EDGE_TARGET = 1e-12


# ---------------------------------------------------------------------------- Clausen, Im Li2

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


# ---------------------------------------------------------------------------- edge pairs

@njit(cache=True)
def _xlogx2(x2, coeff):
    """coeff * ln(x2), 0 when coeff is 0 (the 0 ln 0 limits of touching edges)."""
    if coeff == 0.0 or x2 == 0.0:
        return 0.0
    return coeff * math.log(x2)


@njit(cache=True)
def _f_skew(s, t, c, S, a, d):
    """The skew antiderivative ``f`` (module doc) at one corner, and a bound on its rounding
    error: 8 units of the sum of its addends' sizes (each addend is a few correctly rounded
    operations), plus the Clausen values' absolute error times their coefficient d^2 / (2 sin a)."""
    R2 = s * s + t * t - 2 * s * t * c + d * d
    if R2 < 0.0:
        R2 = 0.0
    val = _xlogx2(R2, 0.5 * c * (s * s + t * t) - s * t)
    mag = abs(val) + abs(s * t)
    Ws = math.sqrt(s * s * S * S + d * d)
    Wt = math.sqrt(t * t * S * S + d * d)
    if s != 0.0:
        x = s * Ws * math.atan2(Ws, t - s * c)
        val += x
        mag += abs(x)
    if t != 0.0:
        x = t * Wt * math.atan2(Wt, s - t * c)
        val += x
        mag += abs(x)
    val += s * t
    cl2 = 0.0
    if d > 0.0:
        k2 = (d / S) * (d / S)
        rs = math.sqrt(s * s + k2)
        rt = math.sqrt(t * t + k2)
        w = s + rs if s >= 0 else k2 / (rs - s)          # s + sqrt(s^2 + k2) without cancellation
        p = t + rt if t >= 0 else k2 / (rt - t)
        w2 = rs - s if s <= 0 else k2 / (rs + s)         # w - 2 s
        g1 = _im_li2_inverse_pair(w / p, S, c)
        g2 = _im_li2(w2 / p, math.pi - a, S, -c)
        x = 0.5 * d * d / S * (g1 - 2 * g2)
        val += x
        mag += 0.5 * d * d / S * (abs(g1) + 2 * abs(g2))
        cl2 = 0.5 * d * d / S * 4 * CL2_ERROR          # four Clausen values
    return val, 8 * _U * mag + cl2


@njit(cache=True)
def _f_parallel(s, t, d):
    """Antiderivative of -ln((s - t)^2 + d^2) - 2 for parallel lines (s, t along the same unit),
    and its rounding bound as :func:`_f_skew`'s."""
    x = s - t
    r2 = x * x + d * d
    val = _xlogx2(r2, 0.5 * (x * x - d * d))
    mag = abs(val) + abs(s * t)
    if d > 0.0:
        y = 2 * x * d * math.acos(x / math.sqrt(r2))
        val -= y
        mag += abs(y)
    return val + s * t, 8 * _U * mag


@njit(cache=True)
def _same(P, p, Q, q):
    return P[p, 0] == Q[q, 0] and P[p, 1] == Q[q, 1] and P[p, 2] == Q[q, 2]


@njit(cache=True)
def _edge_pair(P, p, p1, Q, q, q1):
    """Edge p -> p1 of P against edge q -> q1 of Q in closed form: ``(u . v) (I + 2 La Lb)`` with
    ``I = int int ln r^2`` over the two edges (the corner sum of ``f``, negated), the sum of the
    corners' absolute values, a derived bound on the term's error (docs/formfactors.md,
    "Nearly parallel edges"): the corners' rounding plus the error of the closest points of the
    two lines, which the corner sum is as sensitive to as to moving one edge along its line; and
    the largest the corners' values can be where the closest points are within the edges' span
    (``4 (|w0| + La + Lb)^2 (2 + max |ln r^2|)``): corner values beyond it are lost digits, not
    a sum's size the pair could be expected to lose to anyway.

    Edges sharing an end point are measured from it (I does not depend on their direction; the
    sign of u . v is kept): the lines meet there exactly, so d = 0 and the closest points are that
    point, with no error however parallel the edges are."""
    sa = sb = 1.0
    a, a1, b, b1 = p, p1, q, q1
    if _same(P, p1, Q, q):
        a, a1, sa = p1, p, -1.0
    elif _same(P, p, Q, q1):
        b, b1, sb = q1, q, -1.0
    elif _same(P, p1, Q, q1):
        a, a1, sa, b, b1, sb = p1, p, -1.0, q1, q, -1.0
    ux, uy, uz = P[a1, 0] - P[a, 0], P[a1, 1] - P[a, 1], P[a1, 2] - P[a, 2]
    vx, vy, vz = Q[b1, 0] - Q[b, 0], Q[b1, 1] - Q[b, 1], Q[b1, 2] - Q[b, 2]
    La = math.sqrt(ux * ux + uy * uy + uz * uz)
    Lb = math.sqrt(vx * vx + vy * vy + vz * vz)
    if La == 0.0 or Lb == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    ux, uy, uz = ux / La, uy / La, uz / La
    vx, vy, vz = vx / Lb, vy / Lb, vz / Lb
    c = ux * vx + uy * vy + uz * vz
    cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    S = math.sqrt(cx * cx + cy * cy + cz * cz)
    wx, wy, wz = P[a, 0] - Q[b, 0], P[a, 1] - Q[b, 1], P[a, 2] - Q[b, 2]     # w0 = a0 - b0
    w = math.sqrt(wx * wx + wy * wy + wz * wz)
    far2 = (w + La + Lb) ** 2                           # >= r^2 on the two edges
    sign = sa * sb
    if S < 1e-4:       # nearly parallel: the parallel form, with its model error, may be better
        par = _parallel_term(wx, wy, wz, w, ux, uy, uz, vx, vy, vz, c, S, La, Lb, far2)
        if S == 0.0:
            return -sign * par[0], par[1], par[2], par[3]
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    ang = math.atan2(S, c)
    uw = ux * wx + uy * wy + uz * wz
    vw = vx * wx + vy * wy + vz * wz
    det = 1.0 - c * c
    det = S * S if det < S * S else det
    sc = (c * vw - uw) / det                              # closest point on line a: a0 + sc u
    tc = (vw - c * uw) / det                              # on line b: b0 + tc v
    d = abs(wx * cx + wy * cy + wz * cz) / S
    s0, s1 = -sc, La - sc
    t0, t1 = -tc, Lb - tc
    f1, e1 = _f_skew(s1, t1, c, S, ang, d)
    f2, e2 = _f_skew(s0, t1, c, S, ang, d)
    f3, e3 = _f_skew(s1, t0, c, S, ang, d)
    f4, e4 = _f_skew(s0, t0, c, S, ang, d)
    # sc, tc: numerators of size |w0| S with rounding |w0| u (the unit vectors' cross product is
    # known only to u), over det = S^2; d: rounding |w0| u / S. Moving an edge by e along its
    # line changes I by at most e Lb (2 + max |ln r^2|); changing d by e changes it by at most
    # e 2 pi d / S^2 (1 + ln(1 + S^2 (La^2 + Lb^2) / d^2)) (docs/formfactors.md)
    dsc = 6 * _U * (w + abs(sc) * S * S) / (S * S)
    dd = 6 * _U * w / S
    lam = 2 + abs(math.log(far2)) + abs(math.log(max(d * d, (_U * far2) ** 2)))
    err = e1 + e2 + e3 + e4 + dsc * lam * (La + Lb)
    if d > 0.0:
        err += dd * min(2 * La * Lb / d, 2 * math.pi * d / (S * S) * (1 + math.log1p(S * S * (La * La + Lb * Lb) / (d * d))))
    if S < 1e-4 and par[2] < abs(c) * err:
        return -sign * par[0], par[1], par[2], par[3]
    return (-sign * c * (f1 - f2 - f3 + f4), abs(c) * (abs(f1) + abs(f2) + abs(f3) + abs(f4)),
            abs(c) * err, abs(c) * 4 * far2 * lam)


@njit(cache=True)
def _parallel_term(wx, wy, wz, w, ux, uy, uz, vx, vy, vz, c, S, La, Lb, far2):
    """:func:`_edge_pair`'s term by the parallel form, edge b turned about its start onto the
    direction +-u (angle theta = asin S), with its bound: rounding, plus the turn's model error.
    Turning moves b's points by at most theta Lb, and ``|grad ln r^2| = 2 / r``, so I changes by
    at most ``2 theta Lb La Lb / delta``, delta a lower bound on the distance from a's line to b
    along the way (docs/formfactors.md); infinite where delta is not positive."""
    sgn = 1.0 if c >= 0.0 else -1.0
    t0 = -(wx * ux + wy * uy + wz * uz)               # (b0 - a0) . u
    t1 = t0 + Lb * sgn
    px, py, pz = wx + t0 * ux, wy + t0 * uy, wz + t0 * uz
    d = math.sqrt(px * px + py * py + pz * pz)
    f1, e1 = _f_parallel(La, t1, d)
    f2, e2 = _f_parallel(0.0, t1, d)
    f3, e3 = _f_parallel(La, t0, d)
    f4, e4 = _f_parallel(0.0, t0, d)
    shift = 4 * _U * w                                # t0 and d are rounded dot products
    lam = 2 + abs(math.log(far2)) + abs(math.log(max(d * d, (_U * far2) ** 2)))
    err = e1 + e2 + e3 + e4 + shift * 2 * lam * (La + Lb)
    if S > 0.0:
        # b's nearest approach to a's line: |p + t q|, p = b0's offset from the line, q = v's part across it
        qx, qy, qz = vx - c * ux, vy - c * uy, vz - c * uz
        qq = qx * qx + qy * qy + qz * qz
        t = 0.0 if qq == 0.0 else min(max((px * qx + py * qy + pz * qz) / qq, 0.0), Lb)   # p = -(w + t0 u)
        mx, my, mz = -px + t * qx, -py + t * qy, -pz + t * qz
        theta = math.asin(min(S, 1.0))
        delta = math.sqrt(mx * mx + my * my + mz * mz) - 8 * _U * (w + Lb) - theta * Lb
        err += 2 * theta * Lb * La * Lb / delta if delta > 0.0 else np.inf
    return f1 - f2 - f3 + f4, abs(f1) + abs(f2) + abs(f3) + abs(f4), err, 4 * far2 * lam


# ---------------------------------------------------------------------------- edge quadrature

_GL8_X, _GL8_W = np.polynomial.legendre.leggauss(8)
_GL16_X, _GL16_W = np.polynomial.legendre.leggauss(16)


@njit(cache=True)
def _log_prim(x, h2):
    """Antiderivative in x of ln(x^2 + h2), h2 >= 0 (0 at x = 0)."""
    val = -2 * x
    if x != 0.0:
        val += x * math.log(x * x + h2)
    if h2 > 0.0:
        h = math.sqrt(h2)
        val += 2 * h * math.atan(x / h)
    return val


@njit(cache=True)
def _log_to_segment(px, py, pz, Q, b, vx, vy, vz, Lb):
    """``int_0^Lb ln |p - Q[b] - t v|^2 dt`` (v unit) in closed form: the distance to the line
    from a cross product, so it keeps its digits however close p is to the line."""
    wx, wy, wz = px - Q[b, 0], py - Q[b, 1], pz - Q[b, 2]
    tau = wx * vx + wy * vy + wz * vz
    hx, hy, hz = wy * vz - wz * vy, wz * vx - wx * vz, wx * vy - wy * vx
    h2 = hx * hx + hy * hy + hz * hz
    return _log_prim(Lb - tau, h2) - _log_prim(-tau, h2)


@njit(cache=True)
def _gauss(P, a, ux, uy, uz, Q, b, vx, vy, vz, Lb, lo, hi, X, W):
    m, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    total = 0.0
    for k in range(len(X)):
        s = m + h * X[k]
        total += W[k] * _log_to_segment(P[a, 0] + s * ux, P[a, 1] + s * uy, P[a, 2] + s * uz,
                                        Q, b, vx, vy, vz, Lb)
    return h * total


@njit(cache=True)
def _edge_pair_quadrature(P, p, p1, Q, q, q1, tol):
    """The term of :func:`_edge_pair` with ``I`` integrated numerically: the inner integral in
    closed form (:func:`_log_to_segment`, well conditioned), the outer one by adaptive
    Gauss-Legendre, split first where the integrand is not smooth (the feet of Q's end points
    on P's edge, and the lines' closest point), each piece accepted where the 8- and 16-point
    rules agree within its share of ``tol``. Returns (term, |term|, the sum of those
    differences). For nearly parallel edges, where the closed form cannot keep its digits."""
    ux, uy, uz = P[p1, 0] - P[p, 0], P[p1, 1] - P[p, 1], P[p1, 2] - P[p, 2]
    vx, vy, vz = Q[q1, 0] - Q[q, 0], Q[q1, 1] - Q[q, 1], Q[q1, 2] - Q[q, 2]
    La = math.sqrt(ux * ux + uy * uy + uz * uz)
    Lb = math.sqrt(vx * vx + vy * vy + vz * vz)
    if La == 0.0 or Lb == 0.0:
        return 0.0, 0.0, 0.0
    ux, uy, uz = ux / La, uy / La, uz / La
    vx, vy, vz = vx / Lb, vy / Lb, vz / Lb
    c = ux * vx + uy * vy + uz * vz
    cuts = np.empty(5)
    cuts[0], cuts[1] = 0.0, La
    n = 2
    for e in (q, q1):
        f = (Q[e, 0] - P[p, 0]) * ux + (Q[e, 1] - P[p, 1]) * uy + (Q[e, 2] - P[p, 2]) * uz
        if 0.0 < f < La:
            cuts[n] = f
            n += 1
    wx, wy, wz = P[p, 0] - Q[q, 0], P[p, 1] - Q[q, 1], P[p, 2] - Q[q, 2]
    det = 1.0 - c * c
    if det > 0.0:
        sc = (c * (vx * wx + vy * wy + vz * wz) - (ux * wx + uy * wy + uz * wz)) / det
        if 0.0 < sc < La:
            cuts[n] = sc
            n += 1
    cuts = np.sort(cuts[:n])
    # below this the two rules' difference is rounding: sum of ~|I| La terms, each good to ~u
    w = math.sqrt(wx * wx + wy * wy + wz * wz)
    floor = 64 * _U * La * Lb * (2 + abs(math.log((w + La + Lb) ** 2)) + abs(math.log(Lb * Lb)))
    tol = max(tol, floor)
    stack = np.empty((128, 2))
    total = 0.0
    err = 0.0
    pieces = 0
    for k in range(n - 1):
        if cuts[k + 1] <= cuts[k]:
            continue
        top = 0
        stack[0, 0], stack[0, 1] = cuts[k], cuts[k + 1]
        top = 1
        while top > 0:
            top -= 1
            lo, hi = stack[top, 0], stack[top, 1]
            g16 = _gauss(P, p, ux, uy, uz, Q, q, vx, vy, vz, Lb, lo, hi, _GL16_X, _GL16_W)
            g8 = _gauss(P, p, ux, uy, uz, Q, q, vx, vy, vz, Lb, lo, hi, _GL8_X, _GL8_W)
            e = abs(g16 - g8)
            pieces += 1
            mid = 0.5 * (lo + hi)
            if e <= tol * (hi - lo) / La or top + 2 > len(stack) or pieces > 2000 or not (lo < mid < hi):
                total += g16
                err += e
            else:
                stack[top, 0], stack[top, 1] = mid, hi
                stack[top + 1, 0], stack[top + 1, 1] = lo, mid
                top += 2
    term = c * (total + 2 * La * Lb)
    return term, abs(term), abs(c) * err


@njit(cache=True)
def _contour(P, nP, Q, nQ, rel):
    """A_P F_PQ (= A_Q F_QP) for convex planar polygons P (nP vertices) and Q, both clipped; the
    sum of the absolute values of the corner terms it adds up; and a bound on its error (all /
    (4 pi)). The first and the last: their ratio times the rounding unit estimates the digits lost
    to cancellation between edge pairs. Edge pairs whose closed form's error bound exceeds their
    share of ``rel`` times the value (or, where larger, of the sum's own rounding) are integrated
    numerically instead (:func:`_edge_pair_quadrature`); returns, last, whether any was."""
    n = nP * nQ
    terms = np.empty(n)
    errs = np.empty(n)
    mags = np.empty(n)
    scales = np.empty(n)
    total = 0.0
    for p in range(nP):
        p1 = p + 1 if p + 1 < nP else 0
        for q in range(nQ):
            q1 = q + 1 if q + 1 < nQ else 0
            k = p * nQ + q
            terms[k], mags[k], errs[k], scales[k] = _edge_pair(P, p, p1, Q, q, q1)
            total += terms[k]
    quadrature = False
    for _ in range(4):        # the value the shares are of may itself have been wrong: until it holds
        # no edge pair need be better than the sum's own rounding (CANCELLATION of its terms' sizes)
        sizes = np.minimum(mags, scales)
        if errs.sum() <= 0.5 * max(rel * abs(total), CANCELLATION * sizes.sum()):
            break
        again = False
        for k in range(n):
            # its share of the target, or its own rounding, whichever is larger
            share = 0.5 * max(rel * abs(total) / n, CANCELLATION * sizes[k])
            if errs[k] > share:
                p, q = k // nQ, k % nQ
                p1 = p + 1 if p + 1 < nP else 0
                q1 = q + 1 if q + 1 < nQ else 0
                t, m, e = _edge_pair_quadrature(P, p, p1, Q, q, q1, 0.5 * share)
                if e < errs[k]:
                    total += t - terms[k]
                    terms[k], mags[k], errs[k] = t, m, e
                    quadrature = again = True
        if not again:
            break
    total = 0.0
    for k in range(n):         # summed again in order, so the value does not depend on the rounds
        total += terms[k]
    return abs(total) / (4 * math.pi), mags.sum() / (4 * math.pi), errs.sum() / (4 * math.pi), quadrature


@njit(cache=True)
def _side(T, k, px, py, pz, nx, ny, nz):
    return nx * (T[k, 0] - px) + ny * (T[k, 1] - py) + nz * (T[k, 2] - pz)


@njit(cache=True)
def _clip(T, px, py, pz, nx, ny, nz, out):
    """Sutherland-Hodgman: the part of triangle T with n . (x - p) >= 0 -> out (<= 4 rows)."""
    h0 = _side(T, 0, px, py, pz, nx, ny, nz)
    h1 = _side(T, 1, px, py, pz, nx, ny, nz)
    h2 = _side(T, 2, px, py, pz, nx, ny, nz)
    if not (h0 > 0 or h1 > 0 or h2 > 0):
        return 0
    n = 0
    for k in range(3):
        k1 = k + 1 if k < 2 else 0
        hk = h0 if k == 0 else (h1 if k == 1 else h2)
        hk1 = h0 if k1 == 0 else (h1 if k1 == 1 else h2)
        if hk >= 0:
            out[n, 0], out[n, 1], out[n, 2] = T[k, 0], T[k, 1], T[k, 2]
            n += 1
        if (hk > 0 and hk1 < 0) or (hk < 0 and hk1 > 0):
            f = hk / (hk - hk1)
            for c in range(3):
                out[n, c] = T[k, c] + f * (T[k1, c] - T[k, c])
            n += 1
    return n


@njit(cache=True)
def _needs_clip(T, px, py, pz, nx, ny, nz):
    for k in range(3):
        if _side(T, k, px, py, pz, nx, ny, nz) < 0:
            return True
    return False


# ---------------------------------------------------------------------------- point factor

@njit(cache=True)
def _lambert(px, py, pz, nx, ny, nz, T, poly):
    """F_{dA -> T} from point p, unit normal n, to triangle T (3, 3); 0 on T's plane.
    ``poly`` is a (4, 3) work array."""
    return _lambert_terms(px, py, pz, nx, ny, nz, T, poly)[0]


@njit(cache=True)
def _lambert_terms(px, py, pz, nx, ny, nz, T, poly):
    """:func:`_lambert` and the sum of the absolute values of its terms (both / (2 pi)): their ratio
    times the rounding unit estimates the digits lost where T is seen edge-on and nearly in the
    receiver's plane (the terms are ~L / r, their sum ~L^2 cos_i cos_j / r^2)."""
    e1x, e1y, e1z = T[1, 0] - T[0, 0], T[1, 1] - T[0, 1], T[1, 2] - T[0, 2]
    e2x, e2y, e2z = T[2, 0] - T[0, 0], T[2, 1] - T[0, 1], T[2, 2] - T[0, 2]
    mx, my, mz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    mm = math.sqrt(mx * mx + my * my + mz * mz)
    if mm == 0.0 or nx * nx + ny * ny + nz * nz == 0.0:
        return 0.0, 0.0
    size = 0.0
    for k in range(3):
        size = max(size, abs(T[k, 0] - px), abs(T[k, 1] - py), abs(T[k, 2] - pz))
    if abs(_side(T, 0, px, py, pz, mx, my, mz)) / mm <= 1e-12 * size:
        return 0.0, 0.0
    k = _clip(T, px, py, pz, nx, ny, nz, poly)
    if k < 2:
        return 0.0, 0.0
    return _lambert_front(px, py, pz, nx, ny, nz, poly, k)


@njit(cache=True)
def _lambert_normal(points, m, normals, n, T, poly):
    """:func:`_lambert` from points[m] with normals[n] made unit (0 for a zero normal)."""
    nx, ny, nz = normals[n, 0], normals[n, 1], normals[n, 2]
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if norm == 0.0:
        return 0.0
    return _lambert(points[m, 0], points[m, 1], points[m, 2], nx / norm, ny / norm, nz / norm, T, poly)


@njit(cache=True)
def _lambert_many(points, normals, tris):
    out = np.empty(len(points))
    poly = np.empty((4, 3))
    for m in range(len(points)):
        out[m] = _lambert_normal(points, m, normals, m, tris[m], poly)
    return out


def _broadcast(points, normals, triangles):
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    M = max(len(p), len(n), len(T))
    return (np.ascontiguousarray(np.broadcast_to(p, (M, 3))), np.ascontiguousarray(np.broadcast_to(n, (M, 3))),
            np.ascontiguousarray(np.broadcast_to(T, (M, 3, 3))))


def point_to_triangles(point, normal, triangles):
    """Factors from one differential receiver (point (3,), normal (3,)) to triangles (M,3,3) -> (M,)."""
    return _lambert_many(*_broadcast(np.asarray(point)[None], np.asarray(normal)[None], triangles))


def triangle_to_points(triangle, points, normals):
    """Factors from many receivers (points (M,3), normals (M,3)) to one shooter triangle (3,3) -> (M,)."""
    return _lambert_many(*_broadcast(points, normals, np.asarray(triangle)[None]))


# ---------------------------------------------------------------------------- patch factors

_A1, _A2 = (6 - math.sqrt(15)) / 21, (6 + math.sqrt(15)) / 21
_W1, _W2 = (155 - math.sqrt(15)) / 1200, (155 + math.sqrt(15)) / 1200
#: Radon's degree-5 rule: barycentric points and weights (sum 1)
_RULE7 = np.array([[1 / 3, 1 / 3, 1 / 3],
                   [_A1, _A1, 1 - 2 * _A1], [_A1, 1 - 2 * _A1, _A1], [1 - 2 * _A1, _A1, _A1],
                   [_A2, _A2, 1 - 2 * _A2], [_A2, 1 - 2 * _A2, _A2], [1 - 2 * _A2, _A2, _A2]])
_RULE7_W = np.array([9 / 40, _W1, _W1, _W1, _W2, _W2, _W2])


def _collapsed_gauss(n):
    """n x n Gauss-Legendre on the square mapped onto the triangle (Duffy): positive weights
    (sum 1), exact to degree 2n - 2. Returns barycentric points (n^2, 3) and weights (n^2,)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = (x + 1) / 2, w / 2
    u, v = np.meshgrid(x, x, indexing="ij")
    wu, wv = np.meshgrid(w, w, indexing="ij")
    a, b = u.ravel(), (v * (1 - u)).ravel()
    return np.stack([1 - a - b, a, b], axis=1), 2 * (wu * wv * (1 - u)).ravel()


_RULE25, _RULE25_W = _collapsed_gauss(5)
_RULE64, _RULE64_W = _collapsed_gauss(8)
_RULE144, _RULE144_W = _collapsed_gauss(12)     # degree 22: grazing pairs, cheaper than a split


@njit(cache=True)
def _far_bound(area_i, D, rho, degree):
    """Derived bound on |error of F_ji| of a positive rule exact to ``degree`` (module doc)."""
    q = 4.0 * rho / D
    if q >= 0.5:
        return np.inf
    return (2 / math.pi) * area_i * 8.17 / (D * D) * q ** (degree + 1) / (1 - q)


@njit(cache=True)
def _normal(T):
    e1x, e1y, e1z = T[1, 0] - T[0, 0], T[1, 1] - T[0, 1], T[1, 2] - T[0, 2]
    e2x, e2y, e2z = T[2, 0] - T[0, 0], T[2, 1] - T[0, 1], T[2, 2] - T[0, 2]
    mx, my, mz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    m = math.sqrt(mx * mx + my * my + mz * mz)
    if m == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    return mx / m, my / m, mz / m, m


@njit(cache=True)
def _radius(T, cx, cy, cz):
    r = 0.0
    for k in range(3):
        r = max(r, math.sqrt((T[k, 0] - cx) ** 2 + (T[k, 1] - cy) ** 2 + (T[k, 2] - cz) ** 2))
    return r


@njit(cache=True)
def _cubature(Ti, Tj, njx, njy, njz, rule, weights, poly):
    f = 0.0
    for r in range(len(weights)):
        x = rule[r, 0] * Tj[0, 0] + rule[r, 1] * Tj[1, 0] + rule[r, 2] * Tj[2, 0]
        y = rule[r, 0] * Tj[0, 1] + rule[r, 1] * Tj[1, 1] + rule[r, 2] * Tj[2, 1]
        z = rule[r, 0] * Tj[0, 2] + rule[r, 1] * Tj[1, 2] + rule[r, 2] * Tj[2, 2]
        f += weights[r] * _lambert(x, y, z, njx, njy, njz, Ti, poly)
    return f


@njit(cache=True)
def _centroid(T):
    return (T[0, 0] + T[1, 0] + T[2, 0]) / 3, (T[0, 1] + T[1, 1] + T[2, 1]) / 3, (T[0, 2] + T[1, 2] + T[2, 2]) / 3


@njit(cache=True)
def _far(Tt, Tr, target, stats, P):
    """``A_r F_rt`` by a cubature over the receiver Tr of the point factor to Tt, with the first
    rule whose derived bound (module doc) is within ``target`` of the value; -1.0 if none is.
    Neither triangle may need clipping."""
    ntx, nty, ntz, At2 = _normal(Tt)
    nrx, nry, nrz, Ar2 = _normal(Tr)
    ctx, cty, ctz = _centroid(Tt)
    crx, cry, crz = _centroid(Tr)
    rho_t = _radius(Tt, ctx, cty, ctz)
    rho_r = _radius(Tr, crx, cry, crz)
    D = math.sqrt((crx - ctx) ** 2 + (cry - cty) ** 2 + (crz - ctz) ** 2) - rho_t   # <= dist(cr, Tt)
    if D <= 8 * rho_r:
        return -1.0
    At = 0.5 * At2
    Ar = 0.5 * Ar2
    f1, mag = _lambert_terms(crx, cry, crz, nrx, nry, nrz, Tt, P)
    if not f1 > 0 or CANCELLATION * mag > target * f1:
        return -1.0             # edge-on: the point factor itself loses the target to rounding
    if _far_bound(At, D, rho_r, 1) <= target * f1:
        stats[2] += 1
        return Ar * f1
    # a rule is computed only where the bound, against the centroid's estimate of the value, looks
    # met; it is accepted only where the bound holds against its own value
    if _far_bound(At, D, rho_r, 5) <= 0.9 * target * f1:
        f = _cubature(Tt, Tr, nrx, nry, nrz, _RULE7, _RULE7_W, P)
        if f > 0 and _far_bound(At, D, rho_r, 5) <= target * f:
            stats[3] += 1
            return Ar * f
    if _far_bound(At, D, rho_r, 8) <= 0.9 * target * f1:
        f = _cubature(Tt, Tr, nrx, nry, nrz, _RULE25, _RULE25_W, P)
        if f > 0 and _far_bound(At, D, rho_r, 8) <= target * f:
            stats[4] += 1
            return Ar * f
    if _far_bound(At, D, rho_r, 14) <= 0.9 * target * f1:
        f = _cubature(Tt, Tr, nrx, nry, nrz, _RULE64, _RULE64_W, P)
        if f > 0 and _far_bound(At, D, rho_r, 14) <= target * f:
            stats[5] += 1
            return Ar * f
    return -1.0


@njit(cache=True)
def _lambert_front(px, py, pz, nx, ny, nz, O, nO):
    """:func:`_lambert_terms` for a convex polygon O (nO vertices) already wholly in front of the
    receiver's plane (no clipping): the factor and the sum of its terms' absolute values."""
    total = 0.0
    mag = 0.0
    for e in range(nO):
        e1 = e + 1 if e + 1 < nO else 0
        ax, ay, az = O[e, 0] - px, O[e, 1] - py, O[e, 2] - pz
        bx, by, bz = O[e1, 0] - px, O[e1, 1] - py, O[e1, 2] - pz
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        cn = math.sqrt(cx * cx + cy * cy + cz * cz)
        if cn > 0.0:
            term = math.atan2(cn, ax * bx + ay * by + az * bz) * (cx * nx + cy * ny + cz * nz) / cn
            total += term
            mag += abs(term)
    return abs(total) / (2 * math.pi), mag / (2 * math.pi)


@njit(cache=True)
def _grazing_bound(rho, D, degree):
    """Relative error bound of a positive rule exact to ``degree`` on a triangle of radius rho whose
    centroid is at least D from the other polygon (docs/formfactors.md "Grazing pairs"): the
    cosines are left out, so it holds however grazing the pair is. Best of a few ball radii k D."""
    best = np.inf
    if D <= 0.0:
        return best
    for k in (0.25, 0.3, 1.0 / 3.0, 0.38):
        q = rho / (k * D)
        if q < 1.0:
            c = 1.0 / (1.0 - 2.0 * k - k * k) ** 2
            best = min(best, 2.0 * c * (1.0 + rho / D) ** 4 * q ** degree / (1.0 - q))
    return best


@njit(cache=True)
def _polygon_ball(O, nO):
    """Vertex mean of a convex polygon and the largest distance from it to a vertex."""
    cx = cy = cz = 0.0
    for k in range(nO):
        cx += O[k, 0]
        cy += O[k, 1]
        cz += O[k, 2]
    cx, cy, cz = cx / nO, cy / nO, cz / nO
    r = 0.0
    for k in range(nO):
        r = max(r, math.sqrt((O[k, 0] - cx) ** 2 + (O[k, 1] - cy) ** 2 + (O[k, 2] - cz) ** 2))
    return cx, cy, cz, r


@njit(cache=True)
def _split4(T, stack, top):
    """The midpoint split of triangle T into stack[top:top + 4], in the order the cubatures pop them."""
    for m in range(4):
        for c in range(3):
            a, b, e = T[0, c], T[1, c], T[2, c]
            ab, be, ea = 0.5 * (a + b), 0.5 * (b + e), 0.5 * (e + a)
            if m == 0:
                stack[top + m, 0, c], stack[top + m, 1, c], stack[top + m, 2, c] = a, ab, ea
            elif m == 1:
                stack[top + m, 0, c], stack[top + m, 1, c], stack[top + m, 2, c] = ab, b, be
            elif m == 2:
                stack[top + m, 0, c], stack[top + m, 1, c], stack[top + m, 2, c] = ea, be, e
            else:
                stack[top + m, 0, c], stack[top + m, 1, c], stack[top + m, 2, c] = be, ea, ab


@njit(cache=True)
def _grazing_nodes(I, nI, ox, oy, oz, orho, target, X, W):
    """Cubature nodes X (rows) and weights W (area included) over polygon I, fanned into triangles,
    each split in 4 until :func:`_grazing_bound` against the other polygon's ball (centre o,
    radius orho) is within ``target``; returns their number, -1 if X is too short for it."""
    stack = np.empty((16, 3, 3))
    depth = np.zeros(16, dtype=np.int64)
    top = 0
    for k in range(1, nI - 1):
        for c in range(3):
            stack[top, 0, c], stack[top, 1, c], stack[top, 2, c] = I[0, c], I[k, c], I[k + 1, c]
        top += 1
    n = 0
    while top > 0:
        top -= 1
        T = stack[top].copy()
        level = depth[top]
        cx, cy, cz = _centroid(T)
        rho = _radius(T, cx, cy, cz)
        D = math.sqrt((cx - ox) ** 2 + (cy - oy) ** 2 + (cz - oz) ** 2) - orho
        if _grazing_bound(rho, D, 5) <= target:
            rule, weights = _RULE7, _RULE7_W
        elif _grazing_bound(rho, D, 8) <= target:
            rule, weights = _RULE25, _RULE25_W
        elif _grazing_bound(rho, D, 14) <= target:
            rule, weights = _RULE64, _RULE64_W
        elif _grazing_bound(rho, D, 22) <= target:
            rule, weights = _RULE144, _RULE144_W
        elif level < 3 and top + 4 <= len(stack):
            _split4(T, stack, top)                   # children of half the radius
            depth[top:top + 4] = level + 1
            top += 4
            continue
        else:
            return -1
        if n + len(weights) > len(W):
            return -1
        _, _, _, A2 = _normal(T)
        for r in range(len(weights)):
            for c in range(3):
                X[n, c] = rule[r, 0] * T[0, c] + rule[r, 1] * T[1, c] + rule[r, 2] * T[2, c]
            W[n] = 0.5 * A2 * weights[r]
            n += 1
    return n


@njit(cache=True)
def _grazing(P, nP, npx, npy, npz, Q, nQ, nqx, nqy, nqz, target):
    """``A_P F_PQ`` by a product cubature over both polygons (each wholly in front of the other's
    plane, unit normals np, nq) of ``h_P(x) h_Q(y) / (pi r^4)``, the heights above the other's plane
    computed directly (so grazing cosines keep their digits), each side's rule within target / 2 by
    the cosine-free bound; -1.0 where 3 levels of splitting do not suffice."""
    px, py, pz, prho = _polygon_ball(P, nP)
    qx, qy, qz, qrho = _polygon_ball(Q, nQ)
    X = np.empty((4096, 3))
    WX = np.empty(4096)
    # cheaper where the point factor keeps its digits (not edge-on): the cubature over the smaller
    # polygon of the exact point factor to the other, the bound within the whole target
    if prho > qrho:
        P, nP, npx, npy, npz, px, py, pz, Q, nQ, nqx, nqy, nqz, qx, qy, qz, qrho = \
            Q, nQ, nqx, nqy, nqz, qx, qy, qz, P, nP, npx, npy, npz, px, py, pz, prho
    f, mag = _lambert_front(px, py, pz, npx, npy, npz, Q, nQ)
    if f > 0.0 and CANCELLATION * mag <= 0.1 * target * f:
        nx = _grazing_nodes(P, nP, qx, qy, qz, qrho, target, X, WX)
        if nx >= 0:
            total = 0.0
            for a in range(nx):
                total += WX[a] * _lambert_front(X[a, 0], X[a, 1], X[a, 2], npx, npy, npz, Q, nQ)[0]
            return total
    prho = _polygon_ball(P, nP)[3]
    Y = np.empty((4096, 3))
    WY = np.empty(4096)
    nx = _grazing_nodes(P, nP, qx, qy, qz, qrho, 0.5 * target, X, WX)
    if nx < 0:
        return -1.0
    ny = _grazing_nodes(Q, nQ, px, py, pz, prho, 0.5 * target, Y, WY)
    if ny < 0:
        return -1.0
    for b in range(ny):      # W times the height of y above P's plane
        WY[b] *= npx * (Y[b, 0] - P[0, 0]) + npy * (Y[b, 1] - P[0, 1]) + npz * (Y[b, 2] - P[0, 2])
    inner = _inner_sums(X, nx, Y, WY, ny)
    total = 0.0
    for a in range(nx):
        hx = nqx * (X[a, 0] - Q[0, 0]) + nqy * (X[a, 1] - Q[0, 1]) + nqz * (X[a, 2] - Q[0, 2])
        total += WX[a] * hx * inner[a]
    if not math.isfinite(total):
        return -1.0             # coincident nodes (touching polygons): keep the closed form
    return abs(total) / math.pi


@njit(cache=True, error_model="numpy")
def _inner_sums(X, nx, Y, WY, ny):
    """(nx,): ``sum_b WY[b] / |X[a] - Y[b]|^4`` for every node a, each sum in the order b = 0, 1, ...
    The b loop is outside so that the a loop, whose sums are independent, runs in SIMD lanes
    (a sum over b cannot: float addition does not reassociate); each a's sum is the same
    arithmetic, in the same order, as a loop over b for that a alone, so the same bits.
    ``error_model="numpy"``: a division by 0 gives inf instead of raising, which is what lets
    the compiler vectorise the division (3.5x faster); the caller rejects a sum that is not finite."""
    x0 = np.ascontiguousarray(X[:nx, 0])
    x1 = np.ascontiguousarray(X[:nx, 1])
    x2 = np.ascontiguousarray(X[:nx, 2])
    inner = np.zeros(nx)
    for b in range(ny):
        y0, y1, y2, w = Y[b, 0], Y[b, 1], Y[b, 2], WY[b]
        for a in range(nx):
            dx, dy, dz = x0[a] - y0, x1[a] - y1, x2[a] - y2
            r2 = dx * dx + dy * dy + dz * dz
            inner[a] += w / (r2 * r2)
    return inner


@njit(cache=True)
def _before(A, B):
    """Lexicographic order of two triangles' coordinates (a canonical order of a pair)."""
    for k in range(3):
        for c in range(3):
            if A[k, c] != B[k, c]:
                return A[k, c] < B[k, c]
    return False


@njit(cache=True)
def _pair(Ti, Tj, target, stats, P, Q):
    """A_j F_ji (= A_i F_ij) for shooter Ti, receiver Tj; stats[method] += 1. P, Q: (4, 3) work
    arrays. The pair is first put in a canonical order, so that (Ti, Tj) and (Tj, Ti) give the
    same bits: reciprocity holds exactly and a pair's value can be reused for the reverse pair."""
    if _before(Tj, Ti):
        Ti, Tj = Tj, Ti
    nix, niy, niz, Ai2 = _normal(Ti)
    njx, njy, njz, Aj2 = _normal(Tj)
    if Ai2 == 0.0 or Aj2 == 0.0:
        stats[0] += 1
        return 0.0
    if (not _needs_clip(Tj, Ti[0, 0], Ti[0, 1], Ti[0, 2], nix, niy, niz)
            and not _needs_clip(Ti, Tj[0, 0], Tj[0, 1], Tj[0, 2], njx, njy, njz)):
        # integrate over the smaller triangle: the bound falls with its radius
        cix, ciy, ciz = _centroid(Ti)
        cjx, cjy, cjz = _centroid(Tj)
        if _radius(Tj, cjx, cjy, cjz) <= _radius(Ti, cix, ciy, ciz):
            value = _far(Ti, Tj, target, stats, P)
        else:
            value = _far(Tj, Ti, target, stats, P)
        if value >= 0.0:
            return value
    nP = _clip(Tj, Ti[0, 0], Ti[0, 1], Ti[0, 2], nix, niy, niz, P)     # receiver part in front of the shooter
    nQ = _clip(Ti, Tj[0, 0], Tj[0, 1], Tj[0, 2], njx, njy, njz, Q)     # shooter part in front of the receiver
    if nP < 3 or nQ < 3:
        stats[0] += 1
        return 0.0
    # each edge pair held to a tenth of the pair's target (EDGE_TARGET for the reference, target 0)
    value, size, err, quadrature = _contour(P, nP, Q, nQ, 0.1 * target if target > 0.0 else EDGE_TARGET)
    if CANCELLATION * size + err > max(target, EDGE_TARGET) * value:
        # the closed form may have lost the target to cancellation (grazing far pairs, slivers):
        # a product cubature with the cosine-free bound instead, else two high-order rules
        if target > 0.0:
            g = _grazing(P, nP, njx, njy, njz, Q, nQ, nix, niy, niz, target)
            if g >= 0.0:
                stats[6] += 1
                return g
        if Aj2 <= Ai2:          # over the smaller one's part in front of the other
            g = _two_rules(P, nP, njx, njy, njz, Ti, max(target, EDGE_TARGET))
        else:
            g = _two_rules(Q, nQ, nix, niy, niz, Tj, max(target, EDGE_TARGET))
        if g >= 0.0:
            stats[8] += 1
            return g
        stats[9] += 1           # no method met the target: counted, so a render can report it
        return value
    stats[7 if quadrature else 1] += 1
    return value


@njit(cache=True)
def _two_rules(O, nO, nx, ny, nz, T, target):
    """``A_O F_OT`` for a convex polygon O (nO vertices, unit normal n: the smaller patch's part in
    front of the other's plane) and a triangle T, by a cubature over O of the exact point factor
    to T: O fanned into triangles, each split in 4 until, on each part, the 64- and 144-point
    rules agree within its share of a tenth of ``target`` (at most 256 parts), where the point
    factor keeps its digits at O's centre; -1.0 otherwise. The tangent plane is O's at every
    node, so the point factor's clipping of T is the same at all: the integrand is analytic. For
    slivers, whose contour sum cancels by their aspect ratio."""
    P = np.empty((4, 3))
    cx, cy, cz, _ = _polygon_ball(O, nO)
    f1, mag = _lambert_terms(cx, cy, cz, nx, ny, nz, T, P)
    if not f1 > 0 or CANCELLATION * mag > 0.1 * target * f1:
        return -1.0
    stack = np.empty((64, 3, 3))
    top = 0
    area = 0.0
    for k in range(1, nO - 1):
        for c in range(3):
            stack[top, 0, c], stack[top, 1, c], stack[top, 2, c] = O[0, c], O[k, c], O[k + 1, c]
        area += _normal(stack[top])[3]
        top += 1
    tol = 0.1 * target * f1 * area     # against the centre's estimate, checked at the end
    parts, total = 0, 0.0
    while top > 0:
        top -= 1
        S = stack[top].copy()
        a2 = _normal(S)[3]
        f64 = _cubature(T, S, nx, ny, nz, _RULE64, _RULE64_W, P) * a2
        f144 = _cubature(T, S, nx, ny, nz, _RULE144, _RULE144_W, P) * a2
        parts += 1
        if abs(f144 - f64) <= tol * a2 / area:
            total += f144
        elif parts + top + 4 > 256 or top + 4 > len(stack):
            return -1.0
        else:
            _split4(S, stack, top)
            top += 4
    if not total > 0 or f1 * area > 2 * total:
        return -1.0            # the centre's estimate was too large: the shares were too loose
    return 0.5 * total


@njit(cache=True, parallel=True)
def _pairs(shooters, receivers, target, methods):
    """Every pair on the thread pool: pairs are independent, each with its own work arrays and
    its own row of ``methods`` (M, len(METHODS)), so the result does not depend on the threads."""
    out = np.empty(len(shooters))
    for m in prange(len(shooters)):
        P = np.empty((4, 3))
        Q = np.empty((4, 3))
        out[m] = _pair(shooters[m], receivers[m], target, methods[m], P, Q)
    return out


def pair_factors(shooters, receivers, *, target=FAR_TARGET, stats=None):
    """``A_j F_ji`` for shooter triangles i (M,3,3) and receiver triangles j (M,3,3) -> (M,).

    Symmetric in (i, j) bit for bit (the kernel puts each pair in a canonical order). ``stats``, an int64
    array of len(METHODS), counts the pairs per method. Geometry only: which side faces which
    is :func:`exchange_mask`'s business; a pair where one lies wholly behind the other's plane
    gets 0.
    """
    S = np.ascontiguousarray(np.asarray(shooters, dtype=np.float64).reshape(-1, 3, 3))
    R = np.ascontiguousarray(np.asarray(receivers, dtype=np.float64).reshape(-1, 3, 3))
    S, R = np.broadcast_arrays(S, R)
    methods = np.zeros((len(S), len(METHODS)), dtype=np.int64)
    out = _pairs(np.ascontiguousarray(S), np.ascontiguousarray(R), float(target), methods)
    if stats is not None:
        stats += methods.sum(axis=0)
    return out


def exchange_mask(scene, i):
    """bool (N,): receivers j that can exchange light with shooter i, so rays only where they count.

    j qualifies when all of these hold, each decided exactly on the float scene
    (:func:`blockray.exact_float.plane_signs`; no tolerance, so tiny patches beside huge ones
    are treated like any others):

    - j != i, j has non-zero area and a reflectance that is not all zero;
    - some vertex of j is strictly in front of i's plane (i emits from its front) and some vertex
      of i strictly in front of j's plane: exactly the pairs whose clipped factor is not 0.
    """
    eligible = (scene.reflectance > 0).any(axis=1) & (scene.areas > 0)
    return _exchange_row(scene.patch_vertices, int(i), eligible)


_UNITS = np.eye(3, dtype=np.int64)
_ONES = np.ones(3, dtype=np.int64)


@njit(cache=True)
def _vertex_in_front(P, T):
    """Some vertex of triangle P strictly in front of T's plane (exact signs)."""
    for k in range(3):
        if _plane_sign(T, P, _UNITS[k]) > 0:
            return True
    return False


@njit(cache=True)
def _exchange_row(V, i, eligible):
    mask = np.zeros(len(V), dtype=np.bool_)
    for j in range(len(V)):
        if j != i and eligible[j] and _vertex_in_front(V[j], V[i]) and _vertex_in_front(V[i], V[j]):
            mask[j] = True
    return mask


def centroid_in_front(scene, i, receivers):
    """bool (len(receivers),): receiver j's centroid (its ray end point) strictly in front of i's
    plane. Where it is not, rays from i to j's centroid say nothing about the light i sends to the
    part of j in front of it; the render casts the reverse rays instead."""
    return _centroids_in_front(scene.patch_vertices, int(i), np.asarray(receivers, dtype=np.int64))


@njit(cache=True)
def _centroids_in_front(V, i, receivers):
    out = np.empty(len(receivers), dtype=np.bool_)
    for m in range(len(receivers)):
        out[m] = _plane_sign(V[i], V[receivers[m]], _ONES) > 0
    return out


def samples_in_front(scene, samples, i, receivers):
    """bool (len(receivers), K): sample point k of shooter i strictly in front of receiver j's
    plane (exact signs). Only those rays carry light from i to j."""
    V = scene.patch_vertices
    receivers = np.asarray(receivers, dtype=np.int64)
    K = samples.count
    tri = np.repeat(V[receivers], K, axis=0)
    pts = np.broadcast_to(V[i], (len(tri), 3, 3))
    w = np.tile(samples.weights, (len(receivers), 1))
    return (plane_signs(tri, pts, w) > 0).reshape(len(receivers), K)


def sample_weights(scene, samples, i, receivers):
    """(len(receivers), K): each ray's share of the light shooter i sends to receiver j: the
    point factor from sample point k of i (normal of i) to triangle j, where the sample is
    strictly in front of j's plane (:func:`samples_in_front`), else 0. Their weighted mean of
    clear rays estimates the kernel-weighted visible fraction (a plain mean weighs a sample
    near j like one far from it)."""
    receivers = np.asarray(receivers, dtype=np.int64)
    return pair_sample_weights(scene, samples, np.full(len(receivers), i), receivers)


def weight_points(scene, samples, patches=None):
    """(len(patches), K, 3): the float sample points of each patch (default: all) as
    :func:`pair_sample_weights` weighs them, each triangle's computed alone (so the same bits
    whichever patches are asked for together)."""
    V = scene.patch_vertices
    patches = range(scene.patches) if patches is None else patches
    points = [samples.points(V[j][None])[0] for j in patches]
    return np.stack(points) if points else np.zeros((0, samples.count, 3))


def pair_sample_weights(scene, samples, shooters, receivers, points=None):
    """:func:`sample_weights` of many (shooter, receiver) pairs in one call: row m is the weight row
    of the pair (shooters[m], receivers[m]), the same arithmetic row by row, so the same bits however
    the pairs are batched. For the reverse rays of a shooter's straddling receivers. ``points``:
    :func:`weight_points` of every patch, if the caller keeps them (else computed for these
    shooters)."""
    shooters = np.asarray(shooters, dtype=np.int64)
    receivers = np.asarray(receivers, dtype=np.int64)
    if len(shooters) == 0:
        return np.zeros((0, samples.count))
    if points is None:
        unique, which = np.unique(shooters, return_inverse=True)
        points, shooters = weight_points(scene, samples, unique), which.reshape(-1).astype(np.int64)
        normals = np.ascontiguousarray(scene.normals[unique], dtype=np.float64)
        return _sample_weights(scene.patch_vertices, normals, points, samples.weights, shooters,
                               receivers, unique)
    return _sample_weights(scene.patch_vertices, np.ascontiguousarray(scene.normals, dtype=np.float64), points,
                           samples.weights, shooters, receivers, np.arange(scene.patches))


@njit(cache=True)
def _weight_row(V, normals, points, weights, s, i, j, out, poly):
    """out[:]: for shooter i (its points and normal at index s), receiver j, the point factor of
    each sample strictly in front of j's plane, else 0."""
    for k in range(len(weights)):
        if _plane_sign(V[j], V[i], weights[k]) > 0:
            out[k] = _lambert_normal(points[s], k, normals, s, V[j], poly)


def _weights(V, normals, points, weights, shooters, receivers, patch, out):
    for m in prange(len(shooters)):
        _weight_row(V, normals, points, weights, shooters[m], patch[shooters[m]], receivers[m], out[m],
                    np.empty((4, 3)))


_weights_par, _weights_ser = _threads.twins(_weights)


def _sample_weights(V, normals, points, weights, shooters, receivers, patch):
    """Row m: the weight row of shooter ``patch[shooters[m]]`` (its points and normal at index
    shooters[m]) and receiver receivers[m]; rows on the thread pool when there are enough rays
    (each row its own, so the same bits on any number of threads)."""
    out = np.zeros((len(shooters), len(weights)))
    run = _weights_par if _threads.parallel(out.size) else _weights_ser
    run(V, normals, points, weights, shooters, receivers, patch, out)
    return out


class PairCache:
    """``A_j F_ji`` of a scene's pairs, each unordered pair computed once: the pair kernel gives
    the same bits for (i, j) and (j, i), so the column of shooter j reuses what the column of
    shooter i computed. Dense N x N float64 (NaN: not yet computed), so only for scenes of up to
    ``max_patches`` patches (73 MB at the room's 3032); larger scenes compute every column."""

    def __init__(self, scene, *, target=FAR_TARGET, max_patches=5000):
        self.target = target
        N = scene.patches
        self.values = np.full((N, N), np.nan) if N <= max_patches else None
        self.computed = 0           # pairs computed (the rest were reused)

    def pairs(self, scene, i, j, stats=None):
        """``A_j F_ji`` for shooter i and receivers j (array of indices)."""
        V = scene.patch_vertices
        if self.values is None:
            self.computed += len(j)
            return pair_factors(V[i][None], V[j], target=self.target, stats=stats)
        row = self.values[i, j]
        todo = np.isnan(row)
        if todo.any():
            row[todo] = pair_factors(V[i][None], V[j[todo]], target=self.target, stats=stats)
            self.computed += int(todo.sum())
            self.values[i, j] = row
            self.values[j, i] = row
        return row


def unoccluded_factors(scene, i, *, stats=None, cache=None, target=FAR_TARGET):
    """(N,) exact patch-to-patch ``F_ji`` from every receiver j to shooter patch i; 0 outside
    :func:`exchange_mask`. ``cache``, a :class:`PairCache`, reuses the pairs of earlier columns
    (the same bits) and then sets the far-pair target itself."""
    mask = exchange_mask(scene, i)
    out = np.zeros(scene.patches)
    j = np.flatnonzero(mask)
    if len(j):
        if cache is not None:
            out[j] = cache.pairs(scene, i, j, stats=stats) / scene.areas[j]
        else:
            out[j] = pair_factors(scene.patch_vertices[i][None], scene.patch_vertices[j], target=target,
                                  stats=stats) / scene.areas[j]
    return out


def form_factor_matrix(scene, visibility=None):
    """Dense unoccluded ``F[j, i] = F_ji`` (receiver rows, shooter columns), masked.

    ``visibility`` (N, N), optional, multiplies F elementwise (fraction of clear rays). Memory is
    N^2 floats: for small scenes and tests; the render loop builds columns with
    :func:`unoccluded_factors` and the board.
    """
    F = np.zeros((scene.patches, scene.patches))
    for i in range(scene.patches):
        F[:, i] = unoccluded_factors(scene, i)
    if visibility is not None:
        F *= visibility
    return F
