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
from numba import njit, prange

from blockray.errors import ParameterError, option

from ... import threads as _threads  # (also chooses the threading layer before any kernel runs)

__all__ = ["VoxelGrid", "TraversalStats", "default_voxels", "cost_model", "COST_MODEL"]

#: Constants of the paper's cost model, eqs. (5)-(8) (times in microseconds).
COST_MODEL = dict(p=2.5, k_l=2.9, k_L=0.43, t_I0=0.02, t_BT0=9.6, t_BT=0.4)

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


# ---- compiled traversals ------------------------------------------------------------------
#
# Both traversals are numba kernels over whole batches (cache=True: compiled once per machine).
# They do the float arithmetic of the vectorised numpy forms they replaced, operation for
# operation (no fast-math, no fused multiply-add), so they visit the same voxels in the same
# order (checked against them when they were replaced: renders byte-identical, docs/measurements.md).
# A large batch runs on the thread pool (prange, threads.parallel), a small one on the calling
# thread (the same per-item function); each block or ray writes only its own output, so the
# result does not depend on the number of threads. _interval is the scalar form of
# VoxelGrid._range (used, vectorised, by the registration).

@njit(cache=True, inline="always")
def _interval(x, lo, s, m):
    """Closed index range [a, b] (unclipped) of the grown voxels containing coordinate x."""
    return np.int64(math.ceil((x - m - lo) / s)) - 1, np.int64(math.floor((x + m - lo) / s))


@njit(cache=True)
def _emit_box(x0, x1, y0, y1, z0, z1, v, count, nonempty_only, out, o):
    """Visit the voxels of an index box, x outer, z inner. Writes the kept ones (all, or the
    nonempty ones) to ``out[o:]`` when ``out`` is not empty. Returns (visited, tests, kept)."""
    visited = tests = kept = 0
    if x1 < x0 or y1 < y0 or z1 < z0:
        return visited, tests, kept
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            base = (ix * v + iy) * v
            for iz in range(z0, z1 + 1):
                c = count[base + iz]
                visited += 1
                tests += c
                if c > 0 or not nonempty_only:
                    if out.size:
                        out[o + kept] = base + iz
                    kept += 1
    return visited, tests, kept


@njit(cache=True, inline="always")
def _event_t(src, i, p, q, lo, s, m):
    """t (clipped to [0, 1]) of the next event of source i (see :func:`_walk_ray`)."""
    k, e = src[i, 0], src[i, 3]
    if src[i, 6] == 0:
        t = (lo[k] + e * s[k] - m - p[k]) / (q[k] - p[k])
    else:
        t = (lo[k] + (e + 1) * s[k] + m - p[k]) / (q[k] - p[k])
    return min(max(t, 0.0), 1.0)


@njit(cache=True, inline="always")
def _set_source(src, i, k, kind, field, first, last, step, form, offset):
    src[i, 0], src[i, 1], src[i, 2], src[i, 3] = k, kind, field, first
    src[i, 4], src[i, 5], src[i, 6], src[i, 7] = last, step, form, offset


