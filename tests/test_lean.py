"""The lean array (rtl/lean.py) and its cycle model (sim/lean_model.py).

The model's bits against the independent orient3d predicate (``blocked_reference``) on the
processor vectors and on a small scene; the RTL against the model in Amaranth's simulator with
zero tolerance: every marker's cycle and the accumulators' bits when it leaves, and the cycle
every step is presented under the model's credits.
"""

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from amaranth.hdl import Cat, Fragment, Module, Signal, signed
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from blockray.cell import Cell
from blockray.errors import ParameterError
from blockray.exact import blocked_block, blocked_reference, patch_normals
from blockray.filtered import FilterFormat, rounded_receiver_filter_terms
from blockray.host_driver.render.render import render
from blockray.params import BoardParams, Widths
from blockray.timing import LEAN_LATENCY, BoardTiming
from blockray.records import pack_array, patch_columns, patch_layout, point_columns, point_layout
from blockray.rtl.board import BoardTop
from blockray.rtl.filtered import FilteredArray
from blockray.rtl.lean import LeanArray, LeanExact, LeanReceiver, LeanRowUnit
from blockray.rtl.processor import ReceiverUnit
from blockray.rtl.lutdot import bit_heap, dot_product
from blockray.sim.cocotb_support import build_verilator, run_cocotb
from blockray.sim.lean_model import (LEAN_EXACT_INTERVAL, LEAN_EXACT_LATENCY, LEAN_HANDOFF_STAGES, Gap, LeanArrayModel, Mark, Record,
                                     default_lean_depth)

from board_scenes import crossing_patches, random_points
from lean_bench import LeanBench, StepDriver
from processor_vectors import hard_cases, random_tests
from scenes import RTL_BITS as BITS, RTL_PARAMS as PARAMS


def _reference(P, Q, V):
    return np.array([blocked_reference(*(tuple(int(c) for c in x) for x in (p, q, v[0], v[1], v[2])))
                     for p, q, v in zip(P, Q, V)], dtype=bool)


def _single_tests(tests, first_mark=True):
    """Each test a 1 x 1 record with its own patch (address = its index), a marker after it."""
    steps = []
    for i in range(len(tests)):
        steps.append(Record(i, True, tests.P[i:i + 1], tests.Q[i:i + 1], np.ones(1, bool), np.ones(1, bool)))
        if first_mark:
            steps.append(Mark())
    return steps


class RowChainModel:
    """The Amaranth simulator's stand-in for ``ECP5Target(fabric_units={"rounded"})``: the row
    unit's w_k products as rtl/lutdot.py's CCU2C bit heaps built from their INIT tables
    (``ccu2c = "model"``); pQ's products generic."""
    ccu2c = "model"
    fabric_units = frozenset({"rounded"})

    def __repr__(self):         # the test id: the same on every xdist worker (no address)
        return "row-chains"


def _receiver_cases(bits, fmt, rng, hard_step, count):
    """Receiver-unit tests (hard cases, every ``hard_step``-th, then random: ``count`` of each), the
    terms :func:`rounded_receiver_filter_terms` gives them and their exact pQ."""
    tests = hard_cases(bits)[::hard_step][:count] + random_tests(bits, count, rng)
    dQ, E = tests.Q[:, None] - tests.V, np.roll(tests.V, -1, axis=-2) - tests.V
    pq = np.einsum("tc,tc->t", tests.Q - tests.V[:, 0], tests.n)
    return tests, rounded_receiver_filter_terms(dQ, E, fmt), pq


def _check_receiver_terms(got, want, pq):
    """``got``: (m, pos, neg, truncated, plane) per test, in order."""
    assert len(got) == len(pq)
    for i, (m, pos, neg, trunc, plane) in enumerate(got):
        assert m == want["m"][i].tolist(), i
        assert (pos, neg, trunc) == (want["pos"][i].tolist(), want["neg"][i].tolist(),
                                     want["truncated"][i].astype(int).tolist()), i
        assert plane == pq[i], i


def _terms_tuple(v, plane):
    return ([[v.m[k][c] for c in range(3)] for k in range(3)], [v.pos[k] for k in range(3)],
            [v.neg[k] for k in range(3)], [(v.truncated >> k) & 1 for k in range(3)], plane)


