"""The bit-exact board model: exactly what the hardware computes, with the same cycle counts.

Two levels:

* :class:`BoardModel` is **one board** driven by its command stream, the RTL-facing contract. An
  RTL testbench feeds the same list of :class:`Command` to the RTL and to
  :meth:`BoardModel.execute` and compares result words and cycle counts with zero tolerance.
* :class:`ModelBoard` is the host's :class:`~blockray.host_driver.board.Board`: ``P`` boards,
  each holding a disjoint part of the voxels' patch records (:func:`partition_records`), run block rays and OR their
  bits. It computes the same memories, bits and cycles as building each board's command stream and
  executing it (a test checks that), but gathers a whole block's records at once.

Command stream (one board; opcodes :class:`blockray.timing.Op`; costs :class:`blockray.timing.BoardTiming`)::

    WRITE_PATCH   index=address  value=packed patch record (patch_layout(B), an int)
    WRITE_VOXEL   index=voxel    value=(start, count)     voxel-table entry: records start..start+count-1
    BEGIN_BLOCK                                           clear accumulators and row/column valid masks
    LOAD_RECEIVER index=row      value=(x, y, z)          receiver end point Q of row r; row r valid
    LOAD_SHOOTER  index=col      value=(x, y, z)          shooter sample point P of column s; column s valid
    LOAD_POINTS   value=((shooter, index, (x, y, z)), ...) up to POINTS_PER_LOAD of the two loads above at once
    VOXEL         index=voxel                             stream the voxel's records to all R x S processors
    END_BLOCK                                             emit the R x S result word (drain_latency later)
    READ_COUNTERS                                         emit a counter snapshot covering the commands before it

Result word: bit ``r * S + s`` is 1 when the ray from shooter column s to receiver row r is blocked
by some streamed record (rows/columns not loaded in the block are 0).

Memory layout of a board: patch records in voxel order (a patch registered in k voxels occupies k
words over the boards; within a voxel in increasing patch id) and a voxel table of (start, count)
per voxel.

Partition (:data:`PARTITIONS`): ``deal`` (default) deals every voxel's records round robin over
the P boards (registration k of the whole table, in voxel order, goes to board k % P), so a
voxel's counts on the boards differ by at most one and the boards stream their shares of a block
in equal time; ``patch`` puts every record of patch i on board i % P (the paper's "partition of
the patches"), whose per-voxel counts can be far apart. Either way every (voxel, patch)
registration is on exactly one board, so the OR of the boards' words is the same.
Voxel linear index: ``(ix * v + iy) * v + iz``.

Counters: ``tests_issued`` = R x S per record streamed (every processor sees every broadcast, used
or not); ``tests_useful`` = real rays x records streamed; ``utilization`` = useful / (processors x
cycles). The host sends each batch of blocks (one :meth:`ModelBoard.run`) to every board without
waiting, and waits for the last result word: a batch's machine time is the slowest board's board
cycles for the batch plus the drain of its last END_BLOCK (``drain_latency``); ``board_cycles``
sums that over batches. Memory loading is counted apart (``load_cycles``).
"""

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import CapacityError, ParameterError
from ..fixedpoint import DEFAULT_MAX_ERROR, resolve_bits
from ..params import BoardParams
from ..records import patch_layout, patch_columns, pack_array, unpack_array
from ..timing import POINTS_PER_LOAD, BoardTiming, Op
from ..host_driver.board import Board, BlockBatch, BlockBits, ranges as _ranges
from . import kernel


def _cube_root_floor(n):
    """The largest v with v**3 <= n."""
    v = round(n ** (1 / 3))
    while v ** 3 > n:
        v -= 1
    while (v + 1) ** 3 <= n:
        v += 1
    return v


class QuantisationWarning(UserWarning):
    """The chosen bits merge vertices or flatten patches of the scene."""

__all__ = ["Command", "ExecResult", "BoardModel", "ModelBoard", "registration", "load_points_commands",
           "partition_records", "check_partition", "PARTITIONS"]

@dataclass(frozen=True)
class Command:
    op: Op
    index: int = 0
    value: object = None


