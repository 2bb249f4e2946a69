"""cocotb test of the whole board behind its byte link (Verilator), driven by tests/test_board_cocotb.py.

The pytest side pickles a list of **runs** into ``$BOARD_BATCH``; each run is one board's batch
(``commands``), a seed for the random host timing, the probabilities of an idle command-byte cycle
and of a back-pressured result-byte cycle, an optional probability of bursts (long stalls on both
streams), and an optional cycle at which the host resets the board in the middle of the batch (it
then replays, ``ReplayingHost`` of tests/board_host.py). Every run starts with a reset.

The parts are kept apart as in cocotb's examples/matrix_multiplier: :class:`LinkDriver` drives
the command bytes and the result ``ready`` (the shared drive loop,
:class:`blockray.sim.drive.StreamHost`, inside :class:`board_host.BatchRun`), :class:`LinkMonitor`
samples the handshakes and the result bytes into the run's :class:`board_host.RunLog`; the
reference model (:class:`blockray.sim.model.BoardModel`) and the scoreboard
(:func:`board_host.check_run`) run on the pytest side on the logs written to ``$BOARD_LOG``.

Timing discipline: inputs are driven just after a rising edge; at the falling edge the settled
``valid``/``ready`` decide which transfers the next rising edge makes.
"""

import os
import pickle
import time

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import FallingEdge, RisingEdge

from blockray.sim.drive import HostTiming

from board_host import BatchRun


#: the streams' port names: BoardCore's bytes, or BoardTop's command and result records
PORTS = {"bytes": ("i_bytes", "o_bytes"), "records": ("commands", "results")}


class LinkDriver:
    """Puts the host's next command byte (or record) and its result ``ready`` on the board's ports."""

    def __init__(self, dut, stream, link="bytes"):
        self.dut, self.stream = dut, stream
        i, o = PORTS[link]
        self.i_valid, self.i_payload = getattr(dut, f"{i}__valid"), getattr(dut, f"{i}__payload")
        self.o_ready = getattr(dut, f"{o}__ready")

    def drive(self):
        valid, payload, ready = self.stream.drive()
        self.i_valid.value = valid
        self.i_payload.value = payload
        self.o_ready.value = ready

    def idle(self):
        self.i_valid.value = 0
        self.o_ready.value = 0


class LinkMonitor:
    """Samples the handshakes at the falling edge; reports them after the rising edge."""

    def __init__(self, dut, link="bytes"):
        self.dut = dut
        i, o = PORTS[link]
        self.i_ready = getattr(dut, f"{i}__ready")
        self.o_valid, self.o_payload = getattr(dut, f"{o}__valid"), getattr(dut, f"{o}__payload")

    async def sample(self):
        await FallingEdge(self.dut.clk)
        valid = int(self.o_valid.value)
        sampled = (int(self.i_ready.value), valid, int(self.o_payload.value) if valid else 0)
        await RisingEdge(self.dut.clk)
        return sampled


async def _reset(dut, driver, cycles=2):
    driver.idle()
    dut.rst.value = 1
    for _ in range(cycles):
        await RisingEdge(dut.clk)
    dut.rst.value = 0


async def _run(dut, params, spec):
    burst = spec.get("bursts", 0.0)
    link = spec.get("link", "bytes")
    run = BatchRun(params, spec["commands"], link=link, seed=spec["seed"], reset_at=spec.get("reset_at"),
                   idle=HostTiming(spec["idle"], burst=burst), backpressure=HostTiming(spec["backpressure"], burst=burst),
                   max_cycles=spec.get("max_cycles", 10_000_000))
    driver, monitor = LinkDriver(dut, run.stream, link), LinkMonitor(dut, link)
    await _reset(dut, driver)
    while not run.done:
        if run.reset_due():
            await _reset(dut, driver, 1)
            run.after_reset()
            continue
        driver.drive()
        run.after_cycle(run.stream.sample(*await monitor.sample()))
    return run.log, run.total


@cocotb.test()
async def board_batches(dut):
    with open(os.environ["BOARD_BATCH"], "rb") as f:
        batch = pickle.load(f)
    Clock(dut.clk, 10, unit="ns").start()
    logs = []
    for spec in batch["runs"]:
        t0 = time.perf_counter()
        log, cycles = await _run(dut, batch["params"], spec)
        seconds = time.perf_counter() - t0
        dut._log.info(f"run: {cycles} cycles in {seconds:.2f} s ({cycles / seconds:.0f} cycles/s), "
                      f"resets {log.answered_at_reset}")
        logs.append({"log": log, "cycles": cycles, "seconds": seconds})
    with open(os.environ["BOARD_LOG"], "wb") as f:
        pickle.dump(logs, f)
