"""The ``golden`` board: the float64 reference for what is right.

It answers block rays with the same predicate as :mod:`blockray.exact` (strict plane crossing,
closed edge test), evaluated in float64 on the scene's own (unquantised) geometry::

    blocked  <=>  sign(pP) * sign(pQ) < 0  and  (s_0, s_1, s_2 all >= 0 or all <= 0)
    pP = n . (P - V0),  pQ = n . (Q - V0),  s_k = (P - V_k) . ((Q - V_k) x (V_{k+1} - V_k))

**The one tolerance.** In exact integer arithmetic the sample points lie exactly on their
patches' planes, so the strict plane test alone keeps a ray from being blocked by its own
shooter or receiver patch or a coplanar neighbour. Float sample points (weighted means of float
vertices) are off their planes by rounding noise, of either sign, so the plane signs use a
threshold: ``|n . (X - V0)| <= PLANE_TOLERANCE * scene_scale * |n|`` (a distance of 1e-10 of the
scene's size) counts as on the plane, sign 0. That is the only tolerance: the edge sides are used
with their exact float signs. Rays that pass within rounding of a triangle's edge are a
measure-zero set, and to keep even those from slipping through a shared edge each edge side is
computed from the edge's endpoints in a canonical (lexicographic) order and negated if swapped,
so the two triangles sharing an edge get exactly opposite values (watertight, as in the exact
predicate).

Sample points are computed as ``(sum_k w_k V_k) / D`` with the integer weights of
:class:`~blockray.samples.SampleScheme` (the same points as ``samples.points``, rounded once):
for integer vertices that are multiples of D they are exact, and for small integer scenes every
product then fits 53 bits, so the golden board agrees bit for bit with the exact predicate there.

Registration: the board reads the voxel grid's CSR tables (``start``, ``count``, ``patches``,
linear index ``(ix * v + iy) * v + iz``). Every patch registered in any voxel of a block is tested
once against all R_b x S_b rays of the block (the union: a patch in two visited voxels is one
test per ray). ``margin`` is 1e-9 of the scene's size, enough for the grid to absorb rounding.
"""

import numpy as np

from .board import Board
from .formfactor import PLANE_TOLERANCE, scene_scale

__all__ = ["GoldenBoard"]

#: voxel registration margin relative to the scene size
MARGIN = 1e-9


class GoldenBoard(Board):
    """float64 reference board; vectorised over rays x patches of each block."""

    name = "golden"

    def __init__(self):
        self._grid = None
        self._reset()

    def _reset(self):
        self._counters = {"blocks": 0, "rays": 0, "tests": 0, "voxels": 0, "crossings": 0}

    def prepare(self, scene, samples):
        V = np.asarray(scene.patch_vertices, dtype=np.float64)
        w = np.asarray(samples.weights, dtype=np.float64)
        self._shooters = np.einsum("kj,njc->nkc", w, V) / samples.denominator    # (N, K, 3)
        self._receivers = V.sum(axis=1) / 3.0                                     # (N, 3) centroids
        self._v0 = V[:, 0]
        self._normal = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])             # (N, 3) unnormalised
        scale = scene_scale(scene)
        self._plane_tol = PLANE_TOLERANCE * scale * np.linalg.norm(self._normal, axis=1)
        # canonical edge endpoints: a_k <= b_k lexicographically, sign -1 where swapped
        start, end = V, np.roll(V, -1, axis=1)
        swap = np.zeros(start.shape[:2], dtype=bool)
        decided = np.zeros_like(swap)
        for c in range(3):
            swap |= ~decided & (start[..., c] > end[..., c])
            decided |= start[..., c] != end[..., c]
        self._edge_a = np.where(swap[..., None], end, start)
        self._edge_b = np.where(swap[..., None], start, end)
        self._edge_sign = np.where(swap, -1.0, 1.0)
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

    def _signs(self, X, t):
        """Plane signs of points X (M, 3) against patches t: (M, T) in {-1, 0, 1}."""
        d = np.einsum("mtc,tc->mt", X[:, None, :] - self._v0[t][None], self._normal[t])
        return np.where(np.abs(d) <= self._plane_tol[t], 0.0, np.sign(d))

    def blocked(self, P, Q, t):
        """bool (R, S): rays from shooter points P (S, 3) to receiver points Q (R, 3) blocked by
        any of the patches t (T,)."""
        R, S = len(Q), len(P)
        out = np.zeros(R * S, dtype=bool)
        if R == 0 or S == 0 or len(t) == 0:
            return out.reshape(R, S)
        sP, sQ = self._signs(P, t), self._signs(Q, t)                     # (S, T), (R, T)
        r, s, k = np.nonzero(sQ[:, None, :] * sP[None, :, :] < 0)         # plane crossings
        self._counters["crossings"] += len(r)
        if len(r):
            a, b = self._edge_a[t[k]], self._edge_b[t[k]]                 # (C, 3, 3)
            dP = P[s][:, None, :] - a
            dQ = Q[r][:, None, :] - a
            side = self._edge_sign[t[k]] * np.einsum("xec,xec->xe", dP, np.cross(dQ, b - a))
            inside = (side >= 0).all(axis=1) | (side <= 0).all(axis=1)
            out[(r * S + s)[inside]] = True
        return out.reshape(R, S)

    def run(self, blocks):
        if self._grid is None:
            raise RuntimeError("GoldenBoard.run before load(grid)")
        results = []
        for block in blocks:
            t = self.patches_of(block.voxels)
            P = self._shooters[np.asarray(block.shooter_patch, dtype=np.int64),
                               np.asarray(block.shooter_sample, dtype=np.int64)]
            Q = self._receivers[np.asarray(block.receiver_patch, dtype=np.int64)]
            results.append(self.blocked(P.reshape(-1, 3), Q.reshape(-1, 3), t))
            rays = len(P) * len(Q)
            self._counters["blocks"] += 1
            self._counters["rays"] += rays
            self._counters["tests"] += rays * len(t)
            self._counters["voxels"] += len(np.asarray(block.voxels).reshape(-1))
        return results

    def counters(self):
        """``blocks``, ``rays``, ``tests`` (ray-patch tests, each patch once per block),
        ``voxels`` (voxel visits) and ``crossings`` (tests that passed the plane test)."""
        return dict(self._counters)
