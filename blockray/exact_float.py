"""The occlusion predicate of :mod:`blockray.exact`, evaluated exactly on float64 inputs.

Floats are dyadic rationals, so every sign the predicate needs has one exact answer. The end
points of a segment are rational too: a sample point ``P = sum_k w_k E_k / sum_k w_k`` of float
vertices E with small integer weights (the shooter samples and centroids of
:class:`~blockray.samples.SampleScheme`, taken exactly, not rounded: so a sample point lies
exactly on its own patch's plane and the strict plane test needs no tolerance). Every sign is a
3 x 3 determinant whose rows are ``sum_k w_k (E_k - b)`` (= D (P - b), the same sign as P - b):

    plane side  det[P - V0; V1 - V0; V2 - V0]      edge side  det[P - b; Q - b; a - b]

**Filter** (Shewchuk's adaptive predicates, stage A): the determinant of the rounded rows
``x = fl(P) - b``, with ``|fl(P) - P| <= eta_P = 5 u max|E|`` (u = 2^-53: three products, two
sums and a division each round once), is certified when its magnitude exceeds

    10 u p0 + 1.01 (eta_x g_x + eta_y g_y + 2 eta_x eta_y sum|e|)

(p0 = sum of the six |products|, g_x / g_y = the same with row x / y replaced by ones: the first
term covers the rounding of the differences and of the evaluation, 8 u p0, the others the
rounding of the end points). **Exact stage**: otherwise the determinant is evaluated in
floating-point expansions (Shewchuk 1997: two-sum, two-product by Dekker's split, grow and
scale with zero elimination) and its sign is that of the largest component. Expansion arithmetic
is exact while nothing overflows or underflows: :func:`check_range` requires every coordinate to
be 0 or within 2^-300 .. 2^300 in magnitude (products of three differences then stay within
2^-1074 .. 2^1000).

Both stages are compiled with numba (``cache=True``).
"""

import math

import numpy as np
from numba import njit

from .errors import ParameterError

__all__ = ["check_range", "plane_signs", "blocked_rays", "orient_sign", "LOW", "HIGH"]

U = 2.0 ** -53
#: magnitudes of nonzero coordinates for which the exact stage is exact
LOW, HIGH = 2.0 ** -300, 2.0 ** 300
_SPLITTER = 134217729.0           # 2^27 + 1


def check_range(vertices, what="scene"):
    """Raise ParameterError if a coordinate is outside the range where the predicate is exact."""
    v = np.abs(np.asarray(vertices, dtype=np.float64))
    if not np.isfinite(v).all():
        raise ParameterError(f"{what}: a coordinate is not finite")
    nz = v[v > 0]
    if nz.size and (nz.min() < LOW or nz.max() > HIGH):
        raise ParameterError(f"{what}: coordinates must be 0 or between 2^-300 and 2^300 in magnitude "
                             f"for the exact predicate (found {nz.min():.3g} .. {nz.max():.3g})")


# ---------------------------------------------------------------------------- expansions

@njit(cache=True, inline="always")
def _two_sum(a, b):
    x = a + b
    bv = x - a
    av = x - bv
    return x, (a - av) + (b - bv)


@njit(cache=True, inline="always")
def _split(a):
    c = _SPLITTER * a
    big = c - a
    hi = c - big
    return hi, a - hi


@njit(cache=True, inline="always")
def _two_product(a, b):
    x = a * b
    ahi, alo = _split(a)
    bhi, blo = _split(b)
    err = x - ahi * bhi
    err -= alo * bhi
    err -= ahi * blo
    return x, alo * blo - err


@njit(cache=True)
def _grow(e, n, b):
    """e (n components, nonoverlapping, increasing) + b -> new expansion (zero-eliminated)."""
    h = np.empty(n + 1)
    m = 0
    q = b
    for i in range(n):
        q, hh = _two_sum(q, e[i])
        if hh != 0.0:
            h[m] = hh
            m += 1
    if q != 0.0 or m == 0:
        h[m] = q
        m += 1
    return h[:m]


@njit(cache=True)
def _add(e, f):
    h = e
    for i in range(len(f)):
        h = _grow(h, len(h), f[i])
    return h


@njit(cache=True)
def _scale(e, b):
    """e * b (Shewchuk's scale_expansion_zeroelim)."""
    h = np.empty(2 * len(e))
    m = 0
    q, hh = _two_product(e[0], b)
    if hh != 0.0:
        h[m] = hh
        m += 1
    for i in range(1, len(e)):
        p1, p0 = _two_product(e[i], b)
        s, hh = _two_sum(q, p0)
        if hh != 0.0:
            h[m] = hh
            m += 1
        q = p1 + s
        hh = s - (q - p1)
        if hh != 0.0:
            h[m] = hh
            m += 1
    if q != 0.0 or m == 0:
        h[m] = q
        m += 1
    return h[:m]


