"""The compiled host kernels: the board model's arithmetic (blockray.sim.kernel) against the
Python-integer oracle (blockray.exact.blocked_reference) on random queries, and every kernel's
independence of the thread count. (The hard cases run through the same kernel in
tests/test_hard_cases.py via BoardModel.execute.)"""

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.exact import blocked_reference, patch_normals
from blockray import threads
from blockray.host_driver.render.render import render
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import TraversalStats
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.sim import kernel
from blockray.sim.model import ModelBoard

from board_scenes import BoxGrid, random_blocks, scattered_scene as random_scene

SEED = 1313


def rng_for(name):
    seed = SEED + sum(map(ord, name))
    print(f"seed={seed}")
    return np.random.default_rng(seed)


def reference(P, Q, V):
    """(R, S, N) blocked bits by the oracle."""
    return np.array([[[blocked_reference(p, q, *t) for t in V.tolist()] for p in P.tolist()]
                     for q in Q.tolist()], dtype=bool).reshape(len(Q), len(P), len(V))


def random_query(rng, span, top):
    """Shooters, receivers and triangles on a small lattice [0, span] (many ties: shared planes,
    edges and vertices, end points on triangles) placed anywhere in [0, top)."""
    S, R, N = (int(x) for x in rng.integers(1, [9, 9, 12]))
    base = rng.integers(0, top - span, 3)
    pick = lambda *shape: base + rng.integers(0, span + 1, shape) * ((top - 1 - base) // span)
    V = pick(N, 3, 3)
    zero = rng.random(N) < 0.2
    V[zero, 2] = V[zero, 0]                                       # some zero-area triangles
    P, Q = pick(S, 3), pick(R, 3)
    # some end points exactly on a triangle (its centroid scaled to stay on the lattice)
    on = rng.random(R) < 0.3
    Q[on] = V[rng.integers(0, N, int(on.sum()))].sum(axis=1) // 3
    return P.astype(np.int64), Q.astype(np.int64), V.astype(np.int64)


@pytest.mark.parametrize("span, top", [(3, 1 << 4), (7, 1 << 12), (5, 1 << 20)])
def test_any_blocked_agrees_with_the_oracle_on_random_queries(span, top):
    rng = rng_for(f"any-{span}-{top}")
    blocked = 0
    for _ in range(150):
        P, Q, V = random_query(rng, span, top)
        n = patch_normals(V)
        ref = reference(P, Q, V)
        np.testing.assert_array_equal(kernel.any_blocked(P, Q, V, n), ref.any(axis=2))
        # each record alone: the arithmetic of every test, not only the first hit of a ray
        for t in range(len(V)):
            np.testing.assert_array_equal(kernel.any_blocked(P, Q, V[t:t + 1], n[t:t + 1]), ref[:, :, t])
        blocked += int(ref.sum())
    assert blocked > 100


def test_any_blocked_of_an_empty_block():
    V = np.zeros((0, 3, 3), np.int64)
    assert kernel.any_blocked(np.ones((2, 3), np.int64), np.ones((3, 3), np.int64), V,
                              np.zeros((0, 3), np.int64)).shape == (3, 2)


def model_board(seed=5, v=3):
    samples = SampleScheme(8)
    scene = random_scene(seed, n=40)
    board = ModelBoard(BoardParams(rows=8, cols=8, boards=3, bits=14))
    board.prepare(scene, samples)
    grid = BoxGrid(scene.patch_vertices, v, margin=board.margin)
    board.load(grid)
    return scene, samples, board, grid


@pytest.fixture
def parallel_always(monkeypatch):
    """Every batch on the thread pool, however small."""
    monkeypatch.setattr(threads, "PARALLEL_MIN_RAYS", 0)


def thread_counts():
    return sorted({1, min(2, threads.available()), threads.available()})


def test_board_kernel_does_not_depend_on_the_thread_count(parallel_always):
    runs = []
    for n in thread_counts():
        scene, samples, board, grid = model_board()
        blocks = random_blocks(rng_for("board-threads"), scene, samples, board.params, 300, len(grid.voxel_patches))
        with threads.using(n):
            bits = board.run(blocks)
        runs.append((bits.flat.copy(), board.counters()))
    for flat, counters in runs[1:]:
        np.testing.assert_array_equal(flat, runs[0][0])
        assert counters == runs[0][1]
    assert runs[0][0].any() and not runs[0][0].all()


def test_traversals_do_not_depend_on_the_thread_count(parallel_always):
    rng = rng_for("traverse-threads")
    tri = rng.uniform(0, 10, (200, 1, 3)) + rng.normal(0, 0.8, (200, 3, 3))
    grid = VoxelGrid(tri, 9, margin=0.01)
    B = 200
    S, R = rng.integers(1, 9, B), rng.integers(1, 9, B)
    starts, ends = rng.uniform(0, 10, (S.sum(), 3)), rng.uniform(0, 10, (R.sum(), 3))
    so, eo = np.concatenate([[0], np.cumsum(S)]), np.concatenate([[0], np.cumsum(R)])
    P, Q = rng.uniform(-1, 11, (500, 3)), rng.uniform(-1, 11, (500, 3))
    runs = []
    for n in thread_counts():
        with threads.using(n):
            runs.append(grid.traverse_blocks(starts, so, ends, eo, nonempty_only=True)
                        + grid.rays_voxels(P, Q) + grid.rays_counts(P, Q))
    for run in runs[1:]:
        for a, b in zip(run, runs[0]):
            np.testing.assert_array_equal(a, b)
    # the batch is the blocks one by one, and the kept voxels are the nonempty ones of the full list
    vox, off = runs[0][0], runs[0][1]
    for b in range(0, B, 17):
        full = grid.block_voxels(starts[so[b]:so[b + 1]], ends[eo[b]:eo[b + 1]])
        np.testing.assert_array_equal(vox[off[b]:off[b + 1]], full[grid.count[full] > 0])
        assert runs[0][2][b] == len(full) and runs[0][3][b] == grid.count[full].sum()
    for i in range(0, 500, 23):
        np.testing.assert_array_equal(runs[0][4][runs[0][5][i]:runs[0][5][i + 1]], grid.ray_voxels(P[i], Q[i]))
        assert runs[0][6][i] == len(grid.ray_voxels(P[i], Q[i]))


def test_sample_weights_do_not_depend_on_the_thread_count(monkeypatch):
    """The rays' weights of many pairs, serial and on the pool with each thread count: the same bits."""
    from blockray.host_driver.scene import builtin
    from blockray.host_driver.radiosity import ray_weights
    scene, samples = builtin.load("cornell"), SampleScheme(8)
    rng = rng_for("weights-threads")
    shooters, receivers = rng.integers(0, scene.patches, 400), rng.integers(0, scene.patches, 400)
    points = ray_weights.weight_points(scene, samples)
    monkeypatch.setattr(threads, "PARALLEL_MIN_RAYS", 1 << 40)
    serial = ray_weights.pair_sample_weights(scene, samples, shooters, receivers, points=points)
    monkeypatch.setattr(threads, "PARALLEL_MIN_RAYS", 0)
    for n in thread_counts():
        with threads.using(n):
            np.testing.assert_array_equal(ray_weights.pair_sample_weights(scene, samples, shooters, receivers,
                                                                         points=points), serial)
    # the caller's points are those the function computes for the shooters alone
    np.testing.assert_array_equal(ray_weights.pair_sample_weights(scene, samples, shooters, receivers), serial)
    assert (serial > 0).any() and (serial == 0).any()


def test_stats_of_a_batch_equal_the_blocks_one_by_one():
    rng = rng_for("stats-batch")
    tri = rng.uniform(0, 4, (50, 1, 3)) + rng.normal(0, 0.5, (50, 3, 3))
    grid = VoxelGrid(tri, 4, lo=[-2, -2, -2], hi=[6, 6, 6], margin=0.02)
    blocks = [(rng.uniform(0, 4, (int(rng.integers(1, 5)), 3)), rng.uniform(0, 4, (int(rng.integers(1, 6)), 3)))
              for _ in range(60)]
    one = TraversalStats(grid, sample_fraction=0.4, seed=3)
    for s, e in blocks:
        one.add_block(grid.block_voxels(s, e), s, e)
    many = TraversalStats(grid, sample_fraction=0.4, seed=3)
    starts, ends = np.concatenate([s for s, _ in blocks]), np.concatenate([e for _, e in blocks])
    so = np.concatenate([[0], np.cumsum([len(s) for s, _ in blocks])])
    eo = np.concatenate([[0], np.cumsum([len(e) for _, e in blocks])])
    _, _, visited, tests = grid.traverse_blocks(starts, so, ends, eo)
    many.add_blocks(starts, so, ends, eo, visited, tests)
    assert many.summary() == one.summary()
    assert 0 < one.sampled_blocks < 60
    # the per-ray DDA totals are those of the walks one ray at a time
    dda = sum(len(grid.ray_voxels(p, q)) for s, e in blocks for p in s for q in e)
    every = TraversalStats(grid)
    every.add_blocks(starts, so, ends, eo, visited, tests, sample=True)
    assert every.dda_voxels == dda and every.sampled_blocks == 60


def test_render_does_not_depend_on_the_thread_count(parallel_always):
    from blockray.host_driver.scene import builtin
    scene = builtin.load("cornell")
    runs = [render(scene, backend="model", max_shots=6, threads=n) for n in thread_counts()]
    for r in runs[1:]:
        np.testing.assert_array_equal(r.radiosity, runs[0].radiosity)
        for key in ("rays", "blocks", "tests", "board_cycles", "tests_issued_per_board", "traversal_stats"):
            assert r.report[key] == runs[0].report[key]
    assert [r.report["threads"] for r in runs] == thread_counts()


@pytest.mark.parametrize("value", ["0", "100000", "two"])
def test_cli_bad_threads_exit_2(capsys, value):
    with pytest.raises(SystemExit) as e:
        raise SystemExit(main(["render", "cornell", "--max-shots", "1", "--quiet", "--threads", value]))
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert "--threads" in err and "Traceback" not in err
