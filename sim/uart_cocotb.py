"""cocotb side of the simulated real board (``--board ulx3s-sim``): a virtual serial port that
runs in lockstep with the host.

The simulation is the board's top level at its pins (:class:`blockray.rtl.link.SerialLink`: UART,
framed link, the core). One cocotb test connects to the host on
``127.0.0.1:$BLOCKRAY_UART_PORT`` and plays the USB-serial bridge: bytes from the host are driven
on ``rx`` as 8N1 frames of ``$BLOCKRAY_UART_DIVISOR`` clock cycles per bit, frames seen on ``tx``
are decoded in the middle of each bit. Simulated time advances only when the host asks
(``R``), so the host's time-outs count clock cycles, not the wall clock: a run is the same on a
loaded machine as on an idle one.

Host to simulator messages: a type byte and a 2-byte little-endian length, then the payload:
``D`` bytes to send (queued; they go out during runs), ``R`` run for at most the 4-byte
little-endian number of cycles, ``B`` break on (rx held low, the queue dropped), ``b`` break
off, ``Q`` quit. The simulator answers each ``R`` once the cycles have passed or, earlier, on
the clock cycle a frame delimiter (a zero byte) was decoded on ``tx``: ``T``, the cycles run,
the bytes still queued for ``rx`` and the number of received bytes (4 bytes each,
little-endian), then those bytes.
"""

import os
import socket

import cocotb
from cocotb.clock import Clock
from cocotb.simtime import get_sim_time
from cocotb.triggers import ClockCycles, Event, FallingEdge, First, RisingEdge

#: the clock period in ns (the host converts cycles to simulated seconds with it)
PERIOD_NS = 10


class _Port:
    """The bridge's state: bytes queued for ``rx``, bytes decoded from ``tx``, the break."""

    def __init__(self):
        self.queue = bytearray()
        self.queued = Event()
        self.received = bytearray()
        self.delimiter = Event()
        self.brk = False


async def _monitor(dut, port, divisor):
    while True:
        await FallingEdge(dut.tx)
        await ClockCycles(dut.clk, divisor // 2)            # the middle of the start bit
        byte = 0
        for k in range(8):
            await ClockCycles(dut.clk, divisor)
            byte |= int(dut.tx.value) << k
        await ClockCycles(dut.clk, divisor)                 # the stop bit
        if int(dut.tx.value) == 1:
            port.received.append(byte)
            if byte == 0:
                port.delimiter.set()


async def _driver(dut, port, divisor):
    while True:
        while port.brk or not port.queue:
            port.queued.clear()
            await port.queued.wait()
        byte = port.queue.pop(0)
        for bit in [0] + [(byte >> k) & 1 for k in range(8)] + [1]:
            if port.brk:                                    # a break cuts the byte short
                break
            dut.rx.value = bit
            await ClockCycles(dut.clk, divisor)


def _cycles():
    return round(get_sim_time(unit="ns")) // PERIOD_NS


class _Messages:
    """The host's messages from a blocking socket: the simulation stands still while it waits."""

    def __init__(self, sock):
        self.sock, self.pending = sock, bytearray()

    def next(self):
        while len(self.pending) < 3 or len(self.pending) < 3 + int.from_bytes(self.pending[1:3], "little"):
            data = self.sock.recv(65536)
            if not data:
                return None, b""
            self.pending += data
        kind, n = self.pending[0], int.from_bytes(self.pending[1:3], "little")
        payload = bytes(self.pending[3:3 + n])
        del self.pending[:3 + n]
        return chr(kind), payload


async def _run(dut, port, sock, cycles):
    start = _cycles()
    if not port.delimiter.is_set():
        await First(ClockCycles(dut.clk, cycles), port.delimiter.wait())
    port.delimiter.clear()
    out, port.received = bytes(port.received), bytearray()
    sock.sendall(b"T" + (_cycles() - start).to_bytes(4, "little") + len(port.queue).to_bytes(4, "little")
                 + len(out).to_bytes(4, "little") + out)


@cocotb.test()
async def serve(dut):
    divisor = int(os.environ["BLOCKRAY_UART_DIVISOR"])
    sock = socket.create_connection(("127.0.0.1", int(os.environ["BLOCKRAY_UART_PORT"])))
    Clock(dut.clk, PERIOD_NS, unit="ns").start()
    dut.rx.value = 1
    dut.rst.value = 1
    await ClockCycles(dut.clk, 2)
    dut.rst.value = 0
    await RisingEdge(dut.clk)
    port = _Port()
    cocotb.start_soon(_monitor(dut, port, divisor))
    cocotb.start_soon(_driver(dut, port, divisor))
    messages = _Messages(sock)
    while True:
        kind, payload = messages.next()
        if kind in (None, "Q"):
            break
        if kind == "D":
            port.queue += payload
            port.queued.set()
        elif kind == "R":
            await _run(dut, port, sock, max(1, int.from_bytes(payload, "little")))
        elif kind == "B":
            port.brk = True
            port.queue.clear()
            dut.rx.value = 0
        elif kind == "b":
            port.brk = False
            dut.rx.value = 1
            port.queued.set()
    sock.close()
