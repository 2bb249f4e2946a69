"""Rows that end at their own points (host_driver/traverse/endpoints.py, BlockRay.receiver_weights): every
board tests the ray to the point the weights give, and the rules put the points where they say.

Oracles: the exact predicate on end points computed here from the weights (integer arithmetic),
and the kernel cos cos / r^2 integrated over the receiver on a fine grid written here."""

from types import SimpleNamespace

import numpy as np
import pytest

from blockray.errors import ParameterError
from blockray.exact import blocked_reference, patch_normals
from blockray.board import BlockRay
from blockray.host_driver.radiosity import ray_weights
from blockray.host_driver.traverse.endpoints import EndPoints
from blockray.host_driver.traverse.visibility import Visibility, visible_fraction
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.board.golden import GoldenBoard
from blockray.host_driver.render.options import RenderOptions
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.sim.model import BoardModel, ModelBoard

from board_scenes import BoxGrid, random_blocks, scattered_scene
from scenes import make_scene


def one_voxel(n):
    """Grid stand-in: a single voxel holding every patch."""
    return SimpleNamespace(v=1, start=np.array([0]), count=np.array([n]), patches=np.arange(n))

SAMPLES = SampleScheme(8)
D, PRIME = SAMPLES.denominator, SAMPLES.prime


def _allowed_weights(rng, n):
    """n random barycentric weights on the 1/D lattice, strictly inside, no weight a multiple of p."""
    out = []
    while len(out) < n:
        a, b = rng.integers(1, D - 1, 2)
        w = np.array([a, b, D - a - b])
        if (w >= 1).all() and (w % PRIME != 0).all():
            out.append(w)
    return np.array(out, dtype=np.int64)


def _with_ends(rng, blocks):
    return [BlockRay(b.shooter_patch, b.shooter_sample, b.receiver_patch, b.voxels,
                     _allowed_weights(rng, len(b.receiver_patch))) for b in blocks]


def _model_board(scene_seed, boards):
    scene = scattered_scene(scene_seed)
    board = ModelBoard(BoardParams(rows=4, cols=3, boards=boards, bits=12))
    board.prepare(scene, SAMPLES)
    grid = BoxGrid(scene.patch_vertices, 3, margin=board.margin)
    board.load(grid)
    return scene, board, grid


