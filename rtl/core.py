"""The board behind its link: the compact byte format of :mod:`blockray.protocol` in front of
:class:`~blockray.rtl.board.BoardTop`.

``i_bytes`` carries commands (a header byte, then the payload bytes its opcode needs), ``o_bytes``
results (the low bytes of each result record, as many as its tag says). A transport (UART, USB,
a simulator's pipe) connects to these two byte streams and nothing else::

    i_bytes --> deframer --> [command record] --> BoardTop --> [result record] --> serialiser --> o_bytes

The deframer assembles one command at a time into the board's command record and holds it in an
output register until the board takes it; it takes a byte per cycle while that register is free
or being emptied, so bytes cost no board cycles: the board's ``cycles`` counter, and with it the
cycle contract, is the same as for :class:`BoardTop` fed the records directly (the extra clock
cycles while the bytes of the next command arrive are stalls). A header byte with an unknown
opcode is dropped. The serialiser sends a result's bytes one per cycle and takes the next result
the cycle after the last byte left.

With ``rays`` (rays made on the board): the commands of :mod:`blockray.board_rays` (opcodes 10 to
13) become the block sequencer's items (:func:`~blockray.rtl.sequencer.command_items` is their
reference), its records go to :class:`BoardTop` in their place; no byte is taken while the
sequencer works, so the commands after them wait (the board's cycles are the model's: the
sequencer's own are stalls to the board). IDENTIFY then answers version
:data:`~blockray.protocol.RAYS_VERSION` (3): the host's sign that the board makes its rays.
``blockray bitstream`` builds the core with it.
"""

from types import SimpleNamespace

from amaranth.hdl import Const, Module, Mux, Signal
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from ..board_rays import MAX_SAMPLES, RECEIVERS_PER_COMMAND, WEIGHT_BITS, RayOp, RayProtocol
from ..cell import Cell
from ..errors import ParameterError
from ..params import BoardParams
from ..protocol import POINTS_PER_LOAD, Op, ResultKind
from .board import BoardTop
from .sequencer import ItemOp, item_layout

__all__ = ["BoardCore"]


