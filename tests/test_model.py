"""The bit-exact board model (blockray.sim.model): memories, bits, cycles and counters."""

import numpy as np
import pytest

from blockray.errors import CapacityError, ParameterError
from blockray.exact import blocked_reference, blocked_block
from blockray.board import BlockRay
from blockray.params import BoardParams
from blockray.records import patch_layout, unpack_array
from blockray.samples import SampleScheme
from blockray.memory import registration
from blockray.protocol import (BeginBlock, EndBlock, LoadReceiver, LoadShooter, ReadCounters, Voxel,
                               WritePatch, WriteVoxel)
from blockray.sim.model import BoardModel, ModelBoard, result_word
from blockray.timing import BoardTiming

from board_scenes import BoxGrid, random_blocks, scattered_scene as random_scene
from scenes import mesh_scene as make_scene


def setup_board(seed=0, v=3, params=None, bits=None, samples=SampleScheme(8), partition="deal"):
    scene = random_scene(seed)
    board = ModelBoard((params or BoardParams(rows=4, cols=3, boards=3)).with_(bits=bits), partition=partition)
    board.prepare(scene, samples)
    grid = BoxGrid(scene.patch_vertices, v, margin=board.margin)
    board.load(grid)
    return scene, board, grid


def test_run_equals_independent_exact_evaluation():
    samples = SampleScheme(8)
    scene, board, grid = setup_board(seed=1, bits=12, samples=samples)
    q = board.quantised
    rng = np.random.default_rng(2)
    blocks = random_blocks(rng, scene, samples, board.params, 60, len(grid.voxel_patches))
    bits = board.run(blocks)
    seen_blocked = 0
    for block, out in zip(blocks, bits):
        assert out.shape == (len(block.receiver_patch), len(block.shooter_patch))
        patches = sorted({int(t) for v in block.voxels for t in grid.voxel_patches[v]})
        for r, j in enumerate(block.receiver_patch):
            for s, (i, k) in enumerate(zip(block.shooter_patch, block.shooter_sample)):
                P, Q = q.shooters[i, k].tolist(), q.receivers[j].tolist()
                expect = any(blocked_reference(P, Q, *q.vertices[t].tolist()) for t in patches)
                assert out[r, s] == expect
                seen_blocked += expect
    assert seen_blocked > 20          # the scene is dense enough that blocking is exercised


def test_run_equals_command_streams_per_board():
    samples = SampleScheme(8)
    scene, board, grid = setup_board(seed=3, samples=samples)
    rng = np.random.default_rng(4)
    blocks = random_blocks(rng, scene, samples, board.params, 12, len(grid.voxel_patches))
    bits = board.run(blocks)
    c = board.counters()
    stream = [cmd for b in blocks for cmd in board.memory.block_commands(b)]
    ored = [np.zeros_like(b) for b in bits]
    for b in range(board.params.boards):
        bm = BoardModel(board.params, board.timing)
        loaded = bm.execute(board.memory.load_commands(b))           # memory filled through WRITE_* commands
        assert loaded.cycles == c["load_cycles_per_board"][b]
        res = bm.execute(stream)
        assert res.cycles == c["board_cycles_per_board"][b]
        assert res.tests_issued == c["tests_issued_per_board"][b]
        assert res.tests_useful == c["tests_useful_per_board"][b]
        for k, (blk, word) in enumerate(zip(blocks, res.blocked)):
            Rb, Sb = len(blk.receiver_patch), len(blk.shooter_patch)
            assert not word[Rb:].any() and not word[:, Sb:].any()   # unloaded rows/cols stay 0
            ored[k] |= word[:Rb, :Sb]
        assert res.words == [result_word(w) for w in res.blocked]
    for a, b in zip(ored, bits):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("partition", ["deal", "patch"])
