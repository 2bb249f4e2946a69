"""The uniform voxel grid, its patch registration, and the two traversals (per-ray and block ray).

This is the host side of the paper's section 3: space is cut into v x v x v equal voxels, every
patch is registered in every voxel its triangle touches, and rays are walked through the grid,
either one at a time (3D-DDA, the reference) or as a **block ray**: the bundle of all rays from
a few shooter points to the receivers whose end points share a voxel, marched one voxel slab at
a time along the axis the bundle moves furthest, visiting every voxel its cross-section covers.

Conservativeness and the margin
-------------------------------
Voxel boxes are **closed** (a point on a face belongs to both neighbours) and are **grown by
``margin``** (scene units, per axis: a box, not a sphere) in both the registration and the
traversals. A patch is registered in voxel V when its triangle touches V's grown box; a ray
visits V when its segment touches V's grown box. This is what a board that perturbs geometry by
up to ``margin`` (per coordinate) needs: if the perturbed ray hits the perturbed triangle at X,
the original segment and the original triangle each pass within ``margin`` of X, so both reach
the grown box of the voxel holding X (for a scene inside ``[lo, hi]``). On top of ``margin`` a
rounding tolerance :attr:`VoxelGrid.tolerance` (1e-9 of the grid's coordinate scale) is added,
so float rounding can only add voxels, never drop one. Geometry further than ``margin`` outside
``[lo, hi]`` touches no voxel; the grid therefore requires the scene to lie inside ``[lo, hi]``.

Linear voxel index: ``idx = (ix * v + iy) * v + iz``.
"""

import math

import numpy as np

from ...errors import ParameterError, option
from .walk import _traverse_blocks, _walk_rays

__all__ = ["VoxelGrid"]

_CHUNK_PAIRS = 1 << 20          # triangle-voxel candidate pairs per SAT batch (bounds memory)
_MAX_VOXELS = 256
_SLAB_ROWS = 1 << 18         # blocks x v slabs per traversal batch (bounds memory)


