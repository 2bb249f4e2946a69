"""The bit-exact board model: exactly what the hardware computes, with the same cycle counts.

Two levels:

* :class:`BoardModel` is **one board** driven by its command stream, the RTL-facing contract. An
  RTL testbench feeds the same list of commands to the RTL and to
  :meth:`BoardModel.execute` and compares result words and cycle counts with zero tolerance.
* :class:`ModelBoard` is the host's :class:`~blockray.board.Board`: ``P`` boards,
  each holding a disjoint part of the voxels' patch records (:class:`blockray.memory.BoardMemories`),
  run block rays and OR their bits. It computes the same memories, bits and cycles as building each
  board's command stream and executing it (a test checks that), but gathers a whole block's records
  at once. It is a model of the hardware only: the host's side (commands, encoding, transports)
  is host_driver/board/driver.py.

Commands are the typed records of :mod:`blockray.protocol` (docs/board-protocol.md); their costs
:class:`blockray.timing.BoardTiming`. Result word: bit ``r * S + s`` is 1 when the ray from
shooter column s to receiver row r is blocked by some streamed record (rows/columns not loaded in
the block are 0). The memories and the partition over the boards: :mod:`blockray.memory`.

Counters: ``tests_issued`` = R x S per record streamed (every processor sees every broadcast, used
or not); ``tests_useful`` = real rays x records streamed; ``utilization`` = useful / (processors x
cycles). The host sends each batch of blocks (one :meth:`ModelBoard.run`) to every board without
waiting, and waits for the last result word: a batch's machine time is the slowest board's board
cycles for the batch plus the drain of its last END_BLOCK (``drain_latency``); ``board_cycles``
sums that over batches. Memory loading is counted apart (``load_cycles``).
"""

from dataclasses import dataclass, field

import numpy as np

from ..board import BlockBatch, BlockBits, CountingBoard
from ..cell import Cell, check_cell
from ..errors import ParameterError
from ..filtered import filtered_block
from ..fixedpoint import DEFAULT_MAX_ERROR
from ..memory import BoardMemories, QuantisationWarning, check_partition, ranges
from ..params import BoardParams
from ..protocol import POINTS_PER_LOAD, BoardProtocol, BoardResult, Op, ResultKind
from ..records import patch_layout, unpack_array
from ..timing import BoardTiming
from . import kernel
from .filtered_model import (EXACT_LATENCY, ISSUE_TO_HANDOFF, STEP_BUBBLE, STEP_DRAIN, STEP_MARKER, STEP_PLAIN, STEP_RECORD,
                             board_clock, default_array_depth)
from .lean_model import LEAN_EXACT_INTERVAL, LEAN_EXACT_LATENCY, LEAN_HANDOFF_STAGES, default_lean_depth


def _exact_unit(cell):
    """:func:`board_clock`'s shared exact unit of a filtering cell (filtered: a Processor, a test
    a cycle; lean: LeanExact, behind the hand-off register), as keyword arguments."""
    if cell.lean:
        return {"exact_latency": LEAN_EXACT_LATENCY, "exact_interval": LEAN_EXACT_INTERVAL,
                "issue_to_handoff": ISSUE_TO_HANDOFF + LEAN_HANDOFF_STAGES}
    return {"exact_latency": EXACT_LATENCY, "exact_interval": 1}


def _array_depth(cell):
    """The board's array credits of the filtered or lean cell."""
    return default_lean_depth() if cell.lean else default_array_depth()

__all__ = ["ExecResult", "BoardModel", "ModelBoard", "QuantisationWarning", "result_word"]



@dataclass
class ExecResult:
    words: list = field(default_factory=list)        # one int per END_BLOCK (bit r*S + s)
    blocked: list = field(default_factory=list)      # the same as (R, S) bool arrays
    cycles: int = 0                                   # board cycles of the whole stream
    starts: list = field(default_factory=list)       # cycle at which each command began
    tests_issued: int = 0
    tests_useful: int = 0
    busy: int = 0                                     # cycles that issued a patch record
    counters: list = field(default_factory=list)     # one dict per READ_COUNTERS (cycles, busy, tests_issued, tests_useful)
    results: list = field(default_factory=list)      # every result in order, as BoardResult


def result_word(bits):
    """(R, S) bool -> int with bit r*S + s set where blocked."""
    flat = np.asarray(bits, dtype=bool).ravel()
    return int(sum(1 << int(i) for i in np.flatnonzero(flat)))


def _any_blocked(P, Q, V, n):
    """OR over records of the exact predicate: (R, S) bool (the compiled kernel)."""
    return kernel.any_blocked(np.ascontiguousarray(P, dtype=np.int64), np.ascontiguousarray(Q, dtype=np.int64),
                              np.ascontiguousarray(V, dtype=np.int64), np.ascontiguousarray(n, dtype=np.int64))


