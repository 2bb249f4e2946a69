"""The board interface: block rays in, one blocked/clear bit per ray out.

Every back-end (``golden`` float64, ``model`` bit-exact, the driven boards of host_driver/board/driver.py) implements
:class:`Board`, and the host driver talks to nothing else. A **block ray** is the paper's bundle:
the rays from S_b shooter sample points to one end point on each of R_b receiver patches (every
shooter-receiver pair is a ray), together with the voxels the bundle visits. A row's end point is
its patch's centroid, or the point ``receiver_weights[r]`` gives (barycentric integer weights
summing to the sample denominator D, so that it is exact on the board's grid like the samples). The board tests
every patch registered in those voxels against every ray of the block.

Life cycle::

    board.prepare(scene, samples)   # fix the board's geometry (e.g. quantise); sets board.margin
    grid = VoxelGrid(..., margin=board.margin)
    board.load(grid)                # patch memory and voxel tables
    bits = board.run(blocks)        # list of (R_b, S_b) bool arrays, True = blocked
    board.counters()                # dict of measured counters (at least "tests")

``blocks`` is a list of :class:`BlockRay` or a :class:`BlockBatch` (the host's form: many blocks in
flat arrays, which iterates as BlockRay views, so a back-end that loops over blocks takes either).
A back-end may answer a batch with :class:`BlockBits` (all bits in one flat array, a sequence of
the same (R_b, S_b) arrays).
"""

import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from .errors import ParameterError, option
from .fixedpoint import resolve_bits
from .memory import QuantisationWarning, ranges
from .timing import BoardTiming

__all__ = ["BlockRay", "BlockBatch", "BlockBits", "Board", "CountingBoard", "ranges"]


@dataclass
class BlockRay:
    shooter_patch: np.ndarray    # (S_b,) int64: patch of each shooter point (array column)
    shooter_sample: np.ndarray   # (S_b,) int64: sample index on that patch (see SampleScheme)
    receiver_patch: np.ndarray   # (R_b,) int64: receiver patches (array rows)
    voxels: np.ndarray           # (K,) int64: linear voxel indices the bundle visits, in order
    receiver_weights: np.ndarray = None   # (R_b, 3) int64 summing to D: each row's end point; None: centroids

    @property
    def rays(self):
        return len(self.shooter_patch) * len(self.receiver_patch)


def _offsets(counts):
    return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)


class BlockBatch:
    """Many block rays in flat arrays: block b's columns are ``col_off[b]:col_off[b+1]`` of
    ``shooter_patch`` / ``shooter_sample``, its rows ``row_off[b]:row_off[b+1]`` of
    ``receiver_patch`` (and of ``receiver_weights``, (rows, 3), when the rows' end points are not the
centroids), its voxels ``vox_off[b]:vox_off[b+1]`` of ``voxels`` (all int64).

    A sequence of :class:`BlockRay` (views into the arrays); compiled back-ends read the arrays.
    """

    def __init__(self, shooter_patch, shooter_sample, col_off, receiver_patch, row_off, voxels, vox_off,
                 receiver_weights=None):
        a = lambda x: np.ascontiguousarray(x, dtype=np.int64)
        self.shooter_patch, self.shooter_sample, self.col_off = a(shooter_patch), a(shooter_sample), a(col_off)
        self.receiver_patch, self.row_off = a(receiver_patch), a(row_off)
        self.voxels, self.vox_off = a(voxels), a(vox_off)
        self.receiver_weights = None if receiver_weights is None else a(receiver_weights).reshape(-1, 3)

    @classmethod
    def from_blocks(cls, blocks):
        """A batch holding a list of :class:`BlockRay`."""
        if isinstance(blocks, BlockBatch):
            return blocks
        cat = lambda xs: (np.concatenate([np.asarray(x, dtype=np.int64).reshape(-1) for x in xs])
                          if len(xs) else np.zeros(0, np.int64))
        weighted = {b.receiver_weights is not None for b in blocks}
        if len(weighted) > 1:
            raise ValueError("a batch's blocks either all give their rows' end points or none does")
        weights = (np.concatenate([np.asarray(b.receiver_weights, dtype=np.int64).reshape(-1, 3) for b in blocks])
                   if weighted == {True} else None)
        return cls(cat([b.shooter_patch for b in blocks]), cat([b.shooter_sample for b in blocks]),
                   _offsets([len(b.shooter_patch) for b in blocks]),
                   cat([b.receiver_patch for b in blocks]), _offsets([len(b.receiver_patch) for b in blocks]),
                   cat([b.voxels for b in blocks]), _offsets([len(np.asarray(b.voxels).reshape(-1)) for b in blocks]),
                   weights)

    def __len__(self):
        return len(self.col_off) - 1

    def __getitem__(self, b):
        if not -len(self) <= b < len(self):
            raise IndexError(b)
        b %= len(self)
        c, r, v = slice(*self.col_off[b:b + 2]), slice(*self.row_off[b:b + 2]), slice(*self.vox_off[b:b + 2])
        w = None if self.receiver_weights is None else self.receiver_weights[r]
        return BlockRay(self.shooter_patch[c], self.shooter_sample[c], self.receiver_patch[r], self.voxels[v], w)

    def __iter__(self):
        return (self[b] for b in range(len(self)))

    @property
    def cols(self):
        """(B,) shooter points (array columns) of each block."""
        return np.diff(self.col_off)

    @property
    def rows(self):
        """(B,) receivers (array rows) of each block."""
        return np.diff(self.row_off)

    @property
    def ray_off(self):
        """(B + 1,) offsets of each block's rays in a flat array of all rays (row-major (R_b, S_b))."""
        return _offsets(self.rows * self.cols)

    @property
    def rays(self):
        return int((self.rows * self.cols).sum())