@pytest.mark.parametrize("bits,fmt", [(16, FilterFormat(9, 9, 12)), (16, FilterFormat(4, 5, 3)),
                                      (20, FilterFormat(9, 9, 14)), (6, FilterFormat(7, 9, 12))], ids=str)
def test_lean_receiver_terms_equal_the_model(bits, fmt):
    """LeanReceiver against :func:`blockray.filtered.rounded_receiver_filter_terms` and the exact
    pQ, term by term, one test per cycle with gaps, at its latency 7: 300 hard and 300 random
    tests (B = 6 with 12-bit inputs: nothing rounded)."""
    seed = 3500 + bits
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    tests, want, pq = _receiver_cases(bits, fmt, rng, 40, 300)
    dut = LeanReceiver(bits, fmt)
    qw = pack_array(point_layout(bits), point_columns(tests.Q))
    vw = pack_array(patch_layout(bits), patch_columns(tests.V, tests.n))
    gaps = rng.random(2 * len(tests)) < 0.2
    got = []

    async def bench(ctx):
        t = 0
        for gap in gaps:
            if not gap and t < len(tests):
                ctx.set(dut.point.as_value(), qw[t])
                ctx.set(dut.patch.as_value(), vw[t])
            ctx.set(dut.valid, int(not gap and t < len(tests)))
            t += int(not gap and t < len(tests))
            await ctx.tick()
            if ctx.get(dut.terms_valid):
                got.append(_terms_tuple(ctx.get(dut.terms), ctx.get(dut.plane_out)))
    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(bench)
    sim.run()
    assert min(len(tests), int((~gaps).sum())) == len(tests)       # every test went in
    _check_receiver_terms(got, want, pq)


class _UnitStreams(wiring.Component):
    """Row or receiver units fed the same tests, elaborated for ``plat``, behind the streams the
    native vector harness drives: ``i`` (point, patch) into every unit's ``point``, ``patch`` and
    ``valid``; out on ``o`` when the first unit's ``terms_valid``: each unit's ``terms`` (and the
    first's ``plane_out`` if it has one), and ``apart``, set for good once the units' ``terms_valid``
    differed in a cycle. The units never wait: ``i.ready`` is always high, and the host never
    back-pressures ``o``."""

    def __init__(self, bits, units, plat):
        self.units, self.plat = units, plat
        fields = {f"terms{k}": u.terms.shape() for k, u in enumerate(units)}
        if hasattr(units[0], "plane_out"):
            fields["plane"] = signed(Widths(bits).orient)
        fields["apart"] = 1
        super().__init__({
            "i": In(stream.Signature(data.StructLayout({"point": point_layout(bits), "patch": patch_layout(bits)}))),
            "o": Out(stream.Signature(data.StructLayout(fields)))})

    def elaborate(self, platform):
        m = Module()
        for k, u in enumerate(self.units):
            m.submodules[f"unit{k}"] = Fragment.get(u, self.plat)
            m.d.comb += [u.point.eq(self.i.payload.point), u.patch.eq(self.i.payload.patch), u.valid.eq(self.i.valid),
                         self.o.payload[f"terms{k}"].eq(u.terms)]
        differ = Cat(u.terms_valid != self.units[0].terms_valid for u in self.units[1:]).any()
        m.d.sync += self.o.payload.apart.eq(self.o.payload.apart | differ)
        if hasattr(self.units[0], "plane_out"):
            m.d.comb += self.o.payload.plane.eq(self.units[0].plane_out)
        m.d.comb += [self.i.ready.eq(1), self.o.valid.eq(self.units[0].terms_valid)]
        return m


