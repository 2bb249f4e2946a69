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

The result is ``A_j F_ji``, symmetric in (i, j) up to rounding: reciprocity holds by
construction. :func:`unoccluded_factors` divides by the receiver's area.

**Far pairs.** The edge-pair terms are of size L^2 ln D while their sum is of size L^4 / D^2, so
the closed form loses about (D / L)^2 digits to cancellation. Far pairs use a cubature over the
receiver of the exact point-to-triangle factor (below) instead, wherever a derived bound shows
it within ``FAR_TARGET`` (relative): the point factor is analytic in the receiver point; its
Taylor remainder of degree p over a ball of radius rho is at most ``M q^(p+1) / (1 - q)``
(Cauchy, along each line through the centroid, q = rho / R) where M bounds the kernel on the
complex ball of radius R = D / 4 around the receiver's centroid (D = distance to the shooter):
``M <= 8.17 / D^2`` per unit shooter area. A rule exact to degree p with positive weights errs by
at most twice that, so ``|error of F_ji| <= (2/pi) A_i 8.17 / D^2 q^(p+1) / (1 - q)``. The
rules: centroid (degree 1), Radon's 7 points (degree 5), 8 x 8 collapsed Gauss (degree 14), the
first that meets the bound. The bound is applied only where neither
patch needs clipping (otherwise the integrand is not analytic).

