"""The framed link (:mod:`blockray.framing`) in the host driver, the model board's side of it,
and a transport that injects faults.

* :class:`FramedTransport`: a :class:`~blockray.host_driver.board.transport.Transport` that carries
  the core's bytes in numbered, CRC-checked frames over a raw byte ``pipe`` and resends what was
  lost or corrupted. A fault is corrected, or, after ``max_retries`` rounds without progress,
  ends the run with one :class:`TransportError` naming the link and the last fault seen. It
  reads the board's own counters (frames resent, errors, frames accepted) with a status frame.
  Over a serial port (a ULX3S, :mod:`~blockray.host_driver.board.serial_link`) and the simulated one
  (``ulx3s-sim``, :mod:`~blockray.host_driver.board.uart_sim`) the pipe's ``reset()`` is a break, which
  resets the board's link and core.
* :class:`ModelBoardLink`: the pipe to the bit-exact model behind the board's half of the
  framing (an :class:`~blockray.framing.Endpoint`, as the RTL is to be): ``--board model-link``.
* :class:`FaultyPipe`: flips, drops and duplicates bytes of a pipe in both directions at a rate
  per byte, seeded (``--link-faults RATE --link-seed N``).

A pipe has ``write(data)``, ``read(timeout) -> bytes`` (what arrived within ``timeout``
seconds; empty: a time-out) and ``reset()``; optionally ``stats()`` and ``close()``.
"""

import time
from dataclasses import dataclass

import numpy as np

from ...errors import ParameterError, option
from ...framing import BOARD_LINK, HOST_LINK, Endpoint
from .transport import Transport, TransportError

__all__ = ["FramedTransport", "ModelBoardLink", "FaultyPipe", "LinkFaults", "FaultInjector", "integrity_report"]


@dataclass(frozen=True)
class LinkFaults:
    """Faults to inject: each byte, in each direction, is with probability ``rate`` flipped (one
    random bit), dropped or duplicated (one of the three, equally likely); ``seed`` seeds it."""
    rate: float
    seed: int = 0

    def __post_init__(self):
        if not 0 <= self.rate < 1:
            raise ParameterError(f"{option('link_faults')} must be a rate per byte from 0 to below 1, not {self.rate}",
                                 parameter="link_faults")

    def injector(self, board, direction):
        """The injector of board ``board``'s ``direction`` (0: to the board, 1: from it)."""
        return FaultInjector(self.rate, np.random.default_rng([self.seed, board, direction]))


class FaultInjector:
    """Corrupts byte strings at ``rate`` faults per byte (``counts``: flipped, dropped, duplicated)."""

    KINDS = ("flipped", "dropped", "duplicated")

    def __init__(self, rate, rng):
        self.rate, self.rng = rate, rng
        self.counts = dict.fromkeys(self.KINDS, 0)

    def __call__(self, data):
        if not data or not self.rate:
            return data
        hits = np.flatnonzero(self.rng.random(len(data)) < self.rate)
        if not len(hits):
            return data
        out, last = bytearray(), 0
        for i in hits.tolist():
            out += data[last:i]
            kind = self.KINDS[int(self.rng.integers(3))]
            self.counts[kind] += 1
            if kind == "flipped":
                out.append(data[i] ^ (1 << int(self.rng.integers(8))))
            elif kind == "duplicated":
                out += data[i:i + 1] * 2
            last = i + 1
        return bytes(out + data[last:])


class FaultyPipe:
    """``pipe`` with ``outgoing`` / ``incoming`` :class:`FaultInjector` on its two directions."""

    def __init__(self, pipe, outgoing, incoming):
        self.pipe, self.outgoing, self.incoming = pipe, outgoing, incoming

    def write(self, data):
        self.pipe.write(self.outgoing(data))

    def read(self, timeout):
        return self.incoming(self.pipe.read(timeout))

    def reset(self):
        self.pipe.reset()

    def close(self):
        if hasattr(self.pipe, "close"):
            self.pipe.close()

    def stats(self):
        pipe = self.pipe.stats() if hasattr(self.pipe, "stats") else {}
        return {**pipe, "injected": {"to_board": dict(self.outgoing.counts),
                                                  "from_board": dict(self.incoming.counts)}}


class ModelBoardLink:
    """The board's half of the framed link in front of ``core`` (a
    :class:`~blockray.host_driver.board.simulated.ModelTransport`): frames accepted go to the core at
    once, its results are framed when the host reads (the board answers only; it has no timer)."""

    def __init__(self, core, config=BOARD_LINK):
        self.core = core
        self.endpoint = Endpoint(config)

    def write(self, data):
        payload = self.endpoint.receive(data)
        if payload:
            self.core.send(payload)

    def read(self, timeout):
        self.endpoint.submit(self.core.run(whole=False))
        return self.endpoint.output()

    def reset(self):
        self.core.reset()
        self.endpoint.reset()

    def stats(self):
        """The model's own counts (the host reads the same over the link, as ``board``)."""
        e = self.endpoint
        return {"board_model": {"frames_resent": e.counts["frames_resent"], "errors": e.faults(), **e.counts}}


#: the longest time-out, in units of FramedTransport's ``timeout``
_MAX_BACKOFF = 16


