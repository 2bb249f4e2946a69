"""The whole board in the Amaranth simulator against the bit-exact model.

Blocked words and counters are compared with zero tolerance, under random host idle cycles,
random result back-pressure (with bursts of long stalls) and a reset in the middle of the batch
(the host replays; nothing is lost, duplicated or reordered), both for ``BoardTop`` fed command
records and for ``BoardCore``, the board behind its byte link (the wire format). Also: the
protocol's record packing and wire format, capacity errors and the timing contract's latencies
against the RTL's.
"""

import numpy as np
import pytest
from amaranth.hdl import ClockDomain, Module
from amaranth.sim import Simulator

from blockray.errors import CapacityError, ParameterError
from blockray.params import BoardParams
from blockray.protocol import (BeginBlock, BoardProtocol, BoardResult, EndBlock, Identify, LoadPoints, LoadReceiver,
                               LoadShooter, Op, ReadCounters, ResultKind, Voxel, WritePatch, WriteVoxel,
                               check_capacity, fit_params)
from blockray.rtl.board import BoardTop
from blockray.rtl.core import BoardCore
from blockray.sim.drive import HostTiming, amaranth_cycle
from blockray.sim.model import result_word
from blockray.timing import BoardTiming

from board_host import BatchRun, ReplayingHost, check_run, replay_after_reset
from board_scenes import crossing_patches, load_commands, make_batch, random_memory, random_points


def run_board(params, commands, *, seed, idle=HostTiming(), backpressure=HostTiming(), reset_at=None,
              link="records", encode=None):
    """Run the batch in the Amaranth simulator on BoardTop (``link="records"``) or BoardCore
    (``"bytes"``) through the shared drive loop; return (RunLog, clock cycles)."""
    dut = BoardTop(params) if link == "records" else BoardCore(params)
    i, o = (dut.commands, dut.results) if link == "records" else (dut.i_bytes, dut.o_bytes)
    top = Module()
    top.domains.sync = cd = ClockDomain()
    top.submodules.board = dut
    sim = Simulator(top)
    sim.add_clock(1e-8)
    run = BatchRun(params, commands, link=link, idle=idle, backpressure=backpressure, seed=seed,
                   reset_at=reset_at, max_cycles=400_000, encode=encode)

    async def testbench(ctx):
        while not run.done:
            if run.reset_due():
                ctx.set(i.valid, 0)
                ctx.set(o.ready, 0)
                ctx.set(cd.rst, 1)
                await ctx.tick()
                ctx.set(cd.rst, 0)
                run.after_reset()
                continue
            run.after_cycle(await amaranth_cycle(ctx, run.stream, i, o))

    sim.add_testbench(testbench)
    sim.run()
    return run.log, run.total


def test_latencies_match_timing_contract():
    from amaranth.hdl import Fragment
    for bits in (4, 8, 16, 20):
        board = BoardTop(BoardParams(rows=1, cols=1, bits=bits, patch_depth=4, voxel_depth=2))
        Fragment.get(board, None)          # elaborates (and asserts the submodules' latencies)
        contract = BoardTiming.for_cell()
        assert board.timing == contract
        assert board.drain_latency == contract.drain_latency
        assert board.memory_latency == contract.memory_latency
        assert board.processor_latency == contract.processor_latency
        assert contract.cost(Op.END_BLOCK) == 1 == contract.cost(Op.READ_COUNTERS) == contract.cost(Op.IDENTIFY)
        assert board.result_queue_depth == contract.result_latency + 1


@pytest.mark.parametrize("seed,rows,cols", [(101, 2, 2), (102, 2, 3)])
def test_board_back_to_back_exact_cycles(seed, rows, cols):
    """No idle, no back-pressure: results and counters equal the model, and the only stall is
    the first cycle (the command register is empty until the first command is taken)."""
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=rows, cols=cols, bits=8)
    log, _ = run_board(params, cmds, seed=seed)
    check_run(params, cmds, log)
    last = max(log.results)
    counters = BoardProtocol(params).decode_result(log.results[last]).counters
    assert counters["stalls"] == 1, counters
    # a result reaches the host result_latency cycles after its command's own cycle, which is the
    # cycle after the command was accepted
    latency = BoardTiming.for_cell().result_latency
    assert {log.received[i] - log.accepted[i] for i in log.results} == {latency + 1}