@njit(cache=True)
def _walk_ray(p, q, v, lo, s, m, count, nonempty_only, out, o, src, cur, head):
    """3D-DDA of one segment (see :meth:`VoxelGrid.ray_voxels`). ``src`` (6, 8), ``cur`` (3, 2)
    int64 and ``head`` (6,) float64 are scratch. Returns (visited, tests, kept) as
    :func:`_emit_box`."""
    # event sources, at most two per axis (entering, leaving), each sorted by t:
    # src[i] = axis, kind (0 entering, 1 leaving), field (0: a, 1: b), next e, last e, step,
    #          t form (0: lo + e s - m, 1: lo + (e + 1) s + m), value offset (field := e + offset)
    ns = 0
    for k in range(3):
        a0, b0 = _interval(p[k], lo[k], s[k], m)
        a1, b1 = _interval(q[k], lo[k], s[k], m)
        cur[k, 0], cur[k, 1] = max(a0, 0), min(b0, v - 1)
        d = q[k] - p[k]
        if d > 0:
            _set_source(src, ns, k, 0, 1, max(b0 + 1, 0), min(b1, v - 1), 1, 0, 0)
            _set_source(src, ns + 1, k, 1, 0, max(a0, 0), min(a1 - 1, v - 1), 1, 1, 1)
            ns += 2
        elif d < 0:
            _set_source(src, ns, k, 0, 0, min(a0 - 1, v - 1), max(a1, 0), -1, 1, 0)
            _set_source(src, ns + 1, k, 1, 1, min(b0, v - 1), max(b1 + 1, 0), -1, 0, -1)
            ns += 2
    for i in range(ns):
        head[i] = _event_t(src, i, p, q, lo, s, m) if (src[i, 3] - src[i, 4]) * src[i, 5] <= 0 else np.inf
    visited, tests, kept = _emit_box(cur[0, 0], cur[0, 1], cur[1, 0], cur[1, 1], cur[2, 0], cur[2, 1],
                                     v, count, nonempty_only, out, o)
    # merge the sources in order of (t, kind, source): what a stable sort by (t, kind) gives
    while True:
        best = -1
        for i in range(ns):
            if head[i] == np.inf:
                continue                                    # exhausted
            if best < 0 or head[i] < head[best] or (head[i] == head[best] and src[i, 1] < src[best, 1]):
                best = i
        if best < 0:
            break
        k, kind, e = src[best, 0], src[best, 1], src[best, 3]
        cur[k, src[best, 2]] = e + src[best, 7]
        src[best, 3] = e + src[best, 5]
        head[best] = (_event_t(src, best, p, q, lo, s, m) if (src[best, 3] - src[best, 4]) * src[best, 5] <= 0
                      else np.inf)
        if kind == 0:
            # entering: the new slab, the other axes at their current intervals
            a0, a1 = cur[k, 0], cur[k, 1]
            cur[k, 0] = cur[k, 1] = e
            dv, dt, dk = _emit_box(cur[0, 0], cur[0, 1], cur[1, 0], cur[1, 1], cur[2, 0], cur[2, 1],
                                   v, count, nonempty_only, out, o + kept)
            cur[k, 0], cur[k, 1] = a0, a1
            visited += dv
            tests += dt
            kept += dk
    return visited, tests, kept


_CHUNK = 64     # rays or blocks per parallel work item


@njit(cache=True)
def _walk_chunk(c, P, Q, v, lo, s, m, count, nonempty_only, out, off, visited, tests, kept):
    """:func:`_walk_ray` of rays c * _CHUNK ... Counts into visited, tests, kept; with a
    non-empty ``out``, writes ray i's kept voxels at ``out[off[i]:]`` instead."""
    src, cur, head = np.empty((6, 8), np.int64), np.empty((3, 2), np.int64), np.empty(6)
    for i in range(c * _CHUNK, min(len(P), (c + 1) * _CHUNK)):
        if out.size:
            _walk_ray(P[i], Q[i], v, lo, s, m, count, nonempty_only, out, off[i], src, cur, head)
        else:
            visited[i], tests[i], kept[i] = _walk_ray(P[i], Q[i], v, lo, s, m, count, nonempty_only,
                                                      out, 0, src, cur, head)


def _walk(P, Q, v, lo, s, m, count, nonempty_only, out, off, visited, tests, kept):
    for c in prange((len(P) + _CHUNK - 1) // _CHUNK):
        _walk_chunk(c, P, Q, v, lo, s, m, count, nonempty_only, out, off, visited, tests, kept)


_walk_par, _walk_ser = _threads.twins(_walk)


def _walk_rays(P, Q, v, lo, s, m, count, nonempty_only, fill):
    """:func:`_walk_ray` of rays P[i] -> Q[i]. Returns (voxels, offsets (n + 1,), visited (n,),
    tests (n,)); voxels (the kept ones, CSR) only when ``fill``."""
    n = len(P)
    walk = _walk_par if _threads.parallel(n) else _walk_ser
    visited, tests, kept = np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, np.int64)
    none = np.zeros(0, np.int64)
    walk(P, Q, v, lo, s, m, count, nonempty_only, none, none, visited, tests, kept)
    off = np.concatenate([[0], np.cumsum(kept)]).astype(np.int64)
    out = none
    if fill and off[-1]:
        out = np.empty(off[-1], np.int64)
        walk(P, Q, v, lo, s, m, count, nonempty_only, out, off, visited, tests, kept)
    return out, off, visited, tests


