"""Formal proofs of the board's frame receiver (blockray.rtl.framing.FrameReceiver; and, bounded
and slow, of its sender, FrameSender: SenderSpec below) with
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
from amaranth.hdl import Array, Assert, Assume, Cover, Elaboratable, Module, Mux, Signal
from amaranth.lib import crc

from blockray.rtl.framing import FrameReceiver, FrameSender

pytestmark = pytest.mark.synth

DEPTH = 13
#: frames of at most 12 decoded bytes (up to 4 payload bytes): a 16-byte memory for the solver
MAX_BODY = 12


class _Unstuffed:
    """The reference's COBS decoder of the wire bytes ``byte`` taken on ``take``: stuffed bytes
    in the chunk (``raw``), decoded bytes (``count``; ``out``/``out_byte``: one this cycle), the
    block state (``code``, ``zero``) and the header fields and first payload byte. The caller
    clears ``raw``, ``count``, ``code`` and ``zero`` at a delimiter."""

    def __init__(self, m, take, byte):
        self.raw, self.count, self.code, self.zero = Signal(9), Signal(9), Signal(8), Signal()
        self.flags, self.seq, self.length, self.first = Signal(8), Signal(8), Signal(8), Signal(8)
        self.out, self.out_byte = Signal(), Signal(8)
        with m.If(take & (byte != 0)):
            m.d.sync += self.raw.eq(self.raw + (self.raw != 511))
            with m.If(self.code == 0):
                m.d.comb += [self.out.eq(self.zero), self.out_byte.eq(0)]
                m.d.sync += [self.code.eq(byte - 1), self.zero.eq(byte != 0xFF)]
            with m.Else():
                m.d.comb += [self.out.eq(1), self.out_byte.eq(byte)]
                m.d.sync += self.code.eq(self.code - 1)
        with m.If(self.out):
            m.d.sync += self.count.eq(self.count + (self.count != 511))
            for k, field in ((0, self.flags), (1, self.seq), (3, self.length), (4, self.first)):
                with m.If(self.count == k):
                    m.d.sync += field.eq(self.out_byte)


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
        ref = _Unstuffed(m, take, byte)
        raw, count, code, zero, out, out_byte = ref.raw, ref.count, ref.code, ref.zero, ref.out, ref.out_byte
        flags, seq, length, first = ref.flags, ref.seq, ref.length, ref.first
        m.d.comb += [ref_crc.data.eq(out_byte), ref_crc.valid.eq(out)]

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


@pytest.mark.slow      # minutes; the default suite keeps its covers and must-fail mutants
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


# -- the sender ------------------------------------------------------------------------------------

SENDER_PAYLOAD, SENDER_WINDOW = 1, 2
#: a new data frame of one payload byte is built, stuffed and sent within it
SENDER_DEPTH = 23
#: result bytes the reference remembers (more than the window holds)
SHADOW = 8


class SenderSpec(Elaboratable):
    """The board's frame sender (FrameSender) against a reference: the core's results, the UART's
    ``ready``, the receiver's news (acknowledgements, RESEND, NAKs, status requests) and the
    counters are free, but for one rule: the host acknowledges only frames it received whole.
    At every delimiter: the frame's stuffing is complete, it has its header, its length field is
    its payload's size (at most the frame's payload; 6 for a status frame); a data frame carries
    the next new number or one of the window's before it (a resend); and a new frame's payload
    is the next bytes taken from ``results``, none skipped or repeated. (The CRC of the sender's
    frames is checked by the host's Endpoint in tests/test_framing_rtl.py's loopback; with the
    CRC residue here the solver did not finish step 21 in 10 minutes.) ``skew``: the reference
    expects the result byte that many places later (1: the proof must fail)."""

    def __init__(self, *, skew=0):
        self.skew = skew

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = FrameSender(payload=SENDER_PAYLOAD, window=SENDER_WINDOW)
        for port in (dut.results.valid, dut.results.payload, dut.wire.ready, dut.report, dut.status.expect,
                     dut.status.peer, dut.status.peer_ack, dut.status.peer_resend, dut.status.ack_due,
                     dut.status.nak, dut.status.status_due):
            m.d.comb += port.eq(AnySeq(len(port)))
        shadow = Array(Signal(8, name=f"shadow{k}") for k in range(SHADOW))
        taken = Signal(8)
        with m.If(dut.results.valid & dut.results.ready):
            m.d.sync += [shadow[taken % SHADOW].eq(dut.results.payload), taken.eq(taken + 1)]

        ref = _Unstuffed(m, dut.wire.valid & dut.wire.ready, dut.wire.payload)
        news, emitted = Signal(8), Signal(8)            # new data frames out, their payload bytes
        is_new = (ref.seq == news) & ~ref.flags[1]
        with m.If(ref.out & (ref.count >= 4) & (ref.count < 4 + ref.length) & is_new):
            at = Signal(8)
            m.d.comb += at.eq(emitted + ref.count - 4 + self.skew)
            m.d.comb += [Assert((taken - at)[:8] >= 1), Assert((taken - at)[:8] <= SHADOW),
                         Assert(ref.out_byte == shadow[at % SHADOW])]
        m.d.comb += Assume(~dut.status.peer | ((news - dut.status.peer_ack)[:8] < 128))

        delimiter = dut.wire.valid & dut.wire.ready & (dut.wire.payload == 0)
        data = (ref.length != 0) & ~ref.flags[1]
        behind = Signal(8)
        m.d.comb += behind.eq(news - ref.seq)
        with m.If(delimiter):
            m.d.comb += [Assert(ref.code == 0), Assert(ref.count == ref.length + 8),
                         Assert(Mux(ref.flags[1], ref.length == 6, ref.length <= SENDER_PAYLOAD))]
            with m.If(data & ~is_new):
                m.d.comb += Assert((behind >= 1) & (behind <= SENDER_WINDOW))
            with m.If(data & is_new):
                m.d.sync += [news.eq(news + 1), emitted.eq(emitted + ref.length)]
            m.d.sync += [ref.raw.eq(0), ref.count.eq(0), ref.code.eq(0), ref.zero.eq(0)]
        m.d.comb += Cover(delimiter & data & is_new & (ref.length == SENDER_PAYLOAD))
        return m


SENDER_RUNS = {"proof": (0, "bmc", "PASS"), "cover": (0, "cover", "PASS"), "wrong": (1, "bmc", "FAIL")}


@pytest.mark.slow
@pytest.mark.parametrize("run", SENDER_RUNS)
def test_sender_frames_are_good_numbered_and_carry_the_results(formal, tmp_path, run):
    """proof: the properties hold for SENDER_DEPTH steps; cover: a new data frame leaves whole
    within them (not vacuous); wrong: against a skewed reference sby finds a counterexample."""
    skew, mode, expected = SENDER_RUNS[run]
    result = formal(SenderSpec(skew=skew), name=f"sender_{run}", mode=mode, depth=SENDER_DEPTH, workdir=tmp_path, script=SCRIPT)
    assert result.status == expected, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"
