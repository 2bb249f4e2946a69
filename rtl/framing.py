"""The framed link (:mod:`blockray.framing`) in gateware: :class:`FrameReceiver` (stuffed wire
bytes in, the payload of every accepted frame out to the core, and what the sender needs to
know), :class:`FrameSender` (the core's results out in numbered, checked, stuffed frames, resent
go-back-N) and :class:`FramedBridge` (both, with the FIFOs, between a UART and a core).

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
is accepted, and again at a POLL numbered past ``expect`` (the sender's resend round is over
and a frame is still missing) or a RESEND while the gap is open (the NAK may have been lost).

While a payload leaves, ``wire.ready`` is low: the receive FIFO in front absorbs the UART (the
host's window, 8 frames of 256 wire bytes, is the FIFO's 2048 bytes).
"""

import operator

from amaranth.hdl import Array, Cat, Module, Mux, Signal
from amaranth.lib import crc, stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from ..framing import CRC_BYTES, FrameSplitter, HEADER_BYTES, POLL, RESEND, STATUS, STATUS_FIELDS

__all__ = ["LinkStatus", "FrameReceiver", "FrameSender", "FramedBridge", "COMMAND_DEPTH", "FRAME_MEMORY"]

_BODY_MAX = FrameSplitter.limit - 1     # header + payload + CRC: 254 bytes, one COBS block
#: accepted payload bytes waiting for the core: two frames
COMMAND_DEPTH = 512
#: the receiver's frame memory and the sender's stuffed frame, in bytes
FRAME_MEMORY = 256

#: what the receiver tells the sender: the next number it accepts (the sender's ``ack``) and, as
#: one-cycle strobes, a good frame (``peer``: its ``peer_ack`` and RESEND flag), an
#: acknowledgement owed, a NAK owed, a status frame asked for
LinkStatus = wiring.Signature({"expect": Out(8), "peer": Out(1), "peer_ack": Out(8), "peer_resend": Out(1),
                               "ack_due": Out(1), "nak": Out(1), "status_due": Out(1)})
#: a status frame's payload bytes (STATUS_FIELDS, 2 bytes each)
_STATUS_BYTES = 2 * len(STATUS_FIELDS)