class VoxelGrid:
    """A v x v x v grid over ``[lo, hi]`` with every patch registered in the voxels it touches.

    Parameters
    ----------
    vertices : (N, 3, 3) float array
        Corners of each patch (triangle).
    v : int
        Voxels per axis, 1 to 256.
    lo, hi : (3,) float, optional
        Grid box. Default: the vertices' bounding box; an axis on which the scene is flat (extent
        below 1e-6 of the largest) is padded to 1e-3 of the largest extent, so voxels never have
        zero size. The scene must lie inside ``[lo, hi]`` (see the module docstring).
    margin : float
        Registration and traversal margin in scene units (>= 0), normally ``board.margin``.

    Attributes
    ----------
    v, lo, hi, voxel_size, margin, tolerance
    start, count : (v**3,) int64
        CSR registration: the patches of voxel ``i`` are ``patches[start[i]:start[i] + count[i]]``.
    patches : (M,) int64
        Patch indices, ascending within each voxel.
    """

    def __init__(self, vertices, v, *, lo=None, hi=None, margin=0.0):
        tri = np.asarray(vertices, dtype=np.float64)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3):
            raise ParameterError(f"voxel grid: vertices must have shape (N, 3, 3), not {tri.shape}")
        if not np.all(np.isfinite(tri)):
            raise ParameterError("voxel grid: vertices must be finite")
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= _MAX_VOXELS:
            raise ParameterError(f"{option('voxels')} must be an integer from 1 to {_MAX_VOXELS}, not {v!r}")
        margin = float(margin)
        if not (math.isfinite(margin) and margin >= 0):
            raise ParameterError(f"voxel grid: margin must be a finite number >= 0, not {margin!r}")
        self.v = int(v)
        self.margin = margin

        if lo is None or hi is None:
            if len(tri) == 0:
                raise ParameterError("voxel grid: an empty scene needs an explicit lo and hi")
            pts = tri.reshape(-1, 3)
            blo, bhi = pts.min(axis=0), pts.max(axis=0)
            extent = bhi - blo
            size = extent.max() if extent.max() > 0 else 1.0
            flat = extent < 1e-6 * size
            pad = np.where(flat, 0.5e-3 * size, 0.0)
            blo, bhi = blo - pad, bhi + pad
            lo = blo if lo is None else lo
            hi = bhi if hi is None else hi
        self.lo = np.array(lo, dtype=np.float64).reshape(3)
        self.hi = np.array(hi, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(self.lo)) and np.all(np.isfinite(self.hi))
                and np.all(self.hi > self.lo)):
            raise ParameterError(f"voxel grid: need finite lo < hi on every axis, not {self.lo}, {self.hi}")
        self.voxel_size = (self.hi - self.lo) / self.v
        scale = max(np.abs(self.lo).max(), np.abs(self.hi).max(), (self.hi - self.lo).max())
        #: rounding allowance (scene units) added to the margin: rounding adds voxels, never drops one
        self.tolerance = 1e-9 * scale
        self._m = self.margin + self.tolerance
        if len(tri):
            slack = self.tolerance + 1e-12 * scale
            pts = tri.reshape(-1, 3)
            if np.any(pts < self.lo - slack) or np.any(pts > self.hi + slack):
                raise ParameterError("voxel grid: the scene must lie inside [lo, hi]")
        self.n_patches = len(tri)
        self._register(tri)

    # ---- indexing -------------------------------------------------------------------------

    @property
    def voxels(self):
        """Total number of voxels, v**3."""
        return self.v ** 3

    def cell_of(self, points):
        """(M, 3) int64 voxel coordinates ijk of each point, clamped into the grid."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = np.floor((p - self.lo) / self.voxel_size)
        return np.clip(ijk, 0, self.v - 1).astype(np.int64)

    def voxel_of(self, points):
        """(M,) int64 linear index of the voxel holding each point, clamped into the grid."""
        return self.index_of(self.cell_of(points))

    def index_of(self, ijk):
        """Linear index of voxel coordinates (..., 3)."""
        ijk = np.asarray(ijk, dtype=np.int64)
        return (ijk[..., 0] * self.v + ijk[..., 1]) * self.v + ijk[..., 2]

    def ijk_of(self, idx):
        """(M, 3) voxel coordinates of linear indices."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        ix, rest = np.divmod(idx, self.v * self.v)
        iy, iz = np.divmod(rest, self.v)
        return np.stack([ix, iy, iz], axis=1)

    def box_of(self, idx):
        """(lo, hi) corners, each (M, 3), of the (ungrown) boxes of voxels ``idx``."""
        ijk = self.ijk_of(idx)
        return self.lo + ijk * self.voxel_size, self.lo + (ijk + 1) * self.voxel_size

    def patches_in(self, voxel):
        """int64 array of the patches registered in one voxel (ascending)."""
        s = self.start[voxel]
        return self.patches[s:s + self.count[voxel]]

    def group_points(self, points):
        """Group points by their voxel: list of (voxel, point indices), voxels ascending."""
        vox = self.voxel_of(points)
        order = np.argsort(vox, kind="stable")
        keys = vox[order]
        cuts = np.flatnonzero(np.diff(keys)) + 1
        return [(int(keys[g[0]]), order[g]) for g in np.split(np.arange(len(order)), cuts) if len(g)]

    def _range(self, x, axis_lo, size):
        """Closed index range [a, b] (unclipped) of the grown voxels containing coordinate x."""
        u_lo = (x - self._m - axis_lo) / size
        u_hi = (x + self._m - axis_lo) / size
        return np.ceil(u_lo).astype(np.int64) - 1, np.floor(u_hi).astype(np.int64)

    # ---- registration ---------------------------------------------------------------------

    def _register(self, tri):
        v, m = self.v, self._m
        n = len(tri)
        a, b = self._range(tri.min(axis=1), self.lo, self.voxel_size)     # (N, 3) each
        b = self._range(tri.max(axis=1), self.lo, self.voxel_size)[1]
        inside = np.all((a <= v - 1) & (b >= 0), axis=1)
        a, b = np.clip(a, 0, v - 1), np.clip(b, 0, v - 1)
        size = np.where(inside[:, None], b - a + 1, 0)
        cand = size.prod(axis=1)
        vox_parts, pat_parts = [], []
        t0 = 0
        while t0 < n:
            # take as many triangles as fit in one batch (at least one)
            csum = np.cumsum(cand[t0:])
            t1 = t0 + max(1, int(np.searchsorted(csum, _CHUNK_PAIRS, side="right")))
            tri_idx = np.repeat(np.arange(t0, t1), cand[t0:t1])
            if len(tri_idx):
                first = np.cumsum(cand[t0:t1]) - cand[t0:t1]
                local = np.arange(len(tri_idx)) - np.repeat(first, cand[t0:t1])
                sz = size[tri_idx]
                iz = local % sz[:, 2]
                rest = local // sz[:, 2]
                iy = rest % sz[:, 1]
                ix = rest // sz[:, 1]
                ijk = a[tri_idx] + np.stack([ix, iy, iz], axis=1)
                center = self.lo + (ijk + 0.5) * self.voxel_size
                half = self.voxel_size / 2 + m
                keep = _tri_box_overlap(tri[tri_idx], center, half)
                vox_parts.append(self.index_of(ijk[keep]))
                pat_parts.append(tri_idx[keep])
            t0 = t1
        vox = np.concatenate(vox_parts) if vox_parts else np.zeros(0, np.int64)
        pat = np.concatenate(pat_parts) if pat_parts else np.zeros(0, np.int64)
        order = np.argsort(vox, kind="stable")      # stable: patches stay ascending in a voxel
        self.patches = pat[order].astype(np.int64)
        self.count = np.bincount(vox, minlength=v ** 3).astype(np.int64)
        self.start = (np.cumsum(self.count) - self.count).astype(np.int64)

    # ---- traversals (compiled kernels below) ----------------------------------------------

    def _args(self):
        return self.v, self.lo, self.voxel_size, self._m, self.count

    def ray_voxels(self, p, q):
        """Voxels the segment p -> q touches (grown by margin), in the order it first touches them.

        3D-DDA in the manner of Amanatides and Woo, generalised to closed grown boxes. Along each
        axis the set of grown voxels containing the point is an index interval [a(t), b(t)] whose
        ends move monotonically with t; the segment touches exactly the voxels of the union over
        t in [0, 1] of the products of the three intervals. The walk merges the events where an
        interval gains an index (**entering**) or loses one (**leaving**), in order of t, entering
        first at equal t, so a voxel touched only at a corner or edge (a tie) is still visited, and
        emits, at each entering event, the new slab of voxels. Every voxel is emitted once (the
        intervals are monotone, so each voxel is touched during one interval of t). With margin 0
        this is the classic DDA plus every neighbour touched at exact face, edge and corner
        crossings.
        """
        P = np.asarray(p, dtype=np.float64).reshape(1, 3)
        Q = np.asarray(q, dtype=np.float64).reshape(1, 3)
        return self.rays_voxels(P, Q)[0]

    def rays_voxels(self, P, Q, *, nonempty_only=False):
        """:meth:`ray_voxels` of many segments P[i] -> Q[i] (n, 3) at once: (voxels, offsets (n + 1,)),
        ray i's voxels being ``voxels[offsets[i]:offsets[i + 1]]``; only those holding patches
        with ``nonempty_only``."""
        P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 3)
        Q = np.ascontiguousarray(Q, dtype=np.float64).reshape(-1, 3)
        vox, off, _, _ = _walk_rays(P, Q, *self._args(), bool(nonempty_only), True)
        return vox, off

    def rays_counts(self, P, Q):
        """Per segment P[i] -> Q[i]: the voxels it visits (:meth:`ray_voxels`) and the patch records
        they hold, (n,) int64 each, without listing the voxels."""
        P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 3)
        Q = np.ascontiguousarray(Q, dtype=np.float64).reshape(-1, 3)
        _, _, visited, tests = _walk_rays(P, Q, *self._args(), False, False)
        return visited, tests

    def block_axis(self, starts, ends):
        """The axis along which the bundle moves furthest (its centroid's displacement)."""
        move = np.abs(ends.sum(axis=0) / len(ends) - starts.sum(axis=0) / len(starts))
        return int(move.argmax())

    def block_voxels(self, starts, ends):
        """Voxels a block ray visits: the bundle of all rays from every start to every end.

        The march axis D is :meth:`block_axis`. For each voxel slab j along D (grown by margin)
        between the bundle's extreme points, every ray's segment is clipped to the slab; the
        bundle's cross-section there is the bounding rectangle, on the two other axes, of all
        clipped pieces, grown by margin; every voxel of slab j the rectangle covers is visited.
        Slabs are visited in the direction the bundle moves, so the result is in march order,
        without duplicates.

        This is a superset of the voxels every member ray touches (:meth:`ray_voxels`): a ray
        touching voxel (j, i1, i2) at parameter t lies in grown slab j at t, so its point at t is
        inside the clipped piece, hence inside the rectangle, whose grown voxel range includes
        i1 and i2.
        """
        return self.block_voxels_many([(starts, ends)])[0]

    def block_voxels_many(self, blocks):
        """:meth:`block_voxels` of many blocks: a list of (starts, ends) -> list of arrays."""
        P = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p, _ in blocks]
        Q = [np.asarray(q, dtype=np.float64).reshape(-1, 3) for _, q in blocks]
        cat = lambda xs: np.concatenate(xs) if xs else np.zeros((0, 3))
        off = lambda xs: np.concatenate([[0], np.cumsum([len(x) for x in xs], dtype=np.int64)])
        vox, voff, _, _ = self.traverse_blocks(cat(P), off(P), cat(Q), off(Q))
        return np.split(vox, voff[1:-1])

    def traverse_blocks(self, starts, start_off, ends, end_off, *, nonempty_only=False):
        """:meth:`block_voxels` of block rays b = (starts[start_off[b]:start_off[b+1]],
        ends[end_off[b]:end_off[b+1]]), all at once.

        Returns ``(voxels, offsets, visited, tests)``: block b's voxels in march order are
        ``voxels[offsets[b]:offsets[b+1]]`` (only those holding patches with ``nonempty_only``);
        ``visited`` (B,) counts all the voxels it visits and ``tests`` (B,) the patch records
        they hold.
        """
        starts = np.ascontiguousarray(starts, dtype=np.float64).reshape(-1, 3)
        ends = np.ascontiguousarray(ends, dtype=np.float64).reshape(-1, 3)
        start_off = np.asarray(start_off, dtype=np.int64)
        end_off = np.asarray(end_off, dtype=np.int64)
        B = len(start_off) - 1
        take = max(1, _SLAB_ROWS // self.v)            # bounds the (blocks, v, 6) slab table
        if B <= take:
            return _traverse_blocks(starts, start_off, ends, end_off, *self._args(), bool(nonempty_only))
        parts = [_traverse_blocks(starts, start_off[b:b + take + 1], ends, end_off[b:b + take + 1],
                                  *self._args(), bool(nonempty_only)) for b in range(0, B, take)]
        vox = np.concatenate([p[0] for p in parts])
        sizes = np.concatenate([np.diff(p[1]) for p in parts])
        return (vox, np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]))


