"""The board's serial link: UART bytes to the core's command stream, results back as frames.

::

    rx pin -> UARTRx -> command FIFO --------------------------> core.i_bytes
                                 (a credit owed per byte taken)
    tx pin <- UARTTx <- framer <- result FIFO <------------------ core.o_bytes
                          ^ credit grants

:class:`LinkBridge` is the byte-level part (FIFOs, credits, framing; the framing is
:mod:`blockray.link`'s). :class:`SerialLink` adds the UART and the core and has only the pins
``rx``/``tx``: the same component runs on the ULX3S (:mod:`blockray.rtl.ulx3s`) and under
Verilator (``--board ulx3s-sim``). A break on ``rx`` resets the bridge and the core (not the
UART), and the board is silent while it lasts.

The core is any component with ``i_bytes: In(stream.Signature(8))`` (command bytes) and
``o_bytes: Out(stream.Signature(8))`` (result bytes).

Formal properties (tests/test_link_formal.py, SymbiYosys): with a host that sends only against
credits, no byte is lost, duplicated or reordered on either path, every ``valid`` holds (with its
payload) until ``ready``, the command FIFO never overflows and the owed credits never exceed the
FIFO depth or go below zero.
"""

import operator

from amaranth.hdl import Module, Mux, ResetInserter, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from ..link import FRAME_MAX, GRANT_FLAG
from .uart import UARTRx, UARTTx

__all__ = ["LinkBridge", "SerialLink", "EchoCore", "ECHO_XOR", "CORE_MEMBERS", "is_core"]


#: what the link needs of a core (a component may have more ports): command bytes in, result bytes out
CORE_MEMBERS = {"i_bytes": In(stream.Signature(8)), "o_bytes": Out(stream.Signature(8))}


def is_core(component):
    """Whether ``component`` has the ports :data:`CORE_MEMBERS` names."""
    members = getattr(getattr(component, "signature", None), "members", {})
    return all(name in members and members[name] == member for name, member in CORE_MEMBERS.items())


