"""One board (the paper's figure 3): host interface, voxel-to-patch memory, R x S processor array.

The host sends one stream of commands and reads one stream of results
(:class:`~blockray.protocol.BoardProtocol` layouts; rtl/core.py puts the byte format of the link in front; docs/board-protocol.md). Commands run in
order, one at a time, in a single **execute slot**: a VOXEL occupies the memory controller's issue
slot, every other command the board's command register. The next command is taken from the
stream in the cycle the current one does its last step, so a busy host never costs a cycle, and
each command costs exactly what :class:`blockray.timing.BoardTiming` says::

    commands --> [command register | memory controller issue slot] --> patch memory
                        |                                                  |
                 point registers (written memory_latency later) ---> processor array
                        |                                                  |
                 masks, counters --> markers (drain_latency) --> result FIFO <-- accumulators

Every cycle is either a **board cycle** (a command makes progress) or a **stall** (the slot is
empty because the command stream was, or END_BLOCK / READ_COUNTERS waits for a result credit).
The ``cycles`` counter counts board cycles only, so it equals the model's cycle count whatever
the host's timing.

END_BLOCK, READ_COUNTERS and IDENTIFY take one cycle: each sends a **marker** (its kind, the block's row
and column masks, whether the block issued any record) down a register chain of drain_latency
stages, beside the pipeline, so it arrives exactly when the block's last record has reached the
accumulators and before the next block's first record has (that one issues after END_BLOCK).
There the result word is formed (the OR of the block's tests, masked; a READ_COUNTERS takes the
snapshot queued when it executed) and written to the result FIFO. The next block's BEGIN_BLOCK,
loads and records run while the previous block drains. ``result_queue_depth`` credits (results
in flight plus queued) make a host that does not read results stall the board, not lose them.

Ordering is exact (no hazards): a LOAD reaches the point registers :attr:`memory_latency` cycles
late, exactly when the records issued after it reach the array; BEGIN_BLOCK's accumulator clear
travels with the first record issued after it (``first``); the voxel table is read-transparent.

Latencies: :attr:`memory_latency` (issue to array input), :attr:`processor_latency` (array input
to accumulators), :attr:`drain_latency` = memory_latency + processor_latency - 1 (END_BLOCK starts
the cycle after the last issue). :attr:`timing` is the matching :class:`BoardTiming`.

Reset (the ``sync`` domain's synchronous reset) empties the command register, the issue slot, the
pipeline, the markers and the result FIFO, the masks, accumulators and counters. Memory contents are not
reset but the protocol treats them as lost: after a reset the host reloads and replays.
"""

from types import SimpleNamespace

from amaranth.hdl import Cat, Const, Module, Mux, Signal
from amaranth.lib import data, stream, wiring
from amaranth.lib.fifo import SyncFIFO, SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from ..errors import ParameterError
from ..params import BoardParams
from ..records import point_layout
from ..board_rays import RayProtocol
from ..protocol import POINTS_PER_LOAD, BoardProtocol, Op, ResultKind
from ..timing import BoardTiming
from ..cell import Cell, check_cell
from .array import ProcessorArray
from .filtered import FilteredArray
from .lean import LeanArray
from .memctrl import MemoryController
from .sequencer import BlockSequencer, item_layout
from .processor import ArrayTiming, _delay

__all__ = ["BoardTop"]


def _popcount(value):
    return sum((value[i] for i in range(len(value))), Const(0, range(len(value) + 1)))


