"""Voxel grid: registration against brute force, per-ray DDA against the segment, block rays
against their member rays, statistics and the cost model.

The references here are independent of host_driver/traverse/voxel.py: a voxel's grown box is tested by
plain comparisons over every index, a segment against a box by the slab method, and a triangle
against a box by Sutherland-Hodgman clipping. Adversarial cases use a grid with unit voxels at
the origin (lo = 0, hi = v), so grid lines, corners and faces are exact in floating point.
"""

import numpy as np
import pytest

from blockray.errors import ParameterError
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import TraversalStats, cost_model, default_voxels

SEED = 20240611


def rng_for(name):
    seed = SEED + sum(map(ord, name))
    print(f"seed={seed}")
    return np.random.default_rng(seed)


def unit_grid(v, margin=0.0):
    """An empty grid of unit voxels [0, v]^3 (grid lines, corners and faces exact in floats)."""
    return VoxelGrid(np.zeros((0, 3, 3)), v, lo=[0, 0, 0], hi=[v, v, v], margin=margin)


#: the unit grids of the adversarial tests: sizes x margins
UNIT_GRIDS = pytest.mark.parametrize("v, margin", [(v, m) for v in (1, 2, 7, 32) for m in (0.0, 0.25)])
#: a grid box of odd, unequal sides off the origin (the random tests)
ODD_LO, ODD_HI = np.array([-1.3, 2.1, 0.7]), np.array([2.9, 3.0, 5.2])


def both_ways(check, grid, pairs):
    """``check(grid, a, b)`` and ``check(grid, b, a)`` for each pair: a segment or block reversed."""
    for a, b in pairs:
        check(grid, a, b)
        check(grid, b, a)


# ---- independent references ---------------------------------------------------------------

def boxes(grid, grow):
    """(v**3, 3) lower and upper corners of every voxel box grown by ``grow``, in index order."""
    v = grid.v
    ijk = np.stack(np.meshgrid(np.arange(v), np.arange(v), np.arange(v), indexing="ij"), -1)
    ijk = ijk.reshape(-1, 3)
    assert np.array_equal((ijk[:, 0] * v + ijk[:, 1]) * v + ijk[:, 2], np.arange(v ** 3))
    s = (grid.hi - grid.lo) / v
    return grid.lo + ijk * s - grow, grid.lo + (ijk + 1) * s + grow


def voxels_holding(grid, point, grow):
    """Every voxel whose closed box grown by ``grow`` contains the point (brute force per axis)."""
    v = grid.v
    s = (grid.hi - grid.lo) / v
    i = np.arange(v)
    per_axis = [i[(grid.lo[k] + i * s[k] - grow <= point[k]) & (point[k] <= grid.lo[k] + (i + 1) * s[k] + grow)]
                for k in range(3)]
    return {(a * v + b) * v + c for a in per_axis[0] for b in per_axis[1] for c in per_axis[2]}


def segment_touch(grid, p, q, grow):
    """(v**3,) t at which the segment p->q first touches each grown voxel box, inf if never."""
    blo, bhi = boxes(grid, grow)
    d = q - p
    t0 = np.zeros(len(blo))
    t1 = np.ones(len(blo))
    for k in range(3):
        if d[k] == 0:
            inside = (blo[:, k] <= p[k]) & (p[k] <= bhi[:, k])
            t1 = np.where(inside, t1, -1.0)
        else:
            ta = (blo[:, k] - p[k]) / d[k]
            tb = (bhi[:, k] - p[k]) / d[k]
            t0 = np.maximum(t0, np.minimum(ta, tb))
            t1 = np.minimum(t1, np.maximum(ta, tb))
    return np.where(t0 <= t1, t0, np.inf)


def clip_touches(tri, blo, bhi):
    """Sutherland-Hodgman: does the triangle keep a non-empty part inside the closed box?"""
    poly = [np.asarray(x, float) for x in tri]
    for k in range(3):
        for sign, bound in ((1.0, blo[k]), (-1.0, bhi[k])):
            out = []
            for i in range(len(poly)):
                a, b = poly[i], poly[(i + 1) % len(poly)]
                fa, fb = sign * (a[k] - bound), sign * (b[k] - bound)
                if fa >= 0:
                    out.append(a)
                if (fa >= 0) != (fb >= 0):
                    out.append(a + (b - a) * (fa / (fa - fb)))
            poly = out
            if not poly:
                return False
    return True


