"""Small random board workloads for the board's RTL tests (Amaranth simulator and cocotb).

Everything is seeded by the caller. Patches are biased to sit across the block's rays so that
blocked and clear results both occur; voxel registrations include empty voxels and patches
registered in several voxels.
"""

import numpy as np

from blockray.board import BlockRay
from blockray.exact import patch_normals
from blockray.params import BoardParams
from blockray.records import pack_array, patch_columns, patch_layout
from blockray.protocol import (POINTS_PER_LOAD, BeginBlock, EndBlock, Identify, LoadPoints, LoadReceiver, LoadShooter,
                               ReadCounters, Voxel, WritePatch, WriteVoxel, fit_params)

from scenes import mesh_scene

__all__ = ["crossing_patches", "random_memory", "load_commands", "random_block", "random_points", "make_batch",
           "scattered_scene", "BoxGrid", "random_blocks"]


def random_points(rng, bits, n):
    return rng.integers(0, 1 << bits, (n, 3)).astype(np.int64)


def crossing_patches(rng, bits, P, Q, n, *, crossing=0.7):
    """``n`` triangles (n, 3, 3) int64; a fraction ``crossing`` sit around a point of a ray P_s -> Q_r."""
    top = 1 << bits
    V = rng.integers(0, top, (n, 3, 3)).astype(np.int64)
    for i in range(n):
        if rng.random() < crossing:
            s, r = rng.integers(len(P)), rng.integers(len(Q))
            x = P[s] + rng.random() * (Q[r] - P[s])
            size = top * rng.uniform(0.01, 0.3)
            V[i] = np.clip(np.rint(x + rng.normal(0.0, size, (3, 3))), 0, top - 1).astype(np.int64)
    if n >= 4:                               # a degenerate and an axis-aligned one
        V[0, 2] = V[0, 1]
        V[1, :, 2] = V[1, 0, 2]
    return V


def random_memory(rng, bits, vertices, voxels, *, empty=0.3, max_registrations=3):
    """Register each patch in 1..max_registrations random voxels (a fraction ``empty`` of the
    voxels gets none) and lay the records out in voxel order.

    Returns ``(patch_ids, start, count)``: ``patch_ids`` the patch of each memory word.
    """
    n = len(vertices)
    occupied = np.flatnonzero(rng.random(voxels) >= empty)
    if len(occupied) == 0:
        occupied = np.array([0])
    regs = []
    for t in range(n):
        k = int(rng.integers(1, max_registrations + 1))
        for v in rng.choice(occupied, size=min(k, len(occupied)), replace=False):
            regs.append((int(v), t))
    regs.sort()
    vox = np.array([v for v, _ in regs], dtype=np.int64)
    ids = np.array([t for _, t in regs], dtype=np.int64)
    count = np.bincount(vox, minlength=voxels).astype(np.int64)
    start = np.cumsum(count) - count
    return ids, start, count


def load_commands(bits, vertices, patch_ids, start, count):
    """WRITE_PATCH for every memory word, then WRITE_VOXEL for every voxel."""
    V = vertices[patch_ids]
    words = pack_array(patch_layout(bits), patch_columns(V, patch_normals(V)))
    cmds = [WritePatch(a, int(w)) for a, w in enumerate(words)]
    cmds += [WriteVoxel(v, int(s), int(c)) for v, (s, c) in enumerate(zip(start, count))]
    return cmds


def random_block(rng, rows, cols, P, Q, voxels, *, max_voxels=6):
    """One well-formed block: BEGIN_BLOCK, LOADs of a random subset of rows and columns, VOXELs
    (random, repeats and empty voxels allowed), END_BLOCK."""
    cmds = [BeginBlock()]
    nr = int(rng.integers(0, rows + 1)) if rng.random() < 0.3 else rows
    nc = int(rng.integers(0, cols + 1)) if rng.random() < 0.3 else cols
    loads = [LoadReceiver(int(r), tuple(int(c) for c in Q[rng.integers(len(Q))]))
             for r in rng.permutation(rows)[:nr]]
    loads += [LoadShooter(int(s), tuple(int(c) for c in P[rng.integers(len(P))]))
              for s in rng.permutation(cols)[:nc]]
    rng.shuffle(loads)
    if rng.random() < 0.5:
        # the same loads packed POINTS_PER_LOAD at a time into LOAD_POINTS (in order: a later
        # slot of the same row or column would win, as a later LOAD does)
        slots = [(True, c.col, c.point) if isinstance(c, LoadShooter) else (False, c.row, c.point) for c in loads]
        if slots and rng.random() < 0.3:       # a row or column loaded twice: the later point counts
            shooter, where, _ = slots[0]
            again = P if shooter else Q
            slots.insert(int(rng.integers(1, len(slots) + 1)),
                         (shooter, where, tuple(int(c) for c in again[rng.integers(len(again))])))
        loads = []
        while slots:
            take = int(rng.integers(1, POINTS_PER_LOAD + 1))
            loads.append(LoadPoints(tuple(slots[:take])))
            slots = slots[take:]
    cmds += loads
    cmds += [Voxel(int(v)) for v in rng.integers(0, voxels, int(rng.integers(0, max_voxels + 1)))]
    cmds.append(EndBlock())
    return cmds


