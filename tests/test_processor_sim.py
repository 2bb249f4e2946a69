"""The intersection processor in the Amaranth simulator against blockray.exact (bit for bit).

Seeded; each test prints its seed. Vector counts are modest (pysim runs a few thousand cycles per
second); the 100 000-vector run is tests/test_processor_cocotb.py.
"""

import numpy as np
import pytest
from amaranth.hdl import Module, Signal
from amaranth.lib import data
from amaranth.sim import Simulator

from blockray.errors import ParameterError
from blockray.exact import block_terms, blocked_block, blocked_reference, patch_normals
from blockray.params import Widths
from blockray.records import pack, pack_array, patch_columns, point_columns, unpack
from blockray.rtl.processor import (
    ArrayTiming, Intersector, Processor, ReceiverUnit, ShooterUnit, _delay, _delay_memory, receiver_terms_layout,
    shooter_terms_layout, query_layout,
)

from processor_run import check_results, run_intersector
from processor_vectors import hard_cases, random_tests

SEED = 20240604

# components built only to check that their constructor rejects a parameter are never elaborated
pytestmark = pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")


# -- parameters ----------------------------------------------------------------------------

@pytest.mark.parametrize("cls", [ShooterUnit, ReceiverUnit, Processor, Intersector, ArrayTiming])
@pytest.mark.parametrize("bits", [3, 21, 0, -1])
def test_bits_out_of_range(cls, bits):
    with pytest.raises(ParameterError, match="bits"):
        cls(bits)


@pytest.mark.parametrize("cls", [ShooterUnit, Processor, Intersector])
@pytest.mark.parametrize("bits", [16.0, "16", True, None])
def test_bits_not_integer(cls, bits):
    with pytest.raises(ParameterError, match="bits must be an integer"):
        cls(bits)


def test_timing_balanced():
    t = ArrayTiming(16)
    assert ShooterUnit.latency == ReceiverUnit.latency == t.unit
    assert t.latency == t.unit + Processor.latency


# -- the units, term by term ---------------------------------------------------------------

@pytest.mark.parametrize("bits", [6, 16, 20])
def test_units_terms(bits):
    """ShooterUnit/ReceiverUnit outputs equal the numpy terms, with valid and latency checked;
    inputs change every cycle and valid has random gaps."""
    seed = SEED + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    L = (1 << bits) - 1
    count = 40
    pts = rng.integers(0, L + 1, (count, 3))
    pts[:4] = [[0, 0, 0], [L, L, L], [0, L, 0], [L, 0, L]]
    V = rng.integers(0, L + 1, (count, 3, 3))
    V[:4] = [[[L, L, L], [0, 0, 0], [L, 0, L]], [[0, 0, 0], [L, L, 0], [0, L, L]],
             [[L, 0, 0], [0, L, 0], [0, 0, L]], [[0, 0, 0], [0, 0, 0], [L, L, L]]]
    n = patch_normals(V)
    valid = rng.random(count) < 0.7
    # expected terms, straight from the definitions (independent of the gateware split)
    d = pts[:, None, :] - V                                            # (count, 3, 3)
    w = np.cross(d, np.roll(V, -1, axis=1) - V)
    plane = np.einsum("tc,tc->t", d[:, 0], n)
    Wd = Widths(bits)
    assert np.abs(w).max() < 1 << (Wd.cross - 1) and np.abs(plane).max() < 1 << (Wd.orient - 1)

    pcols = point_columns(pts)
    vcols = patch_columns(V, n)
    for cls, layout in ((ShooterUnit, shooter_terms_layout(bits)), (ReceiverUnit, receiver_terms_layout(bits))):
        dut = cls(bits)
        pwords = pack_array(dut.point.shape(), pcols)
        vwords = pack_array(dut.patch.shape(), vcols)
        seen = []

        async def tb(ctx):
            for t in range(count + dut.latency + 1):
                if t < count:
                    ctx.set(dut.point.as_value(), pwords[t])
                    ctx.set(dut.patch.as_value(), vwords[t])
                    ctx.set(dut.valid, int(valid[t]))
                else:
                    ctx.set(dut.valid, 0)
                await ctx.tick()
                if ctx.get(dut.terms_valid):
                    seen.append((t + 1, unpack(layout, ctx.get(dut.terms.as_value()))))

        sim = Simulator(dut)
        sim.add_clock(1e-8)
        sim.add_testbench(tb)
        sim.run()
        idx = np.flatnonzero(valid)
        assert [c for c, _ in seen] == list(idx + dut.latency)      # output in cycle t + latency
        for t, (_, terms) in zip(idx, seen):
            if cls is ShooterUnit:
                assert terms["pp"] == plane[t]
                assert [[v[a] for a in "xyz"] for v in terms["d"]] == d[t].tolist()
            else:
                assert [[v[a] for a in "xyz"] for v in terms["w"]] == w[t].tolist()
                assert terms["pq"] == np.einsum("c,c->", pts[t] - V[t, 0], n[t])


