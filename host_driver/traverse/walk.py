"""The compiled traversals of the voxel grid (:class:`~.voxel.VoxelGrid`): the per-ray 3D-DDA
and the block ray's slabs.

Both traversals are numba kernels over whole batches (cache=True: compiled once per machine).
They do the float arithmetic of the vectorised numpy forms they replaced, operation for
operation (no fast-math, no fused multiply-add), so they visit the same voxels in the same
order (checked against them when they were replaced: renders byte-identical, docs/measurements.md).
A large batch runs on the thread pool (prange, threads.parallel), a small one on the calling
thread (the same per-item function); each block or ray writes only its own output, so the
result does not depend on the number of threads. _interval is the scalar form of
VoxelGrid._range (used, vectorised, by the registration).
"""

import math

import numpy as np
from numba import njit, prange

from ... import threads as _threads  # (also chooses the threading layer before any kernel runs)

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
