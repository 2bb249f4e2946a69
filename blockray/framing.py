"""Link integrity: frames with a sequence number, an acknowledgement, a length and a CRC-32, COBS
framed, resent go-back-N. One definition for the host (:mod:`blockray.host_driver.board.framed`) and
the board's side (the model behind ``model-link``; the RTL is to follow it byte for byte).

A frame before stuffing (docs/board-protocol.md, "Link integrity")::

    flags (1) | seq (1) | ack (1) | len (1) | payload (len bytes) | CRC-32 (4, little-endian)

``flags`` bit 0 (:data:`RESEND`): "resend everything from ``ack`` on" (a NAK, or the host's poll
after a time-out). ``flags`` bit 2 (:data:`POLL`), on a frame without payload: "I have sent every
frame before ``seq``; ask again for any you lack"; a sender ends every resend round with one, so a
side asked to resend always answers, and a receiver whose resent frame was hit again asks again
at once. ``flags`` bit 1 (:data:`STATUS`): a link-status frame, never data: with
``len == 0`` it asks the other side for its counters, with a payload it carries them
(:data:`STATUS_FIELDS`, 2 bytes each, little-endian, mod 65536). ``seq``: the frame's number (mod 256) if it carries a payload; a frame with
``len == 0`` is a pure acknowledgement and takes no number. ``ack``: the next frame number the
sender expects from the other side (cumulative). The CRC (CRC-32/ISO-HDLC, ``zlib.crc32``) covers
the first four fields and the payload. On the wire the frame is COBS-stuffed (no zero bytes)
and ends with a zero byte, so a receiver resynchronises at the next zero after any garbage.

Both directions are the same protocol (:class:`Endpoint`). A receiver accepts a frame only with
a good CRC, a matching length and the next sequence number, so no frame is accepted twice or out
of order and a corrupted frame is never delivered; on a gap or a bad frame it sends one NAK until
the gap is filled, and again at a POLL that finds the gap still open or at a RESEND while it is
open (the frame that carried the NAK may be the one lost). A sender keeps at
most ``window`` unacknowledged frames and, on a NAK (or, the host only, on a time-out), sends them
all again, then a POLL. The board never times out: it only answers.
"""

import zlib
from collections import deque
from dataclasses import dataclass

from cobs import cobs

__all__ = ["RESEND", "STATUS", "POLL", "STATUS_FIELDS", "HEADER_BYTES", "CRC_BYTES", "MAX_PAYLOAD", "DELIMITER", "crc32", "encode_frame",
           "parse_frame", "Frame", "FrameError", "FrameSplitter", "Endpoint", "wire_frame_bytes", "LinkConfig",
           "HOST_LINK", "BOARD_LINK"]

RESEND = 0x01
STATUS = 0x02
POLL = 0x04
#: a status frame's payload: these counts of the side that sends it, 2 bytes each
STATUS_FIELDS = ("frames_resent", "errors", "frames_accepted")
HEADER_BYTES = 4
CRC_BYTES = 4
#: a frame's payload at most: header + payload + CRC = 254 bytes, so COBS adds exactly one byte
MAX_PAYLOAD = 254 - HEADER_BYTES - CRC_BYTES
DELIMITER = 0
_SEQ = 256          # sequence numbers are mod 256; a window must stay below half of it


def crc32(data):
    """CRC-32/ISO-HDLC (reflected 0x04C11DB7, init and xorout 0xFFFFFFFF): ``zlib.crc32``."""
    return zlib.crc32(data) & 0xFFFFFFFF


def wire_frame_bytes(payload):
    """Bytes a frame of ``payload`` bytes takes on the wire (COBS code bytes and the delimiter)."""
    body = HEADER_BYTES + payload + CRC_BYTES
    return body + (body + 253) // 254 + 1


@dataclass(frozen=True)
class Frame:
    flags: int
    seq: int
    ack: int
    payload: bytes = b""


class FrameError(ValueError):
    """A received frame is unusable; the message says why (the fault counted in the report)."""

    def __init__(self, kind, message):
        self.kind = kind
        super().__init__(message)


def encode_frame(frame):
    """A :class:`Frame` as its wire bytes (stuffed, delimiter last)."""
    if len(frame.payload) > MAX_PAYLOAD:
        raise ValueError(f"a frame carries at most {MAX_PAYLOAD} bytes, not {len(frame.payload)}")
    body = bytes([frame.flags, frame.seq % _SEQ, frame.ack % _SEQ, len(frame.payload)]) + bytes(frame.payload)
    return cobs.encode(body + crc32(body).to_bytes(CRC_BYTES, "little")) + bytes([DELIMITER])