def _run_units(tests, bits, make_units, name, seed):
    """The tests through ``_UnitStreams(bits, make_units(), RowChainModel())`` in the native vector
    harness, the host idle on 20% of the cycles: the output views, one a test, and the clock cycles.
    Converted to Verilog every time (no ``source``: the wrapper here is not part of the build
    index's key); the build itself is cached by the Verilog's content."""
    from blockray.sim.drive import HostTiming
    from blockray.sim.native.vectors import NativeVectors

    top = _UnitStreams(bits, make_units(), RowChainModel())        # for its output layout
    top._MustUse__silence = True
    for u in top.units:
        u._MustUse__silence = True
    runner = NativeVectors(lambda: _UnitStreams(bits, make_units(), RowChainModel()), name=name,
                           idle=HostTiming(0.2), seed=seed)
    try:
        words = [q | (v << point_layout(bits).size) for q, v in
                 zip(pack_array(point_layout(bits), point_columns(tests.Q)),
                     pack_array(patch_layout(bits), patch_columns(tests.V, tests.n)))]
        out = runner.run(np.array([list(w.to_bytes(runner.n_in, "little")) for w in words], dtype=np.uint8))
        cycles = runner.cycles
    finally:
        runner.close()
    layout = top.o.payload.shape()
    return [layout.from_bits(int.from_bytes(row.tobytes(), "little")) for row in out], cycles


@pytest.mark.cocotb
def test_lean_receiver_terms_on_carry_chains_equal_the_model():
    """The same with w_k's products on modelled CCU2C carry chains (``RowChainModel``), B = 16, in
    the native vector harness (Verilator; the bit-level chains take 0.7 s a clock cycle in
    Amaranth's simulator): 1 200 hard and 1 200 random tests, the host idle on 20% of the cycles."""
    bits, fmt, seed = 16, FilterFormat(9, 9, 12), 3516
    print(f"seed {seed}")
    tests, want, pq = _receiver_cases(bits, fmt, np.random.default_rng(seed), 10, 1200)
    views, cycles = _run_units(tests, bits, lambda: [LeanReceiver(bits, fmt)], "lean_receiver_chains", seed)
    assert cycles > len(tests) * 1.1                        # the host did idle
    _check_receiver_terms([_terms_tuple(v.terms0, v.plane) for v in views], want, pq)


@pytest.mark.cocotb
def test_row_unit_with_carry_chains_equals_the_receiver_unit():
    """LeanRowUnit with its w_k bit heaps on modelled CCU2C cells (RowChainModel, what
    ``--fabric-units rounded`` builds on ECP5) against a ReceiverUnit on plain products, cycle for
    cycle and every bit of ``terms`` (w_k and pQ), B = 16, in the native vector harness: 400 hard
    and 1 000 random tests, the host idle on 20% of the cycles."""
    bits, seed = 16, 3700
    print(f"seed {seed}")
    tests = hard_cases(bits)[::20][:400] + random_tests(bits, 1000, np.random.default_rng(seed))
    views, _ = _run_units(tests, bits, lambda: [LeanRowUnit(bits), ReceiverUnit(bits)], "lean_row_unit_chains", seed)
    assert len(views) == len(tests) and not views[-1].apart          # valid in the same cycles throughout
    chains, plain = [v.terms0.as_bits() for v in views], [v.terms1.as_bits() for v in views]
    assert chains == plain
    assert len(set(plain)) >= 20        # the terms do change


def test_model_constants_are_the_rtls():
    assert LEAN_EXACT_LATENCY == LeanExact.latency == 12 and LEAN_EXACT_INTERVAL == LeanExact.interval == 3
    assert LeanArrayModel(8, 2, 2).depth == LeanArray.default_depth() == 65
    assert default_lean_depth() == LeanArray.default_depth(2) == 67       # behind the board's memory
    # the register before the hand-off: one cycle more than the filtered array, in the board's timing too
    assert LEAN_HANDOFF_STAGES == LeanArray.handoff_stages == LeanArray.latency - FilteredArray.latency == 1
    assert BoardTiming.for_cell(Cell("lean")).processor_latency == LEAN_LATENCY == LeanArray.latency + 3


@pytest.mark.parametrize("bits,fmt", [(6, FilterFormat(3, 3)), (16, None), (16, FilterFormat(3, 4)),
                                      (16, FilterFormat(9, 9, 12))])
