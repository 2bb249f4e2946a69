"""The board's receiving half of the framed link in gateware (rtl/framing.py FrameReceiver)
against the model's (blockray/framing.py Endpoint.receive), byte for byte, in the Amaranth
simulator: the payload delivered, the NAKs, the acknowledgements it reports and the next number,
for a stream of frames with faults, garbage, duplicates and frames out of order. Seeded; the
seed is printed."""

import random

import numpy as np
import pytest
from amaranth.hdl import Module
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from blockray.framing import POLL, RESEND, STATUS, Endpoint, FrameError, FrameSplitter, LinkConfig, encode_frame, Frame, parse_frame
from blockray.host_driver.board.framed import FaultInjector
from blockray.rtl.framing import FramedBridge, FrameReceiver


def _stream(seed, rate):
    """Frames of a host (some resent, some out of order), garbage, acknowledgements, status
    requests and status frames between them, faults."""
    rng = random.Random(seed)
    host = Endpoint(LinkConfig(payload=40, window=6))
    host.submit(bytes(rng.randrange(256) for _ in range(1500)))
    wire = bytearray()
    while host.pending:
        out = host.output()
        frames = [f + b"\x00" for f in out.split(b"\x00")[:-1]]
        if len(frames) > 2 and rng.random() < 0.2:
            frames[0], frames[1] = frames[1], frames[0]
        wire += b"".join(frames)
        if rng.random() < 0.2:
            wire += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 30)))
        if rng.random() < 0.05:
            wire += bytes(rng.randrange(1, 256) for _ in range(300)) + b"\x00"      # overlong
        # an ack, a POLL or a status request
        wire += encode_frame(Frame(rng.randrange(8), rng.randrange(256), rng.randrange(256)))
        if rng.random() < 0.2:          # a status frame numbered as the next data frame: never data
            wire += encode_frame(Frame(STATUS | rng.randrange(2), host.next, rng.randrange(256), bytes(6)))
        host.receive(encode_frame(Frame(0, 0, host.next)))        # acknowledge all: go on
    return FaultInjector(rate, np.random.default_rng(seed))(bytes(wire))


def _model(wire):
    board = Endpoint(LinkConfig())
    payload = board.receive(wire)
    peers = []
    splitter = FrameSplitter()
    for chunk in splitter.feed(wire)[0]:
        try:
            f = parse_frame(chunk) if chunk is not None else None
        except FrameError:
            f = None
        if f is not None:
            peers.append((f.ack, f.flags & 1))
    return payload, board.counts["naks_sent"], board.expect, peers, board.counts["frames_accepted"], board.faults()


def _rtl(wire, seed):
    dut = FrameReceiver()
    sim = Simulator(dut)
    sim.add_clock(1e-8)
    got = {"payload": bytearray(), "naks": 0, "peers": []}
    rng = random.Random(seed)

    async def bench(ctx):
        i = 0
        idle = 0
        while i < len(wire) or idle < 300:
            ctx.set(dut.wire.valid, i < len(wire))
            ctx.set(dut.wire.payload, wire[i] if i < len(wire) else 0)
            ctx.set(dut.payload.ready, rng.random() < 0.7)
            await ctx.delay(1e-9)
            if ctx.get(dut.wire.valid) and ctx.get(dut.wire.ready):
                i += 1
            if ctx.get(dut.payload.valid) and ctx.get(dut.payload.ready):
                got["payload"].append(ctx.get(dut.payload.payload))
            got["naks"] += ctx.get(dut.status.nak)
            if ctx.get(dut.status.peer):
                got["peers"].append((ctx.get(dut.status.peer_ack), ctx.get(dut.status.peer_resend)))
            idle = idle + 1 if i >= len(wire) else 0
            await ctx.tick()
        got["expect"] = ctx.get(dut.status.expect)
        got["frames"] = ctx.get(dut.frames)
        got["errors"] = ctx.get(dut.errors)

    sim.add_testbench(bench)
    sim.run()
    return got


@pytest.mark.parametrize("rate", [0.0, 2e-3, 1e-2])
def test_frame_receiver_equals_the_model(rate, rng_seed):
    seed = rng_seed
    wire = _stream(seed, rate)
    payload, naks, expect, peers, accepted, errors = _model(wire)
    got = _rtl(wire, seed)
    assert len(payload) > 0 or naks > 0          # (a lost first frame leaves only gaps)
    assert bytes(got["payload"]) == payload
    assert (got["naks"], got["expect"], got["frames"], got["errors"]) == (naks, expect, accepted, errors)
    assert got["peers"] == peers


def _frames_through_receiver(frames, space):
    """(NAKs while each frame came and was checked, errors, frames accepted) of a FrameReceiver
    given ``frames`` (Frame) with the consumer's room ``space(k)`` while frame ``k`` is checked."""
    dut = FrameReceiver()
    sim = Simulator(dut)
    sim.add_clock(1e-8)
    got = {"naks": [0] * len(frames)}

    async def bench(ctx):
        ctx.set(dut.payload.ready, 1)
        for k, frame in enumerate(frames):
            ctx.set(dut.space, space(k))
            for byte in encode_frame(frame):
                ctx.set(dut.wire.valid, 1)
                ctx.set(dut.wire.payload, byte)
                await ctx.delay(1e-9)
                while not ctx.get(dut.wire.ready):
                    await ctx.tick()
                    await ctx.delay(1e-9)
                got["naks"][k] += ctx.get(dut.status.nak)
                await ctx.tick()
            ctx.set(dut.wire.valid, 0)
            for _ in range(300):            # the check and the payload out
                await ctx.delay(1e-9)
                got["naks"][k] += ctx.get(dut.status.nak)
                await ctx.tick()
        got["errors"], got["frames"] = ctx.get(dut.errors), ctx.get(dut.frames)

    sim.add_testbench(bench)
    sim.run()
    return got["naks"], got["errors"], got["frames"]