class FrameReceiver(wiring.Component):
    """See the module docstring. Ports: ``wire`` (In, stuffed bytes), ``payload`` (Out, accepted
    bytes), ``space`` (In: bytes ``payload``'s consumer can take at once; a frame with more is not
    accepted, so a payload never waits and the frames behind it, the host's acknowledgements
    among them, are never held up. A refusal is flow control, not a fault: no error, no NAK for
    it or the gap behind it, and one NAK when ``space`` has room for it again, so the host
    resends once the core has drained, not into a full FIFO), ``status`` (Out, :data:`LinkStatus`:
    ``expect``, the next sequence number accepted, and the strobes), ``accept``
    (a frame accepted), ``error`` (a bad frame, or a gap not caused by a frame refused for
    space: :meth:`Endpoint.faults`); ``frames`` / ``errors``: counts."""

    wire: In(stream.Signature(8))
    payload: Out(stream.Signature(8))
    status: Out(LinkStatus)
    accept: Out(1)
    error: Out(1)
    frames: Out(16)
    errors: Out(16)
    space: In(8, init=255)

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
        refused = Signal()                              # a frame was refused for space: its gap is no fault
        refused_length, resumed = Signal(8), Signal()   # its length; the NAK for it sent (room again)
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
                m.d.comb += self.status.nak.eq(1)
                m.d.sync += nak_sent.eq(1)

        m.d.comb += [self.payload.payload.eq(rd.data), self.status.peer_ack.eq(ack),
                     self.status.peer_resend.eq(flags[0])]
        with m.If(self.error):
            m.d.sync += self.errors.eq(self.errors + 1)
        with m.If(self.accept):
            m.d.sync += self.frames.eq(self.frames + 1)

        # room again for the frame refused: ask for it now (before the FSM: a refusal there wins)
        with m.If(refused & ~resumed & (self.space >= refused_length) & ~self.accept):
            m.d.comb += self.status.nak.eq(1)
            m.d.sync += [resumed.eq(1), nak_sent.eq(1)]

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
                self._check(m, raw <= raw_max, count, code_left, check, flags, seq, length, nak_sent,
                            (refused, refused_length, resumed), addr, left, raise_nak)
                restart()
            with m.State("Emit"):
                m.d.comb += self.payload.valid.eq(1)
                with m.If(self.payload.ready):
                    m.d.sync += [addr.eq(addr + 1), left.eq(left - 1)]
                    with m.If(left == 1):
                        m.next = "Collect"
        return m

    def _check(self, m, fits, count, code_left, check, flags, seq, length, nak_sent, refusal, addr, left, raise_nak):
        """The frame is complete: accept it, acknowledge a duplicate, refuse it for want of room, or
        ask for a resend. ``refusal``: (refused, its length, resumed)."""
        refused, refused_length, resumed = refusal
        good = Signal()
        m.d.comb += good.eq(fits & (code_left == 0) & (count >= HEADER_BYTES + CRC_BYTES)
                            & check.match_detected & (length == count - HEADER_BYTES - CRC_BYTES))
        gap = Signal(8)
        m.d.comb += gap.eq(seq - self.status.expect)
        m.next = "Collect"
        with m.If(~good):
            m.d.comb += self.error.eq(1)
            raise_nak()
        with m.Else():
            m.d.comb += self.status.peer.eq(1)
            with m.If(flags[1]):                                # STATUS: never data
                m.d.comb += self.status.status_due.eq(length == 0)
            with m.Elif(length == 0):
                pass                                            # a pure acknowledgement
            with m.Elif((gap == 0) & (length > self.space)):
                # no room behind: not accepted, so never blocking the acknowledgements behind it
                m.d.sync += [refused.eq(1), refused_length.eq(length), resumed.eq(0)]
            with m.Elif(gap == 0):
                m.d.comb += [self.accept.eq(1), self.status.ack_due.eq(1)]
                m.d.sync += [self.status.expect.eq(self.status.expect + 1), nak_sent.eq(0), refused.eq(0),
                             addr.eq(HEADER_BYTES), left.eq(length)]
                m.next = "Emit"
            with m.Elif(gap < 128):                             # frames were lost (or refused: wait for room)
                with m.If(~refused):
                    with m.If(~nak_sent):
                        m.d.comb += self.error.eq(1)
                    raise_nak()
            with m.Else():                                      # one accepted before
                m.d.comb += self.status.ack_due.eq(1)
            # the NAK sent did not help: a POLL past the gap (the resend round missed it again) or a
            # RESEND while it stays open (our NAK may have gone with the frame lost): NAK again. Not
            # while a frame waits for room: a resend now would find the FIFO full again
            poll_gap = flags[2] & ~flags[1] & (length == 0) & (gap != 0) & (gap < 128)
            with m.If((poll_gap | (flags[0] & nak_sent & ~self.accept)) & ~refused):
                m.d.comb += self.status.nak.eq(1)
                m.d.sync += nak_sent.eq(1)