def test_model_and_its_command_streams_end_rows_at_their_points():
    seed = 31
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    scene, board, grid = _model_board(1, boards=2)
    q = board.quantised
    blocks = _with_ends(rng, random_blocks(rng, scene, SAMPLES, board.params, 40, len(grid.voxel_patches)))
    bits = board.run(blocks)
    blocked = 0
    for block, out in zip(blocks, bits):
        patches = sorted({int(t) for v in block.voxels for t in grid.voxel_patches[v]})
        for r, j in enumerate(block.receiver_patch):
            num = (block.receiver_weights[r][:, None] * q.vertices[j]).sum(axis=0)
            assert (num % D == 0).all()
            Q = (num // D).tolist()
            for s, (i, k) in enumerate(zip(block.shooter_patch, block.shooter_sample)):
                expect = any(blocked_reference(q.shooters[i, k].tolist(), Q, *q.vertices[t].tolist())
                             for t in patches)
                assert out[r, s] == expect
                blocked += expect
    assert blocked > 20
    # the command stream the driven boards (RTL, link) receive loads the same points
    stream = [cmd for b in blocks for cmd in board.memory.block_commands(b)]
    ored = [np.zeros_like(b) for b in bits]
    for p in range(board.params.boards):
        bm = BoardModel(board.params, board.timing)
        bm.execute(board.memory.load_commands(p))
        for k, (blk, word) in enumerate(zip(blocks, bm.execute(stream).blocked)):
            ored[k] |= word[:len(blk.receiver_patch), :len(blk.shooter_patch)]
    for a, b in zip(ored, bits):
        np.testing.assert_array_equal(a, b)


def test_golden_board_ends_rows_at_their_points():
    """Integer triangles (multiples of D, so every point is exact) on a small lattice."""
    seed = 32
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    V = (rng.integers(0, 6, (30, 1, 3)) + rng.integers(-2, 3, (30, 3, 3))) * D
    V = V[np.linalg.norm(patch_normals(V), axis=1) > 0]
    board = GoldenBoard()
    board.prepare(make_scene(V), SAMPLES)
    board.load(one_voxel(len(V)))
    P_all = SAMPLES.points_int(V)
    total = blocked = 0
    for _ in range(8):
        blk = BlockRay(rng.integers(0, len(V), 5), rng.integers(0, SAMPLES.count, 5), rng.integers(0, len(V), 6),
                       np.array([0]), _allowed_weights(rng, 6))
        bits = board.run([blk])[0]
        Q = np.einsum("rk,rkc->rc", blk.receiver_weights, V[blk.receiver_patch]) // D
        P = P_all[blk.shooter_patch, blk.shooter_sample]
        ref = np.array([[any(blocked_reference(p.tolist(), q.tolist(), *v.tolist()) for v in V) for p in P] for q in Q])
        np.testing.assert_array_equal(bits, ref)
        total, blocked = total + bits.size, blocked + int(bits.sum())
    assert 0.1 * total < blocked < 0.9 * total


def test_centroid_weights_are_the_boards_own_centroids():
    seed = 33
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    scene, model, grid = _model_board(2, boards=1)
    golden = GoldenBoard()
    golden.prepare(scene, SAMPLES)
    golden.load(one_voxel(scene.patches))
    plain = random_blocks(rng, scene, SAMPLES, model.params, 30, len(grid.voxel_patches))
    for board, voxels in ((model, None), (golden, np.array([0]))):
        blocks = [BlockRay(b.shooter_patch, b.shooter_sample, b.receiver_patch,
                           b.voxels if voxels is None else voxels) for b in plain]
        centred = [BlockRay(b.shooter_patch, b.shooter_sample, b.receiver_patch, b.voxels,
                            np.full((len(b.receiver_patch), 3), D // 3)) for b in blocks]
        for a, b in zip(board.run(blocks), board.run(centred)):
            np.testing.assert_array_equal(a, b)


def _pair_scene():
    """A small shooter (patch 0) facing down, off to the side above a large floor triangle (patch 1)."""
    return make_scene(np.array([[[0.0, 0.0, 1.0], [0.0, 0.3, 1.0], [0.3, 0.0, 1.0]],
                                [[0.0, 0.0, 0.0], [6.0, 0.0, 0.0], [0.0, 6.0, 0.0]]]))


def _kernel_on_fine_grid(scene, n=120):
    """Barycentric centres (M, 3) of the receiver's n^2 congruent cells and the kernel summed over
    the shooter's sample points at each (M,), straight from the definition."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j < n)
    a, b = i[up] + 1 / 3, j[up] + 1 / 3                    # upward cells
    c, d = i[(i + j < n - 1)] + 2 / 3, j[(i + j < n - 1)] + 2 / 3   # downward cells
    uv = np.concatenate([np.stack([a, b], 1), np.stack([c, d], 1)]) / n
    bary = np.stack([1 - uv.sum(1), uv[:, 0], uv[:, 1]], axis=1)
    V = scene.patch_vertices
    Y = bary @ V[1]
    X = SAMPLES.points(V[:1])[0]
    n0, n1 = np.cross(V[0, 1] - V[0, 0], V[0, 2] - V[0, 0]), np.cross(V[1, 1] - V[1, 0], V[1, 2] - V[1, 0])
    g = np.zeros(len(Y))
    for x in X:
        d = Y - x
        r2 = (d * d).sum(1)
        g += np.maximum(d @ n0, 0) * np.maximum(-(d @ n1), 0) / r2 ** 2
    return bary, g


def test_kernel_rule_ends_near_the_kernel_weighted_centroid():
    scene = _pair_scene()
    w = EndPoints(scene, SAMPLES, "kernel").weights(0, [1])[0]
    bary, g = _kernel_on_fine_grid(scene)
    target = (g[:, None] * bary).sum(0) / g.sum()
    assert w.sum() == D and (w >= 1).all() and (w % PRIME != 0).all()
    # within two lattice steps of the oracle's centroid, and moved from the area centroid towards it
    assert np.abs(w / D - target).max() < 2 / D, (w, target * D)
    assert np.abs(target - 1 / 3).max() > 3 / D          # the case is not the centroid in disguise
    assert np.abs(w / D - target).sum() < np.abs(1 / 3 - target).sum()


def test_draw_rule_follows_the_kernel_density():
    """Drawn end points over many seeds fall in the receiver's quarters (first midpoint cut) as the
    kernel's mass does, integrated here on a fine grid."""
    scene = _pair_scene()
    n_draws, first_seed = 3000, 7000
    print(f"seeds={first_seed}..{first_seed + n_draws - 1}")
    W = np.array([EndPoints(scene, SAMPLES, "draw", seed=s).weights(0, [1])[0] for s in
                  range(first_seed, first_seed + n_draws)])
    assert (W.sum(1) == D).all() and (W >= 1).all() and (W % PRIME != 0).all()

    def quarter(bary):          # corner quarters where one weight exceeds 1/2, else the middle one
        big = bary > 0.5
        return np.where(big.any(1), np.argmax(big, axis=1), 3)

    bary, g = _kernel_on_fine_grid(scene)
    mass = np.bincount(quarter(bary), weights=g, minlength=4) / g.sum()
    freq = np.bincount(quarter(W / D), minlength=4) / n_draws
    print(f"kernel mass per quarter {mass.round(3)}, drawn {freq.round(3)}")
    assert mass.max() > 0.4                                # a density far from uniform
    assert np.abs(freq - mass).max() < 0.05


def test_a_pairs_draw_does_not_depend_on_its_batch():
    scene = scattered_scene(3)
    ends = EndPoints(scene, SAMPLES, "draw", seed=5)
    J = np.arange(1, scene.patches)
    w = ends.weights(0, J)
    np.testing.assert_array_equal(ends.weights(0, J[::-1]), w[::-1])
    np.testing.assert_array_equal(ends.weights(0, J[3:9]), w[3:9])
    assert (EndPoints(scene, SAMPLES, "draw", seed=6).weights(0, J) != w).any()
    assert EndPoints(scene, SAMPLES, "centroid").weights(0, J) is None


def test_end_point_options_are_checked():
    with pytest.raises(ParameterError) as e:
        RenderOptions.of(end_points="corner")
    assert e.value.parameter == "end_points"
    with pytest.raises(ParameterError):
        RenderOptions.of(end_seed=-1)
    assert RenderOptions.of(end_points="draw", end_seed=3).ray.end_points == "draw"


@pytest.mark.parametrize("count", [1, 8, 32, 64])
@pytest.mark.parametrize("lattice", [2, 8, 16])
def test_a_finer_end_lattice_keeps_the_sample_points(count, lattice):
    """Only the denominator changes: the same float sample points and centroid, weights summing to
    3 p lattice, none a multiple of p."""
    base, fine = SampleScheme(count), SampleScheme(count, lattice)
    V = np.random.default_rng(0).random((5, 3, 3))
    assert fine.denominator == 3 * base.prime * lattice and fine.prime == base.prime
    np.testing.assert_allclose(fine.points(V), base.points(V), rtol=0, atol=1e-15)
    assert (fine.weights.sum(1) == fine.denominator).all() and (fine.weights % fine.prime != 0).all()
    np.testing.assert_array_equal(fine.centroid_weights * 3, [fine.denominator] * 3)


def test_drawn_points_on_a_finer_lattice_reach_the_edge_strip():
    """On the 1/D lattice no point comes nearer than 1/D to an edge; on a lattice 8 times finer the
    draws reach into that strip, and still follow the kernel's mass."""
    scene = _pair_scene()
    fine = SampleScheme(8, 8)
    Df = fine.denominator
    seeds = range(500, 2500)
    W = np.array([EndPoints(scene, fine, "draw", seed=s).weights(0, [1])[0] for s in seeds])
    assert (W.sum(1) == Df).all() and (W >= 1).all() and (W % fine.prime != 0).all()
    near = (W.min(axis=1) < Df // D).mean()          # nearer an edge than the coarse lattice allows
    bary, g = _kernel_on_fine_grid(scene)
    strip = g[bary.min(axis=1) < 1 / D].sum() / g.sum()
    print(f"kernel mass in the strip {strip:.3f}, drawn there {near:.3f}")
    # the density is constant over each of 16 sub-triangles, so it spreads a corner's peak over its
    # cell: the draws reach the strip, though not with all of the kernel's mass there
    assert strip > 0.1 and 0.6 * strip < near < strip + 0.05


def test_rows_per_pair_average_the_exact_predicate_of_each_draw():
    """``end_draws`` rows per pair: each pair's clear fraction is the mean over its draws of the
    exact predicate's weighted clear fraction, from the weights each draw gives (checked ray by ray
    here on the quantised scene)."""
    samples, draws = SampleScheme(4, 2), 3
    scene = scattered_scene(11, n=24)
    board = ModelBoard(BoardParams(rows=3, cols=2, boards=1, bits=14))
    board.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, 3, margin=board.margin)
    board.load(grid)
    ends = EndPoints(scene, samples, "draw", seed=4, draws=draws)
    vis = Visibility(scene, board, grid, samples, rows=3, cols=2, ends=ends)
    q, Dq = board.quantised, samples.denominator
    checked = partial = 0
    for i in range(0, scene.patches, 3):
        J = np.array([j for j in range(scene.patches) if j != i])
        J = J[ray_weights.centroid_in_front(scene, i, J)]
        frac = visible_fraction(scene, vis, samples, i, J, vis.phases)
        a = ray_weights.pair_sample_weights(scene, samples, np.full(len(J), i), J)
        for m, j in enumerate(J):
            if a[m].sum() == 0:
                continue
            clear = np.zeros(samples.count)
            for d in range(draws):
                w = ends.weights(i, [j], d)[0]
                Q = ((w[:, None] * q.vertices[j]).sum(0) // Dq).tolist()
                clear += [not any(blocked_reference(q.shooters[i, k].tolist(), Q, *q.vertices[t].tolist())
                                  for t in range(scene.patches)) for k in range(samples.count)]
            expect = (a[m] * clear).sum() / (draws * a[m].sum())
            assert frac[m] == pytest.approx(expect, rel=1e-12, abs=1e-15), (i, j)
            checked += 1
            partial += 0 < expect < 1
    assert checked > 40 and partial > 10, (checked, partial)


def test_end_lattice_and_draws_options_are_checked():
    for bad, name in ((dict(end_points="draw", end_lattice=3), "end_lattice"),
                      (dict(end_lattice=4), "end_lattice"),                     # centroid: bits for nothing
                      (dict(end_points="draw", end_draws=0), "end_draws"),
                      (dict(end_points="kernel", end_draws=2), "end_draws"),
                      (dict(end_points="draw", samples=SampleScheme(8, 4), end_lattice=2), "end_lattice")):
        with pytest.raises(ParameterError) as e:
            RenderOptions.of(**bad)
        assert e.value.parameter == name, bad
    o = RenderOptions.of(end_points="draw", end_lattice=4, end_draws=2)
    assert o.ray.samples == SampleScheme(8, 4)
    assert o.with_(end_lattice=2).ray.samples == SampleScheme(8, 2)
    assert RenderOptions.of(end_points="draw", samples=SampleScheme(8, 4)).ray.end_lattice == 4
