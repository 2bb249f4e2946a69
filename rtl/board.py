"""One board (the paper's figure 3): host interface, voxel-to-patch memory, R x S processor array.

The host sends one stream of commands and reads one stream of results
(:class:`~blockray.rtl.protocol.BoardProtocol` layouts; docs/board-protocol.md). Commands run in
order, one at a time, in a single **execute slot**: a VOXEL occupies the memory controller's issue
slot, every other command the board's command register. The next command is taken from the
stream in the cycle the current one does its last step, so a busy host never costs a cycle, and
each command costs exactly what :class:`blockray.timing.BoardTiming` says::

    commands --> [command register | memory controller issue slot] --> patch memory
                        |                                                  |
                 point registers (written memory_latency later) ---> processor array
                        |                                                  |
                 masks, counters -------------------> result register <-- accumulators

Every cycle is either a **board cycle** (a command makes progress) or a **stall** (the slot is
empty because the command stream was, or END_BLOCK / READ_COUNTERS waits for the result
register). The ``cycles`` counter counts board cycles only, so it equals the model's cycle count
whatever the host's timing.

Ordering is exact (no hazards): a LOAD reaches the point registers :attr:`memory_latency` cycles
late, exactly when the records issued after it reach the array; BEGIN_BLOCK's accumulator clear
travels with the first record issued after it (``first``); the voxel table is read-transparent.

Latencies: :attr:`memory_latency` (issue to array input), :attr:`processor_latency` (array input
to accumulators), :attr:`drain_latency` = memory_latency + processor_latency - 1 (END_BLOCK starts
the cycle after the last issue). :attr:`timing` is the matching :class:`BoardTiming`.

Reset (the ``sync`` domain's synchronous reset) empties the command register, the issue slot, the
pipeline, the result register, the masks, accumulators and counters. Memory contents are not
reset but the protocol treats them as lost: after a reset the host reloads and replays.
"""

from amaranth.hdl import Cat, Const, Module, Mux, Signal
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from ..errors import ParameterError
from ..params import BoardParams
from ..records import point_layout
from ..timing import BoardTiming, Op
from .array import ProcessorArray
from .memctrl import MemoryController
from .processor import ArrayTiming
from .protocol import BoardProtocol, ResultKind

__all__ = ["BoardTop"]


def _delay(m, value, cycles, name):
    for n in range(cycles):
        reg = Signal.like(value, name=f"{name}_{n + 1}")
        m.d.sync += reg.eq(value)
        value = reg
    return value


def _popcount(value):
    return sum((value[i] for i in range(len(value))), Const(0, range(len(value) + 1)))