def parse_frame(stuffed):
    """The :class:`Frame` of one delimited chunk (without its delimiter); :class:`FrameError`
    if it is not one (bad stuffing, too short, wrong length or CRC)."""
    try:
        body = cobs.decode(bytes(stuffed))
    except cobs.DecodeError:
        raise FrameError("stuffing", "a frame with broken byte stuffing") from None
    if len(body) < HEADER_BYTES + CRC_BYTES:
        raise FrameError("short", f"a frame of {len(body)} bytes (at least {HEADER_BYTES + CRC_BYTES})")
    data, crc = body[:-CRC_BYTES], int.from_bytes(body[-CRC_BYTES:], "little")
    if crc32(data) != crc:
        raise FrameError("crc", "a frame with a wrong CRC")
    if data[3] != len(data) - HEADER_BYTES:
        raise FrameError("length", f"a frame whose length field says {data[3]}, with {len(data) - HEADER_BYTES}")
    return Frame(data[0], data[1], data[2], bytes(data[HEADER_BYTES:]))


class FrameSplitter:
    """Cuts a received byte stream at the delimiters; a chunk longer than any frame is garbage,
    dropped up to the next delimiter (so a receiver's buffer stays bounded, as in hardware) and
    given as None there (a bad frame, in its place in the stream)."""

    limit = wire_frame_bytes(MAX_PAYLOAD) - 1

    def __init__(self):
        self._buf = bytearray()
        self._overlong = False

    def feed(self, data):
        """Complete chunks (each a candidate frame, without its delimiter), and the number of
        bytes dropped as overlong."""
        parts = bytes(data).split(bytes([DELIMITER]))
        out, dropped = [], 0
        for k, part in enumerate(parts):
            self._buf += part
            if len(self._buf) > self.limit:
                dropped += len(self._buf)
                self._buf, self._overlong = bytearray(), True
            if k == len(parts) - 1:         # no delimiter after the last part yet
                break
            if self._overlong:
                out.append(None)
            elif self._buf:
                out.append(bytes(self._buf))
            self._buf, self._overlong = bytearray(), False
        return out, dropped

    def clear(self):
        self._buf, self._overlong = bytearray(), False


@dataclass(frozen=True)
class LinkConfig:
    """A direction's sender: ``payload`` bytes per frame at most, ``window`` frames unacknowledged
    at most (below 128, for the mod-256 numbers)."""
    payload: int = MAX_PAYLOAD
    window: int = 8

    def __post_init__(self):
        if not 1 <= self.payload <= MAX_PAYLOAD:
            raise ValueError(f"a frame's payload must be 1 to {MAX_PAYLOAD} bytes, not {self.payload}")
        if not 1 <= self.window < _SEQ // 2:
            raise ValueError(f"the resend window must be 1 to {_SEQ // 2 - 1} frames, not {self.window}")


#: the host's sender: full frames, 8 in flight (8 x 256 wire bytes fit the board's 2048-byte
#: receive FIFO, so a UART byte never finds it full: the window is the credit)
HOST_LINK = LinkConfig(MAX_PAYLOAD, 8)
#: the board's sender: 4 frames of 128 result bytes, a 512-byte replay memory (the result FIFO's size)
BOARD_LINK = LinkConfig(128, 4)


def _ahead(a, b):
    """How far sequence number ``a`` is ahead of ``b`` (mod 256)."""
    return (a - b) % _SEQ


