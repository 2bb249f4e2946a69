"""Oracles for the form factors that share no code with blockray: closed forms (prior-art.md D.2,
Howell's catalogue), the double contour integral in mpmath, the clipping of a polygon to a plane,
and the random pairs they are checked on (imported as ``oracles``; tests/test_formfactor.py,
test_formfactor_degenerate.py, test_solver.py, benchmarks/bench_formfactor.py)."""

import math

import numpy as np


# ---------------------------------------------------------------------------- closed forms (D.2)

def parallel_closed_form(a, b, c):
    """Identical, parallel, directly opposed rectangles a x b at distance c (Howell C-11)."""
    X, Y = a / c, b / c
    return 2 / (math.pi * X * Y) * (
        0.5 * math.log((1 + X * X) * (1 + Y * Y) / (1 + X * X + Y * Y))
        + X * math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))
        + Y * math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
        - X * math.atan(X) - Y * math.atan(Y))


def perpendicular_closed_form(w, h, l):
    """Base w x l to the perpendicular h x l sharing the edge of length l (Howell C-14)."""
    W, H = w / l, h / l
    S = W * W + H * H
    log = (math.log((1 + W * W) * (1 + H * H) / (1 + S))
           + W * W * math.log(W * W * (1 + S) / ((1 + W * W) * S))
           + H * H * math.log(H * H * (1 + S) / ((1 + H * H) * S)))
    return 1 / (math.pi * W) * (W * math.atan(1 / W) + H * math.atan(1 / H)
                                 - math.sqrt(S) * math.atan(1 / math.sqrt(S)) + 0.25 * log)


def corner_closed_form(a, b, c):
    """Differential element parallel to an a x b rectangle at height c, normal through a corner."""
    A, B = a / c, b / c
    return 1 / (2 * math.pi) * (A / math.sqrt(1 + A * A) * math.atan(B / math.sqrt(1 + A * A))
                                + B / math.sqrt(1 + B * B) * math.atan(A / math.sqrt(1 + B * B)))


def parallel_offset_closed_form(x, y, xi, eta, z):
    """Parallel rectangles [x0,x1]x[y0,y1] at height 0 and [xi0,xi1]x[eta0,eta1] at height z:
    A_1 F_12 by the corner sum (Howell C-12, general position)."""
    def G(u, v):
        return (u * math.sqrt(v * v + z * z) * math.atan2(u, math.sqrt(v * v + z * z))
                + v * math.sqrt(u * u + z * z) * math.atan2(v, math.sqrt(u * u + z * z))
                - z * z / 2 * math.log(u * u + v * v + z * z)) / (2 * math.pi)
    return sum((-1) ** (i + j + k + l) * G(x[i] - xi[k], y[j] - eta[l])
               for i in range(2) for j in range(2) for k in range(2) for l in range(2))


# ---------------------------------------------------------------------------- contour integral, random pairs

def _inner_oracle(p, b0, v, L, mp):
    """int_0^L ln |p - b0 - t v|^2 dt for unit v (elementary, in mpmath)."""
    w = [p[i] - b0[i] for i in range(3)]
    t0 = sum(w[i] * v[i] for i in range(3))
    h2 = max(sum(x * x for x in w) - t0 * t0, mp.mpf(0))
    h = mp.sqrt(h2)

    def prim(x):
        if h == 0:
            return 0 if x == 0 else x * mp.log(x * x) - 2 * x
        return x * mp.log(x * x + h2) - 2 * x + 2 * h * mp.atan(x / h)
    return prim(L - t0) - prim(-t0)


