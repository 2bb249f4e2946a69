"""The ``golden`` board: the exact reference for what is right, on the scene's float geometry.

It answers block rays with the predicate of :mod:`blockray.exact` (strict plane crossing, closed
edge test)::

    blocked  <=>  sign(pP) * sign(pQ) < 0  and  (s_0, s_1, s_2 all >= 0 or all <= 0)

evaluated **exactly** on the unquantised float64 scene by :mod:`blockray.exact_float` (a
certified floating-point filter, then exact expansion arithmetic; compiled with numba). The ray
end points are the exact rational sample points ``sum_k w_k V_k / D`` of
:class:`~blockray.samples.SampleScheme` and the exact centroids, not their roundings: so a
sample point lies exactly on its own patch's plane, and own patches, coplanar neighbours and
zero-area triangles never block, with no tolerance at all (none scaled to the scene, so a tiny
patch beside a huge one is treated like any other). Every sign is exact, so the edge test is
watertight: a segment through a shared edge or vertex of a closed mesh is always blocked.

The board has no tolerance; its only scene-relative length is the voxel registration
``margin`` (1e-9 of the scene's size), which makes the *grid* conservative (a patch registered in
a voxel it only nearly touches costs a test, never a wrong answer).

Registration: the board reads the voxel grid's CSR tables (``start``, ``count``, ``patches``,
linear index ``(ix * v + iy) * v + iz``). Every patch registered in any voxel of a block is tested
once against all R_b x S_b rays of the block (the union: a patch in two visited voxels is one
test per ray).
"""

import numpy as np

from ...exact_float import blocked_rays, check_exact_range
from ...board import Board

__all__ = ["GoldenBoard"]

#: voxel registration margin relative to the scene size
MARGIN = 1e-9
_POINT = np.array([1, 0, 0], dtype=np.int64)        # weights of a plain float point (E, E, E)


class GoldenBoard(Board):
    """Exact reference board (float scene, exact predicate); compiled per block."""

    name = "golden"

    def __init__(self):
        self._grid = None
        self._reset()

    def _reset(self):
        self._counters = {"blocks": 0, "rays": 0, "tests": 0, "voxels": 0, "crossings": 0}
        self._crossings = np.zeros(1, dtype=np.int64)

    def prepare(self, scene, samples):
        V = np.ascontiguousarray(scene.patch_vertices, dtype=np.float64)
        check_exact_range(V, f"scene {scene.name!r} on the golden board")
        self._V = V
        self._weights = samples.weights_of(np.arange(scene.patches))      # (N, K, 3), per patch if drawn
        lo, hi = scene.bbox
        self.margin = MARGIN * float(max(np.max(hi - lo), np.finfo(float).tiny))
        self._reset()

    def load(self, grid):
        self._grid = grid
        self._start = np.asarray(grid.start, dtype=np.int64)
        self._count = np.asarray(grid.count, dtype=np.int64)
        self._patches = np.asarray(grid.patches, dtype=np.int64)

    def patches_of(self, voxels):
        """Sorted union of the patches registered in the given linear voxel indices."""
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1)
        if voxels.size == 0:
            return np.zeros(0, dtype=np.int64)
        counts = self._count[voxels]
        offsets = np.repeat(self._start[voxels] - np.cumsum(counts) + counts, counts)
        return np.unique(self._patches[offsets + np.arange(counts.sum())])

    def blocked_samples(self, shooter_patch, shooter_sample, receiver_patch, t, receiver_weights=None):
        """bool (R, S): rays from the exact sample points (shooter_patch[s], shooter_sample[s])
        to the exact centroids of receiver_patch[r] (or the exact points of receiver_weights[r]),
        blocked by any of the patches t."""
        sp = np.asarray(shooter_patch, dtype=np.int64).reshape(-1)
        P_w = self._weights[sp, np.asarray(shooter_sample, dtype=np.int64).reshape(-1)]
        rp = np.asarray(receiver_patch, dtype=np.int64).reshape(-1)
        Q_w = np.ones(3, dtype=np.int64) if receiver_weights is None else receiver_weights
        return blocked_rays(self._V[sp], P_w, self._V[rp], Q_w,
                            self._V[np.asarray(t, dtype=np.int64)], self._crossings)

    def blocked(self, P, Q, t):
        """bool (R, S): segments from float points P (S, 3) to float points Q (R, 3) (taken as the
        exact values of the floats) blocked by any of the patches t (T,)."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        Q = np.asarray(Q, dtype=np.float64).reshape(-1, 3)
        return blocked_rays(np.repeat(P[:, None], 3, axis=1), _POINT, np.repeat(Q[:, None], 3, axis=1), _POINT,
                            self._V[np.asarray(t, dtype=np.int64)], self._crossings)

    def run(self, blocks):
        if self._grid is None:
            raise RuntimeError("GoldenBoard.run before load(grid)")
        results = []
        for block in blocks:
            t = self.patches_of(block.voxels)
            bits = self.blocked_samples(block.shooter_patch, block.shooter_sample, block.receiver_patch, t,
                                        block.receiver_weights)
            results.append(bits)
            rays = bits.size
            self._counters["blocks"] += 1
            self._counters["rays"] += rays
            self._counters["tests"] += rays * len(t)
            self._counters["voxels"] += len(np.asarray(block.voxels).reshape(-1))
        return results

    def counters(self):
        """``blocks``, ``rays``, ``tests`` (ray-patch tests, each patch once per block),
        ``voxels`` (voxel visits) and ``crossings`` (tests that passed the plane test and were
        not already blocked)."""
        return dict(self._counters, crossings=int(self._crossings[0]))