**The point factor.** From a differential receiver at p with unit normal n to a whole shooter
triangle T (Lambert's contour integral; Baum, Rushmeier, Winget 1989)::

    F_{dA -> T} = 1/(2 pi) | sum_k beta_k n . (R_k x R_{k+1}) / |R_k x R_{k+1}| |,  R_k = V_k - p

evaluated on the part of T in front of the receiver's tangent plane.
"""

import math

import numpy as np
from numba import njit

from ..exact_float import plane_signs

__all__ = ["point_to_triangles", "triangle_to_points", "exchange_mask", "pair_factors",
           "unoccluded_factors", "form_factor_matrix", "FAR_TARGET", "METHODS"]

#: relative error bound a far-pair cubature must meet to replace the closed form
FAR_TARGET = 1e-9
#: method codes in the statistics of :func:`pair_factors`
METHODS = ("zero", "closed form", "centroid", "7-point", "64-point")


# ---------------------------------------------------------------------------- Clausen, Im Li2

def _clausen_coefficients(terms=40):
    """|B_2n| / (2n (2n+1)!) for n = 1..terms (exact Bernoulli numbers, then rounded)."""
    from fractions import Fraction
    B = [Fraction(1)]
    for m in range(1, 2 * terms + 1):
        B.append(-sum(math.comb(m + 1, k) * B[k] for k in range(m)) / (m + 1))
    return np.array([float(abs(B[2 * n]) / (2 * n * math.factorial(2 * n + 1)))
                     for n in range(1, terms + 1)])


_CL2 = _clausen_coefficients()


@njit(cache=True)
def _cl2(theta):
    """Clausen's Cl2(theta) = -int_0^theta ln|2 sin(x/2)| dx, to ~1e-16 absolute."""
    t = theta - 2 * math.pi * math.floor(theta / (2 * math.pi) + 0.5)     # in [-pi, pi]
    if t == 0.0:
        return 0.0
    sign = 1.0
    if t < 0:
        sign, t = -1.0, -t
    t2 = t * t
    power = t * t2
    total = t - t * math.log(t)
    for c in _CL2:                    # |terms| fall at least as fast as 4^-n (t <= pi)
        term = c * power
        total += term
        if term < 1e-18 * abs(total) + 1e-300:
            break
        power *= t2
    return sign * total


@njit(cache=True)
def _im_li2(m, a):
    """Im Li2(m e^{ia}) for m >= 0, 0 < a < pi (Lewin's identity in Clausen functions)."""
    if m == 0.0:
        return 0.0
    omega = math.atan2(m * math.sin(a), 1.0 - m * math.cos(a))
    return omega * math.log(m) + 0.5 * (_cl2(2 * a) + _cl2(2 * omega) - _cl2(2 * omega + 2 * a))


# ---------------------------------------------------------------------------- edge pairs

@njit(cache=True)
def _xlogx2(x2, coeff):
    """coeff * ln(x2), 0 when coeff is 0 (the 0 ln 0 limits of touching edges)."""
    if coeff == 0.0 or x2 == 0.0:
        return 0.0
    return coeff * math.log(x2)


@njit(cache=True)
def _f_skew(s, t, c, S, a, d):
    R2 = s * s + t * t - 2 * s * t * c + d * d
    if R2 < 0.0:
        R2 = 0.0
    val = _xlogx2(R2, 0.5 * c * (s * s + t * t) - s * t)
    Ws = math.sqrt(s * s * S * S + d * d)
    Wt = math.sqrt(t * t * S * S + d * d)
    if s != 0.0:
        val += s * Ws * math.atan2(Ws, t - s * c)
    if t != 0.0:
        val += t * Wt * math.atan2(Wt, s - t * c)
    val += s * t
    if d > 0.0:
        k2 = (d / S) * (d / S)
        rs = math.sqrt(s * s + k2)
        rt = math.sqrt(t * t + k2)
        w = s + rs if s >= 0 else k2 / (rs - s)          # s + sqrt(s^2 + k2) without cancellation
        p = t + rt if t >= 0 else k2 / (rt - t)
        w2 = rs - s if s <= 0 else k2 / (rs + s)         # w - 2 s
        val += 0.5 * d * d / S * (_im_li2(w / p, a) + _im_li2(p / w, a) - 2 * _im_li2(w2 / p, math.pi - a))
    return val


@njit(cache=True)
def _f_parallel(s, t, d):
    """Antiderivative of -ln((s - t)^2 + d^2) - 2 for parallel lines (s, t along the same unit)."""
    x = s - t
    r2 = x * x + d * d
    val = _xlogx2(r2, 0.5 * (x * x - d * d))
    if d > 0.0:
        val -= 2 * x * d * math.acos(x / math.sqrt(r2))
    return val + s * t


@njit(cache=True)
def _edge_pair(a0, a1, b0, b1):
    """(u . v) * (minus the corner sum of f) for edges a0->a1, b0->b1: the pair's share of
    sum (u.v) int int ln r^2, up to the dropped constant."""
    u = a1 - a0
    v = b1 - b0
    La = math.sqrt(u @ u)
    Lb = math.sqrt(v @ v)
    if La == 0.0 or Lb == 0.0:
        return 0.0
    u = u / La
    v = v / Lb
    c = u @ v
    cr = np.cross(u, v)
    S = math.sqrt(cr @ cr)
    w0 = a0 - b0
    if S < 1e-9:                                         # parallel (to rounding): both along u
        t0 = (b0 - a0) @ u
        t1 = (b1 - a0) @ u
        perp = w0 + t0 * u
        d = math.sqrt(perp @ perp)
        return -(_f_parallel(La, t1, d) - _f_parallel(0.0, t1, d)
                 - _f_parallel(La, t0, d) + _f_parallel(0.0, t0, d))
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    a = math.atan2(S, c)
    uw, vw = u @ w0, v @ w0
    det = 1.0 - c * c
    det = S * S if det < S * S else det
    sc = (c * vw - uw) / det                              # closest point on line a: a0 + sc u
    tc = (vw - c * uw) / det                              # on line b: b0 + tc v
    d = abs(w0 @ cr) / S
    s0, s1 = -sc, La - sc
    t0, t1 = -tc, Lb - tc
    return -c * (_f_skew(s1, t1, c, S, a, d) - _f_skew(s0, t1, c, S, a, d)
                 - _f_skew(s1, t0, c, S, a, d) + _f_skew(s0, t0, c, S, a, d))


@njit(cache=True)
def _contour(P, nP, Q, nQ):
    """A_P F_PQ (= A_Q F_QP) for convex planar polygons P (nP vertices) and Q, both clipped."""
    total = 0.0
    for p in range(nP):
        for q in range(nQ):
            total += _edge_pair(P[p], P[(p + 1) % nP], Q[q], Q[(q + 1) % nQ])
    return abs(total) / (4 * math.pi)


@njit(cache=True)
def _clip(T, point, normal, out):
    """Sutherland-Hodgman: the part of triangle T with normal . (x - point) >= 0 -> out (<= 4)."""
    h = np.empty(3)
    pos = False
    for k in range(3):
        h[k] = normal @ (T[k] - point)
        pos = pos or h[k] > 0
    if not pos:
        return 0
    n = 0
    for k in range(3):
        k1 = (k + 1) % 3
        if h[k] >= 0:
            out[n] = T[k]
            n += 1
        if (h[k] > 0 and h[k1] < 0) or (h[k] < 0 and h[k1] > 0):
            out[n] = T[k] + (h[k] / (h[k] - h[k1])) * (T[k1] - T[k])
            n += 1
    return n


@njit(cache=True)
def _needs_clip(T, point, normal):
    neg = False
    for k in range(3):
        neg = neg or normal @ (T[k] - point) < 0
    return neg


# ---------------------------------------------------------------------------- point factor

@njit(cache=True)
def _lambert(p, n, T):
    """F_{dA -> T} from point p, unit normal n, to triangle T (3, 3); 0 on T's plane."""
    m = np.cross(T[1] - T[0], T[2] - T[0])
    mm = math.sqrt(m @ m)
    if mm == 0.0 or (n @ n) == 0.0:
        return 0.0
    size = 0.0
    for k in range(3):
        for c in range(3):
            size = max(size, abs(T[k, c] - p[c]))
    if abs(m @ (T[0] - p)) / mm <= 1e-12 * size:
        return 0.0
    poly = np.empty((4, 3))
    k = _clip(T, p, n, poly)
    if k < 2:
        return 0.0
    total = 0.0
    for e in range(k):
        a = poly[e] - p
        b = poly[(e + 1) % k] - p
        cr = np.cross(a, b)
        cn = math.sqrt(cr @ cr)
        if cn > 0.0:
            total += math.atan2(cn, a @ b) * (cr @ n) / cn
    return abs(total) / (2 * math.pi)


@njit(cache=True)
def _lambert_many(points, normals, tris):
    out = np.empty(len(points))
    for m in range(len(points)):
        nn = normals[m]
        norm = math.sqrt(nn @ nn)
        out[m] = 0.0 if norm == 0.0 else _lambert(points[m], nn / norm, tris[m])
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


_RULE64, _RULE64_W = _collapsed_gauss(8)


@njit(cache=True)
def _far_bound(area_i, D, rho, degree):
    """Derived bound on |error of F_ji| of a positive rule exact to ``degree`` (module doc)."""
    q = 4.0 * rho / D
    if q >= 0.5:
        return np.inf
    return (2 / math.pi) * area_i * 8.17 / (D * D) * q ** (degree + 1) / (1 - q)


@njit(cache=True)
def _pair(Ti, Tj, target, stats):
    """A_j F_ji for shooter Ti, receiver Tj; stats[method] += 1."""
    ni = np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0])
    nj = np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0])
    Ai2 = math.sqrt(ni @ ni)
    Aj2 = math.sqrt(nj @ nj)
    if Ai2 == 0.0 or Aj2 == 0.0:
        stats[0] += 1
        return 0.0
    ni = ni / Ai2
    nj = nj / Aj2
    ci = (Ti[0] + Ti[1] + Ti[2]) / 3
    cj = (Tj[0] + Tj[1] + Tj[2]) / 3
    if not _needs_clip(Tj, Ti[0], ni) and not _needs_clip(Ti, Tj[0], nj):
        rho_i = rho_j = 0.0
        for k in range(3):
            rho_i = max(rho_i, math.sqrt((Ti[k] - ci) @ (Ti[k] - ci)))
            rho_j = max(rho_j, math.sqrt((Tj[k] - cj) @ (Tj[k] - cj)))
        D = math.sqrt((cj - ci) @ (cj - ci)) - rho_i          # <= distance from cj to Ti
        if D > 8 * rho_j:
            Ai = 0.5 * Ai2
            Aj = 0.5 * Aj2
            f1 = _lambert(cj, nj, Ti)
            if f1 > 0 and _far_bound(Ai, D, rho_j, 1) <= target * f1:
                stats[2] += 1
                return Aj * f1
            f7 = 0.0
            for r in range(7):
                x = _RULE7[r, 0] * Tj[0] + _RULE7[r, 1] * Tj[1] + _RULE7[r, 2] * Tj[2]
                f7 += _RULE7_W[r] * _lambert(x, nj, Ti)
            if f7 > 0 and _far_bound(Ai, D, rho_j, 5) <= target * f7:
                stats[3] += 1
                return Aj * f7
            f64 = 0.0
            for r in range(64):
                x = _RULE64[r, 0] * Tj[0] + _RULE64[r, 1] * Tj[1] + _RULE64[r, 2] * Tj[2]
                f64 += _RULE64_W[r] * _lambert(x, nj, Ti)
            if f64 > 0 and _far_bound(Ai, D, rho_j, 14) <= target * f64:
                stats[4] += 1
                return Aj * f64
    P = np.empty((4, 3))
    Q = np.empty((4, 3))
    nP = _clip(Tj, Ti[0], ni, P)                         # receiver part in front of the shooter
    nQ = _clip(Ti, Tj[0], nj, Q)                         # shooter part in front of the receiver
    if nP < 3 or nQ < 3:
        stats[0] += 1
        return 0.0
    stats[1] += 1
    return _contour(P, nP, Q, nQ)


