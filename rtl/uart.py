"""UART receiver and transmitter: 8 data bits, no parity, 1 stop bit (8N1), LSB first.

``divisor`` is the bit time in clock cycles (``round(f_clk / baud)``; at least 4): 3 Mbaud
from the ULX3S's 45 MHz board clock is 15. (amaranth-stdio's serial core would fit, but it is not on PyPI.)

:class:`UARTRx` samples each bit in its middle: it waits half a bit time after the start bit's
falling edge, checks the line is still low, then samples every ``divisor`` cycles. A byte whose
stop bit is high is put on ``o_bytes`` (one cycle of ``valid``; a UART cannot wait, so ``ready``
is not looked at: the link's credits keep it high, see :mod:`blockray.rtl.link`). A low stop bit
is a framing error: the byte is dropped, and if the byte was all zeros the line is held low,
a **break**, and ``brk`` stays high until the line goes high again. Tolerates a baud mismatch of
up to about 1/20 (the last sample is 9.5 bit times after the edge).

:class:`UARTTx` takes a byte from ``i_bytes`` when idle and shifts it out on ``tx`` (high when
idle); one byte every ``10 * divisor`` cycles at most.
"""

import operator

from amaranth.hdl import Cat, Module, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

__all__ = ["UARTRx", "UARTTx", "MIN_DIVISOR"]

#: the smallest bit time in clock cycles (the receiver needs a half bit of at least 2 cycles)
MIN_DIVISOR = 4


class _BitTimed(wiring.Component):
    """What the receiver and the transmitter share: the bit time ``divisor`` (clock cycles, at
    least :data:`MIN_DIVISOR`) and a timer that counts it down."""

    def __init__(self, divisor):
        divisor = operator.index(divisor)
        if divisor < MIN_DIVISOR:
            raise ValueError(f"UART divisor must be at least {MIN_DIVISOR} clock cycles per bit, not {divisor}")
        self._divisor = divisor
        super().__init__()

    @property
    def divisor(self):
        return self._divisor

    def _timer(self, m):
        """A down-counter in ``m`` that stops at zero; load ``n - 1`` into it to wait n cycles."""
        timer = Signal(range(self._divisor))
        with m.If(timer != 0):
            m.d.sync += timer.eq(timer - 1)
        return timer


class UARTRx(_BitTimed):
    """8N1 receiver. Ports: ``rx`` (the pin, asynchronous: synchronised here), ``o_bytes``
    (received bytes; ``ready`` ignored), ``frame_error`` (one cycle per dropped byte), ``brk``
    (the line held low past a frame)."""

    rx: In(1, init=1)
    o_bytes: Out(stream.Signature(8))
    frame_error: Out(1)
    brk: Out(1)

    def elaborate(self, platform):
        m = Module()
        line = Signal(init=1)
        m.submodules.sync_rx = FFSynchronizer(self.rx, line, init=1)

        timer = self._timer(m)
        bits = Signal(range(9))
        shift = Signal(8)

        m.d.sync += [self.o_bytes.valid.eq(0), self.frame_error.eq(0)]
        with m.FSM():
            with m.State("Idle"):
                with m.If(~line):
                    m.d.sync += timer.eq(self._divisor // 2 - 1)
                    m.next = "Start"
            with m.State("Start"):
                with m.If(timer == 0):
                    with m.If(line):                      # a glitch, not a start bit
                        m.next = "Idle"
                    with m.Else():
                        m.d.sync += [timer.eq(self._divisor - 1), bits.eq(0)]
                        m.next = "Data"
            with m.State("Data"):
                with m.If(timer == 0):
                    m.d.sync += [shift.eq(Cat(shift[1:], line)), timer.eq(self._divisor - 1),
                                 bits.eq(bits + 1)]
                    with m.If(bits == 7):
                        m.next = "Stop"
            with m.State("Stop"):
                with m.If(timer == 0):
                    with m.If(line):
                        m.d.sync += [self.o_bytes.payload.eq(shift), self.o_bytes.valid.eq(1)]
                        m.next = "Idle"
                    with m.Else():
                        m.d.sync += self.frame_error.eq(1)
                        m.next = "Break"
            with m.State("Break"):
                # a zero byte with a low stop bit is a break; any other framing error ends when
                # the line goes high again too
                m.d.comb += self.brk.eq(shift == 0)
                with m.If(line):
                    m.next = "Idle"
        return m


class UARTTx(_BitTimed):
    """8N1 transmitter. Ports: ``i_bytes`` (bytes to send), ``tx`` (the pin, high when idle)."""

    i_bytes: In(stream.Signature(8))
    tx: Out(1, init=1)

    def elaborate(self, platform):
        m = Module()
        timer = self._timer(m)
        frame = Signal(9, init=0x1FF)         # stop, data[7:0]: shifted out LSB first
        left = Signal(range(10))              # bits of the frame still to send after this one

        with m.If((timer == 0) & (left != 0)):
            m.d.sync += [self.tx.eq(frame[0]), frame.eq(Cat(frame[1:], 1)), left.eq(left - 1),
                         timer.eq(self._divisor - 1)]
        with m.Elif(timer == 0):
            m.d.comb += self.i_bytes.ready.eq(1)
            with m.If(self.i_bytes.valid):     # the start bit at once: a byte every 10 bit times
                m.d.sync += [self.tx.eq(0), frame.eq(Cat(self.i_bytes.payload, 1)), left.eq(9),
                             timer.eq(self._divisor - 1)]
        return m