def test_core_back_to_back_counts_board_cycles_only():
    """BoardCore behind its byte link, host never idle: results and counters equal the model (the
    bytes cost stalls, not board cycles), every result in as many bytes as its tag says."""
    seed = 103
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=3, bits=8)
    log, _ = run_board(params, cmds, seed=seed, link="bytes")
    check_run(params, cmds, log)
    counters = BoardProtocol(params).decode_result(log.results[max(log.results)]).counters
    assert counters["stalls"] > counters["cycles"] // 4, counters     # the link, not the board, is the limit


def test_core_drops_unknown_headers_and_padding():
    """Bytes a host should not send: an unknown opcode's header is dropped, and the padding bits
    of a short LOAD_POINTS do not load the next slot; the results are the clean stream's."""
    seed = 104
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=2, bits=8)
    proto = BoardProtocol(params)
    slot = proto.point_slot_layout.size
    spare = 8 - slot % 8 if slot % 8 else 0
    assert spare, "the test needs a LOAD_POINTS slot that does not fill its last byte"

    def dirty(command):
        data = bytearray(proto.encode(command))
        if command.op is Op.LOAD_POINTS and len(command.slots) == 1:
            data[-1] |= ((1 << spare) - 1) << (8 - spare)     # would set slot 1's valid bit
        if command.op is Op.BEGIN_BLOCK:
            data = bytearray([0x0F]) + data                   # opcode 15 does not exist
        return bytes(data)

    assert any(c.op is Op.LOAD_POINTS and len(c.slots) == 1 for c in cmds)
    log, _ = run_board(params, cmds, seed=seed, link="bytes", encode=dirty)
    check_run(params, cmds, log)


@pytest.mark.parametrize("seed,link", [(201, "records"), (202, "bytes")])
def test_board_idle_and_backpressure(seed, link):
    """Random idle and back-pressure on both streams, with bursts of long stalls."""
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=2, bits=10)
    timing = dict(idle=HostTiming(0.3, burst=0.002, burst_length=(20, 300)),
                  backpressure=HostTiming(0.4, burst=0.002, burst_length=(20, 300)))
    log, _ = run_board(params, cmds, seed=seed, link=link, **timing)
    check_run(params, cmds, log)
    last = max(log.results)
    assert BoardProtocol(params).decode_result(log.results[last]).counters["stalls"] > 1


@pytest.mark.parametrize("seed,fraction,link", [(301, 0.5, "records"), (302, 0.8, "bytes")])
def test_board_reset_mid_batch(seed, fraction, link):
    """Reset in the middle of the batch; the host reloads and replays."""
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=2, bits=8)
    timing = dict(idle=HostTiming(0.2), backpressure=HostTiming(0.3))
    _, clean = run_board(params, cmds, seed=seed, link=link, **timing)
    log, _ = run_board(params, cmds, seed=seed, reset_at=int(clean * fraction), link=link, **timing)
    assert log.answered_at_reset, "the reset did not happen"
    print("results answered before the reset:", log.answered_at_reset)
    check_run(params, cmds, log)
    assert any(e == 1 for e in log.epoch.values())


# -- protocol ----------------------------------------------------------------------------------