def test_model_bits_equal_the_reference_on_processor_vectors(bits, fmt):
    """Every delivered bit of the model (filter where decided, exact unit where not) equals the
    independent orient3d predicate, on hard cases and random blocks, one test per record."""
    seed = 3000 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    hard = hard_cases(bits)
    tests = hard[rng.permutation(len(hard))[:1500]] + random_tests(bits, 800, rng)
    model = LeanArrayModel(bits, 1, 1, fmt=fmt)
    trace = model.run(_single_tests(tests), tests.V, tests.n)
    got = np.array([h[0, 0] for h in trace.hits])
    want = _reference(tests.P, tests.Q, tests.V)
    assert (got == want).all(), np.flatnonzero(got != want)[:10]
    assert trace.undecided.sum() > 0                     # the exact unit's path is exercised
    print("undecided", int(trace.undecided.sum()), "of", len(tests), "cycles", trace.cycles)


def _scene_blocks(rng, bits, rows, cols, blocks, patches):
    """Random blocks of the board's kind: points, crossing-heavy patches, some records gapped."""
    out = []
    for _ in range(blocks):
        P, Q = random_points(rng, bits, cols), random_points(rng, bits, rows)
        V = crossing_patches(rng, bits, P, Q, int(rng.integers(1, patches)))
        out.append((P, Q, V))
    return out


def _steps(rng, blocks, rows, cols, gap=0.2, partial=True):
    """Steps of ``blocks`` (P, Q, V of each) with patch addresses into the concatenated V; a
    marker after each block; random gaps; a partial block's row and column masks."""
    steps, Vs = [], []
    for P, Q, V in blocks:
        row_mask, col_mask = np.ones(rows, bool), np.ones(cols, bool)
        if partial and rng.random() < 0.3:
            row_mask[rng.integers(rows)] = False
            col_mask[rng.integers(cols)] = False
        for i in range(len(V)):
            while rng.random() < gap:
                steps.append(Gap())
            steps.append(Record(len(Vs), i == 0, P, Q, row_mask, col_mask))
            Vs.append(V[i])
        steps.append(Mark())
    V = np.array(Vs, dtype=np.int64)
    return steps, V, patch_normals(V)


def test_model_on_a_small_scene_equals_the_exact_blocks():
    """2 x 3 array, 3 x 3-bit filter (many undecided), 30 blocks: the OR at each marker equals
    blocked_block's OR over the block, where the rows and columns are loaded."""
    seed = 3101
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    bits, rows, cols = 10, 2, 3
    blocks = _scene_blocks(rng, bits, rows, cols, 30, 10)
    steps, V, n = _steps(rng, blocks, rows, cols)
    trace = LeanArrayModel(bits, rows, cols, fmt=FilterFormat(3, 3)).run(steps, V, n)
    records = [s for s in steps if isinstance(s, Record)]
    k = 0
    for b, (P, Q, Vb) in enumerate(blocks):
        mask = records[k].row_mask[:, None] & records[k].col_mask[None, :]
        want = blocked_block(P, Q, Vb, patch_normals(Vb)).any(axis=2)
        assert ((trace.hits[b] & mask) == (want & mask)).all(), b
        k += len(Vb)
    assert trace.undecided.sum() > 20
    print("undecided", int(trace.undecided.sum()), "cycles", trace.cycles)


def _run_rtl(bits, rows, cols, fmt, depth, steps, V, n, platform=None):
    """The RTL in the Amaranth simulator under the owner's credits (tests/lean_bench.py): the
    cycle each step is presented, each marker's cycle and ``hit`` then. ``platform``: the one
    every ``elaborate`` sees (None: the generic netlist)."""
    words = pack_array(patch_layout(bits), patch_columns(V, n))
    bench = LeanBench(bits, rows, cols, fmt, depth, words)
    driver = StepDriver(steps, words, bits, rows, cols, depth)
    sim = Simulator(bench if platform is None else Fragment.get(bench, platform))
    sim.add_clock(1e-8)

    async def drive(ctx):
        limit = 60 * len(steps) + 500
        while not driver.done and driver.t < limit:
            for name, value in driver.inputs().items():
                port = getattr(bench, name)
                ctx.set(port.as_value() if hasattr(port, "as_value") else port, value)
            driver.observe(ctx.get(bench.delivered), ctx.get(bench.mark_out), ctx.get(bench.hit))
            await ctx.tick()
        assert driver.done, "the array stopped delivering"

    sim.add_testbench(drive)
    sim.run()
    return np.array(driver.presented), np.array(driver.marks), driver.hits


