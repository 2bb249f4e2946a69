"""The serial link in the Amaranth simulator: UART against bit-level references, the bridge's
FIFOs and credits under random idles and back-pressure, the whole link at its pins with a break.

Every random test is seeded and prints its seed. The references are written here from the 8N1
definition (bit times counted in clock cycles), not taken from the code under test.
"""

import random

import pytest
from amaranth.hdl import Module
from amaranth.sim import Simulator

from blockray.link import LinkHost, frame_results, grant_header, parse_header, result_header
from blockray.rtl.link import LinkBridge, SerialLink
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


def test_framing_constants():
    host = LinkHost()
    stream = bytes([grant_header(3)]) + frame_results(b"abc") + bytes([grant_header(128)])
    assert host.feed(stream[:3]) == b"a" and host.credits == 3
    assert host.feed(stream[3:]) == b"bc" and host.credits == 131
    assert parse_header(result_header(128)) == (False, 128) and parse_header(grant_header(1)) == (True, 1)
    host.spend(131)
    with pytest.raises(ValueError):
        host.spend(1)


def run_bridge(seed, *, fifo_depth, n, repeat, idle, backpressure, hold):
    """LinkBridge + EchoCore with a host model at the byte streams (no UART): command bytes sent
    only against credits at random times, the transmitter's ready random. Returns the host."""
    print("seed", seed)
    rng = random.Random(seed)
    bridge = LinkBridge(fifo_depth=fifo_depth, result_depth=16)
    core = EchoCore(depth=4, repeat=repeat)
    m = Module()
    m.submodules.bridge, m.submodules.core = bridge, core
    from amaranth.lib import wiring
    wiring.connect(m, bridge=bridge.commands, core=core.i_bytes)
    wiring.connect(m, core=core.o_bytes, bridge=bridge.results)
    sim = Simulator(m)
    sim.add_clock(1e-8)
    data = bytes(rng.randrange(256) for _ in range(n))
    host = LinkHost()
    state = {"sent": 0, "results": bytearray(), "owed": []}

    async def testbench(ctx):
        held = None                       # (payload) offered on tx and not yet taken
        cycles = 0
        while len(state["results"]) < n * repeat or host.credits < fifo_depth:
            cycles += 1
            assert cycles < 200 * n, f"no progress: {len(state['results'])} results, {host.credits} credits"
            # the UART receiver: a byte arrives when the host had a credit (no ready to wait for)
            send = state["sent"] < n and host.credits > 0 and rng.random() >= idle
            ctx.set(bridge.rx_bytes.valid, send)
            if send:
                ctx.set(bridge.rx_bytes.payload, data[state["sent"]])
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
                host.spend(1)
                state["sent"] += 1
            if valid and ready:
                state["results"] += host.feed(bytes([payload]))
        state["owed"] = ctx.get(bridge.owed)

    sim.add_testbench(testbench)
    sim.run()
    assert bytes(state["results"]) == echo(data, repeat)
    assert host.credits == fifo_depth and state["owed"] == 0
    assert host.granted == fifo_depth + n
    return host


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_bridge_random_idle_and_backpressure(seed):
    run_bridge(seed, fifo_depth=8, n=300, repeat=1, idle=0.3, backpressure=0.4, hold=0.2)


@pytest.mark.parametrize("seed", [4, 5])
def test_bridge_result_path_full(seed):
    # two result bytes per command byte and a slow transmitter: the result FIFO fills, the core
    # stalls, credits stop, nothing is lost
    run_bridge(seed, fifo_depth=16, n=200, repeat=2, idle=0.0, backpressure=0.7, hold=0.05)


def test_bridge_bursts():
    # long stalls, not only per-cycle coin flips: whole runs of idle and back-pressure
    seed = 6
    run_bridge(seed, fifo_depth=4, n=120, repeat=1, idle=0.9, backpressure=0.9, hold=0.9)


def test_bridge_rejects_bad_depths():
    with pytest.raises(ValueError, match="fifo_depth"):
        LinkBridge(fifo_depth=12)
    with pytest.raises(ValueError, match="result_depth"):
        LinkBridge(result_depth=2)


@pytest.mark.parametrize("seed", [11, 12])
def test_serial_link_pins_with_break(seed):
    """The whole link at its pins: the host bit-bangs command frames against credits with random
    gaps, decodes the board's frames from the tx pin, and sends a break half-way: the link and the
    core reset, the board is silent during the break, and grants start again from the depth."""
    print("seed", seed)
    rng = random.Random(seed)
    divisor, depth = 4, 8
    core = EchoCore(depth=4, repeat=1)
    dut = SerialLink(core, divisor=divisor, fifo_depth=depth, result_depth=8)
    first = bytes(rng.randrange(256) for _ in range(40))
    second = bytes(rng.randrange(256) for _ in range(40))
    host = LinkHost()
    got = bytearray()
    state = {"phase": 0, "during_break": bytearray()}

    async def host_tx(ctx):
        ctx.set(dut.rx, 1)
        for phase, data in enumerate((first, second)):
            for byte in data:
                while host.credits == 0:
                    await ctx.tick()
                host.spend(1)
                await send_frame(ctx, dut.rx, byte, divisor)
                ctx.set(dut.rx, 1)
                await wait(ctx, rng.choice([0, 0, 2, 9]))
            if phase == 0:
                while len(got) < len(first) // 2:
                    await ctx.tick()
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
        while len(got) < len(second) or host.credits < depth:
            await ctx.tick()

    async def host_rx(ctx):
        dec = LineDecoder(divisor)
        async for _clk, _rst, tx in ctx.tick().sample(dut.tx):
            byte = dec.step(tx)
            if byte is None:
                continue
            if state["phase"] == 1:
                state["during_break"].append(byte)
            else:
                got.extend(host.feed(bytes([byte])))

    sim = _sim(dut)
    sim.add_testbench(host_tx)
    sim.add_process(host_rx)
    sim.run()
    assert bytes(got) == echo(second)
    assert host.granted == depth + len(second) and host.credits == depth
    assert not state["during_break"], "the board spoke during the break"