def contour_oracle(Tj, Ti, dps=20):
    """A_j F_ji by the double contour integral: inner integral in closed form, outer by mpmath's
    adaptive tanh-sinh quadrature (independent of the dilogarithm closed form). Tj, Ti: convex
    planar polygons (k, 3), each wholly in front of the other's plane."""
    import mpmath as mp
    mp.mp.dps = dps
    total = mp.mpf(0)
    for p in range(len(Tj)):
        a0 = [mp.mpf(float(x)) for x in Tj[p]]
        a1 = [mp.mpf(float(x)) for x in Tj[(p + 1) % len(Tj)]]
        La = mp.sqrt(sum((a1[i] - a0[i]) ** 2 for i in range(3)))
        if La == 0:                   # a repeated vertex (clipping at a vertex): no edge
            continue
        u = [(a1[i] - a0[i]) / La for i in range(3)]
        for q in range(len(Ti)):
            b0 = [mp.mpf(float(x)) for x in Ti[q]]
            b1 = [mp.mpf(float(x)) for x in Ti[(q + 1) % len(Ti)]]
            Lb = mp.sqrt(sum((b1[i] - b0[i]) ** 2 for i in range(3)))
            if Lb == 0:
                continue
            v = [(b1[i] - b0[i]) / Lb for i in range(3)]
            uv = sum(u[i] * v[i] for i in range(3))
            if uv == 0:
                continue
            f = lambda s: _inner_oracle([a0[i] + s * u[i] for i in range(3)], b0, v, Lb, mp)
            # split where the inner integrand's singular behaviour moves (projections of b's ends)
            cuts = sorted({mp.mpf(0), La, *[min(max(sum((e[i] - a0[i]) * u[i] for i in range(3)), 0), La)
                                            for e in (b0, b1)]})
            total += uv * mp.quad(f, cuts)
    return float(abs(total) / (4 * mp.pi))


def clip_front(T, S):
    """The part of polygon T on the front side of triangle S's plane (numpy, independent of the
    kernel's clipping), as a (k, 3) polygon; for the oracle of clipped pairs."""
    n = np.cross(S[1] - S[0], S[2] - S[0])
    h = (T - S[0]) @ n
    out = []
    for k in range(len(T)):
        k1 = (k + 1) % len(T)
        if h[k] >= 0:
            out.append(T[k])
        if h[k] * h[k1] < 0:
            out.append(T[k] + h[k] / (h[k] - h[k1]) * (T[k1] - T[k]))
    return np.array(out)


def random_pair(rng, kind):
    """Shooter Ti, receiver Tj, each wholly in front of the other (no clipping: the oracles
    integrate the signed cosines)."""
    while True:
        Ti = rng.normal(size=(3, 3))
        if kind == "edge":
            Tj = np.array([Ti[1], Ti[0], Ti[0] + rng.normal(size=3)])
        elif kind == "vertex":
            Tj = np.array([Ti[0], Ti[0] + rng.normal(size=3), Ti[0] + rng.normal(size=3)])
        elif kind == "near":
            n = np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0])
            Tj = (Ti + 0.05 * n / np.linalg.norm(n))[::-1] + rng.normal(size=3) * 0.1
        elif kind == "far":
            Tj = rng.normal(size=(3, 3)) + rng.normal(size=3) * 15
        else:
            Tj = rng.normal(size=(3, 3)) + rng.normal(size=3) * 2
        ni, nj = np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0]), np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0])
        front_j = ((Tj - Ti[0]) @ ni >= 0).all() and ((Tj - Ti[0]) @ ni > 0).any()
        front_i = ((Ti - Tj[0]) @ nj >= 0).all() and ((Ti - Tj[0]) @ nj > 0).any()
        if front_i and front_j:
            return Ti, Tj


def far_pair(rng, D, size=0.4):
    """Shooter Ti, receiver Tj of size ~``size`` whose centroids are ~``D`` apart, facing each
    other, each wholly in front of the other (the oracles integrate unclipped cosines)."""
    while True:
        Ti = rng.normal(size=(3, 3)) * size
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        Tj = rng.normal(size=(3, 3)) * size + D * d
        if np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0]) @ d < 0:
            Ti = Ti[::-1]
        if np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0]) @ d > 0:
            Tj = Tj[::-1]
        ni, nj = np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0]), np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0])
        if ((Tj - Ti[0]) @ ni >= 0).all() and ((Ti - Tj[0]) @ nj >= 0).all():
            return Ti, Tj