def registered(grid):
    """Set of (voxel, patch) pairs, also checking the CSR invariants."""
    assert grid.start.shape == grid.count.shape == (grid.v ** 3,)
    assert grid.start.dtype == grid.count.dtype == grid.patches.dtype == np.int64
    assert np.array_equal(grid.start, np.concatenate([[0], np.cumsum(grid.count)[:-1]]))
    assert grid.count.sum() == len(grid.patches)
    pairs = set()
    for vox in range(grid.v ** 3):
        pl = grid.patches_in(vox)
        assert np.all(np.diff(pl) > 0), "patches ascending and unique within a voxel"
        pairs.update((vox, int(p)) for p in pl)
    return pairs


# ---- rays ---------------------------------------------------------------------------------

def adversarial_rays(rng, v):
    """Segments on a grid with unit voxels [0, v]^3: grid lines, corners, faces, boundary."""
    ints = lambda n: rng.integers(0, v + 1, size=(n, 3)).astype(float)
    rays = []
    for _ in range(6):
        a, b = ints(1)[0], ints(1)[0]
        rays.append((a, b))                                   # corner to corner (diagonals)
        c = a.copy(); k = rng.integers(3); c[k] = rng.uniform(-1, v + 1)
        rays.append((a, c))                                   # along a grid line
        e = b.copy(); e[k] = a[k]
        rays.append((a, e))                                   # in a grid plane, corner to corner
        h = a + 0.5; h2 = h.copy(); h2[k] = v - h[k]
        rays.append((h, h2))                                  # axis aligned through voxel centres
        rays.append((a, a.copy()))                            # zero length on a corner
        f = rng.uniform(0, v, 3); f[k] = float(rng.integers(0, v + 1))
        rays.append((f, f.copy()))                            # zero length on a face
        g = rng.uniform(0, v, 3); g2 = rng.uniform(0, v, 3); g[k] = g2[k] = float(rng.integers(0, v + 1))
        rays.append((g, g2))                                  # within a face plane
        bd = rng.uniform(0, v, 3); bd2 = rng.uniform(0, v, 3); bd[k] = bd2[k] = v * rng.integers(2)
        rays.append((bd, bd2))                                # on the grid boundary
        out = rng.uniform(-2, v + 2, 3); out2 = rng.uniform(-2, v + 2, 3)
        rays.append((out, out2))                              # partly or wholly outside
        # through an interior corner at an irrational-looking slope (exact tie mid-segment)
        corner = ints(1)[0]
        dirn = rng.integers(-3, 4, 3).astype(float)
        rays.append((corner - dirn * 0.5, corner + dirn * 0.75))
    return rays


def check_dda(grid, p, q):
    m, tol = grid.margin, grid.tolerance
    vox = grid.ray_voxels(p, q)
    assert vox.dtype == np.int64
    assert len(set(vox.tolist())) == len(vox), "no voxel twice"
    got = set(vox.tolist())
    # every voxel the segment touches (grown by margin) is visited ...
    t_exact = segment_touch(grid, p, q, m)
    assert set(np.flatnonzero(np.isfinite(t_exact)).tolist()) <= got, (p, q)
    # ... and only voxels it touches, allowing the rounding tolerance
    t_loose = segment_touch(grid, p, q, m + 3 * tol)
    assert got <= set(np.flatnonzero(np.isfinite(t_loose)).tolist()), (p, q)
    # dense points along the segment: each point's voxels (all, on boundaries) are visited
    for t in np.concatenate([np.linspace(0, 1, 41), [0.5 ** 20, 1 - 0.5 ** 20]]):
        assert voxels_holding(grid, p + t * (q - p), m) <= got, (p, q, t)
    # in visiting order: first-touch parameters never decrease
    first = t_loose[vox]
    assert np.all(np.diff(first) >= -1e-9), (p, q)
    return got


@UNIT_GRIDS
def test_dda_adversarial(v, margin):
    both_ways(check_dda, unit_grid(v, margin), adversarial_rays(rng_for(f"dda-adv-{v}-{margin}"), v))