class BlockBits:
    """A batch's blocked bits in one flat array (``ray_off`` as :attr:`BlockBatch.ray_off`); a
    sequence of the (R_b, S_b) bool arrays."""

    def __init__(self, flat, rows, cols):
        self.flat = np.asarray(flat, dtype=bool)
        self.rows, self.cols = np.asarray(rows), np.asarray(cols)
        self.ray_off = _offsets(self.rows * self.cols)

    def __len__(self):
        return len(self.rows)

    def __getitem__(self, b):
        return self.flat[self.ray_off[b]:self.ray_off[b + 1]].reshape(self.rows[b], self.cols[b])

    def __iter__(self):
        return (self[b] for b in range(len(self)))

    def __add__(self, other):
        return list(self) + list(other)

    def __radd__(self, other):
        return list(other) + list(self)


class Board(ABC):
    """Answers visibility queries for block rays. See the module docstring for the life cycle."""

    name = "abstract"

    #: registration/traversal margin in scene units the voxel grid must add (set by prepare)
    margin: float = 0.0

    @abstractmethod
    def prepare(self, scene, samples):
        """Take the scene's geometry and the sample scheme; set :attr:`margin`."""

    @abstractmethod
    def load(self, grid):
        """Take the voxel grid's patch registration (voxel -> patch lists)."""

    @abstractmethod
    def run(self, blocks):
        """Return one (R_b, S_b) bool array per block: True where the ray is blocked."""

    @abstractmethod
    def counters(self):
        """Measured counters since prepare: at least ``tests`` (ray-patch tests performed)."""

    def close(self):
        """Release what the board holds (a simulator, serial links); whoever built the board
        closes it (``with board:``)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class CountingBoard(Board):
    """A board of ``params.boards`` boards that keeps the machine's counters the same way,
    whoever computes them (the bit-exact model, or the host driver from the boards' own counter
    snapshots): see :meth:`counters`. Subclasses set ``params`` (``params.bits``: the B asked
    for, None: chosen for the scene), ``max_error``, ``cell``, ``load_cycles``, prepare with
    :meth:`_quantise` and call :meth:`_add_batch` per batch of blocks."""

    def _take(self, params):
        """Build for ``params``; ``params.bits`` is the B every :meth:`_quantise` asks for (None:
        chosen for each scene)."""
        self.params, self._asked_bits = params, params.bits

    def _quantise(self, scene, samples):
        """What every quantising board's ``prepare`` does: the scene on the B-bit grid (B, asked
        for as ``params.bits`` or chosen for the scene, is resolved here, once, and carried by the
        quantised scene and ``params`` from here on; a board prepared again asks for the B of
        its params as given), the grid's margin, the cell's timing (a
        ``_timing`` given at construction wins) and fresh counters. Returns the quantised scene."""
        q = resolve_bits(scene, samples, self._asked_bits, max_error=self.max_error)
        if len(q.collapsed) or len(q.degenerate):
            # reported, not ignored: such patches never block and vertices merged at this grid
            warnings.warn(
                f"scene {scene.name!r} at B = {q.bits} bits: {sum(len(g) for g in q.collapsed)} vertices "
                f"collapse onto {len(q.collapsed)} grid points and {len(q.degenerate)} patches degenerate "
                f"to zero area (they never block); use more {option('bits')} to keep them", QuantisationWarning)
        self.quantised, self.samples, self.margin = q, samples, q.margin
        self.params = self.params.with_(bits=q.bits)
        self.timing = getattr(self, "_timing", None) or BoardTiming.for_cell(self.cell)
        self._reset_counters()
        return q

    def check_block(self, block):
        """(R_b, S_b) of a block ray; ParameterError if it does not fit the array."""
        p = self.params
        Rb, Sb = len(block.receiver_patch), len(block.shooter_patch)
        if Rb > p.rows or Sb > p.cols:
            raise ParameterError(f"block of {Rb} receivers x {Sb} shooter points exceeds the "
                                 f"{p.rows} x {p.cols} array ({option('rows')}/{option('cols')}); the host must split it")
        return Rb, Sb

    def _add_batch(self, batch):
        """Account one batch: per-board board cycles ``batch`` (P,); the machine waits for the
        slowest board and the drain of its last END_BLOCK (``drain_latency``: what the host
        knows from the counters; a filtering cell's last result may leave its array later)."""
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
            "cell": self._cell_name(),
            "drain_latency": self.timing.drain_latency if self.timing else None,
            "quantisation": self.quantised.report() if self.quantised else None,
        }

    def _cell_name(self):
        """The boards' processor cell with its filter's format (``--board ulx3s``: the bitstream's)."""
        cell = getattr(self, "cell", None)
        if cell is None:
            return None
        return str(cell if self.params.bits is None else cell.at(self.params.bits))

    def _reset_counters(self):
        P = self.params.boards
        self._cycles = 0
        self._cycles_b = np.zeros(P, dtype=np.int64)
        self._issued_b = np.zeros(P, dtype=np.int64)
        self._useful_b = np.zeros(P, dtype=np.int64)
        self._blocks = 0
        self._rays = 0
