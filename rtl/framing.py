"""The board's receiving half of the framed link (:mod:`blockray.framing`): stuffed wire bytes
in, the payload of every accepted frame out to the core, and what the sender needs to know.

::

    wire (from the receive FIFO) --> COBS decode --> frame memory + CRC-32 --(delimiter)--> check
                                                                        |
                       payload (to the core) <-- Emit <-- accepted -----+--> peer / ack_due / nak

A frame's bytes go into a 256-byte memory while their CRC is computed
(:class:`amaranth.lib.crc.Processor`, CRC32_ETHERNET = ``zlib.crc32``); nothing leaves before the
delimiter, when the frame is accepted only if its stuffing, size (at most 255 stuffed bytes, as
:class:`~blockray.framing.FrameSplitter`), CRC residue and length field are good and it carries
the next sequence number. Then its payload is read out of the memory to ``payload``. The
decisions are :class:`~blockray.framing.Endpoint.receive`'s, in the same order (tests compare
them byte for byte): a good frame reports its ``ack`` and RESEND flag on ``peer``; an accepted or
duplicate one raises ``ack_due``; a gap or a bad frame raises ``nak`` once until the next frame
is accepted.

While a payload leaves, ``wire.ready`` is low: the receive FIFO in front absorbs the UART (the
host's window, 8 frames of 256 wire bytes, is the FIFO's 2048 bytes).
"""

import operator

from amaranth.hdl import Module, Signal
from amaranth.lib import crc, stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from ..framing import CRC_BYTES, FrameSplitter, HEADER_BYTES

__all__ = ["FrameReceiver"]

_BODY_MAX = FrameSplitter.limit - 1     # header + payload + CRC: 254 bytes, one COBS block


