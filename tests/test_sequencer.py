"""Rays made on the board, at the model level: the commands of blockray/board_rays.py (their wire
format both ways) and the block sequencer's model (sim/sequencer.py).

On cornell (the CLI's B and K = 8, the 1 x 2 and 2 x 2 boards) the host packs shooter columns
as ``--traversal board`` does (Visibility on the lattice grid, the integer block walk). Sent as
COLUMN and RECEIVERS through the wire format, the sequencer must make exactly the internal
records the host sends for those blocks today (``BoardMemories.block_commands``: the same
points, the same voxels in the same order) and the board model the same blocked bits as
``ModelBoard.run`` of the batch. The clear fractions must equal those of ``--traversal block``
(float rays on the float grid) exactly: both walks are conservative, so every ray is tested
against every patch that can block it in either mode.
"""

import random

import numpy as np
import pytest

from blockray.board_rays import (Column, LoadGrid, LoadSamples, RayProtocol, Receivers, column_commands,
                                 describe, record_addresses)
from blockray.errors import CapacityError, ParameterError
from blockray.params import BoardParams
from blockray.protocol import EndBlock, Identify, LoadPoints, ReadCounters, Voxel
from blockray.samples import SampleScheme
from blockray.sim import sequencer
from blockray.sim.model import ModelBoard

SHOOTERS = 3


def _params(rows, cols, bits=16):
    return BoardParams(rows=rows, cols=cols, boards=1, bits=bits, patch_depth=2048, voxel_depth=512)


def test_commands_round_trip_the_wire_format(rng_seed):
    rng = random.Random(rng_seed)
    D = 21
    proto = RayProtocol(_params(2, 2))

    def triple():
        a = rng.randint(0, D)
        b = rng.randint(0, D - a)
        return (a, b, D - a - b)
    for _ in range(50):
        weighted = rng.random() < 0.5
        cmds = [LoadSamples(tuple(triple() for _ in range(rng.randint(1, 64)))),
                LoadGrid(tuple(rng.randrange(1 << 16) for _ in range(3)), rng.randint(0, 16), rng.randint(1, 8)),
                Column(rng.randrange(2048)), ReadCounters(),
                Receivers(tuple((rng.randrange(2048), rng.random() < 0.5, triple() if weighted else None)
                                for _ in range(rng.randint(1, 4)))),
                LoadPoints(((True, 1, (5, 6, 7)),)), Voxel(rng.randrange(512)), EndBlock(), Identify()]
        wire = proto.encode_all(cmds)
        assert proto.decode_commands(wire) == cmds
        assert len(wire) == sum(len(proto.encode(c)) for c in cmds)


def test_describe_gives_the_bytes_of_the_design():
    text = describe(_params(1, 2, 16))
    assert "| COLUMN | 12 | the shooter's record address (11 bits) | 3 |" in text        # 1 + 11 bits
    assert "| RECEIVERS | 13 |" in text and "| 3 to 7 (weighted 7 to 22) |" in text     # 1 + 4 x 12 bits; weighted 4 x 42


@pytest.mark.parametrize("command", [
    LoadSamples(((7, 7, 8), (7, 7, 7))),                        # sums to 22, then 21
    LoadSamples(((600, 0, 0),)),                                # D above 528
    LoadSamples(()),
    LoadGrid((0, 0, 0), 17, 4),                                 # shift above B
    LoadGrid((0, 0, 0), 4, 9),                                  # 729 voxels > voxel_depth
    Column(2048),
    Receivers(()),
    Receivers(((1, True, None), (2, True, (7, 7, 7)))),         # mixed weighted and not
])
def test_bad_operands_are_one_error(command):
    with pytest.raises((ParameterError, CapacityError)):
        RayProtocol(_params(2, 2)).encode(command)


def test_a_board_without_b_is_one_error():
    with pytest.raises(ParameterError):
        RayProtocol(BoardParams(bits=None))


class _Recorder:
    """A board that keeps the batches the host sends it (Visibility reads ``quantised``)."""

    def __init__(self, board):
        self.board, self.quantised, self.batches = board, board.quantised, []

    def run(self, batch):
        self.batches.append(batch)
        return self.board.run(batch)


@pytest.fixture(scope="module")
def cornell():
    from blockray.host_driver.scene.builtin import load_scene
    return load_scene("cornell")