class LinkBridge(wiring.Component):
    """FIFOs, credits and framing between the UART's byte streams and the core's.

    Parameters: ``fifo_depth`` command bytes the board buffers (the credits a host starts with;
    a power of two, at least 4), ``result_depth`` result bytes buffered towards the UART,
    ``grant_min``: while results wait, credits are granted only in batches of at least this many
    (a grant costs a byte of the result path); default ``min(32, fifo_depth // 4)``.

    Ports: ``rx_bytes`` (from the UART receiver: a byte that finds the FIFO full is lost and
    sets ``overrun``, which a host keeping to its credits never causes), ``commands`` (to the
    core), ``results`` (from the core), ``tx_bytes`` (to the UART transmitter), ``owed`` (credits
    owed to the host: the command bytes taken since their grant, plus the initial fifo_depth),
    ``tx_header`` (the byte offered on ``tx_bytes`` is a frame header), ``command_level`` /
    ``result_level`` (bytes in the two FIFOs): status, and what the formal proofs' invariants
    are stated in. Elaborated for ``platform="formal"`` it asserts its own invariants: a grant
    being sent never exceeds the credits owed, a result frame never the bytes queued.
    """

    def __init__(self, *, fifo_depth=2048, result_depth=512, grant_min=None):
        self._MustUse__silence = True       # no "never used" warning when a parameter is refused
        self._fifo_depth = operator.index(fifo_depth)
        self._result_depth = operator.index(result_depth)
        for name, value in (("fifo_depth", self._fifo_depth), ("result_depth", self._result_depth)):
            if value < 4 or value & (value - 1):
                raise ValueError(f"link {name} must be a power of two, at least 4, not {value}")
        self._grant_min = min(32, self._fifo_depth // 4) if grant_min is None else operator.index(grant_min)
        if not 1 <= self._grant_min <= FRAME_MAX:
            raise ValueError(f"link grant_min must be from 1 to {FRAME_MAX}, not {self._grant_min}")
        super().__init__({
            "rx_bytes": In(stream.Signature(8)),
            "commands": Out(stream.Signature(8)),
            "results": In(stream.Signature(8)),
            "tx_bytes": Out(stream.Signature(8)),
            "owed": Out(range(self._fifo_depth + 1), init=self._fifo_depth),
            "overrun": Out(1),
            "tx_header": Out(1),
            "command_level": Out(range(self._fifo_depth + 1)),
            "result_level": Out(range(self._result_depth + 1)),
        })
        self._MustUse__silence = False

    @property
    def fifo_depth(self):
        return self._fifo_depth

    @property
    def result_depth(self):
        return self._result_depth

    def elaborate(self, platform):
        m = Module()
        m.submodules.command_fifo = cmd = SyncFIFOBuffered(width=8, depth=self._fifo_depth)
        m.submodules.result_fifo = res = SyncFIFOBuffered(width=8, depth=self._result_depth)

        m.d.comb += [self.command_level.eq(cmd.r_level), self.result_level.eq(res.r_level)]

        # command path: UART -> FIFO -> core
        m.d.comb += [cmd.w_data.eq(self.rx_bytes.payload), cmd.w_en.eq(self.rx_bytes.valid),
                     self.rx_bytes.ready.eq(cmd.w_rdy)]
        with m.If(self.rx_bytes.valid & ~cmd.w_rdy):
            m.d.sync += self.overrun.eq(1)
        wiring.connect(m, fifo=cmd.r_stream, core=wiring.flipped(self.commands))
        wiring.connect(m, core=wiring.flipped(self.results), fifo=res.w_stream)

        # tx path: one header byte, then (result frames) its bytes from the result FIFO
        header = Signal(8)
        amount = Signal(range(FRAME_MAX + 1))     # credits of a grant, or result bytes of a frame
        is_grant = Signal()
        left = Signal(range(FRAME_MAX + 1))       # result bytes of the frame still to send
        granted = Signal(range(FRAME_MAX + 1))    # credits whose grant header is taken this cycle
        grant_n = Signal(range(FRAME_MAX + 1))
        frame_n = Signal(range(FRAME_MAX + 1))
        m.d.comb += [
            grant_n.eq(Mux(self.owed > FRAME_MAX, FRAME_MAX, self.owed)),
            frame_n.eq(Mux(res.r_level > FRAME_MAX, FRAME_MAX, res.r_level)),
        ]
        with m.FSM() as fsm:
            with m.State("Choose"):
                with m.If((self.owed >= self._grant_min) | ((self.owed != 0) & (res.r_level == 0))):
                    m.d.sync += [header.eq(GRANT_FLAG | (grant_n - 1)), amount.eq(grant_n), is_grant.eq(1)]
                    m.next = "Header"
                with m.Elif(res.r_level != 0):
                    m.d.sync += [header.eq(frame_n - 1), amount.eq(frame_n), is_grant.eq(0)]
                    m.next = "Header"
            with m.State("Header"):
                m.d.comb += [self.tx_bytes.valid.eq(1), self.tx_bytes.payload.eq(header), self.tx_header.eq(1)]
                with m.If(self.tx_bytes.ready):
                    with m.If(is_grant):
                        m.d.comb += granted.eq(amount)
                        m.next = "Choose"
                    with m.Else():
                        m.d.sync += left.eq(amount)
                        m.next = "Data"
            with m.State("Data"):
                # the frame's bytes were in the FIFO when it was chosen, and only we read it
                m.d.comb += [self.tx_bytes.valid.eq(res.r_rdy), self.tx_bytes.payload.eq(res.r_data),
                             res.r_en.eq(self.tx_bytes.ready)]
                with m.If(self.tx_bytes.valid & self.tx_bytes.ready):
                    m.d.sync += left.eq(left - 1)
                    with m.If(left == 1):
                        m.next = "Choose"

        taken = Signal()
        m.d.comb += taken.eq(self.commands.valid & self.commands.ready)
        m.d.sync += self.owed.eq(self.owed + taken - granted)

        if platform == "formal":
            from amaranth.hdl import Assert
            with m.If(fsm.ongoing("Header")):
                m.d.comb += [Assert((amount >= 1) & (amount <= FRAME_MAX)),
                             Assert(header == Mux(is_grant, GRANT_FLAG | (amount - 1), amount - 1))]
                with m.If(is_grant):
                    m.d.comb += Assert(amount <= self.owed)
                with m.Else():
                    m.d.comb += Assert(amount <= res.r_level)
            with m.If(fsm.ongoing("Data")):
                m.d.comb += Assert((left >= 1) & (left <= res.r_level))
            m.d.comb += Assert(self.owed + cmd.r_level <= self._fifo_depth)
        return m


class SerialLink(wiring.Component):
    """UART, :class:`LinkBridge` and a core: the board as two pins, ``rx`` and ``tx``.

    ``core``: a component with the ports of :data:`CORE_MEMBERS`; ``divisor``: UART bit time in
    clock cycles; ``fifo_depth``, ``result_depth``: :class:`LinkBridge`'s. A break on ``rx``
    resets the bridge and the core (``link_reset`` shows it).
    """

    rx: In(1, init=1)
    tx: Out(1, init=1)
    link_reset: Out(1)

    def __init__(self, core, *, divisor, fifo_depth=2048, result_depth=512):
        if not is_core(core):
            raise TypeError(f"the link's core needs i_bytes/o_bytes byte streams, not {core!r}")
        self._core = core
        self._divisor = divisor
        self._rx = UARTRx(divisor)
        self._tx = UARTTx(divisor)
        self._bridge = LinkBridge(fifo_depth=fifo_depth, result_depth=result_depth)
        super().__init__()

    @property
    def core(self):
        return self._core

    @property
    def bridge(self):
        return self._bridge

    @property
    def divisor(self):
        return self._divisor

    def elaborate(self, platform):
        m = Module()
        m.submodules.uart_rx = rx = self._rx
        m.submodules.uart_tx = tx = self._tx
        # the break resets what holds link state; the UART only frames bits
        reset = {"sync": rx.brk}
        m.submodules.bridge = bridge = ResetInserter(reset)(self._bridge)
        m.submodules.core = core = ResetInserter(reset)(self._core)
        m.d.comb += [rx.rx.eq(self.rx), self.tx.eq(tx.tx), self.link_reset.eq(rx.brk)]
        wiring.connect(m, uart=rx.o_bytes, bridge=self._bridge.rx_bytes)
        wiring.connect(m, bridge=self._bridge.commands, core=self._core.i_bytes)
        wiring.connect(m, core=self._core.o_bytes, bridge=self._bridge.results)
        wiring.connect(m, bridge=self._bridge.tx_bytes, uart=tx.i_bytes)
        return m


#: what EchoCore does to each byte (so a test sees the core was passed through, not bypassed)
ECHO_XOR = 0xA5


class EchoCore(wiring.Component):
    """The link's test core (``blockray bitstream --core echo`` brings a board's link up without
    the board core; the tests' stand-in core). Answers every command byte b with ``repeat``
    result bytes: b ^ ECHO_XOR, then b + 1, b + 2... (mod 256), through a FIFO of ``depth``
    command bytes. ``hold`` high: takes no command byte
    (a busy core). With ``repeat`` 2 it answers faster than a UART carries: the result path
    fills and back-pressures the core."""

    i_bytes: In(stream.Signature(8))
    o_bytes: Out(stream.Signature(8))
    hold: In(1)

    def __init__(self, *, depth=8, repeat=1):
        self._depth, self._repeat = depth, repeat
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.fifo = fifo = SyncFIFOBuffered(width=8, depth=self._depth)
        phase = Signal(range(self._repeat))
        last = phase == self._repeat - 1
        m.d.comb += [
            fifo.w_data.eq(self.i_bytes.payload),
            fifo.w_en.eq(self.i_bytes.valid & ~self.hold),
            self.i_bytes.ready.eq(fifo.w_rdy & ~self.hold),
            self.o_bytes.payload.eq(Mux(phase == 0, fifo.r_data ^ ECHO_XOR, fifo.r_data + phase)),
            self.o_bytes.valid.eq(fifo.r_rdy),
            fifo.r_en.eq(self.o_bytes.ready & last),
        ]
        with m.If(self.o_bytes.valid & self.o_bytes.ready):
            m.d.sync += phase.eq(Mux(last, 0, phase + 1))
        return m
