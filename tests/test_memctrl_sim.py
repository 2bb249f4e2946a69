"""The voxel-to-patch memory controller in the Amaranth simulator.

Checked per cycle: records leave in voxel order, each voxel occupies the issue slot for exactly
max(1, count) cycles, there is no gap between voxels offered in time, a gap appears only when the
producer had nothing to offer, and records arrive ``latency`` cycles after their issue.
"""

import numpy as np
import pytest
from amaranth.sim import Simulator

from blockray.errors import ParameterError
from blockray.params import BoardParams
from blockray.records import patch_layout
from blockray.rtl.memctrl import MemoryController


def _table(counts):
    counts = np.asarray(counts)
    starts = np.cumsum(counts) - counts
    return [{"start": int(s) if c else 0, "count": int(c)} for s, c in zip(starts, counts)]


def _run(dut, voxels, idle, *, writes=()):
    """Drive ``writes`` (("patch", (address, word)) | ("table", entry), one per cycle; the first
    voxel is offered in the cycle of the last write) then the voxel numbers, with ``idle[i]``
    empty cycles before voxel i. Returns the per-cycle trace."""
    sim = Simulator(dut)
    sim.add_clock(1e-8)
    trace = []
    done = []

    async def producer(ctx):
        port = None
        for i, (kind, payload) in enumerate(writes):
            if kind == "patch":
                port = dut.patch_write
                ctx.set(port.payload.address, payload[0])
                ctx.set(port.payload.patch.as_value(), payload[1])
            else:
                port = dut.table_write
                ctx.set(port.payload, payload)
            ctx.set(port.valid, 1)
            if i == len(writes) - 1:
                break                           # written in the first voxel's accept cycle
            await ctx.tick()
            ctx.set(port.valid, 0)
        for v, gap in zip(voxels, idle):
            if gap:
                await ctx.tick().repeat(gap)
            ctx.set(dut.voxels.payload, v)
            ctx.set(dut.voxels.valid, 1)
            await ctx.tick().until(dut.voxels.ready)
            ctx.set(dut.voxels.valid, 0)
            if port is not None:
                ctx.set(port.valid, 0)
                port = None
        await ctx.tick().repeat(dut.params.patch_depth + dut.latency + 2)   # the last voxel drains
        done.append(True)

    async def monitor(ctx):
        while not done:
            _, _, valid, ready, step, issue, rvalid, record = await ctx.tick().sample(
                dut.voxels.valid, dut.voxels.ready, dut.step, dut.issue,
                dut.records.valid, dut.records.payload.as_value())
            trace.append(dict(offered=valid, accept=valid and ready, step=step, issue=issue,
                              rvalid=rvalid, record=record))

    sim.add_testbench(producer)
    sim.add_testbench(monitor, background=True)
    sim.run()
    return trace


def _check(trace, voxels, counts, words, latency):
    expect = [words[a] for v in voxels for a in range(_table(counts)[v]["start"],
                                                       _table(counts)[v]["start"] + counts[v])]
    got = [t["record"] for t in trace if t["rvalid"]]
    assert got == expect, "records out of order, lost or duplicated"
    # each record arrives `latency` cycles after its issue
    issued = [i for i, t in enumerate(trace) if t["issue"]]
    arrived = [i for i, t in enumerate(trace) if t["rvalid"]]
    assert arrived == [i + latency for i in issued]
    # the slot: after each accept, exactly max(1, count) step cycles follow, starting next cycle
    accepts = [i for i, t in enumerate(trace) if t["accept"]]
    assert len(accepts) == len(voxels)
    steps = [i for i, t in enumerate(trace) if t["step"]]
    expect_steps = []
    for i, v in zip(accepts, voxels):
        expect_steps += range(i + 1, i + 1 + max(1, counts[v]))
    assert steps == expect_steps, "a voxel did not take exactly max(1, count) consecutive cycles"
    # issue = a step of a non-empty voxel
    assert len(issued) == sum(counts[v] for v in voxels)
    # no avoidable gap: a cycle without a step follows a cycle in which nothing was offered
    for i in range(accepts[0] + 1, steps[-1]):
        if not trace[i]["step"]:
            assert not trace[i - 1]["offered"], f"bubble in cycle {i} although a voxel was offered"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_memctrl_streams_voxels(seed):
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    params = BoardParams(rows=1, cols=1, bits=6, patch_depth=40, voxel_depth=9)
    counts = rng.integers(0, 6, params.voxel_depth)
    counts[[0, 3]] = 0                                  # empty voxels
    counts[5] = 1
    counts = counts.tolist()
    assert sum(counts) <= params.patch_depth
    size = patch_layout(params.bits).size
    words = [int(rng.integers(0, 1 << 62)) << (size - 62) | int(rng.integers(0, 1 << 62))
             for _ in range(params.patch_depth)]
    words = [w & ((1 << size) - 1) for w in words]
    assert MemoryController.latency == 2
    voxels = [int(v) for v in rng.integers(0, params.voxel_depth, 40)] + [0, 0, 3, 5, 5, 0]
    # back to back first (no idle at all), then random idle
    for idle in ([0] * len(voxels), [int(g) if rng.random() < 0.4 else 0 for g in rng.integers(1, 4, len(voxels))]):
        dut = MemoryController(params, patch_init=words, table_init=_table(counts))
        trace = _run(dut, voxels, idle)
        _check(trace, voxels, counts, words, 2)
        if not any(idle):
            accepts = [i for i, t in enumerate(trace) if t["accept"]]
            steps = [i for i, t in enumerate(trace) if t["step"]]
            # no bubbles at all between back-to-back voxels
            assert steps == list(range(accepts[0] + 1, accepts[0] + 1 + sum(max(1, c) for c in (counts[v] for v in voxels))))


def test_memctrl_write_ports_and_transparent_table():
    """Memories loaded through the write ports; a voxel offered in the cycle its table entry is
    written reads the new entry (the table read is transparent)."""
    seed = 7
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    params = BoardParams(rows=1, cols=1, bits=5, patch_depth=12, voxel_depth=4)
    size = patch_layout(params.bits).size
    words = [int(rng.integers(0, 1 << min(size, 62))) for _ in range(params.patch_depth)]
    counts = [3, 0, 5, 4]
    table = _table(counts)
    writes = [("patch", (a, w)) for a, w in enumerate(words)]
    writes += [("table", {"voxel": v, "entry": e}) for v, e in enumerate(table)]
    dut = MemoryController(params, table_init=[{"start": 0, "count": 1}] * 4)
    # voxel 3 is offered in the cycle its table entry is written
    voxels = [3, 2, 0, 1, 3]
    trace = _run(dut, voxels, [0] * len(voxels), writes=writes)
    _check(trace, voxels, counts, words, 2)


def test_memctrl_parameters_validated():
    with pytest.raises(ParameterError, match="BoardParams"):
        MemoryController(16)
    with pytest.raises(ParameterError, match="patch_depth"):
        MemoryController(BoardParams(patch_depth=2, voxel_depth=2), patch_init=[0, 0, 0])
