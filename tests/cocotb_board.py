"""cocotb test of the whole board (Verilator), driven by tests/test_board_cocotb.py.

The pytest side pickles a list of **runs** into ``$BOARD_BATCH``; each run is one board's batch
(``commands``), a seed for the random host timing, the probabilities of an idle command cycle and
of a back-pressured result cycle, and an optional cycle at which the host resets the board in the
middle of the batch (it then replays, :class:`blockray.rtl.protocol.ReplayingHost`). Every run
starts with a reset. The host here only drives and records; the pytest side compares the
:class:`board_host.RunLog` of each run with the model (``$BOARD_LOG``).

Timing discipline: inputs are driven just after a rising edge; at the falling edge the settled
``valid``/``ready`` decide which transfers the next rising edge makes.
"""

import os
import pickle
import random
import time
from collections import deque

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import FallingEdge, RisingEdge

from blockray.rtl.protocol import BoardProtocol, ReplayingHost

from board_host import RunLog


async def _reset(dut, cycles=2):
    dut.commands__valid.value = 0
    dut.results__ready.value = 0
    dut.rst.value = 1
    for _ in range(cycles):
        await RisingEdge(dut.clk)
    dut.rst.value = 0


async def _run(dut, proto, run):
    rng = random.Random(run["seed"])
    host = ReplayingHost(run["commands"])
    encoded = {}
    log = RunLog()
    await _reset(dut)
    queue = deque(host.pending())
    offer = None
    cycle = 0                   # rising edges since the last reset's release
    total = 0
    reset_at = run.get("reset_at")
    while not host.done:
        total += 1
        if total > run.get("max_cycles", 10_000_000):
            raise AssertionError("the board stopped making progress")
        if reset_at is not None and total == reset_at:
            await _reset(dut, 1)
            log.answered_at_reset.append(host.answered)
            host.reset()
            queue, offer, cycle = deque(host.pending()), None, 0
            continue
        if offer is None and queue and rng.random() >= run["idle"]:
            offer = queue.popleft()
            word = encoded.get(offer[0])
            if word is None:
                word = encoded[offer[0]] = proto.encode(offer[1])
            dut.commands__payload.value = word
        dut.commands__valid.value = int(offer is not None)
        rready = int(rng.random() >= run["backpressure"])
        dut.results__ready.value = rready
        await FallingEdge(dut.clk)
        cready = int(dut.commands__ready.value)
        rvalid = int(dut.results__valid.value)
        rword = int(dut.results__payload.value) if rvalid else None
        await RisingEdge(dut.clk)
        if offer is not None and cready:
            log.accepted[offer[0]] = cycle
            offer = None
        if rvalid and rready:
            log.receive(host, rword, cycle)
        cycle += 1
    return log, total


@cocotb.test()
async def board_batches(dut):
    with open(os.environ["BOARD_BATCH"], "rb") as f:
        batch = pickle.load(f)
    proto = BoardProtocol(batch["params"])
    Clock(dut.clk, 10, unit="ns").start()
    logs = []
    for run in batch["runs"]:
        t0 = time.perf_counter()
        log, cycles = await _run(dut, proto, run)
        seconds = time.perf_counter() - t0
        dut._log.info(f"run: {cycles} cycles in {seconds:.2f} s ({cycles / seconds:.0f} cycles/s), "
                      f"resets {log.answered_at_reset}")
        logs.append({"log": log, "cycles": cycles, "seconds": seconds})
    with open(os.environ["BOARD_LOG"], "wb") as f:
        pickle.dump(logs, f)