@njit(cache=True)
def _mul(e, f):
    h = _scale(e, f[0])
    for i in range(1, len(f)):
        h = _add(h, _scale(e, f[i]))
    return h


@njit(cache=True)
def _neg(e):
    return -e


@njit(cache=True)
def _row(E, w, b, c):
    """Exact component c of sum_k w_k (E_k - b) as an expansion."""
    h = np.zeros(1)
    for k in range(3):
        if w[k] != 0:
            d1, d0 = _two_sum(E[k, c], -b[c])
            h = _add(h, _scale(np.array([d0, d1]), float(w[k])))
    return h


@njit(cache=True)
def _exact_sign(Ex, wx, Ey, wy, Ez, wz, b):
    """Sign of det[rows sum w (E - b)] for the three (E, w) rows, exactly."""
    x0, x1, x2 = _row(Ex, wx, b, 0), _row(Ex, wx, b, 1), _row(Ex, wx, b, 2)
    y0, y1, y2 = _row(Ey, wy, b, 0), _row(Ey, wy, b, 1), _row(Ey, wy, b, 2)
    z0, z1, z2 = _row(Ez, wz, b, 0), _row(Ez, wz, b, 1), _row(Ez, wz, b, 2)
    c0 = _add(_mul(y1, z2), _neg(_mul(y2, z1)))
    c1 = _add(_mul(y2, z0), _neg(_mul(y0, z2)))
    c2 = _add(_mul(y0, z1), _neg(_mul(y1, z0)))
    det = _add(_add(_mul(x0, c0), _mul(x1, c1)), _mul(x2, c2))
    top = det[len(det) - 1]
    return 1 if top > 0 else (-1 if top < 0 else 0)


# ---------------------------------------------------------------------------- filter

@njit(cache=True, inline="always")
def _point(E, w):
    """Rounded point sum w E / sum w (3,) and its error bound eta."""
    D = float(w[0] + w[1] + w[2])
    p = np.empty(3)
    M = 0.0
    for c in range(3):
        p[c] = (w[0] * E[0, c] + w[1] * E[1, c] + w[2] * E[2, c]) / D
        for k in range(3):
            if w[k] != 0:
                M = max(M, abs(E[k, c]))
    exact = (w[0] == 0) + (w[1] == 0) + (w[2] == 0) == 2 and D == 1.0
    return p, 0.0 if exact else 5.0 * U * M


@njit(cache=True)
def _filtered(x, ex, y, ey, z):
    """Sign of det[x; y; z] if certified, else 2. Rows x, y carry end-point errors ex, ey."""
    c0 = y[1] * z[2] - y[2] * z[1]
    c1 = y[2] * z[0] - y[0] * z[2]
    c2 = y[0] * z[1] - y[1] * z[0]
    det = x[0] * c0 + x[1] * c1 + x[2] * c2
    ax0, ax1, ax2 = abs(x[0]), abs(x[1]), abs(x[2])
    ay0, ay1, ay2 = abs(y[0]), abs(y[1]), abs(y[2])
    az0, az1, az2 = abs(z[0]), abs(z[1]), abs(z[2])
    m0 = ay1 * az2 + ay2 * az1
    m1 = ay2 * az0 + ay0 * az2
    m2 = ay0 * az1 + ay1 * az0
    p0 = ax0 * m0 + ax1 * m1 + ax2 * m2
    gy = ax0 * (az1 + az2) + ax1 * (az0 + az2) + ax2 * (az0 + az1)
    bound = 10.0 * U * p0 + 1.01 * (ex * (m0 + m1 + m2) + ey * gy + 2.0 * ex * ey * (az0 + az1 + az2))
    if abs(det) > bound and bound > 1e-280:
        return 1 if det > 0 else -1
    return 2


_UNIT = np.array([1, 0, 0], dtype=np.int64)


@njit(cache=True)
def _plane_sign(T, E, w):
    """Sign of the rational point sum w E / sum w against the plane of triangle T (right-handed)."""
    p, eta = _point(E, w)
    x = p - T[0]
    y = T[1] - T[0]
    z = T[2] - T[0]
    s = _filtered(x, eta, y, 0.0, z)
    if s != 2:
        return s
    return _exact_sign(E, w, _rows_of(T[1]), _UNIT, _rows_of(T[2]), _UNIT, T[0])


@njit(cache=True, inline="always")
def _rows_of(v):
    out = np.empty((3, 3))
    out[0] = v
    out[1] = v
    out[2] = v
    return out


@njit(cache=True)
def _plane_signs(T, E, W):
    out = np.empty(len(T), dtype=np.int8)
    for m in range(len(T)):
        out[m] = _plane_sign(T[m], E[m], W[m])
    return out


