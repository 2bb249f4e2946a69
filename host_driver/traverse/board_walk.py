"""The integer block traverse the board can make itself (``--traversal board``): the reference the
board's block sequencer (sim/sequencer.py, then the RTL) equals bit for bit.

The host's float traversal (walk.py) walks float rays with a registration margin; a board holds
only integers. Here everything is on the scene's B-bit lattice (:mod:`blockray.fixedpoint`):

* **The grid** (:class:`LatticeGrid`): v x v x v voxels of edge L = 2^e lattice units from an
  integer ``origin``; voxel i on an axis is the closed interval [origin + i L, origin + (i + 1) L].
  The quantised triangles are registered in every voxel their closed triangle touches (the float
  registration of :class:`~.voxel.VoxelGrid` in lattice coordinates, margin 0: its rounding
  tolerance adds voxels, never drops one).
* **A ray** P -> Q (integer end points) visits exactly the voxels whose closed box the closed
  segment touches: an integer 3D DDA over the grid planes it crosses, event times compared as
  fractions by cross-multiplication (no division), simultaneous crossings merged, so rays along
  planes, through edges and corners, axis-parallel or of zero length are exact. At t = 0 and at
  each crossing it visits the box of voxels the point lies in (up to 2 x 2 x 2), x outer, z inner.
* **A block** (R_b rows x S_b columns) walks its rays in blocked-word order (row r outer, column s
  inner) and emits each voxel the first time any ray visits it, empty ones (count 0) skipped with
  ``nonempty_only``: a stamp per voxel-table entry, the board's visited bit.

Conservative: a ray that hits a patch at X passes through a voxel box holding X, the patch touches
that box, so the patch is registered there and the ray visits it.
"""

import math

import numpy as np
from numba import njit

from ...errors import ParameterError, option
from .voxel import VoxelGrid

__all__ = ["LatticeGrid", "lattice_shift", "walk_block", "board_grid"]


def lattice_shift(extent, voxels, bits):
    """The voxel edge exponent e (0 .. B): the largest edge 2^e that cuts ``extent`` lattice units
    into at least ``voxels`` voxels (the nearer, coarser edge halves the array's rate on cornell,
    benchmarks/bench_board_rays.py)."""
    if extent <= 0:
        return 0
    return int(min(max(math.floor(math.log2(extent / voxels)), 0), bits))


