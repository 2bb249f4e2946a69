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

Cycles: the records cost what they cost today (:class:`~blockray.timing.BoardTiming`); the
sequencer's own cycles (points, walk) are not modelled yet.
"""

from ..block_walk import walk_block
from ..board_rays import RayOp, RayProtocol
from ..errors import ParameterError
from ..memory import load_points_commands
from ..points import PointArithmetic
from ..protocol import BeginBlock, EndBlock, Op, Voxel
from .points import point_of

__all__ = ["BlockSequencer", "execute"]


class BlockSequencer:
    """The sequencer of one board built for ``params``. :meth:`feed` takes one command at a time;
    its state (weights and their D, grid, the column's points, the open run) persists between
    calls, as the board's between link frames."""

    def __init__(self, params):
        self.protocol = RayProtocol(params)
        self.params = params
        self.weights = self.arithmetic = self.grid = self.column = None
        self.rows = []

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
        op = command.op
        if not isinstance(op, RayOp):
            return [command]
        if op is RayOp.LOAD_SAMPLES:
            self.weights = [tuple(int(x) for x in w) for w in command.weights]
            self.arithmetic = PointArithmetic(self.params.bits, sum(self.weights[0]))   # D: the weights' sum
            self.column = None
        elif op is RayOp.LOAD_GRID:
            self.grid = (tuple(command.origin), command.shift, command.v)
        elif op is RayOp.COLUMN:
            if self.rows:
                raise ParameterError("COLUMN with a run of receivers left open (no slot flagged last)")
            if self.weights is None:
                raise ParameterError("COLUMN before LOAD_SAMPLES")
            V = self._record(memory, command.address)
            self.column = [point_of(V, w, self.arithmetic) for w in self.weights]
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
            if len(self.rows) > self.params.rows:
                raise ParameterError(f"a run of more than R = {self.params.rows} receivers")
            if last:
                out += self._blocks(memory)
                self.rows = []
        return out

    def _blocks(self, memory):
        """One block per chunk of S samples for the closed run."""
        origin, shift, v = self.grid
        count, S, out = memory.count[:v ** 3], self.params.cols, []
        for c in range(0, len(self.column), S):
            starts = self.column[c:c + S]
            voxels = walk_block(starts, self.rows, origin, shift, v, count)
            out += ([BeginBlock()] + load_points_commands(self.rows, starts)
                    + [Voxel(int(i)) for i in voxels] + [EndBlock()])
        return out


def execute(model, commands):
    """Run a stream of both kinds of command on :class:`~blockray.sim.model.BoardModel` ``model``
    through a new sequencer. Returns ``(ExecResult, records)``: the model's result of the internal
    records, and the records."""
    records = BlockSequencer(model.params).expand(commands, model)
    return model.execute(records), records
