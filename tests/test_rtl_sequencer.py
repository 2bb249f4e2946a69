"""The block sequencer's gateware (rtl/sequencer.py BlockSequencer) against its bit-exact model
(sim/sequencer.py, whose records test_sequencer.py checks against the host's block commands):
from the same commands of rays made on the board, split into items, the same internal records,
bit for bit, each offered in the sequencer cycle the model gives it (docs/board-protocol.md,
"The sequencer's cycles"), and the same cycles in all. Small random scenes (vertices multiples
of D, voxel counts 0 or not, grids that clip the rays), D changed mid-stream and a second grid,
2-bit stamps so the visited stamps are cleared every third block; with random idle on the items
and back-pressure on the records, and without; seeded."""

import random

import numpy as np
import pytest
from amaranth.hdl import Elaboratable, Module, unsigned
from amaranth.lib import wiring
from amaranth.lib.memory import Memory

from blockray.board_rays import Column, LoadGrid, LoadSamples, RayProtocol, Receivers, RECEIVERS_PER_COMMAND
from blockray.errors import ParameterError
from blockray.exact import patch_normals
from blockray.params import BoardParams
from blockray.protocol import BoardProtocol, ReadCounters, WritePatch, WriteVoxel
from blockray.rtl.core import BoardCore
from blockray.records import pack, patch_layout
from blockray.rtl.sequencer import BlockSequencer, command_items
from blockray.sim import sequencer
from stream_bench import drive_streams

STAMP_BITS = 2


class _Board(Elaboratable):
    """The sequencer with the patch memory and the voxel table it reads."""

    def __init__(self, params, vertices, count):
        self.params, self.vertices, self.count = params, vertices, count
        self.seq = BlockSequencer(params, stamp_bits=STAMP_BITS)

    def elaborate(self, platform):
        m = Module()
        p, layout = self.params, patch_layout(self.params.bits)
        m.submodules.seq = self.seq
        m.submodules.patches = patches = Memory(shape=unsigned(layout.size), depth=p.patch_depth,
                                                init=_words(p, self.vertices))
        m.submodules.table = table = Memory(shape=BoardProtocol(p).table_entry_layout, depth=p.voxel_depth,
                                            init=[{"start": 0, "count": int(c)} for c in self.count])
        wiring.connect(m, self.seq.patch_read, patches.read_port())
        wiring.connect(m, self.seq.table_read, table.read_port())
        return m


def _words(params, vertices):
    """The packed patch records of ``vertices``, with their normals."""
    layout, normals = patch_layout(params.bits), patch_normals(vertices)
    return [pack(layout, {**{f"v{j}": dict(zip("xyz", map(int, v[j]))) for j in range(3)},
                          "normal": dict(zip("xyz", map(int, n)))}) for v, n in zip(vertices, normals)]


def _triple(rng, D):
    a = rng.randint(0, D)
    b = rng.randint(0, D - a)
    return (a, b, D - a - b)


