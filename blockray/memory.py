"""What the P boards' memories hold: the quantised scene's patch records partitioned over the
boards, and the commands that fill them and run a block ray.

Shared by the bit-exact model (sim/model.py), which computes with these memories directly, and
the host driver (host_driver/board/driver.py), which sends them to real or simulated boards.

Memory layout of a board: patch records in voxel order (a patch registered in k voxels occupies k
words over the boards; within a voxel in increasing patch id) and a voxel table of (start, count)
per voxel. Voxel linear index: ``(ix * v + iy) * v + iz``.

Partition (:data:`PARTITIONS`): ``deal`` (default) deals every voxel's records round robin over
the P boards (registration k of the whole table, in voxel order, goes to board k % P), so a
voxel's counts on the boards differ by at most one and the boards stream their shares of a block
in equal time; ``patch`` puts every record of patch i on board i % P (the paper's "partition of
the patches"), whose per-voxel counts can be far apart. Either way every (voxel, patch)
registration is on exactly one board, so the OR of the boards' words is the same.
"""

import numpy as np

from .errors import CapacityError, ParameterError, Spelled, option
from .protocol import POINTS_PER_LOAD, BeginBlock, EndBlock, LoadPoints, Voxel, WritePatch, WriteVoxel
from .records import pack_array, patch_columns, patch_layout

__all__ = ["QuantisationWarning", "ranges", "registration", "partition_records",
           "check_partition", "PARTITIONS", "BoardMemories", "load_points_commands"]

PARTITIONS = ("deal", "patch")


class QuantisationWarning(Spelled, UserWarning):
    """The chosen bits merge vertices or flatten patches of the scene."""


def _cube_root_floor(n):
    """The largest v with v**3 <= n."""
    v = round(n ** (1 / 3))
    while v ** 3 > n:
        v -= 1
    while (v + 1) ** 3 <= n:
        v += 1
    return v


def ranges(starts, counts):
    """Concatenation of arange(start, start + count) for each pair, vectorised."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    offsets = np.cumsum(counts) - counts
    return np.repeat(np.asarray(starts, dtype=np.int64) - offsets, counts) + np.arange(total)


def check_partition(partition):
    """``partition`` if it names one of :data:`PARTITIONS`, else ParameterError."""
    if partition not in PARTITIONS:
        raise ParameterError(f"{option('partition')} must be one of {', '.join(PARTITIONS)}, not {partition!r}",
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
        pat = np.asarray(grid.patches, dtype=np.int64)[ranges(start, count)]
    else:
        raise TypeError(f"cannot read the patch registration of {type(grid).__name__}")
    order = np.lexsort((pat, vox))
    return vox[order], pat[order], nvox


def load_points_commands(receivers, shooters):
    """LOAD_POINTS commands loading receiver rows 0.. with ``receivers`` (R_b, 3) and shooter
    columns 0.. with ``shooters`` (S_b, 3), :data:`POINTS_PER_LOAD` points per command."""
    slots = [(False, r, tuple(int(c) for c in pt)) for r, pt in enumerate(receivers)]
    slots += [(True, s, tuple(int(c) for c in pt)) for s, pt in enumerate(shooters)]
    return [LoadPoints(tuple(slots[i:i + POINTS_PER_LOAD])) for i in range(0, len(slots), POINTS_PER_LOAD)]


class BoardMemories:
    """The quantised scene ``q`` partitioned over ``params.boards`` boards for a voxel ``grid``.

    ``memories[b]``: board b's patch ids (``patch``, one per word) and voxel table (``start``,
    ``count``); ``nvox``; ``records``: the largest partition's word count. Raises
    :class:`CapacityError` when a partition does not fit ``params``' memories.
    """

    def __init__(self, q, grid, params, partition="deal"):
        self.q, self.params = q, params
        vox, pat, nvox = registration(grid)
        if nvox > params.voxel_depth:
            raise CapacityError(f"voxel table: {nvox} voxels do not fit the board's voxel_depth "
                                f"{params.voxel_depth}; use {option('voxels')} {_cube_root_floor(params.voxel_depth)} or fewer")
        self.nvox = nvox
        self.memories = []
        owner = partition_records(vox, pat, params.boards, partition)
        for b in range(params.boards):
            mine = owner == b
            rec = pat[mine]
            if len(rec) > params.patch_depth:
                raise CapacityError(
                    f"patch memory of board {b}: {len(rec)} patch records (registrations) do not fit "
                    f"patch_depth {params.patch_depth}; use more {option('boards')} or fewer {option('voxels')} (each voxel a patch "
                    f"touches costs a record)")
            count = np.bincount(vox[mine], minlength=nvox).astype(np.int64)
            start = np.cumsum(count) - count
            self.memories.append({"patch": rec, "start": start, "count": count})
        self.records = max((len(m["patch"]) for m in self.memories), default=0)

    def memory_image(self, board):
        """Board ``board``'s memory as the hardware loads it: packed patch words (patch_layout(B)),
        voxel-table starts and counts, and the patch id of each word."""
        m, q = self.memories[board], self.q
        words = pack_array(patch_layout(self.params.bits),
                           patch_columns(q.vertices[m["patch"]], q.normals[m["patch"]]))
        return {"patch": words, "start": m["start"].copy(), "count": m["count"].copy(),
                "patch_id": m["patch"].copy()}

    def load_commands(self, board):
        """WRITE_PATCH / WRITE_VOXEL commands that fill board ``board``'s memories."""
        img = self.memory_image(board)
        cmds = [WritePatch(a, int(w)) for a, w in enumerate(img["patch"])]
        cmds += [WriteVoxel(v, int(s), int(c)) for v, (s, c) in enumerate(zip(img["start"], img["count"]))]
        return cmds

    def block_commands(self, block):
        """The command stream of one block ray (the same for every board)."""
        q = self.q
        P = q.shooters[block.shooter_patch, block.shooter_sample]
        Q = q.end_points(block.receiver_patch, block.receiver_weights)
        return ([BeginBlock()] + load_points_commands(Q, P)
                + [Voxel(int(v)) for v in block.voxels] + [EndBlock()])
