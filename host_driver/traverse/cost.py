"""Traversal statistics and the paper's cost model (section 4, eqs. (5)-(8)): what a run's
block rays visit and test (l, n, L and the block ray's overhead), the model's predicted time per
ray and the voxel count that minimises it.
"""

import numpy as np

from ...errors import ParameterError

__all__ = ["COST_MODEL", "TraversalStats", "cost_model", "default_voxels"]

#: Constants of the paper's cost model, eqs. (5)-(8) (times in microseconds).
COST_MODEL = dict(p=2.5, k_l=2.9, k_L=0.43, t_I0=0.02, t_BT0=9.6, t_BT=0.4)


class TraversalStats:
    """Traversal statistics of a run, fed a batch of block rays at a time.

    Always accumulated (cheap): blocks, rays, receivers (end points) per block **L**, voxels per
    block, and the patch tests the blocks cause (sum over visited voxels of the patch count, times
    the block's rays). For a sampled fraction of blocks (``sample_fraction``, seeded; 1 for all)
    it also walks every member ray with the per-ray DDA (compiled, :meth:`VoxelGrid.rays_counts`),
    which gives **l** (voxels per ray), **n** (patches per voxel a ray visits) and the two
    overheads, over the sampled blocks:

    - ``overhead`` = sum over blocks of (voxels the block visits x its rays) / sum over rays of
      the ray's DDA voxels (the paper estimates 2.6); both counted over all voxels, empty or not;
    - ``test_overhead`` = patch tests the blocks cause / patch tests the rays alone would need.
    """

    def __init__(self, grid, *, sample_fraction=0.0, seed=0):
        if not 0.0 <= sample_fraction <= 1.0:
            raise ParameterError(f"statistics sample fraction must be in [0, 1], not {sample_fraction!r}")
        self.grid = grid
        self.sample_fraction = float(sample_fraction)
        self._rng = np.random.default_rng(seed)
        self.blocks = 0
        self.rays = 0
        self.receivers = 0
        self.block_voxels = 0          # sum of voxels per block (as given)
        self.block_tests = 0           # sum of patch tests (voxels as given)
        self.sampled_blocks = 0
        self.sampled_rays = 0
        self.sampled_block_voxel_rays = 0
        self.sampled_block_tests = 0
        self.dda_voxels = 0
        self.dda_tests = 0

    def add_block(self, voxels, starts, ends, *, sample=None):
        """Account one block: the voxels it visits, its start (S, 3) and end (R, 3) points.
        ``sample`` as in :meth:`add_blocks`."""
        starts = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        voxels = np.asarray(voxels, dtype=np.int64)
        self.add_blocks(starts, [0, len(starts)], ends, [0, len(ends)], [len(voxels)],
                        [int(self.grid.count[voxels].sum())], sample=sample)

    def add_blocks(self, starts, start_off, ends, end_off, visited, tests, *, sample=None):
        """Account blocks b = (starts[start_off[b]:start_off[b+1]], ends[end_off[b]:end_off[b+1]])
        that visit ``visited[b]`` voxels holding ``tests[b]`` patch records (as
        :meth:`VoxelGrid.traverse_blocks` returns them).

        ``sample``: True / False forces / skips the per-ray DDA for these blocks; None draws each
        block with probability ``sample_fraction`` (one draw per block, in order).
        """
        S, R = np.diff(start_off), np.diff(end_off)
        visited, tests = np.asarray(visited, dtype=np.int64), np.asarray(tests, dtype=np.int64)
        rays = S * R
        self.blocks += len(rays)
        self.rays += int(rays.sum())
        self.receivers += int(R.sum())
        self.block_voxels += int(visited.sum())
        self.block_tests += int((tests * rays).sum())
        if sample is None:
            pick = (self._rng.random(len(rays)) < self.sample_fraction if self.sample_fraction > 0
                    else np.zeros(len(rays), bool))
        else:
            pick = np.full(len(rays), bool(sample))
        b = np.flatnonzero(pick)
        if len(b) == 0:
            return
        self.sampled_blocks += len(b)
        self.sampled_rays += int(rays[b].sum())
        self.sampled_block_voxel_rays += int((visited[b] * rays[b]).sum())
        self.sampled_block_tests += int((tests[b] * rays[b]).sum())
        # every member ray (start k, end r) of the sampled blocks, walked by the DDA
        block = np.repeat(b, rays[b])
        local = np.arange(len(block)) - np.repeat(np.cumsum(rays[b]) - rays[b], rays[b])
        k, r = np.divmod(local, R[block])
        starts, ends = np.asarray(starts, dtype=np.float64), np.asarray(ends, dtype=np.float64)
        dda_visited, dda_tests = self.grid.rays_counts(starts[np.asarray(start_off)[block] + k],
                                                       ends[np.asarray(end_off)[block] + r])
        self.dda_voxels += int(dda_visited.sum())
        self.dda_tests += int(dda_tests.sum())

    _COUNTS = ("blocks", "rays", "receivers", "block_voxels", "block_tests", "sampled_blocks", "sampled_rays",
               "sampled_block_voxel_rays", "sampled_block_tests", "dda_voxels", "dda_tests")

    def counts(self):
        """The accumulated counts (a dict of ints), to merge another run's with :meth:`add_counts`."""
        return {name: int(getattr(self, name)) for name in self._COUNTS}

    def add_counts(self, counts):
        """Add the counts of another run over the same grid (e.g. another host + board set's)."""
        for name in self._COUNTS:
            setattr(self, name, getattr(self, name) + counts[name])

    @staticmethod
    def _ratio(a, b):
        return float(a) / b if b else None

    @property
    def l(self):
        """Mean voxels per ray (DDA, sampled blocks)."""
        return self._ratio(self.dda_voxels, self.sampled_rays)

    @property
    def n(self):
        """Mean patches per voxel a ray visits (DDA, sampled blocks)."""
        return self._ratio(self.dda_tests, self.dda_voxels)

    @property
    def L(self):
        """Mean ray end points (receivers) per block, i.e. per occupied end-point voxel."""
        return self._ratio(self.receivers, self.blocks)

    @property
    def overhead(self):
        return self._ratio(self.sampled_block_voxel_rays, self.dda_voxels)

    @property
    def test_overhead(self):
        return self._ratio(self.sampled_block_tests, self.dda_tests)

    def summary(self):
        """A JSON-ready dict of the statistics (None where nothing was sampled)."""
        return {
            "blocks": self.blocks,
            "rays": self.rays,
            "rays_per_block": self._ratio(self.rays, self.blocks),
            "L": self.L,
            "voxels_per_block": self._ratio(self.block_voxels, self.blocks),
            "tests_by_blocks": self.block_tests,
            "l": self.l,
            "n": self.n,
            "overhead": self.overhead,
            "test_overhead": self.test_overhead,
            "sampled_blocks": self.sampled_blocks,
            "sampled_rays": self.sampled_rays,
        }