def test_protocol_records_pack_like_amaranth():
    seed = 5
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    params = BoardParams(rows=3, cols=2, bits=6, patch_depth=20, voxel_depth=9)
    proto = BoardProtocol(params)
    assert (proto.address_width, proto.count_width, proto.voxel_width) == (5, 5, 4)
    P = random_points(rng, 6, 3)
    V = crossing_patches(rng, 6, P, P, 4)
    cmds = load_commands(6, V, np.arange(4), np.array([0, 2, 2]), np.array([2, 0, 2]))
    cmds += [BeginBlock(), LoadReceiver(2, (1, 2, 3)), LoadShooter(1, (63, 0, 5)), Voxel(8), EndBlock(),
             ReadCounters(), Identify(), LoadPoints(((True, 1, (1, 2, 3)), (False, 2, (4, 5, 6)))),
             LoadPoints(((False, 0, (1, 2, 3)),) * 4)]
    for c in cmds:
        value = {"op": c.op, "arg": {c.member: c.arg(proto)} if c.member else {}}
        word = proto.record(c)
        assert word == proto.command_layout.const(value).as_bits()
        back = proto.decode_record(word)
        assert back["op"] is c.op
        if c.member is not None:
            assert back["arg"][c.member] == value["arg"][c.member]
    # the wire format: header, then the member's bits only; the inverse gives the commands back
    wire = proto.encode_all(cmds)
    back = proto.decode_commands(wire)
    assert proto.encode_all(back) == wire
    # equal but for an empty voxel's start, which the encoding sets to 0 (never read)
    assert [c for c in back if c.op is not Op.WRITE_VOXEL] == [c for c in cmds if c.op is not Op.WRITE_VOXEL]
    assert [(c.voxel, c.count, c.start if c.count else 0) for c in cmds if c.op is Op.WRITE_VOXEL] == [
        (c.voxel, c.count, c.start) for c in back if c.op is Op.WRITE_VOXEL]
    assert len(proto.encode(Voxel(8))) == 1 + (proto.voxel_width + 7) // 8 == 2
    assert [len(proto.encode(c)) for c in (BeginBlock(), EndBlock(), ReadCounters(), Identify())] == [1] * 4
    slot = proto.point_slot_layout.size
    assert len(proto.encode(cmds[-2])) == 1 + (2 * slot + 7) // 8 < len(proto.encode(cmds[-1]))
    with pytest.raises(ParameterError, match="byte 0"):
        proto.decode_commands(bytes([0x0F]))
    with pytest.raises(ParameterError, match="stream ends"):
        proto.decode_commands(proto.encode(Voxel(8))[:1])
    for result in (BoardResult(ResultKind.BLOCKED, blocked=0b100101),
                   BoardResult(ResultKind.COUNTERS, counters=dict(cycles=7, busy=1, tests_issued=6,
                                                                  tests_useful=2, stalls=(1 << 48) - 1)),
                   BoardResult(ResultKind.IDENTITY, identity=proto.identity())):
        word = proto.encode_result(result)
        assert proto.decode_result(word) == result
        wire = proto.result_wire(result)
        assert len(wire) == proto.result_length(wire[0]) == proto.result_bytes(result.kind)
        assert proto.decode_result(wire) == result
    # R x S = 6 blocked bits and the 2-bit tag: one byte
    assert proto.result_bytes(ResultKind.BLOCKED) == 1


def test_protocol_capacity_errors():
    params = BoardParams(rows=2, cols=2, bits=6, patch_depth=8, voxel_depth=4)
    proto = BoardProtocol(params)
    with pytest.raises(CapacityError, match="patch_depth 8"):
        proto.encode(WritePatch(8, 0))
    with pytest.raises(CapacityError, match="voxel_depth 4"):
        proto.encode(Voxel(4))
    with pytest.raises(CapacityError, match="patch_depth 8"):
        proto.encode(WriteVoxel(1, 5, 4))
    with pytest.raises(CapacityError, match="receiver row 2 .*rows 2"):
        proto.encode(LoadReceiver(2, (0, 0, 0)))
    with pytest.raises(CapacityError, match="shooter column 2 .*cols 2"):
        proto.encode(LoadShooter(2, (0, 0, 0)))
    with pytest.raises(CapacityError, match="shooter column -1 .*cols 2"):
        proto.encode(LoadPoints(((False, 1, (0, 0, 0)), (True, -1, (0, 0, 0)))))
    for slots in ((), ((False, 0, (0, 0, 0)),) * 5):       # a LOAD_POINTS carries 1 to 4 points
        with pytest.raises(ParameterError, match=f"not {len(slots)}"):
            proto.encode(LoadPoints(slots))
    with pytest.raises(CapacityError, match="patch_depth 8"):
        check_capacity(params, records=9, voxels=4)
    with pytest.raises(CapacityError, match="voxel_depth 4"):
        check_capacity(params, records=8, voxels=5)
    check_capacity(params, records=8, voxels=4)
    assert fit_params(params, records=100, voxels=27).patch_depth == 100
    with pytest.raises(ParameterError, match="BoardParams"):
        BoardTop("8x8")


