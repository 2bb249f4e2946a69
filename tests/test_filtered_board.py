"""The board with the filtered cell (``BoardTop(cell=Cell("filtered"))``) in the Amaranth simulator
against the bit-exact model (``BoardModel(cell=Cell("filtered"))``), zero tolerance.

The filtered board's cycles depend on the data: the undecided tests of a record wait for the
array's one exact unit, records leave the array in order, and when the array's credits run out
the broadcast stalls (cycles lost, counted as board cycles). The model mirrors the hand-off
cycle by cycle (:class:`blockray.sim.filtered_model.FilteredBoardClock`); here the counters the
board reports (cycles included) must equal the model's, and the blocked words the exact
board's, with narrow filters (3 x 3 bits: many undecided tests in one broadcast, the queue
fills) and small credits. The host keeps the command stream full (the model's assumption).
"""

import functools

import numpy as np
import pytest
from amaranth.hdl import ClockDomain, Fragment, Module
from amaranth.sim import Simulator

from blockray.cell import Cell
from blockray.errors import ParameterError
from blockray.filtered import FilterFormat
from blockray.params import BoardParams
from blockray.protocol import ReadCounters, WritePatch
from blockray.rtl.board import BoardTop
from blockray.rtl.filtered import FilteredArray
from blockray.sim.drive import amaranth_cycle
from blockray.sim.filtered_model import default_array_depth
from blockray.timing import BoardTiming
from blockray.sim.model import BoardModel, ModelBoard

from board_host import BatchRun, check_run
from board_scenes import make_batch


def run_filtered(params, commands, *, fmt, depth, seed, kind="filtered"):
    dut = BoardTop(params, cell=Cell(kind, fmt), depth=depth)
    top = Module()
    top.domains.sync = ClockDomain()
    top.submodules.board = dut
    sim = Simulator(top)
    sim.add_clock(1e-8)
    run = BatchRun(params, commands, link="records", seed=seed, max_cycles=200_000)

    async def testbench(ctx):
        while not run.done:
            run.reset_due()
            run.after_cycle(await amaranth_cycle(ctx, run.stream, dut.commands, dut.results))

    sim.add_testbench(testbench)
    sim.run()
    return run.log


@pytest.mark.parametrize("seed,rows,cols,fmt,depth,kind", [
    (201, 2, 2, FilterFormat(3, 3), None, "filtered"),      # many undecided tests: the credits run out
    (202, 2, 3, FilterFormat(3, 3), 6, "filtered"),         # small credits: the broadcast stalls often
    (203, 3, 2, FilterFormat(4, 5), 9, "filtered"),
    (204, 2, 2, None, None, "filtered"),                    # the default format: (almost) all decided
    (205, 2, 2, FilterFormat(3, 3), None, "lean"),          # the tags re-read the patch memory
    (206, 2, 3, FilterFormat(3, 3), 6, "lean"),
    (207, 3, 2, FilterFormat(3, 3, 5), None, "lean"),       # the row units from 5-bit inputs
])
def test_filtered_board_equals_model(seed, rows, cols, fmt, depth, kind):
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=rows, cols=cols, bits=8)
    fmt = fmt or FilterFormat(9, 18)                # d_k exact at B = 8, w_k at 18 bits
    model = functools.partial(BoardModel, cell=Cell(kind, fmt), depth=depth)
    log = run_filtered(params, cmds, fmt=fmt, depth=depth, seed=seed, kind=kind)
    expect = check_run(params, cmds, log, model=lambda p, t: model(p, t))[0]
    # the blocked words are the exact board's, whatever the filter left undecided
    exact, filtered = BoardModel(params).execute(cmds), model(params).execute(cmds)
    assert [r for r in filtered.results if r.kind.name == "BLOCKED"] == \
        [r for r in exact.results if r.kind.name == "BLOCKED"]
    lost = filtered.cycles - exact.cycles
    print(f"board cycles: exact cell {exact.cycles}, filtered {filtered.cycles} ({lost} lost)")
    if fmt == FilterFormat(3, 3):
        assert lost > 0, "the test should make the array's credits run out"
    assert any(kind == "counters" for kind, _ in expect.values())


def _blocks(cmds):
    """(begin, end) command indices of each BEGIN_BLOCK .. END_BLOCK in ``cmds``."""
    begins = [i for i, c in enumerate(cmds) if c.op.name == "BEGIN_BLOCK"]
    return [(b, next(i for i in range(b, len(cmds)) if cmds[i].op.name == "END_BLOCK")) for b in begins]