def make_batch(seed, *, rows, cols, bits, patches=14, voxels=6, blocks=6):
    """Params sized for the scene, and a batch: memory load, blocks, READ_COUNTERS between some."""
    rng = np.random.default_rng(seed)
    P, Q = random_points(rng, bits, 6), random_points(rng, bits, 6)
    V = crossing_patches(rng, bits, P, Q, patches)
    ids, start, count = random_memory(rng, bits, V, voxels)
    params = fit_params(BoardParams(rows=rows, cols=cols, bits=bits), records=len(ids), voxels=voxels)
    cmds = [Identify()] + load_commands(bits, V, ids, start, count) + [ReadCounters()]
    for b in range(blocks):
        cmds += random_block(rng, rows, cols, P, Q, voxels)
        if rng.random() < 0.5:
            cmds.append(ReadCounters())
    # back to back: a VOXEL right after a WRITE_VOXEL of the same voxel, results back to back
    cmds += [WriteVoxel(0, int(start[1]), int(count[1])), BeginBlock()]
    cmds += [LoadReceiver(r, tuple(map(int, Q[r]))) for r in range(rows)]
    cmds += [LoadShooter(s, tuple(map(int, P[s]))) for s in range(cols)]
    cmds += [Voxel(0), Voxel(1), EndBlock(), Identify(), ReadCounters()]
    return params, cmds


def scattered_scene(seed, n=30):
    """``n`` random triangles scattered in an 8-unit cube (printed seed)."""
    rng = np.random.default_rng(seed)
    print(f"seed={seed}")
    centres = rng.random((n, 1, 3)) * 8
    v = centres + (rng.random((n, 3, 3)) - 0.5) * 3
    return mesh_scene(v.reshape(-1, 3), np.arange(3 * n))


class BoxGrid:
    """Test grid: a patch is registered in every voxel its bounding box (plus margin) overlaps."""

    def __init__(self, patch_vertices, v, margin=0.0):
        lo = patch_vertices.reshape(-1, 3).min(axis=0)
        hi = patch_vertices.reshape(-1, 3).max(axis=0)
        size = (hi - lo) / v
        lists = [[] for _ in range(v ** 3)]
        for i, tri in enumerate(patch_vertices):
            a = np.clip(((tri.min(axis=0) - margin - lo) // size).astype(int), 0, v - 1)
            b = np.clip(((tri.max(axis=0) + margin - lo) // size).astype(int), 0, v - 1)
            for ix in range(a[0], b[0] + 1):
                for iy in range(a[1], b[1] + 1):
                    for iz in range(a[2], b[2] + 1):
                        lists[(ix * v + iy) * v + iz].append(i)
        self.voxel_patches = [np.array(x, dtype=np.int64) for x in lists]
        self.count = np.array([len(x) for x in lists])


def random_blocks(rng, scene, samples, params, nblocks, nvox):
    blocks = []
    for _ in range(nblocks):
        Rb = int(rng.integers(1, params.rows + 1))
        Sb = int(rng.integers(1, params.cols + 1))
        blocks.append(BlockRay(
            shooter_patch=rng.integers(0, scene.patches, Sb),
            shooter_sample=rng.integers(0, samples.count, Sb),
            receiver_patch=rng.integers(0, scene.patches, Rb),
            voxels=rng.choice(nvox, int(rng.integers(0, nvox + 1)), replace=False)))
    return blocks