class FrameSender(wiring.Component):
    """The board's sending half of the framed link: the core's result bytes in numbered frames
    of at most ``payload`` bytes, at most ``window`` unacknowledged (a replay memory of
    ``payload * window`` bytes), acknowledging with the receiver's ``expect``; CRC-32 appended,
    COBS-stuffed, a delimiter after each (:class:`~blockray.framing.Endpoint.output`'s frames).

    Ports: ``results`` (In, from the core; taken while the open frame has room and the window a
    free slot), ``wire`` (Out, stuffed bytes to the UART), ``status`` (In, :data:`LinkStatus`,
    from a :class:`FrameReceiver`), ``resent`` (frames sent again), ``report`` (the counters a
    status frame carries, :data:`~blockray.framing.STATUS_FIELDS` from bit 0 up, 16 bits each).
    A frame leaves when the transmitter is free, in :meth:`Endpoint.output`'s order: the
    unacknowledged frames again after a RESEND and a POLL after them, else the open frame if it holds a byte, else a
    status frame if one was asked for, else a pure acknowledgement (or NAK) if one is due. A
    RESEND asks for an acknowledgement too, so the host's poll is always answered."""

    results: In(stream.Signature(8))
    wire: Out(stream.Signature(8))
    status: In(LinkStatus)
    resent: Out(16)
    report: In(16 * len(STATUS_FIELDS))

    def __init__(self, *, payload=128, window=4):
        for name, value, low, high in (("payload", payload, 1, _BODY_MAX - HEADER_BYTES - CRC_BYTES - 1),
                                       ("window", window, 1, 127)):
            if not low <= operator.index(value) <= high or (name == "window" and value & (value - 1)):
                raise ValueError(f"frame sender {name} must be {low} to {high}"
                                 f"{' and a power of two' if name == 'window' else ''}, not {value}")
        self._payload, self._window = payload, window
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        P, W = self._payload, self._window
        m.submodules.replay = replay = Memory(shape=8, depth=P * W, init=[])
        m.submodules.encoded = encoded = Memory(shape=8, depth=FRAME_MEMORY, init=[])
        m.submodules.crc = check = crc.catalog.CRC32_ETHERNET(data_width=8).create()
        fill_w, replay_r = replay.write_port(), replay.read_port(domain="comb")
        enc_w, enc_r = encoded.write_port(), encoded.read_port(domain="comb")

        slot_bits = max(1, ceil_log2(W))
        lens = Array(Signal(range(P + 1), name=f"len{k}") for k in range(W))
        base, nxt = Signal(8), Signal(8)
        in_flight = Signal(8)
        m.d.comb += in_flight.eq(nxt - base)
        open_slot = Signal(slot_bits)
        m.d.comb += open_slot.eq(nxt % W)
        open_len = lens[open_slot]
        resend, ask_resend, ack_owed = Signal(), Signal(), Signal()
        self._status_owed = Signal()

        # the core's bytes fill the open frame while the window has its slot
        fill = Signal()
        m.d.comb += [self.results.ready.eq((in_flight < W) & (open_len < P)),
                     fill.eq(self.results.valid & self.results.ready),
                     fill_w.data.eq(self.results.payload), fill_w.addr.eq(open_slot * P + open_len),
                     fill_w.en.eq(fill)]
        with m.If(fill):
            m.d.sync += open_len.eq(open_len + 1)
        self._acknowledgements(m, W, slot_bits, lens, base, in_flight, resend, ask_resend, ack_owed)
        self._frames(m, P, W, lens, base, nxt, in_flight, open_len, resend, ask_resend, ack_owed,
                     replay_r, enc_w, enc_r, check)
        return m

    def _acknowledgements(self, m, W, slot_bits, lens, base, in_flight, resend, ask_resend, ack_owed):
        """The receiver's news: release acknowledged frames (their slots emptied), note a RESEND,
        an acknowledgement or a NAK owed."""
        acked = Signal(8)
        m.d.comb += acked.eq(self.status.peer_ack - base)
        with m.If(self.status.peer & (acked <= in_flight)):     # else an impossible ack: ignored
            m.d.sync += base.eq(self.status.peer_ack)
            for k in range(W):
                with m.If((k - base)[:slot_bits] % W < acked):
                    m.d.sync += lens[k].eq(0)
        with m.If(self.status.peer & self.status.peer_resend):
            m.d.sync += [resend.eq(1), ack_owed.eq(1)]
        with m.If(self.status.nak):
            m.d.sync += ask_resend.eq(1)
        with m.If(self.status.ack_due):
            m.d.sync += ack_owed.eq(1)
        with m.If(self.status.status_due):
            m.d.sync += self._status_owed.eq(1)

    def _frames(self, m, P, W, lens, base, nxt, in_flight, open_len, resend, ask_resend, ack_owed,
                replay_r, enc_w, enc_r, check):
        """Choose a frame, build its body into the stuffed buffer (COBS by back-patching each
        block's code byte), send it and its delimiter."""
        cursor, resending, seq, length = Signal(8), Signal(), Signal(8), Signal(8)
        flags, ack = Signal(8), Signal(8)
        is_status, report = Signal(), Signal.like(self.report)
        status_owed = self._status_owed
        idx = Signal(9)                         # body byte being built
        wp, code_pos, rd = Signal(8), Signal(8), Signal(8)
        body = Signal(8)
        crc_at = length + HEADER_BYTES
        with m.FSM(init="Choose"):
            with m.State("Choose"):
                off = Signal(8)
                m.d.comb += off.eq(cursor - base)
                start, report_start, poll_start = Signal(), Signal(), Signal()
                with m.If(resend):
                    m.d.sync += [cursor.eq(base), resending.eq(1), resend.eq(0)]
                with m.Elif(resending & (off >= 128)):          # acknowledged meanwhile
                    m.d.sync += cursor.eq(base)
                with m.Elif(resending & (off < in_flight)):
                    m.d.sync += [seq.eq(cursor), cursor.eq(cursor + 1), length.eq(lens[cursor % W]),
                                 self.resent.eq(self.resent + 1)]
                    m.d.comb += start.eq(1)
                with m.Elif(resending):                         # the round ends with a POLL
                    m.d.sync += [resending.eq(0), seq.eq(nxt), length.eq(0)]
                    m.d.comb += [start.eq(1), poll_start.eq(1)]
                with m.Elif((open_len != 0) & (in_flight < W)):
                    m.d.sync += [seq.eq(nxt), nxt.eq(nxt + 1), length.eq(open_len + (self.results.valid &
                                                                                        self.results.ready))]
                    m.d.comb += start.eq(1)
                with m.Elif(status_owed):
                    m.d.sync += [seq.eq(nxt), length.eq(_STATUS_BYTES), status_owed.eq(0), report.eq(self.report)]
                    m.d.comb += [start.eq(1), report_start.eq(1)]
                with m.Elif(ack_owed | ask_resend):
                    m.d.sync += [seq.eq(nxt), length.eq(0)]
                    m.d.comb += start.eq(1)
                with m.If(start):
                    m.d.sync += [flags.eq(Mux(ask_resend, RESEND, 0) | Mux(report_start, STATUS, 0)
                                          | Mux(poll_start, POLL, 0)),
                                 is_status.eq(report_start), ack.eq(self.status.expect), ask_resend.eq(0),
                                 ack_owed.eq(0),
                                 idx.eq(0), wp.eq(1), code_pos.eq(0)]
                    m.next = "Build"
            with m.State("Build"):
                with m.Switch(idx):
                    for k, field in enumerate((flags, seq, ack, length)):
                        with m.Case(k):
                            m.d.comb += body.eq(field)
                    with m.Default():
                        m.d.comb += replay_r.addr.eq((seq % W) * P + idx - HEADER_BYTES)
                        with m.If((idx < crc_at) & is_status):
                            m.d.comb += body.eq(report.word_select((idx - HEADER_BYTES)[:3], 8))
                        with m.Elif(idx < crc_at):
                            m.d.comb += body.eq(replay_r.data)
                        with m.Else():
                            m.d.comb += body.eq(check.crc.word_select((idx - crc_at)[:2], 8))
                m.d.comb += [check.data.eq(body), check.valid.eq(idx < crc_at), check.start.eq(idx == 0)]
                with m.If(body == 0):                           # a block ends: patch its code byte
                    m.d.comb += [enc_w.addr.eq(code_pos), enc_w.data.eq(wp - code_pos), enc_w.en.eq(1)]
                    m.d.sync += code_pos.eq(wp)
                with m.Else():
                    m.d.comb += [enc_w.addr.eq(wp), enc_w.data.eq(body), enc_w.en.eq(1)]
                m.d.sync += [wp.eq(wp + 1), idx.eq(idx + 1)]
                with m.If(idx == crc_at + CRC_BYTES - 1):
                    m.next = "Finish"
            with m.State("Finish"):
                m.d.comb += [enc_w.addr.eq(code_pos), enc_w.data.eq(wp - code_pos), enc_w.en.eq(1)]
                m.d.sync += rd.eq(0)
                m.next = "Send"
            with m.State("Send"):
                m.d.comb += [enc_r.addr.eq(rd), self.wire.valid.eq(1), self.wire.payload.eq(enc_r.data)]
                with m.If(self.wire.ready):
                    m.d.sync += rd.eq(rd + 1)
                    with m.If(rd + 1 == wp):
                        m.next = "Delimiter"
            with m.State("Delimiter"):
                m.d.comb += [self.wire.valid.eq(1), self.wire.payload.eq(0)]
                with m.If(self.wire.ready):
                    m.next = "Choose"