def test_lean_board_rewrites_patches_after_the_array_drains():
    """The block with the most blocked tests again, and right behind it every patch rewritten as
    a point (which blocks nothing) while its undecided tests still wait for the lean exact unit.
    That unit re-reads their records from the patch memory, so each WRITE_PATCH waits until the
    array is empty (lost cycles, in the model too); bits and cycles equal the model's, the
    blocked words the exact board's (without the wait they read the points)."""
    seed, fmt = 209, FilterFormat(3, 3)       # its block with the most blocked bits needs the exact unit
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=2, bits=8)
    exact = BoardModel(params).execute(cmds)
    blocks = _blocks(cmds)
    b, e = max(blocks, key=lambda be: bin(exact.words[blocks.index(be)]).count("1"))
    rewrite = len(cmds) + e + 1 - b
    cmds = cmds + cmds[b:e + 1] + [WritePatch(a, 0) for a in range(params.patch_depth)] + cmds[b:e + 1]
    model = functools.partial(BoardModel, cell=Cell("lean", fmt))
    log = run_filtered(params, cmds, fmt=fmt, depth=None, seed=seed, kind="lean")
    check_run(params, cmds, log, model=lambda p, t: model(p, t))
    lean, exact = model(params).execute(cmds), BoardModel(params).execute(cmds)
    assert lean.words == exact.words and exact.words[-2] != 0 and exact.words[-1] == 0
    waited = lean.starts[rewrite + 1] - lean.starts[rewrite] - 1
    print(f"the rewrite waited {waited} cycles for the array to drain")
    assert waited > 0


def test_filtered_board_latencies_and_parameters():
    params = BoardParams(rows=2, cols=2, bits=8, patch_depth=4, voxel_depth=2)
    board = BoardTop(params, cell=Cell("filtered"))
    Fragment.get(board, None)
    assert board.cell == Cell("filtered", FilterFormat(9, 18))      # the default format at B = 8
    assert board.timing == BoardTiming.for_cell(Cell("filtered"))
    assert board.array_depth == default_array_depth() == FilteredArray.default_depth(board.memory_latency)
    assert board.result_queue_depth >= board.array_depth + 3
    with pytest.raises(ParameterError, match="cell must be one of exact, filtered, lean, not 'fast'"):
        Cell("fast")
    for build in (BoardTop, BoardModel):            # a kind's name alone is not a cell
        with pytest.raises(ParameterError, match="cell must be a Cell"):
            build(params, cell="filtered")


@pytest.mark.parametrize("fmt,depth", [(FilterFormat(3, 3), None), (FilterFormat(6, 8), None),
                                       (FilterFormat(3, 3), 3)])       # the READ_COUNTERS waits
def test_model_board_equals_command_streams(fmt, depth):
    """ModelBoard with the filtered cell gathers a batch at once (compiled: the undecided tests of
    every record, each board's clock); it equals each board's command stream, with the host's
    READ_COUNTERS behind it, run through BoardModel with that cell: bits, and cycles per board
    up to that snapshot (its wait for a credit included); its bits equal the exact cell's."""
    from blockray.samples import SampleScheme
    from board_scenes import BoxGrid, random_blocks, scattered_scene as random_scene

    samples = SampleScheme(8)
    scene = random_scene(5)
    boards = {}
    for cell in (Cell(), Cell("filtered", fmt)):
        board = ModelBoard(BoardParams(rows=4, cols=3, boards=3, bits=None), partition="deal", cell=cell,
                           depth=depth if cell.filtered else None)
        board.prepare(scene, samples)
        grid = BoxGrid(scene.patch_vertices, 3, margin=board.margin)
        board.load(grid)
        rng = np.random.default_rng(6)
        blocks = random_blocks(rng, scene, samples, board.params, 12, len(grid.voxel_patches))
        boards[cell.kind] = (board, board.run(blocks))
    board, bits = boards["filtered"]
    np.testing.assert_array_equal(bits.flat, boards["exact"][1].flat)
    c = board.counters()
    stream = [cmd for b in blocks for cmd in board.memory.block_commands(b)] + [ReadCounters()]
    for b in range(board.params.boards):
        res = board.board_model(b).execute(stream)
        assert res.counters[-1]["cycles"] == c["board_cycles_per_board"][b]
        assert res.tests_issued == c["tests_issued_per_board"][b]
    assert c["board_cycles"] == max(c["board_cycles_per_board"]) + board.timing.drain_latency
    lost = c["board_cycles"] - boards["exact"][0].counters()["board_cycles"]
    print(f"{fmt}: board_cycles exact cell {boards['exact'][0].counters()['board_cycles']}, filtered "
          f"{c['board_cycles']}")
    if fmt == FilterFormat(3, 3):
        assert lost > 0


@pytest.mark.parametrize("depth", [0, 2, 2.5])
def test_handoff_depth_below_three_is_refused(depth):
    """A 2-deep hand-off FIFO would drop a test the credits let in (the k-induction proof found
    it), so the array refuses such a depth when built, naming it."""
    with pytest.raises(ValueError, match="depth"):
        FilteredArray(8, 1, 2, depth=depth)
    built = FilteredArray(8, 1, 2, depth=3)
    built._MustUse__silence = True          # built, never elaborated: its warning would land in another test
