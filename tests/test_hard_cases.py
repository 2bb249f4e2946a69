"""Hard cases of the exact predicate, run through the bit-exact board model.

Every case goes through :meth:`BoardModel.execute` (the command stream the RTL will get) and its
decision is compared with :func:`blockray.exact.blocked_reference` (Python integers, orient3d form).
The closed-mesh cases also assert the property itself: a segment from inside to outside is blocked
(never a leak).
"""

import itertools
import math
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st, HealthCheck

from blockray.exact import blocked_reference, blocked_block, block_terms, patch_normals
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.protocol import BeginBlock, EndBlock, LoadReceiver, LoadShooter, Voxel
from blockray.sim.model import BoardModel

HYPOTHESIS = settings(derandomize=True, max_examples=200, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow])


def model_blocked(vertices, shooters, receivers, bits=20):
    """Blocked bits (R, S) of the board model for one block over all ``vertices`` (one voxel)."""
    V = np.asarray(vertices, dtype=np.int64).reshape(-1, 3, 3)
    P = np.asarray(shooters, dtype=np.int64).reshape(-1, 3)
    Q = np.asarray(receivers, dtype=np.int64).reshape(-1, 3)
    assert V.min(initial=0) >= 0 and max(V.max(initial=0), P.max(), Q.max()) < 1 << bits
    assert P.min() >= 0 and Q.min() >= 0
    params = BoardParams(rows=len(Q), cols=len(P), boards=1, bits=bits,
                         patch_depth=max(1, len(V)), voxel_depth=1)
    bm = BoardModel(params)
    bm.load_memory(V, patch_normals(V), [0], [len(V)])
    cmds = [BeginBlock()]
    cmds += [LoadReceiver(r, tuple(q)) for r, q in enumerate(Q.tolist())]
    cmds += [LoadShooter(s, tuple(p)) for s, p in enumerate(P.tolist())]
    cmds += [Voxel(0), EndBlock()]
    return bm.execute(cmds).blocked[0]


def reference_blocked(vertices, shooters, receivers):
    V = np.asarray(vertices, dtype=np.int64).reshape(-1, 3, 3).tolist()
    return np.array([[any(blocked_reference(p, q, *t) for t in V) for p in np.asarray(shooters).tolist()]
                     for q in np.asarray(receivers).tolist()], dtype=bool)


def check(vertices, shooters, receivers, bits=20):
    """Model == independent exact evaluation, per ray and per triangle. Returns the model bits."""
    got = model_blocked(vertices, shooters, receivers, bits)
    np.testing.assert_array_equal(got, reference_blocked(vertices, shooters, receivers))
    V = np.asarray(vertices, dtype=np.int64).reshape(-1, 3, 3)
    per = blocked_block(shooters, receivers, V, patch_normals(V))
    for r, q in enumerate(np.asarray(receivers).tolist()):
        for s, p in enumerate(np.asarray(shooters).tolist()):
            for t, tri in enumerate(V.tolist()):
                assert per[r, s, t] == blocked_reference(p, q, *tri)
    return got


# -- closed meshes -------------------------------------------------------------------------------