@dataclass
class ExecResult:
    words: list = field(default_factory=list)        # one int per END_BLOCK (bit r*S + s)
    blocked: list = field(default_factory=list)      # the same as (R, S) bool arrays
    cycles: int = 0                                   # board cycles of the whole stream
    starts: list = field(default_factory=list)       # cycle at which each command began
    tests_issued: int = 0
    tests_useful: int = 0
    busy: int = 0                                     # cycles that issued a patch record
    counters: list = field(default_factory=list)     # one dict per READ_COUNTERS (cycles, busy, tests_issued, tests_useful)


def result_word(bits):
    """(R, S) bool -> int with bit r*S + s set where blocked."""
    flat = np.asarray(bits, dtype=bool).ravel()
    return int(sum(1 << int(i) for i in np.flatnonzero(flat)))


def _any_blocked(P, Q, V, n):
    """OR over records of the exact predicate: (R, S) bool (the compiled kernel)."""
    return kernel.any_blocked(np.ascontiguousarray(P, dtype=np.int64), np.ascontiguousarray(Q, dtype=np.int64),
                              np.ascontiguousarray(V, dtype=np.int64), np.ascontiguousarray(n, dtype=np.int64))


class BoardModel:
    """One board: patch memory, voxel table, an R x S processor array, driven by commands.

    Memory contents are the unpacked patch records (``vertices``, ``normals``), so what the model
    tests is what the packed memory image holds.
    """

    def __init__(self, params, timing=None):
        self.params = params
        self.timing = timing or BoardTiming.for_bits(params.bits)
        self.layout = patch_layout(params.bits)
        self.vertices = np.zeros((params.patch_depth, 3, 3), dtype=np.int64)
        self.normals = np.zeros((params.patch_depth, 3), dtype=np.int64)
        self.start = np.zeros(params.voxel_depth, dtype=np.int64)
        self.count = np.zeros(params.voxel_depth, dtype=np.int64)
        self._begin()

    def _begin(self):
        R, S = self.params.rows, self.params.cols
        self.receivers = np.zeros((R, 3), dtype=np.int64)
        self.shooters = np.zeros((S, 3), dtype=np.int64)
        self.row_valid = np.zeros(R, dtype=bool)
        self.col_valid = np.zeros(S, dtype=bool)
        self.pending = []

    def load_memory(self, vertices, normals, start, count):
        """Bulk memory load (same state as the WRITE_PATCH / WRITE_VOXEL commands)."""
        n, v = len(vertices), len(start)
        self.vertices[:n] = vertices
        self.normals[:n] = normals
        self.start[:v] = start
        self.count[:v] = count

    def _check_voxel(self, v):
        if not 0 <= v < self.params.voxel_depth:
            raise ParameterError(f"voxel {v} is outside the voxel table (voxel_depth {self.params.voxel_depth})")

    def execute(self, commands):
        """Run a command stream; return an :class:`ExecResult` (results, cycles, per-command starts)."""
        p, t = self.params, self.timing
        R, S = p.rows, p.cols
        res = ExecResult()
        for cmd in commands:
            op = Op(cmd.op)
            res.starts.append(res.cycles)
            count = 0
            if op is Op.WRITE_PATCH:
                if not 0 <= cmd.index < p.patch_depth:
                    raise ParameterError(f"patch address {cmd.index} is outside patch memory (patch_depth {p.patch_depth})")
                cols = unpack_array(self.layout, [cmd.value])
                self.vertices[cmd.index] = [[cols[(k, a)][0] for a in "xyz"] for k in ("v0", "v1", "v2")]
                self.normals[cmd.index] = [cols[("normal", a)][0] for a in "xyz"]
            elif op is Op.WRITE_VOXEL:
                self._check_voxel(cmd.index)
                start, n = cmd.value
                if start < 0 or n < 0 or start + n > p.patch_depth:
                    raise ParameterError(f"voxel entry ({start}, {n}) is outside patch memory (patch_depth {p.patch_depth})")
                self.start[cmd.index], self.count[cmd.index] = start, n
            elif op is Op.BEGIN_BLOCK:
                self._begin()
            elif op is Op.LOAD_RECEIVER:
                self.receivers[cmd.index] = cmd.value
                self.row_valid[cmd.index] = True
            elif op is Op.LOAD_SHOOTER:
                self.shooters[cmd.index] = cmd.value
                self.col_valid[cmd.index] = True
            elif op is Op.LOAD_POINTS:
                for shooter, where, point in cmd.value:       # in order: a later slot wins
                    if shooter:
                        self.shooters[where] = point
                        self.col_valid[where] = True
                    else:
                        self.receivers[where] = point
                        self.row_valid[where] = True
            elif op is Op.VOXEL:
                self._check_voxel(cmd.index)
                count = int(self.count[cmd.index])
                self.pending.append((int(self.start[cmd.index]), count))
                res.tests_issued += R * S * count
                res.busy += count
                res.tests_useful += int(self.row_valid.sum()) * int(self.col_valid.sum()) * count
            elif op is Op.END_BLOCK:
                bits = self._evaluate()
                res.blocked.append(bits)
                res.words.append(result_word(bits))
            elif op is Op.READ_COUNTERS:
                res.counters.append({"cycles": res.cycles, "busy": res.busy,
                                     "tests_issued": res.tests_issued, "tests_useful": res.tests_useful})
            res.cycles += t.cost(op, count)
        return res

    def _evaluate(self):
        rows, cols = np.flatnonzero(self.row_valid), np.flatnonzero(self.col_valid)
        out = np.zeros((self.params.rows, self.params.cols), dtype=bool)
        if self.pending and len(rows) and len(cols):
            starts, counts = zip(*self.pending)
            idx = _ranges(starts, counts)
            sub = _any_blocked(self.shooters[cols], self.receivers[rows], self.vertices[idx], self.normals[idx])
            out[np.ix_(rows, cols)] = sub
        return out