@pytest.mark.parametrize("v", [1, 2, 7, 32])
def test_dda_random(v):
    rng = rng_for(f"dda-rand-{v}")
    lo, hi = ODD_LO, ODD_HI
    for margin in (0.0, 0.013):
        grid = VoxelGrid(np.zeros((0, 3, 3)), v, lo=lo, hi=hi, margin=margin)
        for _ in range(15):
            span = hi - lo
            p = lo + rng.uniform(-0.1, 1.1, 3) * span
            q = lo + rng.uniform(-0.1, 1.1, 3) * span
            check_dda(grid, p, q)


def test_dda_known_path():
    """A hand-worked case: the segment (0.5,0.5) -> (3.5,1.5) crosses y = 1 exactly at x = 2."""
    grid = unit_grid(4)
    ijk = grid.ijk_of(grid.ray_voxels([0.5, 0.5, 0.5], [3.5, 1.5, 0.5]))
    assert sorted(ijk.tolist()) == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 0, 0], [2, 1, 0], [3, 1, 0]]
    assert ijk[0].tolist() == [0, 0, 0] and ijk[-1].tolist() == [3, 1, 0]


# ---- block rays ---------------------------------------------------------------------------

def bundles(rng, v):
    """Start and end point sets: random, adversarial, degenerate, huge and tiny."""
    u = lambda n, a=0.0, b=float(v): rng.uniform(a, b, size=(n, 3))
    ints = lambda n: rng.integers(0, v + 1, size=(n, 3)).astype(float)
    out = []
    cell = rng.integers(0, v, 3)
    out.append((u(1), cell + rng.uniform(0, 1, (6, 3))))                 # one shooter, one end voxel
    out.append((u(1).repeat(4, 0) + rng.normal(0, 0.05, (4, 3)), cell + rng.uniform(0, 1, (5, 3))))
    out.append((u(8), u(8)))                                              # huge bundle
    out.append((ints(3), ints(3)))                                       # corners to corners
    c = ints(1)
    out.append((c, c.copy()))                                             # zero-length ray on a corner
    out.append((c, c + np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]]) * v))  # along grid lines
    a = u(1); b = a.copy(); k = rng.integers(3); b[0, k] = v - a[0, k]
    out.append((a, b))                                                    # axis aligned
    out.append((a, np.concatenate([b, a])))                               # one zero-length member
    e = u(4); e[:, k] = float(rng.integers(0, v + 1))
    out.append((u(2), e))                                                 # ends on one grid plane
    bd = u(3); bd[:, k] = v
    out.append((u(2), bd))                                                # ends on the boundary
    tiny = u(1)
    out.append((tiny, tiny + rng.normal(0, 1e-9, (3, 3))))               # tiny bundle
    out.append((u(2, -2, v + 2), u(3, -2, v + 2)))                       # partly outside
    return out


def check_block(grid, starts, ends):
    vox = grid.block_voxels(starts, ends)
    assert vox.dtype == np.int64
    assert len(set(vox.tolist())) == len(vox), "no voxel twice"
    got = set(vox.tolist())
    need = set()
    for p in starts:
        for q in ends:
            ray = set(grid.ray_voxels(p, q).tolist())
            # the DDA is checked against the segment by the DDA tests; here check it is exact too
            t = segment_touch(grid, p, q, grid.margin)
            assert set(np.flatnonzero(np.isfinite(t)).tolist()) <= ray
            need |= ray
    missing = need - got
    assert not missing, f"block misses {sorted(missing)[:5]} for starts {starts} ends {ends}"
    # march order: the slab index along the march axis moves one way only
    axis = grid.block_axis(starts, ends)
    slab = grid.ijk_of(vox)[:, axis]
    steps = np.diff(slab)
    assert np.all(steps >= 0) or np.all(steps <= 0)
    return got, need


@UNIT_GRIDS
def test_block_covers_member_rays(v, margin):
    both_ways(check_block, unit_grid(v, margin), bundles(rng_for(f"block-{v}-{margin}"), v))


