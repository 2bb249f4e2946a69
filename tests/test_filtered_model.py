"""The cycle-exact model of the 1 x 1 filtered array (sim/filtered_model.py) against its RTL in the
Amaranth simulator: the cycle each test is accepted, the cycle each result is delivered, and the
answers, equal for every test, with random input gaps and output stalls (seeded, printed), and
with a hand-off too small for the exact path's latency (credit stalls that depend on the data).
"""

import numpy as np
import pytest
from amaranth.sim import Simulator

from blockray.filtered import FilterFormat
from blockray.records import unpack
from blockray.rtl.filtered import FilteredIntersector
from blockray.rtl.processor import result_layout
from blockray.rtl.processor import Processor
from blockray.sim.filtered_model import DATAPATH_LATENCY, EXACT_LATENCY, FilteredIntersectorModel

from processor_vectors import hard_cases, random_tests


def run_rtl(dut, tests, offer, ready):
    """The RTL driven as FilteredIntersectorModel.run drives the model: (accepted, delivered,
    blocked, tags in delivery order)."""
    words = tests.words(dut._bits)
    T = len(tests)
    accepted, delivered, blocked, tags = np.full(T, -1), np.full(T, -1), np.zeros(T, dtype=bool), []

    async def tb(ctx):
        sent = done = t = 0
        held = False
        while done < T:
            assert t < 50 * T + 1000, "no progress"
            valid = sent < T and (held or bool(offer[t % len(offer)]))
            if sent < T:
                ctx.set(dut.i.payload.as_value(), words[sent])
            ctx.set(dut.i.valid, valid)
            ctx.set(dut.o.ready, bool(ready[t % len(ready)]))
            accept = valid and ctx.get(dut.i.ready)
            if accept:
                accepted[sent] = t
            if ctx.get(dut.o.valid) and ready[t % len(ready)]:
                r = unpack(result_layout(), ctx.get(dut.o.payload.as_value()))
                tags.append(r["tag"])
                delivered[r["tag"]] = t
                blocked[r["tag"]] = r["blocked"]
                done += 1
            held = valid and not accept
            sent += accept
            await ctx.tick()
            t += 1

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(tb)
    sim.run()
    return accepted, delivered, blocked, tags


def test_model_latencies_are_the_rtls():
    assert FilteredIntersector.latency == DATAPATH_LATENCY and Processor.latency == EXACT_LATENCY


@pytest.mark.parametrize("fmt, depth", [(FilterFormat.square(9), None), (FilterFormat.square(9), 8),
                                        (FilterFormat(3, 3), 5), (None, None)], ids=str)
def test_model_equals_rtl_cycle_for_cycle(fmt, depth):
    seed = 1616 + (depth or 0)
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    bits = 16
    tests = hard_cases(bits)
    tests = tests[np.sort(rng.choice(len(tests), 250, replace=False))] + random_tests(bits, 150, rng)
    offer, ready = rng.random(997) < 0.8, rng.random(991) < 0.85
    dut = FilteredIntersector(bits, fmt, depth)
    model = FilteredIntersectorModel(bits, fmt, depth)
    assert model.depth == dut.depth and model.fmt == dut.fmt
    trace = model.run(tests.P, tests.Q, tests.V, tests.n, offer, ready)
    accepted, delivered, blocked, tags = run_rtl(dut, tests, offer, ready)
    print(f"{int((~trace.decided).sum())} undecided of {len(tests)}, {trace.cycles} cycles")
    assert tags == list(range(len(tests)))
    assert (blocked == tests.blocked).all() and (trace.blocked == tests.blocked).all()
    assert np.array_equal(trace.accepted, accepted), np.flatnonzero(trace.accepted != accepted)[:5]
    assert np.array_equal(trace.delivered, delivered), np.flatnonzero(trace.delivered != delivered)[:5]
