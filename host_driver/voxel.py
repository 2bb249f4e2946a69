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

from blockray.errors import ParameterError

__all__ = ["VoxelGrid", "TraversalStats", "default_voxels", "cost_model", "COST_MODEL"]

#: Constants of the paper's cost model, eqs. (5)-(8) (times in microseconds).
COST_MODEL = dict(p=2.5, k_l=2.9, k_L=0.43, t_I0=0.02, t_BT0=9.6, t_BT=0.4)

_CHUNK_PAIRS = 1 << 20          # triangle-voxel candidate pairs per SAT batch (bounds memory)
_MAX_VOXELS = 256


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
            raise ParameterError(f"--voxels must be an integer from 1 to {_MAX_VOXELS}, not {v!r}")
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

    # ---- per-ray traversal ----------------------------------------------------------------

    def ray_voxels(self, p, q):
        """Voxels the segment p -> q touches (grown by margin), in the order it first touches them.

        3D-DDA in the manner of Amanatides and Woo, generalised to closed grown boxes. Along each
        axis the set of grown voxels containing the point is an index interval [a(t), b(t)] whose
        ends move monotonically with t; the segment touches exactly the voxels of the union over
        t in [0, 1] of the products of the three intervals. The walk sorts the events where an
        interval gains an index (**entering**) or loses one (**leaving**), entering first at equal
        t, so a voxel touched only at a corner or edge (a tie) is still visited, and emits, at
        each entering event, the new slab of voxels. Every voxel is emitted once (the intervals
        are monotone, so each voxel is touched during one interval of t). With margin 0 this is
        the classic DDA plus every neighbour touched at exact face, edge and corner crossings.
        """
        p = np.asarray(p, dtype=np.float64).reshape(3)
        q = np.asarray(q, dtype=np.float64).reshape(3)
        v, lo, s = self.v, self.lo, self.voxel_size
        d = q - p
        a0, b0 = self._range(p, lo, s)
        a1, b1 = self._range(q, lo, s)
        # initial (clipped) intervals and the events, per axis
        cur_a = np.maximum(a0, 0)
        cur_b = np.minimum(b0, v - 1)
        ts, kinds, axes, fields, values = [], [], [], [], []
        m = self._m
        for k in range(3):
            if d[k] > 0:
                ent = np.arange(max(b0[k] + 1, 0), min(b1[k], v - 1) + 1)       # b <- k'
                lev = np.arange(max(a0[k], 0), min(a1[k] - 1, v - 1) + 1)      # a <- k'+1
                t_ent = (lo[k] + ent * s[k] - m - p[k]) / d[k]
                t_lev = (lo[k] + (lev + 1) * s[k] + m - p[k]) / d[k]
                new = [(t_ent, 0, 1, ent), (t_lev, 1, 0, lev + 1)]
            elif d[k] < 0:
                ent = np.arange(min(a0[k] - 1, v - 1), max(a1[k], 0) - 1, -1)   # a <- k'
                lev = np.arange(min(b0[k], v - 1), max(b1[k] + 1, 0) - 1, -1)   # b <- k'-1
                t_ent = (lo[k] + (ent + 1) * s[k] + m - p[k]) / d[k]
                t_lev = (lo[k] + lev * s[k] - m - p[k]) / d[k]
                new = [(t_ent, 0, 0, ent), (t_lev, 1, 1, lev - 1)]
            else:
                continue
            for t, kind, field, val in new:
                ts.append(t)
                kinds.append(np.full(len(t), kind))
                axes.append(np.full(len(t), k))
                fields.append(np.full(len(t), field))
                values.append(val)
        if ts:
            t = np.clip(np.concatenate(ts), 0.0, 1.0)
            kind = np.concatenate(kinds)
            order = np.lexsort((kind, t))
            kind = kind[order]
            axis = np.concatenate(axes)[order]
            field = np.concatenate(fields)[order]
            value = np.concatenate(values)[order]
        else:
            kind = axis = field = value = np.zeros(0, np.int64)
        E = len(kind)
        # interval ends after every event: forward-fill the value each event sets
        pos = np.arange(E)
        rng = np.empty((E + 1, 3, 2), np.int64)       # [event, axis, (a, b)]
        rng[0, :, 0], rng[0, :, 1] = cur_a, cur_b
        for k in range(3):
            for f in range(2):
                hit = (axis == k) & (field == f)
                last = np.maximum.accumulate(np.where(hit, pos, -1)) if E else pos
                col = np.where(last >= 0, value[np.maximum(last, 0)], rng[0, k, f]) if E else last
                rng[1:, k, f] = col
        # emissions: the initial box, then at each entering event the slab it adds
        ent = np.flatnonzero(kind == 0)
        boxes = rng[np.concatenate([[0], ent + 1])].copy()      # (B, 3, 2)
        ent_axis = axis[ent]
        ent_val = value[ent]
        bi = np.arange(1, len(boxes))
        boxes[bi, ent_axis, 0] = ent_val
        boxes[bi, ent_axis, 1] = ent_val
        return self._expand(boxes)

    def _expand(self, boxes):
        """Linear indices of the voxels of a sequence of index boxes (B, 3, 2), box by box."""
        ext = boxes[:, :, 1] - boxes[:, :, 0] + 1
        ext = np.where(np.all(ext > 0, axis=1)[:, None], ext, 0)
        n = ext.prod(axis=1)
        total = int(n.sum())
        if total == 0:
            return np.zeros(0, np.int64)
        box = np.repeat(np.arange(len(boxes)), n)
        local = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
        e = ext[box]
        iz = local % e[:, 2]
        rest = local // e[:, 2]
        iy = rest % e[:, 1]
        ix = rest // e[:, 1]
        b = boxes[box, :, 0]
        return ((b[:, 0] + ix) * self.v + b[:, 1] + iy) * self.v + b[:, 2] + iz

    # ---- block-ray traversal --------------------------------------------------------------

    def block_axis(self, starts, ends):
        """The axis along which the bundle moves furthest (its centroid's displacement)."""
        move = np.abs(ends.sum(axis=0) / len(ends) - starts.sum(axis=0) / len(starts))
        return int(move.argmax())

    def block_voxels(self, starts, ends):
        """Voxels a block ray visits: the bundle of all rays from every start to every end.

        The march axis D is :meth:`block_axis`. For each voxel slab j along D (grown by margin),
        every ray's segment is clipped to the slab; the bundle's cross-section there is the
        bounding rectangle, on the two other axes, of all clipped pieces, grown by margin; every
        voxel of slab j the rectangle covers is visited. Slabs are visited in the direction the
        bundle moves, so the result is in march order, without duplicates.

        This is a superset of the voxels every member ray touches (:meth:`ray_voxels`): a ray
        touching voxel (j, i1, i2) at parameter t lies in grown slab j at t, so its point at t is
        inside the clipped piece, hence inside the rectangle, whose grown voxel range includes
        i1 and i2.
        """
        P = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        Q = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        if len(P) == 0 or len(Q) == 0:
            return np.zeros(0, np.int64)
        v, lo, s, m = self.v, self.lo, self.voxel_size, self._m
        D = self.block_axis(P, Q)
        E = [(D + 1) % 3, (D + 2) % 3]
        # slabs the bundle can reach along D
        xD = np.concatenate([P[:, D], Q[:, D]])
        j0 = max(math.ceil((xD.min() - m - lo[D]) / s[D]) - 1, 0)
        j1 = min(math.floor((xD.max() + m - lo[D]) / s[D]), v - 1)
        if j0 > j1:
            return np.zeros(0, np.int64)
        js = np.arange(j0, j1 + 1)
        if Q[:, D].sum() / len(Q) < P[:, D].sum() / len(P):
            js = js[::-1]
        # rays r = (start r // R, end r % R): p (n,), d (n,) along D; pe, de (n, 2) across
        pD = np.repeat(P[:, D], len(Q))
        dD = (Q[None, :, D] - P[:, None, D]).reshape(-1)
        pe = np.repeat(P[:, E], len(Q), axis=0)
        de = (Q[None, :, E] - P[:, None, E]).reshape(-1, 2)
        x_lo = (lo[D] - m) + js[:, None] * s[D]            # (J, 1) grown slab bounds
        x_hi = (lo[D] + m) + (js[:, None] + 1) * s[D]
        moving = dD != 0
        if moving.all():
            inv = 1.0 / dD
            ta = (x_lo - pD) * inv
            tb = (x_hi - pD) * inv
            t0 = np.maximum(np.minimum(ta, tb), 0.0)                            # (J, n)
            t1 = np.minimum(np.maximum(ta, tb), 1.0)
            ok = t0 <= t1
        else:
            inv = 1.0 / np.where(moving, dD, 1.0)
            ta = (x_lo - pD) * inv
            tb = (x_hi - pD) * inv
            t0 = np.where(moving, np.maximum(np.minimum(ta, tb), 0.0), 0.0)
            t1 = np.where(moving, np.minimum(np.maximum(ta, tb), 1.0), 1.0)
            ok = np.where(moving, t0 <= t1, (x_lo <= pD) & (pD <= x_hi))
        c0 = pe + t0[:, :, None] * de                                           # (J, n, 2)
        c1 = pe + t1[:, :, None] * de
        okk = ok[:, :, None]
        cmin = np.where(okk, np.minimum(c0, c1), np.inf).min(axis=1)            # (J, 2)
        cmax = np.where(okk, np.maximum(c0, c1), -np.inf).max(axis=1)
        any_ok = ok.any(axis=1)
        cmin[~any_ok] = 0.0
        cmax[~any_ok] = 0.0
        a = np.ceil((cmin - m - lo[E]) / s[E]).astype(np.int64) - 1
        b = np.floor((cmax + m - lo[E]) / s[E]).astype(np.int64)
        boxes = np.empty((len(js), 3, 2), np.int64)
        boxes[:, D, 0] = js
        boxes[:, D, 1] = js
        boxes[:, E, 0] = np.maximum(a, 0)
        boxes[:, E, 1] = np.where(any_ok[:, None], np.minimum(b, v - 1), -1)
        return self._expand(boxes)


    def block_voxels_many(self, blocks, *, chunk=1 << 20):
        """:meth:`block_voxels` of many blocks at once: a list of (starts, ends) -> list of arrays.

        The same computation, vectorised across blocks (rays padded to the largest block, slabs to
        v + 1). It saves the per-call overhead when blocks are large and the grid coarse (2-4x at
        v <= 9 in benchmarks/bench_traverse.py); at v = 32 the padding eats the gain.
        ``chunk`` bounds the working arrays (blocks x slabs x rays elements per batch).
        """
        out = [None] * len(blocks)
        order = []
        for b, (P, Q) in enumerate(blocks):
            P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
            Q = np.asarray(Q, dtype=np.float64).reshape(-1, 3)
            if len(P) == 0 or len(Q) == 0:
                out[b] = np.zeros(0, np.int64)
            else:
                order.append((b, P, Q))
        n_max = max((len(P) * len(Q) for _, P, Q in order), default=1)
        take = max(1, chunk // (n_max * (self.v + 1)))
        for k in range(0, len(order), take):
            group = order[k:k + take]
            for (b, _, _), vox in zip(group, self._block_batch([(P, Q) for _, P, Q in group])):
                out[b] = vox
        return out

    def _block_batch(self, blocks):
        v, lo, s, m = self.v, self.lo, self.voxel_size, self._m
        B = len(blocks)
        n = max(len(P) * len(Q) for P, Q in blocks)
        p = np.zeros((B, n, 3))
        d = np.zeros((B, n, 3))
        valid = np.zeros((B, n), bool)
        mean_move = np.empty((B, 3))
        for b, (P, Q) in enumerate(blocks):
            r = len(P) * len(Q)
            p[b, :r] = np.repeat(P, len(Q), axis=0)
            d[b, :r] = (Q[None, :, :] - P[:, None, :]).reshape(-1, 3)
            valid[b, :r] = True
            mean_move[b] = Q.sum(axis=0) / len(Q) - P.sum(axis=0) / len(P)
        D = np.abs(mean_move).argmax(axis=1)                          # (B,)
        E = np.stack([(D + 1) % 3, (D + 2) % 3], axis=1)              # (B, 2)
        bi = np.arange(B)
        pD, dD = p[bi, :, D], d[bi, :, D]                             # (B, n)
        pe = np.take_along_axis(p, E[:, None, :], axis=2)             # (B, n, 2)
        de = np.take_along_axis(d, E[:, None, :], axis=2)
        loD, sD = lo[D], s[D]
        xs = np.where(valid, pD, np.nan)
        xe = np.where(valid, pD + dD, np.nan)
        xmin = np.fmin(np.nanmin(xs, axis=1), np.nanmin(xe, axis=1))
        xmax = np.fmax(np.nanmax(xs, axis=1), np.nanmax(xe, axis=1))
        j0 = np.maximum(np.ceil((xmin - m - loD) / sD).astype(np.int64) - 1, 0)
        j1 = np.minimum(np.floor((xmax + m - loD) / sD).astype(np.int64), v - 1)
        J = np.maximum(j1 - j0 + 1, 0)
        Jm = int(J.max())
        if Jm == 0:
            return [np.zeros(0, np.int64) for _ in range(B)]
        jj = np.arange(Jm)
        forward = mean_move[bi, D] >= 0
        js = np.where(forward[:, None], j0[:, None] + jj, j1[:, None] - jj)        # (B, J)
        slab_ok = jj < J[:, None]
        x_lo = ((loD - m)[:, None] + js * sD[:, None])[:, :, None]                 # (B, J, 1)
        x_hi = ((loD + m)[:, None] + (js + 1) * sD[:, None])[:, :, None]
        moving = (dD != 0)[:, None, :]
        inv = 1.0 / np.where(moving, dD[:, None, :], 1.0)
        ta = (x_lo - pD[:, None, :]) * inv
        tb = (x_hi - pD[:, None, :]) * inv
        t0 = np.where(moving, np.maximum(np.minimum(ta, tb), 0.0), 0.0)            # (B, J, n)
        t1 = np.where(moving, np.minimum(np.maximum(ta, tb), 1.0), 1.0)
        still = (x_lo <= pD[:, None, :]) & (pD[:, None, :] <= x_hi)
        ok = np.where(moving, t0 <= t1, still) & valid[:, None, :] & slab_ok[:, :, None]
        c0 = pe[:, None] + t0[..., None] * de[:, None]                             # (B, J, n, 2)
        c1 = pe[:, None] + t1[..., None] * de[:, None]
        okk = ok[..., None]
        cmin = np.where(okk, np.minimum(c0, c1), np.inf).min(axis=2)               # (B, J, 2)
        cmax = np.where(okk, np.maximum(c0, c1), -np.inf).max(axis=2)
        any_ok = ok.any(axis=2)
        cmin[~any_ok] = 0.0
        cmax[~any_ok] = 0.0
        loE, sE = lo[E][:, None, :], s[E][:, None, :]
        a = np.ceil((cmin - m - loE) / sE).astype(np.int64) - 1
        b = np.floor((cmax + m - loE) / sE).astype(np.int64)
        boxes = np.empty((B, Jm, 3, 2), np.int64)
        Dj = np.broadcast_to(D[:, None], (B, Jm))
        bb, jb = np.meshgrid(bi, jj, indexing="ij")
        boxes[bb, jb, Dj, 0] = js
        boxes[bb, jb, Dj, 1] = js
        for c in range(2):
            Ec = np.broadcast_to(E[:, None, c], (B, Jm))
            boxes[bb, jb, Ec, 0] = np.maximum(a[..., c], 0)
            boxes[bb, jb, Ec, 1] = np.where(any_ok, np.minimum(b[..., c], v - 1), -1)
        flat = boxes.reshape(-1, 3, 2)
        ext = flat[:, :, 1] - flat[:, :, 0] + 1
        sizes = np.where(np.all(ext > 0, axis=1), ext.prod(axis=1), 0).reshape(B, Jm).sum(axis=1)
        return np.split(self._expand(flat), np.cumsum(sizes)[:-1])


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


# ---- statistics ---------------------------------------------------------------------------

class TraversalStats:
    """Traversal statistics of a run, fed one block ray at a time.

    Always accumulated (cheap): blocks, rays, receivers (end points) per block **L**, voxels per
    block, and the patch tests the blocks cause (sum over visited voxels of the patch count, times
    the block's rays). For a sampled fraction of blocks (``sample_fraction``, seeded) it also
    walks every member ray with the per-ray DDA, which gives **l** (voxels per ray), **n**
    (patches per voxel a ray visits) and the two overheads, over the sampled blocks:

    - ``overhead`` = sum over blocks of (voxels the block visits x its rays) / sum over rays of
      the ray's DDA voxels (the paper estimates 2.6); both counted over all voxels, empty or not,
      with the block's voxels recomputed by :meth:`VoxelGrid.block_voxels`;
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

        ``sample``: True / False forces / skips the per-ray DDA for this block; None draws it with
        probability ``sample_fraction``.
        """
        starts = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        voxels = np.asarray(voxels, dtype=np.int64)
        rays = len(starts) * len(ends)
        count = self.grid.count
        self.blocks += 1
        self.rays += rays
        self.receivers += len(ends)
        self.block_voxels += len(voxels)
        self.block_tests += int(count[voxels].sum()) * rays
        if sample is None:
            sample = self.sample_fraction > 0 and self._rng.random() < self.sample_fraction
        if not sample:
            return
        full = self.grid.block_voxels(starts, ends)
        self.sampled_blocks += 1
        self.sampled_rays += rays
        self.sampled_block_voxel_rays += len(full) * rays
        self.sampled_block_tests += int(count[full].sum()) * rays
        for p in starts:
            for q in ends:
                vox = self.grid.ray_voxels(p, q)
                self.dda_voxels += len(vox)
                self.dda_tests += int(count[vox].sum())

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
