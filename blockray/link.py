"""The serial link's framing: credits for command bytes, frames for result bytes.

A UART cannot be paused: a byte the board has no room for is lost. So the host may send a command
byte only against a **credit**, and the board returns one credit for every command byte its core
takes from the link's command FIFO. The board's byte stream (towards the host) is made of frames,
each starting with a header byte:

``0x00 | (n - 1)``  (n = 1..128)  a **result frame**: n result bytes of the core follow;
``0x80 | (n - 1)``  (n = 1..128)  a **credit grant**: the host may send n more command bytes.

After a reset the board owes the host its whole command FIFO (``fifo_depth`` credits) and grants
them at once, so the host needs no configuration to start: it counts what it is granted. The
host's credits, the bytes on the wire, the FIFO's bytes and the credits the board owes always add
up to ``fifo_depth`` (:mod:`blockray.rtl.link` proves this for the gateware, tests/test_link_formal.py).

Reset: a **break** (the host holds the line low for longer than a frame) resets the link and the
core; the board stays silent while the break lasts, so the host can drop what it received before
and, when it releases the line, count the fresh grants from zero.

This module is the one home of these constants and of the host's side of the framing
(:class:`LinkHost`), used by the gateware, the serial transport, the simulated UART transport and
the tests alike.
"""

__all__ = ["DEFAULT_BAUD", "FRAME_MAX", "GRANT_FLAG", "result_header", "grant_header", "parse_header", "LinkHost",
           "frame_results", "wire_bytes"]

#: the link's baud rate unless a bitstream is built for another (``--baud``): 3 Mbaud, the FT231X's fastest
DEFAULT_BAUD = 3_000_000
#: the largest frame: 128 result bytes, or a grant of 128 credits
FRAME_MAX = 128
#: header bit 7: a credit grant (else a result frame)
GRANT_FLAG = 0x80


def result_header(n):
    """The header of a frame of ``n`` result bytes (1..128)."""
    if not 1 <= n <= FRAME_MAX:
        raise ValueError(f"a result frame carries 1 to {FRAME_MAX} bytes, not {n}")
    return n - 1


def grant_header(n):
    """The header granting ``n`` credits (1..128)."""
    if not 1 <= n <= FRAME_MAX:
        raise ValueError(f"a grant carries 1 to {FRAME_MAX} credits, not {n}")
    return GRANT_FLAG | (n - 1)


def parse_header(byte):
    """``(is_grant, n)`` of a header byte."""
    return bool(byte & GRANT_FLAG), (byte & (GRANT_FLAG - 1)) + 1


def frame_results(data):
    """``data`` (result bytes) as result frames of at most 128 bytes: what a board sends when
    it owes no credits (tests and the link-rate figures)."""
    out = bytearray()
    for i in range(0, len(data), FRAME_MAX):
        chunk = data[i:i + FRAME_MAX]
        out.append(result_header(len(chunk)))
        out += chunk
    return bytes(out)


def wire_bytes(payload, *, frame=FRAME_MAX):
    """Bytes on the wire for ``payload`` bytes framed in frames of ``frame`` bytes (a header each)."""
    return payload + -(-payload // frame)


class LinkHost:
    """The host's side of the framing: parse the board's bytes, keep the credits.

    ``feed(data)`` takes bytes read from the link and returns the result bytes among them;
    ``credits`` is how many command bytes the host may send now; ``spend(n)`` takes n of them.
    A frame may be split over any number of ``feed`` calls.
    """

    def __init__(self):
        self.reset()

    def reset(self):
        """Forget everything: call after the board was reset (the grants start again from zero)."""
        self.credits = 0
        self.granted = 0            # credits granted since the reset (the board's FIFO depth, once all came)
        self._left = 0              # result bytes still due in the current frame

    def feed(self, data):
        out = bytearray()
        i, n = 0, len(data)
        while i < n:
            if self._left:
                take = min(self._left, n - i)
                out += data[i:i + take]
                self._left -= take
                i += take
                continue
            grant, count = parse_header(data[i])
            i += 1
            if grant:
                self.credits += count
                self.granted += count
            else:
                self._left = count
        return bytes(out)

    def spend(self, n):
        if n > self.credits:
            raise ValueError(f"{n} command bytes against {self.credits} credits")
        self.credits -= n
