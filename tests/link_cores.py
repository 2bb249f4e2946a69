"""Stand-in cores for the serial link's tests: anything with i_bytes/o_bytes byte streams."""

from amaranth.hdl import Module, Mux, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

#: what EchoCore does to each byte (so a test sees the core was passed through, not bypassed)
ECHO_XOR = 0xA5


class EchoCore(wiring.Component):
    """Answers every command byte b with ``repeat`` result bytes: b ^ ECHO_XOR, then b + 1, b + 2...
    (mod 256), through a FIFO of ``depth`` command bytes. ``hold`` high: takes no command byte
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


def echo(data, repeat=1):
    """EchoCore's answer to command bytes ``data``."""
    out = bytearray()
    for b in data:
        out.append(b ^ ECHO_XOR)
        out += bytes((b + k) & 0xFF for k in range(1, repeat))
    return bytes(out)
