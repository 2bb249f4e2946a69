"""Form factors against closed forms (prior-art.md D.2) and an independent quadrature.

The mesh builders here (``rectangle``, ``make_scene``, ``closed_box``) are also used by
test_solver.py and test_golden.py.
"""

import math

import numpy as np
import pytest

from blockray.host_driver.formfactor import (exchange_mask, form_factor_matrix, point_to_triangles,
                                             triangle_to_patches, triangle_to_points,
                                             unoccluded_factors)
from blockray.host_driver.scene import Scene


# ---------------------------------------------------------------------------- mesh builders

def rectangle(origin, u, v, nu, nv):
    """Triangles (2 nu nv, 3, 3) of the parallelogram origin + [0,1] u + [0,1] v; normal along u x v."""
    origin, u, v = (np.asarray(x, dtype=np.float64) for x in (origin, u, v))
    a = np.arange(nu + 1) / nu
    b = np.arange(nv + 1) / nv
    P = origin + a[:, None, None] * u + b[None, :, None] * v
    tris = []
    for i in range(nu):
        for j in range(nv):
            tris.append([P[i, j], P[i + 1, j], P[i + 1, j + 1]])
            tris.append([P[i, j], P[i + 1, j + 1], P[i, j + 1]])
    return np.array(tris)


def make_scene(triangles, reflectance=0.5, emission=0.0, groups=None, name="test"):
    """A Scene from a triangle soup (M, 3, 3); reflectance/emission broadcast to (M, 3)."""
    T = np.asarray(triangles, dtype=np.float64)
    M = len(T)
    return Scene(name=name, vertices=T.reshape(-1, 3), triangles=np.arange(3 * M).reshape(M, 3),
                 reflectance=np.broadcast_to(np.asarray(reflectance, float), (M, 3)).copy(),
                 emission=np.broadcast_to(np.asarray(emission, float), (M, 3)).copy(),
                 group=np.zeros(M, dtype=np.int64) if groups is None else np.asarray(groups),
                 group_names=["all"])


def closed_box(n, size=1.0):
    """The six faces of a cube [0, size]^3, each n x n cells of 2 triangles, normals inward.
    Returns (triangles (12 n^2, 3, 3), face index per triangle)."""
    s = size
    X, Y, Z = np.eye(3) * s
    O = np.zeros(3)
    faces = [rectangle(O, X, Y, n, n),          # z = 0, normal +z
             rectangle(Z, Y, X, n, n),          # z = s, normal -z
             rectangle(O, Z, X, n, n),          # y = 0, normal +y
             rectangle(Y, X, Z, n, n),          # y = s, normal -y
             rectangle(O, Y, Z, n, n),          # x = 0, normal +x
             rectangle(X, Z, Y, n, n)]          # x = s, normal -x
    return np.concatenate(faces), np.repeat(np.arange(6), 2 * n * n)


def area_average_factor(receiver, shooter):
    """Patch-set to patch-set factor: area-weighted mean over receiver patches of the point factor
    from each receiver centroid to the whole shooter set."""
    scene = make_scene(receiver)
    f = sum(triangle_to_points(t, scene.centroids, scene.normals) for t in shooter)
    return float((scene.areas * f).sum() / scene.areas.sum())


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


@pytest.mark.parametrize("args, value", [((1, 1, 1), 0.199825), ((1, 1, 2), 0.068590),
                                         ((1, 1, 0.5), 0.415253), ((2, 1, 1), 0.285875)])
def test_parallel_closed_form_transcription(args, value):
    assert parallel_closed_form(*args) == pytest.approx(value, abs=1e-6)


@pytest.mark.parametrize("args, value", [((1, 1, 1), 0.200044), ((1, 2, 1), 0.232853),
                                         ((2, 1, 1), 0.116426), ((1, 1, 2), 0.240636)])
def test_perpendicular_closed_form_transcription(args, value):
    assert perpendicular_closed_form(*args) == pytest.approx(value, abs=1e-6)


# ---------------------------------------------------------------------------- point factor

@pytest.mark.parametrize("a, b, c, value", [(1, 1, 1, 0.138532), (1, 2, 1, 0.167375),
                                            (0.5, 0.5, 2, 0.018369)])
def test_point_to_rectangle_corner(a, b, c, value):
    """Two triangles of the rectangle at height c over the receiver, foot point at a corner."""
    tris = rectangle([0, 0, c], [a, 0, 0], [0, b, 0], 1, 1)
    f = point_to_triangles([0, 0, 0], [0, 0, 1], tris)
    assert f.sum() == pytest.approx(value, abs=1e-6)
    assert f.sum() == pytest.approx(corner_closed_form(a, b, c), rel=1e-12)