@pytest.mark.parametrize("bits", [6, 16])
def test_processor_hit_accumulates(bits):
    """Processor fed with terms of whole blocks back to back: per-test ``blocked`` equals
    blocked_block, and ``hit`` after each block's last test equals the OR over the block."""
    seed = SEED + 100 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    L = (1 << bits) - 1
    dut = Processor(bits)
    slay, rlay = shooter_terms_layout(bits), receiver_terms_layout(bits)
    stream = []                      # (shooter word, receiver word, first, expected, last)
    for b in range(12):
        N = int(rng.integers(1, 8))
        P = rng.integers(0, L + 1, (1, 3))
        Q = rng.integers(0, L + 1, (1, 3))
        V = rng.integers(0, L + 1, (N, 3, 3))
        if b % 3 == 1:                                  # make some blocks hit: patches between
            mid = (P + Q) // 2
            V = mid[:, None, :] + rng.integers(-L // 8, L // 8 + 1, (N, 3, 3))
            V = np.clip(V, 0, L)
        n = patch_normals(V)
        pP, pQ, _ = block_terms(P, Q, V, n)
        expected = blocked_block(P, Q, V, n)[0, 0]
        d = P[0][None, None, :] - V
        w = np.cross(Q[0][None, None, :] - V, np.roll(V, -1, axis=1) - V)
        for t in range(N):
            sw = pack(slay, {"d": [dict(zip("xyz", v)) for v in d[t]], "pp": pP[0, t]})
            rw = pack(rlay, {"w": [dict(zip("xyz", v)) for v in w[t]], "pq": pQ[0, t]})
            stream.append((sw, rw, t == 0, bool(expected[t]), t == N - 1, bool(expected.any())))
    assert any(s[5] for s in stream) and not all(s[5] for s in stream)
    got = []

    async def tb(ctx):
        for t in range(len(stream) + dut.latency):
            if t < len(stream):
                sw, rw, first, *_ = stream[t]
                ctx.set(dut.shooter.as_value(), sw)
                ctx.set(dut.receiver.as_value(), rw)
                ctx.set(dut.first, first)
                ctx.set(dut.valid, 1)
            else:
                ctx.set(dut.valid, 0)
            await ctx.tick()
            if ctx.get(dut.result_valid):
                got.append((ctx.get(dut.blocked), ctx.get(dut.hit)))

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(tb)
    sim.run()
    assert len(got) == len(stream)
    assert [bool(b) for b, _ in got] == [s[3] for s in stream]
    assert [bool(h) for (_, h), s in zip(got, stream) if s[4]] == [s[5] for s in stream if s[4]]


# -- the streamed 1 x 1 array ----------------------------------------------------------------

def test_latency_and_throughput():
    """One test alone appears exactly ``latency`` cycles later; back-to-back tests with the
    output always ready come out one per cycle (no bubbles from the credit loop)."""
    bits = 8
    tests = random_tests(bits, 64, np.random.default_rng(SEED))
    out, cycles, dut = run_intersector(bits, tests[:1], seed=SEED)
    assert dut.latency == dut.timing.latency + 2 == 10
    assert cycles == dut.latency + 1                   # sampled on the edge after it appears
    check_results(out, tests[:1])
    out, cycles, _ = run_intersector(bits, tests, seed=SEED)
    check_results(out, tests)
    assert cycles == len(tests) + dut.latency


@pytest.mark.parametrize("bits", [6, 12, 16])
def test_intersector_random(bits):
    """Random and crossing-heavy random tests with bubbles and backpressure."""
    seed = SEED + 1000 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    tests = random_tests(bits, 600, rng)
    assert 0.05 < tests.blocked.mean() < 0.5
    out, _, _ = run_intersector(bits, tests, seed=seed, bubble=0.3, stall=0.3)
    check_results(out, tests)


@pytest.mark.parametrize("bits", [6, 16])
def test_intersector_hard_cases(bits):
    """Every hard case (cube corners 0 and 2**B - 1, shared edges and vertices, rays in a plane,
    zero-area patches, grid coincidences): a seeded sample of 1500 for the sim, every one in
    the cocotb run."""
    seed = SEED + 2000 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    tests = hard_cases(bits)
    tests = tests[np.sort(rng.choice(len(tests), 1500, replace=False))]
    assert tests.blocked.any() and not tests.blocked.all()
    out, _, _ = run_intersector(bits, tests, seed=seed, bubble=0.2, stall=0.2)
    check_results(out, tests)


def test_vectors_agree_with_reference():
    """The expectations (blocked_block) agree with the independent orient3d evaluation on the
    hard cases and random tests used above, so a shared bug in the split cannot hide."""
    seed = SEED + 3000
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    for bits in (6, 16, 20):
        tests = hard_cases(bits)
        tests = tests[rng.choice(len(tests), 3000, replace=False)] + random_tests(bits, 1000, rng)
        ref = [blocked_reference(tests.P[i], tests.Q[i], *tests.V[i]) for i in range(len(tests))]
        assert (np.array(ref) == tests.blocked).all()


def test_test_layout_packing():
    """The packed words equal the layout's own const encoding (pack_array vs amaranth)."""
    bits = 12
    tests = random_tests(bits, 5, np.random.default_rng(SEED))
    layout = query_layout(bits)
    for i, word in enumerate(tests.words(bits)):
        value = {"shooter": dict(zip("xyz", tests.P[i].tolist())),
                 "receiver": dict(zip("xyz", tests.Q[i].tolist())),
                 "patch": {**{f"v{k}": dict(zip("xyz", tests.V[i, k].tolist())) for k in range(3)},
                           "normal": dict(zip("xyz", tests.n[i].tolist()))},
                 "tag": i}
        assert word == layout.const(value).as_bits()


def test_no_combinational_ready_valid_paths():
    """Stream rules: ``o.valid``/``o.payload`` do not depend on ``o.ready``, and ``i.ready`` does
    not depend on ``i.valid`` or ``o.ready`` within a cycle (checked while the pipeline fills,
    is full and drains)."""
    bits = 6
    seed = SEED + 4000
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    dut = Intersector(bits)
    words = random_tests(bits, 40, rng).words(bits)
    seen_full = []

    async def tb(ctx):
        for cycle in range(120):
            ctx.set(dut.i.payload.as_value(), words[cycle % len(words)])
            probes = []
            for i_valid, o_ready in ((0, 0), (1, 0), (0, 1), (1, 1)):
                ctx.set(dut.i.valid, i_valid)
                ctx.set(dut.o.ready, o_ready)
                probes.append((ctx.get(dut.i.ready), ctx.get(dut.o.valid), ctx.get(dut.o.payload.as_value())))
            assert len(set(probes)) == 1, f"cycle {cycle}: {probes}"
            seen_full.append(probes[0][0] == 0)
            ctx.set(dut.i.valid, int(cycle < 60))
            ctx.set(dut.o.ready, int(cycle >= 30 and rng.random() < 0.5))
            await ctx.tick()

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(tb)
    sim.run()
    assert any(seen_full) and not all(seen_full)       # the credit limit was reached and released


@pytest.mark.parametrize("cycles", [2, 3, 8])
def test_memory_delay_equals_register_chain(cycles):
    """``_delay_memory`` (the filtered arrays' wide delays) gives ``_delay``'s outputs on every
    cycle, from reset on, for random inputs, a struct of two fields among them."""
    seed = SEED + cycles
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    layout = data.StructLayout({"a": 13, "b": 7})
    m = Module()
    value = Signal(layout)
    chain, memory = _delay(m, value, cycles, "chain"), _delay_memory(m, value, cycles, "memory")
    sim = Simulator(m)
    sim.add_clock(1e-6)
    seen = []

    async def bench(ctx):
        for word in rng.integers(0, 1 << 20, size=5 * cycles + 7):
            ctx.set(value.as_value(), int(word))
            await ctx.tick()
            seen.append((ctx.get(chain.as_value()), ctx.get(memory.as_value())))

    sim.add_testbench(bench)
    sim.run()
    assert len(seen) == 5 * cycles + 7
    assert all(c == w for c, w in seen), seen
    assert any(c != 0 for c, _ in seen)


def test_memory_delay_needs_two_cycles():
    with pytest.raises(ValueError, match="at least 2 cycles"):
        _delay_memory(Module(), Signal(4), 1, "d")