def test_block_random_grid():
    rng = rng_for("block-random-grid")
    lo, hi = ODD_LO, ODD_HI
    for v in (2, 7, 32):
        grid = VoxelGrid(np.zeros((0, 3, 3)), v, lo=lo, hi=hi, margin=0.004)
        for _ in range(6):
            S, R = rng.integers(1, 5), rng.integers(1, 7)
            starts = lo + rng.uniform(0, 1, (S, 3)) * (hi - lo)
            ends = grid.box_of([rng.integers(v ** 3)])[0] + rng.uniform(0, 1, (R, 3)) * grid.voxel_size
            check_block(grid, starts, ends)


def test_block_of_one_axis_ray_is_its_dda():
    """A single ray along an axis through voxel centres: the block adds nothing."""
    grid = unit_grid(7)
    got, need = check_block(grid, np.array([[0.5, 3.5, 2.5]]), np.array([[6.5, 3.5, 2.5]]))
    assert got == need and len(got) == 7


# ---- registration -------------------------------------------------------------------------

def check_registration_exact(grid, tri):
    """Two-sided comparison with clipping, over every (triangle, voxel) pair."""
    pairs = registered(grid)
    tight_lo, tight_hi = boxes(grid, grid.margin)
    loose_lo, loose_hi = boxes(grid, grid.margin + 3 * grid.tolerance)
    for t in range(len(tri)):
        for vox in range(grid.v ** 3):
            if (vox, t) in pairs:
                assert clip_touches(tri[t], loose_lo[vox], loose_hi[vox]), (t, vox)
            else:
                assert not clip_touches(tri[t], tight_lo[vox], tight_hi[vox]), (t, vox)


@pytest.mark.parametrize("v", [1, 2, 7])
def test_registration_random_triangles(v):
    rng = rng_for(f"reg-{v}")
    lo, hi = np.array([-1.0, 0.5, 2.0]), np.array([3.0, 2.0, 4.5])
    centre = lo + rng.uniform(0, 1, (40, 1, 3)) * (hi - lo)
    tri = centre + rng.normal(0, 0.4, (40, 3, 3)) * (hi - lo) / 4
    tri = np.clip(tri, lo, hi)
    for margin in (0.0, 0.07):
        grid = VoxelGrid(tri, v, lo=lo, hi=hi, margin=margin)
        check_registration_exact(grid, tri)


def adversarial_triangles(rng, v):
    ints = lambda: rng.integers(0, v + 1, 3).astype(float)
    tris = []
    for _ in range(8):
        k = rng.integers(3)
        t = rng.uniform(0, v, (3, 3)); t[:, k] = float(rng.integers(0, v + 1))
        tris.append(t)                                   # in a grid plane (on voxel faces)
        c = ints(); t = c + rng.uniform(0, 1, (3, 3)) * (rng.integers(0, 2, 3) * 2 - 1)
        t[0] = c
        tris.append(t)                                   # touches a voxel corner with a vertex
        a, b = ints(), ints()
        tris.append(np.array([a, b, a + rng.uniform(0, 1, 3)]))    # an edge between lattice points
        tris.append(np.array([ints(), ints(), ints()]))            # lattice corners only
        t = rng.uniform(0, v, (3, 3)); t[:, k] = v * rng.integers(2)
        tris.append(t)                                   # on the grid boundary
        p = rng.uniform(0, v, 3)
        tris.append(np.array([p, p + rng.uniform(-1, 1, 3), p + 1e-7 * rng.uniform(-1, 1, 3)]))  # sliver
    return np.clip(np.array(tris), 0, v)


@pytest.mark.parametrize("v", [1, 2, 7])
@pytest.mark.parametrize("margin", [0.0, 0.25])
def test_registration_adversarial(v, margin):
    rng = rng_for(f"reg-adv-{v}-{margin}")
    tri = adversarial_triangles(rng, v)
    grid = VoxelGrid(tri, v, lo=[0, 0, 0], hi=[v, v, v], margin=margin)
    check_registration_exact(grid, tri)
    # dense point sampling: each point's voxels (all of them, on boundaries) list the triangle
    pairs = registered(grid)
    w = rng.dirichlet([1, 1, 1], 60)
    w = np.concatenate([w, np.eye(3), [[0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]]])
    for t, corners in enumerate(tri):
        for point in w @ corners:
            for vox in voxels_holding(grid, point, margin):
                assert (vox, t) in pairs, (t, vox, point)