def _case(rng, params, columns, max_v):
    """(vertices, voxel counts, commands): two sample schemes, two grids of 2 to ``max_v`` voxels
    an axis, ``columns`` columns each."""
    B, R = params.bits, params.rows
    grid_v = [rng.randint(2, max_v) for _ in range(2)]
    patches = rng.randint(4, params.patch_depth)
    commands = []
    for half in range(2):
        D = rng.choice((3, 6, 12, 21, 24, 42))
        commands.append(LoadSamples(tuple(_triple(rng, D) for _ in range(rng.randint(1, 7)))))
        v = grid_v[half]
        shift = B + 1 - v.bit_length() - rng.randint(0, 1)             # the scene's box or about half of it
        commands.append(LoadGrid(tuple(rng.randrange(1 << (B - 3)) for _ in range(3)), shift, v))
        for _ in range(columns):
            commands.append(Column(rng.randrange(patches)))
            weighted, slots = rng.random() < 0.4, []
            for _ in range(rng.randint(1, 3)):
                run = rng.randint(1, R)
                slots += [(rng.randrange(patches), k == run - 1, _triple(rng, D) if weighted else None)
                          for k in range(run)]
            commands += [Receivers(tuple(slots[i:i + RECEIVERS_PER_COMMAND]))
                         for i in range(0, len(slots), RECEIVERS_PER_COMMAND)]
    vertices = np.array([[[rng.randrange((1 << B) // 42) * 42 for _ in range(3)] for _ in range(3)]
                         for _ in range(patches)])                       # multiples of every D above
    count = [rng.choice((0, 0, 1, 3)) for _ in range(params.voxel_depth)]
    return vertices, count, commands


def _model(params, vertices, count, commands):
    """The model's records (packed) with their cycles, and its cycles in all."""
    seq, proto = sequencer.BlockSequencer(params, stamp_bits=STAMP_BITS), BoardProtocol(params)
    memory = type("Memory", (), {"vertices": vertices, "count": np.array(count)})()
    timed = [(c, proto.record(r)) for cmd in commands for c, r in seq.feed_timed(cmd, memory)]
    return timed, seq.cycle


def _run(params, vertices, count, commands, rng, offer, accept):
    """The gateware's records (packed) with the sequencer cycle each is offered in, and its cycles."""
    board = _Board(params, vertices, count)
    seq, rays = board.seq, RayProtocol(params)
    items = [item for cmd in commands for item in command_items(rays, cmd)]
    s = {"counted": 0, "taken": 0, "waiting": None, "done": False, "got": []}

    def step(ctx, cycle, item):
        assert cycle < 10 ** 6, "the sequencer stopped"
        if item is None and s["taken"] == len(items) and ctx.get(seq.commands.ready):
            s["done"] = True                                            # back in Idle with nothing left
            return
        s["taken"] += item is not None
        valid, ready = ctx.get(seq.records.valid), ctx.get(seq.records.ready)
        if valid:
            bits = ctx.get(seq.records.payload.as_value())
            if s["waiting"] is None:
                s["got"].append((s["counted"], bits))
            else:
                assert bits == s["waiting"], f"cycle {cycle}: a record changed while it waited"
            s["waiting"] = None if ready else bits
        idle = ctx.get(seq.commands.ready) and item is None
        s["counted"] += not idle and not (valid and not ready)

    drive_streams(board, seq.commands, seq.records, items, rng, step, payload=lambda item: item,
                  until=lambda: s["done"], offer=offer, accept=accept)
    return s["got"], s["counted"]


def _check(rng_seed, params, columns, max_v, offer, accept):
    rng = random.Random(rng_seed)
    vertices, count, commands = _case(rng, params, columns, max_v)
    want, cycles = _model(params, vertices, count, commands)
    got, counted = _run(params, vertices, count, commands, rng, offer, accept)
    assert len(got) == len(want) and counted == cycles
    for n, ((c, bits), (wc, wbits)) in enumerate(zip(got, want)):
        assert bits == wbits, f"record {n}: {bits:#x}, the model's {wbits:#x}"
        assert c == wc, f"record {n} offered in sequencer cycle {c}, the model's {wc}"


@pytest.mark.parametrize("offer, accept", [(1.0, 1.0), (0.6, 0.5)], ids=["no-idle", "idle-backpressure"])
def test_records_and_cycles_equal_the_model(rng_seed, offer, accept):
    """The 2 x 3 board at B = 10, grids up to 5^3, 6 columns a grid (a few seconds)."""
    params = BoardParams(rows=2, cols=3, boards=1, bits=10, patch_depth=32, voxel_depth=125)
    _check(rng_seed, params, 6, 5, offer, accept)


@pytest.mark.slow
def test_records_and_cycles_equal_the_model_long(rng_seed):
    """The 4 x 4 board at B = 14, grids up to 8^3, 40 columns a grid."""
    params = BoardParams(rows=4, cols=4, boards=1, bits=14, patch_depth=64, voxel_depth=512)
    _check(rng_seed, params, 40, 8, 0.7, 0.6)


def test_board_core_equals_the_model_link(rng_seed):
    """BoardCore with the sequencer behind its deframer: the byte stream of --board model-link
    (memory writes, the ray commands, a shooter's record rewritten just before its COLUMN,
    READ_COUNTERS) gives the model's results exactly: the blocked words and the counters (board
    cycles included); random idle and back-pressure."""
    from blockray.host_driver.board.simulated import ModelTransport
    rng = random.Random(rng_seed)
    params = BoardParams(rows=2, cols=3, boards=1, bits=10, patch_depth=32, voxel_depth=125)
    vertices, count, commands = _case(rng, params, 3, 5)
    writes = [WritePatch(a, w) for a, w in enumerate(_words(params, vertices))]
    writes += [WriteVoxel(i, rng.randrange(len(vertices) - c + 1), c) for i, c in enumerate(count)]
    fresh = _case(rng, params, 0, 2)[0]                 # the shooter's record rewritten just before
    commands = [x for c in commands for x in ([WritePatch(c.address, _words(params, fresh[:1])[0])]
                                              if isinstance(c, Column) else []) + [c]]
    wire = RayProtocol(params).encode_all(writes + commands + [ReadCounters()])
    want = ModelTransport(params).run(wire)
    core, got = BoardCore(params, rays=True), []

    def step(ctx, cycle, _):
        assert cycle < 200 * len(wire), "the board stopped"
        if ctx.get(core.o_bytes.valid) and ctx.get(core.o_bytes.ready):
            got.append(ctx.get(core.o_bytes.payload))

    drive_streams(core, core.i_bytes, core.o_bytes, list(wire), rng, step, payload=lambda b: b,
                  until=lambda: len(got) == len(want))
    assert _results(params, bytes(got)) == _results(params, want)


def _results(params, wire):
    """The results of a result byte stream, the counters without ``stalls`` (the model has no
    host timing)."""
    proto, out = BoardProtocol(params), []
    while wire:
        n = proto.result_length(wire[0])
        r = proto.decode_result(wire[:n])
        out.append((r.kind, r.blocked, None if r.counters is None else
                    {k: v for k, v in r.counters.items() if k != "stalls"}))
        wire = wire[n:]
    return out


@pytest.mark.parametrize("kw", [{"params": "8x8"}, {"params": BoardParams(bits=None)}, {"stamp_bits": 1},
                                {"stamp_bits": True}, {"stamp_bits": 2.0}])
def test_bad_parameters_are_one_error(kw):
    with pytest.raises(ParameterError):
        BlockSequencer(**({"params": BoardParams()} | kw))