def _render_columns(scene, rows, cols, traversal, shooters, voxels=5):
    """(the board, the recording board, clear fractions) of ``shooters``' columns to every patch."""
    from blockray.host_driver.traverse.board_walk import LatticeGrid
    from blockray.host_driver.traverse.visibility import Visibility
    from blockray.host_driver.traverse.voxel import VoxelGrid
    samples = SampleScheme(8)
    board = ModelBoard(BoardParams(rows=rows, cols=cols, boards=1, bits=None))
    board.prepare(scene, samples)
    grid = (LatticeGrid.for_scene(board.quantised, voxels) if traversal == "board"
            else VoxelGrid(scene.patch_vertices, voxels, margin=board.margin))
    board.load(grid)
    rec = _Recorder(board)
    vis = Visibility(scene, rec, grid, samples, rows=rows, cols=cols, traversal=traversal)
    frac = [vis.clear_fraction(i, np.delete(np.arange(scene.patches), i)) for i in shooters]
    return board, grid, rec, np.concatenate(frac)


@pytest.mark.parametrize("rows,cols", [(1, 2), (2, 2)])
def test_sequencer_makes_the_hosts_blocks_and_bits(cornell, rows, cols, rng_seed):
    shooters = random.Random(rng_seed).sample(range(cornell.patches), SHOOTERS)
    board, grid, rec, frac = _render_columns(cornell, rows, cols, "board", shooters)
    q, params, memory = board.quantised, board.params, board.memory
    proto = RayProtocol(params)
    address = record_addresses(memory.memories[0]["patch"], cornell.patches)
    model = board.board_model(0)
    setup = [LoadSamples(tuple(map(tuple, SampleScheme(8).weights.tolist()))), LoadGrid((0, 0, 0), grid.shift, grid.v)]
    for batch in rec.batches:
        wire = proto.encode_all(setup + column_commands(batch, address, 8, cols))
        result, records = sequencer.execute(model, proto.decode_commands(wire))
        assert records == [c for block in batch for c in memory.block_commands(block)]
        bits = board.run(batch)
        assert result.words == [sum(1 << k for k, x in enumerate(bits[b].ravel()) if x) for b in range(len(batch))]
    assert 0 < frac.mean() < 1                                  # blocked and clear rays both occur
    _, _, _, float_frac = _render_columns(cornell, rows, cols, "block", shooters)
    assert np.array_equal(frac, float_frac)


@pytest.mark.parametrize("voxels", [5, 16])
def test_every_blocking_patch_is_in_a_voxel_of_its_block(cornell, voxels, rng_seed):
    """Conservative on cornell: for every ray of the blocks of a few columns, each patch that
    blocks it (the exact predicate against every patch of the scene) is registered in a voxel the
    block streams; and the clear fractions equal those of the float traversal."""
    from blockray.exact import blocked_block
    shooters = random.Random(rng_seed).sample(range(cornell.patches), 2)
    board, grid, rec, frac = _render_columns(cornell, 2, 2, "board", shooters, voxels)
    q = board.quantised
    held = [set(grid.patches[grid.start[i]:grid.start[i] + grid.count[i]].tolist()) for i in range(grid.voxels)]
    hits = 0
    for batch in rec.batches:
        for block in batch:
            blocked = blocked_block(q.shooters[block.shooter_patch, block.shooter_sample],
                                    q.end_points(block.receiver_patch), q.vertices, q.normals)
            streamed = set().union(*(held[i] for i in block.voxels))
            hits += int(blocked.sum())
            assert set(np.flatnonzero(blocked.any(axis=(0, 1))).tolist()) <= streamed
    assert hits > 100
    _, _, _, float_frac = _render_columns(cornell, 2, 2, "block", shooters, voxels)
    assert np.array_equal(frac, float_frac)


def test_sequencer_refuses_ill_formed_streams():
    from blockray.sim.model import BoardModel
    params = _params(1, 2)
    model = BoardModel(params)
    seq = sequencer.BlockSequencer(params)
    with pytest.raises(ParameterError):
        seq.feed(Column(0), model)                                  # before LOAD_SAMPLES
    seq.feed(LoadSamples(((7, 7, 7),)), model)
    seq.feed(LoadGrid((0, 0, 0), 14, 4), model)
    seq.feed(Column(0), model)
    with pytest.raises(ParameterError):
        seq.feed(Receivers(((0, False, None), (1, True, None))), model)     # a run of 2 rows on R = 1


# -- --traversal board through the CLI ------------------------------------------------------------

def _csv(capsys, tmp_path, *args):
    import clirun
    out = tmp_path / f"{'-'.join(args)}.csv"
    code, err = clirun.cli(capsys, ["render", "cornell", "--rows", "2", "--cols", "2", "--boards", "1",
                                    "--max-shots", "4", "--quiet", "--patches", out, *args])
    assert code == 0, err
    return out.read_bytes()


def test_board_traversal_renders_equal_the_block_traversal(capsys, tmp_path):
    """model (the host sends the integer walk's blocks), model-link (it sends COLUMN and
    RECEIVERS; the sequencer makes the blocks behind the link) and --traversal block: one CSV."""
    block = _csv(capsys, tmp_path, "--board", "model", "--traversal", "block")
    assert _csv(capsys, tmp_path, "--board", "model", "--traversal", "board") == block
    assert _csv(capsys, tmp_path, "--board", "model-link", "--traversal", "board") == block


