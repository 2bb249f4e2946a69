"""Shooter sample points drawn per patch (``SampleScheme(seed=)``, ``--sample-points draw``).

Oracles written here: the cell of a barycentric point in the triangle's 4 x 4 congruent cells
(row by row, from the point's coordinates), the exact predicate on sample points computed here from
the weights, and a shooter whose contact shadow has a closed form (a shelf resting on a wall: a
ray from height y on the wall clears the shelf's front edge exactly when y is above a line)."""

from types import SimpleNamespace

import numpy as np
import pytest

from blockray.errors import ParameterError
from blockray.exact import blocked_reference, patch_normals
from blockray.board import BlockRay
from blockray.host_driver.board.golden import GoldenBoard
from blockray.host_driver.radiosity import ray_weights
from blockray.host_driver.render.options import RenderOptions
from blockray.host_driver.traverse.endpoints import EndPoints
from blockray.host_driver.traverse.visibility import Visibility, visible_fraction
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.sim.model import ModelBoard

from board_scenes import scattered_scene
from scenes import make_scene


def _cell(weights, D, n=4):
    """Index of the cell (of n x n, row by row, up and down cells alternating) holding the point of
    barycentric ``weights`` / D, from its coordinates: x = n (b1 + b2) picks the row, y = n b2 the
    column, and a down cell is the one above the diagonal y - a = x - row."""
    b = np.asarray(weights, dtype=np.float64) / D
    x, y = n * (b[..., 1] + b[..., 2]), n * b[..., 2]
    row, a = np.floor(x).astype(int), np.floor(y).astype(int)
    down = (y - a) > (x - row)
    return row * row + 2 * a + down


@pytest.mark.parametrize("count, lattice", [(8, 1), (8, 8), (16, 2), (5, 4), (1, 1), (64, 8)])
def test_drawn_weights_are_allowed_lattice_points_one_per_stratum(count, lattice):
    scheme = SampleScheme(count, lattice, seed=11)
    D, p = scheme.denominator, scheme.prime
    W = scheme.weights_of(np.arange(500))
    assert W.shape == (500, count, 3)
    assert (W.sum(axis=2) == D).all() and (W >= 1).all() and (W % p != 0).all()
    n = max(4, int(np.sqrt(count)))                  # cells a side: 4, finer for more than 16 strata
    cell = _cell(W, D, n)
    k = np.arange(count)
    # stratum k is [k, k + 1) / K of the area: the cells it overlaps, of n^2 equal ones
    lo, hi = np.floor(n * n * k / count).astype(int), np.ceil(n * n * (k + 1) / count).astype(int) - 1
    assert ((cell >= lo) & (cell <= hi)).all()
    if count > 1:                                                 # (one point of 132 allowed repeats)
        assert len({tuple(w.ravel()) for w in W}) == 500          # every patch its own points


def test_drawn_points_are_uniform_and_reach_the_edge_strip():
    """Over many patches the points cover the triangle evenly, the strip along its edges included
    (the fixed pattern never goes there)."""
    scheme = SampleScheme(8, 8, seed=5)
    b = scheme.weights_of(np.arange(5000)).reshape(-1, 3) / scheme.denominator
    np.testing.assert_allclose(b.mean(axis=0), 1 / 3, atol=0.005)
    strip = (b.min(axis=1) < 0.05).mean()            # area within 0.05 of an edge: 1 - (1 - 3 x 0.05)^2
    print(f"share of drawn points in the strip {strip:.4f} (its area {1 - 0.85 ** 2:.4f})")
    assert abs(strip - (1 - 0.85 ** 2)) < 0.01
    fixed = SampleScheme(8, 8).weights / SampleScheme(8, 8).denominator
    assert (fixed.min(axis=1) >= 0.05).all()


def test_a_patch_draws_the_same_points_in_any_batch_and_seeds_differ():
    scheme = SampleScheme(8, 2, seed=3)
    W = scheme.weights_of(np.arange(40))
    np.testing.assert_array_equal(scheme.weights_of(np.arange(40)[::-1]), W[::-1])
    np.testing.assert_array_equal(scheme.weights_of([17])[0], W[17])
    assert (SampleScheme(8, 2, seed=4).weights_of(np.arange(40)) != W).any()
    V = scattered_scene(3).patch_vertices
    np.testing.assert_array_equal(scheme.points(V[[5, 9]], [5, 9]), scheme.points(V)[[5, 9]])
    with pytest.raises(ParameterError):
        scheme.weights                                  # no one pattern: each patch has its own


