"""The serial link in the Amaranth simulator: UART against bit-level references, the framed
bridge under random idles, back-pressure and a busy core, the whole link at its pins with a break.

Every random test is seeded and prints its seed. The references are written here from the 8N1
definition (bit times counted in clock cycles), not taken from the code under test.
"""

import random

import pytest
from amaranth.hdl import Module
from amaranth.sim import Simulator

from blockray.framing import Endpoint, LinkConfig
from blockray.rtl.framing import FramedBridge
from blockray.rtl.link import SerialLink
from blockray.rtl.uart import UARTRx, UARTTx

from link_cores import EchoCore, echo


def _sim(dut):
    m = Module()
    m.submodules.dut = dut
    sim = Simulator(m)
    sim.add_clock(1e-8)
    return sim


async def wait(ctx, cycles):
    if cycles:
        await ctx.tick().repeat(cycles)


def _frame_bits(byte):
    return [0] + [(byte >> i) & 1 for i in range(8)] + [1]


async def send_frame(ctx, pin, byte, divisor, *, scale=1.0, bits=None):
    """Drive one 8N1 frame on ``pin`` (or the given ``bits``); a bit lasts ``divisor * scale``
    cycles (boundaries rounded)."""
    edge = 0
    for k, bit in enumerate(bits or _frame_bits(byte)):
        ctx.set(pin, bit)
        nxt = round((k + 1) * divisor * scale)
        await ctx.tick().repeat(nxt - edge)
        edge = nxt


class LineDecoder:
    """8N1 bytes from a line sampled every clock cycle, checking that every bit lasts exactly
    ``divisor`` cycles and the stop bit is high. ``step(level)`` returns a byte or None."""

    def __init__(self, divisor):
        self.divisor = divisor
        self.cells = None
        self.cycle = 0
        self.starts = []        # cycle of each frame's start bit

    def step(self, level):
        self.cycle += 1
        if self.cells is None:
            if level == 0:
                self.cells = [0]
                self.starts.append(self.cycle)
            return None
        self.cells.append(level)
        if len(self.cells) < 10 * self.divisor:
            return None
        cells, self.cells, d = self.cells, None, self.divisor
        bits = []
        for k in range(10):
            bit = cells[k * d:(k + 1) * d]
            assert len(set(bit)) == 1, f"bit {k} is not {d} cycles long: {bit}"
            bits.append(bit[0])
        assert bits[9] == 1, "stop bit low"
        return sum(b << i for i, b in enumerate(bits[1:9]))


def decode_trace(trace, divisor):
    """(bytes, start cycles) of a whole trace."""
    dec = LineDecoder(divisor)
    out = bytearray(b for b in map(dec.step, trace) if b is not None)
    assert dec.cells is None, "a frame is cut off"
    return bytes(out), dec.starts