class BoardTop(wiring.Component):
    """One board: ``commands`` in, ``results`` out.

    Parameters: ``params`` (:class:`~blockray.params.BoardParams`; ``boards`` is ignored: a board
    is one of the P); ``patch_init`` / ``table_init`` optional memory contents (tests); ``cell``
    the array's :class:`~blockray.cell.Cell` (exact or filtered; its format at ``params.bits``).

    Ports
    ``commands``  In stream of :attr:`protocol` ``.command_layout``.
    ``results``   Out stream of :attr:`protocol` ``.result_layout``, from the output register
                  of a FIFO. No ``valid`` or ``ready`` depends combinationally on a port of
                  the other stream.
    ``rays``      with ``rays``: In stream of the block sequencer's items
                  (:func:`~blockray.rtl.sequencer.item_layout`); its records take the command
                  stream's place while it offers them (rtl/core.py keeps the two in order).
    ``idle``      with ``rays``: Out, no command in the execute slot.
    """

    def __init__(self, params, *, patch_init=(), table_init=(), cell=Cell(), depth=None, rays=False):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        if not isinstance(params, BoardParams):
            raise ParameterError(f"board needs BoardParams, not {params!r}")
        self._cell = check_cell(cell).at(params.bits)
        array = LeanArray if self._cell.lean else FilteredArray
        self._depth = depth if depth is not None else array.default_depth(MemoryController.latency)
        self._params = params
        self._protocol = BoardProtocol(params)
        self._patch_init, self._table_init = patch_init, table_init
        self._array_timing = ArrayTiming(params.bits)
        self._rays = rays
        super().__init__({
            "commands": In(stream.Signature(self._protocol.command_layout)),
            "results": Out(stream.Signature(self._protocol.result_layout)),
        } | ({"rays": In(stream.Signature(item_layout(RayProtocol(params)))), "idle": Out(1)} if rays else {}))
        self._MustUse__silence = False

    @property
    def params(self):
        return self._params

    @property
    def protocol(self):
        return self._protocol

    @property
    def cell(self):
        """The array's :class:`~blockray.cell.Cell`, exact or filtered, its format chosen."""
        return self._cell

    @property
    def array_depth(self):
        """The filtered array's credits: items (records and markers) issued and not delivered."""
        return self._depth

    @property
    def memory_latency(self):
        """Cycles from a record's issue to the array's input (memory read + broadcast register)."""
        return MemoryController.latency

    @property
    def processor_latency(self):
        """Cycles from the array's input to the accumulators (the filtered array's least: a
        record with no undecided test, to its delivery and the accumulator's register)."""
        if self._cell.filtered:
            return (LeanArray if self._cell.lean else FilteredArray).latency + 3
        return self._array_timing.latency

    @property
    def latency(self):
        """Cycles from a record's issue to its blocked bits in the accumulators."""
        return self.memory_latency + self.processor_latency

    @property
    def drain_latency(self):
        """Cycles from END_BLOCK's own cycle to the one that forms its result word (the marker
        register chain); the next commands run meanwhile."""
        return self.latency - 1

    @property
    def result_queue_depth(self):
        """Results that may be in flight or queued at once (markers plus the result FIFO). One
        more than a result every cycle for drain_latency + 2 cycles needs, so a host that reads
        at once never stalls the board."""
        if self._cell.filtered:          # markers wait in the array: as many as its credits
            return max(self.drain_latency, self._depth) + 3
        return self.drain_latency + 3

    @property
    def timing(self):
        return BoardTiming(processor_latency=self.processor_latency, memory_latency=self.memory_latency)

    def elaborate(self, platform):
        # one method per stage, in the order the board's signals are made (the Verilog keeps it);
        # the stages share their signals through ``w``
        m, w = Module(), SimpleNamespace(filtered=self._cell.filtered, lean=self._cell.lean)
        self._units(m, w)
        self._fetch(m, w)
        self._result_queue(m, w)
        self._execute(m, w)
        self._point_registers(m, w)
        self._feed_array(m, w)
        self._counters(m, w)
        self._markers_and_results(m, w)
        return m

    def _units(self, m, w):
        p = self._params
        R, S = p.rows, p.cols
        m.submodules.memctrl = mc = MemoryController(p, patch_init=self._patch_init, table_init=self._table_init,
                                                     rays=self._rays, exact_read=w.lean)
        marker_layout = data.StructLayout({
            "valid": 1, "counters": 1, "identify": 1, "fresh": 1, "rows": R, "cols": S,
        })
        if w.lean:
            m.submodules.array = array = LeanArray(p.bits, R, S, fmt=self._cell.format, depth=self._depth,
                                                   mark_shape=marker_layout,
                                                   address_bits=self._protocol.address_width)
        elif w.filtered:
            m.submodules.array = array = FilteredArray(p.bits, R, S, fmt=self._cell.format, depth=self._depth,
                                                       mark_shape=marker_layout)
        else:
            m.submodules.array = array = ProcessorArray(p.bits, R, S)
            assert array.latency == self.processor_latency
        assert mc.latency == self.memory_latency
        w.mc, w.array, w.marker_layout = mc, array, marker_layout

    def _sequencer(self, m, w):
        """With ``rays``: the block sequencer between ``rays`` and the command stream. The core
        keeps the order: a record waits while the sequencer is busy, an item until ``idle`` (no
        command in the execute slot: the memory writes before it are done)."""
        if not self._rays:
            return self.commands
        m.submodules.sequencer = seq = BlockSequencer(self._params)
        wiring.connect(m, wiring.flipped(self.rays), seq.commands)
        wiring.connect(m, seq.patch_read, w.mc.rays_patch)
        wiring.connect(m, seq.table_read, w.mc.rays_table)
        source = stream.Signature(self._protocol.command_layout).create()
        own = seq.records.valid
        m.d.comb += [source.valid.eq(own | self.commands.valid),
                     source.payload.eq(Mux(own, seq.records.payload, self.commands.payload)),
                     seq.records.ready.eq(source.ready), self.commands.ready.eq(source.ready & ~own),
                     self.idle.eq(~w.cur_valid)]
        return source

    def _fetch(self, m, w):
        """The head of the command stream goes to the free execute slot."""
        mc = w.mc
        cur = Signal(self._protocol.command_layout)
        cur_valid = Signal()
        w.cur_valid = cur_valid
        commands = self._sequencer(m, w)
        cur_done = Signal()                              # cur does its last step this cycle
        cur_step = Signal()                              # cur makes progress this cycle
        cur_free = ~cur_valid | cur_done
        head = commands.payload
        head_voxel = head.op == Op.VOXEL
        m.d.comb += [
            mc.voxels.valid.eq(commands.valid & head_voxel & cur_free),
            mc.voxels.payload.eq(head.arg.voxel.voxel),
            commands.ready.eq(cur_free & mc.free),
        ]
        pop = commands.valid & commands.ready
        with m.If(pop & ~head_voxel):
            m.d.sync += [cur.eq(head), cur_valid.eq(1)]
        with m.Elif(cur_done):
            m.d.sync += cur_valid.eq(0)
        w.cur, w.cur_valid, w.cur_done, w.cur_step = cur, cur_valid, cur_done, cur_step

    def _result_queue(self, m, w):
        """END_BLOCK and READ_COUNTERS take one cycle each; their result follows the block's last
        record through the pipeline as a marker (drain_latency registers), so the next block
        streams while this one drains. Credits bound the results in flight plus those queued, so a
        host that does not read results stalls the board, never loses one."""
        proto = self._protocol
        queue_depth = self.result_queue_depth
        m.submodules.results = results = SyncFIFOBuffered(width=proto.result_layout.size, depth=queue_depth)
        m.submodules.snapshots = snapshots = SyncFIFO(width=proto.counters_layout.size,
                                                      depth=queue_depth if w.filtered else self.drain_latency + 1)
        outstanding = Signal(range(queue_depth + 1))
        credit = outstanding < queue_depth
        marker = Signal(w.marker_layout)
        leave = self.results.valid & self.results.ready
        m.d.sync += outstanding.eq(outstanding + marker.valid - leave)
        m.d.comb += [
            self.results.valid.eq(results.r_rdy),
            self.results.payload.eq(results.r_data),
            results.r_en.eq(self.results.ready),
        ]
        w.results, w.snapshots, w.credit, w.marker = results, snapshots, credit, marker

    def _execute(self, m, w):
        """Every command in the command register takes one cycle; END_BLOCK and READ_COUNTERS
        wait (stall) for a result credit."""
        mc, cur, cur_valid = w.mc, w.cur, w.cur_valid
        op = cur.op
        needs_result = (op == Op.END_BLOCK) | (op == Op.READ_COUNTERS) | (op == Op.IDENTIFY)
        # the filtered array's credits: records and markers issued and not yet delivered (it
        # delivers in order and late when tests wait for the exact unit); without a credit the
        # issue slot and the markers wait: cycles lost, counted as board cycles
        array_credit = Signal(init=1)
        drain = Signal()        # lean: a WRITE_PATCH waits until no tag can re-read the memory
        lost = Signal()
        if w.filtered:
            inside = Signal(range(self._depth + 1))
            if w.lean:
                m.d.comb += drain.eq(cur_valid & (op == Op.WRITE_PATCH) & (inside != 0))
            m.d.comb += [array_credit.eq(inside < self._depth), mc.enable.eq(array_credit),
                         lost.eq((~array_credit & (~mc.free | (cur_valid & needs_result))) | drain)]
            m.d.sync += inside.eq(inside + (mc.issue | (w.cur_step & needs_result)) - w.array.delivered)
        m.d.comb += [
            w.cur_step.eq(cur_valid & (~needs_result | (w.credit & array_credit)) & ~drain),
            w.cur_done.eq(w.cur_step),
        ]

        m.d.comb += [
            mc.patch_write.valid.eq(cur_valid & (op == Op.WRITE_PATCH) & ~drain),
            mc.patch_write.payload.eq(cur.arg.write_patch),
            mc.table_write.valid.eq(cur_valid & (op == Op.WRITE_VOXEL)),
            mc.table_write.payload.eq(cur.arg.write_voxel),
        ]
        w.op, w.needs_result, w.lost = op, needs_result, lost

    def _point_registers(self, m, w):
        """The masks of the rows / columns loaded since BEGIN_BLOCK, and the point registers."""
        p, proto, cur, cur_valid, op = self._params, self._protocol, w.cur, w.cur_valid, w.op
        R, S = p.rows, p.cols
        # masks: effective at once (they count useful tests at issue and mask the result word)
        row_valid = Signal(R)
        col_valid = Signal(S)
        fresh = Signal(init=1)               # no record issued since BEGIN_BLOCK (or reset)
        with m.If(cur_valid & (op == Op.BEGIN_BLOCK)):
            m.d.sync += [row_valid.eq(0), col_valid.eq(0), fresh.eq(1)]
        with m.If(w.mc.issue):
            m.d.sync += fresh.eq(0)

        # point registers, written memory_latency cycles after the LOAD: records issued before
        # the LOAD have reached the array by then, those issued after it have not. A LOAD_POINTS
        # writes up to POINTS_PER_LOAD of them (a later slot wins); a single LOAD uses slot 0.
        point = point_layout(p.bits)
        write_layout = data.StructLayout({
            "receiver": 1, "shooter": 1, "index": proto.point_slot_layout["index"].shape, "point": point,
        })
        writes = Signal(data.ArrayLayout(write_layout, POINTS_PER_LOAD))
        load_points = cur_valid & (op == Op.LOAD_POINTS)
        for k in range(POINTS_PER_LOAD):
            slot = cur.arg.load_points[k]
            m.d.comb += [
                writes[k].receiver.eq(load_points & slot.valid & ~slot.shooter),
                writes[k].shooter.eq(load_points & slot.valid & slot.shooter),
                writes[k].index.eq(slot.index),
                writes[k].point.eq(slot.point),
            ]
        with m.If(cur_valid & (op == Op.LOAD_RECEIVER)):
            m.d.comb += [writes[0].receiver.eq(1), writes[0].index.eq(cur.arg.load_receiver.row),
                         writes[0].point.eq(cur.arg.load_receiver.point)]
        with m.If(cur_valid & (op == Op.LOAD_SHOOTER)):
            m.d.comb += [writes[0].shooter.eq(1), writes[0].index.eq(cur.arg.load_shooter.col),
                         writes[0].point.eq(cur.arg.load_shooter.point)]
        # masks: effective at once (they count useful tests at issue and travel with END_BLOCK)
        for k in range(POINTS_PER_LOAD):
            with m.If(writes[k].receiver):
                m.d.sync += row_valid.bit_select(writes[k].index, 1).eq(1)
            with m.If(writes[k].shooter):
                m.d.sync += col_valid.bit_select(writes[k].index, 1).eq(1)
        late = _delay(m, writes, self.memory_latency - 1, "writes")
        receivers = Signal(data.ArrayLayout(point, R))
        shooters = Signal(data.ArrayLayout(point, S))
        for k in range(POINTS_PER_LOAD):
            for r in range(R):
                with m.If(late[k].receiver & (late[k].index == r)):
                    m.d.sync += receivers[r].eq(late[k].point)
            for s in range(S):
                with m.If(late[k].shooter & (late[k].index == s)):
                    m.d.sync += shooters[s].eq(late[k].point)
        w.row_valid, w.col_valid, w.fresh, w.receivers, w.shooters = row_valid, col_valid, fresh, receivers, shooters

    def _feed_array(self, m, w):
        mc, array = w.mc, w.array
        first = _delay(m, mc.issue & w.fresh, self.memory_latency, "first")
        m.d.comb += [
            array.patch.eq(mc.records.payload),
            array.valid.eq(mc.records.valid),
            array.first.eq(first),
            array.receivers.eq(w.receivers),
            array.shooters.eq(w.shooters),
        ]
        if w.lean:          # the exact unit re-reads an undecided test's record
            m.d.comb += array.address.eq(mc.record_address)
            m.d.comb += [mc.exact_patch.addr.eq(array.patch_read.addr), mc.exact_patch.en.eq(array.patch_read.en),
                         array.patch_read.data.eq(mc.exact_patch.data)]
        if w.filtered:      # the masks and markers as seen by the records issued with them
            m.d.comb += [
                array.row_mask.eq(_delay(m, w.row_valid, self.memory_latency, "row_mask")),
                array.col_mask.eq(_delay(m, w.col_valid, self.memory_latency, "col_mask")),
                array.mark.eq(_delay(m, w.marker.valid, self.memory_latency, "mark")),
                array.mark_data.eq(_delay(m, w.marker, self.memory_latency, "mark_data")),
            ]

    def _counters(self, m, w):
        p = self._params
        counters = Signal(self._protocol.counters_layout)
        work = w.cur_step | w.mc.step | w.lost
        useful = _popcount(w.row_valid) * _popcount(w.col_valid)
        m.d.sync += [
            counters.cycles.eq(counters.cycles + work),
            counters.stalls.eq(counters.stalls + ~work),
        ]
        with m.If(w.mc.issue):
            m.d.sync += [
                counters.busy.eq(counters.busy + 1),
                counters.tests_issued.eq(counters.tests_issued + p.rows * p.cols),
                counters.tests_useful.eq(counters.tests_useful + useful),
            ]
        w.counters = counters

    def _markers_and_results(self, m, w):
        """Markers enter in the command's own cycle and leave drain_latency cycles later, when
        the block's last record has reached the accumulators and the next block's first record
        has not (it issues after END_BLOCK); the counter snapshot is taken on entry."""
        proto, op, marker, snapshots = self._protocol, w.op, w.marker, w.snapshots
        R, S = self._params.rows, self._params.cols
        m.d.comb += [
            marker.valid.eq(w.cur_step & w.needs_result),
            marker.counters.eq(op == Op.READ_COUNTERS),
            marker.identify.eq(op == Op.IDENTIFY),
            marker.fresh.eq(w.fresh),
            marker.rows.eq(w.row_valid),
            marker.cols.eq(w.col_valid),
            snapshots.w_en.eq(marker.valid & marker.counters),
            snapshots.w_data.eq(w.counters),
        ]
        if w.filtered:      # markers leave the array in order, after every record before them
            done = Signal(w.marker_layout)
            m.d.comb += [done.eq(w.array.mark_data_out), done.valid.eq(w.array.mark_out)]
        else:
            done = _delay(m, marker, self.drain_latency, "marker")
        mask = Cat(done.rows[r] & done.cols[s] for r in range(R) for s in range(S))
        result = Signal(proto.result_layout)
        with m.If(done.counters):
            m.d.comb += [
                result.kind.eq(ResultKind.COUNTERS),
                result.data.counters.eq(snapshots.r_data),
            ]
        with m.Elif(done.identify):
            m.d.comb += [
                result.kind.eq(ResultKind.IDENTITY),
                result.data.identity.eq(proto.identity_layout.const(proto.identity(rays=self._rays, cell=self._cell))),
            ]
        with m.Else():
            m.d.comb += [
                result.kind.eq(ResultKind.BLOCKED),
                result.data.blocked.eq(Mux(done.fresh, 0, w.array.hit & mask)),
            ]
        m.d.comb += [
            snapshots.r_en.eq(done.valid & done.counters),
            w.results.w_en.eq(done.valid),
            w.results.w_data.eq(result),
        ]
