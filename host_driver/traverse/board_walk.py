"""The integer block traverse the board can make itself (``--traversal board``): the host's
reference, which the board's block sequencer (sim/sequencer.py, then the RTL) equals bit for bit.

The host's float traversal (walk.py) walks float rays with a registration margin; a board holds
only integers. Here everything is on the scene's B-bit lattice (:mod:`blockray.fixedpoint`).
**The grid** (:class:`LatticeGrid`): v x v x v voxels of edge L = 2^e lattice units from an
integer ``origin``, closed boxes. The quantised triangles are registered in every voxel their
closed triangle touches (the float registration of :class:`~.voxel.VoxelGrid` in lattice
coordinates, margin 0: its rounding tolerance adds voxels, never drops one). **The walk** is
:mod:`blockray.block_walk` (the shared base: the sequencer's model runs the same kernel): per ray
exactly the voxels whose closed box the closed segment touches, a block's voxels once each.

Conservative: a ray that hits a patch at X passes through a voxel box holding X, the patch touches
that box, so the patch is registered there and the ray visits it."""

import math

import numpy as np

from ...block_walk import walk_blocks
from ...errors import ParameterError, option
from .voxel import VoxelGrid

__all__ = ["LatticeGrid", "lattice_shift", "board_grid"]


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

    #: the board makes this grid's blocks (the driver sends COLUMN and RECEIVERS)
    lattice = True

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
        return walk_blocks(S, np.asarray(start_off, dtype=np.int64), E, np.asarray(end_off, dtype=np.int64),
                            self.origin, self.shift, self.v, self.count, bool(nonempty_only))


def board_grid(board, voxels):
    """``--traversal board``'s grid: :meth:`LatticeGrid.for_scene` of the board's quantised scene."""
    q = getattr(board, "quantised", None)
    if q is None:
        raise ParameterError(f"{option('traversal')} board needs a board that holds the scene on its integer "
                             f"grid (not {getattr(board, 'name', 'this board')!r})", parameter="traversal")
    return LatticeGrid.for_scene(q, voxels)
