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
"""

from amaranth.hdl import Module, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from ..cell import Cell
from ..errors import ParameterError
from ..params import BoardParams
from ..protocol import POINTS_PER_LOAD, Op, ResultKind
from .board import BoardTop

__all__ = ["BoardCore"]


class BoardCore(wiring.Component):
    """One board with byte-stream ports (see the module docstring).

    Ports
    ``i_bytes``  In stream of bytes: commands in the wire format.
    ``o_bytes``  Out stream of bytes: results in the wire format.

    ``board`` is the wrapped :class:`BoardTop` (its ``params``, ``protocol``, ``timing`` and
    latencies are this core's); ``cell``, ``patch_init``, ``table_init`` are passed to it.
    """

    def __init__(self, params, *, patch_init=(), table_init=(), cell=Cell()):
        if not isinstance(params, BoardParams):
            raise ParameterError(f"board needs BoardParams, not {params!r}")
        self.board = BoardTop(params, patch_init=patch_init, table_init=table_init, cell=cell)
        super().__init__({
            "i_bytes": In(stream.Signature(8)),
            "o_bytes": Out(stream.Signature(8)),
        })

    @property
    def params(self):
        return self.board.params

    @property
    def protocol(self):
        return self.board.protocol

    @property
    def timing(self):
        return self.board.timing

    def elaborate(self, platform):
        m = Module()
        m.submodules.board = top = self.board
        proto = self.protocol
        arg_size = proto.arg_layout.size
        max_payload = max(proto.command_bytes(op) - 1 for op in Op)
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

        with m.If(take):
            with m.If(~collecting):
                with m.If(known & (head_need == 0)):
                    m.d.sync += [out.op.eq(byte[:4]), out.arg.as_value().eq(0), out_valid.eq(1)]
                with m.Elif(known):
                    m.d.sync += [header.eq(byte), collecting.eq(1), got.eq(0), need.eq(head_need), buf.eq(0)]
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


