"""Streaming tests through an intersection processor in the Amaranth simulator and checking its
results (imported as ``processor_run``; tests/test_processor_sim.py, test_filtered_sim.py)."""

import numpy as np
from amaranth.sim import Simulator

from blockray.records import unpack
from blockray.rtl.processor import Intersector, result_layout


def run_intersector(bits, tests, *, seed, bubble=0.0, stall=0.0, max_cycles=None, dut=None):
    """Stream ``tests`` through an :class:`Intersector` (or ``dut``, a component with its
    ports), with random input gaps (probability ``bubble`` per cycle) and output backpressure
    (``stall``). Checks the stream rules on ``o``. Returns (results in output order as dicts,
    cycles simulated, the dut)."""
    dut = Intersector(bits) if dut is None else dut
    words = tests.words(bits)
    rng = np.random.default_rng(seed)
    gaps = rng.random(len(words) * 4) < bubble
    stalls = rng.random(len(words) * 8 + 64) < stall
    out = []
    cycles = [0]

    async def producer(ctx):
        g = 0
        for word in words:
            while gaps[g % len(gaps)]:
                g += 1
                await ctx.tick()
            g += 1
            ctx.set(dut.i.payload.as_value(), word)
            ctx.set(dut.i.valid, 1)
            await ctx.tick().until(dut.i.ready)
            ctx.set(dut.i.valid, 0)

    async def consumer(ctx):
        held = None                        # (payload) offered but not taken on the last edge
        layout = result_layout()
        limit = max_cycles or 20 * len(words) + 100
        while len(out) < len(words):
            ready = not stalls[cycles[0] % len(stalls)]
            ctx.set(dut.o.ready, ready)
            _, _, valid, payload = await ctx.tick().sample(dut.o.valid, dut.o.payload.as_value())
            cycles[0] += 1
            assert cycles[0] < limit, f"no progress after {cycles[0]} cycles ({len(out)} results)"
            if held is not None:
                assert valid and payload == held, "o.valid/o.payload changed before the transfer"
            held = None
            if valid and ready:
                out.append(unpack(layout, payload))
            elif valid:
                held = payload

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(producer)
    sim.add_testbench(consumer)
    sim.run()
    return out, cycles[0], dut


def check_results(out, tests):
    assert len(out) == len(tests)
    tags = np.array([o["tag"] for o in out])
    assert (tags == np.arange(len(tests)) % (1 << 16)).all(), "results out of order or lost"
    got = np.array([o["blocked"] for o in out], dtype=bool)
    bad = np.flatnonzero(got != tests.blocked)
    assert len(bad) == 0, (
        f"{len(bad)} mismatches, first at test {bad[0]}: P={tests.P[bad[0]]} Q={tests.Q[bad[0]]} "
        f"V={tests.V[bad[0]].tolist()} expected {tests.blocked[bad[0]]}")
