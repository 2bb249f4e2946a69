"""The host's bulk wire format (blockray/protocol.py): ``BoardProtocol.encode_blocks`` gives the
bytes of ``encode_all`` over each block's typed commands (``BoardMemories.block_commands``'s
stream), ``decode_blocked`` the blocked bits ``decode_result`` gives one result at a time; on
seeded random blocks with the edge values (points 0 and 2**B - 1, the last voxel, blocks without
rows or columns, full arrays, point counts on and off a LOAD_POINTS boundary)."""

import numpy as np
import pytest

from blockray.errors import CapacityError
from blockray.memory import load_points_commands
from blockray.params import BoardParams
from blockray.protocol import BeginBlock, BoardProtocol, BoardResult, EndBlock, ResultKind, Voxel


def _offsets(counts):
    return np.concatenate(([0], np.cumsum(counts))).astype(np.int64)


def _random_blocks(rng, params, blocks):
    """Rows, columns, voxels of ``blocks`` random blocks; edge values drawn often."""
    top = (1 << params.bits) - 1
    rows = rng.choice([0, 1, params.rows, *rng.integers(0, params.rows + 1, 3)], blocks)
    cols = rng.choice([0, 1, params.cols, *rng.integers(0, params.cols + 1, 3)], blocks)
    nvox = rng.choice([0, 1, 2, 7], blocks)

    def points(n):
        p = rng.integers(0, top + 1, (n, 3))
        return np.where(rng.random((n, 3)) < 0.2, rng.choice([0, top], (n, 3)), p)

    voxels = rng.integers(0, params.voxel_depth, int(nvox.sum()))
    voxels = np.where(rng.random(len(voxels)) < 0.2, params.voxel_depth - 1, voxels)
    return points(int(rows.sum())), _offsets(rows), points(int(cols.sum())), _offsets(cols), voxels, _offsets(nvox)


def _per_record(proto, receivers, row_off, shooters, col_off, voxels, vox_off):
    out = b""
    for k in range(len(row_off) - 1):
        commands = ([BeginBlock()] + load_points_commands(receivers[row_off[k]:row_off[k + 1]], shooters[col_off[k]:col_off[k + 1]])
                    + [Voxel(int(v)) for v in voxels[vox_off[k]:vox_off[k + 1]]] + [EndBlock()])
        out += proto.encode_all(commands)
    return out


@pytest.mark.parametrize("rows,cols,bits,voxel_depth", [(2, 2, 10, 27), (3, 5, 4, 1), (8, 8, 18, 32768), (8, 8, 17, 65536),
                                                        (1, 7, 20, 300), (5, 3, 12, 256)])
def test_bulk_commands_are_the_per_record_bytes(rows, cols, bits, voxel_depth):
    seed = 4000 + 97 * rows + 13 * cols + bits + voxel_depth
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    params = BoardParams(rows=rows, cols=cols, bits=bits, voxel_depth=voxel_depth, patch_depth=100)
    proto = BoardProtocol(params)
    for blocks in (0, 1, 5, 60):
        batch = _random_blocks(rng, params, blocks)
        want = _per_record(proto, *batch)
        assert proto.encode_blocks(*batch) == want, f"{blocks} blocks"
    assert want and proto.decode_commands(want)     # the oracle's bytes are a command stream


def test_bulk_commands_take_offsets_into_larger_arrays():
    """A batch's voxels from an offset other than 0 (a slice of a larger batch's arrays)."""
    rng = np.random.default_rng(4100)
    print("seed=4100")
    proto = BoardProtocol(BoardParams(rows=2, cols=2, bits=10, voxel_depth=64, patch_depth=10))
    receivers, row_off, shooters, col_off, voxels, vox_off = _random_blocks(rng, proto.params, 9)
    k = 4
    want = _per_record(proto, receivers[row_off[k]:], row_off[k:] - row_off[k], shooters[col_off[k]:], col_off[k:] - col_off[k],
                       voxels[vox_off[k]:], vox_off[k:] - vox_off[k])
    assert proto.encode_blocks(receivers, row_off[k:], shooters, col_off[k:], voxels, vox_off[k:]) == want


def test_bulk_commands_check_their_operands():
    proto = BoardProtocol(BoardParams(rows=2, cols=2, bits=10, voxel_depth=64, patch_depth=10))
    point = np.zeros((3, 3), dtype=np.int64)
    one, none = np.array([0, 1]), np.array([0, 0])
    with pytest.raises(CapacityError, match="receiver row 2"):
        proto.encode_blocks(point, np.array([0, 3]), point[:1], one, np.array([0]), none)
    with pytest.raises(ValueError, match="does not fit 10 bits"):
        proto.encode_blocks(np.array([[0, 1024, 0]]), one, point[:1], one, np.array([0]), none)
    with pytest.raises(CapacityError, match="voxel 64"):
        proto.encode_blocks(point[:1], one, point[:1], one, np.array([64]), one)
    assert proto.encode_blocks(point[:1], one, point[:1], one, np.array([63]), one)


@pytest.mark.parametrize("rows,cols", [(2, 2), (3, 5), (8, 8)])
def test_bulk_blocked_results_are_the_per_result_bits(rows, cols):
    seed = 4200 + rows * cols
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    proto = BoardProtocol(BoardParams(rows=rows, cols=cols, bits=10))
    n = rows * cols
    words = [0, (1 << n) - 1, 1, 1 << (n - 1)] + [int.from_bytes(rng.bytes(8), "little") & ((1 << n) - 1) for _ in range(40)]
    nb = proto.result_bytes(ResultKind.BLOCKED)
    wire = b"".join(proto.result_wire(BoardResult(ResultKind.BLOCKED, blocked=w)) for w in words)
    wire += proto.result_wire(BoardResult(ResultKind.COUNTERS, counters=dict.fromkeys(
        ("cycles", "busy", "tests_issued", "tests_useful", "stalls"), 5)))    # bytes after the blocks are not read
    tags, bits = proto.decode_blocked(wire, len(words))
    assert bits.shape == (len(words), n) and (tags == ResultKind.BLOCKED).all()
    for k, w in enumerate(words):
        assert proto.decode_result(wire[k * nb:(k + 1) * nb]).blocked == w
        assert sum(1 << int(i) for i in np.flatnonzero(bits[k])) == w, f"result {k}"
    corrupt = bytearray(wire)
    corrupt[3 * nb] |= 3
    corrupt[5 * nb] = corrupt[5 * nb] & ~3 | ResultKind.COUNTERS
    tags, _ = proto.decode_blocked(bytes(corrupt), len(words))
    assert tags[3] == 3 and tags[5] == ResultKind.COUNTERS and (np.delete(tags, [3, 5]) == 0).all()
