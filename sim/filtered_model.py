"""Cycle-exact models of the filtered arrays: the 1 x 1 array
(:class:`blockray.rtl.filtered.FilteredIntersector`, :class:`FilteredIntersectorModel`) and the
board's R x S array with its shared exact unit (:class:`blockray.rtl.filtered.ArrayResolve`
behind the board's credits, :func:`board_clock`, compiled; used by
:class:`blockray.sim.model.BoardModel` and :class:`~blockray.sim.model.ModelBoard` with
a filtering :class:`~blockray.cell.Cell`).

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
from numba import njit

from ..cell import Cell
from ..exact import blocked_block
from ..filtered import filtered_tests

__all__ = ["BufferedFifo", "FilteredIntersectorModel", "Trace", "DATAPATH_LATENCY", "EXACT_LATENCY",
           "board_clock", "STEP_PLAIN", "STEP_BUBBLE", "STEP_RECORD", "STEP_MARKER", "STEP_DRAIN",
           "default_array_depth", "ISSUE_TO_HANDOFF"]

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
        self.fmt = fmt if fmt is not None else Cell("filtered").format_at(bits)
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


#: a board step for :func:`board_clock`: no credit needed (WRITE_*, BEGIN_BLOCK, LOAD_*), an
#: empty voxel's bubble (a credit, nothing issued), a record (``undecided`` tests), a marker, a
#: step that waits until the array is empty (the lean board's WRITE_PATCH)
STEP_PLAIN, STEP_BUBBLE, STEP_RECORD, STEP_MARKER, STEP_DRAIN = 0, 1, 2, 3, 4
_NONE, _MARK = -2, -1          # in the issue line and the pending FIFO: nothing, a marker


@njit(cache=True, inline="always")
def _fifo_step(buf, k, head, n, rdy, rdata, w_en, w_data, r_en):
    """``SyncFIFOBuffered`` ``k`` (of depth buf.shape[1]: an inner FIFO of depth - 1 and an
    output register ``rdy``/``rdata``) at the clock edge: :meth:`BufferedFifo.step`."""
    depth = buf.shape[1]
    do_write = w_en and n[k] != depth - 1
    if n[k] > 0 and (not rdy[k] or r_en):
        rdata[k], rdy[k] = buf[k, head[k]], True
        head[k] = (head[k] + 1) % depth
        n[k] -= 1
    elif r_en:
        rdy[k] = False
    if do_write:
        buf[k, (head[k] + n[k]) % depth] = w_data
        n[k] += 1


@njit(cache=True)
def board_clock(kinds, undecided, depth, exact_latency=EXACT_LATENCY, issue_to_handoff=ISSUE_TO_HANDOFF,
                exact_interval=1):
    """The filtered board's cycles when the host keeps the command stream full: every cycle is a
    board cycle, a step of the current command or one lost waiting for the array's credits.

    ``kinds`` (N,): the commands' steps in order (STEP_*), ``undecided`` (N,): a record's tests
    the exact unit must decide. Mirrors, cycle by cycle, the board's credits (items issued and
    not delivered < ``depth``), the ``issue_to_handoff`` cycles from issue to the array's hand-off
    (:data:`ISSUE_TO_HANDOFF` on the board) and :class:`blockray.rtl.filtered.ArrayResolve`: its
    three ``SyncFIFOBuffered`` (0 pending, 1 queue, 2 answers), the server (the queue head's
    undecided tests into the exact unit, one per ``exact_interval`` cycles) and the exact unit
    (``exact_latency``: the filtered array's Processor, :data:`EXACT_LATENCY`, a test a cycle;
    the lean array's LeanExact, 11, a test every 3 cycles).
    Returns ``lost`` (N,): the cycles lost before each step, and ``marks``: the cycle (counted
    from the first step) each marker left the array.
    """
    n_steps = len(kinds)
    lost = np.zeros(n_steps, np.int64)
    marks = np.full(n_steps, -1, np.int64)
    n_marks = 0
    buf = np.zeros((3, depth), np.int64)
    head, n = np.zeros(3, np.int64), np.zeros(3, np.int64)
    rdy, rdata = np.zeros(3, np.bool_), np.zeros(3, np.int64)
    line = np.full(issue_to_handoff, _NONE, np.int64)          # issue -> hand-off input
    exact = np.full(exact_latency, -1, np.int64)                # `last` of each test fed, -1 none
    pos = epos = 0
    started, remaining = False, 0
    wait = 0                                                    # cycles until the exact unit takes a test
    inside = cycle = 0
    i = 0
    waiting = False                                             # the step waits for a credit
    while i < n_steps or inside > 0:
        item = _NONE
        if i < n_steps:
            kind = kinds[i]
            waits = inside > 0 if kind == STEP_DRAIN else (kind != STEP_PLAIN and inside >= depth)
            if waits:
                lost[i] += 1
                waiting = True
            else:
                waiting = False
                if kind == STEP_RECORD:
                    item = undecided[i]
                elif kind == STEP_MARKER:
                    item = _MARK
        entering = line[pos]
        line[pos] = item
        pos = (pos + 1) % issue_to_handoff
        # the server and the pending head, from this cycle's registers
        feeding = rdy[1] and wait == 0
        last = False
        current = 0
        if feeding:
            current = remaining if started else rdata[1]
            last = current == 1
        needs = rdy[0] and rdata[0] > 0
        deliver = rdy[0] and (not needs or rdy[2])
        if deliver and rdata[0] == _MARK:
            marks[n_marks] = cycle
            n_marks += 1
        # the clock edge
        leaving = exact[epos]
        exact[epos] = (1 if last else 0) if feeding else -1
        epos = (epos + 1) % exact_latency
        _fifo_step(buf, 0, head, n, rdy, rdata, entering != _NONE, entering, deliver)
        _fifo_step(buf, 1, head, n, rdy, rdata, entering > 0, entering, feeding and last)
        _fifo_step(buf, 2, head, n, rdy, rdata, leaving == 1, 1, deliver and needs)
        if feeding:
            started, remaining = not last, current - 1
            wait = exact_interval - 1
        elif wait > 0:
            wait -= 1
        inside += (item != _NONE) - deliver
        cycle += 1
        if not waiting:
            i += 1
    return lost, marks[:n_marks]


def default_array_depth():
    """The filtered board's array credits (:meth:`blockray.rtl.filtered.FilteredArray.default_depth`
    with the board's memory latency): issue to delivery, 16 cycles, and 4."""
    return ISSUE_TO_HANDOFF + 2 + 4