class FramedTransport(Transport):
    """The core's bytes over ``pipe`` in frames (see the module docstring). ``where`` names the
    link in errors; ``timeout``: seconds of silence before a resend (a board answers within a
    USB round trip, a few ms), doubled after each time-out up to 16 times, halved after progress
    (so a window still in transit is not resent over and over); ``max_retries``: the link is given up after ``max_retries`` time-outs
    worth of time without progress (no frame acknowledged or accepted);
    ``answer_timeout``: if given, every :meth:`reset` waits at most this long for the board's
    answer to a status frame (a board that does not answer is one :class:`TransportError`)."""

    def __init__(self, pipe, *, where, config=HOST_LINK, timeout=0.05, max_retries=32, answer_timeout=None):
        super().__init__()
        self.pipe, self.where, self.timeout, self.max_retries = pipe, where, timeout, max_retries
        self.answer_timeout = answer_timeout
        self.endpoint = Endpoint(config)
        self._results = bytearray()
        self._resets = 0
        self._failed = False
        self._wait = 1          # the time-out in units of ``timeout``: doubled on a time-out, halved on progress
        self.wire_sent = self.wire_received = 0     # bytes on the wire, frames and resends included

    def send(self, data):
        self.endpoint.submit(bytes(data))
        self._flush()

    def _flush(self):
        out = self.endpoint.output()
        if out:
            self.pipe.write(out)
            self.wire_sent += len(out)

    def recv(self, count, *, timeout=None):
        e = self.endpoint
        silence = self.timeout if timeout is None else timeout
        mark, since = None, time.monotonic()
        while len(self._results) < count:
            self._flush()
            data = self.pipe.read(self._wait * silence)
            self.wire_received += len(data)
            if data:
                self._results += e.receive(data)
            now = (e.base, e.expect)
            if now != mark:
                mark, since = now, time.monotonic()
                self._wait = max(1, self._wait // 2)
                continue
            if time.monotonic() - since > self.max_retries * silence:
                self._failed = True
                raise TransportError(self._failure(count, silence))
            if not data:        # a time-out: resend, and wait longer next time (the window may be in transit)
                e.rewind()
                self._wait = min(2 * self._wait, _MAX_BACKOFF)
        self._flush()                               # acknowledge what came
        out = bytes(self._results[:count])
        del self._results[:count]
        return out

    def _failure(self, count, silence):
        fault = (self.endpoint.last_fault or "no answer from the board").replace("the other side", "the board")
        return (f"{self.where}: the link failed: no progress in {self.max_retries} time-outs of {silence:g} s, "
                f"{len(self._results)} of {count} result bytes received (last fault: {fault})")

    def reset(self):
        """Reset the pipe (and with it the board's link), number frames from 0 again; with an
        ``answer_timeout``, check the board answers."""
        self.pipe.reset()
        self.endpoint.reset()
        self._results.clear()
        self._resets += 1
        self._failed = False
        if self.answer_timeout is not None and self.board_status(self.answer_timeout) is None:
            self._failed = True
            raise TransportError(f"{self.where}: no answer from the board within {self.answer_timeout:g} s of a "
                                 f"reset (is the bitstream loaded, at this baud rate?)")

    def board_status(self, seconds):
        """The board's counters (:data:`~blockray.framing.STATUS_FIELDS`, mod 65536) from a status
        frame, asked again each ``timeout`` without an answer; None if none came in ``seconds``."""
        e = self.endpoint
        e.request_status()
        deadline = time.monotonic() + seconds
        while True:
            self._flush()
            data = self.pipe.read(max(0.0, min(self.timeout, deadline - time.monotonic())))
            self.wire_received += len(data)
            if data:
                self._results += e.receive(data)
            if e.peer_status is not None:
                return e.peer_status
            if time.monotonic() >= deadline:
                return None
            if not data:                    # the request or its answer was lost: ask again
                e.request_status()

    def close(self):
        if hasattr(self.pipe, "close"):
            self.pipe.close()

    def stats(self):
        """The pipe's, the host's frame counts, the board's (read over the link; absent once the
        link has failed) and the wire bytes."""
        e = self.endpoint
        pipe = self.pipe.stats() if hasattr(self.pipe, "stats") else {}
        out = {**pipe, "host": {"frames_resent": e.counts["frames_resent"], "errors": e.faults(), **e.counts}}
        board = None if self._failed else self.board_status(max(1.0, self.max_retries * self.timeout))
        if board is not None:
            out["board"] = board
        return {**out, "resets": self._resets, "wire_bytes_sent": self.wire_sent,
                "wire_bytes_received": self.wire_received}


def integrity_report(stats):
    """The report's ``link_integrity`` from the transports' ``stats()``: frames resent and errors
    seen, both sides together and the board's alone (``board_*``: the board's own counters, read
    over the link), and the faults injected; None if no link is framed."""
    stats = [s for s in stats if "host" in s]
    if not stats:
        return None
    out = {"frames_sent": 0, "frames_resent": 0, "errors": 0, "board_frames_resent": 0, "board_errors": 0}
    for s in stats:
        out["frames_sent"] += s["host"]["frames_sent"]
        for key in ("wire_bytes_sent", "wire_bytes_received"):
            out[key] = out.get(key, 0) + s[key]
        for side in ("host", "board"):
            for key in ("frames_resent", "errors"):
                out[key] += s.get(side, {}).get(key, 0)
        for key in ("frames_resent", "errors"):
            out[f"board_{key}"] += s.get("board", {}).get(key, 0)
        for counts in s.get("injected", {}).values():
            for kind, n in counts.items():
                out[f"injected_{kind}"] = out.get(f"injected_{kind}", 0) + n
    return out