class BoardTop(wiring.Component):
    """One board: ``commands`` in, ``results`` out.

    Parameters: ``params`` (:class:`~blockray.params.BoardParams`; ``boards`` is ignored: a board
    is one of the P); ``patch_init`` / ``table_init`` optional memory contents (tests).

    Ports
    ``commands``  In stream of :attr:`protocol` ``.command_layout``.
    ``results``   Out stream of :attr:`protocol` ``.result_layout``. ``commands.ready`` may depend
                  combinationally on ``results.ready`` (a result leaves and the next one is
                  formed in the same cycle); no ``valid`` depends on any ``ready``.
    """

    def __init__(self, params, *, patch_init=(), table_init=()):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        if not isinstance(params, BoardParams):
            raise ParameterError(f"board needs BoardParams, not {params!r}")
        self._params = params
        self._protocol = BoardProtocol(params)
        self._patch_init, self._table_init = patch_init, table_init
        self._array_timing = ArrayTiming(params.bits)
        super().__init__({
            "commands": In(stream.Signature(self._protocol.command_layout)),
            "results": Out(stream.Signature(self._protocol.result_layout)),
        })
        self._MustUse__silence = False

    @property
    def params(self):
        return self._params

    @property
    def protocol(self):
        return self._protocol

    @property
    def memory_latency(self):
        """Cycles from a record's issue to the array's input (memory read + broadcast register)."""
        return MemoryController.latency

    @property
    def processor_latency(self):
        """Cycles from the array's input to the accumulators."""
        return self._array_timing.latency

    @property
    def latency(self):
        """Cycles from a record's issue to its blocked bits in the accumulators."""
        return self.memory_latency + self.processor_latency

    @property
    def drain_latency(self):
        """END_BLOCK's waiting cycles: it costs drain_latency + 1."""
        return self.latency - 1

    @property
    def timing(self):
        return BoardTiming(processor_latency=self.processor_latency, memory_latency=self.memory_latency)

    def elaborate(self, platform):
        m = Module()
        p, proto = self._params, self._protocol
        R, S = p.rows, p.cols
        m.submodules.memctrl = mc = MemoryController(p, patch_init=self._patch_init, table_init=self._table_init)
        m.submodules.array = array = ProcessorArray(p.bits, R, S)
        assert mc.latency == self.memory_latency and array.latency == self.processor_latency

        # -- fetch: the head of the command stream goes to the free execute slot ---------------
        cur = Signal(proto.command_layout)
        cur_valid = Signal()
        cur_done = Signal()                              # cur does its last step this cycle
        cur_step = Signal()                              # cur makes progress this cycle
        cur_free = ~cur_valid | cur_done
        head = self.commands.payload
        head_voxel = head.op == Op.VOXEL
        m.d.comb += [
            mc.voxels.valid.eq(self.commands.valid & head_voxel & cur_free),
            mc.voxels.payload.eq(head.arg.voxel.voxel),
            self.commands.ready.eq(cur_free & mc.free),
        ]
        pop = self.commands.valid & self.commands.ready
        with m.If(pop & ~head_voxel):
            m.d.sync += [cur.eq(head), cur_valid.eq(1)]
        with m.Elif(cur_done):
            m.d.sync += cur_valid.eq(0)

        # -- result register ---------------------------------------------------------------------
        result = Signal(proto.result_layout)
        result_valid = Signal()
        result_free = ~result_valid | self.results.ready
        new_result = Signal(proto.result_layout)
        emit = Signal()
        m.d.comb += [self.results.valid.eq(result_valid), self.results.payload.eq(result)]
        with m.If(emit):
            m.d.sync += [result.eq(new_result), result_valid.eq(1)]
        with m.Elif(self.results.valid & self.results.ready):
            m.d.sync += result_valid.eq(0)

        # -- execute the command register --------------------------------------------------------
        op = cur.op
        drain = Signal(range(self.drain_latency + 1))
        needs_result = (op == Op.END_BLOCK) | (op == Op.READ_COUNTERS)
        ready_to_emit = Mux(op == Op.END_BLOCK, drain == self.drain_latency, 1)
        m.d.comb += [
            cur_step.eq(cur_valid & ~(needs_result & ready_to_emit & ~result_free)),
            cur_done.eq(cur_step & (~needs_result | ready_to_emit)),
            emit.eq(cur_done & needs_result),
        ]
        with m.If(pop):
            m.d.sync += drain.eq(0)
        with m.Elif(cur_step & (op == Op.END_BLOCK) & (drain != self.drain_latency)):
            m.d.sync += drain.eq(drain + 1)

        m.d.comb += [
            mc.patch_write.valid.eq(cur_valid & (op == Op.WRITE_PATCH)),
            mc.patch_write.payload.eq(cur.arg.write_patch),
            mc.table_write.valid.eq(cur_valid & (op == Op.WRITE_VOXEL)),
            mc.table_write.payload.eq(cur.arg.write_voxel),
        ]

        # masks of the rows / columns loaded since BEGIN_BLOCK (effective at once: they count
        # useful tests at issue and mask the result word)
        row_valid = Signal(R)
        col_valid = Signal(S)
        fresh = Signal(init=1)               # no record issued since BEGIN_BLOCK (or reset)
        with m.If(cur_valid & (op == Op.BEGIN_BLOCK)):
            m.d.sync += [row_valid.eq(0), col_valid.eq(0), fresh.eq(1)]
        with m.If(cur_valid & (op == Op.LOAD_RECEIVER)):
            m.d.sync += row_valid.bit_select(cur.arg.load_receiver.row, 1).eq(1)
        with m.If(cur_valid & (op == Op.LOAD_SHOOTER)):
            m.d.sync += col_valid.bit_select(cur.arg.load_shooter.col, 1).eq(1)
        with m.If(mc.issue):
            m.d.sync += fresh.eq(0)

        # point registers, written memory_latency cycles after the LOAD: records issued before
        # the LOAD have reached the array by then, those issued after it have not
        point = point_layout(p.bits)
        load_layout = data.StructLayout({
            "receiver": 1, "shooter": 1,
            "row": proto.row_width, "col": proto.col_width, "point": point,
        })
        load = Signal(load_layout)
        m.d.comb += [
            load.receiver.eq(cur_valid & (op == Op.LOAD_RECEIVER)),
            load.shooter.eq(cur_valid & (op == Op.LOAD_SHOOTER)),
            load.row.eq(cur.arg.load_receiver.row),
            load.col.eq(cur.arg.load_shooter.col),
            load.point.eq(Mux(op == Op.LOAD_RECEIVER, cur.arg.load_receiver.point.as_value(),
                              cur.arg.load_shooter.point.as_value())),
        ]
        late = _delay(m, load, self.memory_latency - 1, "load")
        receivers = Signal(data.ArrayLayout(point, R))
        shooters = Signal(data.ArrayLayout(point, S))
        for r in range(R):
            with m.If(late.receiver & (late.row == r)):
                m.d.sync += receivers[r].eq(late.point)
        for s in range(S):
            with m.If(late.shooter & (late.col == s)):
                m.d.sync += shooters[s].eq(late.point)

        # -- the array ---------------------------------------------------------------------------
        first = _delay(m, mc.issue & fresh, self.memory_latency, "first")
        m.d.comb += [
            array.patch.eq(mc.records.payload),
            array.valid.eq(mc.records.valid),
            array.first.eq(first),
            array.receivers.eq(receivers),
            array.shooters.eq(shooters),
        ]
        mask = Cat(row_valid[r] & col_valid[s] for r in range(R) for s in range(S))

        # -- counters ----------------------------------------------------------------------------
        counters = Signal(proto.counters_layout)
        work = cur_step | mc.step
        useful = _popcount(row_valid) * _popcount(col_valid)
        m.d.sync += [
            counters.cycles.eq(counters.cycles + work),
            counters.stalls.eq(counters.stalls + ~work),
        ]
        with m.If(mc.issue):
            m.d.sync += [
                counters.busy.eq(counters.busy + 1),
                counters.tests_issued.eq(counters.tests_issued + R * S),
                counters.tests_useful.eq(counters.tests_useful + useful),
            ]

        with m.If(op == Op.END_BLOCK):
            m.d.comb += [
                new_result.kind.eq(ResultKind.BLOCKED),
                new_result.data.blocked.eq(Mux(fresh, 0, array.hit & mask)),
            ]
        with m.Else():
            m.d.comb += [
                new_result.kind.eq(ResultKind.COUNTERS),
                new_result.data.counters.eq(counters),
            ]
        return m
