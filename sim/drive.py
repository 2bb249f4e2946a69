"""The host's side of a simulated board's streams, one clock cycle at a time: the one drive loop
of the Amaranth-simulator tests, the cocotb bench and the simulated render transports.

Simulator-neutral: a testbench calls :meth:`StreamHost.drive` before a clock edge (what to put on
the command stream's ``valid``/``payload`` and the result stream's ``ready``), then
:meth:`StreamHost.sample` with the board's ``ready``, ``valid`` and ``payload`` as they were at
that edge. The Amaranth simulator (``ctx.set``/``ctx.get``, ``ctx.tick``) and cocotb (signal
handles, ``RisingEdge``) each need only those few lines of glue (:func:`amaranth_cycle`).

Host timing: :class:`Stalls` says in which cycles the host does not offer a command item (idle)
or does not take a result item (back-pressure): per-cycle coin flips with probability ``rate``
and **bursts**, long stalls of ``burst_length`` cycles starting with probability ``burst``. Reset
and replay are above this level (the board tests' ``ReplayingHost``, tests/board_host.py): after a
reset the host calls :meth:`StreamHost.reset` and sends the replay.

The items are whatever the stream carries: bytes for :class:`~blockray.rtl.core.BoardCore`,
command records (ints) for :class:`~blockray.rtl.board.BoardTop`.
"""

import random
from collections import deque
from dataclasses import dataclass

__all__ = ["HostTiming", "Stalls", "StreamHost", "amaranth_cycle"]


@dataclass(frozen=True)
class HostTiming:
    """Random host timing for one stream: ``rate`` per-cycle stall probability, ``burst``
    probability per cycle that a long stall of ``burst_length`` = (min, max) cycles starts."""
    rate: float = 0.0
    burst: float = 0.0
    burst_length: tuple = (16, 256)

    def __post_init__(self):
        for name in ("rate", "burst"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise ValueError(f"host timing {name} must be in [0, 1), not {v!r}")
        lo, hi = self.burst_length
        if not 1 <= lo <= hi:
            raise ValueError(f"burst length {self.burst_length!r} must be 1 <= min <= max")

    @property
    def never(self):
        return self.rate == 0.0 and self.burst == 0.0


class Stalls:
    """Cycle by cycle: is the host stalled? (:class:`HostTiming` with a seeded ``random.Random``)."""

    def __init__(self, timing, rng):
        self.timing, self.rng = timing, rng
        self._left = 0

    def __call__(self):
        t = self.timing
        if t.never:
            return False
        if self._left:
            self._left -= 1
            return True
        if t.burst and self.rng.random() < t.burst:
            self._left = self.rng.randint(*t.burst_length) - 1
            return True
        return bool(t.rate) and self.rng.random() < t.rate


class StreamHost:
    """The host on a board's two streams: offers queued command items (idle per ``idle``), takes
    result items (back-pressure per ``backpressure``). ``seed`` seeds both."""

    def __init__(self, *, idle=HostTiming(), backpressure=HostTiming(), seed=0):
        rng = random.Random(seed)
        self._idle = Stalls(idle, rng)
        self._pressure = Stalls(backpressure, rng)
        self.queue = deque()
        self.received = deque()
        self._offer = None
        self._ready = 0
        self.cycles = 0          # clock edges since the last reset
        self.taken = 0           # items the board took since the last reset

    def send(self, items):
        self.queue.extend(items)

    @property
    def idle(self):
        """Nothing left to offer."""
        return self._offer is None and not self.queue

    def drive(self):
        """``(valid, payload, ready)`` for the coming clock edge."""
        if self._offer is None and self.queue and not self._idle():
            self._offer = self.queue.popleft()
        self._ready = int(not self._pressure())
        return int(self._offer is not None), self._offer or 0, self._ready

    def sample(self, command_ready, result_valid, result_payload):
        """The edge happened with these board outputs: returns the item received or None."""
        self.cycles += 1
        if self._offer is not None and command_ready:
            self._offer = None
            self.taken += 1
        if result_valid and self._ready:
            self.received.append(result_payload)
            return result_payload
        return None

    def reset(self):
        """The board was reset: drop what was queued, in flight and received."""
        self.queue.clear()
        self.received.clear()
        self._offer = None
        self.cycles = 0
        self.taken = 0


def _raw(value):
    """A stream payload as a plain value (a layout's view as its bits)."""
    return value.as_value() if hasattr(value, "as_value") else value


async def amaranth_cycle(ctx, host, commands, results):
    """One clock cycle of ``host`` on Amaranth streams ``commands`` (into the board) and
    ``results`` (out of it) in an Amaranth testbench; returns the item received or None."""
    valid, payload, ready = host.drive()
    ctx.set(commands.valid, valid)
    ctx.set(_raw(commands.payload), payload)
    ctx.set(results.ready, ready)
    cready, rvalid = ctx.get(commands.ready), ctx.get(results.valid)
    rpayload = ctx.get(_raw(results.payload))
    await ctx.tick()
    return host.sample(cready, rvalid, rpayload)
