"""The whole board in the Amaranth simulator against the bit-exact model.

Blocked words and counters are compared with zero tolerance, under random host idle cycles,
random result back-pressure and a reset in the middle of the batch (the host replays; nothing is
lost, duplicated or reordered). Also: the protocol's record packing, capacity errors and the
timing contract's latencies against the RTL's.
"""

from collections import deque

import numpy as np
import pytest
from amaranth.hdl import ClockDomain, Module
from amaranth.sim import Simulator

from blockray.errors import CapacityError, ParameterError
from blockray.params import BoardParams
from blockray.rtl.board import BoardTop
from blockray.rtl.protocol import (BoardProtocol, ReplayingHost, ResultKind, BoardResult, check_capacity,
                                   fit_params, replay_after_reset)
from blockray.sim.model import Command, result_word
from blockray.timing import BoardTiming, Op

from board_host import RunLog, check_run
from board_scenes import crossing_patches, load_commands, random_block, random_memory, random_points


def make_batch(seed, *, rows, cols, bits, patches=14, voxels=6, blocks=6):
    """Params sized for the scene, and a batch: memory load, blocks, READ_COUNTERS between some."""
    rng = np.random.default_rng(seed)
    P, Q = random_points(rng, bits, 6), random_points(rng, bits, 6)
    V = crossing_patches(rng, bits, P, Q, patches)
    ids, start, count = random_memory(rng, bits, V, voxels)
    params = fit_params(BoardParams(rows=rows, cols=cols, bits=bits), records=len(ids), voxels=voxels)
    cmds = load_commands(bits, V, ids, start, count) + [Command(Op.READ_COUNTERS)]
    for b in range(blocks):
        cmds += random_block(rng, rows, cols, P, Q, voxels)
        if rng.random() < 0.5:
            cmds.append(Command(Op.READ_COUNTERS))
    # back to back: a VOXEL right after a WRITE_VOXEL of the same voxel, results back to back
    cmds += [Command(Op.WRITE_VOXEL, 0, (int(start[1]), int(count[1]))), Command(Op.BEGIN_BLOCK)]
    cmds += [Command(Op.LOAD_RECEIVER, r, tuple(map(int, Q[r]))) for r in range(rows)]
    cmds += [Command(Op.LOAD_SHOOTER, s, tuple(map(int, P[s]))) for s in range(cols)]
    cmds += [Command(Op.VOXEL, 0), Command(Op.VOXEL, 1), Command(Op.END_BLOCK), Command(Op.READ_COUNTERS)]
    return params, cmds


def run_board(params, commands, *, seed, idle=0.0, backpressure=0.0, reset_at=None):
    """Run the batch on BoardTop in the Amaranth simulator; return (RunLog, clock cycles)."""
    rng = np.random.default_rng(seed)
    dut = BoardTop(params)
    proto = dut.protocol
    top = Module()
    top.domains.sync = cd = ClockDomain()
    top.submodules.board = dut
    sim = Simulator(top)
    sim.add_clock(1e-8)
    log = RunLog()
    host = ReplayingHost(commands)
    state = {"cycles": 0}

    async def testbench(ctx):
        queue = deque(host.pending())
        offer = None
        cycle = 0                       # clock edges since the last reset's release
        total = 0
        while not host.done:
            total += 1
            if total > 200_000:
                raise AssertionError("the board stopped making progress")
            if reset_at is not None and total == reset_at:
                ctx.set(dut.commands.valid, 0)
                ctx.set(dut.results.ready, 0)
                ctx.set(cd.rst, 1)
                await ctx.tick()
                ctx.set(cd.rst, 0)
                log.answered_at_reset.append(host.answered)
                host.reset()
                queue, offer, cycle = deque(host.pending()), None, 0
                continue
            if offer is None and queue and rng.random() >= idle:
                offer = queue.popleft()
                ctx.set(dut.commands.payload.as_value(), proto.encode(offer[1]))
            ctx.set(dut.commands.valid, offer is not None)
            ctx.set(dut.results.ready, int(rng.random() >= backpressure))
            _, _, cvalid, cready, rvalid, rready, rword = await ctx.tick().sample(
                dut.commands.valid, dut.commands.ready, dut.results.valid, dut.results.ready,
                dut.results.payload.as_value())
            if cvalid and cready:
                log.accepted[offer[0]] = cycle
                offer = None
            if rvalid and rready:
                log.receive(host, rword, cycle)
            cycle += 1
        state["cycles"] = total

    sim.add_testbench(testbench)
    sim.run()
    return log, state["cycles"]


def test_latencies_match_timing_contract():
    from amaranth.hdl import Fragment
    for bits in (4, 8, 16, 20):
        board = BoardTop(BoardParams(rows=1, cols=1, bits=bits, patch_depth=4, voxel_depth=2))
        Fragment.get(board, None)          # elaborates (and asserts the submodules' latencies)
        contract = BoardTiming.for_bits(bits)
        assert board.timing == contract
        assert board.drain_latency == contract.drain_latency
        assert board.memory_latency == contract.memory_latency
        assert board.processor_latency == contract.processor_latency
        assert contract.cost(Op.END_BLOCK) == 1 == contract.cost(Op.READ_COUNTERS)
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
    latency = BoardTiming.for_bits(params.bits).result_latency
    assert {log.received[i] - log.accepted[i] for i in log.results} == {latency + 1}


