"""Visibility through a board: block rays of one shooter packed, traversed and run, and the
clear fraction of each (shooter, receiver) pair, with the phases' times. Used by the render loop
(render.py) and by each host + board set on a cluster worker (cluster.py)."""

import time

import numpy as np
from numba import njit

from ...errors import ParameterError, option
from ..radiosity import ray_weights
from ...board import BlockBatch, BlockBits, ranges

__all__ = ["Phases", "Visibility", "visible_fraction", "TRAVERSALS", "PACKINGS"]

TRAVERSALS = ("block", "ray", "board")
PACKINGS = ("voxel", "cube", "fill")
#: ``cube`` packing: a block's receivers end in one cube of 2**CUBE voxels a side (the paper's
#: block on a coarser grid of end points: fuller rows, bundles not much wider).
CUBE = 2


def _morton(ijk):
    """Interleave the bits of voxel coordinates (M, 3) -> (M,) int64 (Z-order)."""
    ijk = np.asarray(ijk, dtype=np.int64)
    code = np.zeros(len(ijk), dtype=np.int64)
    for bit in range(9):
        for axis in range(3):
            code |= ((ijk[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    return code


def packed_runs(key, packing, rows, *groups):
    """How block rays pack their rows (one a receiver end point): sorted by ``groups`` (most
    significant first), then by ``key``, the end's voxel (its Z-order code; its index for
    ``voxel``), and cut into runs of at most ``rows`` that start anew where a group changes or,
    unless ``fill``, the end's voxel (``voxel``) or its cube of 2**CUBE voxels a side (``cube``:
    Z-order codes share their high bits within a cube). Returns that order and the runs' starts and
    lengths in it."""
    order = np.lexsort((key,) + groups[::-1])
    n = len(order)
    cuts = [g[order] for g in groups]
    if packing != "fill":
        cuts.append(key[order] >> (3 * CUBE if packing == "cube" else 0))
    first = np.ones(n, dtype=bool)
    first[1:] = False
    for c in cuts:
        first[1:] |= c[1:] != c[:-1]
    run_start = np.flatnonzero(within_groups(first) % rows == 0)
    return order, run_start, np.diff(np.append(run_start, n))


def within_groups(first):
    """Each position's index within its group, the groups starting where ``first`` is set
    (``first[0]`` must be)."""
    return np.arange(len(first)) - np.flatnonzero(first)[np.cumsum(first) - 1]


class Phases:
    """Seconds spent per phase: wall clock (``seconds``) and CPU time of the whole process, every
    thread (``cpu``; on a shared machine the steadier measure of the host's own work)."""

    def __init__(self):
        self.seconds = {}
        self.cpu = {}

    def add(self, phase, dt, dcpu=0.0):
        self.seconds[phase] = self.seconds.get(phase, 0.0) + dt
        self.cpu[phase] = self.cpu.get(phase, 0.0) + dcpu

    def timed(self, phase):
        return _Timed(self, phase)


class _Timed:
    """Context manager adding its block's wall and CPU seconds to one phase (one class, not one
    per call: a render times tens of thousands of blocks)."""

    def __init__(self, phases, phase):
        self.phases, self.phase = phases, phase

    def __enter__(self):
        self.t0, self.c0 = time.perf_counter(), time.process_time()

    def __exit__(self, *exc):
        self.phases.add(self.phase, time.perf_counter() - self.t0, time.process_time() - self.c0)


class Visibility:
    """Casts the rays of one shooter to many receivers through the board, as block rays.

    Receivers are grouped by the voxel that holds their end point (the paper's block): each group
    of at most R receivers and each chunk of at most S shooter samples is one block ray.
    ``traversal="ray"`` sends one block per ray with its 3D-DDA voxels instead (the per-ray
    reference, for measuring what block traversal saves). ``traversal="board"`` packs and walks
    the blocks as a board making its own rays does: the board's integer points
    (``board.quantised``) on a :class:`~.board_walk.LatticeGrid` ``grid`` (board_walk.py).
    """

    def __init__(self, scene, board, grid, samples, *, rows, cols, traversal="block", packing="voxel",
                 phases=None, stats=None, ends=None):
        if traversal not in TRAVERSALS:
            raise ParameterError(f"{option('traversal')} must be one of {', '.join(TRAVERSALS)}, not {traversal!r}")
        self.scene, self.board, self.grid, self.samples = scene, board, grid, samples
        self.rows, self.cols, self.traversal = rows, cols, traversal
        self.phases = phases or Phases()
        self.stats = stats
        self.ends = ends        # an endpoints.EndPoints choosing each pair's end point; None: centroids
        self.sample_points = samples.points(scene.patch_vertices)        # (N, K, 3) float
        self.weight_points = ray_weights.weight_points(scene, samples)    # the same, as the ray weights take them
        self.centroids = scene.centroids
        self.quantised = getattr(board, "quantised", None) if traversal == "board" else None
        if traversal == "board":                # the board's integer points, grouped on its lattice grid
            if self.quantised is None:
                raise ParameterError(f"{option('traversal')} board needs a board that holds the scene on its "
                                     f"integer grid", parameter="traversal")
            if not getattr(grid, "lattice", False):     # a float grid would take the integers for scene units
                raise ParameterError(f"{option('traversal')} board needs the voxel grid on the board's lattice "
                                     f"(board_walk.LatticeGrid), not {type(grid).__name__}", parameter="traversal")
            self.sample_points, self.centroids = self.quantised.shooters, self.quantised.receivers
        self.end_voxel = grid.voxel_of(self.centroids)
        self.end_morton = _morton(grid.cell_of(self.centroids))
        if packing not in PACKINGS:
            raise ParameterError(f"{option('packing')} must be one of {', '.join(PACKINGS)}, not {packing!r}")
        self.packing = packing
        self.nonempty = grid.count > 0
        self.rays = 0
        self.blocks = 0
        self.columns = 0     # columns cast: a shooter to its receivers, or a reverse receiver to its shooter

    def _end_points(self, receivers, end_weights):
        """Float end points of pairs on ``receivers``: their centroids, or the points of their
        ``end_weights`` (barycentric, summing to the sample denominator)."""
        if end_weights is None:
            return self.centroids[receivers]
        if self.quantised is not None:
            return self.quantised.end_points(receivers, end_weights)
        V = self.scene.patch_vertices[receivers]
        return np.einsum("rk,rkd->rd", end_weights / self.samples.denominator, V)

    def _ray_batch(self, shooters, receivers, end_weights=None, sets=None):
        """One block per ray (pairs in order, samples inner) with its 3D-DDA voxels; each block's
        row is its pair."""
        K = self.samples.count
        pair = np.repeat(np.arange(len(receivers)), K)
        ks = np.tile(np.arange(K), len(receivers)) + (0 if sets is None else K * sets[pair])
        ends = self._end_points(receivers, end_weights)
        with self.phases.timed("traverse"):
            vox, off = self.grid.rays_voxels(self.sample_points[shooters[pair], ks], ends[pair], nonempty_only=True)
        one = np.arange(len(pair) + 1)
        weights = None if end_weights is None else end_weights[pair]
        return BlockBatch(shooters[pair], ks, one, receivers[pair], one, vox, off, weights), pair

    def _blocks_for(self, i, receivers):
        """The block rays of shooter i to ``receivers``, packed and traversed, as a BlockBatch."""
        receivers = np.asarray(receivers, dtype=np.int64)
        return self._pair_blocks(np.full(len(receivers), i, dtype=np.int64), receivers)[0]

    def _pair_blocks(self, shooters, receivers, end_weights=None, sets=None):
        """The block rays of the pairs (shooters[m], receivers[m]), packed and traversed, as one
        BlockBatch, and the pair of each of its rows; each pair's row ends at the point of
        ``end_weights[m]`` if given, else at the receiver's centroid; its rays start at the
        shooter's sample set ``sets[m]`` (default 0: the first K points).

        A run of equal consecutive (shooter, set) is one column: its receivers are packed as those
        of one shooter (:meth:`_blocks_for`), columns in order, so a column's blocks are the same
        whatever else shares the batch."""
        if self.traversal == "ray":
            return self._ray_batch(shooters, receivers, end_weights, sets)
        K = self.samples.count
        with self.phases.timed("commands"):
            if end_weights is None:
                pair_voxel, pair_morton, pair_end = (self.end_voxel[receivers], self.end_morton[receivers],
                                                     self.centroids[receivers])
            else:
                pair_end = self._end_points(receivers, end_weights)
                pair_voxel, pair_morton = self.grid.voxel_of(pair_end), _morton(self.grid.cell_of(pair_end))
            column = np.zeros(len(shooters), dtype=np.int64)
            change = shooters[1:] != shooters[:-1]
            column[1:] = np.cumsum(change if sets is None else change | (sets[1:] != sets[:-1]))
            # Runs of at most R receivers of a column (the paper's block: those whose end points
            # share a voxel; ``cube``, ``fill``: in Z-order across voxels, a little wider bundles),
            # times chunks of at most S samples.
            pair, run_start, run_len = packed_runs(pair_voxel if self.packing == "voxel" else pair_morton,
                                                   self.packing, self.rows, column)
            chunk_start = np.arange(0, K, self.cols)
            chunk_len = np.minimum(self.cols, K - chunk_start)
            nr, nc = len(run_start), len(chunk_start)
            rows, cols = np.repeat(run_len, nc), np.tile(chunk_len, nr)
            row_pair = pair[ranges(np.repeat(run_start, nc), rows)]
            receiver_patch = receivers[row_pair]
            first_k = np.tile(chunk_start, nr) + (0 if sets is None else np.repeat(K * sets[pair[run_start]], nc))
            shooter_sample = ranges(first_k, cols)
            shooter_patch = np.repeat(shooters[pair[run_start]], K)     # each run's K samples
            row_off = np.concatenate([[0], np.cumsum(rows)])
            col_off = np.concatenate([[0], np.cumsum(cols)])
            starts, ends = self.sample_points[shooter_patch, shooter_sample], pair_end[row_pair]
        with self.phases.timed("traverse"):
            vox, vox_off, visited, tests = self.grid.traverse_blocks(starts, col_off, ends, row_off,
                                                                     nonempty_only=True)
            if self.stats is not None:
                self.stats.add_blocks(starts, col_off, ends, row_off, visited, tests)
        weights = None if end_weights is None else end_weights[row_pair]
        return BlockBatch(shooter_patch, shooter_sample, col_off, receiver_patch, row_off, vox, vox_off,
                          weights), row_pair

    def clear_fraction(self, i, receivers, weights=None):
        """Fraction of the K rays from shooter i to each receiver that is not blocked; with
        ``weights`` (len(receivers), K), the weighted fraction (a receiver whose weights are all
        0 gets the plain one)."""
        receivers = np.asarray(receivers, dtype=np.int64)
        return self.pair_clear_fraction(np.full(len(receivers), i, dtype=np.int64), receivers, weights,
                                        columns=1)

    def pair_clear_fraction(self, shooters, receivers, weights=None, *, columns=None, end_weights=None, sets=None):
        """:meth:`clear_fraction` of the pairs (shooters[m], receivers[m]), all in one board batch
        (a run of equal consecutive shooters is one column; ``columns`` counts them unless given),
        pair m's rays from its shooter's sample set ``sets[m]`` (default 0).
        Each pair's value is the one :meth:`clear_fraction` gives it alone, to the bit."""
        shooters = np.asarray(shooters, dtype=np.int64)
        receivers = np.asarray(receivers, dtype=np.int64)
        n = len(receivers)
        if columns is None:
            columns = int(np.count_nonzero(shooters[1:] != shooters[:-1])) + 1 if n else 0
        self.columns += columns
        if n == 0:
            return np.zeros(0)
        batch, row_pair = self._pair_blocks(shooters, receivers, end_weights,
                                            None if sets is None else np.asarray(sets, dtype=np.int64))
        with self.phases.timed("board"):
            bits = self.board.run(batch)
        flat = bits.flat if isinstance(bits, BlockBits) else np.concatenate(
            [np.asarray(b, dtype=bool).ravel() for b in bits])
        # the clear bit of every (pair, sample) ray, whatever block and batch it was cast in
        K = self.samples.count
        bit = _clear_bits(batch.row_off, batch.col_off, batch.shooter_sample % K, row_pair, flat, n, K)
        self.rays += batch.rays
        self.blocks += len(batch)
        plain = bit.sum(axis=1) / self.samples.count
        if weights is None:
            return plain
        # one weighted sum per pair in sample order: the same float result however the rays
        # were grouped into blocks and batches
        w_clear = (bit * weights).sum(axis=1)
        total = weights.sum(axis=1)
        return np.where(total > 0, w_clear / np.where(total > 0, total, 1), plain)


def visible_fraction(scene, vis, samples, i, receivers, phases):
    """The board's clear fraction of each (shooter ``i``, receiver) pair, for the exact factor.

    Each ray weighs by the light its sample sends to the receiver (0 from samples behind the
    receiver's plane: the exact factor already leaves out that part of i, so counting those rays
    would clip it twice). A receiver straddling i's plane with its centroid behind it gets the
    reverse rays, from its samples in front of i's plane to i's centroid (visibility is symmetric).
    All of them, i's own rays and the reverse rays, go to the board as one batch (i's column).
    """
    receivers = np.asarray(receivers, dtype=np.int64)
    with phases.timed("formfactor"):
        direct = ray_weights.centroid_in_front(scene, i, receivers)
        forward = receivers[direct]
        reverse = receivers[~direct]
        # i's own rays first, then one column per reverse receiver, each in receiver order
        shooters = np.concatenate([np.full(len(forward), i, dtype=np.int64), reverse])
        targets = np.concatenate([forward, np.full(len(reverse), i, dtype=np.int64)])
        weights = ray_weights.pair_sample_weights(scene, samples, shooters, targets, points=vis.weight_points)
        K, S = samples.count, weights.shape[1] // samples.count        # S sample sets per patch
        ends, draws, sets, back = None, 1, None, 1
        if vis.ends is not None and vis.ends.rule != "centroid":
            # i's own rows end where the rule puts them, ``draws`` rows per pair (all in i's one
            # column), row d from sample set d if the patches have a set per row; reverse rows at
            # i's centroid, from set 0, or with sets one per row from each set once (a thin front
            # of a straddling receiver may hold none of one set's K points; an emitter's extra
            # rows would only repeat the same rays to the same centroid)
            draws, nf, nr = vis.ends.draws_of(i), len(forward), len(reverse)
            back = min(draws, S)
            ends = np.concatenate([vis.ends.rows(i, forward)]
                                  + [np.full((back * nr, 3), samples.denominator // 3, dtype=np.int64)])
            shooters = np.concatenate([np.full(draws * nf, i, dtype=np.int64), np.repeat(reverse, back)])
            targets = np.concatenate([np.tile(forward, draws), np.full(back * nr, i, dtype=np.int64)])
            rows = np.arange(draws) % S
            sets = np.concatenate([np.repeat(rows, nf), np.tile(rows[:back], nr)])
            own, theirs = weights[:nf].reshape(nf, S, K), weights[nf:].reshape(nr, S, K)
            weights = np.concatenate([own[:, rows].transpose(1, 0, 2).reshape(-1, K),
                                      theirs[:, rows[:back]].reshape(-1, K)])
            if S == 1:
                sets = None
        weights = weights[:, :K]
    frac = np.empty(len(receivers))
    # the column count as one call per column would give it: i's own (even if empty), one per reverse
    f = vis.pair_clear_fraction(shooters, targets, weights, columns=1 + len(reverse), end_weights=ends, sets=sets)
    split = draws * len(forward)
    own = f[:split].reshape(draws, len(forward)).T
    # with a set per row, a row whose K samples all lie behind the receiver's plane carries no
    # light and does not count (its plain fraction would stand in). The others count equally, not
    # by weight: their end points were drawn by that weight already
    frac[direct] = own.mean(axis=1) if S == 1 else _lit_mean(own, weights[:split].sum(axis=1).reshape(draws, -1).T)
    frac[~direct] = f[split:] if back == 1 else _pooled(f[split:].reshape(-1, back),
                                                         weights[split:].sum(axis=1).reshape(-1, back))
    return frac


def _pooled(f, total):
    """Each pair's rows (n, rows) as one weighted fraction: the rows' fractions weighed by their
    weight totals, so a row whose samples carry no light (total 0) does not count; the plain mean
    where no row carries any."""
    t = total.sum(axis=1)
    return np.where(t > 0, (f * total).sum(axis=1) / np.where(t > 0, t, 1), f.mean(axis=1))


def _lit_mean(f, total):
    """Each pair's rows (n, rows) averaged over those whose samples carry light (total > 0); the
    plain mean where none does."""
    lit = total > 0
    n = lit.sum(axis=1)
    return np.where(n > 0, (f * lit).sum(axis=1) / np.maximum(n, 1), f.mean(axis=1))


@njit(cache=True)
def _clear_bits(row_off, col_off, shooter_sample, row_pair, blocked, n, K):
    """(n, K) float64: 1 where the ray of pair m from shooter sample k is clear. ``blocked`` in the
    batch's flat ray order (block by block, each (R_b, S_b) row-major); row r is pair row_pair[r]."""
    bit = np.zeros((n, K))
    ray = 0
    for b in range(len(row_off) - 1):
        for r in range(row_off[b], row_off[b + 1]):
            m = row_pair[r]
            for c in range(col_off[b], col_off[b + 1]):
                if not blocked[ray]:
                    bit[m, shooter_sample[c]] = 1.0
                ray += 1
    return bit