@pytest.mark.parametrize("divisor,scale", [(4, 1.0), (16, 1.0), (16, 1.03), (16, 0.97), (5, 1.0)])
def test_uart_rx_against_reference_frames(divisor, scale):
    seed = 1000 + divisor * 7 + int(scale * 100)
    print("seed", seed)
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(40)) + b"\x00\xff"
    dut = UARTRx(divisor)
    got, errors = [], []

    async def sender(ctx):
        ctx.set(dut.rx, 1)
        await ctx.tick().repeat(3)
        for i, byte in enumerate(data):
            if i == 5:      # a glitch shorter than half a bit is not a start bit
                ctx.set(dut.rx, 0)
                await ctx.tick().repeat(max(1, divisor // 2 - 2))
                ctx.set(dut.rx, 1)
                await ctx.tick().repeat(divisor)
            if i == 9:      # a frame with a low stop bit is dropped, as a framing error
                await send_frame(ctx, dut.rx, None, divisor, bits=_frame_bits(0x3C)[:9] + [0])
                ctx.set(dut.rx, 1)
                await ctx.tick().repeat(2 * divisor)
            await send_frame(ctx, dut.rx, byte, divisor, scale=scale)
            ctx.set(dut.rx, 1)
            await wait(ctx, rng.choice([0, 0, 1, 3, divisor * 2]))
        await ctx.tick().repeat(4 * divisor)

    async def monitor(ctx):
        async for _clk, _rst, valid, payload, ferr in ctx.tick().sample(
                dut.o_bytes.valid, dut.o_bytes.payload, dut.frame_error):
            if valid:
                got.append(payload)
            if ferr:
                errors.append(len(got))

    sim = _sim(dut)
    sim.add_testbench(sender)
    sim.add_process(monitor)
    sim.run()
    assert bytes(got) == data
    assert len(errors) == 1, errors


@pytest.mark.parametrize("divisor", [4, 7, 16])
def test_uart_tx_bit_times_exact(divisor):
    seed = 2000 + divisor
    print("seed", seed)
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(30))
    dut = UARTTx(divisor)
    trace = []

    async def producer(ctx):
        for byte in data:
            await wait(ctx, rng.choice([0, 0, 1, 5, 37]))
            ctx.set(dut.i_bytes.payload, byte)
            ctx.set(dut.i_bytes.valid, 1)
            await ctx.tick().until(dut.i_bytes.ready)
            ctx.set(dut.i_bytes.valid, 0)
        await ctx.tick().repeat(12 * divisor)

    async def line(ctx):
        async for _clk, _rst, tx in ctx.tick().sample(dut.tx):
            trace.append(tx)

    sim = _sim(dut)
    sim.add_testbench(producer)
    sim.add_process(line)
    sim.run()
    sent, starts = decode_trace(trace, divisor)
    assert sent == data
    # back to back (no idle between bytes): a byte every 10 bit times exactly
    assert min(b - a for a, b in zip(starts, starts[1:])) == 10 * divisor


def run_bridge(seed, *, n, repeat, idle, backpressure, hold):
    """FramedBridge + EchoCore with the host's Endpoint at the byte streams (no UART): frames
    sent at random times (at most one byte per 3 cycles, a UART's pace), the transmitter's ready
    random, the core busy at random; a valid result byte must hold until taken."""
    print("seed", seed)
    rng = random.Random(seed)
    bridge = FramedBridge(fifo_depth=256, payload=16, window=4)
    core = EchoCore(depth=4, repeat=repeat)
    m = Module()
    m.submodules.bridge, m.submodules.core = bridge, core
    from amaranth.lib import wiring
    wiring.connect(m, bridge=bridge.commands, core=core.i_bytes)
    wiring.connect(m, core=core.o_bytes, bridge=bridge.results)
    sim = Simulator(m)
    sim.add_clock(1e-8)
    data = bytes(rng.randrange(256) for _ in range(n))
    host = Endpoint(LinkConfig(payload=24, window=4))
    host.submit(data)
    results = bytearray()

    async def testbench(ctx):
        held, queue, silent = None, bytearray(), 0
        for cycle in range(400 * n):
            if len(results) >= n * repeat and not host.pending:
                break
            if not queue:
                queue += host.output()
            send = bool(queue) and cycle % 3 == 0 and rng.random() >= idle
            ctx.set(bridge.rx_bytes.valid, send)
            ctx.set(bridge.rx_bytes.payload, queue[0] if send else 0)
            ready = rng.random() >= backpressure
            ctx.set(bridge.tx_bytes.ready, ready)
            ctx.set(core.hold, rng.random() < hold)
            valid, payload = ctx.get(bridge.tx_bytes.valid), ctx.get(bridge.tx_bytes.payload)
            if held is not None:
                assert valid and payload == held, "tx valid or payload changed before ready"
            held = payload if valid and not ready else None
            assert not ctx.get(bridge.overrun)
            await ctx.tick()
            if send:
                del queue[0]
            if valid and ready:
                results.extend(host.receive(bytes([payload])))
                silent = 0
            else:
                silent += 1
            if silent > 2000 and not queue:         # (nothing is lost here: a resend never comes)
                host.rewind()
                silent = 0
        assert host.counts["timeouts"] == 0 and host.faults() == 0

    sim.add_testbench(testbench)
    sim.run()
    assert bytes(results) == echo(data, repeat)
    return host


@pytest.mark.parametrize("seed", [1, 2])
def test_bridge_random_idle_and_backpressure(seed):
    run_bridge(seed, n=300, repeat=1, idle=0.3, backpressure=0.4, hold=0.2)


@pytest.mark.parametrize("seed", [4])
def test_bridge_result_path_full(seed):
    # two result bytes per command byte and a slow transmitter: the replay memory fills, the
    # core stalls, frames wait for their acknowledgements, nothing is lost
    run_bridge(seed, n=200, repeat=2, idle=0.0, backpressure=0.7, hold=0.05)


@pytest.mark.parametrize("seed", [11])
def test_serial_link_pins_with_break(seed):
    """The whole link at its pins: the host bit-bangs its frames with random gaps, decodes the
    board's frames from the tx pin, and sends a break half-way: the link and the core reset, the
    board is silent during the break, and both sides number their frames from 0 again."""
    print("seed", seed)
    rng = random.Random(seed)
    divisor = 4
    core = EchoCore(depth=4, repeat=1)
    dut = SerialLink(core, divisor=divisor, fifo_depth=128, payload=16, window=4)
    first = bytes(rng.randrange(256) for _ in range(40))
    second = bytes(rng.randrange(256) for _ in range(40))
    host = Endpoint(LinkConfig(payload=16, window=4))
    got = bytearray()
    state = {"phase": 0, "during_break": bytearray()}

    async def host_tx(ctx):
        ctx.set(dut.rx, 1)
        for phase, data in enumerate((first, second)):
            host.submit(data)
            while host.pending or len(got) < len(data):
                for byte in host.output():
                    await send_frame(ctx, dut.rx, byte, divisor)
                    ctx.set(dut.rx, 1)
                    await wait(ctx, rng.choice([0, 0, 2, 9]))
                await ctx.tick()
                if phase == 0 and len(got) >= len(first) // 2:
                    break
            if phase == 0:
                # break: hold rx low for 3 frames; drop what came before; release
                ctx.set(dut.rx, 0)
                await ctx.tick().repeat(12 * divisor)
                assert ctx.get(dut.link_reset)
                await ctx.tick().repeat(10 * divisor)     # a byte already on the line ends
                state["phase"] = 1
                await ctx.tick().repeat(20 * divisor)
                state["phase"] = 2
                got.clear()
                host.reset()
                ctx.set(dut.rx, 1)
        assert host.next == host.base == 3               # frames 0, 1, 2 after the break: numbered from 0

    async def host_rx(ctx):
        dec = LineDecoder(divisor)
        async for _clk, _rst, tx in ctx.tick().sample(dut.tx):
            byte = dec.step(tx)
            if byte is None:
                continue
            if state["phase"] == 1:
                state["during_break"].append(byte)
            else:
                got.extend(host.receive(bytes([byte])))

    sim = _sim(dut)
    sim.add_testbench(host_tx)
    sim.add_process(host_rx)
    sim.run()
    assert bytes(got) == echo(second)
    assert host.faults() == 0 and not state["during_break"], "the board spoke during the break"