def load_points_commands(receivers, shooters):
    """LOAD_POINTS commands loading receiver rows 0.. with ``receivers`` (R_b, 3) and shooter
    columns 0.. with ``shooters`` (S_b, 3), :data:`POINTS_PER_LOAD` points per command."""
    slots = [(False, r, tuple(int(c) for c in pt)) for r, pt in enumerate(receivers)]
    slots += [(True, s, tuple(int(c) for c in pt)) for s, pt in enumerate(shooters)]
    return [Command(Op.LOAD_POINTS, 0, tuple(slots[i:i + POINTS_PER_LOAD]))
            for i in range(0, len(slots), POINTS_PER_LOAD)]


PARTITIONS = ("deal", "patch")


def check_partition(partition):
    """``partition`` if it names one of :data:`PARTITIONS`, else ParameterError."""
    if partition not in PARTITIONS:
        raise ParameterError(f"--partition must be one of {', '.join(PARTITIONS)}, not {partition!r}",
                             parameter="partition")
    return partition


def partition_records(voxels, patches, boards, partition="deal"):
    """The board (0 .. boards-1) of each registration ``(voxels[k], patches[k])``, sorted by voxel
    then patch as :func:`registration` gives them (see the module docstring)."""
    if check_partition(partition) == "patch":
        return np.asarray(patches, dtype=np.int64) % boards
    return np.arange(len(voxels), dtype=np.int64) % boards


def registration(grid):
    """A voxel grid's registration as ``(voxel, patch)`` int64 arrays sorted by voxel, then patch,
    and the number of voxels.

    Accepts a grid with CSR arrays (``start``/``count``/``patches``, or ``offsets``/``patches``)
    or ``voxel_patches`` (a list of patch-id arrays, one per voxel).
    """
    count = getattr(grid, "count", None)
    if hasattr(grid, "voxel_patches"):
        lists = [np.asarray(x, dtype=np.int64) for x in grid.voxel_patches]
        nvox = len(lists)
        vox = np.repeat(np.arange(nvox), [len(x) for x in lists])
        pat = np.concatenate(lists) if lists else np.zeros(0, dtype=np.int64)
    elif hasattr(grid, "patches") and (hasattr(grid, "start") or hasattr(grid, "offsets")) and count is not None:
        count = np.asarray(count, dtype=np.int64)
        start = np.asarray(grid.start if hasattr(grid, "start") else grid.offsets[:-1], dtype=np.int64)
        nvox = len(count)
        vox = np.repeat(np.arange(nvox), count)
        pat = np.asarray(grid.patches, dtype=np.int64)[_ranges(start, count)]
    else:
        raise TypeError(f"cannot read the patch registration of {type(grid).__name__}")
    order = np.lexsort((pat, vox))
    return vox[order], pat[order], nvox