class BoardModel:
    """One board: patch memory, voxel table, an R x S processor array, driven by commands.

    Memory contents are the unpacked patch records (``vertices``, ``normals``), so what the model
    tests is what the packed memory image holds. ``cell``: the array's
    :class:`~blockray.cell.Cell` (its format chosen at ``params.bits``); a filtering one has
    ``depth`` credits (default: its array's). ``rays``: the board built with the block sequencer
    (its IDENTIFY answers :data:`~blockray.protocol.RAYS_VERSION`; the sequencer's model is
    :class:`~blockray.sim.sequencer.BlockSequencer`, in front of this one).
    """

    def __init__(self, params, timing=None, *, cell=Cell(), depth=None, rays=False):
        self.params = params
        self.rays = rays
        self.cell = check_cell(cell).at(params.bits)
        if cell.filtered:               # filtered or lean: the same hand-off, its exact unit's latency
            self.depth = depth or _array_depth(cell)
        self.timing = timing or BoardTiming.for_cell(cell)
        self.layout = patch_layout(params.bits)
        self.protocol = BoardProtocol(params)
        self.vertices = np.zeros((params.patch_depth, 3, 3), dtype=np.int64)
        self.normals = np.zeros((params.patch_depth, 3), dtype=np.int64)
        self.start = np.zeros(params.voxel_depth, dtype=np.int64)
        self.count = np.zeros(params.voxel_depth, dtype=np.int64)
        self._begin()

    def _begin(self):
        R, S = self.params.rows, self.params.cols
        self.receivers = np.zeros((R, 3), dtype=np.int64)
        self.shooters = np.zeros((S, 3), dtype=np.int64)
        self.row_valid = np.zeros(R, dtype=bool)
        self.col_valid = np.zeros(S, dtype=bool)
        self.pending = []

    def load_memory(self, vertices, normals, start, count):
        """Bulk memory load (same state as the WRITE_PATCH / WRITE_VOXEL commands)."""
        n, v = len(vertices), len(start)
        self.vertices[:n] = vertices
        self.normals[:n] = normals
        self.start[:v] = start
        self.count[:v] = count

    def _check_voxel(self, v):
        if not 0 <= v < self.params.voxel_depth:
            raise ParameterError(f"voxel {v} is outside the voxel table (voxel_depth {self.params.voxel_depth})")

    def execute(self, commands):
        """Run a command stream; return an :class:`ExecResult` (results, cycles, per-command starts)."""
        p, t = self.params, self.timing
        R, S = p.rows, p.cols
        res = ExecResult()
        filtered = self.cell.filtered
        kinds, undecided, ends = [], [], []          # the filtered board's steps; each command's last
        for cmd in commands:
            op = cmd.op
            res.starts.append(res.cycles)
            count = 0
            if filtered:
                self._filtered_steps(cmd, kinds, undecided)
                ends.append(len(kinds))
            if op is Op.WRITE_PATCH:
                if not 0 <= cmd.address < p.patch_depth:
                    raise ParameterError(f"patch address {cmd.address} is outside patch memory (patch_depth {p.patch_depth})")
                cols = unpack_array(self.layout, [cmd.patch])
                self.vertices[cmd.address] = [[cols[(k, a)][0] for a in "xyz"] for k in ("v0", "v1", "v2")]
                self.normals[cmd.address] = [cols[("normal", a)][0] for a in "xyz"]
            elif op is Op.WRITE_VOXEL:
                self._check_voxel(cmd.voxel)
                if cmd.start < 0 or cmd.count < 0 or cmd.start + cmd.count > p.patch_depth:
                    raise ParameterError(f"voxel entry ({cmd.start}, {cmd.count}) is outside patch memory "
                                         f"(patch_depth {p.patch_depth})")
                self.start[cmd.voxel], self.count[cmd.voxel] = cmd.start, cmd.count
            elif op is Op.BEGIN_BLOCK:
                self._begin()
            elif op is Op.LOAD_RECEIVER:
                self.receivers[cmd.row] = cmd.point
                self.row_valid[cmd.row] = True
            elif op is Op.LOAD_SHOOTER:
                self.shooters[cmd.col] = cmd.point
                self.col_valid[cmd.col] = True
            elif op is Op.LOAD_POINTS:
                for shooter, where, point in cmd.slots:       # in order: a later slot wins
                    if shooter:
                        self.shooters[where] = point
                        self.col_valid[where] = True
                    else:
                        self.receivers[where] = point
                        self.row_valid[where] = True
            elif op is Op.VOXEL:
                self._check_voxel(cmd.voxel)
                count = int(self.count[cmd.voxel])
                self.pending.append((int(self.start[cmd.voxel]), count))
                res.tests_issued += R * S * count
                res.busy += count
                res.tests_useful += int(self.row_valid.sum()) * int(self.col_valid.sum()) * count
            elif op is Op.END_BLOCK:
                bits = self._evaluate()
                res.blocked.append(bits)
                res.words.append(result_word(bits))
                res.results.append(BoardResult(ResultKind.BLOCKED, blocked=res.words[-1]))
            elif op is Op.READ_COUNTERS:
                res.counters.append({"cycles": res.cycles, "busy": res.busy,
                                     "tests_issued": res.tests_issued, "tests_useful": res.tests_useful})
                res.results.append(BoardResult(ResultKind.COUNTERS, counters=res.counters[-1]))
            elif op is Op.IDENTIFY:
                res.results.append(BoardResult(ResultKind.IDENTITY, identity=self.protocol.identity(rays=self.rays, cell=self.cell)))
            res.cycles += t.cost(op, count)
        if filtered:
            self._add_lost_cycles(res, commands, kinds, undecided, ends)
        return res

    def _filtered_steps(self, cmd, kinds, undecided):
        """Append command ``cmd``'s steps on the filtered board (:func:`board_clock`)."""
        op = cmd.op
        if op is Op.VOXEL:
            self._check_voxel(cmd.voxel)
            start, count = int(self.start[cmd.voxel]), int(self.count[cmd.voxel])
            u = self._undecided(start, count)
            kinds += [STEP_RECORD] * count if count else [STEP_BUBBLE]
            undecided += list(u) if count else [0]
        elif op in (Op.END_BLOCK, Op.READ_COUNTERS, Op.IDENTIFY):
            kinds.append(STEP_MARKER)
            undecided.append(0)
        elif op is Op.WRITE_PATCH and self.cell.lean:       # no tag may re-read the old record
            kinds.append(STEP_DRAIN)
            undecided.append(0)
        else:
            kinds.append(STEP_PLAIN)
            undecided.append(0)

    def _add_lost_cycles(self, res, commands, kinds, undecided, ends):
        """The cycles lost waiting for the filtered array's credits: in the total, in each
        command's start and in each READ_COUNTERS snapshot (its own wait included: it precedes
        the snapshot)."""
        lost, _ = board_clock(np.array(kinds, dtype=np.int64), np.array(undecided, dtype=np.int64),
                                      self.depth, **_exact_unit(self.cell))
        before = np.concatenate([[0], np.cumsum(lost)])
        snapshots = iter(res.counters)
        begin = 0
        for i, (cmd, end) in enumerate(zip(commands, ends)):
            res.starts[i] += int(before[begin])
            if cmd.op is Op.READ_COUNTERS:
                next(snapshots)["cycles"] += int(before[begin + 1])
            begin = end
        res.cycles += int(before[-1])

    def _undecided(self, start, count):
        """(count,) the undecided tests of each record of the loaded rows and columns (what the
        filtered array sends to its exact unit)."""
        rows, cols = np.flatnonzero(self.row_valid), np.flatnonzero(self.col_valid)
        if not len(rows) or not len(cols):
            return np.zeros(count, dtype=np.int64)
        idx = np.arange(start, start + count)
        decided, _ = filtered_block(self.shooters[cols], self.receivers[rows], self.vertices[idx],
                                    self.normals[idx], self.cell.format)
        return (~decided).sum(axis=(0, 1))

    def _evaluate(self):
        rows, cols = np.flatnonzero(self.row_valid), np.flatnonzero(self.col_valid)
        out = np.zeros((self.params.rows, self.params.cols), dtype=bool)
        if self.pending and len(rows) and len(cols):
            starts, counts = zip(*self.pending)
            idx = ranges(starts, counts)
            sub = _any_blocked(self.shooters[cols], self.receivers[rows], self.vertices[idx], self.normals[idx])
            out[np.ix_(rows, cols)] = sub
        return out


