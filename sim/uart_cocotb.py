"""cocotb side of the simulated real board (``--board ulx3s-sim``): a virtual serial port.

The simulation is the board's top level at its pins (:class:`blockray.rtl.link.SerialLink`: UART,
framed link, the core). One cocotb test connects to the host on
``127.0.0.1:$BLOCKRAY_UART_PORT`` and plays the USB-serial bridge: bytes from the host are driven
on ``rx`` as 8N1 frames of ``$BLOCKRAY_UART_DIVISOR`` clock cycles per bit, frames seen on ``tx``
are decoded in the middle of each bit and sent to the host. Host to simulator messages: a type
byte and a 2-byte little-endian length, then the payload: ``D`` bytes to send, ``B`` break on (rx
held low), ``b`` break off, ``Q`` quit. Simulator to host: the received bytes, raw. While the host
has nothing to send, the simulation runs on in steps of a frame time, so the board keeps answering.
"""

import os
import socket

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import ClockCycles, FallingEdge, RisingEdge


async def _monitor(dut, sock, divisor):
    while True:
        await FallingEdge(dut.tx)
        await ClockCycles(dut.clk, divisor // 2)            # the middle of the start bit
        byte = 0
        for k in range(8):
            await ClockCycles(dut.clk, divisor)
            byte |= int(dut.tx.value) << k
        await ClockCycles(dut.clk, divisor)                 # the stop bit
        if int(dut.tx.value) == 1:
            sock.sendall(bytes([byte]))


async def _send(dut, byte, divisor):
    for bit in [0] + [(byte >> k) & 1 for k in range(8)] + [1]:
        dut.rx.value = bit
        await ClockCycles(dut.clk, divisor)


@cocotb.test()
async def serve(dut):
    divisor = int(os.environ["BLOCKRAY_UART_DIVISOR"])
    sock = socket.create_connection(("127.0.0.1", int(os.environ["BLOCKRAY_UART_PORT"])))
    Clock(dut.clk, 10, unit="ns").start()
    dut.rx.value = 1
    dut.rst.value = 1
    await ClockCycles(dut.clk, 2)
    dut.rst.value = 0
    await RisingEdge(dut.clk)
    cocotb.start_soon(_monitor(dut, sock, divisor))
    sock.setblocking(False)
    pending = bytearray()
    while True:
        try:
            data = sock.recv(65536)
            if not data:
                break
            pending += data
        except BlockingIOError:
            pass
        if len(pending) < 3 or len(pending) < 3 + int.from_bytes(pending[1:3], "little"):
            await ClockCycles(dut.clk, 10 * divisor)        # nothing to do: let the board run
            continue
        kind, n = pending[0], int.from_bytes(pending[1:3], "little")
        payload = bytes(pending[3:3 + n])
        del pending[:3 + n]
        if kind == ord("Q"):
            break
        if kind == ord("B"):
            dut.rx.value = 0
            await ClockCycles(dut.clk, 10 * divisor)
        elif kind == ord("b"):
            dut.rx.value = 1
            await ClockCycles(dut.clk, divisor)
        else:
            for byte in payload:
                await _send(dut, byte, divisor)
    sock.close()