def cost_model(v, n_patches, parallelism=1):
    """Predicted time per ray in microseconds, the paper's eqs. (5)-(8).

    T = n l t_I0 / parallelism + (t_BT0 + (l - 1) t_BT) / L, with n = N / v^p, l = k_l v,
    L = k_L N / v^p (p = 2.5, k_l = 2.9, k_L = 0.43; t_I0 = 0.02, t_BT0 = 9.6, t_BT = 0.4 us).
    ``parallelism`` divides t_I0 (R processors testing R rays at once, section 4.2). The model
    is used as published: L is not clamped at 1 for very fine grids.
    """
    c = COST_MODEL
    v = np.asarray(v, dtype=np.float64)
    n = n_patches / v ** c["p"]
    l = c["k_l"] * v
    L = c["k_L"] * n_patches / v ** c["p"]
    return n * l * c["t_I0"] / parallelism + (c["t_BT0"] + (l - 1) * c["t_BT"]) / L


def default_voxels(n_patches, *, parallelism=1, v_max=64):
    """The voxels per axis (1 to ``v_max``) that minimise :func:`cost_model` for the scene."""
    if n_patches < 1:
        return 1
    if parallelism < 1:
        raise ParameterError(f"parallelism must be >= 1, not {parallelism!r}")
    vs = np.arange(1, v_max + 1)
    return int(vs[np.argmin(cost_model(vs, n_patches, parallelism))])