def _tri_box_overlap(tri, center, half):
    """Akenine-Moller separating-axis test, vectorised: does triangle k touch box k (closed)?

    tri (P, 3, 3), center (P, 3), half (3,) or (P, 3). Thirteen axes: the three box normals, the
    triangle normal and the nine edge x box-axis cross products. Touching counts as overlap.
    """
    v0 = tri[:, 0] - center
    v1 = tri[:, 1] - center
    v2 = tri[:, 2] - center
    h = np.broadcast_to(half, v0.shape)
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    sep = np.zeros(len(v0), bool)
    # box normals
    for k in range(3):
        mn = np.minimum(np.minimum(v0[:, k], v1[:, k]), v2[:, k])
        mx = np.maximum(np.maximum(v0[:, k], v1[:, k]), v2[:, k])
        sep |= (mn > h[:, k]) | (mx < -h[:, k])
    x0, y0, z0 = v0[:, 0], v0[:, 1], v0[:, 2]
    x1, y1, z1 = v1[:, 0], v1[:, 1], v1[:, 2]
    x2, y2, z2 = v2[:, 0], v2[:, 1], v2[:, 2]
    # edge x axis cross products: e x X = (0, ez, -ey), e x Y = (-ez, 0, ex), e x Z = (ey, -ex, 0)
    for ex, ey, ez in ((x1 - x0, y1 - y0, z1 - z0), (x2 - x1, y2 - y1, z2 - z1),
                       (x0 - x2, y0 - y2, z0 - z2)):
        for pa, pb, pc, r in (
                (ez * y0 - ey * z0, ez * y1 - ey * z1, ez * y2 - ey * z2, hy * np.abs(ez) + hz * np.abs(ey)),
                (ex * z0 - ez * x0, ex * z1 - ez * x1, ex * z2 - ez * x2, hx * np.abs(ez) + hz * np.abs(ex)),
                (ey * x0 - ex * y0, ey * x1 - ex * y1, ey * x2 - ex * y2, hx * np.abs(ey) + hy * np.abs(ex))):
            mn = np.minimum(np.minimum(pa, pb), pc)
            mx = np.maximum(np.maximum(pa, pb), pc)
            sep |= (mn > r) | (mx < -r)
    # triangle normal
    nrm = np.cross(v1 - v0, v2 - v1)
    pa = np.einsum("ij,ij->i", nrm, v0)
    pb = np.einsum("ij,ij->i", nrm, v1)
    pc = np.einsum("ij,ij->i", nrm, v2)
    r = np.einsum("ij,ij->i", h, np.abs(nrm))
    mn = np.minimum(np.minimum(pa, pb), pc)
    mx = np.maximum(np.maximum(pa, pb), pc)
    sep |= (mn > r) | (mx < -r)
    return ~sep