def test_registration_v32_sampled():
    """v = 32: every registered pair really touches; sampled points find their triangle."""
    rng = rng_for("reg-32")
    tri = rng.uniform(0, 1, (300, 1, 3)) * 10 + rng.normal(0, 0.6, (300, 3, 3))
    grid = VoxelGrid(tri, 32, margin=0.02)
    pairs = registered(grid)
    loose_lo, loose_hi = boxes(grid, grid.margin + 3 * grid.tolerance)
    listed = sorted(pairs)
    for n in rng.choice(len(listed), 500, replace=False):
        vox, t = listed[n]
        assert clip_touches(tri[t], loose_lo[vox], loose_hi[vox])
    w = rng.dirichlet([1, 1, 1], 40)
    for t in range(0, 300, 7):
        for point in w @ tri[t]:
            for vox in voxels_holding(grid, point, grid.margin):
                assert (vox, t) in pairs


def test_registration_is_not_the_bounding_box():
    """A long thin diagonal triangle is registered along its diagonal only."""
    v = 8
    tri = np.array([[[0, 0, 0.5], [8, 8, 0.5], [8, 7.9, 0.5]]])
    grid = VoxelGrid(tri, v, lo=[0, 0, 0], hi=[8, 8, 8])
    ijk = grid.ijk_of(np.flatnonzero(grid.count))
    assert np.all(ijk[:, 2] == 0)
    assert np.all(np.abs(ijk[:, 0] - ijk[:, 1]) <= 1)
    assert len(ijk) < 3 * v


# ---- indexing and parameters --------------------------------------------------------------

def test_indexing_and_clamping():
    grid = VoxelGrid(np.zeros((0, 3, 3)), 7, lo=[0, 0, 0], hi=[7, 14, 21])
    pts = np.array([[1.5, 2.5, 20.0], [-3, 100, 0], [7, 14, 21]])
    assert grid.cell_of(pts).tolist() == [[1, 1, 6], [0, 6, 0], [6, 6, 6]]
    assert grid.voxel_of(pts).tolist() == [(1 * 7 + 1) * 7 + 6, (0 * 7 + 6) * 7 + 0, 342]
    assert np.array_equal(grid.ijk_of(grid.voxel_of(pts)), grid.cell_of(pts))
    groups = grid.group_points(np.array([[0.5, 0.5, 0.5], [6.9, 13.9, 20.9], [0.1, 0.1, 0.1]]))
    assert [(g, idx.tolist()) for g, idx in groups] == [(0, [0, 2]), (342, [1])]


def test_default_box_of_a_flat_scene():
    tri = np.array([[[0, 0, 1.0], [2, 0, 1.0], [0, 3, 1.0]]])
    grid = VoxelGrid(tri, 4)
    assert np.all(grid.voxel_size > 0)
    assert grid.lo[2] < 1.0 < grid.hi[2]
    assert np.all(grid.count[grid.voxel_of(tri[0])] == 1)


def test_parameter_errors():
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 1.0]]])
    for bad in (0, 257, 2.5, True):
        with pytest.raises(ParameterError, match="voxels"):
            VoxelGrid(tri, bad)
    with pytest.raises(ParameterError, match="margin"):
        VoxelGrid(tri, 2, margin=-1)
    with pytest.raises(ParameterError, match="inside"):
        VoxelGrid(tri, 2, lo=[0, 0, 0], hi=[0.5, 1, 1])
    with pytest.raises(ParameterError, match="shape"):
        VoxelGrid(np.zeros((3, 3)), 2)


# ---- statistics and cost model ------------------------------------------------------------