class ModelBoard(Board):
    """P bit-exact boards behind the host's Board interface (``--board model``).

    ``bits=None`` chooses B per scene (:func:`blockray.fixedpoint.choose_bits`); an int forces it
    (``--bits``). ``params.bits`` is replaced by the B actually used. ``partition``: how the
    patch records are spread over the P boards (:data:`PARTITIONS`, ``--partition``).
    """

    name = "model"

    def __init__(self, params=None, *, bits=None, timing=None, max_error=DEFAULT_MAX_ERROR, partition="deal"):
        self.params = params or BoardParams()
        self.bits = bits
        self.partition = check_partition(partition)
        self.max_error = max_error
        self._timing = timing
        self.timing = None
        self.quantised = None
        self.margin = 0.0
        self.memories = None
        self._reset_counters()

    # -- Board interface -------------------------------------------------------------------------

    def prepare(self, scene, samples):
        q = resolve_bits(scene, samples, self.bits, max_error=self.max_error)
        if len(q.collapsed) or len(q.degenerate):
            # reported, not ignored: such patches never block and vertices merged at this grid
            warnings.warn(
                f"scene {scene.name!r} at B = {q.bits} bits: {sum(len(g) for g in q.collapsed)} vertices "
                f"collapse onto {len(q.collapsed)} grid points and {len(q.degenerate)} patches degenerate "
                f"to zero area (they never block); use more --bits to keep them", QuantisationWarning)
        self.quantised = q
        self.samples = samples
        self.params = self.params.with_(bits=q.bits)
        self.timing = self._timing or BoardTiming.for_bits(q.bits)
        # The host registers float triangles and traverses float rays; the quantised triangle and
        # segment lie within max(displacement) of them (convex combinations with the same weights),
        # so a margin of that much covers every hit point. The slack covers float rounding.
        self.margin = max(q.displacement, q.end_displacement) * (1 + 1e-9) + 1e-12 * q.diagonal
        self.memories = None
        self._reset_counters()

    def load(self, grid):
        if self.quantised is None:
            raise RuntimeError("prepare() before load()")
        q, p = self.quantised, self.params
        vox, pat, nvox = registration(grid)
        if nvox > p.voxel_depth:
            raise CapacityError(f"voxel table: {nvox} voxels do not fit the board's "
                                f"voxel_depth {p.voxel_depth}; use --voxels {_cube_root_floor(p.voxel_depth)} or fewer")
        self.memories = []
        owner = partition_records(vox, pat, p.boards, self.partition)
        for b in range(p.boards):
            mine = owner == b
            rec = pat[mine]
            if len(rec) > p.patch_depth:
                raise CapacityError(
                    f"patch memory of board {b}: {len(rec)} patch records (registrations) do not fit "
                    f"patch_depth {p.patch_depth}; use more --boards or fewer --voxels (each voxel a patch "
                    f"touches costs a record)")
            count = np.bincount(vox[mine], minlength=nvox).astype(np.int64)
            start = np.cumsum(count) - count
            self.memories.append({"patch": rec, "start": start, "count": count})
        # all boards' records in one array (board b at offset[b]) for one gather per block
        self._offset = np.cumsum([0] + [len(m["patch"]) for m in self.memories])
        allrec = np.concatenate([m["patch"] for m in self.memories])
        self._V = q.vertices[allrec]
        self._n = q.normals[allrec]
        self._start = np.stack([m["start"] + o for m, o in zip(self.memories, self._offset)])   # (P, nvox)
        self._count = np.stack([m["count"] for m in self.memories])                          # (P, nvox)
        self.load_cycles = [len(m["patch"]) + nvox for m in self.memories]

    def check_block(self, block):
        """(R_b, S_b) of a block ray; ParameterError if it does not fit the array."""
        p = self.params
        Rb, Sb = len(block.receiver_patch), len(block.shooter_patch)
        if Rb > p.rows or Sb > p.cols:
            raise ParameterError(f"block of {Rb} receivers x {Sb} shooter points exceeds the "
                                 f"{p.rows} x {p.cols} array (--rows/--cols); the host must split it")
        return Rb, Sb

    def run(self, blocks):
        """Blocked bits of a batch (a list of BlockRay or a BlockBatch), as :class:`BlockBits`."""
        if self.memories is None:
            raise RuntimeError("load() before run()")
        q, p = self.quantised, self.params
        batch = BlockBatch.from_blocks(blocks)
        Rb, Sb = batch.rows, batch.cols
        too_big = np.flatnonzero((Rb > p.rows) | (Sb > p.cols))
        if len(too_big):
            self.check_block(batch[int(too_big[0])])
        bits, records, streamed = kernel.run_blocks(
            q.shooters, q.receivers, batch.col_off, batch.shooter_patch, batch.shooter_sample,
            batch.row_off, batch.receiver_patch, batch.vox_off, batch.voxels,
            self._start, self._count, self._V, self._n, batch.ray_off)
        # cycles and counters depend on the records streamed only, never on the tests' results
        self._add_batch(self.timing.blocks_cycles(Rb, Sb, streamed).sum(axis=0))
        self._issued_b += p.processors * records.sum(axis=0)
        self._useful_b += ((Rb * Sb)[:, None] * records).sum(axis=0)
        self._blocks += len(batch)
        self._rays += int((Rb * Sb).sum())
        return BlockBits(bits, Rb, Sb)

    def _add_batch(self, batch):
        """Account one batch: per-board board cycles ``batch`` (P,); the machine waits for the
        slowest board and the drain of its last END_BLOCK."""
        if batch.any():
            self._cycles_b += batch
            self._cycles += int(batch.max()) + self.timing.drain_latency

    def counters(self):
        p = self.params
        procs = p.processors
        util_b = [float(u) / (procs * c) if c else 0.0 for u, c in zip(self._useful_b, self._cycles_b)]
        useful = int(self._useful_b.sum())
        return {
            "tests": useful,
            "tests_useful": useful,
            "tests_issued": int(self._issued_b.sum()),
            "board_cycles": int(self._cycles),
            "utilization": useful / (procs * p.boards * self._cycles) if self._cycles else 0.0,
            "board_cycles_per_board": [int(c) for c in self._cycles_b],
            "tests_issued_per_board": [int(c) for c in self._issued_b],
            "tests_useful_per_board": [int(c) for c in self._useful_b],
            "utilization_per_board": util_b,
            "load_cycles_per_board": list(getattr(self, "load_cycles", [])),
            "blocks": self._blocks,
            "rays": self._rays,
            "bits": p.bits,
            "drain_latency": self.timing.drain_latency if self.timing else None,
            "quantisation": self.quantised.report() if self.quantised else None,
        }

    # -- RTL-facing helpers ----------------------------------------------------------------------

    def _reset_counters(self):
        P = self.params.boards
        self._cycles = 0
        self._cycles_b = np.zeros(P, dtype=np.int64)
        self._issued_b = np.zeros(P, dtype=np.int64)
        self._useful_b = np.zeros(P, dtype=np.int64)
        self._blocks = 0
        self._rays = 0

    def memory_image(self, board):
        """Board ``board``'s memory as the RTL loads it: packed patch words (patch_layout(B)),
        voxel-table starts and counts, and the patch id of each word."""
        m = self.memories[board]
        q = self.quantised
        words = pack_array(patch_layout(self.params.bits),
                           patch_columns(q.vertices[m["patch"]], q.normals[m["patch"]]))
        return {"patch": words, "start": m["start"].copy(), "count": m["count"].copy(),
                "patch_id": m["patch"].copy()}

    def load_commands(self, board):
        """WRITE_PATCH / WRITE_VOXEL commands that fill board ``board``'s memories."""
        img = self.memory_image(board)
        cmds = [Command(Op.WRITE_PATCH, a, w) for a, w in enumerate(img["patch"])]
        cmds += [Command(Op.WRITE_VOXEL, v, (int(s), int(c)))
                 for v, (s, c) in enumerate(zip(img["start"], img["count"]))]
        return cmds

    def block_commands(self, block):
        """The command stream of one block ray (the same for every board)."""
        q = self.quantised
        P = q.shooters[block.shooter_patch, block.shooter_sample]
        Q = q.receivers[block.receiver_patch]
        cmds = [Command(Op.BEGIN_BLOCK)]
        cmds += load_points_commands(Q, P)
        cmds += [Command(Op.VOXEL, int(v)) for v in block.voxels]
        cmds.append(Command(Op.END_BLOCK))
        return cmds

    def board_model(self, board):
        """A :class:`BoardModel` whose memories hold board ``board``'s partition (bulk-loaded)."""
        m = self.memories[board]
        q = self.quantised
        bm = BoardModel(self.params, self.timing)
        bm.load_memory(q.vertices[m["patch"]], q.normals[m["patch"]], m["start"], m["count"])
        return bm
