"""Bit-exact model of the board's block sequencer (rays made on the board, docs/board-protocol.md):
the commands of :mod:`blockray.board_rays` in, the internal records the host sends today out.

Between the deframer and the board's command stream: ``LOAD_SAMPLES`` fills the sample weight
memory, ``LOAD_GRID`` the grid registers; ``COLUMN`` makes the shooter's K sample points with the
point unit (:func:`~blockray.sim.points.point_of`) from the record patch memory holds at its
address; each ``RECEIVERS`` slot makes its row's end point (the centroid, or the slot's weights)
the same way, and a slot flagged ``last`` closes the run: for each chunk of S samples one block,
``BEGIN_BLOCK``, ``LOAD_POINTS`` (:func:`~blockray.memory.load_points_commands`), a ``VOXEL`` per
voxel of the integer block walk over the voxel table's counts
(:func:`~blockray.block_walk.walk_block`, the host's reference itself),
``END_BLOCK``. Every other command passes through unchanged, in order.

Cycles (the contract :class:`blockray.rtl.sequencer.BlockSequencer` is tested against;
docs/board-protocol.md, "The sequencer's cycles"): the sequencer does one thing at a time, and
:meth:`BlockSequencer.feed_timed` gives each record the sequencer cycle it is offered in, counting
every cycle but those it waits in for a command or for its record to be taken:

* a command item (a weight triple, the grid, the column, a receiver slot) is taken in one cycle;
  the first weight triple then costs B - 1 more (d^-1 mod 2^B, a bit a cycle);
* a point (each of the column's K, a receiver's) :data:`POINT_CYCLES`: the record and weights
  read, the job given, the point unit's :data:`~blockray.points.POINT_LATENCY`;
* per block: v^3 cycles to clear the visited stamps when the block's tag would wrap (and the
  first block after ``LOAD_GRID``), one cycle a record (BEGIN_BLOCK, each LOAD_POINTS, END_BLOCK),
  :data:`GATHER_CYCLES` a point put in a LOAD_POINTS slot, and the walk's cycles
  (:func:`~blockray.block_walk.walk_block_cycles`: 2 a ray, 1 a box, 1 a voxel of a box).

Every other command passes by the sequencer (no cycles here; the board's own are
:class:`~blockray.timing.BoardTiming`'s).
"""

from ..block_walk import walk_block_cycles
from ..board_rays import STAMP_BITS, RayOp, RayProtocol
from ..errors import ParameterError
from ..memory import load_points_commands
from ..points import POINT_LATENCY, PointArithmetic
from ..protocol import BeginBlock, EndBlock, Op, Voxel
from .points import point_of

__all__ = ["BlockSequencer", "execute", "POINT_CYCLES", "GATHER_CYCLES"]

#: a point: its record (and weights) read, the job taken by the point unit, its latency
POINT_CYCLES = 2 + POINT_LATENCY
#: a point of a LOAD_POINTS record: read from the point memory, put in its slot
GATHER_CYCLES = 2


