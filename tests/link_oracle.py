"""What the faults injected on a framed link imply, derived from the bytes alone (imported as
``link_oracle``; it shares no code with blockray.framing, whose receivers it checks).

A fault injector with ``record`` keeps, per direction, the bytes it was given (``given``: what
the sender sent) and gave (``gave``: what the receiver got). Frames end at zero bytes. Every
chunk the receiver got that is no chunk the sender sent is a corrupted frame: the receiver
counts it as one error (its CRC, stuffing or length fails; a CRC-32 collision aside). Every
frame the sender sent for the first time that did not arrive intact must be sent again.
"""

from difflib import SequenceMatcher


def chunks(stream):
    """The non-empty, delimited chunks of ``stream`` (a trailing unterminated part is not one)."""
    return [c for c in bytes(stream).split(b"\x00")[:-1] if c]


def unstuff(chunk):
    """COBS decoding of one chunk (None if the stuffing is broken)."""
    out, i = bytearray(), 0
    while i < len(chunk):
        code = chunk[i]
        if code == 0 or i + code > len(chunk):
            return None
        out += chunk[i + 1:i + code]
        i += code
        if code < 0xFF and i < len(chunk):
            out.append(0)
    return bytes(out)


def corrupted(injector):
    """Chunks the receiver got that the sender never sent: its errors, exactly."""
    sent = set(chunks(injector.given))
    return sum(c not in sent for c in chunks(injector.gave))


def first_sends_hit(injector):
    """Data frames (a payload, no status flag) the sender sent for the first time that a fault
    hit (aligned chunk by chunk with what arrived): each must have been resent at least once."""
    sent, got = chunks(injector.given), chunks(injector.gave)
    hit = set()
    for op, i1, i2, _, _ in SequenceMatcher(None, sent, got, autojunk=False).get_opcodes():
        if op in ("replace", "delete"):
            hit.update(range(i1, i2))
    count, new = 0, 0
    for i, chunk in enumerate(sent):
        body = unstuff(chunk)
        flags, seq, length = body[0], body[1], body[3]
        if length and not flags & 0x02 and seq == new:
            new = (new + 1) % 256
            count += i in hit
    return count


def check_direction(injector, *, errors, resent, where):
    """The receiver's ``errors`` equal the corrupted chunks, the sender resent at least every
    first send that was hit; returns (corrupted, first sends hit) for the caller's own checks."""
    bad, hit = corrupted(injector), first_sends_hit(injector)
    print(where, "corrupted", bad, "errors", errors, "first sends hit", hit, "resent", resent)
    assert errors == bad, where
    assert resent >= hit, where
    return bad, hit


class Planted:
    """A planted fault pattern in place of a rate (a :class:`FaultInjector`'s interface: called on
    the bytes of one direction; ``counts``, ``given``, ``gave``, ``restart``): the data frame
    numbered ``seq`` has one bit of its last byte flipped the first ``times`` times it passes, so
    with ``times`` 2 its resend is hit again. Nothing else is touched; a chunk is passed on when its
    delimiter has come (the wire only delays it)."""

    def __init__(self, seq, times=2):
        self.seq, self.left = seq, times
        self.counts = {"flipped": 0, "dropped": 0, "duplicated": 0}
        self.restart()

    def restart(self):
        self.given, self.gave, self._tail = bytearray(), bytearray(), bytearray()

    def __call__(self, data):
        self._tail += data
        *whole, tail = bytes(self._tail).split(b"\x00")
        self._tail = bytearray(tail)
        out = bytearray()
        for chunk in whole:
            self.given += chunk + b"\x00"
            body = unstuff(chunk) if chunk else None
            if body and len(body) >= 4 and body[3] and not body[0] & 0x02 and body[1] == self.seq and self.left:
                self.left -= 1
                self.counts["flipped"] += 1
                chunk = chunk[:-1] + bytes([chunk[-1] ^ (1 if chunk[-1] != 1 else 2)])
            out += chunk + b"\x00"
        self.gave += out
        return bytes(out)