@pytest.mark.parametrize("sets", [1, 3])
def test_boards_cast_from_each_patchs_drawn_points(sets):
    """The golden board and the model test rays from the points the drawn weights give (exact
    predicate on points computed here from the weights), every set's points with ``sets``."""
    seed = 41
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    scheme = SampleScheme(8, 2, seed=9, sets=sets)
    D = scheme.denominator
    V = (rng.integers(0, 6, (30, 1, 3)) + rng.integers(-2, 3, (30, 3, 3))) * D
    V = V[np.linalg.norm(patch_normals(V), axis=1) > 0]
    golden = GoldenBoard()
    golden.prepare(make_scene(V), scheme)
    golden.load(SimpleNamespace(v=1, start=np.array([0]), count=np.array([len(V)]), patches=np.arange(len(V))))
    total = blocked = 0
    for _ in range(8):
        sp, ss = rng.integers(0, len(V), 5), rng.integers(0, scheme.per_patch, 5)
        blk = BlockRay(sp, ss, rng.integers(0, len(V), 6), np.array([0]))
        bits = golden.run([blk])[0]
        P = [(scheme.weights_of([i])[0][k][:, None] * V[i]).sum(0) // D for i, k in zip(sp, ss)]
        Q = V[blk.receiver_patch].sum(axis=1) // 3
        ref = [[any(blocked_reference(p.tolist(), q.tolist(), *v.tolist()) for v in V) for p in P] for q in Q]
        np.testing.assert_array_equal(bits, ref)
        total, blocked = total + bits.size, blocked + int(bits.sum())
    assert 0.1 * total < blocked < 0.9 * total
    scene = scattered_scene(4)
    model = ModelBoard(BoardParams(rows=4, cols=3, boards=1, bits=14))
    model.prepare(scene, scheme)
    q = model.quantised
    for i in range(scene.patches):
        W = scheme.weights_of([i])[0]
        np.testing.assert_array_equal(q.shooters[i], (W[:, :, None] * q.vertices[i][None]).sum(1) // D)


def test_ray_weights_take_each_patchs_own_points():
    """A sample counts only in front of the receiver's plane: with drawn points, the test is made
    on each shooter's own points (signs computed here in integers)."""
    scheme = SampleScheme(8, 4, seed=2)
    scene = scattered_scene(6, n=20)
    V = scene.patch_vertices
    for i in range(0, scene.patches, 4):
        J = np.array([j for j in range(scene.patches) if j != i])
        front = ray_weights.samples_in_front(scene, scheme, i, J)
        w = ray_weights.pair_sample_weights(scene, scheme, np.full(len(J), i), J)
        X = scheme.points(V[i][None], [i])[0]
        n = np.cross(V[J, 1] - V[J, 0], V[J, 2] - V[J, 0])
        side = np.einsum("jc,kjc->jk", n, X[:, None] - V[J, 0][None])
        ok = np.abs(side) > 1e-9 * np.abs(n).sum(1)[:, None]
        np.testing.assert_array_equal(front[ok], (side > 0)[ok])
        assert ((w > 0) <= front).all()


def _shelf_scene(shelf_depth=0.2):
    """A wall shooter (patch 0, plane x = 0, facing +x, from y = 1 to 1.6) with a shelf resting on
    the wall along its lower edge (y = 1, from x = 0 to ``shelf_depth``, z in [-3, 3], facing up),
    and small receivers facing the wall at x = 2, at heights from 0.2 to 0.95."""
    wall = [[0, 1, 0.3], [0, 1, -0.3], [0, 1.6, 0.0]]
    d = shelf_depth
    shelf = [[[0, 1, -3], [0, 1, 3], [d, 1, 3]], [[0, 1, -3], [d, 1, 3], [d, 1, -3]]]
    heights = np.linspace(0.2, 0.95, 12)
    recv = [[[2, y - 0.01, 0.01], [2, y + 0.01, 0.0], [2, y - 0.01, -0.01]] for y in heights]
    return make_scene(np.array([wall] + shelf + recv, dtype=np.float64)), heights


def _clear_share(heights, d, n=400):
    """Clear share of each receiver (small, at x = 2, height h, z = 0) as seen from the wall
    triangle, weighted by the kernel: a ray from (0, y, z) to (2, h, 0) meets the shelf's plane
    y = 1 at x = 2 (y - 1) / (y - h), on the shelf when that is <= d, so it is clear exactly when
    y > (2 - d h) / (2 - d). Midpoint rule on the triangle's n x n cells."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    keep = i + j < n
    u, v = (i[keep] + 1 / 3) / n, (j[keep] + 1 / 3) / n
    k2 = i[i + j < n - 1], j[i + j < n - 1]
    u = np.concatenate([u, (k2[0] + 2 / 3) / n]); v = np.concatenate([v, (k2[1] + 2 / 3) / n])
    A, B, C = np.array([0, 1, 0.3]), np.array([0, 1, -0.3]), np.array([0, 1.6, 0.0])
    P = A + u[:, None] * (B - A) + v[:, None] * (C - A)
    out = []
    for h in heights:
        dv = np.array([2.0, h, 0.0]) - P
        k = dv[:, 0] ** 2 / (dv * dv).sum(1) ** 2          # cos_i cos_j / r^2 up to constants: both normals along x
        out.append(k[P[:, 1] > (2 - d * h) / (2 - d)].sum() / k.sum())
    return np.array(out)


def _golden_fraction(scene, scheme, i, receivers, ends=None):
    """visible_fraction of shooter i's pairs with ``receivers`` on the golden board (a 4 x 4
    array), and the rays it cast."""
    board = GoldenBoard()
    board.prepare(scene, scheme)
    grid = VoxelGrid(scene.patch_vertices, 2, margin=board.margin)
    board.load(grid)
    vis = Visibility(scene, board, grid, scheme, rows=4, cols=4, ends=ends)
    return visible_fraction(scene, vis, scheme, i, np.asarray(receivers), vis.phases), board.counters()["rays"]


def _estimate(scene, scheme, draws=1, seed=0):
    ends = EndPoints(scene, scheme, "draw", seed, draws) if draws > 1 else None
    return _golden_fraction(scene, scheme, 0, np.arange(3, scene.patches), ends)[0]


def test_drawn_samples_see_a_contact_shadow_in_proportion():
    """The fixed pattern misjudges how much of the shooter the shelf hides from each receiver (the
    shadow is a strip along the contact line); the drawn points, averaged over seeds, agree with
    the closed form."""
    scene, heights = _shelf_scene()
    truth = _clear_share(heights, 0.2)
    assert ((truth > 0.02) & (truth < 0.98)).sum() >= 6             # the shadow line crosses the shooter
    fixed = _estimate(scene, SampleScheme(16, 8))
    seeds = range(300)
    drawn = np.array([_estimate(scene, SampleScheme(16, 8, seed=s)) for s in seeds])
    mean, err = drawn.mean(axis=0), drawn.std(axis=0) / np.sqrt(len(seeds))
    print("truth", np.round(truth, 3), "\nfixed", np.round(fixed, 3), "\ndrawn", np.round(mean, 3),
          "\nstd err", np.round(err, 3))
    assert np.abs(fixed - truth).max() > 0.1                     # the bias the drawn points remove
    assert (np.abs(mean - truth) < 4 * err + 0.01).all()
    assert abs((mean - truth).mean()) < 0.01


@pytest.mark.parametrize("count, sets, cells", [(8, 8, 8), (8, 4, 5), (4, 2, 4)])
def test_row_sets_are_stratified_together(count, sets, cells):
    """``sets`` sets of K points per patch (``--sample-points rows``): point d K + k lies in
    stratum k sets + d of the K sets equal-area strata (isqrt(K sets) cells a side, at least 4),
    so each set spreads over the whole triangle and together they fill every stratum once."""
    scheme = SampleScheme(count, 8, seed=11, sets=sets)
    D, S = scheme.denominator, count * sets
    W = scheme.weights_of(np.arange(300))
    assert W.shape == (300, S, 3) and scheme.per_patch == S
    assert (W.sum(axis=2) == D).all() and (W >= 1).all() and (W % scheme.prime != 0).all()
    cell = _cell(W, D, cells)
    t = np.arange(S)
    stratum = (t % count) * sets + t // count
    lo = np.floor(cells ** 2 * stratum / S).astype(int)
    hi = np.ceil(cells ** 2 * (stratum + 1) / S).astype(int) - 1
    assert ((cell >= lo) & (cell <= hi)).all()
    np.testing.assert_array_equal(SampleScheme(count, 8, seed=11, sets=1).weights_of(np.arange(300)),
                                  SampleScheme(count, 8, seed=11).weights_of(np.arange(300)))
    with pytest.raises(ParameterError):
        SampleScheme(count, 8, sets=2)                     # sets are drawn


def test_each_row_of_a_pair_casts_from_its_own_set():
    """The shelf of the contact-shadow test with 4 rows per pair: row d's rays start at set d, so
    a pair's estimate averages 4 K points (the closed form within four standard errors), and its
    spread over seeds is well below the one of 4 rows sharing one drawn set."""
    scene, heights = _shelf_scene()
    truth = _clear_share(heights, 0.2)
    seeds = range(120)
    shared = np.array([_estimate(scene, SampleScheme(8, 8, seed=s), 4, s) for s in seeds])
    rows = np.array([_estimate(scene, SampleScheme(8, 8, seed=s, sets=4), 4, s) for s in seeds])
    mean, err = rows.mean(axis=0), rows.std(axis=0) / np.sqrt(len(seeds))
    lit = (truth > 0.02) & (truth < 0.98)
    ratio = rows.std(axis=0)[lit] / shared.std(axis=0)[lit]
    print("truth", np.round(truth, 3), "\nrows", np.round(mean, 3), "\nstd err", np.round(err, 4),
          "\nspread rows / shared", np.round(ratio, 2))
    assert (np.abs(mean - truth) < 4 * err + 0.01).all()
    assert np.median(ratio) < 0.7


def test_sample_points_option():
    o = RenderOptions.of(sample_points="draw", sample_seed=7, end_lattice=8)
    assert o.ray.samples == SampleScheme(8, 8, seed=7)
    assert o.with_(sample_seed=8).ray.samples == SampleScheme(8, 8, seed=8)
    assert RenderOptions.of(samples=SampleScheme(4, seed=3)).ray.sample_points == "draw"
    assert RenderOptions.of().ray.samples == SampleScheme(8)
    rows = RenderOptions.of(sample_points="rows", sample_seed=7, end_points="draw", end_lattice=8, end_draws=4)
    assert rows.ray.samples == SampleScheme(8, 8, seed=7, sets=4)
    assert RenderOptions.of(samples=SampleScheme(8, 8, seed=3, sets=2), end_points="draw", end_draws=2
                            ).ray.sample_points == "rows"
    assert RenderOptions.of(sample_points="draw", solver="hierarchical").ray.samples.drawn   # every element draws
    for bad, name in ((dict(sample_points="random"), "sample_points"),
                      (dict(sample_points="draw", sample_seed=-1), "sample_seed"),
                      (dict(sample_points="rows", solver="hierarchical"), "sample_points"),
                      (dict(end_lattice=8), "end_lattice")):
        with pytest.raises(ParameterError) as e:
            RenderOptions.of(**bad)
        assert e.value.parameter == name, bad


def _straddling_scene():
    """Shooter 0: a floor-like triangle at y = 1 facing up, beside a wall (x = 0). Receiver 1: a wall
    triangle from y = 0.3 to 1.3, its centroid below the shooter's plane (reverse rays) and only its
    top tip (9% of it) in front. Patches 2, 3: a plate at x = 0.1 below y = 0.98, which hides the
    shooter from the wall's part below its plane, never from the tip."""
    shooter = [[0.02, 1, 0.2], [0.3, 1, 0], [0.02, 1, -0.2]]
    wall = [[0, 0.3, -0.3], [0, 1.3, 0], [0, 0.3, 0.3]]
    plate = [[[0.1, 0, -1], [0.1, 0.98, -1], [0.1, 0.98, 1]], [[0.1, 0, -1], [0.1, 0.98, 1], [0.1, 0, 1]]]
    return make_scene(np.array([shooter, wall] + plate, dtype=np.float64))


def test_a_straddling_receivers_reverse_rows_cast_from_every_set():
    """The light the shooter sends reaches only the wall's tip, which nothing hides: the clear
    fraction is 1. The reverse rays start at the wall's samples; one set of K often has none in
    the tip, and its rays (all through the plate) would give 0. With a set per row every set casts,
    and the rows are pooled by the light their samples carry."""
    scene = _straddling_scene()
    assert not ray_weights.centroid_in_front(scene, 0, [1])[0]          # the reverse path
    got = []
    for seed in range(30):
        scheme = SampleScheme(8, 8, seed=seed, sets=8)
        got.append(_golden_fraction(scene, scheme, 0, [1], EndPoints(scene, scheme, "draw", seed, 8))[0][0])
    print("seeds 0-29: clear fraction", np.round(got, 3))
    np.testing.assert_array_equal(got, 1.0)


def test_an_emitters_reverse_rows_cast_each_set_once():
    """An emitting shooter's pair with a straddling receiver takes the reverse rays, which all end
    at the shooter's centroid: ``emitter_factor`` 4 casts each of the receiver's sets once, the
    same rays and the same fraction as factor 1 (repeating them would add no information)."""
    E = np.zeros((4, 3))
    E[0] = 1.0
    scene = make_scene(_straddling_scene().patch_vertices.astype(np.float64), emission=E)
    assert not ray_weights.centroid_in_front(scene, 0, [1])[0]          # the reverse path
    for seed in range(5):
        scheme = SampleScheme(8, 8, seed=seed, sets=8)
        (f1,), r1 = _golden_fraction(scene, scheme, 0, [1], EndPoints(scene, scheme, "draw", seed, 8, 1))
        (f4,), r4 = _golden_fraction(scene, scheme, 0, [1], EndPoints(scene, scheme, "draw", seed, 8, 4))
        print(f"seed {seed}: factor 1 {f1:.4f} ({r1} rays), factor 4 {f4:.4f} ({r4} rays)")
        assert r1 == r4 == 8 * 8 and f1 == f4


def test_a_straddling_shooters_rows_without_light_do_not_count():
    """The same scene the other way: the wall shoots at the floor-like triangle, whose centroid is
    in front of it (the wall's own rows). Only the wall's tip sends it light, and nothing hides the
    tip: the clear fraction is 1. A set with no sample in the tip carries no light; its row (rays
    from below the floor's plane, through the plate) must not count."""
    scene = _straddling_scene()
    assert ray_weights.centroid_in_front(scene, 1, [0])[0]
    got, dark = [], 0
    for seed in range(30):
        scheme = SampleScheme(8, 8, seed=seed, sets=8)
        got.append(_golden_fraction(scene, scheme, 1, [0], EndPoints(scene, scheme, "draw", seed, 8))[0][0])
        w = ray_weights.pair_sample_weights(scene, scheme, np.array([1]), np.array([0]))[0].reshape(8, 8)
        dark += int((w.sum(axis=1) == 0).sum())
    print("seeds 0-29: clear fraction", np.round(got, 3), f"; rows without light {dark} of {30 * 8}")
    assert dark > 0                                                    # the case is exercised
    np.testing.assert_array_equal(got, 1.0)


def _penumbra_scene():
    """Patch 0: a small emitting triangle at y = 2 facing down. Patches 1, 2: a plate at y = 1
    over x < 0.1. Patch 3: a large floor triangle (y = 0, facing up) that the plate's shadow edge
    crosses, so where its rows end decides the clear fraction."""
    lamp = [[-0.05, 2, -0.05], [0.05, 2, -0.05], [0, 2, 0.05]]
    plate = [[[-2, 1, -2], [0.1, 1, -2], [0.1, 1, 2]], [[-2, 1, -2], [0.1, 1, 2], [-2, 1, 2]]]
    floor = [[-1, 0, -1], [0, 0, 1.5], [1, 0, -1]]
    E = np.zeros((4, 3))
    E[0] = 1.0
    return make_scene(np.array([lamp] + plate + [floor], dtype=np.float64), emission=E)


def _floor_fraction(scene, factor, seed):
    scheme = SampleScheme(8, 8, seed=seed, sets=4)
    f, rays = _golden_fraction(scene, scheme, 0, [3], EndPoints(scene, scheme, "draw", seed, 4, factor))
    return f[0], rays


def test_an_emitters_pairs_cast_emitter_factor_times_the_rows():
    """The lamp's pair with the floor gets 4 x 4 rows with ``emitter_factor`` 4 (4x the rays),
    each row in its own stratum of the floor's density: over 60 seeds the estimate agrees with 4
    rows' and its spread is well below theirs. A patch that does not emit keeps 4 rows."""
    scene = _penumbra_scene()
    one = [_floor_fraction(scene, 1, s) for s in range(60)]
    four = [_floor_fraction(scene, 4, s) for s in range(60)]
    f1, f4 = np.array([f for f, _ in one]), np.array([f for f, _ in four])
    print("seeds 0-59; factor 1: mean %.4f sd %.4f; factor 4: mean %.4f sd %.4f" % (f1.mean(), f1.std(), f4.mean(),
                                                                                  f4.std()))
    assert 0.2 < f1.mean() < 0.8                                      # the shadow edge crosses the floor
    assert {r for _, r in four} == {4 * r for _, r in one}
    assert abs(f4.mean() - f1.mean()) < 4 * f1.std() / np.sqrt(60)
    assert f4.std() < 0.7 * f1.std()
    dark = make_scene(scene.patch_vertices.astype(np.float64))       # the same, nothing emitting
    assert _floor_fraction(dark, 4, 0)[1] == one[0][1]