@njit(cache=True)
def _pairs(shooters, receivers, target, stats):
    out = np.empty(len(shooters))
    for m in range(len(shooters)):
        out[m] = _pair(shooters[m], receivers[m], target, stats)
    return out


def pair_factors(shooters, receivers, *, target=FAR_TARGET, stats=None):
    """``A_j F_ji`` for shooter triangles i (M,3,3) and receiver triangles j (M,3,3) -> (M,).

    Symmetric in (i, j) (reciprocity) up to rounding and the far-pair bound. ``stats``, an int64
    array of len(METHODS), counts the pairs per method. Geometry only: which side faces which
    is :func:`exchange_mask`'s business; a pair where one lies wholly behind the other's plane
    gets 0.
    """
    S = np.ascontiguousarray(np.asarray(shooters, dtype=np.float64).reshape(-1, 3, 3))
    R = np.ascontiguousarray(np.asarray(receivers, dtype=np.float64).reshape(-1, 3, 3))
    S, R = np.broadcast_arrays(S, R)
    counts = np.zeros(len(METHODS), dtype=np.int64) if stats is None else stats
    return _pairs(np.ascontiguousarray(S), np.ascontiguousarray(R), float(target), counts)


def exchange_mask(scene, i):
    """bool (N,): receivers j that can exchange light with shooter i, so rays only where they count.

    j qualifies when all of these hold, each decided exactly on the float scene
    (:func:`blockray.exact_float.plane_signs`; no tolerance, so tiny patches beside huge ones
    are treated like any others):

    - j != i, j has non-zero area and a reflectance that is not all zero;
    - j's centroid (its ray end point) is strictly in front of i's plane: i emits from its front;
    - some vertex of i is strictly in front of j's plane: otherwise the factor is 0 anyway.
    """
    V = scene.patch_vertices
    N = scene.patches
    centroid = np.broadcast_to(np.ones(3, dtype=np.int64), (N, 3))
    in_front_of_i = plane_signs(np.broadcast_to(V[i], (N, 3, 3)), V, centroid) > 0
    i_in_front_of_j = np.zeros(N, dtype=bool)
    for k in range(3):
        corner = np.zeros(3, dtype=np.int64)
        corner[k] = 1
        i_in_front_of_j |= plane_signs(V, np.broadcast_to(V[i], (N, 3, 3)),
                                       np.broadcast_to(corner, (N, 3))) > 0
    mask = in_front_of_i & i_in_front_of_j & (scene.reflectance > 0).any(axis=1) & (scene.areas > 0)
    mask[i] = False
    return mask


def unoccluded_factors(scene, i, *, stats=None):
    """(N,) exact patch-to-patch ``F_ji`` from every receiver j to shooter patch i; 0 outside
    :func:`exchange_mask`."""
    mask = exchange_mask(scene, i)
    out = np.zeros(scene.patches)
    j = np.flatnonzero(mask)
    if len(j):
        V = scene.patch_vertices
        out[j] = pair_factors(V[i][None], V[j], stats=stats) / scene.areas[j]
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