@njit(cache=True)
def _block_slabs(SP, EP, v, lo, s, m, slabs, ray):
    """The slabs of one block ray (see :meth:`VoxelGrid.block_voxels`): starts SP (S, 3), ends
    EP (R, 3). Writes slabs[k] = (D, j, a1, b1, a2, b2) in march order, the index ranges on the
    axes E1 = (D + 1) % 3, E2 = (D + 2) % 3 (empty when b < a); returns their number. ``ray``
    (6, >= S R) is scratch for the rays' terms that do not depend on the slab."""
    S, R = len(SP), len(EP)
    if S == 0 or R == 0:
        return 0
    # march axis: the centroids' displacement (sums in order, as numpy's axis-0 sum)
    best, D, fwd = -1.0, 0, True
    for c in range(3):
        sq, sp = 0.0, 0.0
        for r in range(R):
            sq += EP[r, c]
        for k in range(S):
            sp += SP[k, c]
        mv = sq / R - sp / S
        if abs(mv) > best:
            best, D, fwd = abs(mv), c, mv >= 0
    E1, E2 = (D + 1) % 3, (D + 2) % 3
    xmin, xmax = np.inf, -np.inf
    for k in range(S):
        for r in range(R):
            pD = SP[k, D]
            xe = pD + (EP[r, D] - pD)
            xmin, xmax = min(xmin, pD, xe), max(xmax, pD, xe)
    j0 = max(np.int64(math.ceil((xmin - m - lo[D]) / s[D])) - 1, 0)
    j1 = min(np.int64(math.floor((xmax + m - lo[D]) / s[D])), v - 1)
    J = max(j1 - j0 + 1, 0)
    # per ray (start k, end r): its terms along D and across, computed once for all slabs
    n = 0
    for k in range(S):
        for r in range(R):
            pD = SP[k, D]
            dD = EP[r, D] - pD
            ray[0, n], ray[1, n] = pD, (1.0 / dD if dD != 0 else 0.0)
            ray[2, n], ray[3, n] = SP[k, E1], EP[r, E1] - SP[k, E1]
            ray[4, n], ray[5, n] = SP[k, E2], EP[r, E2] - SP[k, E2]
            n += 1
    for jj in range(J):
        j = j0 + jj if fwd else j1 - jj
        x_lo = (lo[D] - m) + j * s[D]
        x_hi = (lo[D] + m) + (j + 1) * s[D]
        cmin1 = cmin2 = np.inf
        cmax1 = cmax2 = -np.inf
        any_ok = False
        for i in range(n):
            pD, inv = ray[0, i], ray[1, i]
            if inv != 0:
                ta = (x_lo - pD) * inv
                tb = (x_hi - pD) * inv
                t0 = np.maximum(np.minimum(ta, tb), 0.0)
                t1 = np.minimum(np.maximum(ta, tb), 1.0)
                ok = t0 <= t1
            else:
                t0, t1 = 0.0, 1.0
                ok = x_lo <= pD and pD <= x_hi
            if ok:
                any_ok = True
                p1, d1, p2, d2 = ray[2, i], ray[3, i], ray[4, i], ray[5, i]
                c0, c1 = p1 + t0 * d1, p1 + t1 * d1
                cmin1, cmax1 = min(cmin1, c0, c1), max(cmax1, c0, c1)
                c0, c1 = p2 + t0 * d2, p2 + t1 * d2
                cmin2, cmax2 = min(cmin2, c0, c1), max(cmax2, c0, c1)
        if not any_ok:
            cmin1 = cmin2 = cmax1 = cmax2 = 0.0
        slabs[jj, 0], slabs[jj, 1] = D, j
        a1 = np.int64(math.ceil((cmin1 - m - lo[E1]) / s[E1])) - 1
        b1 = np.int64(math.floor((cmax1 + m - lo[E1]) / s[E1]))
        a2 = np.int64(math.ceil((cmin2 - m - lo[E2]) / s[E2])) - 1
        b2 = np.int64(math.floor((cmax2 + m - lo[E2]) / s[E2]))
        slabs[jj, 2], slabs[jj, 3] = max(a1, 0), min(b1, v - 1) if any_ok else -1
        slabs[jj, 4], slabs[jj, 5] = max(a2, 0), min(b2, v - 1) if any_ok else -1
    return J