def test_replay_plan():
    W, B, E, R, L, X = (WritePatch(0, 0), BeginBlock(), EndBlock(),
                        ReadCounters(), LoadReceiver(0, (0, 0, 0)), Voxel(0))
    cmds = [W, W, B, L, X, E, R, W, B, L, R, X, E, L]
    #       0  1  2  3  4  5  6  7  8  9 10 11 12 13
    idx = lambda plan: [i for i, _ in plan]
    assert idx(replay_after_reset(cmds, 0)) == [0, 1] + list(range(2, 14))
    assert idx(replay_after_reset(cmds, 1)) == [0, 1] + list(range(6, 14))
    assert idx(replay_after_reset(cmds, 2)) == [0, 1, 7] + list(range(8, 14))   # block 8..12 again
    assert idx(replay_after_reset(cmds, 3)) == [0, 1, 7] + list(range(8, 14))
    assert idx(replay_after_reset(cmds, 4)) == [0, 1, 7, 13]
    host = ReplayingHost(cmds)
    for word in (10, 11, 12):
        host.receive(word)
    host.reset()
    # the replayed block re-sends READ_COUNTERS 10 (a duplicate: dropped), then END_BLOCK 12 (kept)
    assert host.receive(99) is None
    assert host.receive(98) == 12
    assert host.results == {5: 10, 6: 11, 10: 12, 12: 98} and host.done