class BoardCore(wiring.Component):
    """One board with byte-stream ports (see the module docstring).

    Ports
    ``i_bytes``  In stream of bytes: commands in the wire format.
    ``o_bytes``  Out stream of bytes: results in the wire format.
    ``i_records``  (``records``: simulation only, the native harness) In stream of whole command
                   records (:attr:`~blockray.protocol.BoardProtocol.command_layout`), one a cycle,
                   between the byte stream's commands: a record costs the board what the same
                   command's bytes cost, without the clock cycles of its bytes.

    ``board`` is the wrapped :class:`BoardTop` (its ``params``, ``protocol``, ``timing`` and
    latencies are this core's); ``cell``, ``patch_init``, ``table_init`` are passed to it.
    """

    def __init__(self, params, *, patch_init=(), table_init=(), cell=Cell(), rays=False, records=False):
        if not isinstance(params, BoardParams):
            raise ParameterError(f"board needs BoardParams, not {params!r}")
        self.board = BoardTop(params, patch_init=patch_init, table_init=table_init, cell=cell, rays=rays)
        self._rays = rays
        self._records = records
        ports = {
            "i_bytes": In(stream.Signature(8)),
            "o_bytes": Out(stream.Signature(8)),
        }
        if records:
            ports["i_records"] = In(stream.Signature(self.board.protocol.command_layout))
        super().__init__(ports)

    @property
    def params(self):
        return self.board.params

    @property
    def protocol(self):
        return self.board.protocol

    @property
    def timing(self):
        return self.board.timing

    @property
    def makes_rays(self):
        """Built with the block sequencer (``rays``): it takes the commands of rays made on the board."""
        return self._rays

    def elaborate(self, platform):
        m = Module()
        m.submodules.board = top = self.board
        proto = self.protocol
        arg_size = proto.arg_layout.size
        max_payload = max(proto.command_bytes(op) - 1 for op in Op)
        if self._rays:                      # the ray commands a buffer holds (LOAD_SAMPLES streams)
            rp = RayProtocol(self.params)
            max_payload = max(max_payload, rp.command_bytes(RayOp.LOAD_GRID) - 1,
                              rp.command_bytes(RayOp.RECEIVERS, RECEIVERS_PER_COMMAND, weighted=True) - 1)
        slot = proto.point_slot_layout.size

        # -- deframer: header, then `need` payload bytes into `buf`
        header = Signal(8)
        collecting = Signal()
        got = Signal(range(max_payload + 1))
        need = Signal(range(max_payload + 1))
        buf = Signal(max_payload * 8)
        out = Signal(proto.command_layout)
        out_valid = Signal()
        m.d.comb += [top.commands.payload.eq(out), top.commands.valid.eq(out_valid)]
        with m.If(top.commands.ready):
            m.d.sync += out_valid.eq(0)
        free = ~out_valid | top.commands.ready
        rays = self._ray_items(m, top, out_valid) if self._rays else None
        if rays is not None:
            free = free & rays.free
        if self._records:
            # a whole command record a cycle (simulation only): the board sees it as the deframer's
            # output, so it costs the same board cycles; it goes only while no command is on the
            # byte side (none being collected, none waiting, no ray command's items left)
            between = ~out_valid & ~collecting
            if rays is not None:
                between = between & rays.free & ~rays.samples
            with m.If(~out_valid):
                m.d.comb += [top.commands.payload.eq(self.i_records.payload),
                             top.commands.valid.eq(self.i_records.valid & between)]
            m.d.comb += self.i_records.ready.eq(between & top.commands.ready)
        m.d.comb += self.i_bytes.ready.eq(free)
        byte = self.i_bytes.payload
        take = self.i_bytes.valid & free

        # payload bytes of the header in `byte`; unknown opcodes are not `known`
        head_need = Signal.like(need)
        known = Signal()
        with m.Switch(byte[:4]):
            for op in Op:
                with m.Case(op):
                    m.d.comb += known.eq(1)
                    if op is Op.LOAD_POINTS:
                        with m.Switch(byte[4:6]):
                            for n in range(POINTS_PER_LOAD):
                                with m.Case(n):
                                    m.d.comb += head_need.eq(proto.command_bytes(op, n + 1) - 1)
                    else:
                        m.d.comb += head_need.eq(proto.command_bytes(op) - 1)

        # the payload with the byte now arriving, cut to the slots a LOAD_POINTS carries
        full = Signal(max_payload * 8)
        m.d.comb += [full.eq(buf), full.word_select(got, 8).eq(byte)]
        arg = Signal(arg_size)
        m.d.comb += arg.eq(full[:arg_size])
        with m.If(header[:4] == Op.LOAD_POINTS):
            with m.Switch(header[4:6]):
                for n in range(POINTS_PER_LOAD - 1):
                    with m.Case(n):
                        m.d.comb += arg.eq(full[:(n + 1) * slot])

        samples, ray_done = Const(0), Const(0)      # a LOAD_SAMPLES byte; a buffered ray command's last
        if rays is not None:
            self._ray_header(m, rays, byte, known, head_need)
            samples = rays.samples
            ray_done = (got == need - 1) & (header[:4] >= RayOp.LOAD_GRID)
        with m.If(take & samples):
            if rays is not None:
                self._sample_byte(m, rays, byte)
        with m.Elif(take):
            with m.If(~collecting):
                with m.If(known & (byte[:4] == RayOp.LOAD_SAMPLES) if rays is not None else Const(0)):
                    if rays is not None:
                        m.d.sync += [rays.samples.eq(1), rays.bits.eq(0), rays.k.eq(0), rays.count.eq(0),
                                     rays.sbytes.eq(0)]
                with m.Elif(known & (head_need == 0)):
                    m.d.sync += [out.op.eq(byte[:4]), out.arg.as_value().eq(0), out_valid.eq(1)]
                with m.Elif(known):
                    m.d.sync += [header.eq(byte), collecting.eq(1), got.eq(0), need.eq(head_need), buf.eq(0)]
            with m.Elif(ray_done):
                if rays is not None:
                    m.d.sync += [rays.header.eq(header), rays.buf.eq(full), rays.slot.eq(0), collecting.eq(0),
                                 rays.left.eq(Mux(header[:4] == RayOp.RECEIVERS, header[4:6] + 1, 1))]
            with m.Elif(got == need - 1):
                m.d.sync += [out.op.eq(header[:4]), out.arg.as_value().eq(arg), out_valid.eq(1),
                             collecting.eq(0)]
            with m.Else():
                m.d.sync += [buf.eq(full), got.eq(got + 1)]

        # -- serialiser: the low result_bytes(kind) bytes of each result record
        lengths = {kind: proto.result_bytes(kind) for kind in ResultKind}
        sbuf = Signal(max(lengths.values()) * 8)
        left = Signal(range(max(lengths.values()) + 1))
        m.d.comb += [
            self.o_bytes.valid.eq(left != 0),
            self.o_bytes.payload.eq(sbuf[:8]),
            top.results.ready.eq(left == 0),
        ]
        with m.If(top.results.valid & (left == 0)):
            m.d.sync += sbuf.eq(top.results.payload.as_value())
            with m.Switch(top.results.payload.kind):
                for kind, n in lengths.items():
                    with m.Case(kind):
                        m.d.sync += left.eq(n)
        with m.Elif(self.o_bytes.valid & self.o_bytes.ready):
            m.d.sync += [sbuf.eq(sbuf[8:]), left.eq(left - 1)]
        return m

    def _ray_items(self, m, top, out_valid):
        """Rays made on the board: the ray commands' items to the sequencer, one at a time, each
        when the board has done the commands before it (``idle``); a LOAD_SAMPLES triple as its
        30 bits arrive, a buffered command's items (a RECEIVERS command's slots) after its last
        byte. No byte is taken while an item waits or the sequencer is busy, so every later
        command reaches the board after the records of the ray commands before it."""
        rp = RayProtocol(self.params)
        layout = item_layout(rp)
        triple = 3 * WEIGHT_BITS
        r = SimpleNamespace(samples=Signal(), acc=Signal(triple + 8), bits=Signal(range(triple + 9)),
                            k=Signal(range(MAX_SAMPLES + 1)), count=Signal(range(MAX_SAMPLES + 1)),
                            sbytes=Signal(range(rp.command_bytes(RayOp.LOAD_SAMPLES) + 1)),
                            header=Signal(8), buf=Signal(8 * max(rp.command_bytes(RayOp.LOAD_GRID) - 1, rp.command_bytes(
                                RayOp.RECEIVERS, RECEIVERS_PER_COMMAND, weighted=True) - 1)),
                            left=Signal(range(RECEIVERS_PER_COMMAND + 1)), slot=Signal(range(RECEIVERS_PER_COMMAND)),
                            free=Signal())
        ready_sample = r.samples & (r.count != 0) & (r.bits >= triple) & (r.k != r.count)
        sample_bytes = (7 + rp.count_width + triple * r.count) >> 3
        done = r.samples & (r.count != 0) & (r.k == r.count) & (r.sbytes == sample_bytes)
        item = Signal(layout)
        m.d.comb += [top.rays.payload.eq(item),
                     top.rays.valid.eq((ready_sample | (r.left != 0)) & ~out_valid & top.idle),
                     r.free.eq(~ready_sample & (r.left == 0) & ~done & top.rays.ready)]
        with m.If(done):
            m.d.sync += r.samples.eq(0)
        with m.If(r.samples):
            m.d.comb += [item.op.eq(ItemOp.SAMPLE), item.arg.sample.index.eq(r.k),
                         item.arg.sample.weights.eq(r.acc[:triple])]
        with m.Else():
            self._buffered_item(m, rp, r, item)
        with m.If(top.rays.valid & top.rays.ready):
            with m.If(r.samples):
                m.d.sync += [r.acc.eq(r.acc >> triple), r.bits.eq(r.bits - triple), r.k.eq(r.k + 1)]
            with m.Else():
                m.d.sync += [r.left.eq(r.left - 1), r.slot.eq(r.slot + 1)]
        return r

    def _buffered_item(self, m, rp, r, item):
        """The item of a buffered LOAD_GRID, COLUMN or RECEIVERS slot ``r.slot``."""
        op = r.header[:4]
        with m.If(op == RayOp.LOAD_GRID):
            m.d.comb += [item.op.eq(ItemOp.GRID), item.arg.grid.eq(r.buf[:rp.grid_layout.size])]
        with m.Elif(op == RayOp.COLUMN):
            m.d.comb += [item.op.eq(ItemOp.COLUMN), item.arg.column.eq(r.buf[:rp.column_layout.size])]
        with m.Else():
            receiver = item.arg.receiver
            m.d.comb += [item.op.eq(ItemOp.RECEIVER), receiver.weighted.eq(r.header[6])]
            for weighted, slot_layout in ((0, rp.slot_layout), (1, rp.weighted_slot_layout)):
                slots = data.ArrayLayout(slot_layout, RECEIVERS_PER_COMMAND)(r.buf[:slot_layout.size * RECEIVERS_PER_COMMAND])
                with m.If(r.header[6] == weighted):
                    slot = slots[r.slot]
                    m.d.comb += [receiver.address.eq(slot.address), receiver.last.eq(slot.last)]
                    if weighted:
                        m.d.comb += receiver.weights.eq(slot.weights)

    def _ray_header(self, m, r, byte, known, head_need):
        """A ray command's header byte: known, and the payload bytes a buffered one needs."""
        rp = RayProtocol(self.params)
        with m.Switch(byte[:4]):
            for op in (RayOp.LOAD_GRID, RayOp.COLUMN):
                with m.Case(op):
                    m.d.comb += [known.eq(1), head_need.eq(rp.command_bytes(op) - 1)]
            with m.Case(RayOp.LOAD_SAMPLES):
                m.d.comb += known.eq(1)
            with m.Case(RayOp.RECEIVERS):
                m.d.comb += known.eq(1)
                for n in range(RECEIVERS_PER_COMMAND):
                    for weighted in (0, 1):
                        with m.If((byte[4:6] == n) & (byte[6] == weighted)):
                            m.d.comb += head_need.eq(rp.command_bytes(RayOp.RECEIVERS, n + 1, weighted=bool(weighted)) - 1)

    def _sample_byte(self, m, r, byte):
        """A LOAD_SAMPLES payload byte: the first carries K - 1 in its low bits."""
        width = RayProtocol(self.params).count_width
        m.d.sync += r.sbytes.eq(r.sbytes + 1)
        with m.If(r.count == 0):
            m.d.sync += [r.count.eq(byte[:width] + 1), r.acc.eq(byte >> width), r.bits.eq(8 - width)]
        with m.Else():
            m.d.sync += [r.acc.eq(r.acc | (byte << r.bits)), r.bits.eq(r.bits + 8)]