def test_memory_layout_and_partition(partition):
    scene, board, grid = setup_board(seed=5, v=3, partition=partition)
    P = board.params.boards
    layout = patch_layout(board.params.bits)
    q = board.quantised
    reg_total = sum(len(x) for x in grid.voxel_patches)
    ids, words = [], []
    for b in range(P):
        img = board.memory.memory_image(b)
        assert len(img["patch"]) <= board.params.patch_depth
        assert all(int(w) < 1 << layout.size for w in img["patch"])
        cols = unpack_array(layout, img["patch"])
        for k, name in enumerate(("v0", "v1", "v2")):
            for a, axis in enumerate("xyz"):
                np.testing.assert_array_equal(cols[(name, axis)], q.vertices[img["patch_id"], k, a])
        for a, axis in enumerate("xyz"):
            np.testing.assert_array_equal(cols[("normal", axis)], q.normals[img["patch_id"], a])
        # voxel v's records are exactly board b's share of the patches registered in v,
        # contiguous, in id order: "patch" all of patch i on board i % P; "deal" the voxel's
        # registrations (in voxel order over the whole table) dealt round robin
        dealt = 0
        for v, members in enumerate(grid.voxel_patches):
            got = img["patch_id"][img["start"][v]:img["start"][v] + img["count"][v]]
            members = np.sort(members)
            if partition == "patch":
                mine = members[members % P == b]
            else:
                mine = members[(dealt + np.arange(len(members))) % P == b]
            dealt += len(members)
            np.testing.assert_array_equal(got, mine)
        if partition == "patch":
            assert (img["patch_id"] % P == b).all()
        ids.append(img["patch_id"])
        words.append(img["count"])
    assert sum(len(x) for x in ids) == reg_total        # a patch in k voxels occupies k words
    counts = np.stack(words)                            # (P, voxels)
    spread = (counts.max(axis=0) - counts.min(axis=0)).max()
    if partition == "deal":
        assert spread <= 1                              # the boards' shares of a voxel are equal
    else:
        assert spread > 1                               # (the scene is one where patch ids are not)
    assert layout.size == 15 * board.params.bits + 6


def test_registration_accepts_csr_grid():
    class CSR:
        count = np.array([2, 0, 1])
        start = np.array([0, 2, 2])
        patches = np.array([7, 3, 5])
    vox, pat, nvox = registration(CSR())
    assert nvox == 3 and vox.tolist() == [0, 0, 2] and pat.tolist() == [3, 7, 5]


def test_cycle_counts_and_counters_by_hand():
    # P = 2 boards: board 0 holds patch 0, board 1 patch 1; voxel 0 holds 0 and 1, voxel 1 holds 1
    scene = make_scene([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 4], [4, 0, 4], [0, 4, 4]],
                       [[0, 1, 2], [3, 4, 5]])

    class G:
        voxel_patches = [np.array([0, 1]), np.array([1]), np.array([], dtype=np.int64)]

    params = BoardParams(rows=4, cols=2, boards=2)
    timing = BoardTiming(processor_latency=5, memory_latency=2)
    board = ModelBoard(params.with_(bits=8), timing=timing, partition="patch")
    board.prepare(scene, SampleScheme(1))
    board.load(G())
    # receiver: centroid of patch 1 (z = 4); shooter: the sample of patch 0 (z = 0): crosses nothing
    blk = BlockRay(np.array([0]), np.array([0]), np.array([1, 1, 1]), np.array([0, 1, 2]))
    out = board.run([blk])
    assert out[0].shape == (3, 1) and not out[0].any()
    c = board.counters()
    # board 0 holds patch 0: voxel counts (1, 0, 0); board 1 holds patch 1: (1, 1, 0).
    # BEGIN, one LOAD_POINTS (3 receivers + 1 shooter), three voxels (one bubble each if empty), END
    assert c["board_cycles_per_board"] == [1 + 1 + (1 + 1 + 1) + 1, 1 + 1 + (1 + 1 + 1) + 1]
    # the batch waits for the slowest board and for the last END_BLOCK's drain
    assert c["board_cycles"] == max(c["board_cycles_per_board"]) + (5 + 2 - 1)
    assert c["tests_issued_per_board"] == [8 * 1, 8 * 2]
    assert c["tests_useful_per_board"] == [3 * 1, 3 * 2]
    assert c["tests_useful"] == c["tests"] == 9 and c["tests_issued"] == 24
    assert c["utilization"] == pytest.approx(9 / (8 * 2 * c["board_cycles"]))
    assert c["utilization_per_board"][1] == pytest.approx(6 / (8 * c["board_cycles_per_board"][1]))
    assert c["blocks"] == 1 and c["rays"] == 3
    assert c["load_cycles_per_board"] == [1 + 3, 2 + 3]