class BlockSequencer:
    """The sequencer of one board built for ``params``. :meth:`feed` takes one command at a time;
    its state (weights and their D, grid, the column's points, the open run) persists between
    calls, as the board's between link frames. ``cycle``: the sequencer's cycles so far;
    ``stamp_bits``: the visited stamps' width."""

    def __init__(self, params, *, stamp_bits=STAMP_BITS):
        self.protocol = RayProtocol(params)
        self.params = params
        self.weights = self.arithmetic = self.grid = self.column = None
        self.rows = []
        self.cycle, self.tag, self.stamp_bits = 0, 0, stamp_bits    # tag 0: the stamps need clearing

    def expand(self, commands, memory):
        """The internal records of ``commands`` in order. A memory write is executed on ``memory``
        (a :class:`~blockray.sim.model.BoardModel`) at once, so the commands after it read memory
        as written so far; it stays among the records (executed again in order: a write is
        idempotent)."""
        records = []
        for cmd in commands:
            if cmd.op in (Op.WRITE_PATCH, Op.WRITE_VOXEL):
                memory.execute([cmd])
            records += self.feed(cmd, memory)
        return records

    def feed(self, command, memory):
        """The internal records of ``command``, reading patch memory and the voxel table of
        ``memory`` (a :class:`~blockray.sim.model.BoardModel`: ``vertices``, ``count``)."""
        return [record for _, record in self.feed_timed(command, memory)]

    def feed_timed(self, command, memory):
        """``[(cycle, record), ...]``: :meth:`feed`'s records, each with the sequencer cycle it is
        offered in (the module docstring); :attr:`cycle` advances past the command."""
        op = command.op
        if not isinstance(op, RayOp):
            return [(self.cycle, command)]
        if op is RayOp.LOAD_SAMPLES:
            self.weights = [tuple(int(x) for x in w) for w in command.weights]
            self.arithmetic = PointArithmetic(self.params.bits, sum(self.weights[0]))   # D: the weights' sum
            self.column = None
            self.cycle += len(self.weights) + self.params.bits - 1
        elif op is RayOp.LOAD_GRID:
            self.grid = (tuple(command.origin), command.shift, command.v)
            self.cycle, self.tag = self.cycle + 1, 0
        elif op is RayOp.COLUMN:
            if self.rows:
                raise ParameterError("COLUMN with a run of receivers left open (no slot flagged last)")
            if self.weights is None:
                raise ParameterError("COLUMN before LOAD_SAMPLES")
            V = self._record(memory, command.address)
            self.column = [point_of(V, w, self.arithmetic) for w in self.weights]
            self.cycle += 1 + POINT_CYCLES * len(self.column)
        else:
            return self._receivers(command, memory)
        return []

    def _record(self, memory, address):
        if not 0 <= address < len(memory.vertices):
            raise ParameterError(f"patch address {address} is outside patch memory")
        return memory.vertices[address].tolist()

    def _receivers(self, command, memory):
        if self.column is None or self.grid is None:
            raise ParameterError("RECEIVERS before COLUMN or LOAD_GRID")
        D, out = self.arithmetic.denominator, []
        for address, last, w in command.slots:
            if w is None and D % 3:
                raise ParameterError(f"a centroid needs D divisible by 3, not {D}")
            self.rows.append(point_of(self._record(memory, address), w or (D // 3,) * 3, self.arithmetic))
            self.cycle += 1 + POINT_CYCLES
            if len(self.rows) > self.params.rows:
                raise ParameterError(f"a run of more than R = {self.params.rows} receivers")
            if last:
                out += self._blocks(memory)
                self.rows = []
        return out

    def _blocks(self, memory):
        """One block per chunk of S samples for the closed run, each record with its cycle."""
        origin, shift, v = self.grid
        count, S, out = memory.count[:v ** 3], self.params.cols, []
        for c in range(0, len(self.column), S):
            if self.tag in (0, (1 << self.stamp_bits) - 1):        # every stamp cleared to 0, one a cycle
                self.cycle, self.tag = self.cycle + v ** 3, 1
            else:
                self.tag += 1
            out.append(self._offer(BeginBlock()))
            starts = self.column[c:c + S]
            for load in load_points_commands(self.rows, starts):
                self.cycle += GATHER_CYCLES * len(load.slots)
                out.append(self._offer(load))
            voxels, when, cycles = walk_block_cycles(starts, self.rows, origin, shift, v, count)
            out += [(self.cycle + int(t), Voxel(int(i))) for i, t in zip(voxels, when)]
            self.cycle += cycles
            out.append(self._offer(EndBlock()))
        return out

    def _offer(self, record):
        """A record offered in this cycle, which it takes."""
        self.cycle += 1
        return self.cycle - 1, record


def execute(model, commands):
    """Run a stream of both kinds of command on :class:`~blockray.sim.model.BoardModel` ``model``
    through a new sequencer. Returns ``(ExecResult, records)``: the model's result of the internal
    records, and the records."""
    records = BlockSequencer(model.params).expand(commands, model)
    return model.execute(records), records