def _word(bits_rs):
    return int(sum(1 << int(i) for i in np.flatnonzero(np.asarray(bits_rs).ravel())))


def _run_verilator(bits, rows, cols, fmt, depth, steps, V, n, tmp_path):
    """The Verilog of the same bench under cocotb + Verilator (tests/cocotb_lean.py)."""
    words = pack_array(patch_layout(bits), patch_columns(V, n))
    build = build_verilator(LeanBench(bits, rows, cols, fmt, depth, words), name=f"lean_bench_{rows}x{cols}")
    print(f"verilator build: {'cached' if build.cached else f'{build.seconds:.1f} s'}")
    return _run_bench(build, (steps, words, bits, rows, cols, depth), tmp_path)


def _run_bench(build, steps_etc, tmp_path):
    """Run tests/cocotb_lean.py on a Verilator ``build`` with the pickled steps: (presented, marks, hits)."""
    (tmp_path / "steps.pkl").write_bytes(pickle.dumps(steps_etc))
    out = tmp_path / "out.json"
    run_cocotb(build, "cocotb_lean", module_dir=Path(__file__).parent, test_dir=tmp_path,
               env={"BLOCKRAY_STEPS": str(tmp_path / "steps.pkl"), "BLOCKRAY_OUT": str(out)})
    got = json.loads(out.read_text())
    return np.array(got["presented"]), np.array(got["marks"]), got["hits"]


def _compare(bits, rows, cols, fmt, depth, steps, V, n, run=_run_rtl):
    model = LeanArrayModel(bits, rows, cols, fmt=fmt, depth=depth)
    trace = model.run(steps, V, n)
    presented, marks, hits = run(bits, rows, cols, model.fmt, model.depth, steps, V, n)
    assert (presented == trace.cycle).all(), np.flatnonzero(presented != trace.cycle)[:5]
    assert list(marks) == list(trace.marks)
    masks = []
    for s in steps:
        if isinstance(s, Record):
            mask = _word(s.row_mask[:, None] & s.col_mask[None, :])
        elif isinstance(s, Mark):
            masks.append(mask)
    got = [h & m for h, m in zip(hits, masks)]
    want = [_word(h) & m for h, m in zip(trace.hits, masks)]
    assert got == want, [k for k, (a, b) in enumerate(zip(got, want)) if a != b][:5]
    return trace


@pytest.mark.parametrize("bits,fmt,depth,count", [(6, FilterFormat(3, 3), None, 160), (16, None, None, 160),
                                                   (16, FilterFormat(9, 9, 12), None, 160),
                                                   (16, FilterFormat(3, 4), 5, 120)])