@pytest.mark.parametrize("seed", [201, 202])
def test_board_idle_and_backpressure(seed):
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=2, bits=10)
    log, _ = run_board(params, cmds, seed=seed, idle=0.3, backpressure=0.4)
    check_run(params, cmds, log)
    last = max(log.results)
    assert BoardProtocol(params).decode_result(log.results[last]).counters["stalls"] > 1


@pytest.mark.parametrize("seed,fraction", [(301, 0.5), (302, 0.8)])
def test_board_reset_mid_batch(seed, fraction):
    """Reset in the middle of the batch; the host reloads and replays."""
    print(f"seed={seed}")
    params, cmds = make_batch(seed, rows=2, cols=2, bits=8)
    _, clean = run_board(params, cmds, seed=seed, idle=0.2, backpressure=0.3)
    log, _ = run_board(params, cmds, seed=seed, idle=0.2, backpressure=0.3,
                       reset_at=int(clean * fraction))
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
    cmds += [Command(Op.BEGIN_BLOCK), Command(Op.LOAD_RECEIVER, 2, (1, 2, 3)),
             Command(Op.LOAD_SHOOTER, 1, (63, 0, 5)), Command(Op.VOXEL, 8), Command(Op.END_BLOCK),
             Command(Op.READ_COUNTERS)]
    for c in cmds:
        value = proto.command_value(c)
        word = proto.encode(c)
        assert word == proto.command_layout.const(value).as_bits()
        back = proto.decode_command(word)
        assert back["op"] is Op(c.op)
        member = next(iter(value["arg"]), None)
        if member is not None:
            assert back["arg"][member] == value["arg"][member]
    for result in (BoardResult(ResultKind.BLOCKED, blocked=0b100101),
                   BoardResult(ResultKind.COUNTERS, counters=dict(cycles=7, busy=1, tests_issued=6,
                                                                  tests_useful=2, stalls=(1 << 48) - 1))):
        word = proto.encode_result(result)
        assert proto.decode_result(word) == result


def test_protocol_capacity_errors():
    params = BoardParams(rows=2, cols=2, bits=6, patch_depth=8, voxel_depth=4)
    proto = BoardProtocol(params)
    with pytest.raises(CapacityError, match="patch_depth 8"):
        proto.encode(Command(Op.WRITE_PATCH, 8, 0))
    with pytest.raises(CapacityError, match="voxel_depth 4"):
        proto.encode(Command(Op.VOXEL, 4))
    with pytest.raises(CapacityError, match="patch_depth 8"):
        proto.encode(Command(Op.WRITE_VOXEL, 1, (5, 4)))
    with pytest.raises(CapacityError, match="rows"):
        proto.encode(Command(Op.LOAD_RECEIVER, 2, (0, 0, 0)))
    with pytest.raises(CapacityError, match="patch_depth 8"):
        check_capacity(params, records=9, voxels=4)
    with pytest.raises(CapacityError, match="voxel_depth 4"):
        check_capacity(params, records=8, voxels=5)
    check_capacity(params, records=8, voxels=4)
    assert fit_params(params, records=100, voxels=27).patch_depth == 100
    with pytest.raises(ParameterError, match="BoardParams"):
        BoardTop("8x8")


def test_replay_plan():
    W, B, E, R, L, X = (Command(Op.WRITE_PATCH), Command(Op.BEGIN_BLOCK), Command(Op.END_BLOCK),
                        Command(Op.READ_COUNTERS), Command(Op.LOAD_RECEIVER), Command(Op.VOXEL))
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
        cmds += [Command(Op.BEGIN_BLOCK)] + [Command(Op.LOAD_RECEIVER, r, pt(rc[r])) for r in range(rows)]
        cmds += [Command(Op.LOAD_SHOOTER, s, pt(sh[s])) for s in range(cols)]
        cmds.append(Command(Op.VOXEL, va))
        if abandon:
            cmds += [Command(Op.BEGIN_BLOCK)] + [Command(Op.LOAD_RECEIVER, r, pt(rc[r])) for r in range(rows)]
            cmds += [Command(Op.LOAD_SHOOTER, s, pt(sh[s])) for s in range(cols)]
        cmds += [Command(Op.LOAD_RECEIVER, 1, pt(rc2[1])), Command(Op.LOAD_SHOOTER, 0, pt(sh2[0])),
                 Command(Op.VOXEL, vb), Command(Op.END_BLOCK)]
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
        cmds += [Command(Op.BEGIN_BLOCK)]
        cmds += [Command(Op.LOAD_POINTS, 0, tuple(slots[i:i + 4])) for i in range(0, len(slots), 4)]
        cmds += [Command(Op.VOXEL, v), Command(Op.END_BLOCK)]
    assert min(found.values()) >= 3, found
    cmds.append(Command(Op.READ_COUNTERS))
    log, _ = run_board(params, cmds, seed=seed)
    check_run(params, cmds, log)
    counters = BoardProtocol(params).decode_result(log.results[max(log.results)]).counters
    assert counters["stalls"] == 1, counters


def test_protocol_doc_matches_layouts():
    """docs/board-protocol.md embeds the layout tables generated from the layouts themselves."""
    from pathlib import Path
    from blockray.rtl.protocol import describe
    text = (Path(__file__).resolve().parent.parent / "docs" / "board-protocol.md").read_text()
    begin = "<!-- generated: python -m blockray.rtl.protocol -->\n"
    section = text[text.index(begin) + len(begin):text.index("<!-- end generated -->")]
    assert section == describe(BoardParams())
