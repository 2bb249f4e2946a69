"""The R x S broadcast array in the Amaranth simulator against blockray.exact.blocked_block."""

import numpy as np
import pytest
from amaranth.sim import Simulator

from blockray.errors import ParameterError
from blockray.exact import blocked_block, patch_normals
from blockray.records import pack_array, patch_columns, patch_layout, pack, point_layout
from blockray.rtl.array import ProcessorArray
from blockray.rtl.processor import ArrayTiming

from board_scenes import crossing_patches, random_points


def _word(bits_rs):
    """(R, S) bool -> int, bit r*S + s."""
    return int(sum(1 << int(i) for i in np.flatnonzero(np.asarray(bits_rs).ravel())))


def _point(bits, p):
    return pack(point_layout(bits), dict(zip("xyz", map(int, p))))


@pytest.mark.parametrize("bits,rows,cols,seed", [(8, 2, 3, 11), (12, 3, 2, 12)])
def test_array_matches_exact_blocks(bits, rows, cols, seed):
    """Blocks of records with random bubbles, back to back (``first``), points changed right
    after a block's last record: ``hit`` equals the OR of blocked_block over each block."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    dut = ProcessorArray(bits, rows, cols)
    assert dut.latency == ArrayTiming(bits).latency
    layout = patch_layout(bits)
    blocks = []
    for _ in range(5):
        P, Q = random_points(rng, bits, cols), random_points(rng, bits, rows)
        V = crossing_patches(rng, bits, P, Q, int(rng.integers(1, 12)))
        n = patch_normals(V)
        expect = blocked_block(P, Q, V, n).any(axis=2)
        blocks.append((P, Q, pack_array(layout, patch_columns(V, n)), _word(expect)))
    print("expected words", [hex(b[3]) for b in blocks])

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    got = []

    async def drive(ctx):
        for P, Q, words, _ in blocks:
            for s in range(cols):
                ctx.set(dut.shooters[s].as_value(), _point(bits, P[s]))
            for r in range(rows):
                ctx.set(dut.receivers[r].as_value(), _point(bits, Q[r]))
            for i, w in enumerate(words):
                while rng.random() < 0.3:                      # a bubble: nothing presented
                    ctx.set(dut.valid, 0)
                    ctx.set(dut.patch.as_value(), int(rng.integers(0, 1 << 30)))
                    await ctx.tick()
                ctx.set(dut.patch.as_value(), w)
                ctx.set(dut.valid, 1)
                ctx.set(dut.first, int(i == 0))
                await ctx.tick()
            ctx.set(dut.valid, 0)
            ctx.set(dut.first, 0)
        # scramble the points: records in flight must keep the points they were presented with
        for s in range(cols):
            ctx.set(dut.shooters[s].as_value(), 0)
        await ctx.tick().repeat(dut.latency + 2)

    async def monitor(ctx):
        # the accumulators after each block's last record arrives (the cycle before the next
        # block's first record arrives, or the end)
        seen = 0
        while True:
            await ctx.tick()
            if ctx.get(dut.hit_valid):
                seen += 1
            # track arrivals of each block's last record by counting arrivals
            if seen and seen == sum(len(b[2]) for b in blocks[:len(got) + 1]):
                got.append(ctx.get(dut.hit))
                if len(got) == len(blocks):
                    return

    sim.add_testbench(drive)
    sim.add_testbench(monitor)
    sim.run()
    assert [hex(g) for g in got] == [hex(b[3]) for b in blocks]


def test_array_parameters_validated():
    with pytest.raises(ParameterError, match="rows"):
        ProcessorArray(8, 0, 2)
    with pytest.raises(ParameterError, match="cols"):
        ProcessorArray(8, 2, 65)
    with pytest.raises(ParameterError, match="bits"):
        ProcessorArray(3, 2, 2)