class Endpoint:
    """One side of the link: sends its payload bytes in numbered frames, accepts the other
    side's in order. ``receive(wire)`` returns the payload bytes accepted; ``submit(data)``
    queues bytes to send; ``output()`` gives the wire bytes to send now; ``rewind()`` resends
    every unacknowledged frame (a time-out). ``counts``: faults seen and frames (re)sent."""

    def __init__(self, config):
        self.config = config
        self.reset()

    def reset(self):
        self._splitter = FrameSplitter()
        self.expect = 0                 # next sequence number accepted from the other side
        self.base = 0                   # oldest unacknowledged frame we sent
        self.next = 0                   # next new frame's number
        self._unacked = deque()         # payloads of base .. next - 1
        self._queue = bytearray()       # bytes not yet in a frame
        self._resend = False            # resend every unacknowledged frame (a NAK or a time-out)
        self._ask_resend = False        # our next frame asks the other side to resend
        self._nak_sent = False
        self._ack_due = False
        self._status_due = False        # the other side asked for our counters
        self._ask_status = False        # our next frame asks the other side for its counters
        self.peer_status = None         # the other side's counters (STATUS_FIELDS), when they came
        self.counts = {"frames_sent": 0, "frames_resent": 0, "frames_accepted": 0, "naks_sent": 0,
                       "crc": 0, "length": 0, "stuffing": 0, "short": 0, "garbage_bytes": 0,
                       "out_of_order": 0, "discarded": 0, "duplicate": 0,
                       "timeouts": 0}
        self.last_fault = None

    @property
    def pending(self):
        """Whether we have bytes or frames the other side has not acknowledged."""
        return bool(self._queue or self._unacked)

    def submit(self, data):
        self._queue += data

    def _fault(self, kind, message):
        self.counts[kind] += 1
        self.last_fault = message

    def receive(self, wire):
        """Accept what arrived; returns the payload bytes of the frames accepted, in order."""
        chunks, dropped = self._splitter.feed(wire)
        self.counts["garbage_bytes"] += dropped
        out = bytearray()
        for chunk in chunks:
            try:
                if chunk is None:
                    raise FrameError("length", f"more than {FrameSplitter.limit} bytes without a frame delimiter")
                frame = parse_frame(chunk)
            except FrameError as e:
                self._fault(e.kind, str(e))
                self._nak()
                continue
            naked = self._nak_sent
            self._take_ack(frame)
            if frame.flags & STATUS:
                self._take_status(frame)
            elif frame.payload:
                out += self._take_data(frame)
            if self._asks_again(frame, naked):
                self._nak_sent = False
                self._nak()
        return bytes(out)

    def _asks_again(self, frame, naked):
        """Whether a good frame shows that the NAK already sent for the open gap did not help: a
        POLL numbered past the gap (the resend round is over and missed it again), or a RESEND
        while the gap stays open (the frame that carried our NAK may be the one lost). No new
        error: the loss was counted as it happened."""
        poll_gap = (frame.flags & POLL and not frame.payload and not frame.flags & STATUS
                    and 0 < _ahead(frame.seq, self.expect) < _SEQ // 2)
        return bool(poll_gap or (frame.flags & RESEND and naked and self._nak_sent))

    def _take_ack(self, frame):
        acked = _ahead(frame.ack, self.base)
        if acked <= len(self._unacked):             # else an impossible ack: ignore it
            for _ in range(acked):
                self._unacked.popleft()
            self.base = frame.ack
        if frame.flags & RESEND:
            self._resend = self._ack_due = True
            self.last_fault = "the other side asked for a resend (it received a corrupted frame or missed one)"

    def _take_status(self, frame):
        if not frame.payload:
            self._status_due = True
        elif len(frame.payload) == 2 * len(STATUS_FIELDS):
            p = frame.payload
            self.peer_status = {k: int.from_bytes(p[2 * i:2 * i + 2], "little") for i, k in enumerate(STATUS_FIELDS)}

    def status(self):
        """Our counters as a status frame carries them (:data:`STATUS_FIELDS`, mod 65536)."""
        c = self.counts
        values = (c["frames_resent"], self.faults(), c["frames_accepted"])
        return b"".join((v & 0xFFFF).to_bytes(2, "little") for v in values)

    def request_status(self):
        """Ask the other side for its counters (they come as :attr:`peer_status`)."""
        self._ask_status = True
        self.peer_status = None

    def _take_data(self, frame):
        gap = _ahead(frame.seq, self.expect)
        if gap == 0:
            self.expect = (self.expect + 1) % _SEQ
            self.counts["frames_accepted"] += 1
            self._nak_sent, self._ack_due = False, True
            return frame.payload
        if gap < _SEQ // 2:                         # a gap: frames were lost (one error per gap)
            if not self._nak_sent:
                self._fault("out_of_order", f"frame {frame.seq} where {self.expect} was due")
            self.counts["discarded"] += 1
            self._nak()
        else:                                       # one we accepted before: acknowledge again
            self.counts["duplicate"] += 1
            self._ack_due = True
        return b""

    def _nak(self):
        if not self._nak_sent:
            self._nak_sent = self._ask_resend = True
            self.counts["naks_sent"] += 1

    def rewind(self):
        """A time-out: resend the unacknowledged frames, and ask the other side to resend its own."""
        self._resend = self._ask_resend = True
        self.counts["timeouts"] += 1

    def output(self):
        """Wire bytes to send now: resent frames and a POLL after them, new frames within the
        window, else (if owed) one acknowledgement."""
        out = bytearray()
        if self._resend:
            for k, payload in enumerate(self._unacked):
                out += self._frame((self.base + k) % _SEQ, payload)
                self.counts["frames_resent"] += 1
            out += self._frame(self.next, b"", POLL)
            self._resend = False
        cfg = self.config
        while self._queue and len(self._unacked) < cfg.window:
            payload = bytes(self._queue[:cfg.payload])
            del self._queue[:cfg.payload]
            self._unacked.append(payload)
            out += self._frame(self.next, payload)
            self.next = (self.next + 1) % _SEQ
            self.counts["frames_sent"] += 1
        if self._status_due:
            out += self._frame(self.next, self.status(), STATUS)
            self._status_due = False
        if self._ask_status:
            out += self._frame(self.next, b"", STATUS)
            self._ask_status = False
        if not out and (self._ack_due or self._ask_resend):
            out += self._frame(self.next, b"")
        return bytes(out)

    def _frame(self, seq, payload, flags=0):
        flags |= RESEND if self._ask_resend else 0
        self._ask_resend = self._ack_due = False
        return encode_frame(Frame(flags, seq, self.expect, payload))

    def faults(self):
        """Frames received unusable or out of order (the report's ``errors``)."""
        c = self.counts
        return c["crc"] + c["length"] + c["stuffing"] + c["short"] + c["out_of_order"]