def _dense_scene(seed):
    """A 2 x 2 board at B = 8 and a dense scene (most patches cross the rays) for the tests that
    construct orders and blocks by hand: (rng, P, Q, V, ids, start, count, params)."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    rows, cols, bits, voxels = 2, 2, 8, 6
    P, Q = random_points(rng, bits, 6), random_points(rng, bits, 6)
    V = crossing_patches(rng, bits, P, Q, 40, crossing=0.9)
    ids, start, count = random_memory(rng, bits, V, voxels, empty=0.0, max_registrations=2)
    params = fit_params(BoardParams(rows=rows, cols=cols, bits=bits), records=len(ids), voxels=voxels)
    return rng, P, Q, V, ids, start, count, params


def _blocked(shooters, receivers, Vv):
    """(R, S) bool: the reference OR of the exact predicate over the patches Vv."""
    from blockray.exact import blocked_block, patch_normals
    return blocked_block(np.array(shooters), np.array(receivers), Vv, patch_normals(Vv)).any(axis=2)


def test_board_executes_in_order_beyond_the_model():
    """Orders the model does not define, checked against an in-order reference: a LOAD between
    VOXELs affects only later records (the point registers are written memory_latency late: the
    case is chosen so that the last record before the LOAD would decide differently with the new
    points), and BEGIN_BLOCK while records are in flight clears only what came before it."""
    seed = 401
    rng, P, Q, V, ids, start, count, params = _dense_scene(seed)
    rows, cols, bits, voxels = params.rows, params.cols, params.bits, len(start)
    blocked, word = _blocked, result_word

    def records(v):
        return V[ids[start[v]:start[v] + count[v]]]

    pt = lambda a: tuple(map(int, a))
    cmds = load_commands(bits, V, ids, start, count)
    expect = []
    found = {"load": 0, "abandon": 0}
    for _ in range(400):
        if found["load"] >= 2 and found["abandon"] >= 2:
            break
        sh, rc = [P[i] for i in rng.choice(6, 2, replace=False)], [Q[i] for i in rng.choice(6, 2, replace=False)]
        sh2, rc2 = [P[rng.integers(6)], sh[1]], [rc[0], Q[rng.integers(6)]]
        va, vb = (int(v) for v in rng.integers(0, voxels, 2))
        A, Bv = records(va), records(vb)
        abandon = found["abandon"] < found["load"]
        if abandon:
            # va's records must block something (a missing clear would show), vb's too
            if not blocked(sh, rc, A).any() or not blocked(sh2, rc2, Bv).any():
                continue
            acc = blocked(sh2, rc2, Bv)
        else:
            acc = blocked(sh, rc, A) | blocked(sh2, rc2, Bv)
            late = blocked(sh, rc, A[:-1]) | blocked(sh2, rc2, A[-1:]) | blocked(sh2, rc2, Bv)
            if (acc == late).all():
                continue          # the LOAD's timing would not show
        found["abandon" if abandon else "load"] += 1
        cmds += [BeginBlock()] + [LoadReceiver(r, pt(rc[r])) for r in range(rows)]
        cmds += [LoadShooter(s, pt(sh[s])) for s in range(cols)]
        cmds.append(Voxel(va))
        if abandon:
            cmds += [BeginBlock()] + [LoadReceiver(r, pt(rc[r])) for r in range(rows)]
            cmds += [LoadShooter(s, pt(sh[s])) for s in range(cols)]
        cmds += [LoadReceiver(1, pt(rc2[1])), LoadShooter(0, pt(sh2[0])),
                 Voxel(vb), EndBlock()]
        expect.append(word(acc))
    assert found == {"load": 2, "abandon": 2}, found
    print("expected", [hex(w) for w in expect])
    log, _ = run_board(params, cmds, seed=seed)
    proto = BoardProtocol(params)
    got = [proto.decode_result(log.results[i]).blocked for i in sorted(log.results)]
    assert [hex(w) for w in got] == [hex(w) for w in expect]


def test_board_overlapped_blocks_and_load_points():
    """Blocks back to back, chosen so that a result word formed one cycle early (without the
    block's last record) or a LOAD_POINTS applying its slots in the wrong order would differ;
    every result against the model, cycles equal the model's (END_BLOCK costs one cycle)."""
    seed = 411
    rng, P, Q, V, ids, start, count, params = _dense_scene(seed)
    rows, cols, bits, voxels = params.rows, params.cols, params.bits, len(start)

    def word(shooters, receivers, Vv):
        return result_word(_blocked(shooters, receivers, Vv))

    pt = lambda a: tuple(map(int, a))
    cmds = load_commands(bits, V, ids, start, count)
    found = {"last_record": 0, "slot_order": 0}
    for _ in range(2000):
        if min(found.values()) >= 3:
            break
        sh = [P[i] for i in rng.choice(6, cols, replace=False)]
        rc = [Q[i] for i in rng.choice(6, rows, replace=False)]
        v = int(rng.integers(voxels))
        recs = V[ids[start[v]:start[v] + count[v]]]
        full = word(sh, rc, recs)
        if found["last_record"] <= found["slot_order"]:
            if full == word(sh, rc, recs[:-1]):
                continue                       # the last record does not decide anything
            found["last_record"] += 1
            slots = [(False, r, pt(rc[r])) for r in range(rows)] + [(True, s, pt(sh[s])) for s in range(cols)]
        else:
            early = [Q[rng.integers(6)], rc[1]]         # row 0 first gets another point, then rc[0]
            if word(sh, early, recs) == full:
                continue
            found["slot_order"] += 1
            slots = [(False, 0, pt(early[0])), (True, 0, pt(sh[0])), (False, 0, pt(rc[0])),
                     (False, 1, pt(rc[1])), (True, 1, pt(sh[1]))]
        cmds += [BeginBlock()]
        cmds += [LoadPoints(tuple(slots[i:i + 4])) for i in range(0, len(slots), 4)]
        cmds += [Voxel(v), EndBlock()]
    assert min(found.values()) >= 3, found
    cmds.append(ReadCounters())
    log, _ = run_board(params, cmds, seed=seed)
    check_run(params, cmds, log)
    counters = BoardProtocol(params).decode_result(log.results[max(log.results)]).counters
    assert counters["stalls"] == 1, counters


def test_protocol_doc_matches_layouts():
    """docs/board-protocol.md embeds the layout tables generated from the layouts themselves."""
    from pathlib import Path
    from blockray.protocol import describe
    text = (Path(__file__).resolve().parent.parent / "docs" / "board-protocol.md").read_text()
    begin = "<!-- generated: python -m blockray.protocol -->\n"
    section = text[text.index(begin) + len(begin):text.index("<!-- end generated -->")]
    assert section == describe(BoardParams())
