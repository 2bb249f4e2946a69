"""The filtered cell (rtl/filtered.py) in the Amaranth simulator.

The filter stages against :mod:`blockray.filtered` bit for bit (``decided`` and ``blocked`` of
every test); the streamed 1 x 1 filtered array against the exact predicate with zero tolerance,
in order, with input gaps and output stalls, on hard cases (which take the exact path) and
seeded random tests. Each test prints its seed.
"""

import numpy as np
import pytest
from amaranth.hdl import Module
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from blockray.filtered import FilterFormat, filtered_tests
from blockray.records import pack_array, patch_columns, point_columns
from blockray.rtl.filtered import FilteredIntersector, FilteredProcessor, ReceiverFilter, ShooterFilter
from blockray.rtl.processor import ReceiverUnit, ShooterUnit, _crossing
from blockray.records import patch_layout, point_layout

from processor_vectors import hard_cases, random_tests
from processor_run import check_results, run_intersector

SEED = 16016


class FilterChain(wiring.Component):
    """Exact units -> filters -> filtered cell: one test per cycle, ``decided``/``blocked``."""

    def __init__(self, bits, fmt):
        self.bits, self.fmt = bits, fmt
        self.latency = ShooterUnit.latency + ShooterFilter.latency + FilteredProcessor.latency
        super().__init__({"shooter": In(point_layout(bits)), "receiver": In(point_layout(bits)),
                          "patch": In(patch_layout(bits)), "valid": In(1),
                          "decided": Out(1), "blocked": Out(1), "result_valid": Out(1)})

    def elaborate(self, platform):
        m = Module()
        m.submodules.su = su = ShooterUnit(self.bits)
        m.submodules.ru = ru = ReceiverUnit(self.bits)
        m.submodules.sf = sf = ShooterFilter(self.bits, self.fmt)
        m.submodules.rf = rf = ReceiverFilter(self.bits, self.fmt)
        m.submodules.cell = cell = FilteredProcessor(self.fmt)
        m.d.comb += [
            su.point.eq(self.shooter), su.patch.eq(self.patch), su.valid.eq(self.valid),
            ru.point.eq(self.receiver), ru.patch.eq(self.patch), ru.valid.eq(self.valid),
            sf.exact.eq(su.terms), sf.valid.eq(su.terms_valid), rf.exact.eq(ru.terms), rf.valid.eq(ru.terms_valid),
            cell.shooter.eq(sf.terms), cell.receiver.eq(rf.terms), cell.valid.eq(sf.terms_valid),
            cell.crossing.eq(_crossing(sf.plane_out, rf.plane_out)),
            self.decided.eq(cell.decided), self.blocked.eq(cell.blocked), self.result_valid.eq(cell.result_valid),
        ]
        return m


def run_chain(bits, fmt, tests):
    dut = FilterChain(bits, fmt)
    sw = pack_array(point_layout(bits), point_columns(tests.P))
    rw = pack_array(point_layout(bits), point_columns(tests.Q))
    vw = pack_array(patch_layout(bits), patch_columns(tests.V, tests.n))
    got = []

    async def tb(ctx):
        for t in range(len(tests) + dut.latency):
            if t < len(tests):
                ctx.set(dut.shooter.as_value(), sw[t])
                ctx.set(dut.receiver.as_value(), rw[t])
                ctx.set(dut.patch.as_value(), vw[t])
            ctx.set(dut.valid, int(t < len(tests)))
            await ctx.tick()
            if ctx.get(dut.result_valid):
                got.append((t + 1, ctx.get(dut.decided), ctx.get(dut.blocked)))

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(tb)
    sim.run()
    return got, dut.latency


@pytest.mark.parametrize("bits, fmt", [(6, FilterFormat(4, 5)), (16, FilterFormat.square(9)),
                                       (16, FilterFormat(17, 18)), (20, FilterFormat(12, 14))], ids=str)
def test_filter_stages_equal_the_reference(bits, fmt):
    """``decided`` and ``blocked`` of every test equal blockray.filtered's (not only the final
    answer): hard cases and random tests."""
    seed = SEED + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    tests = hard_cases(bits)
    tests = tests[np.sort(rng.choice(len(tests), 500, replace=False))] + random_tests(bits, 500, rng)
    decided, blocked = filtered_tests(tests.P, tests.Q, tests.V, tests.n, fmt)
    assert not decided.all() and decided.any()
    got, latency = run_chain(bits, fmt, tests)
    assert [t for t, _, _ in got] == list(range(latency, latency + len(tests)))
    assert np.array_equal([d for _, d, _ in got], decided)
    assert np.array_equal(np.array([b for _, _, b in got], dtype=bool)[decided], blocked[decided])


@pytest.mark.parametrize("bits, fmt", [(6, FilterFormat(3, 4)), (16, FilterFormat.square(9)), (16, None)], ids=str)
def test_filtered_intersector_equals_exact(bits, fmt):
    """Zero mismatches with the exact predicate, results in order, with gaps and stalls, and the
    exact path taken (undecided tests among them)."""
    seed = SEED + 100 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    tests = hard_cases(bits)
    tests = tests[np.sort(rng.choice(len(tests), 700, replace=False))] + random_tests(bits, 500, rng)
    dut = FilteredIntersector(bits, fmt)
    decided, _ = filtered_tests(tests.P, tests.Q, tests.V, tests.n, dut.fmt)
    print(f"{int((~decided).sum())} of {len(tests)} tests undecided by {dut.fmt}")
    assert (~decided).sum() > 10
    out, _, _ = run_intersector(bits, tests, seed=seed, bubble=0.2, stall=0.2, dut=dut)
    check_results(out, tests)


def test_all_undecided_back_to_back_does_not_deadlock():
    """Most crossing tests undecided (a 2-bit filter on hard cases), input always valid, output always
    ready: the credits throttle the input, nothing is lost, results in order."""
    bits, fmt = 16, FilterFormat(2, 2)
    tests = hard_cases(bits)[:300]
    dut = FilteredIntersector(bits, fmt)
    out, cycles, _ = run_intersector(bits, tests, seed=SEED, dut=dut)
    check_results(out, tests)
    print(f"{len(tests)} tests in {cycles} cycles")
