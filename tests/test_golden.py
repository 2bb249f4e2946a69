"""The float64 golden board against the exact predicate and against plain geometry.

The voxel grid is replaced by stand-ins (one voxel holding every patch, or hand-made CSR tables)
so these tests depend only on the board.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from blockray.exact import blocked_block, blocked_reference, patch_normals
from blockray.board import BlockRay
from blockray.host_driver.board.golden import GoldenBoard
from blockray.samples import SampleScheme

from scenes import make_scene, rectangle


def one_voxel(n):
    """Grid stand-in: a single voxel (index 0) holding every patch."""
    return SimpleNamespace(v=1, start=np.array([0]), count=np.array([n]), patches=np.arange(n))


def board_for(triangles, samples=SampleScheme(8), grid=None):
    scene = make_scene(triangles)
    board = GoldenBoard()
    board.prepare(scene, samples)
    board.load(grid or one_voxel(scene.patches))
    return scene, board


def rotation(seed):
    q = np.random.default_rng(seed).normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _reference_bits(P, Q, V):
    return np.array([[any(blocked_reference(p, q, *v) for v in V) for p in P] for q in Q])


def test_agrees_with_exact_on_integer_scenes():
    """Random integer triangles (multiples of D, so sample points are exact) on a small lattice,
    where shared edges, coplanar patches and rays through vertices are common."""
    samples = SampleScheme(8)
    D = samples.denominator
    seed = 424242
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    total = blocked_rays = 0
    for trial in range(6):
        N = 24
        V = (rng.integers(0, 6, (N, 1, 3)) + rng.integers(-2, 3, (N, 3, 3))) * D
        V = V[np.linalg.norm(patch_normals(V), axis=1) > 0]                # the scene drops zero-area
        scene, board = board_for(V, samples)
        P_all = samples.points_int(V)                                      # (N, K, 3) exact ints
        Q_all = samples.centroids_int(V)
        blocks = []
        for _ in range(4):
            sp = rng.integers(0, len(V), 5)
            ss = rng.integers(0, samples.count, 5)
            rp = rng.integers(0, len(V), 6)
            blocks.append(BlockRay(sp, ss, rp, np.array([0])))
        for block, bits in zip(blocks, board.run(blocks)):
            P = P_all[block.shooter_patch, block.shooter_sample]
            Q = Q_all[block.receiver_patch]
            ref = _reference_bits(P, Q, V)
            assert np.array_equal(bits, ref), f"trial {trial}"
            assert np.array_equal(bits, blocked_block(P, Q, V, patch_normals(V)).any(axis=-1))
            total += bits.size
            blocked_rays += int(bits.sum())
    print(f"{total} rays, {blocked_rays} blocked, all equal to the exact predicate")
    assert 0.2 * total < blocked_rays < 0.8 * total


def test_agrees_with_exact_through_edges_and_vertices():
    """Integer rays aimed exactly through the edges and vertices of an integer wall mesh: every
    integer point of the z = 10 wall's square lies on an edge (grid lines, diagonals) or a vertex."""
    seed = 99
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    wall = rectangle([0, 0, 10], [0, 8, 0], [8, 0, 0], 4, 4).astype(np.int64)   # step 2, diagonals (1, 1)
    block = rectangle([2, 2, 4], [4, 0, 0], [0, 4, 0], 2, 2).astype(np.int64)   # a second layer below
    tris = np.concatenate([wall, block])
    scene, board = board_for(tris)
    inside = 0
    for _ in range(400):
        X = np.append(rng.integers(-2, 11, 2), 10)                         # crossing point
        d = np.append(rng.integers(-3, 4, 2), rng.integers(1, 8))
        P, Q = X - d, X + d
        got = board.blocked(P[None].astype(float), Q[None].astype(float), np.arange(len(tris)))[0, 0]
        assert got == any(blocked_reference(P, Q, *v) for v in tris), (P, Q)
        if (0 <= X[:2]).all() and (X[:2] <= 8).all():
            assert got, (P, Q)                                             # watertight
            inside += 1
    assert inside > 100