def test_blocking_across_boards_is_ored():
    # a wall (patch 1, on board 1) between a shooter (patch 0, board 0) and a receiver (patch 2, board 0)
    scene = make_scene([[0, 0, 0], [4, 0, 0], [0, 4, 0],
                        [-5, -5, 2], [9, -5, 2], [-5, 9, 2],
                        [0, 0, 4], [0, 4, 4], [4, 0, 4]],
                       [[0, 1, 2], [3, 4, 5], [6, 7, 8]])

    class G:
        voxel_patches = [np.array([0, 1, 2])]

    board = ModelBoard(BoardParams(rows=2, cols=2, boards=2, bits=10))
    board.prepare(scene, SampleScheme(4))
    board.load(G())
    blk = BlockRay(np.array([0, 0]), np.array([0, 3]), np.array([2]), np.array([0]))
    assert board.run([blk])[0].tolist() == [[True, True]]
    blk0 = BlockRay(np.array([0, 0]), np.array([0, 3]), np.array([2]), np.array([], dtype=np.int64))
    assert board.run([blk0])[0].tolist() == [[False, False]]    # no voxel visited: nothing tested


def test_capacity_errors_name_the_memory():
    scene = random_scene(6)
    grid = BoxGrid(scene.patch_vertices, 2)
    board = ModelBoard(BoardParams(boards=2, bits=None, patch_depth=8))
    board.prepare(scene, SampleScheme(8))
    with pytest.raises(CapacityError, match="patch memory.*patch_depth 8"):
        board.load(grid)
    board = ModelBoard(BoardParams(boards=2, bits=None, voxel_depth=7))
    board.prepare(scene, SampleScheme(8))
    with pytest.raises(CapacityError, match="voxel table.*8 voxels.*voxel_depth 7"):
        board.load(grid)


def test_block_larger_than_array_is_refused():
    scene, board, grid = setup_board(seed=7)
    blk = BlockRay(np.zeros(4, dtype=np.int64), np.arange(4), np.arange(2), np.array([0]))
    with pytest.raises(ParameterError, match=r"\(rows/cols\)"):
        board.run([blk])      # 4 shooter points > 3 columns


def test_margin_covers_quantisation():
    for bits in (8, 10, 16):
        scene, board, grid = setup_board(seed=8, bits=bits)
        q = board.quantised
        assert board.margin >= q.displacement and board.margin >= q.end_displacement
        assert board.params.bits == bits
        moved = np.linalg.norm(q.to_scene(q.shooters) - SampleScheme(8).points(scene.patch_vertices), axis=-1)
        assert moved.max() <= board.margin


def test_bits_chosen_when_not_forced():
    scene, board, grid = setup_board(seed=9, bits=None)
    from blockray.fixedpoint import choose_bits
    assert board.params.bits == choose_bits(scene, SampleScheme(8))[0]
    assert board.counters()["bits"] == board.params.bits


def test_execute_rejects_bad_addresses():
    bm = BoardModel(BoardParams(rows=2, cols=2, patch_depth=4, voxel_depth=4))
    with pytest.raises(ParameterError, match="voxel_depth"):
        bm.execute([Voxel(9)])
    with pytest.raises(ParameterError, match="patch_depth"):
        bm.execute([WriteVoxel(0, 2, 3)])
    with pytest.raises(ParameterError, match="patch_depth"):
        bm.execute([WritePatch(4, 0)])


