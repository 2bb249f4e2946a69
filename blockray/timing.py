"""The board's cycle contract: what every command costs, in one place.

The bit-exact model counts cycles with this and the RTL testbenches assert it. The board executes
the host's command stream in order; a command costs exactly:

=============== ======================================================================
WRITE_PATCH     1 (one patch record into patch memory)
WRITE_VOXEL     1 (one (start, count) entry into the voxel table)
BEGIN_BLOCK     1 (clears the R x S accumulators and the row/column ray-valid masks)
LOAD_RECEIVER   1 (a receiver end point into one row's receiver unit)
LOAD_SHOOTER    1 (a shooter sample point into one column's shooter unit)
LOAD_POINTS     1 (up to POINTS_PER_LOAD receiver and shooter points at once)
VOXEL v         max(1, count_v): the voxel's patch records stream out of memory, one per
                cycle, broadcast to all R x S processors; an empty voxel costs one bubble
END_BLOCK       1: a marker enters the pipeline behind the block's last record; the R x S
                result word goes out when it reaches the accumulators, drain_latency cycles
                later, while the next block already streams (blocks overlap, no drain bubble)
READ_COUNTERS   1 (a snapshot of the counters, covering the commands before it, follows the
                same marker path so that results stay in command order)
IDENTIFY        1 (the built configuration, by the same marker path)
=============== ======================================================================

``drain_latency = memory_latency + processor_latency - 1``: END_BLOCK's result word is formed
drain_latency cycles after END_BLOCK's own cycle (the last record issued before END_BLOCK reaches
the accumulators then). Those cycles overlap with the next commands; only a host that waits for
the result before sending more (the end of a batch) sees them, as stalls. Cycles spent waiting
for the host (an empty command stream, or a full result queue nobody reads) are stalls, not board
cycles, so a command stream's board cycles do not depend on the host's timing.
:meth:`BoardTiming.for_cell` gives the RTL's latencies (tests assert them against the RTL).
"""

from dataclasses import dataclass

import numpy as np

from .errors import ParameterError
from .cell import Cell, check_cell
from .protocol import POINTS_PER_LOAD, Op

__all__ = ["Op", "BoardTiming", "POINTS_PER_LOAD", "load_commands_needed"]


def load_commands_needed(receivers, shooters):
    """LOAD_POINTS commands (= cycles) that load ``receivers`` + ``shooters`` points."""
    return -(-(int(receivers) + int(shooters)) // POINTS_PER_LOAD)


#: RTL latencies (asserted against blockray.rtl in tests/test_board_sim.py)
MEMORY_LATENCY = 2      # patch-memory read + broadcast register
UNIT_LATENCY = 4        # ShooterUnit / ReceiverUnit
CELL_LATENCY = 4        # Processor (cell), including the OR into the accumulator
#: the filtered array (rtl/filtered.py FilteredArray) when no test of a record waits for its exact
#: unit: units 4, filters 3, filtered cell 5, the in-order hand-off's FIFO 2, the accumulator 1
FILTERED_LATENCY = 15
#: the lean array: the filtered array's and the register before its hand-off (rtl/lean.py)
LEAN_LATENCY = FILTERED_LATENCY + 1


@dataclass(frozen=True)
class BoardTiming:
    """Cycle costs of the board's commands (see the module docstring).

    processor_latency  cycles from a patch record on the array's input to its blocked bits in the
                       accumulators (receiver/shooter units + processor + OR)
    memory_latency     cycles from a record's issue (its address to patch memory) to the array's
                       input
    """

    processor_latency: int
    memory_latency: int = MEMORY_LATENCY

    def __post_init__(self):
        for name in ("processor_latency", "memory_latency"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ParameterError(f"timing parameter {name} must be a non-negative integer, not {v!r}")

    @classmethod
    def for_cell(cls, cell=Cell(), *, memory_latency=MEMORY_LATENCY):
        """The latencies of the RTL (:class:`blockray.rtl.board.BoardTop`) with processor cell
        ``cell`` (a :class:`~blockray.cell.Cell`); they do not depend on B (at B <= 20 every multiplier is one pipeline stage), and
        a test asserts them against the RTL's properties at several B.

        memory_latency 2: patch-memory read (1) + the broadcast register that fans the record out
        to the array (1). processor_latency 8: shooter/receiver units (4: differences, partial
        products, partial sums, the sum joining the pieces) + processor (4: operand registers,
        partial products, partial sums, the joined sum with the decision and OR).

        A filtering cell: the filtered array's least latency (:data:`FILTERED_LATENCY`; lean:
        :data:`LEAN_LATENCY`, one more for the register before its hand-off); its data-dependent
        cycles (records waiting for the shared exact unit, cycles lost when the array's credits run
        out) come on top (:func:`blockray.sim.filtered_model.board_clock`).
        """
        if check_cell(cell).filtered:            # filtered, lean: the same datapath and hand-off
            latency = LEAN_LATENCY if cell.lean else FILTERED_LATENCY
            return cls(processor_latency=latency, memory_latency=memory_latency)
        return cls(processor_latency=UNIT_LATENCY + CELL_LATENCY, memory_latency=memory_latency)

    @property
    def drain_latency(self):
        """Cycles from END_BLOCK's own cycle to the one that forms its result word. END_BLOCK
        comes at the earliest the cycle after the last record's issue; that record reaches the
        accumulators memory_latency + processor_latency cycles after its issue."""
        return self.processor_latency + self.memory_latency - 1

    @property
    def result_latency(self):
        """Cycles from END_BLOCK / READ_COUNTERS to its result on the result stream (an empty
        result queue and a host that reads at once): drain_latency, the result queue's write,
        its output register."""
        return self.drain_latency + 2

    def cost(self, op, count=0):
        """Board cycles of one command; ``count`` is the voxel's record count for VOXEL."""
        op = Op(op)
        if op is Op.VOXEL:
            return max(1, int(count))
        return 1

    def block_cycles(self, receivers, shooters, voxel_counts):
        """Board cycles of one block as the host sends it: BEGIN_BLOCK, the LOAD_POINTS
        commands, one VOXEL per entry of ``voxel_counts``, END_BLOCK. ``voxel_counts`` (K,)
        gives an int; (P, K), the counts on each of P boards, gives a (P,) array."""
        counts = np.asarray(voxel_counts, dtype=np.int64)
        cycles = self.blocks_cycles(receivers, shooters, np.maximum(counts, 1).sum(axis=-1))
        return int(cycles) if counts.ndim <= 1 else cycles

    @staticmethod
    def blocks_cycles(receivers, shooters, streamed):
        """:meth:`block_cycles` of many blocks at once: ``receivers``, ``shooters`` (B,) and
        ``streamed`` (B,) or (B, P), the cycles of each block's VOXEL commands (sum of
        max(1, count)) on each board. Returns int64 of ``streamed``'s shape."""
        loads = -(-(np.asarray(receivers, dtype=np.int64) + np.asarray(shooters, dtype=np.int64))
                  // POINTS_PER_LOAD)
        streamed = np.asarray(streamed, dtype=np.int64)
        return 1 + loads.reshape(loads.shape + (1,) * (streamed.ndim - loads.ndim)) + streamed + 1