def test_rtl_equals_model_on_processor_vectors(bits, fmt, depth, count):
    """1 x 1 lean array, one test per record and a marker after each: cycles and bits equal the
    model's, zero tolerance (hard cases and random tests)."""
    seed = 3200 + bits + (depth or 0)
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    hard = hard_cases(bits)
    tests = hard[rng.permutation(len(hard))[:count]] + random_tests(bits, count // 2, rng)
    trace = _compare(bits, 1, 1, fmt, depth, _single_tests(tests), tests.V, tests.n)
    assert trace.undecided.sum() > 0
    print("undecided", int(trace.undecided.sum()), "cycles", trace.cycles)


class CarryChainModel:
    """A stand-in target for the Amaranth simulator: the cells' products in the fabric as
    rtl/lutdot.py's CCU2C bit heaps, each carry cell built from its INIT tables in Amaranth logic
    (``ccu2c = "model"``: the tables and wiring the ECP5 netlist instantiates); every other
    product generic."""
    ccu2c = "model"
    fabric_units = frozenset({"cell"})


@pytest.mark.parametrize("na,nb,terms,width,minus", [(9, 9, 3, 20, ()), (3, 3, 3, 8, ()), (9, 12, 3, 23, ()),
                                                     (5, 7, 2, 14, ()), (2, 2, 1, 4, ()), (18, 18, 3, 38, ()),
                                                     (12, 12, 2, 25, (1,)), (3, 3, 2, 7, (1,)), (2, 2, 1, 5, (0,)),
                                                     (5, 4, 3, 10, (0, 2))], ids=str)
def test_carry_chain_dot_product_equals_the_products(na, nb, terms, width, minus):
    """rtl/lutdot.py's bit heap on modelled CCU2C cells against ``reg(reg(a) * reg(b))`` summed
    (the pairs numbered in ``minus`` subtracted: the row unit's W = q_a g_b - q_b g_a), cycle for
    cycle: the extremes of both operands (every sign combination) and random values."""
    rng = np.random.default_rng(3600 + na * nb + terms)
    lo_a, hi_a, lo_b, hi_b = -(1 << na - 1), (1 << na - 1) - 1, -(1 << nb - 1), (1 << nb - 1) - 1
    vectors = [[(x, y)] * terms for x in (lo_a, hi_a, -1, 0, 1) for y in (lo_b, hi_b, -1, 0, 1)]
    vectors += [list(zip(rng.integers(lo_a, hi_a + 1, terms).tolist(), rng.integers(lo_b, hi_b + 1, terms).tolist()))
                for _ in range(400)]
    a = [Signal(signed(na), name=f"a{i}") for i in range(terms)]
    b = [Signal(signed(nb), name=f"b{i}") for i in range(terms)]
    m = Module()
    pairs = [(x, y, i in minus) for i, (x, y) in enumerate(zip(a, b))]
    got = dot_product(m, pairs, width, "heap", CarryChainModel())
    want = dot_product(m, pairs, width, "mul", None)
    assert len(bit_heap(pairs, width)) >= na * terms
    seen = []

    async def bench(ctx):
        for k, v in enumerate(vectors + [[(0, 0)] * terms] * 3):
            for i, (x, y) in enumerate(v):
                ctx.set(a[i], x)
                ctx.set(b[i], y)
            await ctx.tick()
            seen.append((ctx.get(got), ctx.get(want)))

    sim = Simulator(m)
    sim.add_clock(1e-8)
    sim.add_testbench(bench)
    sim.run()
    assert all(g == w for g, w in seen)
    sums = [g for g, _ in seen[2:2 + len(vectors)]]
    assert sums == [sum(-x * y if i in minus else x * y for i, (x, y) in enumerate(v)) for v in vectors]


@pytest.mark.parametrize("bits,rows,cols,fmt,seed", [(16, 1, 1, None, 3511), (12, 2, 2, None, 3512),
                                                     (8, 2, 3, FilterFormat(3, 3), 3513)])
def test_rtl_with_carry_chain_cells_equals_model(bits, rows, cols, fmt, seed):
    """The lean array with its cells' products as CCU2C bit heaps (CarryChainModel, what
    ``--fabric-units cell`` builds on ECP5) against the model, zero tolerance: every step's cycle
    and the bits at every marker (1 x 1: hard cases and random tests; else random blocks)."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    if rows * cols == 1:
        hard = hard_cases(bits)
        tests = hard[rng.permutation(len(hard))[:120]] + random_tests(bits, 60, rng)
        steps, V, n = _single_tests(tests), tests.V, tests.n
    else:
        steps, V, n = _steps(rng, _scene_blocks(rng, bits, rows, cols, 8, 8), rows, cols)
    trace = _compare(bits, rows, cols, fmt, None, steps, V, n,
                     run=lambda *a: _run_rtl(*a, platform=CarryChainModel()))
    assert trace.undecided.sum() > 0
    print("undecided", int(trace.undecided.sum()), "cycles", trace.cycles, "steps", len(steps))


@pytest.mark.parametrize("bits,rows,cols,fmt,depth,seed", [(8, 2, 2, FilterFormat(3, 3), None, 3301),
                                                           (8, 2, 2, FilterFormat(3, 3, 4), None, 3304),
                                                           (8, 2, 3, FilterFormat(3, 3), 6, 3302),
                                                           (12, 2, 2, None, None, 3303)])
def test_rtl_equals_model_on_blocks(bits, rows, cols, fmt, depth, seed):
    """R x S lean arrays on random blocks with gaps, partial blocks and markers: cycles and the
    accumulators' bits at every marker equal the model's (and the small depth loses cycles to
    the credits)."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    blocks = _scene_blocks(rng, bits, rows, cols, 8, 8)
    steps, V, n = _steps(rng, blocks, rows, cols)
    trace = _compare(bits, rows, cols, fmt, depth, steps, V, n)
    print("undecided", int(trace.undecided.sum()), "cycles", trace.cycles, "steps", len(steps))


def test_parameters_are_checked():
    with pytest.raises(ParameterError, match="address_bits"):
        LeanArray(8, 2, 2, address_bits=0)
    with pytest.raises(ValueError, match="depth"):
        LeanArray(8, 2, 2, depth=2)


def test_model_board_lean_equals_exact(rtl_room):
    """The model board with the lean cell (``--cell lean --board model``) and behind the byte
    link: radiosity and tests equal the exact cell's; at 3 x 3 bits (w_k from 5-bit inputs, so
    B = 10 rounds them) the broadcast stalls for the shared exact unit, and the model behind the
    link (``BoardModel``: blockray.filtered) counts the same per-board cycles as the model board
    (``ModelBoard``: the compiled kernel)."""
    def run(board, **cell):
        return render(rtl_room, backend=board, params=PARAMS, bits=BITS, samples=4, max_shots=2, voxels=3, **cell)

    exact = run("model")
    lean = run("model", cell=Cell("lean", FilterFormat(3, 3, 5)))
    assert np.array_equal(lean.radiosity, exact.radiosity)
    for key in ("tests_issued", "tests_useful", "blocks", "rays"):
        assert lean.report[key] == exact.report[key], key
    assert (np.array(lean.report["board_cycles_per_board"]) > np.array(exact.report["board_cycles_per_board"])).all()
    link = run("model-link", cell=Cell("lean", FilterFormat(3, 3, 5)))
    assert np.array_equal(link.radiosity, lean.radiosity)
    for key in ("board_cycles_per_board", "tests_issued_per_board"):
        assert link.report[key] == lean.report[key], key
    print("board_cycles exact", exact.report["board_cycles"], "lean 3x3", lean.report["board_cycles"])


def test_lean_board_latencies_and_its_verilog():
    """The lean board's credits and latencies are the model's; ``blockray synth board --cell lean``
    builds it, its patch memory with the exact unit's read port."""
    from blockray.synth.verilog import unit_verilog
    from blockray.timing import BoardTiming
    params = BoardParams(rows=2, cols=2, bits=8, patch_depth=4, voxel_depth=2)
    board = BoardTop(params, cell=Cell("lean"))
    Fragment.get(board, None)
    assert board.cell == Cell("lean", FilterFormat(9, 9))
    assert board.timing == BoardTiming.for_cell(Cell("lean"))
    assert board.array_depth == default_lean_depth() == LeanArray.default_depth(board.memory_latency)
    text = unit_verilog("board", params, cell=Cell("lean"))
    assert "module blockray_board" in text and "exact_patch" in text


@pytest.mark.slow           # a Verilator build of minutes
@pytest.mark.cocotb
def test_verilator_equals_model_on_blocks(tmp_path):
    """The Verilog 2 x 2 lean array under cocotb + Verilator, B = 12, 3 x 3 bits (many tests to
    the exact unit), random blocks with gaps, partial masks and markers: the cycle every step is
    presented, every marker's cycle and ``hit`` equal the model's."""
    seed = 3401
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    bits, rows, cols = 12, 2, 2
    steps, V, n = _steps(rng, _scene_blocks(rng, bits, rows, cols, 40, 10), rows, cols)
    trace = _compare(bits, rows, cols, FilterFormat(3, 3), None, steps, V, n,
                     run=lambda *a: _run_verilator(*a, tmp_path))
    assert trace.undecided.sum() > 50
    print("undecided", int(trace.undecided.sum()), "cycles", trace.cycles, "steps", len(steps))


@pytest.mark.slow           # a Verilator build of about 10 CPU minutes (16.5 min wall at load 7)
@pytest.mark.cocotb
def test_verilator_ecp5_carry_chain_cells_equal_model(tmp_path):
    """The ECP5 netlist of a 1 x 2 lean array with ``--fabric-units cell`` (its cells' products
    CCU2C bit heaps, the units' MULT18X18D instances) under cocotb + Verilator, with the
    behavioural models synth/ecp5_ccu2c_sim.v and synth/ecp5_mult18x18d_sim.v: every step's cycle,
    every marker's cycle and ``hit`` equal the model's (B = 12, the default 9 x 9 filter)."""
    from amaranth.back import verilog
    from cocotb_tools.runner import get_runner

    from blockray.sim.cocotb_support import DEFAULT_BUILD_ARGS, VerilatorBuild, cached_build, verilator_env
    from blockray.synth.target import CCU2C_SIM, MULT18X18D_SIM, ECP5Target

    seed, bits, rows, cols = 3514, 12, 1, 2
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    steps, V, n = _steps(rng, _scene_blocks(rng, bits, rows, cols, 24, 8), rows, cols)

    def run(bits, rows, cols, fmt, depth, steps, V, n):
        words = pack_array(patch_layout(bits), patch_columns(V, n))
        name = "lean_bench_ecp5_cells"
        text = verilog.convert(LeanBench(bits, rows, cols, fmt, depth, words), name=name, emit_src=False,
                               platform=ECP5Target({"cell"}))
        verilator_env()
        files = {f"{name}.v": text, MULT18X18D_SIM.name: MULT18X18D_SIM.read_text(), CCU2C_SIM.name: CCU2C_SIM.read_text()}

        def build(staging, sources):
            get_runner("verilator").build(sources=sources, hdl_toplevel=name, build_dir=staging,
                                          build_args=list(DEFAULT_BUILD_ARGS), waves=False, always=True)

        build_dir, seconds, cached = cached_build(name=name, toplevel=name, files=files,
                                                  build_args=DEFAULT_BUILD_ARGS, build=build)
        print(f"verilator build: {'cached' if cached else f'{seconds:.1f} s'}; CCU2C cells {text.count('CCU2C #(')}")
        assert text.count("CCU2C #(") > 100
        build = VerilatorBuild(name, build_dir, build_dir / f"{name}.v", seconds, cached)
        return _run_bench(build, (steps, words, bits, rows, cols, depth), tmp_path)

    trace = _compare(bits, rows, cols, None, None, steps, V, n, run=run)
    print("undecided", int(trace.undecided.sum()), "cycles", trace.cycles, "steps", len(steps))


@pytest.mark.synth
def test_yosys_keeps_each_cells_operand_registers(tmp_path):
    """The cells of a row take the same broadcast operands, so Yosys would merge their bit heaps'
    operand registers into one set far from most of them (the routed lean 2 x 8's critical path
    was 9.3 ns of routing from one cell's register into another's heap). With ``OWN_REGISTERS``
    before ``synth_ecp5`` both cells of a 1 x 2 lean array keep as many as each other; without it
    (the control) the row's operand registers are in one cell only."""
    import re
    import subprocess

    from blockray import hdl
    from blockray.synth.target import ECP5Target
    from blockray.synth.yosys import OWN_REGISTERS, yosys_command

    (tmp_path / "a.v").write_text(hdl.convert(LeanArray(16, 1, 2), name="a", emit_src=False,
                                              platform=ECP5Target({"cell"})))

    def operand_ffs(prefix):
        subprocess.run(yosys_command() + ["-q", "-p", f"read_verilog a.v; {prefix}synth_ecp5 -top a; "
                                          "write_json a.json"], cwd=tmp_path, check=True, capture_output=True)
        top = next(m for m in json.loads((tmp_path / "a.json").read_text())["modules"].values()
                   if m.get("attributes", {}).get("top"))
        count = {}
        for name, cell in top["cells"].items():
            found = re.match(r"cell_0_(\d)\.s\d_\d_[ab]\d", name)
            if cell["type"] == "TRELLIS_FF" and found:
                count[found.group(1)] = count.get(found.group(1), 0) + 1
        return count

    merged, own = operand_ffs(""), operand_ffs(OWN_REGISTERS.format(top="a") + "; ")
    print("operand flip-flops per cell, merged:", merged, "own:", own)
    assert merged.get("0", 0) != merged.get("1", 0) and sum(merged.values()) < sum(own.values())  # control
    assert own["0"] == own["1"] > 0