@pytest.mark.parametrize("bits", [10, 12, 14])     # B = 10: 48 lattice steps of D = 21
def test_margin_keeps_host_voxel_traversal_conservative(bits):
    """With the host's VoxelGrid grown by board.margin, the blocks' voxels hold every patch that
    blocks a quantised ray: the answer equals testing all patches (coarse B: large displacement)."""
    from blockray.host_driver.traverse.voxel import VoxelGrid
    samples = SampleScheme(8)
    scene = random_scene(10 + bits, n=60)
    board = ModelBoard(BoardParams(rows=8, cols=8, boards=4, bits=bits))
    board.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, 24, margin=board.margin)
    board.load(grid)
    q = board.quantised
    fpts = samples.points(scene.patch_vertices)
    rng = np.random.default_rng(bits)
    print(f"seed={bits}")
    blocks = []
    for _ in range(40):
        i = int(rng.integers(scene.patches))
        ks = rng.choice(samples.count, 4, replace=False)
        rec = rng.choice(scene.patches, 5, replace=False)
        vox = grid.block_voxels(fpts[i, ks], scene.centroids[rec])
        blocks.append(BlockRay(np.full(4, i), ks, rec, vox))
    got = board.run(blocks)
    misses = 0
    for blk, out in zip(blocks, got):
        full = blocked_block(q.shooters[blk.shooter_patch, blk.shooter_sample], q.receivers[blk.receiver_patch],
                             q.vertices, q.normals).any(axis=2)
        np.testing.assert_array_equal(out, full)
        misses += int(full.sum())
    assert misses > 10


def test_read_counters_snapshot_covers_the_commands_before_it():
    bm = BoardModel(BoardParams(rows=2, cols=3, patch_depth=8, voxel_depth=2),
                    BoardTiming(processor_latency=7, memory_latency=2))
    V = np.array([[[0, 0, 5], [9, 0, 5], [0, 9, 5]]] * 4)
    bm.load_memory(V, np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0]), [0, 3], [3, 0])
    cmds = [ReadCounters(), BeginBlock(), LoadReceiver(0, (1, 1, 9)),
            LoadShooter(2, (1, 1, 0)), Voxel(0), Voxel(1),
            EndBlock(), ReadCounters()]
    res = bm.execute(cmds)
    assert res.counters[0] == {"cycles": 0, "busy": 0, "tests_issued": 0, "tests_useful": 0}
    # READ_COUNTERS, BEGIN, two loads, VOXEL (3 records), VOXEL (empty: a bubble), END (one cycle)
    assert res.counters[1] == {"cycles": 1 + 1 + 1 + 1 + 3 + 1 + 1, "busy": 3,
                               "tests_issued": 3 * 6, "tests_useful": 3 * 1}
    assert res.cycles == res.counters[1]["cycles"] + 1
    assert res.words == [1 << (0 * 3 + 2)]            # row 0, column 2 blocked by the z = 5 triangles


def test_degenerate_patches_at_forced_bits_are_reported(tmp_path, capsys):
    # A sliver far thinner than the grid step at B = 10 flattens; the user is told, not left guessing.
    from blockray.host_driver.scene.objload import load_obj
    from blockray.samples import SampleScheme
    from blockray.sim.model import ModelBoard, QuantisationWarning
    obj = ["v 0 0 0", "v 100 0 0", "v 0 100 0", "v 100 100 0", "v 50 50 0.001", "v 60 50 0.001", "v 55 50.0001 0.002",
           "f 1 2 3", "f 2 4 3", "f 5 6 7"]
    (tmp_path / "s.obj").write_text("\n".join(obj) + "\n")
    scene = load_obj(tmp_path / "s.obj", max_edge=10.0)     # ~400 patches: the sliver is under 1%
    assert scene.patches > 100
    board = ModelBoard(BoardParams(bits=10))
    with pytest.warns(QuantisationWarning, match=r"1 patches degenerate") as caught:
        board.prepare(scene, SampleScheme(4))
    assert len(board.quantised.degenerate) == 1
    # the library names the parameter, the command line its option, as errors do
    assert str(caught[0].message).endswith("use more bits to keep them")
    from blockray.host_driver.cli import main
    code = main(["render", str(tmp_path / "s.obj"), "--max-edge", "10", "--bits", "10", "--samples", "4",
                 "--max-shots", "1", "--quiet"])
    err = capsys.readouterr().err.splitlines()
    assert code == 0 and any(e.startswith("blockray: warning: ") and e.endswith("use more --bits to keep them")
                             for e in err), err
