"""The closed form of the patch-to-patch factor: the double contour integral's edge pairs, with
a derived error bound each, and their quadrature where the bound is too loose (numba).

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
"""

import math

import numpy as np
from numba import njit

from .special import CL2_ERROR, _im_li2, _im_li2_inverse_pair

__all__ = ["CANCELLATION", "EDGE_TARGET"]

#: the closed form is recomputed by the subdivided cubature where this times the sum of the
#: absolute values of its corner terms exceeds the target times its value (about 64 rounding
#: units: the estimated relative error of the sum; docs/formfactors.md "Grazing pairs")
CANCELLATION = 64 * 2.0 ** -53
#: the unit roundoff of float64
_U = 2.0 ** -53
#: relative error the contour sum's edge pairs are held to at ``target=0`` (else a tenth of the
#: target): an edge pair whose closed form's derived error bound exceeds its share of this times
#: the value is integrated numerically
EDGE_TARGET = 1e-12


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