def test_traversal_stats_hand_worked():
    """v = 4 on [0,4]^3, one triangle x, y >= 0, x + y <= 4 in the plane z = 0.5: it touches the
    voxels (i, j, 0) with i + j <= 4 (closed boxes: (3, 1, 0) at its corner), once each."""
    tri = np.array([[[0.0, 0.0, 0.5], [4.0, 0.0, 0.5], [0.0, 4.0, 0.5]]])
    grid = VoxelGrid(tri, 4, lo=[0, 0, 0], hi=[4, 4, 4])
    stats = TraversalStats(grid)
    # block 1: one ray along x at y = z = 0.5: 4 voxels, each holding the triangle once
    starts, ends = np.array([[0.5, 0.5, 0.5]]), np.array([[3.5, 0.5, 0.5]])
    stats.add_block(grid.block_voxels(starts, ends), starts, ends, sample=True)
    assert (stats.l, stats.n, stats.L, stats.overhead, stats.test_overhead) == (4, 1, 1, 1, 1)
    # block 2: rays to y rows 0 and 1 from one start. The second ray, y = 0.5 + (x - 0.5) / 3,
    # crosses y = 1 exactly at x = 2 (a corner tie): it needs (0,0) (1,0) (1,1) (2,0) (2,1) (3,1).
    # The block's cross-section is y in [0.5, 0.67] in slab x = 0 and reaches y >= 1 from slab 1 on.
    ends = np.array([[3.5, 0.5, 0.5], [3.5, 1.5, 0.5]])
    block = grid.block_voxels(starts, ends)
    assert sorted(map(tuple, grid.ijk_of(block).tolist())) == [
        (0, 0, 0), (1, 0, 0), (1, 1, 0), (2, 0, 0), (2, 1, 0), (3, 0, 0), (3, 1, 0)]
    stats.add_block(block, starts, ends, sample=True)
    # totals: DDA voxels 4 + (4 + 6) = 14 over 3 rays; block voxel-rays 4*1 + 7*2 = 18
    assert stats.l == pytest.approx(14 / 3)
    assert stats.overhead == pytest.approx(18 / 14)
    assert stats.L == pytest.approx(1.5)
    assert stats.n == 1
    assert stats.summary()["rays"] == 3 and stats.summary()["blocks"] == 2


def test_traversal_stats_sampling_is_seeded():
    grid = unit_grid(4)
    runs = []
    for _ in range(2):
        stats = TraversalStats(grid, sample_fraction=0.3, seed=5)
        for _ in range(50):
            stats.add_block(np.array([0]), [[0.5, 0.5, 0.5]], [[3.5, 3.5, 3.5]])
        runs.append(stats.sampled_blocks)
    assert runs[0] == runs[1] and 0 < runs[0] < 50


def test_cost_model_formula():
    # v = 1, N = 1: n = 1, l = 2.9, L = 0.43
    assert cost_model(1, 1) == pytest.approx(2.9 * 0.02 + (9.6 + 1.9 * 0.4) / 0.43)
    # v = 4, N = 3200, parallelism 8: v^2.5 = 32, n = 100, l = 11.6, L = 43
    assert cost_model(4, 3200, 8) == pytest.approx(100 * 11.6 * 0.02 / 8 + (9.6 + 10.6 * 0.4) / 43)


def test_default_voxels_minimises_the_model():
    for n in (1, 30, 3013, 30000):
        for par in (1, 8, 512):
            v = default_voxels(n, parallelism=par)
            assert 1 <= v <= 64
            costs = cost_model(np.arange(1, 65), n, par)
            assert costs[v - 1] == costs.min()
    assert default_voxels(30000) >= default_voxels(3013) >= default_voxels(300)
    assert default_voxels(3013, parallelism=512) <= default_voxels(3013)


def test_block_voxels_many_matches_single_calls(monkeypatch):
    """A batch (cut into sub-batches of a few blocks, as a large one is) equals the blocks one by one."""
    from blockray.host_driver.traverse import voxel
    rng = rng_for("block-many")
    for v, margin in ((1, 0.0), (2, 0.25), (7, 0.0), (32, 0.1)):
        grid = unit_grid(v, margin)
        blocks = bundles(rng, v) + [(e, s) for s, e in bundles(rng, v)] + [(np.zeros((0, 3)), np.ones((2, 3)))]
        single = [grid.block_voxels(s, e) for s, e in blocks]
        monkeypatch.setattr(voxel, "_SLAB_ROWS", 3 * v)
        many = grid.block_voxels_many(blocks)
        monkeypatch.undo()
        assert len(many) == len(blocks)
        for (starts, ends), got, one in zip(blocks, many, single):
            assert np.array_equal(got, one), (starts, ends)