def test_watertight_on_float_meshes():
    """A rotated, translated wall in float coordinates: segments through the (rounded) midpoints
    of its inner edges and through its inner vertices are always blocked."""
    for seed in (1, 2, 3):
        print(f"seed={seed}")
        rng = np.random.default_rng(seed)
        R, t = rotation(seed), rng.normal(size=3) * 10
        flat = rectangle([-1, -1, 0], [2, 0, 0], [0, 2.0, 0], 7, 5)
        wall = flat @ R.T + t
        scene, board = board_for(wall)
        points = np.concatenate([((flat + np.roll(flat, -1, axis=1)) / 2).reshape(-1, 3), flat.reshape(-1, 3)])
        points = points[(np.abs(points[:, 0]) < 1 - 1e-9) & (np.abs(points[:, 1]) < 1 - 1e-9)]
        X = points @ R.T + t
        dirs = rng.normal(size=(len(X), 3))
        dirs *= np.sign(dirs @ R[:, 2])[:, None]
        dirs += 0.3 * R[:, 2]
        P = X - dirs * rng.uniform(0.2, 2, (len(X), 1))
        Q = X + dirs * rng.uniform(0.2, 2, (len(X), 1))
        every = np.arange(len(wall))
        leaks = sum(not board.blocked(p[None], q[None], every)[0, 0] for p, q in zip(P, Q))
        print(f"{len(X)} segments through edges and vertices, {leaks} leaked")
        assert leaks == 0


def test_own_patch_and_coplanar_neighbours_never_block():
    """A plane of many patches at float coordinates (exactly coplanar: one z) and one receiver
    above it: the exact sample points lie on the plane, so nothing blocks, with no tolerance."""
    floor = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 6, 6) * 0.1 + [0.3, 0.7, 0.1]
    lamp = rectangle([0.4, 0.4, 0.8], [0, 0.2, 0], [0.2, 0, 0], 1, 1) * 0.1 + [0.3, 0.7, 0.1]
    tris = np.concatenate([floor, lamp])
    scene, board = board_for(tris)
    n = len(tris)
    S = np.repeat(np.arange(n), 8)
    K = np.tile(np.arange(8), n)
    blocks = [BlockRay(S[a:a + 8], K[a:a + 8], np.arange(n), np.array([0])) for a in range(0, len(S), 8)]
    bits = board.run(blocks)
    assert not any(b.any() for b in bits)
    counters = board.counters()
    assert counters["blocks"] == len(blocks) and counters["rays"] == len(S) * n
    assert counters["tests"] == counters["rays"] * n                # every patch once per block
    assert counters["crossings"] == 0                                 # no ray even crosses a plane


def _fr_orient(a, b, c, d):
    m = [[a[i] - d[i] for i in range(3)], [b[i] - d[i] for i in range(3)], [c[i] - d[i] for i in range(3)]]
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


def fraction_blocked(P, Q, V):
    """The predicate in exact rational arithmetic (fractions.Fraction): P, Q, V[k] tuples of Fractions."""
    sign = lambda x: (x > 0) - (x < 0)
    if sign(_fr_orient(V[0], V[1], V[2], P)) * sign(_fr_orient(V[0], V[1], V[2], Q)) >= 0:
        return False
    s = [_fr_orient(P, Q, V[k], V[(k + 1) % 3]) for k in range(3)]
    return all(x >= 0 for x in s) or all(x <= 0 for x in s)


def rational_point(E, w):
    from fractions import Fraction
    D = int(sum(w))
    return tuple(sum(Fraction(int(w[k])) * Fraction(float(E[k][c])) for k in range(3)) / D for c in range(3))


