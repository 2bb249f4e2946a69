"""Formal check of the board's frame sender (blockray.rtl.framing.FrameSender) with SymbiYosys
(yowasp-sby) and Boolector: the core's results, the UART's ``ready``, the receiver's news
(acknowledgements, RESEND, NAKs, status requests) and the counters are all free (AnySeq).

The host is free but for one rule: it acknowledges only frames it has received whole. The
reference is written out here, not taken from the sender: a COBS decoder of the wire bytes
and the CRC of the decoded bytes (amaranth.lib.crc, CRC32_ETHERNET = zlib.crc32), for a sender of
``PAYLOAD`` bytes per frame and a window of ``WINDOW`` frames. Bounded (``DEPTH`` steps: a frame
with a payload leaves whole within them, a cover shows). At every frame delimiter:

* **every frame is well formed**: its stuffing is complete, it has the 4-byte header, its length
  field is its payload's size (at most ``PAYLOAD``; 6 for a status frame) and its CRC residue
  is right, so the host's receiver accepts it;
* **numbers are consecutive and resends stay in the window**: a data frame carries the next new
  number, or one of the ``WINDOW`` numbers before it (a resend);
* **a new frame carries the core's next result bytes**: the payload of each new data frame is
  the bytes the sender took from ``results``, in order, none skipped or repeated.

The proof can fail: against a reference with another CRC (CRC-32C) sby finds a counterexample.
"""

import pytest
from amaranth.asserts import AnySeq
from amaranth.hdl import Array, Assert, Assume, Cover, Elaboratable, Module, Mux, Signal
from amaranth.lib import crc

from blockray.rtl.framing import FrameSender

pytestmark = pytest.mark.synth

PAYLOAD, WINDOW = 1, 2
#: a data frame of PAYLOAD bytes is built (9 cycles), stuffed and sent (10 + 1 bytes) within it
DEPTH = 26
#: result bytes remembered by the reference (more than the window holds)
SHADOW = 8


class SenderSpec(Elaboratable):
    """The sender against the reference; ``algorithm``: the reference's CRC; ``window``: the
    window the reference allows resends in (both wrong for the proofs that must fail)."""

    def __init__(self, algorithm=crc.catalog.CRC32_ETHERNET, *, window=WINDOW):
        self.algorithm, self.window = algorithm, window

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = FrameSender(payload=PAYLOAD, window=WINDOW)
        m.submodules.ref_crc = ref_crc = self.algorithm(data_width=8).create()
        for port in (dut.results.valid, dut.results.payload, dut.wire.ready, dut.report, dut.status.expect,
                     dut.status.peer, dut.status.peer_ack, dut.status.peer_resend, dut.status.ack_due,
                     dut.status.nak, dut.status.status_due):
            m.d.comb += port.eq(AnySeq(len(port)))

        # the core's bytes as the sender took them
        shadow = Array(Signal(8, name=f"shadow{k}") for k in range(SHADOW))
        taken = Signal(8)
        with m.If(dut.results.valid & dut.results.ready):
            m.d.sync += [shadow[taken % SHADOW].eq(dut.results.payload), taken.eq(taken + 1)]

        # the reference: COBS-decode the wire bytes, count them, CRC them, keep the header
        byte = dut.wire.payload
        take = dut.wire.valid & dut.wire.ready
        code, zero, count = Signal(8), Signal(), Signal(9)
        flags, seq, length = Signal(8), Signal(8), Signal(8)
        out, out_byte = Signal(), Signal(8)
        m.d.comb += [ref_crc.data.eq(out_byte), ref_crc.valid.eq(out)]
        with m.If(take & (byte != 0)):
            with m.If(code == 0):
                m.d.comb += [out.eq(zero), out_byte.eq(0)]
                m.d.sync += [code.eq(byte - 1), zero.eq(byte != 0xFF)]
            with m.Else():
                m.d.comb += [out.eq(1), out_byte.eq(byte)]
                m.d.sync += code.eq(code - 1)
        with m.If(out):
            m.d.sync += count.eq(count + (count != 511))
            for k, field in ((0, flags), (1, seq), (3, length)):
                with m.If(count == k):
                    m.d.sync += field.eq(out_byte)

        # a new data frame's payload bytes are the next results taken
        news, emitted = Signal(8), Signal(8)            # new data frames, their payload bytes
        is_new = (seq == news) & ~flags[1]
        with m.If(out & (count >= 4) & (count < 4 + length) & is_new):
            at = Signal(8)
            m.d.comb += at.eq(emitted + count - 4)
            m.d.comb += [Assert((taken - at)[:8] >= 1), Assert((taken - at)[:8] <= SHADOW),
                         Assert(out_byte == shadow[at % SHADOW])]

        delimiter = take & (byte == 0)
        data = (length != 0) & ~flags[1]
        # the host acknowledges only frames it received whole: never one past the last new frame out
        m.d.comb += Assume(~dut.status.peer | ((news - dut.status.peer_ack)[:8] < 128))
        behind = Signal(8)
        m.d.comb += behind.eq(news - seq)
        m.d.comb += ref_crc.start.eq(delimiter)
        with m.If(delimiter):
            m.d.comb += [Assert(code == 0), Assert(count >= 8), Assert(count == length + 8),
                         Assert(ref_crc.match_detected), Assert(Mux(flags[1], length == 6, length <= PAYLOAD))]
            with m.If(data & ~is_new):
                m.d.comb += Assert((behind >= 1) & (behind <= self.window))
            with m.If(data & is_new):
                m.d.sync += [news.eq(news + 1), emitted.eq(emitted + length)]
            m.d.sync += [count.eq(0), code.eq(0), zero.eq(0)]
        m.d.comb += Cover(delimiter & data & is_new & (length == PAYLOAD))
        return m


#: the memories as flip-flops (faster for the solver than SMT arrays)
SCRIPT = ("memory_map", "opt -fast")


@pytest.fixture(scope="module")
def formal():
    from blockray.synth.formal import prove
    return prove


def test_sender_frames_are_good_numbered_and_carry_the_results(formal, tmp_path):
    result = formal(SenderSpec(), name="sender", mode="bmc", depth=DEPTH, workdir=tmp_path, script=SCRIPT)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


def test_sender_reachable(formal, tmp_path):
    """Not vacuous: within the bound a new data frame leaves whole."""
    result = formal(SenderSpec(), name="sender_cover", mode="cover", depth=DEPTH, workdir=tmp_path, script=SCRIPT)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


@pytest.mark.parametrize("wrong", [{"algorithm": crc.catalog.CRC32_CASTAGNOLI}], ids=["crc32c"])
def test_sender_proof_fails_against_a_wrong_reference(formal, tmp_path, wrong):
    result = formal(SenderSpec(**wrong), name="sender_wrong", mode="bmc", depth=DEPTH, workdir=tmp_path,
                    script=SCRIPT)
    assert result.status == "FAIL", result.log[-2000:]