def tetrahedron(c, a):
    v = [c, c + [a, 0, 0], c + [0, a, 0], c + [0, 0, a]]
    return np.array(v), np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def cube(c, a):
    v = np.array([c + a * np.array(p) for p in itertools.product((0, 1), repeat=3)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, np.array([t for a_, b, c_, d in quads for t in ((a_, b, c_), (a_, c_, d))])


def icosahedron(c, a):
    phi = (1 + math.sqrt(5)) / 2
    pts = []
    for s1 in (-1, 1):
        for s2 in (-1, 1):
            pts += [(0, s1, s2 * phi), (s1, s2 * phi, 0), (s2 * phi, 0, s1)]
    pts = np.array(pts)
    v = c + np.rint(pts * a).astype(np.int64)
    # faces: triples of mutually nearest vertices (edge length 2 before scaling)
    faces = [f for f in itertools.combinations(range(12), 3)
             if all(abs(np.linalg.norm(pts[i] - pts[j]) - 2) < 1e-9 for i, j in itertools.combinations(f, 2))]
    assert len(faces) == 20
    return v, np.array(faces)


def pyramid_fan(c, a, n=7):
    """A closed cone: a fan of n triangles around an apex plus a fan of n around the base centre."""
    ang = np.arange(n) * 2 * np.pi / n
    ring = c + np.stack([np.rint(a * np.cos(ang)), np.rint(a * np.sin(ang)), np.zeros(n)], 1).astype(np.int64)
    apex, base = c + [0, 0, a], c + [0, 0, -a // 3]
    v = np.concatenate([ring, [apex, base]])
    faces = [(i, (i + 1) % n, n) for i in range(n)] + [((i + 1) % n, i, n + 1) for i in range(n)]
    return v, np.array(faces)


CENTRE = np.array([1 << 19] * 3, dtype=np.int64)
MESHES = {
    "tetrahedron": lambda: tetrahedron(CENTRE - 300, 1200),
    "cube": lambda: cube(CENTRE - 500, 1000),
    "icosahedron": lambda: icosahedron(CENTRE, 700),
    "fan": lambda: pyramid_fan(CENTRE, 900),
}


def surface_points(v, faces):
    """Points on the surface as (numerator (3,), denominator): vertices, edge points, face points."""
    out = [(p, 1) for p in v]
    edges = {tuple(sorted((f[i], f[(i + 1) % 3]))) for f in faces for i in range(3)}
    for i, j in sorted(edges):
        for a, b in ((1, 1), (1, 2), (3, 1)):
            out.append((a * v[i] + b * v[j], a + b))
    for f in faces:
        out.append((v[f[0]] + v[f[1]] + v[f[2]], 3))
    return out


@pytest.mark.parametrize("name", sorted(MESHES))
def test_closed_mesh_never_leaks_through_edges_and_vertices(name):
    v, faces = MESHES[name]()
    tris = v[faces]
    inner = np.rint(v.mean(axis=0)).astype(np.int64)
    rng = np.random.default_rng(sum(map(ord, name)))
    print(f"seed={sum(map(ord, name))}")
    # shooters inside the (convex or apex-star-shaped) mesh: the centre and small offsets from it
    starts = [inner] + [inner + rng.integers(-60, 61, 3) for _ in range(3)]
    for P in starts:
        ends = []
        for num, den in surface_points(v, faces):
            m = int(rng.integers(1, 4))
            Q = P + m * (num - den * P) if den * m > 1 else P + 2 * (num - P)
            ends.append(Q)            # the segment P -> Q passes exactly through num / den
        ends = np.array(ends)
        for k in range(0, len(ends), 32):
            got = check(tris, [P], ends[k:k + 32])
            assert got.all(), f"leak from {P.tolist()} to {ends[k + int(np.flatnonzero(~got[:, 0])[0])].tolist()}"


@pytest.mark.parametrize("name", sorted(MESHES))
def test_closed_mesh_outside_to_outside_agrees(name):
    v, faces = MESHES[name]()
    tris = v[faces]
    rng = np.random.default_rng(7)
    print("seed=7")
    pts = CENTRE + rng.integers(-3000, 3001, (64, 3))
    check(tris, pts[:16], pts[16:])


@pytest.mark.parametrize("name", ["tetrahedron", "cube", "icosahedron"])
@given(data=st.data())
@HYPOTHESIS
def test_closed_mesh_random_directions_never_leak(name, data):
    v, faces = MESHES[name]()
    tris = v[faces]
    inner = np.rint(v.mean(axis=0)).astype(np.int64)
    off = np.array(data.draw(st.lists(st.integers(-50, 50), min_size=3, max_size=3)))
    d = np.array(data.draw(st.lists(st.integers(-40, 40), min_size=3, max_size=3)))
    if not d.any():
        d = np.array([1, 0, 0])
    P = inner + off
    Q = P + d * 400                    # |d| >= 1 so Q is >= 400 away; the meshes lie within ~1200
    far = np.linalg.norm(Q - inner) > 1.01 * np.linalg.norm(v - inner, axis=1).max()
    got = check(tris, [P], [Q])
    if far:
        assert got.all()


def test_flat_fan_shared_spokes_and_centre():
    # a flat fan of 6 triangles around a centre vertex c in the plane z = c_z
    c = CENTRE
    ring = [c + d for d in ([1000, 0, 0], [500, 866, 0], [-500, 866, 0], [-1000, 0, 0],
                            [-500, -866, 0], [500, -866, 0])]
    tris = np.array([[c, ring[i], ring[(i + 1) % 6]] for i in range(6)])
    crossings = [(c, 1)] + [(c + r, 2) for r in ring] + [(2 * c + r, 3) for r in ring]
    for X, den in crossings:                  # the shared centre vertex and points on shared spokes
        for dz in (1, 5, 333):
            P = c + [7, -3, dz]
            Q = P + 2 * (X - den * P)          # passes through X / den on the fan's plane
            assert check(tris, [P], [Q]).all(), (X.tolist(), den, dz)
            assert check(tris, [Q], [P]).all()


# -- single-triangle hard cases -------------------------------------------------------------------

L20 = (1 << 20) - 1


def test_ray_in_triangle_plane_and_grazing():
    T = [[100, 100, 500], [900, 100, 500], [100, 900, 500]]
    # in the plane, through the interior: never blocked (strict plane test)
    assert not check([T], [[0, 0, 500]], [[1000, 1000, 500]]).any()
    # along an edge, in the plane
    assert not check([T], [[0, 100, 500]], [[1000, 100, 500]]).any()
    # crossing the plane exactly at a vertex and exactly on an edge: blocked (closed edges)
    assert check([T], [[100, 100, 400]], [[100, 100, 600]]).all()
    assert check([T], [[500, 100, 400]], [[500, 100, 600]]).all()
    assert check([T], [[500, 500, 400]], [[500, 500, 600]]).all()        # on the hypotenuse
    # one unit outside an edge / the hypotenuse: clear
    assert not check([T], [[500, 99, 400]], [[500, 99, 600]]).any()
    assert not check([T], [[501, 500, 400]], [[501, 500, 600]]).any()
    # grazing: nearly parallel to the plane, crossing it inside / just outside
    assert check([T], [[0, 300, 499]], [[1000, 300, 501]]).all()
    assert not check([T], [[0, 300, 501]], [[1000, 300, 502]]).any()


def test_end_points_on_other_patches_edges_and_vertices():
    T = [[100, 100, 500], [900, 100, 500], [100, 900, 500]]
    for P in ([100, 100, 500], [500, 100, 500], [300, 300, 500], [500, 500, 500]):   # vertex, edges, inside
        assert not check([T], [P], [[300, 300, 900], [0, 0, 0], [300, 300, 100]]).any()
        assert not check([T], [[300, 300, 900], [0, 0, 0]], [P]).any()


def test_coplanar_overlapping_triangles():
    A = [[0, 0, 300], [600, 0, 300], [0, 600, 300]]
    B = [[100, 100, 300], [700, 100, 300], [100, 700, 300]]
    # sample points of A (on the shared plane) never blocked by A or B
    D = SampleScheme(8).denominator
    VA = np.array(A) * D
    VB = np.array(B) * D
    pts = SampleScheme(8).points_int(VA[None])[0]
    assert not check([VA, VB], pts, [[50 * D, 50 * D, 900 * D], [200 * D, 200 * D, 0]]).any()
    # crossing the plane inside the overlap: blocked by both
    assert blocked_reference([200, 200, 0], [200, 200, 600], *A)
    assert check([A, B], [[200, 200, 0]], [[200, 200, 600]]).all()


def test_zero_area_and_sliver_triangles():
    zero = [[[0, 0, 500], [1000, 0, 500], [2000, 0, 500]],        # collinear
            [[10, 10, 10], [10, 10, 10], [900, 900, 900]],          # repeated vertex
            [[7, 7, 7], [7, 7, 7], [7, 7, 7]]]                      # a point
    for Z in zero:
        rays = ([[500, 0, 0]], [[500, 0, 1000]]) if Z[0][2] == 500 else ([[400, 400, 300]], [[400, 400, 500]])
        assert not check([Z], *rays).any()
        assert not check([Z], [[7, 7, 0]], [[7, 7, 14]]).any()
    sliver = [[0, 0, 500], [L20, 0, 500], [L20, 1, 500]]             # area L/2, height 1
    assert check([sliver], [[L20 - 1, 0, 0]], [[L20 - 1, 0, 1000]]).all()   # on its long edge
    assert not check([sliver], [[L20 - 1, 2, 0]], [[L20 - 1, 2, 1000]]).any()


def test_tiny_triangle_beside_huge_one_at_the_largest_coordinates():
    huge = [[0, 0, 0], [L20, 0, 0], [0, L20, L20]]
    tiny = [[L20 - 3, L20 - 3, L20 - 1], [L20, L20 - 3, L20 - 1], [L20 - 3, L20, L20 - 1]]
    P = [[L20 - 2, L20 - 2, L20], [L20, L20, L20], [0, L20, 0], [L20, 0, L20]]
    Q = [[L20 - 2, L20 - 2, L20 - 2], [0, 0, L20], [L20, L20, 0], [L20 // 2, L20 // 2, 0]]
    got = check([huge, tiny], P, Q)
    assert got[0, 0]                                  # through the tiny one's interior


def exact_terms(P, Q, V):
    """pP, pQ, s_k with Python integers (no int64 anywhere)."""
    P, Q, V = [list(map(int, x)) for x in P], [list(map(int, x)) for x in Q], [[list(map(int, c)) for c in t] for t in V]
    sub = lambda a, b: [a[i] - b[i] for i in range(3)]
    dot = lambda a, b: sum(a[i] * b[i] for i in range(3))
    cross = lambda a, b: [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    out = []
    for t in V:
        n = cross(sub(t[1], t[0]), sub(t[2], t[0]))
        pP = [dot(sub(p, t[0]), n) for p in P]
        pQ = [dot(sub(q, t[0]), n) for q in Q]
        sides = [[[dot(sub(p, t[k]), cross(sub(q, t[k]), sub(t[(k + 1) % 3], t[k]))) for k in range(3)]
                  for p in P] for q in Q]
        out.append((pP, pQ, sides))
    return out


def test_largest_coordinates_do_not_overflow():
    corners = np.array(list(itertools.product((0, L20), repeat=3)), dtype=np.int64)
    rng = np.random.default_rng(20)
    print("seed=20")
    V = corners[rng.integers(0, 8, (40, 3))]
    V = V[np.any(patch_normals(V) != 0, axis=1)][:16]
    P = np.concatenate([corners[:4], rng.choice([0, 1, L20 - 1, L20], (4, 3))])
    Q = np.concatenate([corners[4:], rng.choice([0, 1, L20 - 1, L20], (4, 3))])
    pP, pQ, sides = block_terms(P, Q, V, patch_normals(V))
    biggest = 0
    for t, (eP, eQ, es) in enumerate(exact_terms(P, Q, V)):
        assert pP[:, t].tolist() == eP and pQ[:, t].tolist() == eQ
        assert sides[:, :, t, :].tolist() == es
        biggest = max(biggest, max(map(abs, eP + eQ)), max(abs(x) for r in es for s in r for x in s))
    assert biggest < 2 * L20 ** 3 + 1 and biggest.bit_length() > 58     # the wide end is exercised
    check(V, P, Q)


# -- randomised ----------------------------------------------------------------------------------

def coords(bits):
    L = (1 << bits) - 1
    return st.one_of(st.integers(0, L), st.sampled_from([0, 1, L - 1, L]), st.integers(L // 2 - 3, L // 2 + 3))


@st.composite
def hard_query(draw):
    bits = draw(st.integers(4, 20))
    pt = st.lists(coords(bits), min_size=3, max_size=3).map(np.array)
    tri = np.array([draw(pt) for _ in range(3)])
    P, Q = draw(pt), draw(pt)
    kind = draw(st.sampled_from(["free", "P on vertex", "P on edge", "through vertex", "through edge",
                                 "in plane", "collinear"]))
    if kind == "P on vertex":
        P = tri[draw(st.integers(0, 2))].copy()
    elif kind == "P on edge":
        k = draw(st.integers(0, 2))
        s = tri[k] + tri[(k + 1) % 3]
        if (s % 2 == 0).all():
            P = s // 2
    elif kind == "through vertex":
        X = tri[draw(st.integers(0, 2))]
        Q = 2 * X - P
    elif kind == "through edge":
        k = draw(st.integers(0, 2))
        Q = tri[k] + tri[(k + 1) % 3] - P            # midpoint of the edge is the segment's midpoint
    elif kind == "in plane":
        Q = tri[0] + tri[1] - tri[2]
        P = tri[2] + tri[0] - tri[1]
    elif kind == "collinear":
        tri[2] = 2 * tri[1] - tri[0]
    L = (1 << bits) - 1
    if min(tri.min(), P.min(), Q.min()) < 0 or max(tri.max(), P.max(), Q.max()) > L:
        P, Q, tri = np.clip(P, 0, L), np.clip(Q, 0, L), np.clip(tri, 0, L)
    return bits, tri, P, Q


@given(hard_query())
@settings(derandomize=True, max_examples=600, deadline=None)
def test_random_hard_queries_agree(q):
    bits, tri, P, Q = q
    check([tri], [P], [Q], bits=bits)


# -- agreement with the float64 predicate on the unquantised scene --------------------------------

def float_blocked(P, Q, V):
    """The same predicate in float64 on float inputs: (R, S, N) bool. (The golden board's arithmetic.)"""
    n = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
    pP = np.einsum("snc,nc->sn", P[:, None, :] - V[None, :, 0], n)
    pQ = np.einsum("rnc,nc->rn", Q[:, None, :] - V[None, :, 0], n)
    E = np.roll(V, -1, axis=1) - V
    w = np.cross(Q[:, None, None, :] - V[None], E[None])
    s = np.einsum("snkc,rnkc->rsnk", P[:, None, None, :] - V[None], w)
    crossing = np.sign(pQ)[:, None, :] * np.sign(pP)[None] < 0
    return crossing & ((s >= 0).all(-1) | (s <= 0).all(-1))


def test_float_agreement_by_bits_is_measured():
    from blockray.fixedpoint import quantise
    from board_scenes import scattered_scene as random_scene
    scene = random_scene(12, n=40)
    samples = SampleScheme(8)
    fP = samples.points(scene.patch_vertices).reshape(-1, 3)
    fQ = scene.centroids
    gold = float_blocked(fP, fQ, scene.patch_vertices)
    # float sample points are not exactly on their own plane: the golden board excludes the
    # shooter's and the receiver's own patches by id (the integer model needs no exclusion)
    N, K = scene.patches, samples.count
    own = np.arange(N)
    gold[own, :, own] = False
    gold[:, np.arange(N * K), np.repeat(own, K)] = False
    q12 = quantise(scene, samples, 12)
    model = blocked_block(q12.shooters.reshape(-1, 3), q12.receivers, q12.vertices, q12.normals)
    assert not model[own, :, own].any()                # the model needs no exclusion
    rates = {}
    for bits in (8, 12, 16, 20):
        q = quantise(scene, samples, bits)
        got = blocked_block(q.shooters.reshape(-1, 3), q.receivers, q.vertices, q.normals)
        rates[bits] = float((got.any(-1) != gold.any(-1)).mean())      # per ray
    print("float64 disagreement rate by B:", rates)
    assert gold.any()
    assert rates[20] <= rates[8] and rates[20] < 1e-3


@pytest.mark.slow
def test_a_million_queries_agree_with_the_exact_reference():
    """The done-when run (about 20 s): benchmarks/bench_model.py --part exact."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_model.py"
    spec = importlib.util.spec_from_file_location("bench_model", path)
    bench = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(path.parent))         # its `import _shared`, whichever tests ran before
    try:
        spec.loader.exec_module(bench)
    finally:
        sys.path.remove(str(path.parent))
    assert bench.part_exact(1_000_000, seed=2024) == 0
