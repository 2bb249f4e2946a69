"""The board's serial link: UART bytes in and out, the framed link (:mod:`blockray.rtl.framing`)
between them and the core.

::

    rx pin -> UARTRx -> receive FIFO -> FrameReceiver -> command FIFO ----------> core.i_bytes
    tx pin <- UARTTx <------------------ FrameSender (replay memory) <---------- core.o_bytes

:class:`SerialLink` is the UART, a :class:`~blockray.rtl.framing.FramedBridge` and the core, with
only the pins ``rx``/``tx``: the same component runs on the ULX3S (:mod:`blockray.rtl.ulx3s`) and
under Verilator (``--board ulx3s-sim``). A break on ``rx`` resets the bridge and the core (not the
UART): the host's reset, after which both sides number their frames from 0 again.

The core is any component with ``i_bytes: In(stream.Signature(8))`` (command bytes) and
``o_bytes: Out(stream.Signature(8))`` (result bytes).
"""

from amaranth.hdl import Module, Mux, ResetInserter, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from .framing import FramedBridge
from .uart import UARTRx, UARTTx

__all__ = ["SerialLink", "EchoCore", "ECHO_XOR", "CORE_MEMBERS", "is_core"]


#: what the link needs of a core (a component may have more ports): command bytes in, result bytes out
CORE_MEMBERS = {"i_bytes": In(stream.Signature(8)), "o_bytes": Out(stream.Signature(8))}


def is_core(component):
    """Whether ``component`` has the ports :data:`CORE_MEMBERS` names."""
    members = getattr(getattr(component, "signature", None), "members", {})
    return all(name in members and members[name] == member for name, member in CORE_MEMBERS.items())


class SerialLink(wiring.Component):
    """UART, :class:`~blockray.rtl.framing.FramedBridge` and a core: the board as two pins,
    ``rx`` and ``tx``.

    ``core``: a component with the ports of :data:`CORE_MEMBERS`; ``divisor``: UART bit time in
    clock cycles; ``fifo_depth``: the receive FIFO's bytes (at least the host's window, 8 frames
    of 256 wire bytes); ``payload``, ``window``: the board's frames (bytes, frames unacknowledged).
    A break on ``rx`` resets the bridge and the core (``link_reset`` shows it); ``overrun``: a
    UART byte found the receive FIFO full (a host keeping to its window never causes it).
    """

    rx: In(1, init=1)
    tx: Out(1, init=1)
    link_reset: Out(1)
    overrun: Out(1)

    def __init__(self, core, *, divisor, fifo_depth=2048, payload=128, window=4):
        if not is_core(core):
            raise TypeError(f"the link's core needs i_bytes/o_bytes byte streams, not {core!r}")
        self._core = core
        self._divisor = divisor
        self._rx = UARTRx(divisor)
        self._tx = UARTTx(divisor)
        self._bridge = FramedBridge(fifo_depth=fifo_depth, payload=payload, window=window)
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
        m.d.comb += [rx.rx.eq(self.rx), self.tx.eq(tx.tx), self.link_reset.eq(rx.brk),
                     self.overrun.eq(self._bridge.overrun)]
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