def test_board_traversal_with_end_point_weights(capsys, tmp_path):
    """--end-points kernel: the rows end at weighted points, so RECEIVERS carries the weights."""
    kernel = ("--end-points", "kernel", "--max-shots", "2")
    block = _csv(capsys, tmp_path, "--board", "model", "--traversal", "block", *kernel)
    assert _csv(capsys, tmp_path, "--board", "model-link", "--traversal", "board", *kernel) == block


@pytest.mark.parametrize("args,needle", [(["--board", "golden"], "integer grid"),
                                         (["--board", "model-link", "--boards", "2"], "one board")])
def test_board_traversal_refuses_boards_that_cannot_make_rays(capsys, tmp_path, args, needle):
    import clirun
    code, err = clirun.cli(capsys, ["render", "cornell", "--rows", "2", "--cols", "2", "--boards", "1",
                                    "--max-shots", "1", "--quiet", "--traversal", "board", *args])
    clirun.assert_one_line_error(code, err, needle)


def test_protocol_doc_matches_the_commands():
    """docs/board-protocol.md embeds describe()'s table of the commands."""
    from pathlib import Path
    text = (Path(__file__).resolve().parent.parent / "docs" / "board-protocol.md").read_text()
    begin = "<!-- generated: python -m blockray.board_rays -->\n"
    at = text.index(begin) + len(begin)
    assert text[at:text.index("<!-- end generated -->", at)] == describe(BoardParams())


def test_board_traversal_needs_the_lattice_grid(cornell):
    """A float grid would read the board's integer points as scene units: refused."""
    from blockray.host_driver.traverse.visibility import Visibility
    from blockray.host_driver.traverse.voxel import VoxelGrid
    samples = SampleScheme(8)
    board = ModelBoard(BoardParams(rows=2, cols=2, boards=1, bits=None))
    board.prepare(cornell, samples)
    grid = VoxelGrid(cornell.patch_vertices, 5, margin=board.margin)
    with pytest.raises(ParameterError, match="lattice"):
        Visibility(cornell, board, grid, samples, rows=2, cols=2, traversal="board")


def test_column_commands_refuse_blocks_the_board_would_not_make():
    """Blocks out of the board's order (a chunk missing, a run's rows changing) are one error,
    not commands that make other blocks."""
    from blockray.board import BlockBatch
    address = np.arange(4)

    def batch(samples_per_block, rows_per_block):
        cols = [np.array(s) for s in samples_per_block]
        rows = [np.array(r) for r in rows_per_block]
        def off(xs):
            return np.cumsum([0] + [len(x) for x in xs])
        return BlockBatch(np.zeros(sum(map(len, cols)), np.int64), np.concatenate(cols), off(cols),
                          np.concatenate(rows), off(rows), np.zeros(0, np.int64), np.zeros(len(cols) + 1, np.int64))
    good = batch([[0, 1], [2]], [[1, 2], [1, 2]])
    assert column_commands(good, address, 3, 2) == [Column(0), Receivers(((1, False, None), (2, True, None)))]
    for bad in (batch([[0, 1]], [[1]]), batch([[0, 1], [2]], [[1], [2]]), batch([[1, 0], [2]], [[1], [1]]),
                batch([[0], [1, 2]], [[1], [1]])):
        with pytest.raises(ParameterError):
            column_commands(bad, address, 3, 2)


def test_cycles_follow_the_contract_by_hand():
    """docs/board-protocol.md "The sequencer's cycles", counted by hand on one voxel (v = 1: its
    stamps cleared in 1 cycle), K = 1, one receiver: a ray inside the voxel is one box of one
    voxel (2 + 1 + 1 cycles), its VOXEL offered in the voxel's cycle, after the box's."""
    params = _params(1, 2, bits=10)
    memory = type("Memory", (), {"vertices": np.full((2, 3, 3), 30), "count": np.array([1])})()
    seq = sequencer.BlockSequencer(params)
    commands = [LoadSamples(((1, 1, 1),)), LoadGrid((0, 0, 0), 6, 1), Column(0), Receivers(((1, True, None),))]
    timed = [t for c in commands for t in seq.feed_timed(c, memory)]
    setup = 10 + 1 + (1 + 15) + (1 + 15)           # B cycles of LOAD_SAMPLES, LOAD_GRID, COLUMN, the receiver
    block = setup + 1                               # the stamps cleared
    assert [c for c, _ in timed] == [block, block + 1 + 2 * 2, block + 6 + 3, block + 6 + 4]
    assert [type(r).__name__ for _, r in timed] == ["BeginBlock", "LoadPoints", "Voxel", "EndBlock"]
    assert seq.cycle == block + 6 + 4 + 1
