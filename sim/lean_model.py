"""Cycle-exact model of the lean array (:class:`blockray.rtl.lean.LeanArray`) behind its owner's credits.

Answers: a test the filter decides (:func:`blockray.filtered.filtered_block`, the lean cell's
format) has the filter's bit, which is certified; an undecided test of a loaded row and column
has the exact predicate's (:func:`blockray.exact.blocked_block`, what the shared exact unit
recomputes from the patch and the end points); an undecided test of an unloaded row or column
is not resolved and reads 0 (the board masks it out). So the loaded bits are the exact cell's by
construction. Timing: :func:`blockray.sim.filtered_model.board_clock`, the cycle-by-cycle mirror
of the hand-off the lean array shares with the filtered array, with the lean exact unit's
latency (:data:`LEAN_EXACT_LATENCY` = 12) and interval (:data:`LEAN_EXACT_INTERVAL` = 3: a test
every 3 cycles) and the array's 12 cycles from its input to the hand-off.

    model = LeanArrayModel(bits, rows, cols, fmt=None, depth=None)
    trace = model.run(steps, vertices, normals)
    steps: Gap(), Mark(), Record(address, first, shooters (S, 3), receivers (R, 3), row_mask, col_mask)

The owner (a test bench, the board) presents step i in cycle ``trace.cycle[i]``: a record or a
marker waits while ``depth`` items are inside (issued and not delivered), a gap never does.
"""

from dataclasses import dataclass

import numpy as np

from ..cell import Cell
from ..exact import blocked_block
from ..filtered import filtered_block
from .filtered_model import DATAPATH_LATENCY, STEP_MARKER, STEP_PLAIN, STEP_RECORD, board_clock, default_array_depth

__all__ = ["LEAN_EXACT_INTERVAL", "LEAN_EXACT_LATENCY", "LEAN_HANDOFF_STAGES", "Gap", "Mark", "Record", "LeanTrace",
           "LeanArrayModel", "record_answers", "default_lean_depth"]

#: the lean exact unit's latency (rtl/lean.py LeanExact): tag in, the patch memory and end-point
#: memory read (1), the reads registered (1), the points held (1), its three edges a cycle apart
#: (2), each edge's w_k (3) and s_k (3), the decision (1)
LEAN_EXACT_LATENCY = 3 + 2 + 3 + 3 + 1
#: cycles between two tests into the lean exact unit (one edge a cycle)
LEAN_EXACT_INTERVAL = 3
#: credits for a burst of undecided tests (rtl/lean.py ``LeanArray.burst_credits``)
LEAN_BURST_DEPTH = 30
#: the register between the cells' decisions and the hand-off (``LeanArray.handoff_stages``)
LEAN_HANDOFF_STAGES = 1
#: the lean array's input to its hand-off: the filtered array's datapath and that register
LEAN_DATAPATH_LATENCY = DATAPATH_LATENCY + LEAN_HANDOFF_STAGES
#: credits the lean array has beyond the filtered array's: the hand-off register, its exact
#: unit's latency, 4 and a burst's
LEAN_EXTRA_DEPTH = LEAN_HANDOFF_STAGES + LEAN_EXACT_LATENCY + 4 + LEAN_BURST_DEPTH


def default_lean_depth(extra_latency=2):
    """The lean array's credits (:meth:`blockray.rtl.lean.LeanArray.default_depth`): issue to
    delivery (``extra_latency`` in front of the array: the board's memory, 2), 4, and
    :data:`LEAN_EXTRA_DEPTH`."""
    return default_array_depth() - 2 + extra_latency + LEAN_EXTRA_DEPTH


@dataclass(frozen=True)
class Gap:
    """A cycle with nothing presented."""


@dataclass(frozen=True)
class Mark:
    """A marker: leaves the array when every record before it is in ``hit``."""


@dataclass(frozen=True)
class Record:
    """A broadcast record: patch ``address``, block's ``first``, the points, the loaded rows and
    columns (bool arrays)."""
    address: int
    first: bool
    shooters: np.ndarray
    receivers: np.ndarray
    row_mask: np.ndarray
    col_mask: np.ndarray


@dataclass
class LeanTrace:
    cycle: np.ndarray        # (steps,) the cycle each step is presented
    marks: np.ndarray        # (markers,) the cycle each marker leaves (mark_out)
    hits: list               # (markers,) of (R, S) bool: ``hit`` when the marker leaves
    blocked: list            # (records,) of (R, S) bool: a record's delivered bits
    undecided: np.ndarray    # (records,) tests sent to the exact unit
    cycles: int              # cycles until the last item is delivered


def record_answers(record, vertices, normals, fmt):
    """(blocked (R, S), undecided (R, S)) of one record: the filter's bit where it decides, the
    exact predicate's where it does not and the row and column are loaded, else 0."""
    V, n = vertices[record.address][None], normals[record.address][None]
    decided, filt = (a[:, :, 0] for a in filtered_block(record.shooters, record.receivers, V, n, fmt))
    loaded = np.asarray(record.row_mask, bool)[:, None] & np.asarray(record.col_mask, bool)[None, :]
    undecided = ~decided & loaded
    blocked = filt.copy()
    if undecided.any():
        exact = blocked_block(record.shooters, record.receivers, V, n)[:, :, 0]
        blocked[undecided] = exact[undecided]
    return blocked, undecided


class LeanArrayModel:
    """The answers and cycles of ``LeanArray(bits, rows, cols, fmt, depth)``."""

    def __init__(self, bits, rows, cols, fmt=None, depth=None):
        self.bits, self.rows, self.cols = bits, rows, cols
        self.fmt = Cell("lean", fmt).format_at(bits)
        self.depth = depth if depth is not None else default_lean_depth(0)

    def run(self, steps, vertices, normals):
        vertices, normals = np.asarray(vertices, np.int64), np.asarray(normals, np.int64)
        kinds, counts, blocked, undecided_counts = [], [], [], []
        hits, hit = [], np.zeros((self.rows, self.cols), bool)
        for step in steps:
            if isinstance(step, Record):
                b, u = record_answers(step, vertices, normals, self.fmt)
                hit = b | (hit & (not step.first))
                kinds.append(STEP_RECORD)
                counts.append(int(u.sum()))
                blocked.append(b)
                undecided_counts.append(int(u.sum()))
            elif isinstance(step, Mark):
                kinds.append(STEP_MARKER)
                counts.append(0)
                hits.append(hit.copy())
            elif isinstance(step, Gap):
                kinds.append(STEP_PLAIN)
                counts.append(0)
            else:
                raise TypeError(f"a lean array step is a Gap, Mark or Record, not {step!r}")
        lost, marks = board_clock(np.array(kinds, np.int64), np.array(counts, np.int64), self.depth,
                                  LEAN_EXACT_LATENCY, LEAN_DATAPATH_LATENCY, LEAN_EXACT_INTERVAL)
        cycle = np.arange(len(steps)) + np.cumsum(lost)
        return LeanTrace(cycle, marks, hits, blocked, np.array(undecided_counts, np.int64),
                         int(marks[-1]) + 1 if len(marks) else int(cycle[-1]) + 1 if len(cycle) else 0)
