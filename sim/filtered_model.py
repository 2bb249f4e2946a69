"""Cycle-exact model of the 1 x 1 filtered array (:class:`blockray.rtl.filtered.FilteredIntersector`).

The answers come from :mod:`blockray.filtered` (the filter, bit for bit) and
:func:`blockray.exact.blocked_block` (the exact unit); the timing from a cycle-by-cycle mirror of
the RTL's structure: the credit counter, the 12-cycle filtered datapath, the hand-off's three
``SyncFIFOBuffered`` FIFOs (an inner memory of depth - 1 entries and an output register) and the
4-cycle exact ``Processor``. Because an undecided test holds back the decided ones behind it,
the cycles a test is accepted and delivered depend on the data; the model gives them exactly
(tests/test_filtered_model.py compares it with the RTL cycle for cycle).

    model = FilteredIntersectorModel(bits=16, fmt=None, depth=None)   # the RTL's defaults
    trace = model.run(tests_P, tests_Q, tests_V, tests_n, offer, ready)
    trace.accepted[k], trace.delivered[k], trace.blocked[k]           # cycles and answers per test
"""

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..exact import blocked_block
from ..filtered import default_format, filtered_tests
from ..params import Widths
from ..timing import BoardTiming

__all__ = ["BufferedFifo", "FilteredIntersectorModel", "Trace", "DATAPATH_LATENCY", "EXACT_LATENCY",
           "ArrayResolveModel", "FilteredBoardClock", "default_array_depth", "filtered_timing", "ISSUE_TO_HANDOFF"]

#: cycles from a test's acceptance to the hand-off's input: units 4, filters 3, filtered cell 5
DATAPATH_LATENCY = 12
#: the exact Processor's latency (valid in, result_valid out)
EXACT_LATENCY = 4


class BufferedFifo:
    """``amaranth.lib.fifo.SyncFIFOBuffered`` (depth >= 2) cycle by cycle: ``w_rdy``, ``r_rdy``
    and ``r_data`` in a cycle, :meth:`step` at the clock edge."""

    def __init__(self, depth):
        if depth < 2:
            raise ValueError("the model mirrors SyncFIFOBuffered of depth 2 or more")
        self.inner, self.capacity = deque(), depth - 1
        self.r_rdy, self.r_data = False, None

    @property
    def w_rdy(self):
        return len(self.inner) != self.capacity

    def step(self, w_en, w_data, r_en):
        do_write = w_en and self.w_rdy
        do_inner_read = bool(self.inner) and (not self.r_rdy or r_en)
        if do_inner_read:
            self.r_data, self.r_rdy = self.inner.popleft(), True
        elif r_en:
            self.r_rdy = False
        if do_write:
            self.inner.append(w_data)
        return do_write


@dataclass
class Trace:
    accepted: np.ndarray     # (T,) cycle each test was accepted (i.valid & i.ready)
    delivered: np.ndarray    # (T,) cycle each result was taken (o.valid & o.ready)
    blocked: np.ndarray      # (T,) bool, the delivered answers (the exact predicate's)
    decided: np.ndarray      # (T,) bool, the filter decided the test
    cycles: int              # cycles simulated


class FilteredIntersectorModel:
    """The timing and answers of ``FilteredIntersector(bits, fmt, depth)``."""

    def __init__(self, bits, fmt=None, depth=None):
        self.bits = bits
        self.fmt = fmt if fmt is not None else default_format(bits)
        self.depth = depth if depth is not None else DATAPATH_LATENCY + EXACT_LATENCY + 4

    def answers(self, P, Q, V, n):
        """(decided, filter's blocked, exact blocked) per test."""
        decided, blocked = filtered_tests(P, Q, V, n, self.fmt)
        exact = np.array([blocked_block(P[i:i + 1], Q[i:i + 1], V[i:i + 1], n[i:i + 1])[0, 0, 0]
                          for i in np.flatnonzero(~decided)], dtype=bool)
        full = np.zeros(len(P), dtype=bool)
        full[~decided] = exact
        return decided, blocked, full

    def run(self, P, Q, V, n, offer, ready, max_cycles=None):
        """Drive the tests in order: in cycle t a new test is offered if ``offer[t % len(offer)]``
        (and held until accepted), ``o.ready = ready[t % len(ready)]``."""
        decided, filt, exact = self.answers(P, Q, V, n)
        T = len(P)
        accepted, delivered, out = np.full(T, -1), np.full(T, -1), np.zeros(T, dtype=bool)
        pending, queue, answers = (BufferedFifo(self.depth) for _ in range(3))
        datapath = deque([None] * DATAPATH_LATENCY)           # test index reaching the hand-off
        exact_unit = deque([None] * EXACT_LATENCY)            # test index leaving the exact unit
        count = sent = done = t = 0
        held = False
        limit = max_cycles or 50 * T + 1000
        while done < T:
            if t >= limit:
                raise RuntimeError(f"no progress after {t} cycles ({done} of {T} results)")
            valid = sent < T and (held or bool(offer[t % len(offer)]))
            accept = valid and count < self.depth
            head = pending.r_data if pending.r_rdy else None
            o_valid = head is not None and (decided[head] or answers.r_rdy)
            deliver = o_valid and bool(ready[t % len(ready)])
            if accept:
                accepted[sent] = t
            if deliver:
                delivered[head] = t
                out[head] = filt[head] if decided[head] else answers.r_data
                done += 1
            # the clock edge
            entering = datapath.popleft()
            datapath.append(sent if accept else None)
            leaving = exact_unit.popleft()
            exact_unit.append(queue.r_data if queue.r_rdy else None)
            queue.step(entering is not None and not decided[entering], entering, True)
            pending.step(entering is not None, entering, deliver)
            answers.step(leaving is not None, None if leaving is None else bool(exact[leaving]),
                         deliver and not decided[head])
            count += accept - deliver
            held = valid and not accept
            sent += accept
            t += 1
        return Trace(accepted, delivered, out, decided, t)