def test_rotated_plane_agrees_with_rational_evaluation():
    """Rotated, the float plane is crinkled at rounding scale: whatever the board answers for
    rays skimming it must be what exact rational arithmetic says, ray by ray."""
    from fractions import Fraction
    R = rotation(5)
    floor = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 4, 4) @ R.T + [0.3, 0.7, 0.1]
    scene, board = board_for(floor)
    samples = SampleScheme(8)
    n = len(floor)
    V = [[tuple(Fraction(float(x)) for x in v) for v in t] for t in floor]
    checked = blocked = 0
    for i in range(n):
        bits = board.blocked_samples(np.full(8, i), np.arange(8), np.arange(n), np.arange(n))
        for j in range(n):
            Q = rational_point(floor[j], [1, 1, 1])
            for k in range(8):
                P = rational_point(floor[i], samples.weights[k])
                assert bits[j, k] == any(fraction_blocked(P, Q, v) for v in V), (i, j, k)
                checked += 1
                blocked += int(bits[j, k])
    print(f"{checked} rays skimming a rotated plane, {blocked} blocked, all as exact rationals say")


@pytest.mark.parametrize("half", [False, True])
def test_wall_between_patches(half):
    """Floor and ceiling with a wall between: full wall blocks every ray; a half wall blocks
    exactly the rays whose crossing point lies on it (plain geometry as the oracle)."""
    R = rotation(11)
    shift = np.array([10.0, -3.0, 7.0])
    floor = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 2, 2)
    ceiling = rectangle([0, 0, 1], [0, 1, 0], [1, 0, 0], 2, 2)
    wall = rectangle([-0.5, -0.5, 0.5], [0, 0.85 if half else 2, 0], [2, 0, 0], 3, 3)
    tris = np.concatenate([floor, ceiling, wall]) @ R.T + shift
    scene, board = board_for(tris)
    shooters = np.arange(8)                                            # floor patches
    blocks = [BlockRay(np.full(8, i), np.arange(8), np.arange(8, 16), np.array([0])) for i in shooters]
    bits = np.stack(board.run(blocks))                                 # (shooter, R, S)
    if not half:
        assert bits.all()
    else:
        P = (SampleScheme(8).points(floor))                            # unrotated frame
        Q = ceiling.mean(axis=1)
        X = (P[:, None, :, :] + Q[None, :, None, :]) / 2               # crossing at z = 0.5
        expected = (X[..., 1] >= -0.5) & (X[..., 1] <= 0.35)
        assert 0 < expected.sum() < expected.size
        assert np.array_equal(bits, expected)
    # and without the wall nothing is blocked
    scene, board = board_for(np.concatenate([floor, ceiling]) @ R.T + shift)
    assert not np.stack(board.run(blocks)).any()


def test_registration_union_and_counters():
    """Only patches registered in the visited voxels are tested, each once per block."""
    floor = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 1, 1)
    ceiling = rectangle([0, 0, 1], [0, 1, 0], [1, 0, 0], 1, 1)
    wall = rectangle([-1, -1, 0.5], [0, 3, 0], [3, 0, 0], 1, 1)         # patches 4, 5
    tris = np.concatenate([floor, ceiling, wall])
    # voxel 0: floor + wall patch 4; voxel 1: wall patches 4 and 5 (4 in both); voxel 2: ceiling
    grid = SimpleNamespace(v=2, start=np.array([0, 3, 5]), count=np.array([3, 2, 2]),
                           patches=np.array([0, 1, 4, 4, 5, 2, 3]))
    scene, board = board_for(tris, grid=grid)
    block = lambda voxels: BlockRay(np.array([0, 1]), np.array([0, 3]), np.array([2, 3]), np.array(voxels))
    assert not board.run([block([0, 2])])[0].all()                     # half the wall is unseen
    assert board.counters()["tests"] == 4 * 5
    assert board.run([block([0, 1, 2])])[0].all()
    assert board.counters()["tests"] == 4 * 5 + 4 * 6                 # patch 4 counted once
    assert not board.run([block([2])])[0].any()
    assert board.counters()["voxels"] == 2 + 3 + 1 and board.counters()["blocks"] == 3
    assert board.run([BlockRay(np.zeros(0, int), np.zeros(0, int), np.array([2]), np.array([0]))])[0].shape == (1, 0)