def plane_signs(triangles, points_of, weights):
    """Exact signs (M,) int8 of rational points ``sum_k weights_k points_of_k / sum weights``
    (points_of (M,3,3) float, weights (M,3) int >= 0) against the planes of triangles (M,3,3):
    +1 in front (the side of (V1 - V0) x (V2 - V0)), 0 on, -1 behind."""
    T = np.ascontiguousarray(np.broadcast_to(np.asarray(triangles, dtype=np.float64), np.shape(points_of)))
    E = np.ascontiguousarray(np.asarray(points_of, dtype=np.float64))
    W = np.ascontiguousarray(np.broadcast_to(np.asarray(weights, dtype=np.int64), E.shape[:-1]))
    return _plane_signs(T.reshape(-1, 3, 3), E.reshape(-1, 3, 3), W.reshape(-1, 3)).reshape(E.shape[:-2])


@njit(cache=True)
def _edge_sign(Pp, eP, Pe, Pw, Qp, eQ, Qe, Qw, a, b):
    """Sign of det[P - b; Q - b; a - b]."""
    s = _filtered(Pp - b, eP, Qp - b, eQ, a - b)
    if s != 2:
        return s
    return _exact_sign(Pe, Pw, Qe, Qw, _rows_of(a), _UNIT, b)


@njit(cache=True)
def _blocked_rays(PE, PW, QE, QW, T, out, counters):
    """out[r, s] |= segment P_s -> Q_r blocked by any triangle of T; counters: crossings, exact."""
    S, R, N = len(PE), len(QE), len(T)
    Pp = np.empty((S, 3))
    eP = np.empty(S)
    Qp = np.empty((R, 3))
    eQ = np.empty(R)
    for s in range(S):
        Pp[s], eP[s] = _point(PE[s], PW[s])
    for r in range(R):
        Qp[r], eQ[r] = _point(QE[r], QW[r])
    sP = np.empty(S, dtype=np.int8)
    sQ = np.empty(R, dtype=np.int8)
    for t in range(N):
        V = T[t]
        for s in range(S):
            sP[s] = _plane_sign(V, PE[s], PW[s])
        for r in range(R):
            sQ[r] = _plane_sign(V, QE[r], QW[r])
        for r in range(R):
            if sQ[r] == 0:
                continue
            for s in range(S):
                if out[r, s] or sP[s] * sQ[r] >= 0:
                    continue
                counters[0] += 1
                pos = neg = False
                for k in range(3):
                    e = _edge_sign(Pp[s], eP[s], PE[s], PW[s], Qp[r], eQ[r], QE[r], QW[r],
                                   V[(k + 1) % 3], V[k])
                    pos = pos or e > 0
                    neg = neg or e < 0
                    if pos and neg:
                        break
                if not (pos and neg):
                    out[r, s] = True


def blocked_rays(P_of, P_weights, Q_of, Q_weights, triangles, counters=None):
    """bool (R, S): is the segment from P_s to Q_r blocked by any of ``triangles`` (T,3,3)?

    End points are rational: ``P_s = sum_k P_weights[s,k] P_of[s,k] / sum_k P_weights[s,k]``
    (P_of (S,3,3) float, P_weights (S,3) int >= 0), Q likewise. The predicate is
    :mod:`blockray.exact`'s (strict plane test, closed edge test), evaluated exactly.
    ``counters`` (int64 (1,)) accumulates the plane crossings tested.
    """
    PE = np.ascontiguousarray(np.asarray(P_of, dtype=np.float64).reshape(-1, 3, 3))
    QE = np.ascontiguousarray(np.asarray(Q_of, dtype=np.float64).reshape(-1, 3, 3))
    PW = np.ascontiguousarray(np.broadcast_to(np.asarray(P_weights, dtype=np.int64), (len(PE), 3)))
    QW = np.ascontiguousarray(np.broadcast_to(np.asarray(Q_weights, dtype=np.int64), (len(QE), 3)))
    T = np.ascontiguousarray(np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3))
    out = np.zeros((len(QE), len(PE)), dtype=np.bool_)
    c = np.zeros(1, dtype=np.int64) if counters is None else counters
    if len(PE) and len(QE) and len(T):
        _blocked_rays(PE, PW, QE, QW, T, out, c)
    return out


def orient_sign(a, b, c, d):
    """Exact sign of orient3d(a, b, c, d) = det[a - d; b - d; c - d] for float points (3,)."""
    rows = [np.asarray(x, dtype=np.float64) for x in (a, b, c, d)]
    return int(_exact_sign(_rows_of(rows[0]), _UNIT, _rows_of(rows[1]), _UNIT, _rows_of(rows[2]), _UNIT, rows[3]))