#: cycles from a record's (or marker's) issue to the filtered array's hand-off input: the
#: board's memory (2) and the array's units, filters and cells (12)
ISSUE_TO_HANDOFF = 2 + DATAPATH_LATENCY


class ArrayResolveModel:
    """:class:`blockray.rtl.filtered.ArrayResolve` cycle by cycle, for the timing: an item is
    the number ``u`` of a record's undecided tests (0: none) or ``None`` for a board marker.

    Per cycle, :meth:`cycle` takes the item at the hand-off's input (or nothing) and returns
    the item delivered in that cycle (or nothing), mirroring the three ``SyncFIFOBuffered``
    (pending, queue, answers), the server (one undecided test per cycle into the exact unit,
    a record's tests back to back) and the 4-cycle exact ``Processor``.
    """

    _NOTHING = object()

    def __init__(self, depth):
        self.pending, self.queue, self.answers = (BufferedFifo(depth) for _ in range(3))
        self.exact_unit = deque([None] * EXACT_LATENCY)      # the `last` flag of each test fed
        self.started, self.remaining = False, 0

    def cycle(self, entering=_NOTHING):
        present = entering is not self._NOTHING
        # the server: the queue head's tests, one per cycle
        feeding = self.queue.r_rdy
        last = False
        if feeding:
            current = self.remaining if self.started else self.queue.r_data
            last = current == 1
        # out: the pending head, a record with undecided tests with its answers
        head = self.pending.r_data if self.pending.r_rdy else self._NOTHING
        needs = head is not self._NOTHING and bool(head)
        deliver = head is not self._NOTHING and (not needs or self.answers.r_rdy)
        # the clock edge
        leaving = self.exact_unit.popleft()
        self.exact_unit.append(last if feeding else None)
        self.pending.step(present, entering, deliver)
        self.queue.step(present and bool(entering), entering, feeding and last)
        self.answers.step(bool(leaving), True, deliver and needs)
        if feeding:
            self.started, self.remaining = not last, current - 1
        return head if deliver else self._NOTHING

    @property
    def empty(self):
        return not (self.pending.r_rdy or self.pending.inner)


class FilteredBoardClock:
    """The filtered board's issue slot against its array's credits, cycle by cycle, when the
    host keeps the command stream full (back to back): every cycle is a board cycle, either a
    step of the current command or a cycle lost waiting for a credit.

    :meth:`step` is one step of a command: ``needs_credit`` for a VOXEL's issue cycles (also an
    empty voxel's bubble) and the markers of END_BLOCK, READ_COUNTERS and IDENTIFY; ``item``
    what it issues (``u``, the record's undecided tests; ``None``, a marker; or nothing). It
    returns the cycles lost before the step. ``delivered_marks`` lists the cycles the markers
    left the array.
    """

    def __init__(self, depth):
        self.depth = depth
        self.resolve = ArrayResolveModel(depth)
        self.line = deque([ArrayResolveModel._NOTHING] * ISSUE_TO_HANDOFF)
        self.inside = 0
        self.cycle = 0
        self.delivered_marks = []

    def _tick(self, item):
        left = self.resolve.cycle(self.line.popleft())
        self.line.append(item)
        issued = item is not ArrayResolveModel._NOTHING
        if left is not ArrayResolveModel._NOTHING:
            self.inside -= 1
            if left is None:
                self.delivered_marks.append(self.cycle)
        self.inside += issued
        self.cycle += 1

    def step(self, needs_credit=False, item=ArrayResolveModel._NOTHING):
        lost = 0
        while needs_credit and self.inside >= self.depth:
            self._tick(ArrayResolveModel._NOTHING)
            lost += 1
        self._tick(item)
        return lost

    def drain(self):
        """Run (no board cycles) until every item has left the array."""
        while self.inside:
            self._tick(ArrayResolveModel._NOTHING)

    record = staticmethod(lambda u: int(u))
    marker = None


def default_array_depth():
    """The filtered board's array credits (:meth:`blockray.rtl.filtered.FilteredArray.default_depth`
    with the board's memory latency): issue to delivery, 16 cycles, and 4."""
    return ISSUE_TO_HANDOFF + 2 + 4


def filtered_timing(bits):
    """The filtered board's fixed latencies as a BoardTiming (processor_latency: array input to
    the accumulators when no test waits, 15); its data-dependent cycles come on top."""
    Widths(bits)
    return BoardTiming(processor_latency=DATAPATH_LATENCY + 3)