def test_point_to_rectangle_interior_foot_point():
    """Superposition of four corner rectangles (D.2 item 3) for a foot point inside."""
    tris = rectangle([-0.3, -0.5, 0.7], [1.5, 0, 0], [0, 2.0, 0], 3, 5)
    expected = sum(corner_closed_form(a, b, 0.7) for a in (0.3, 1.2) for b in (0.5, 1.5))
    f = point_to_triangles([0, 0, 0], [0, 0, 1], tris)
    assert f.sum() == pytest.approx(expected, rel=1e-12)


def _quadrature(point, normal, triangle, n=300):
    """Independent midpoint-rule integral of max(cos_j, 0) |cos_i| / (pi r^2) over the triangle
    (n^2 congruent sub-triangles): no clipping, no contour integral."""
    V = np.asarray(triangle, float)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    keep = i + j < n
    up = np.stack([i[keep] + 1 / 3, j[keep] + 1 / 3], axis=1) / n
    keep2 = i + j < n - 1
    down = np.stack([i[keep2] + 2 / 3, j[keep2] + 2 / 3], axis=1) / n
    uv = np.concatenate([up, down])
    X = V[0] + uv[:, :1] * (V[1] - V[0]) + uv[:, 1:] * (V[2] - V[0])
    cross = np.cross(V[1] - V[0], V[2] - V[0])
    area = 0.5 * np.linalg.norm(cross)
    m = cross / (2 * area)
    d = X - np.asarray(point, float)
    r2 = (d * d).sum(axis=1)
    nn = np.asarray(normal, float) / np.linalg.norm(normal)
    cos_j = np.maximum(d @ nn, 0) / np.sqrt(r2)
    cos_i = np.abs(d @ m) / np.sqrt(r2)
    return float((cos_j * cos_i / (math.pi * r2)).sum() * area / len(X))


def test_clipped_factor_matches_quadrature():
    """Triangles that straddle the receiver's tangent plane, against brute-force quadrature."""
    seed = 20240611
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    checked = 0
    while checked < 12:
        tri = rng.uniform(-1.5, 1.5, (3, 3))
        normal = rng.normal(size=3)
        point = np.zeros(3)
        h = (tri - point) @ normal
        centroid_dist = np.linalg.norm(tri.mean(axis=0))
        # keep triangles that straddle the plane and stay clear of the receiver point
        dists = [np.linalg.norm(np.cross(tri[(k + 1) % 3] - tri[k], tri[k] - point))
                 / np.linalg.norm(tri[(k + 1) % 3] - tri[k]) for k in range(3)]
        if not (h.min() < 0 < h.max()) or min(dists) < 0.6 or centroid_dist > 2.5:
            continue
        m = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        if abs((tri[0] - point) @ m) / np.linalg.norm(m) < 0.6:
            continue
        f = point_to_triangles(point, normal, tri[None])[0]
        q = _quadrature(point, normal, tri)
        assert f == pytest.approx(q, rel=2e-3, abs=1e-6), (tri, normal)
        checked += 1


def test_clipping_equals_front_part():
    """A vertical rectangle crossing the receiver's tangent plane counts only its upper half."""
    full = rectangle([1, 0, -0.8], [0, 1.3, 0], [0, 0, 1.6], 2, 3)     # x = 1, z in [-0.8, 0.8]
    upper = rectangle([1, 0, 0], [0, 1.3, 0], [0, 0, 0.8], 1, 1)
    f_full = point_to_triangles([0, 0, 0], [0, 0, 1], full).sum()
    f_upper = point_to_triangles([0, 0, 0], [0, 0, 1], upper).sum()
    assert f_upper > 0.01
    assert f_full == pytest.approx(f_upper, rel=1e-12)


def test_winding_and_shapes():
    seed = 7
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    tris = rng.uniform(-1, 1, (50, 3, 3)) + [0, 0, 2]
    p, n = np.array([0.1, -0.2, 0.0]), np.array([0.2, 0.1, 1.0])
    f = point_to_triangles(p, n, tris)
    assert np.allclose(f, point_to_triangles(p, n, tris[:, ::-1]), rtol=1e-12, atol=0)
    assert np.allclose(f, point_to_triangles(p, 5 * n, tris), rtol=1e-12, atol=0)
    g = np.array([triangle_to_points(t, p[None], n[None])[0] for t in tris])
    assert np.allclose(f, g, rtol=1e-13, atol=0)
    assert (f >= 0).all() and (f <= 1).all()