def _row_ends(q, batch):
    """The kernels' end-point table and each row's index into it: the centroids by patch, or the
    batch's own points row by row."""
    if batch.receiver_weights is None:
        return q.receivers, batch.receiver_patch
    return q.end_points(batch.receiver_patch, batch.receiver_weights), np.arange(len(batch.receiver_patch))


class ModelBoard(CountingBoard):
    """P bit-exact boards behind the host's Board interface (``--board model``).

    ``params.bits=None`` (the default params') chooses B per scene
    (:func:`blockray.fixedpoint.choose_bits`); an int forces it (``--bits``). Once the scene is
    quantised, ``params.bits`` is the B used. ``partition``: how the
    patch records are spread over the P boards (:data:`PARTITIONS`, ``--partition``).
    ``cell``: the boards' :class:`~blockray.cell.Cell`; once the scene is quantised, ``cell``
    holds it with its format chosen for that B.
    """

    name = "model"

    def __init__(self, params=None, *, timing=None, max_error=DEFAULT_MAX_ERROR, partition="deal",
                 cell=Cell(), depth=None):
        self._take(params or BoardParams(bits=None))
        self.cell = self._asked_cell = check_cell(cell)
        self.depth = depth or _array_depth(self.cell)
        self.partition = check_partition(partition)
        self.max_error = max_error
        self._timing = timing
        self.timing = None
        self.quantised = None
        self.margin = 0.0
        self.memories = None
        self._reset_counters()

    # -- Board interface -------------------------------------------------------------------------

    def prepare(self, scene, samples):
        q = self._quantise(scene, samples)
        self.cell = self._asked_cell.at(q.bits)
        self.memories = None

    def load(self, grid):
        if self.quantised is None:
            raise RuntimeError("prepare() before load()")
        q = self.quantised
        self.memory = BoardMemories(q, grid, self.params, self.partition)
        self.memories = self.memory.memories
        nvox = self.memory.nvox
        # all boards' records in one array (board b at offset[b]) for one gather per block
        self._offset = np.cumsum([0] + [len(m["patch"]) for m in self.memories])
        allrec = np.concatenate([m["patch"] for m in self.memories])
        self._V = q.vertices[allrec]
        self._n = q.normals[allrec]
        self._start = np.stack([m["start"] + o for m, o in zip(self.memories, self._offset)])   # (P, nvox)
        self._count = np.stack([m["count"] for m in self.memories])                          # (P, nvox)
        self.load_cycles = [len(m["patch"]) + nvox for m in self.memories]

    def run(self, blocks):
        """Blocked bits of a batch (a list of BlockRay or a BlockBatch), as :class:`BlockBits`."""
        if self.memories is None:
            raise RuntimeError("load() before run()")
        q, p = self.quantised, self.params
        batch = BlockBatch.from_blocks(blocks)
        Rb, Sb = batch.rows, batch.cols
        too_big = np.flatnonzero((Rb > p.rows) | (Sb > p.cols))
        if len(too_big):
            self.check_block(batch[int(too_big[0])])
        ends, end_of_row = _row_ends(q, batch)
        bits, records, streamed = kernel.run_blocks(
            q.shooters, ends, batch.col_off, batch.shooter_patch, batch.shooter_sample,
            batch.row_off, end_of_row, batch.vox_off, batch.voxels,
            self._start, self._count, self._V, self._n, batch.ray_off)
        cycles = self.timing.blocks_cycles(Rb, Sb, streamed)
        if self.cell.filtered:
            self._add_filtered_batch(batch, cycles)
        else:
            # cycles and counters depend on the records streamed only, never on the tests' results
            self._add_batch(cycles.sum(axis=0))
        self._issued_b += p.processors * records.sum(axis=0)
        self._useful_b += ((Rb * Sb)[:, None] * records).sum(axis=0)
        self._blocks += len(batch)
        self._rays += int((Rb * Sb).sum())
        return BlockBits(bits, Rb, Sb)

    def _add_filtered_batch(self, batch, cycles):
        """The filtered board's cycles of a batch: each board's command stream on its clock
        (:func:`~blockray.sim.filtered_model.board_clock`: cycles lost waiting for the array's
        credits), from every record's undecided tests. The batch ends with the host's
        READ_COUNTERS, whose wait for a credit precedes its snapshot: the batch's (its own cycle is
        the next batch's, as on the board, :mod:`blockray.host_driver.board.driver`)."""
        q, f = self.quantised, self.cell.format
        loads = -(-(batch.rows + batch.cols) // POINTS_PER_LOAD)
        step_off = np.vstack([np.zeros((1, cycles.shape[1]), np.int64), np.cumsum(cycles, axis=0)])
        ends, end_of_row = _row_ends(q, batch)
        kinds, undecided = kernel.filtered_steps(
            q.shooters, ends, batch.col_off, batch.shooter_patch, batch.shooter_sample,
            batch.row_off, end_of_row, batch.vox_off, batch.voxels,
            self._start, self._count, self._V, self._n, loads, f.d_bits, f.w_bits, step_off, f.w_input_bits or 0)
        total = cycles.sum(axis=0)
        for b, steps in enumerate(step_off[-1]):
            lost, _ = board_clock(np.append(kinds[b, :steps], STEP_MARKER), np.append(undecided[b, :steps], 0),
                                  self.depth, **_exact_unit(self.cell))
            total[b] += lost.sum()
        self._add_batch(total)

    # -- the model of each board ----------------------------------------------------------------------

    def board_model(self, board):
        """A :class:`BoardModel` whose memories hold board ``board``'s partition (bulk-loaded)."""
        m = self.memories[board]
        q = self.quantised
        bm = BoardModel(self.params, self.timing, cell=self.cell, depth=self.depth)
        bm.load_memory(q.vertices[m["patch"]], q.normals[m["patch"]], m["start"], m["count"])
        return bm
