"""The integer block walk of rays made on the board: one definition for the host's reference
(:class:`blockray.host_driver.traverse.board_walk.LatticeGrid`, ``--traversal board``) and the
block sequencer's model (:mod:`blockray.sim.sequencer`), compiled (numba, cache=True).

The grid: v x v x v voxels of edge L = 2^e lattice units from an integer ``origin``; voxel i on
an axis is the closed interval [origin + i L, origin + (i + 1) L], linear index (ix v + iy) v + iz.

* **A ray** P -> Q (integer end points) visits exactly the voxels whose closed box the closed
  segment touches: an integer 3D DDA over the grid planes it crosses, the crossing times
  t = (k L - p) / d compared as fractions by cross-multiplication (no division), simultaneous
  crossings merged, so rays along planes, through edges and corners, axis-parallel or of zero
  length are exact. At t = 0 and at each crossing it visits the box of voxels the point lies in
  (up to 2 x 2 x 2), x outer, z inner.
* **A block** (R_b rows x S_b columns) walks its rays in blocked-word order (row r outer, column
  s inner) and emits each voxel the first time any ray visits it, empty ones (count 0) skipped
  with ``nonempty_only``: a stamp per voxel-table entry, the board's visited bit.

The block sequencer's walk cycles (its cycle contract, docs/board-protocol.md "The sequencer's
cycles"): per ray :data:`RAY_CYCLES` (its end points read, the job given to the ray walker), per
box :data:`BOX_CYCLES` (taken from the walker, its first voxel's voxel-table entry and visited
stamp read) and per voxel of the clipped box :data:`VOXEL_CYCLES` (decided: a VOXEL record
offered if it is new and not empty, while the next voxel is read), every voxel of a box, visited
or not.
"""

import numpy as np
from numba import njit

__all__ = ["walk_block", "walk_block_cycles", "walk_blocks", "RAY_CYCLES", "BOX_CYCLES", "VOXEL_CYCLES"]

#: the sequencer's cycles per ray, per box and per voxel of a box (the module docstring)
RAY_CYCLES, BOX_CYCLES, VOXEL_CYCLES = 2, 1, 1


def walk_block(starts, ends, origin, shift, v, count, *, nonempty_only=True):
    """One block's voxels (int64, in walk order) on the grid (``origin``, ``shift``, ``v``) whose
    voxel table holds ``count`` records per voxel (v^3 entries): what the board's sequencer
    streams for rows ``ends`` (R_b, 3) and columns ``starts`` (S_b, 3)."""
    return walk_block_cycles(starts, ends, origin, shift, v, count, nonempty_only=nonempty_only)[0]


def walk_block_cycles(starts, ends, origin, shift, v, count, *, nonempty_only=True):
    """:func:`walk_block`'s voxels, the sequencer's cycle (from the walk's first, 0) in which it
    offers each, and the walk's cycles in all (:data:`RAY_CYCLES`, :data:`BOX_CYCLES`,
    :data:`VOXEL_CYCLES`)."""
    S = np.ascontiguousarray(starts, dtype=np.int64).reshape(-1, 3)
    E = np.ascontiguousarray(ends, dtype=np.int64).reshape(-1, 3)
    out, when, _, tally = _walk_blocks(S, np.array([0, len(S)]), E, np.array([0, len(E)]),
                                       np.asarray(origin, dtype=np.int64), int(shift), int(v),
                                       np.ascontiguousarray(count, dtype=np.int64), nonempty_only)
    return out, when, int(tally[0, 2])


@njit(cache=True)
def _emit(lo, hi, v, count, nonempty_only, stamp, tag, out, when, o, tally):
    """Visit the voxels of the index box [lo, hi] (clipped to the grid), x outer, z inner: those
    not stamped ``tag`` yet are stamped, counted in tally (visited, tests) and, if kept, written
    to ``out[o:]`` with the sequencer's cycle in ``when[o:]`` (tally[2] counts the cycles).
    Returns the new o."""
    x0, x1 = max(lo[0], 0), min(hi[0], v - 1)
    y0, y1 = max(lo[1], 0), min(hi[1], v - 1)
    z0, z1 = max(lo[2], 0), min(hi[2], v - 1)
    tally[2] += BOX_CYCLES
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            for iz in range(z0, z1 + 1):
                i = (ix * v + iy) * v + iz
                tally[2] += VOXEL_CYCLES
                if stamp[i] == tag:
                    continue
                stamp[i] = tag
                tally[0] += 1
                tally[1] += count[i]
                if count[i] > 0 or not nonempty_only:
                    out[o], when[o] = i, tally[2] - 1      # offered in the voxel's last cycle
                    o += 1
    return o


@njit(cache=True)
def _walk_ray(p, q, origin, e, v, count, nonempty_only, stamp, tag, out, when, o, tally):
    """The integer DDA of one segment p -> q (see the module docstring). Returns the new o."""
    L = np.int64(1) << e
    tally[2] += RAY_CYCLES
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
    o = _emit(lo, hi, v, count, nonempty_only, stamp, tag, out, when, o, tally)
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
        o = _emit(lo, hi, v, count, nonempty_only, stamp, tag, out, when, o, tally)


def walk_blocks(S, s_off, E, e_off, origin, e, v, count, nonempty_only):
    """Blocks b = (S[s_off[b]:s_off[b+1]], E[e_off[b]:e_off[b+1]]) (int64 points): every block's
    voxels (each once, rays row-major), CSR ``(voxels, offsets)``; the voxels visited and the
    records they hold per block."""
    out, _, off, tally = _walk_blocks(S, s_off, E, e_off, origin, e, v, count, nonempty_only)
    return out, off, tally[:, 0].copy(), tally[:, 1].copy()


@njit(cache=True)
def _walk_blocks(S, s_off, E, e_off, origin, e, v, count, nonempty_only):
    """:func:`walk_blocks`' voxels, each one's cycle in its block's walk, offsets and per block
    tally (visited, tests, walk cycles)."""
    B = len(s_off) - 1
    nvox = v * v * v
    stamp = np.full(nvox, -1, np.int64)
    out = np.empty(max(nvox, 1024), np.int64)
    when = np.empty(len(out), np.int64)
    off = np.zeros(B + 1, np.int64)
    tally = np.zeros((B, 3), np.int64)
    o = 0
    for b in range(B):
        if len(out) - o < nvox:                     # room for a block that visits every voxel
            grown, grown_when = np.empty(2 * len(out) + nvox, np.int64), np.empty(2 * len(out) + nvox, np.int64)
            grown[:o], grown_when[:o] = out[:o], when[:o]
            out, when = grown, grown_when
        for r in range(e_off[b], e_off[b + 1]):
            for s in range(s_off[b], s_off[b + 1]):
                o = _walk_ray(S[s], E[r], origin, e, v, count, nonempty_only, stamp, b, out, when, o, tally[b])
        off[b + 1] = o
    return out[:o].copy(), when[:o].copy(), off, tally