def test_degenerate_cases_give_zero_not_nan():
    T = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float)
    on_plane = [[0.2, 0.2, 0], [0.5, 0, 0], [0, 0, 0], [1, 0, 0], [0.5, 0.5, 0], [3, 2, 0]]
    for p in on_plane:
        for n in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 0, 0]):
            assert point_to_triangles(p, n, T)[0] == 0.0
    # zero-area triangles (collinear, repeated vertex), zero normal
    degenerate = np.array([[[0, 0, 1], [1, 0, 1], [2, 0, 1]], [[0, 0, 1], [0, 0, 1], [1, 1, 1]]], float)
    assert (point_to_triangles([0, 0, 0], [0, 0, 1], degenerate) == 0).all()
    assert point_to_triangles([0, 0, 0], [0, 0, 0], T + [0, 0, 1])[0] == 0.0
    # a triangle touching the tangent plane along an edge or only at a vertex: finite, >= 0
    touching = np.array([[[1, 0, 0], [1, 1, 0], [1, 0, 1]], [[1, 0, 0], [1, 1, -1], [1, -1, -1]]], float)
    f = point_to_triangles([0, 0, 0], [0, 0, 1], touching)
    assert np.isfinite(f).all() and f[0] > 0 and f[1] == 0.0
    # receiver point approaching a shared edge: tends to the perpendicular half-plane value
    wall = rectangle([0, -50, 0], [0, 100, 0], [0, 0, 100], 1, 1)       # x = 0 plane, normal -x... any side
    near = point_to_triangles([1e-9, 0, 0], [0, 0, 1], wall).sum()
    assert near == pytest.approx(0.5, abs=1e-6)


# ---------------------------------------------------------------------------- area factors (D.2)

@pytest.mark.parametrize("a, b, c", [(1, 1, 1), (2, 1, 1), (1, 1, 0.5), (1, 1, 2)])
def test_parallel_rectangles_within_one_percent(a, b, c):
    n = 8                                                              # cells of side 1/8
    lower = rectangle([0, 0, 0], [a, 0, 0], [0, b, 0], n * a, n * b)    # normal +z
    upper = rectangle([0, 0, c], [0, b, 0], [a, 0, 0], n * b, n * a)    # normal -z
    F = area_average_factor(lower, upper)
    exact = parallel_closed_form(a, b, c)
    print(f"parallel {a}x{b} at {c}: F={F:.6f} closed form={exact:.6f} error={F / exact - 1:+.2e}")
    assert F == pytest.approx(exact, rel=0.01)


@pytest.mark.parametrize("w, h, l", [(1, 1, 1), (1, 2, 1), (2, 1, 1), (1, 1, 2)])
def test_perpendicular_rectangles_within_one_percent(w, h, l):
    n = 8                                                              # cells of side 1/8
    base = rectangle([0, 0, 0], [l, 0, 0], [0, w, 0], n * l, n * w)     # z = 0, normal +z
    other = rectangle([0, 0, 0], [0, 0, h], [l, 0, 0], n * h, n * l)    # y = 0, normal +y
    F = area_average_factor(base, other)
    exact = perpendicular_closed_form(w, h, l)
    print(f"perpendicular w={w} h={h} l={l}: F={F:.6f} closed form={exact:.6f} error={F / exact - 1:+.2e}")
    assert F == pytest.approx(exact, rel=0.01)


def test_formula_2_is_what_we_avoid():
    """The centre-to-centre formula (2) on perpendicular unit squares gives 1/pi (59% high),
    while the point-to-triangle factor is within 0.2% on a coarse 4x4 mesh."""
    ca, cb = np.array([0.5, 0.5, 0]), np.array([0.5, 0, 0.5])
    d = cb - ca
    r2 = d @ d
    f2 = (d @ [0, 0, 1]) * (-d @ [0, 1, 0]) / (math.pi * r2 * r2) * 1.0
    exact = perpendicular_closed_form(1, 1, 1)
    assert abs(f2 / exact - 1) > 0.05
    base = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 4, 4)
    other = rectangle([0, 0, 0], [0, 0, 1], [1, 0, 0], 4, 4)
    assert area_average_factor(base, other) == pytest.approx(exact, rel=2e-3)


# ---------------------------------------------------------------------------- closed box

def _face_factors(F, A, face):
    return np.array([[(A[face == p] @ F[np.ix_(face == p, face == q)]).sum() / A[face == p].sum()
                      for q in range(6)] for p in range(6)])


def test_closed_box_centroid_rule_row_sums():
    """Point factors at the centroid tile each receiver's hemisphere: row sums are exactly 1."""
    tris, face = closed_box(4)
    scene = make_scene(tris)
    assert (np.einsum("jc,jc->j", scene.centroids - 0.5, scene.normals) < 0).all()   # inward
    F = form_factor_matrix(scene, subdivision=1)
    assert np.abs(F.sum(axis=1) - 1).max() < 1e-12
    assert (F[face[:, None] == face[None]] == 0).all()                 # coplanar: never