def _data_frames():
    return [Frame(0, seq, 0, bytes([seq + 1]) * 20) for seq in (0, 1)]


@pytest.mark.parametrize("refused,errors", [(True, 0), (False, 1)])
def test_a_frame_refused_for_space_is_no_error(refused, errors):
    """Frame 0 refused for want of room (or, for contrast, lost on the wire): frame 1 after it is
    a gap either way, but only a lost frame counts as an error (the report's ``board_errors``
    count link faults); frames 0 and 1 resent are accepted."""
    f = _data_frames()
    sent = [f[0], f[1], f[0], f[1]] if refused else [f[1], f[0], f[1]]
    naks, got_errors, accepted = _frames_through_receiver(sent, lambda k: 0 if refused and k == 0 else 255)
    assert (sum(naks), got_errors, accepted) == (1, errors, 2)


@pytest.mark.parametrize("room", [19, 20, 255])
def test_a_refusal_waits_for_room_and_then_asks_once(room):
    """A refused frame is flow control: no NAK for it, for the gap behind it, for the POLL that
    ends the round or for a RESEND (a resend into a full FIFO is refused again, and each would
    queue another window on the wire), and exactly one NAK when the room reaches the refused
    frame's length (20 bytes), not before. A lost frame NAKs at once and again at the POLL."""
    f = _data_frames()
    poll, resend = Frame(POLL, 2, 0, b""), Frame(RESEND, 2, 0, b"")
    sent = [f[0], f[1], poll, resend, Frame(0, 0, 0, b""), f[0], f[1]]
    space = [0, 0, 0, 0, room, 255, 255]
    naks, errors, accepted = _frames_through_receiver(sent, lambda k: space[k])
    asked = [0, 0, 0, 0, 1, 0, 0] if room >= 20 else [0, 0, 0, 0, 0, 1, 0]
    assert (naks, errors, accepted) == (asked, 0, 2)
    lost, _, _ = _frames_through_receiver([f[1], poll, f[0], f[1]], lambda k: 255)
    assert lost == [1, 1, 0, 0]


class _Loopback(wiring.Component):
    """FramedBridge with a core that answers every command byte with itself (through a FIFO)."""

    rx_bytes: In(stream.Signature(8))
    tx_bytes: Out(stream.Signature(8))

    def __init__(self):
        self.bridge = FramedBridge(fifo_depth=512, payload=16, window=4)
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.bridge = bridge = self.bridge
        m.submodules.core = core = SyncFIFOBuffered(width=8, depth=8)
        wiring.connect(m, outside=wiring.flipped(self.rx_bytes), bridge=bridge.rx_bytes)
        wiring.connect(m, bridge=bridge.commands, core=core.w_stream)
        wiring.connect(m, core=core.r_stream, bridge=bridge.results)
        wiring.connect(m, bridge=bridge.tx_bytes, outside=wiring.flipped(self.tx_bytes))
        return m


@pytest.mark.parametrize("rate", [0.0, 2e-3, 1e-2])
def test_framed_bridge_against_the_host(rate, rng_seed):
    """The host's Endpoint (HOST_LINK-sized window, short frames) sends through the bridge to a
    looping core; what comes back, through the board's FrameSender, is exactly what was sent,
    with faults both ways. The host resends after 400 silent cycles; the UART never overruns. At
    the end the board's counters come in a status frame."""
    seed = rng_seed
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(300))
    host = Endpoint(LinkConfig(payload=40, window=4))
    host.submit(data)
    down = FaultInjector(rate, np.random.default_rng([seed, 0]))
    up = FaultInjector(rate, np.random.default_rng([seed, 1]))
    dut = _Loopback()
    sim = Simulator(dut)
    sim.add_clock(1e-8)
    got = bytearray()

    async def bench(ctx):
        queue, silent, asked = bytearray(), 0, False
        ctx.set(dut.tx_bytes.ready, 1)
        for cycle in range(150000):
            if not queue:
                queue += down(host.output())
            ctx.set(dut.rx_bytes.valid, bool(queue) and cycle % 3 == 0)      # a UART's pace, no waiting
            ctx.set(dut.rx_bytes.payload, queue[0] if queue else 0)
            await ctx.delay(1e-9)
            if ctx.get(dut.rx_bytes.valid):
                del queue[0]
            if ctx.get(dut.tx_bytes.valid):
                got.extend(host.receive(up(bytes([ctx.get(dut.tx_bytes.payload)]))))
                silent = 0
            else:
                silent += 1
            if silent > 400 and not queue:
                host.rewind()
                silent = 0
            if len(got) >= len(data) and not host.pending:
                if host.peer_status is not None:
                    break
                if not asked:                       # then the board's counters, in a status frame
                    host.request_status()
                    down.rate = up.rate = 0
                    asked = True
            await ctx.tick()
        assert not ctx.get(dut.bridge.overrun)

    sim.add_testbench(bench)
    sim.run()
    assert bytes(got) == data
    # every new frame the host sent was accepted once; without faults nothing was resent or wrong
    board = host.peer_status
    print("board", board, "host", host.counts)
    assert board["frames_accepted"] == host.counts["frames_sent"]
    if rate == 0:
        assert board["errors"] == board["frames_resent"] == 0
