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
floating-point expansions (Shewchuk 1997: two-sum, two-product by Dekker's split, grow with zero
elimination): every row entry is an exact sum of at most 12 floats, and the determinant the exact
sum of all triple products, each split into four floats, grown into one expansion whose largest
component gives the sign. (A shortcut first: a triangle in a plane x_c = const and a point whose
vertices all have that x_c are on the plane, exactly.) Expansion arithmetic is exact while
nothing overflows or underflows: :func:`check_exact_range` requires every coordinate to be 0 or within
2^-300 .. 2^300 in magnitude (products of three differences then stay within 2^-1074 .. 2^1000).

Both stages are compiled with numba (``cache=True``).
"""

import math

import numpy as np
from numba import njit

from .errors import ParameterError

__all__ = ["check_exact_range", "plane_signs", "plane_signs_of", "blocked_rays", "LOW", "HIGH"]

U = 2.0 ** -53
#: magnitudes of nonzero coordinates for which the exact stage is exact
LOW, HIGH = 2.0 ** -300, 2.0 ** 300
_SPLITTER = 134217729.0           # 2^27 + 1


def check_exact_range(vertices, what="scene"):
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


@njit(cache=True, inline="always")
def _grow(h, n, b):
    """h[:n] (nonoverlapping, increasing) + b, in place (Shewchuk's grow_expansion_zeroelim:
    the output index never passes the input index). Returns the new length (>= 1)."""
    m = 0
    q = b
    for i in range(n):
        q, hh = _two_sum(q, h[i])
        if hh != 0.0:
            h[m] = hh
            m += 1
    if q != 0.0 or m == 0:
        h[m] = q
        m += 1
    return m


@njit(cache=True, inline="always")
def _parts(E, w, b, c, out):
    """Floats out[:n] summing exactly to sum_k w_k (E_k[c] - b[c]); n <= 12."""
    n = 0
    for k in range(3):
        if w[k] != 0:
            hi, lo = _two_sum(E[k, c], -b[c])
            for d in (hi, lo):
                if d != 0.0:
                    p, e = _two_product(d, float(w[k]))
                    out[n] = p
                    n += 1
                    if e != 0.0:
                        out[n] = e
                        n += 1
    return n


_PERMS = np.array([[0, 1, 2, 1], [1, 2, 0, 1], [2, 0, 1, 1], [0, 2, 1, -1], [1, 0, 2, -1], [2, 1, 0, -1]])
#: a nonoverlapping expansion within 2^-1074 .. 2^1024 has fewer components than this
_CAPACITY = 2100


@njit(cache=True)
def _exact_sign(Ex, wx, Ey, wy, Ez, wz, b):
    """Sign of det[rows sum w (E - b)] for the three (E, w) rows, exactly: every row entry is an
    exact sum of floats, the determinant the exact sum of all triple products (each split into
    four floats by two-product), accumulated into one expansion."""
    parts = np.empty((3, 3, 12))
    count = np.empty((3, 3), dtype=np.int64)
    for c in range(3):
        count[0, c] = _parts(Ex, wx, b, c, parts[0, c])
        count[1, c] = _parts(Ey, wy, b, c, parts[1, c])
        count[2, c] = _parts(Ez, wz, b, c, parts[2, c])
    h = np.empty(_CAPACITY)
    h[0] = 0.0
    n = 1
    for r in range(6):
        i, j, k, sign = _PERMS[r, 0], _PERMS[r, 1], _PERMS[r, 2], float(_PERMS[r, 3])
        for a in range(count[0, i]):
            for bb in range(count[1, j]):
                p, e = _two_product(parts[0, i, a], parts[1, j, bb])
                for cc in range(count[2, k]):
                    z = parts[2, k, cc]
                    for v in (p, e):
                        if v != 0.0:
                            q1, q0 = _two_product(v, z)
                            n = _grow(h, n, sign * q1)
                            if q0 != 0.0:
                                n = _grow(h, n, sign * q0)
    top = h[n - 1]
    return 1 if top > 0 else (-1 if top < 0 else 0)


# ---------------------------------------------------------------------------- filter

@njit(cache=True, inline="always")
def _point(E, w):
    """Rounded point sum w E / sum w, as 3 scalars, and its error bound eta."""
    D = float(w[0] + w[1] + w[2])
    p0 = (w[0] * E[0, 0] + w[1] * E[1, 0] + w[2] * E[2, 0]) / D
    p1 = (w[0] * E[0, 1] + w[1] * E[1, 1] + w[2] * E[2, 1]) / D
    p2 = (w[0] * E[0, 2] + w[1] * E[1, 2] + w[2] * E[2, 2]) / D
    M = 0.0
    nonzero = 0
    for k in range(3):
        if w[k] != 0:
            nonzero += 1
            for c in range(3):
                M = max(M, abs(E[k, c]))
    eta = 0.0 if (nonzero == 1 and D == 1.0) else 5.0 * U * M
    return p0, p1, p2, eta


@njit(cache=True, inline="always")
def _filtered(x0, x1, x2, ex, y0, y1, y2, ey, z0, z1, z2):
    """Sign of det[x; y; z] if certified, else 2. Rows x, y carry end-point errors ex, ey."""
    c0 = y1 * z2 - y2 * z1
    c1 = y2 * z0 - y0 * z2
    c2 = y0 * z1 - y1 * z0
    det = x0 * c0 + x1 * c1 + x2 * c2
    ax0, ax1, ax2 = abs(x0), abs(x1), abs(x2)
    ay0, ay1, ay2 = abs(y0), abs(y1), abs(y2)
    az0, az1, az2 = abs(z0), abs(z1), abs(z2)
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


@njit(cache=True, inline="always")
def _rows_of(v):
    out = np.empty((3, 3))
    out[0] = v
    out[1] = v
    out[2] = v
    return out


@njit(cache=True)
def _on_axis_plane(T, E, w):
    """Exact zero without arithmetic: T lies in a plane x_c = const and so does every vertex E_k
    that the point depends on (the common case of axis-aligned walls)."""
    for c in range(3):
        v = T[0, c]
        if T[1, c] == v and T[2, c] == v:
            same = True
            for k in range(3):
                if w[k] != 0 and E[k, c] != v:
                    same = False
            if same:
                return True
    return False


@njit(cache=True)
def _plane_sign(T, E, w):
    """Sign of the rational point sum w E / sum w against the plane of triangle T (right-handed)."""
    p0, p1, p2, eta = _point(E, w)
    s = _filtered(p0 - T[0, 0], p1 - T[0, 1], p2 - T[0, 2], eta,
                  T[1, 0] - T[0, 0], T[1, 1] - T[0, 1], T[1, 2] - T[0, 2], 0.0,
                  T[2, 0] - T[0, 0], T[2, 1] - T[0, 1], T[2, 2] - T[0, 2])
    if s != 2:
        return s
    if _on_axis_plane(T, E, w):
        return 0
    return _exact_sign(E, w, _rows_of(T[1]), _UNIT, _rows_of(T[2]), _UNIT, T[0])


@njit(cache=True)
def _plane_signs(T, E, W):
    out = np.empty(len(T), dtype=np.int8)
    for m in range(len(T)):
        out[m] = _plane_sign(T[m], E[m], W[m])
    return out


@njit(cache=True)
def _plane_signs_of(V, tri, pts, W):
    out = np.empty(W.shape[:2], dtype=np.int8)
    for m in range(len(tri)):
        for k in range(W.shape[1]):
            out[m, k] = _plane_sign(V[tri[m]], V[pts[m]], W[m, k])
    return out


def plane_signs_of(vertices, triangle, points_of, weights):
    """:func:`plane_signs` by index, without copying triangles per point: the signs (M, k) int8 of
    the points of weights ``weights[m, j]`` (M, k, 3) on triangle ``points_of[m]`` against the
    plane of triangle ``triangle[m]``, both indices into ``vertices`` (P, 3, 3)."""
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    W = np.ascontiguousarray(weights, dtype=np.int64)
    return _plane_signs_of(V, np.ascontiguousarray(triangle, dtype=np.int64),
                           np.ascontiguousarray(points_of, dtype=np.int64), W)


def plane_signs(triangles, points_of, weights):
    """Exact signs (M,) int8 of rational points ``sum_k weights_k points_of_k / sum weights``
    (points_of (M,3,3) float, weights (M,3) int >= 0) against the planes of triangles (M,3,3):
    +1 in front (the side of (V1 - V0) x (V2 - V0)), 0 on, -1 behind."""
    T = np.ascontiguousarray(np.broadcast_to(np.asarray(triangles, dtype=np.float64), np.shape(points_of)))
    E = np.ascontiguousarray(np.asarray(points_of, dtype=np.float64))
    W = np.ascontiguousarray(np.broadcast_to(np.asarray(weights, dtype=np.int64), E.shape[:-1]))
    return _plane_signs(T.reshape(-1, 3, 3), E.reshape(-1, 3, 3), W.reshape(-1, 3)).reshape(E.shape[:-2])


@njit(cache=True)
def _edge_sign(P, eP, Pe, Pw, Q, eQ, Qe, Qw, a, b):
    """Sign of det[P - b; Q - b; a - b] (P, Q: rounded end points (3,), errors eP, eQ)."""
    s = _filtered(P[0] - b[0], P[1] - b[1], P[2] - b[2], eP, Q[0] - b[0], Q[1] - b[1], Q[2] - b[2], eQ,
                  a[0] - b[0], a[1] - b[1], a[2] - b[2])
    if s != 2:
        return s
    return _exact_sign(Pe, Pw, Qe, Qw, _rows_of(a), _UNIT, b)


@njit(cache=True)
def _blocked_rays(PE, PW, QE, QW, T, out, counters):
    """out[r, s] |= segment P_s -> Q_r blocked by any triangle of T; counters[0] += crossings."""
    S, R, N = len(PE), len(QE), len(T)
    Pp = np.empty((S, 3))
    eP = np.empty(S)
    Qp = np.empty((R, 3))
    eQ = np.empty(R)
    for s in range(S):
        Pp[s, 0], Pp[s, 1], Pp[s, 2], eP[s] = _point(PE[s], PW[s])
    for r in range(R):
        Qp[r, 0], Qp[r, 1], Qp[r, 2], eQ[r] = _point(QE[r], QW[r])
    sP = np.empty(S, dtype=np.int8)
    sQ = np.empty(R, dtype=np.int8)
    for t in range(N):
        V = T[t]
        anyP = False
        for s in range(S):
            sP[s] = _plane_sign(V, PE[s], PW[s])
            anyP = anyP or sP[s] != 0
        if not anyP:
            continue
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
