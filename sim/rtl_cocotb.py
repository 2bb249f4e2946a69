"""cocotb control plane of the RTL harness (sim/rtl_harness.py); the host is sim/rtl_harness.py's HarnessProcess.

One cocotb test serves batches for the life of the simulator: it connects to the host on
``127.0.0.1:$BLOCKRAY_RTL_PORT``, resets the boards, says ``{"ready": ...}``, then for every
request line ``{"bases": [...], "counts": [...], "expects": [...]}`` writes the harness's slice
registers, starts the batch (the harness reads the command file itself) and waits, without any
Python per cycle, until the harness reports it done; it answers ``{"clock": cycles}``. A request
``{"quit": true}`` or the host closing the socket ends the simulation; ``{"reset": true}`` holds
the boards' reset for RESET_CYCLES cycles and answers ``{"clock": cycles}``.
"""

import json
import os
import socket

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge, ValueChange

RESET_CYCLES = 2


def _pack(values):
    word = 0
    for i, v in enumerate(values):
        word |= (int(v) & 0xFFFF_FFFF) << (32 * i)
    return word


@cocotb.test()
async def serve(dut):
    sock = socket.create_connection(("127.0.0.1", int(os.environ["BLOCKRAY_RTL_PORT"])))
    stream = sock.makefile("rwb")

    def send(obj):
        stream.write(json.dumps(obj).encode() + b"\n")
        stream.flush()

    Clock(dut.clk, 10, unit="ns").start()
    dut.rst.value = 1
    for _ in range(RESET_CYCLES):
        await RisingEdge(dut.clk)
    dut.rst.value = 0
    await RisingEdge(dut.clk)
    send({"ready": True, "clock": int(dut.clock.value)})
    batch = 0
    while True:
        line = stream.readline()
        if not line:
            break
        request = json.loads(line)
        if request.get("quit"):
            break
        if request.get("reset"):
            dut.rst.value = 1
            for _ in range(RESET_CYCLES):
                await RisingEdge(dut.clk)
            dut.rst.value = 0
            await RisingEdge(dut.clk)
            send({"clock": int(dut.clock.value)})
            continue
        dut.bases.value = _pack(request["bases"])
        dut.counts.value = _pack(request["counts"])
        dut.expects.value = _pack(request["expects"])
        batch = (batch + 1) & 0xFFFF_FFFF
        dut.start_id.value = batch
        while int(dut.done_id.value) != batch:
            await ValueChange(dut.done_id)
        send({"clock": int(dut.clock.value)})
    sock.close()