class FramedBridge(wiring.Component):
    """The framed link between the UART's byte streams and the core: ``rx_bytes`` -> receive FIFO of
    ``fifo_depth`` bytes -> :class:`FrameReceiver` -> ``commands``; ``results`` ->
    :class:`FrameSender` -> ``tx_bytes``. No credits: the host's window (8 frames of 256 wire
    bytes) fits the FIFO, so a UART byte never finds it full (``overrun`` shows if one did).
    Accepted payloads wait for the core in a 512-byte command FIFO; a frame that does not fit it
    is not accepted, and asked for again once it fits, so the receiver never stalls on a busy
    core and the host never resends into a full FIFO. A status frame
    reports the sender's frames resent and the receiver's errors and frames accepted."""

    rx_bytes: In(stream.Signature(8))
    commands: Out(stream.Signature(8))
    results: In(stream.Signature(8))
    tx_bytes: Out(stream.Signature(8))
    overrun: Out(1)

    def __init__(self, *, fifo_depth=2048, payload=128, window=4):
        fifo_depth = operator.index(fifo_depth)
        if fifo_depth < 4 or fifo_depth & (fifo_depth - 1):
            raise ValueError(f"link fifo_depth must be a power of two, at least 4, not {fifo_depth}")
        self._fifo_depth = fifo_depth
        self.receiver = FrameReceiver()
        self.sender = FrameSender(payload=payload, window=window)
        super().__init__()

    def elaborate(self, platform):
        from amaranth.lib.fifo import SyncFIFOBuffered
        m = Module()
        m.submodules.fifo = fifo = SyncFIFOBuffered(width=8, depth=self._fifo_depth)
        m.submodules.commands = cmd = SyncFIFOBuffered(width=8, depth=COMMAND_DEPTH)
        m.submodules.receiver = rx = self.receiver
        free = COMMAND_DEPTH - cmd.level
        m.d.comb += rx.space.eq(Mux(free > 255, 255, free))
        m.submodules.sender = tx = self.sender
        m.d.comb += [fifo.w_data.eq(self.rx_bytes.payload), fifo.w_en.eq(self.rx_bytes.valid),
                     self.rx_bytes.ready.eq(fifo.w_rdy)]
        with m.If(self.rx_bytes.valid & ~fifo.w_rdy):
            m.d.sync += self.overrun.eq(1)
        wiring.connect(m, fifo=fifo.r_stream, receiver=rx.wire)
        wiring.connect(m, receiver=rx.payload, fifo=cmd.w_stream)
        wiring.connect(m, fifo=cmd.r_stream, core=wiring.flipped(self.commands))
        wiring.connect(m, core=wiring.flipped(self.results), sender=tx.results)
        wiring.connect(m, sender=tx.wire, uart=wiring.flipped(self.tx_bytes))
        wiring.connect(m, receiver=rx.status, sender=tx.status)
        m.d.comb += tx.report.eq(Cat(tx.resent, rx.errors, rx.frames))      # STATUS_FIELDS' order
        return m
