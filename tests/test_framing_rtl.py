"""The board's receiving half of the framed link in gateware (rtl/framing.py FrameReceiver)
against the model's (blockray/framing.py Endpoint.receive), byte for byte, in the Amaranth
simulator: the payload delivered, the NAKs, the acknowledgements it reports and the next number,
for a stream of frames with faults, garbage, duplicates and frames out of order. Seeded; the
seed is printed."""

import random

import numpy as np
import pytest
from amaranth.sim import Simulator

from blockray.framing import Endpoint, FrameError, FrameSplitter, LinkConfig, encode_frame, Frame, parse_frame
from blockray.host_driver.framed import FaultInjector
from blockray.rtl.framing import FrameReceiver


def _stream(seed, rate):
    """Frames of a host (some resent, some out of order), garbage between them, faults."""
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
        wire += encode_frame(Frame(rng.randrange(2), rng.randrange(256), rng.randrange(256)))  # a pure ack
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
    return payload, board.counts["naks_sent"], board.expect, peers, board.counts["frames_accepted"]


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
            got["naks"] += ctx.get(dut.nak)
            if ctx.get(dut.peer):
                got["peers"].append((ctx.get(dut.peer_ack), ctx.get(dut.peer_resend)))
            idle = idle + 1 if i >= len(wire) else 0
            await ctx.tick()
        got["expect"] = ctx.get(dut.expect)
        got["frames"] = ctx.get(dut.frames)

    sim.add_testbench(bench)
    sim.run()
    return got


@pytest.mark.parametrize("rate", [0.0, 2e-3, 1e-2])
def test_frame_receiver_equals_the_model(rate):
    seed = random.randrange(2**32)
    print("seed", seed, "rate", rate)
    wire = _stream(seed, rate)
    payload, naks, expect, peers, accepted = _model(wire)
    got = _rtl(wire, seed)
    assert len(payload) > 0
    assert bytes(got["payload"]) == payload
    assert (got["naks"], got["expect"], got["frames"]) == (naks, expect, accepted)
    assert got["peers"] == peers