def test_closed_box_factors_and_reciprocity():
    n = 4
    tris, face = closed_box(n)
    scene = make_scene(tris)
    A = scene.areas
    F = form_factor_matrix(scene)                                      # defaults
    centroid = form_factor_matrix(scene, subdivision=1)
    rows = np.abs(F.sum(axis=1) - 1).max()
    print(f"row sums: max |sum_i F_ji - 1| = {rows:.2e}")
    assert rows < 3e-3
    faceF = _face_factors(F, A, face)
    opposite, adjacent = parallel_closed_form(1, 1, 1), perpendicular_closed_form(1, 1, 1)
    err = []
    for p in range(6):
        q = p ^ 1
        others = [r for r in range(6) if r not in (p, q)]
        err += [faceF[p, q] / opposite - 1, *(faceF[p, others] / adjacent - 1)]
    print(f"face-to-face factors vs closed forms: max relative error {np.abs(err).max():.2e}")
    assert np.abs(err).max() < 0.01
    # reciprocity A_i F_ij = A_j F_ji holds for exact patch factors; for the estimates the column
    # sums sum_j A_j F_ji / A_i measure it, and receiver subdivision must improve on the centroid rule
    col = (A[:, None] * F).sum(axis=0) / A
    col_centroid = (A[:, None] * centroid).sum(axis=0) / A
    print(f"column sums: default {col.min():.4f}..{col.max():.4f}, "
          f"centroid rule {col_centroid.min():.4f}..{col_centroid.max():.4f}")
    assert np.abs(col - 1).max() < 0.02
    assert np.abs(col - 1).max() < 0.5 * np.abs(col_centroid - 1).max()
    # pairwise, for pairs on different faces at least half the box apart
    AF = A[:, None] * F
    d = np.linalg.norm(scene.centroids[:, None] - scene.centroids[None], axis=-1)
    far = (d > 0.5) & (face[:, None] != face[None])
    rel = np.abs(AF - AF.T)[far] / np.maximum(AF, AF.T)[far]
    print(f"pairwise reciprocity, pairs > 0.5 apart: max relative error {rel.max():.3f}, "
          f"mean {rel.mean():.4f}")
    assert rel.max() < 0.12 and rel.mean() < 0.01


def test_triangle_to_patches_perpendicular_squares():
    """Midpoint rule over receiver sub-triangles, against the closed form."""
    base = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 1, 1)            # two receiver triangles
    other = rectangle([0, 0, 0], [0, 0, 1], [1, 0, 0], 1, 1)
    exact = perpendicular_closed_form(1, 1, 1)
    errors = []
    for m in (1, 4, 8):
        f = sum(triangle_to_patches(t, base, subdivision=m) for t in other)  # equal areas: mean
        errors.append(abs(f.mean() / exact - 1))
    print(f"perpendicular unit squares, 2 receiver triangles, subdivision 1/4/8: errors {errors}")
    assert errors[2] < 0.01 and errors[2] < errors[1] < errors[0]


def test_exchange_mask_rules():
    # floor (2 coplanar triangles, normal +z), a ceiling facing down, a ceiling facing up (away),
    # a black patch facing down, a wall whose tangent plane has the floor patch behind it
    floor = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 1, 1)
    ceiling = rectangle([0, 0, 1], [0, 1, 0], [1, 0, 0], 1, 1)[:1]           # normal -z
    away = rectangle([0, 0, 2], [1, 0, 0], [0, 1, 0], 1, 1)[:1]              # normal +z, above
    black = rectangle([0, 0, 1.5], [0, 1, 0], [1, 0, 0], 1, 1)[:1]           # normal -z, rho = 0
    behind = rectangle([2, 0, 0.5], [0, 1, 0], [0, 0, 1], 1, 1)[:1]          # x = 2, normal +x
    tris = np.concatenate([floor, ceiling, away, black, behind])
    rho = np.full((len(tris), 3), 0.5)
    rho[4] = 0.0
    scene = make_scene(tris, reflectance=rho)
    mask = exchange_mask(scene, 0)
    assert mask.tolist() == [False, False, True, False, False, False]
    # from the ceiling: both floor triangles; the patches above it are behind its plane
    assert exchange_mask(scene, 2).tolist() == [True, True, False, False, False, False]
    f = unoccluded_factors(scene, 0)
    assert (f[~mask] == 0).all() and f[2] > 0