class FrameReceiver(wiring.Component):
    """See the module docstring. Ports: ``wire`` (In, stuffed bytes), ``payload`` (Out, accepted
    bytes), ``expect`` (the next sequence number accepted), one-cycle strobes ``peer`` (a good
    frame: ``peer_ack`` and ``peer_resend`` hold its fields), ``ack_due``, ``nak``, ``accept``
    (a frame accepted), ``error`` (a bad frame or a gap); ``frames`` / ``errors``: counts."""

    wire: In(stream.Signature(8))
    payload: Out(stream.Signature(8))
    expect: Out(8)
    peer: Out(1)
    peer_ack: Out(8)
    peer_resend: Out(1)
    ack_due: Out(1)
    nak: Out(1)
    accept: Out(1)
    error: Out(1)
    frames: Out(16)
    errors: Out(16)

    def __init__(self, *, max_body=_BODY_MAX):
        """``max_body``: the longest frame (header, payload, CRC) in decoded bytes; a chunk of
        more than ``max_body + 1`` stuffed bytes is refused. The protocol's is 254; the formal
        proofs use shorter ones (a smaller memory)."""
        max_body = operator.index(max_body)
        if not HEADER_BYTES + CRC_BYTES <= max_body <= _BODY_MAX:
            raise ValueError(f"a frame's body must be {HEADER_BYTES + CRC_BYTES} to {_BODY_MAX} bytes, not {max_body}")
        self._max_body = max_body
        self._crc = crc.catalog.CRC32_ETHERNET(data_width=8).create()
        super().__init__()

    @property
    def max_body(self):
        return self._max_body

    @property
    def crc(self):
        """The CRC-32 unit over the decoded bytes (the formal proofs compare its register)."""
        return self._crc

    def elaborate(self, platform):
        m = Module()
        body_max, raw_max = self._max_body, self._max_body + 1
        m.submodules.mem = mem = Memory(shape=8, depth=1 << ceil_log2(body_max + 1), init=[])
        wr, rd = mem.write_port(), mem.read_port(domain="comb")
        m.submodules.crc = check = self._crc

        raw = Signal(range(raw_max + 2))                # stuffed bytes of this chunk (saturating)
        count = Signal(range(body_max + 1))             # decoded bytes in the memory
        code_left = Signal(8)                           # bytes left in the COBS block
        zero_due = Signal()                             # the block ends in a zero, unless the frame ends
        header = [Signal(8, name=f"header{k}") for k in range(HEADER_BYTES)]
        flags, seq, ack, length = header              # flags bit 0: RESEND
        nak_sent = Signal()
        addr, left = Signal(range(body_max + 1)), Signal(8)

        put, put_data = Signal(), Signal(8)
        m.d.comb += [wr.addr.eq(count), wr.data.eq(put_data), wr.en.eq(put & (count < body_max)),
                     check.data.eq(put_data), check.valid.eq(put), rd.addr.eq(addr)]
        with m.If(put & (count < body_max)):
            m.d.sync += count.eq(count + 1)
            for k, field in enumerate(header):
                with m.If(count == k):
                    m.d.sync += field.eq(put_data)

        def restart():
            m.d.sync += [raw.eq(0), count.eq(0), code_left.eq(0), zero_due.eq(0)]
            m.d.comb += check.start.eq(1)

        def raise_nak():
            with m.If(~nak_sent):
                m.d.comb += self.nak.eq(1)
                m.d.sync += nak_sent.eq(1)

        m.d.comb += [self.payload.payload.eq(rd.data), self.peer_ack.eq(ack), self.peer_resend.eq(flags[0])]
        with m.If(self.error):
            m.d.sync += self.errors.eq(self.errors + 1)
        with m.If(self.accept):
            m.d.sync += self.frames.eq(self.frames + 1)

        with m.FSM(init="Collect"):
            with m.State("Collect"):
                m.d.comb += self.wire.ready.eq(1)
                byte = self.wire.payload
                with m.If(self.wire.valid & (byte == 0)):
                    with m.If(raw != 0):
                        m.next = "Check"
                with m.Elif(self.wire.valid):
                    with m.If(raw <= raw_max):
                        m.d.sync += raw.eq(raw + 1)
                    with m.If(code_left == 0):                  # a code byte
                        m.d.comb += [put.eq(zero_due), put_data.eq(0)]
                        m.d.sync += [code_left.eq(byte - 1), zero_due.eq(byte != 0xFF)]
                    with m.Else():
                        m.d.comb += [put.eq(1), put_data.eq(byte)]
                        m.d.sync += code_left.eq(code_left - 1)
            with m.State("Check"):
                self._check(m, raw <= raw_max, count, code_left, check, seq, length, nak_sent, addr, left, raise_nak)
                restart()
            with m.State("Emit"):
                m.d.comb += self.payload.valid.eq(1)
                with m.If(self.payload.ready):
                    m.d.sync += [addr.eq(addr + 1), left.eq(left - 1)]
                    with m.If(left == 1):
                        m.next = "Collect"
        return m

    def _check(self, m, fits, count, code_left, check, seq, length, nak_sent, addr, left, raise_nak):
        """The frame is complete: accept it, acknowledge a duplicate, or ask for a resend."""
        good = Signal()
        m.d.comb += good.eq(fits & (code_left == 0) & (count >= HEADER_BYTES + CRC_BYTES)
                            & check.match_detected & (length == count - HEADER_BYTES - CRC_BYTES))
        gap = Signal(8)
        m.d.comb += gap.eq(seq - self.expect)
        m.next = "Collect"
        with m.If(~good):
            m.d.comb += self.error.eq(1)
            raise_nak()
        with m.Else():
            m.d.comb += self.peer.eq(1)
            with m.If(length == 0):
                pass                                            # a pure acknowledgement
            with m.Elif(gap == 0):
                m.d.comb += [self.accept.eq(1), self.ack_due.eq(1)]
                m.d.sync += [self.expect.eq(self.expect + 1), nak_sent.eq(0), addr.eq(HEADER_BYTES), left.eq(length)]
                m.next = "Emit"
            with m.Elif(gap < 128):                             # frames were lost
                with m.If(~nak_sent):
                    m.d.comb += self.error.eq(1)
                raise_nak()
            with m.Else():                                      # one accepted before
                m.d.comb += self.ack_due.eq(1)
