"""Formal proofs of the board's frame receiver (blockray.rtl.framing.FrameReceiver) with
SymbiYosys (yowasp-sby) and Boolector: the wire bytes are free (AnySeq), the core's ``ready`` too.

The reference is written out here, not taken from the receiver: a COBS decoder of the wire
bytes, the CRC of the decoded bytes (amaranth.lib.crc, CRC32_ETHERNET = zlib.crc32) and the
acceptance rule of docs/board-protocol.md ("Link integrity"), for frames of at most ``MAX_BODY``
decoded bytes (the receiver's size parameter; the protocol's is 254). Bounded (``DEPTH`` steps: a
frame with a payload byte is accepted and emitted within them, a cover shows):

* **a corrupted frame is never executed**: the receiver accepts a frame exactly when the
  reference does (stuffing complete, at most 255 stuffed bytes, 8 to 254 decoded bytes, CRC
  residue, length field = payload size, not a status frame, next sequence number), and no
  payload byte leaves before the frame is accepted;
* **no frame accepted twice or out of order**: each accepted frame carries the number of frames
  accepted before it (mod 256), and ``expect`` is that count;
* the first payload byte out is the decoded byte at the payload's start.

The receiver's CRC register equals the reference's at every step (asserted: the lemma that keeps
the solver from proving two unrolled XOR networks equal). And the proof can fail: against a
reference with another CRC (CRC-32C, Castagnoli), or one that ignores the sequence numbers, sby
finds a counterexample.
"""

import pytest
from amaranth.asserts import AnySeq
from amaranth.hdl import Assert, Cover, Elaboratable, Module, Signal
from amaranth.lib import crc

from blockray.rtl.framing import FrameReceiver

pytestmark = pytest.mark.synth

DEPTH = 13
#: frames of at most 12 decoded bytes (up to 4 payload bytes): a 16-byte memory for the solver
MAX_BODY = 12


class ReceiverSpec(Elaboratable):
    """The receiver against the reference; ``algorithm``: the reference's CRC; ``check_seq``
    False: a reference that ignores the numbers (both for the proofs that must fail)."""

    def __init__(self, algorithm=crc.catalog.CRC32_ETHERNET, *, check_seq=True):
        self.algorithm, self.check_seq = algorithm, check_seq

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = FrameReceiver(max_body=MAX_BODY)
        m.submodules.ref_crc = ref_crc = self.algorithm(data_width=8).create()
        byte, valid, ready = AnySeq(8), AnySeq(1), AnySeq(1)
        m.d.comb += [dut.wire.payload.eq(byte), dut.wire.valid.eq(valid), dut.payload.ready.eq(ready)]
        take = valid & dut.wire.ready

        # the reference: COBS-decode the wire bytes, count them, CRC them, keep the header
        raw, count, code, zero = Signal(9), Signal(9), Signal(8), Signal()
        flags, seq, length, first = Signal(8), Signal(8), Signal(8), Signal(8)
        out, out_byte = Signal(), Signal(8)
        m.d.comb += [ref_crc.data.eq(out_byte), ref_crc.valid.eq(out)]
        with m.If(take & (byte != 0)):
            m.d.sync += raw.eq(raw + (raw != 511))
            with m.If(code == 0):
                m.d.comb += [out.eq(zero), out_byte.eq(0)]
                m.d.sync += [code.eq(byte - 1), zero.eq(byte != 0xFF)]
            with m.Else():
                m.d.comb += [out.eq(1), out_byte.eq(byte)]
                m.d.sync += code.eq(code - 1)
        with m.If(out):
            m.d.sync += count.eq(count + (count != 511))
            for k, field in ((0, flags), (1, seq), (3, length), (4, first)):
                with m.If(count == k):
                    m.d.sync += field.eq(out_byte)

        # at the delimiter: the reference's verdict, compared with the receiver's next cycle
        accepted = Signal(8)
        verdict, verdict_first = Signal(), Signal(8)
        delimiter = take & (byte == 0) & (raw != 0)
        verdict_due = Signal()
        m.d.sync += [verdict.eq(0), verdict_due.eq(delimiter)]
        with m.If(delimiter):
            good = ((raw <= MAX_BODY + 1) & (code == 0) & (count >= 8) & (count <= MAX_BODY) & ref_crc.match_detected
                    & (length == count - 8) & (length != 0) & ~flags[1] & ((seq == accepted) | ~self.check_seq))
            m.d.sync += [verdict.eq(good), verdict_first.eq(first), raw.eq(0), count.eq(0), code.eq(0), zero.eq(0)]
        m.d.comb += ref_crc.start.eq(verdict_due)      # the next CRC starts after the verdict (no byte comes then)
        m.d.comb += Assert(dut.accept == verdict)
        # the receiver's CRC register is the reference's at every step: the lemma that spares the
        # solver proving two unrolled XOR networks equal
        m.d.comb += Assert(dut.crc.crc == ref_crc.crc)

        # no frame twice or out of order; nothing leaves unaccepted; the payload's first byte
        emitting, first_out = Signal(), Signal()
        with m.If(dut.accept):
            m.d.sync += [accepted.eq(accepted + 1), emitting.eq(1), first_out.eq(1)]
        m.d.comb += Assert(dut.status.expect == accepted)
        with m.If(dut.payload.valid):
            m.d.comb += Assert(emitting | dut.accept)
            with m.If(first_out):
                m.d.comb += Assert(dut.payload.payload == verdict_first)
            with m.If(ready):
                m.d.sync += first_out.eq(0)
        with m.If(~dut.payload.valid & ~dut.accept):
            m.d.sync += emitting.eq(0)
        m.d.comb += Cover(dut.payload.valid & ready & (accepted == 1))
        return m


#: the memory as flip-flops (faster for the solver than an SMT array)
SCRIPT = ("memory_map", "opt -fast")


@pytest.fixture(scope="module")
def formal():
    from blockray.synth.formal import prove
    return prove


def test_receiver_accepts_exactly_the_good_next_frames(formal, tmp_path):
    """About 3 minutes on the shared 2-core machine."""
    result = formal(ReceiverSpec(), name="receiver", mode="bmc", depth=DEPTH, workdir=tmp_path, script=SCRIPT)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


def test_reachable(formal, tmp_path):
    """Not vacuous: within the bound a frame is accepted and its payload byte leaves."""
    result = formal(ReceiverSpec(), name="receiver_cover", mode="cover", depth=DEPTH, workdir=tmp_path, script=SCRIPT)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


@pytest.mark.parametrize("wrong", [{"algorithm": crc.catalog.CRC32_CASTAGNOLI},
                                   pytest.param({"check_seq": False}, marks=pytest.mark.slow)],
                         ids=["crc32c", "no_seq"])          # no_seq: about 4 minutes to its counterexample
def test_proof_fails_against_a_wrong_reference(formal, tmp_path, wrong):
    result = formal(ReceiverSpec(**wrong), name="receiver_wrong", mode="bmc", depth=DEPTH, workdir=tmp_path,
                    script=SCRIPT)
    assert result.status == "FAIL", result.log[-2000:]