def test_margin_and_prepare():
    scene, board = board_for(rectangle([0, 0, 0], [1000, 0, 0], [0, 10, 0], 1, 1))
    assert 0 < board.margin <= 1e-6 * 1000
    with pytest.raises(RuntimeError):
        GoldenBoard().run([])


# ---------------------------------------------------------------------------- closed float meshes

def _round_bits(x, bits):
    """Round to ``bits`` significant bits (so sums and midpoints below stay exact in float64)."""
    m, e = np.frexp(x)
    return np.ldexp(np.round(m * 2.0 ** bits), e - bits)


def float_icosahedron(seed):
    import itertools
    phi = (1 + 5 ** 0.5) / 2
    pts = np.array([p for s1 in (-1, 1) for s2 in (-1, 1)
                    for p in ((0, s1, s2 * phi), (s1, s2 * phi, 0), (s2 * phi, 0, s1))], float)
    faces = [f for f in itertools.combinations(range(12), 3)
             if all(abs(np.linalg.norm(pts[i] - pts[j]) - 2) < 1e-9 for i, j in itertools.combinations(f, 2))]
    faces = [f if np.cross(pts[f[1]] - pts[f[0]], pts[f[2]] - pts[f[0]]) @ pts[f[0]] > 0 else f[::-1]
             for f in faces]
    v = _round_bits(pts @ rotation(seed).T * 0.7 + [0.31, -0.17, 0.05], 30)
    return v, np.array(faces)


def float_bipyramid(seed, n=40):
    """Two fans of n triangles round two apices over a ring: many triangles share each apex."""
    rng = np.random.default_rng(seed)
    a = np.sort(rng.uniform(0, 2 * np.pi, n))
    ring = np.stack([np.cos(a), np.sin(a), rng.uniform(-0.05, 0.05, n)], axis=1)
    pts = np.concatenate([ring, [[0, 0, 1.3], [0, 0, -0.9]]])
    faces = [(i, (i + 1) % n, n) for i in range(n)] + [((i + 1) % n, i, n + 1) for i in range(n)]
    v = _round_bits(pts @ rotation(seed).T * 1.9 + [-2.3, 0.6, 1.1], 30)
    return v, np.array(faces)


@pytest.mark.parametrize("mesh", ["icosahedron", "bipyramid"])
def test_closed_float_mesh_never_leaks(mesh):
    """Segments from outside to inside a closed float mesh, passing exactly through its vertices
    (the bipyramid's apices carry fans of 40 triangles) and through points of its edges: always
    blocked, and ray by ray the board agrees with exact rational evaluation (fractions.Fraction)."""
    from fractions import Fraction
    seed = 2026 + len(mesh)
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    v, faces = float_icosahedron(seed) if mesh == "icosahedron" else float_bipyramid(seed)
    tris = v[faces]
    scene, board = board_for(tris)
    centre = v.mean(axis=0)
    edges = sorted({tuple(sorted((f[i], f[(i + 1) % 3]))) for f in faces for i in range(3)})
    through = [v[i] for i in range(len(v))] + [(v[i] + v[j]) / 2 for i, j in edges]
    through += [(3 * v[i] + v[j]) / 4 for i, j in edges[::3]]
    V = [[tuple(Fraction(float(x)) for x in p) for p in t] for t in tris]
    every = np.arange(len(tris))
    segments = leaks = 0
    for X in through:
        for _ in range(3):
            d = _round_bits((centre - X) * rng.uniform(0.05, 0.6) + rng.normal(size=3) * 0.02, 20)
            P, Q = X - d, X + d                                             # P outside, Q inside
            Pf, Qf = [tuple(Fraction(float(x)) for x in p) for p in (P, Q)]
            Xf = tuple(Fraction(float(x)) for x in X) if not isinstance(X, tuple) else X
            assert all(Pf[c] + Qf[c] == 2 * Xf[c] for c in range(3))     # X is exactly on the segment
            got = board.blocked(P[None], Q[None], every)[0, 0]
            assert got == any(fraction_blocked(Pf, Qf, t) for t in V), (P, Q)
            leaks += not got
            segments += 1
    print(f"{mesh}: {segments} segments through vertices and edges, {leaks} leaked")
    assert leaks == 0


