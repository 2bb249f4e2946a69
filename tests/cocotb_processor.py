"""cocotb test of the Verilog Intersector (run by tests/test_processor_cocotb.py, not by pytest).

Settings arrive in the environment: BLOCKRAY_BITS, BLOCKRAY_SEED, BLOCKRAY_VECTORS (random tests,
on top of every hard case), BLOCKRAY_BUBBLE / BLOCKRAY_STALL (probability of an input gap /
of ``o.ready`` low per cycle), BLOCKRAY_FLIP (index of one expectation to invert: proves a
mismatch fails the run), BLOCKRAY_STATS (JSON file for the measured rate). Vectors and
expectations (blockray.exact.blocked_block, in bulk) are generated here from the seed.

One coroutine drives both streams: on the falling edge it sets ``i`` and ``o.ready``, in the
read-only phase it reads ``i.ready`` and ``o.valid`` to learn which transfers the next rising
edge makes. The payload is written only when a new test is offered and read only on a transfer.
"""

import json
import os
import time

import cocotb
import numpy as np
from cocotb.clock import Clock
from cocotb.triggers import ClockCycles, FallingEdge, ReadOnly

from blockray.records import unpack_array
from blockray.rtl.processor import TAG_BITS, result_layout

from processor_vectors import hard_cases, random_tests


@cocotb.test()
async def intersector_vectors(dut):
    bits = int(os.environ.get("BLOCKRAY_BITS", "16"))
    seed = int(os.environ.get("BLOCKRAY_SEED", "1"))
    count = int(os.environ.get("BLOCKRAY_VECTORS", "100000"))
    bubble = float(os.environ.get("BLOCKRAY_BUBBLE", "0.1"))
    stall = float(os.environ.get("BLOCKRAY_STALL", "0.1"))
    print(f"seed={seed} bits={bits} random vectors={count} bubble={bubble} stall={stall}")
    rng = np.random.default_rng(seed)
    tests = hard_cases(bits) + random_tests(bits, count, rng)
    expected = tests.blocked.copy()
    if "BLOCKRAY_FLIP" in os.environ:
        expected[int(os.environ["BLOCKRAY_FLIP"])] ^= True
    words = tests.words(bits)
    n = len(words)
    gaps = (rng.random(n * 2 + 1) < bubble).tolist()
    stalls = (rng.random(n * 4 + 64) < stall).tolist()

    Clock(dut.clk, 10, unit="ns").start()
    dut.rst.value = 1
    dut.i__valid.value = 0
    dut.o__ready.value = 0
    await ClockCycles(dut.clk, 2)
    dut.rst.value = 0

    got = []
    sent = 0
    offered = False
    cycle = g = 0
    limit = 4 * n + 1000
    start = time.perf_counter()
    i_valid, i_payload, i_ready = dut.i__valid, dut.i__payload, dut.i__ready
    o_valid, o_payload, o_ready = dut.o__valid, dut.o__payload, dut.o__ready
    while len(got) < n:
        await FallingEdge(dut.clk)
        if not offered and sent < n:
            if gaps[g]:
                i_valid.value = 0
            else:
                i_payload.value = words[sent]
                i_valid.value = 1
                offered = True
            g += 1
        elif not offered:
            i_valid.value = 0
        ready = not stalls[cycle % len(stalls)]
        o_ready.value = ready
        await ReadOnly()
        if offered and i_ready.value:
            sent += 1
            offered = False
        if ready and o_valid.value:
            got.append(int(o_payload.value))
        cycle += 1
        assert cycle < limit, f"no progress: {len(got)} of {n} results after {cycle} cycles"
    seconds = time.perf_counter() - start

    result = unpack_array(result_layout(), got)
    assert (result[("tag",)] == np.arange(n) % (1 << TAG_BITS)).all(), "results lost or out of order"
    blocked = result[("blocked",)].astype(bool)
    bad = np.flatnonzero(blocked != expected)
    for i in bad[:5]:
        print(f"mismatch at {i}: P={tests.P[i].tolist()} Q={tests.Q[i].tolist()} "
              f"V={tests.V[i].tolist()} rtl={blocked[i]} expected={expected[i]}")
    stats = {"bits": bits, "seed": seed, "vectors": n, "hard": n - count, "blocked": int(expected.sum()),
             "cycles": cycle, "seconds": seconds, "vectors_per_second": n / seconds,
             "cycles_per_second": cycle / seconds, "mismatches": len(bad)}
    print(json.dumps(stats))
    if os.environ.get("BLOCKRAY_STATS"):
        with open(os.environ["BLOCKRAY_STATS"], "w") as f:
            json.dump(stats, f)
    assert len(bad) == 0, f"{len(bad)} mismatches of {n} (seed={seed})"
