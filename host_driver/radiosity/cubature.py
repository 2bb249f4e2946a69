"""Cubatures of the point factor (:mod:`.point_factor`) over a patch, for the pairs the closed
form (:mod:`.closed_form`) serves badly: far pairs and grazing pairs (numba).

**Far pairs.** The edge-pair terms are of size L^2 ln D while their sum is of size L^4 / D^2, so
the closed form loses about (D / L)^2 digits to cancellation, and it costs about 9 us a pair.
Far pairs use a cubature of the exact point-to-triangle factor (:mod:`.point_factor`) over the smaller of the
two triangles instead (by reciprocity ``A_j F_ji = A_i F_ij``, either may be integrated),
wherever a derived bound shows it within ``FAR_TARGET`` (relative): the point factor is analytic
in the receiver point; its Taylor remainder of degree p over a ball of radius rho is at most
``M q^(p+1) / (1 - q)`` (Cauchy, along each line through the centroid c, q = rho / R) where M
bounds it on the complex ball of radius R = k D around c (D <= the distance from c to the
shooter). There, with s = |y - c| >= D for a shooter point y, each cosine's numerator is at most
s + k D and |(x - y).(x - y)| >= s^2 - 2 s k D - k^2 D^2, so the kernel is at most
``M(k) / (pi D^2)``, ``M(k) = (1 + k)^2 / (1 - 2k - k^2)^2`` (largest at s = D; 8.16 at k = 1/4),
per unit shooter area. A rule exact to degree p with positive weights errs by at most twice the
remainder, so ``|error of F_ji| <= (2/pi) A_i M(k) / D^2 q^(p+1) / (1 - q)``, q = rho / (k D),
the best over k in ``_FAR_K`` (k < sqrt(2) - 1; a larger ball pays for high degrees).
The rules: centroid (degree 1),
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
"""

import math

import numpy as np
from numba import njit

from .closed_form import CANCELLATION
from .point_factor import _lambert, _lambert_front, _lambert_terms

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
#: the far pairs' rules after the centroid, in the order tried: (degree, points, weights, the
#: method code counted in pair_factors' statistics)
_FAR_RULES = ((5, _RULE7, _RULE7_W, 3), (8, _RULE25, _RULE25_W, 4), (14, _RULE64, _RULE64_W, 5))


#: the radii k D of the complex balls the far bound tries (module doc; it needs 1 - 2k - k^2 > 0)
_FAR_K = (0.25, 0.3, 1.0 / 3.0, 0.38)


@njit(cache=True)
def _far_bound_at(area_i, D, rho, degree, k):
    """The bound of :func:`_far_bound` on the complex ball of radius k D; inf where rho reaches it."""
    q = rho / (k * D)
    if q >= 1.0:
        return np.inf
    M = (1 + k) ** 2 / (1 - 2 * k - k * k) ** 2
    return (2 / math.pi) * area_i * M / (D * D) * q ** (degree + 1) / (1 - q)


@njit(cache=True)
def _far_bound(area_i, D, rho, degree):
    """Derived bound on |error of F_ji| of a positive rule exact to ``degree`` (module doc): the
    best over the ball radii k D of ``_FAR_K``."""
    best = np.inf
    for k in _FAR_K:
        best = min(best, _far_bound_at(area_i, D, rho, degree, k))
    return best


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
def _far(Tt, Tr, target, tolerance, stats, P):
    """``A_r F_rt`` by a cubature over the receiver Tr of the point factor to Tt, with the first
    rule whose derived bound (module doc) is within ``target`` of the value or within the absolute
    ``tolerance`` (on ``A_r F_rt``); -1.0 if none is. Neither triangle may need clipping."""
    ntx, nty, ntz, At2 = _normal(Tt)
    nrx, nry, nrz, Ar2 = _normal(Tr)
    ctx, cty, ctz = _centroid(Tt)
    crx, cry, crz = _centroid(Tr)
    rho_t = _radius(Tt, ctx, cty, ctz)
    rho_r = _radius(Tr, crx, cry, crz)
    D = math.sqrt((crx - ctx) ** 2 + (cry - cty) ** 2 + (crz - ctz) ** 2) - rho_t   # <= dist(cr, Tt)
    if D <= 8 * rho_r:
        return -1.0             # nearer, the closed form keeps its digits and costs less than 64 points
    At = 0.5 * At2
    Ar = 0.5 * Ar2
    f1, mag = _lambert_terms(crx, cry, crz, nrx, nry, nrz, Tt, P)
    if not f1 > 0 or CANCELLATION * mag > target * f1:
        return -1.0             # edge-on: the point factor itself loses the target to rounding
    floor = tolerance / Ar      # the absolute tolerance, on the mean point factor f
    if _far_bound(At, D, rho_r, 1) <= max(target * f1, floor):
        stats[2] += 1
        return Ar * f1
    # a rule is computed only where the bound, against the centroid's estimate of the value, looks
    # met; it is accepted only where the bound holds against its own value
    for degree, rule, weights, method in _FAR_RULES:
        if _far_bound(At, D, rho_r, degree) <= max(0.9 * target * f1, floor):
            f = _cubature(Tt, Tr, nrx, nry, nrz, rule, weights, P)
            if f > 0 and _far_bound(At, D, rho_r, degree) <= max(target * f, floor):
                stats[method] += 1
                return Ar * f
    return -1.0


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