def test_tiny_facing_triangles_beside_a_huge_one():
    """Issue 18 regression: two facing triangles 1e-3 across, 5e-5 apart, next to a triangle 1e6
    across. A tolerance scaled to the whole scene (1e-10 of 1e6 = 1e-4) took them for coplanar and
    gave the receiver B = 0; exact signs give it its first-bounce radiosity rho E F."""
    from blockray.host_driver.radiosity.formfactor import pair_factors
    from blockray.host_driver.render.render import render
    lo = np.array([[0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0]])                 # normal +z: the receiver
    hi = lo[::-1] + [0, 0, 5e-5]                                            # normal -z: the emitter
    huge = np.array([[-5e5, -5e5, -10.0], [-5e5, 5e5, -10.0], [5e5, -5e5, -10.0]])   # below, facing down
    tris = np.stack([lo, hi, huge])
    rho = np.array([[0.5, 0.4, 0.3], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]])
    E = np.array([[0, 0, 0], [1.0, 2.0, 3.0], [0, 0, 0]])
    scene = make_scene(tris, reflectance=rho, emission=E)
    result = render(scene, backend="golden", tolerance=1e-9)
    F = pair_factors(hi[None], lo[None])[0] / scene.areas[0]
    print(f"receiver B = {result.radiosity[0]}, F = {F:.6f}")
    assert F > 0.5
    np.testing.assert_allclose(result.radiosity[0], rho[0] * E[1] * F, rtol=1e-12)


def test_plane_signs_by_index_agree_with_rational_evaluation():
    """``plane_signs_of`` (the hierarchical solver's sample-in-front test) gives each rational
    point's exact side of a plane, as Fraction arithmetic does, on rotated, rounded and coplanar
    triangles: points of a triangle against its own plane and against coplanar neighbours are 0."""
    from fractions import Fraction
    from blockray.exact_float import plane_signs, plane_signs_of
    seed = 23
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    floor = np.round(rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 2, 2) @ rotation(3).T + [0.3, 0.7, 0.1], 6)
    V = np.concatenate([floor, np.round(rng.normal(size=(12, 3, 3)), 7), floor[:2] * 1e-3 + 0.5])
    M, k = 400, 5
    tri, pts = rng.integers(0, len(V), M), rng.integers(0, len(V), M)
    tri[:40], pts[:40] = pts[:40], pts[:40]                            # a triangle's own plane
    W = rng.integers(0, 50, size=(M, k, 3))
    W[:, 0] = [1, 1, 1]
    got = plane_signs_of(V, tri, pts, W)
    assert got.shape == (M, k) and (got[:40] == 0).all()
    assert np.array_equal(got, plane_signs(np.repeat(V[tri], k, axis=0), np.repeat(V[pts], k, axis=0),
                                           W.reshape(-1, 3)).reshape(M, k))
    F = lambda x: Fraction(float(x))
    for m in range(M):
        a, b, c = ([F(x) for x in v] for v in V[tri[m]])
        n = [(b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1]),
             (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2]),
             (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])]
        for j in range(k):
            w = [int(x) for x in W[m, j]]
            if sum(w) == 0:
                continue
            p = [sum(w[i] * F(V[pts[m], i, d]) for i in range(3)) / sum(w) for d in range(3)]
            side = sum(n[d] * (p[d] - a[d]) for d in range(3))
            assert got[m, j] == (side > 0) - (side < 0), (m, j)