@njit(cache=True, inline="always")
def _emit_slab(sl, v, count, nonempty_only, out, o):
    """:func:`_emit_box` of a slab (D, j, a1, b1, a2, b2) from :func:`_block_slabs`."""
    D, j = sl[0], sl[1]
    if D == 0:
        return _emit_box(j, j, sl[2], sl[3], sl[4], sl[5], v, count, nonempty_only, out, o)
    if D == 1:
        return _emit_box(sl[4], sl[5], j, j, sl[2], sl[3], v, count, nonempty_only, out, o)
    return _emit_box(sl[2], sl[3], sl[4], sl[5], j, j, v, count, nonempty_only, out, o)


@njit(cache=True)
def _blocks_chunk(c, SP, s_off, EP, e_off, v, lo, s, m, count, nonempty_only, slabs, J, visited, tests, kept,
                  out, off):
    """Blocks c * _CHUNK ...: their slabs and counts (first pass), or with a non-empty ``out``
    their kept voxels at ``out[off[b]:]`` (second pass, from the stored slabs)."""
    none = np.zeros(0, np.int64)
    ray = np.empty((6, 0))
    for b in range(c * _CHUNK, min(len(s_off) - 1, (c + 1) * _CHUNK)):
        k0 = b % _CHUNK
        if out.size == 0:
            n = (s_off[b + 1] - s_off[b]) * (e_off[b + 1] - e_off[b])
            if ray.shape[1] < n:
                ray = np.empty((6, n))
            J[b] = _block_slabs(SP[s_off[b]:s_off[b + 1]], EP[e_off[b]:e_off[b + 1]], v, lo, s, m,
                                slabs[c, k0], ray)
            for k in range(J[b]):
                dv, dt, dk = _emit_slab(slabs[c, k0, k], v, count, nonempty_only, none, 0)
                visited[b] += dv
                tests[b] += dt
                kept[b] += dk
        else:
            o = off[b]
            for k in range(J[b]):
                o += _emit_slab(slabs[c, k0, k], v, count, nonempty_only, out, o)[2]


def _blocks(SP, s_off, EP, e_off, v, lo, s, m, count, nonempty_only, slabs, J, visited, tests, kept, out, off):
    for c in prange(slabs.shape[0]):
        _blocks_chunk(c, SP, s_off, EP, e_off, v, lo, s, m, count, nonempty_only, slabs, J, visited, tests, kept,
                      out, off)


_blocks_par, _blocks_ser = _threads.twins(_blocks)


def _traverse_blocks(SP, s_off, EP, e_off, v, lo, s, m, count, nonempty_only):
    """Block rays b = (SP[s_off[b]:s_off[b+1]], EP[e_off[b]:e_off[b+1]]). Returns (voxels,
    offsets (B + 1,), visited (B,), tests (B,)): the kept voxels in march order (CSR), and per
    block the voxels visited and the patch records they hold (sum of count)."""
    B = len(s_off) - 1
    rays = int((np.diff(s_off) * np.diff(e_off)).sum())
    run = _blocks_par if _threads.parallel(rays) else _blocks_ser
    slabs = np.empty(((B + _CHUNK - 1) // _CHUNK, _CHUNK, v, 6), np.int64)
    J, visited, tests, kept = (np.zeros(B, np.int64) for _ in range(4))
    none = np.zeros(0, np.int64)
    run(SP, s_off, EP, e_off, v, lo, s, m, count, nonempty_only, slabs, J, visited, tests, kept, none, none)
    off = np.concatenate([[0], np.cumsum(kept)]).astype(np.int64)
    out = none
    if off[-1]:
        out = np.empty(off[-1], np.int64)
        run(SP, s_off, EP, e_off, v, lo, s, m, count, nonempty_only, slabs, J, visited, tests, kept, out, off)
    return out, off, visited, tests


# ---- statistics ---------------------------------------------------------------------------

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


# ---- cost model ---------------------------------------------------------------------------

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