class LatticeGrid:
    """The voxel grid on the B-bit lattice and its registration of a quantised scene ``q``.

    ``shift``: e (voxel edge 2^e units, 0 .. B); ``v``: voxels per axis (1 .. 256); ``origin``: the
    integer corner of voxel (0, 0, 0). Every vertex must lie inside [origin, origin + v 2^e].
    Offers what :class:`~blockray.memory.BoardMemories` and the host's block packing read of a grid
    (``v``, ``count``, ``start``, ``patches``, ``voxels``, ``voxel_of``, ``cell_of``,
    ``traverse_blocks``, ``rays_counts``), with integer points.
    """

    def __init__(self, q, *, shift, v, origin=(0, 0, 0)):
        for name, x in (("shift", shift), ("v", v)):
            if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
                raise ParameterError(f"lattice grid: {name} must be an integer, not {x!r}", parameter=name)
        if not 0 <= shift <= q.bits:
            raise ParameterError(f"lattice grid: shift must be 0 to B = {q.bits}, not {shift}", parameter="shift")
        if not 1 <= v <= 256:
            raise ParameterError(f"lattice grid: v must be 1 to 256, not {v}", parameter="voxels")
        self.origin = np.array(origin, dtype=np.int64).reshape(3)
        self.shift, self.v, self.edge = int(shift), int(v), 1 << int(shift)
        far = self.origin + self.v * self.edge
        if len(q.vertices) and ((q.vertices < self.origin).any() or (q.vertices > far).any()):
            raise ParameterError(f"lattice grid: the scene lies outside [{self.origin.tolist()}, {far.tolist()}]",
                                 parameter="voxels")
        reg = VoxelGrid(q.vertices.astype(np.float64), self.v, lo=self.origin.astype(np.float64),
                        hi=far.astype(np.float64))
        self.count, self.start, self.patches = reg.count, reg.start, reg.patches

    @classmethod
    def for_scene(cls, q, voxels):
        """The grid from origin 0 whose edge is :func:`lattice_shift`'s power of two for the scene's
        largest extent over ``voxels``, and just enough voxels to cover the scene."""
        extent = int(q.vertices.max(initial=0))
        shift = lattice_shift(extent, voxels, q.bits)
        while -(-extent // (1 << shift)) > 256:         # the table's limit, as VoxelGrid's
            shift += 1
        return cls(q, shift=shift, v=max(1, -(-extent // (1 << shift))))

    @property
    def voxels(self):
        return self.v ** 3

    def cell_of(self, points):
        """(M, 3) voxel coordinates of integer points (the voxel whose half-open box holds each),
        clamped into the grid."""
        p = np.asarray(points, dtype=np.int64).reshape(-1, 3) - self.origin
        return np.clip(p >> self.shift, 0, self.v - 1)

    def voxel_of(self, points):
        ijk = self.cell_of(points)
        return (ijk[:, 0] * self.v + ijk[:, 1]) * self.v + ijk[:, 2]

    def ray_voxels(self, p, q):
        """The voxels the segment p -> q (integer points) touches, in walk order."""
        return self.traverse_blocks([p], [0, 1], [q], [0, 1])[0]

    def rays_counts(self, P, Q):
        """Per segment P[i] -> Q[i]: the voxels it visits and the records they hold (the traversal
        statistics' per-ray walk)."""
        one = np.arange(len(P) + 1)
        return self.traverse_blocks(P, one, Q, one)[2:]

    def traverse_blocks(self, starts, start_off, ends, end_off, *, nonempty_only=False):
        """Block rays b = (starts[start_off[b]:start_off[b+1]], ends[end_off[b]:end_off[b+1]]),
        integer points. Returns ``(voxels, offsets, visited, tests)`` as
        :meth:`VoxelGrid.traverse_blocks`: block b's voxels ``voxels[offsets[b]:offsets[b+1]]``,
        the voxels it visits and the records they hold."""
        S = np.ascontiguousarray(starts, dtype=np.int64).reshape(-1, 3)
        E = np.ascontiguousarray(ends, dtype=np.int64).reshape(-1, 3)
        return _walk_blocks(S, np.asarray(start_off, dtype=np.int64), E, np.asarray(end_off, dtype=np.int64),
                            self.origin, self.shift, self.v, self.count, bool(nonempty_only))


def board_grid(board, voxels):
    """``--traversal board``'s grid: :meth:`LatticeGrid.for_scene` of the board's quantised scene."""
    q = getattr(board, "quantised", None)
    if q is None:
        raise ParameterError(f"{option('traversal')} board needs a board that holds the scene on its integer "
                             f"grid (not {getattr(board, 'name', 'this board')!r})", parameter="traversal")
    return LatticeGrid.for_scene(q, voxels)


def walk_block(starts, ends, origin, shift, v, count, *, nonempty_only=True):
    """One block's voxels (int64, in walk order) on the grid (``origin``, ``shift``, ``v``) whose
    voxel table holds ``count`` records per voxel (v^3 entries): what the board's sequencer
    streams for rows ``ends`` (R_b, 3) and columns ``starts`` (S_b, 3)."""
    S = np.ascontiguousarray(starts, dtype=np.int64).reshape(-1, 3)
    E = np.ascontiguousarray(ends, dtype=np.int64).reshape(-1, 3)
    return _walk_blocks(S, np.array([0, len(S)]), E, np.array([0, len(E)]), np.asarray(origin, dtype=np.int64),
                        int(shift), int(v), np.ascontiguousarray(count, dtype=np.int64), nonempty_only)[0]


@njit(cache=True)
def _emit(lo, hi, v, count, nonempty_only, stamp, tag, out, o, tally):
    """Visit the voxels of the index box [lo, hi] (clipped to the grid), x outer, z inner: those
    not stamped ``tag`` yet are stamped, counted in tally (visited, tests) and, if kept, written
    to ``out[o:]``. Returns the new o."""
    x0, x1 = max(lo[0], 0), min(hi[0], v - 1)
    y0, y1 = max(lo[1], 0), min(hi[1], v - 1)
    z0, z1 = max(lo[2], 0), min(hi[2], v - 1)
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            for iz in range(z0, z1 + 1):
                i = (ix * v + iy) * v + iz
                if stamp[i] == tag:
                    continue
                stamp[i] = tag
                tally[0] += 1
                tally[1] += count[i]
                if count[i] > 0 or not nonempty_only:
                    out[o] = i
                    o += 1
    return o


@njit(cache=True)
def _walk_ray(p, q, origin, e, v, count, nonempty_only, stamp, tag, out, o, tally):
    """The integer DDA of one segment p -> q (see the module docstring). Returns the new o."""
    L = np.int64(1) << e
    lo, hi = np.empty(3, np.int64), np.empty(3, np.int64)
    cell, plane = np.empty(3, np.int64), np.empty(3, np.int64)     # open cell, next plane's index
    num, den = np.zeros(3, np.int64), np.ones(3, np.int64)          # next crossing t = num / den
    live = np.zeros(3, np.bool_)
    for c in range(3):
        x, d = p[c] - origin[c], q[c] - p[c]
        lo[c], hi[c] = -((-x) >> e) - 1, x >> e                     # ceil(x / L) - 1, floor(x / L)
        if d > 0:
            cell[c] = hi[c]
            plane[c] = cell[c] + 1
        elif d < 0:
            cell[c] = lo[c]
            plane[c] = cell[c]
    o = _emit(lo, hi, v, count, nonempty_only, stamp, tag, out, o, tally)
    while True:
        for c in range(3):                          # the next crossing of each moving axis, if t <= 1
            x, d = p[c] - origin[c], q[c] - p[c]
            live[c] = d != 0 and (plane[c] * L - x) * (1 if d > 0 else -1) <= abs(d)
            if live[c]:
                num[c], den[c] = (plane[c] * L - x) * (1 if d > 0 else -1), abs(d)
        first = -1
        for c in range(3):
            if live[c] and (first < 0 or num[c] * den[first] < num[first] * den[c]):
                first = c
        if first < 0:
            return o
        for c in range(3):
            d = q[c] - p[c]
            if live[c] and num[c] * den[first] == num[first] * den[c]:
                lo[c], hi[c] = plane[c] - 1, plane[c]               # on the plane: both neighbours
                cell[c] = plane[c] if d > 0 else plane[c] - 1
                plane[c] += 1 if d > 0 else -1
            elif d != 0:
                lo[c] = hi[c] = cell[c]
        o = _emit(lo, hi, v, count, nonempty_only, stamp, tag, out, o, tally)


@njit(cache=True)
def _walk_blocks(S, s_off, E, e_off, origin, e, v, count, nonempty_only):
    """Every block's voxels (each once, rays row-major), CSR; visited and tests per block."""
    B = len(s_off) - 1
    nvox = v * v * v
    stamp = np.full(nvox, -1, np.int64)
    out = np.empty(max(nvox, 1024), np.int64)
    off = np.zeros(B + 1, np.int64)
    visited, tests = np.zeros(B, np.int64), np.zeros(B, np.int64)
    tally = np.zeros(2, np.int64)
    o = 0
    for b in range(B):
        if len(out) - o < nvox:                     # room for a block that visits every voxel
            grown = np.empty(2 * len(out) + nvox, np.int64)
            grown[:o] = out[:o]
            out = grown
        tally[:] = 0
        for r in range(e_off[b], e_off[b + 1]):
            for s in range(s_off[b], s_off[b + 1]):
                o = _walk_ray(S[s], E[r], origin, e, v, count, nonempty_only, stamp, b, out, o, tally)
        off[b + 1] = o
        visited[b], tests[b] = tally[0], tally[1]
    return out[:o].copy(), off, visited, tests
