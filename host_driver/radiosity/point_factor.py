"""The point-to-triangle factor (compiled with numba), and the clipping of a triangle to the
half-space in front of a plane.

From a differential receiver at p with unit normal n to a whole shooter
triangle T (Lambert's contour integral; Baum, Rushmeier, Winget 1989)::

    F_{dA -> T} = 1/(2 pi) | sum_k beta_k n . (R_k x R_{k+1}) / |R_k x R_{k+1}| |,  R_k = V_k - p

evaluated on the part of T in front of the receiver's tangent plane.

"""

import math

import numpy as np
from numba import njit

__all__ = ["point_to_triangles", "triangle_to_points"]

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
