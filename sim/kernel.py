"""The model board's arithmetic, compiled: the exact predicate of :mod:`blockray.exact` over whole
batches of block rays, with numba (``cache=True``: compiled once per machine, kept on disk).

What it computes is exactly :func:`blockray.exact.blocked_block` OR-ed over a block's records,
and so exactly what the R x S array computes; tests check it against
:func:`blockray.exact.blocked_reference` (Python integers) on the hard cases and random queries.
It differs only in *how much* arithmetic it does, never in the answer:

- the shared terms of the array: ``pP`` once per (column, record), ``pQ`` and
  ``w_k = (Q - V_k) x (V_{k+1} - V_k)`` once per (row, record), computed only when some ray of
  the row is still open and crosses the record's plane;
- early exits: a record no shooter point lies off the plane of is skipped, a row whose rays are
  all blocked or none crosses the plane is skipped, and a block stops once all its rays are
  blocked (a ray is blocked by its first blocking record);
- a row's S processors (the edge sides s_k and the decision) run without branches over the
  columns (transposed, P.T), so that the compiler can vectorise them: measured 1.45x faster than
  stopping each ray's edge test at its first pair of sides of opposite sign.

int64 products wrap modulo 2**64 (numba, like numpy, does not trap), a ring, and every value that
decides the answer fits 3B + 2 <= 62 bits, so the sums are exact (see :mod:`blockray.exact`).

The board's cycles do not depend on any test result, so they are not computed here: the batch
kernel returns, per block and board, the records streamed and the VOXEL commands' cycles
(``max(1, count)`` per voxel), from which :meth:`blockray.timing.BoardTiming.block_cycles` gives
the block's cycles. Blocks run in parallel (``prange``); each writes only its own bits, so the
results do not depend on the number of threads.
"""

import numpy as np
from numba import njit, prange

from .. import threads as _threads  # (also chooses the threading layer)

__all__ = ["any_blocked", "run_blocks", "filtered_steps"]


@njit(cache=True, inline="always")
def _sign(x):
    return (x > 0) - (x < 0)


@njit(cache=True)
def _test_records(P, PT, Q, V, n, t0, t1, hit, row_left, left, sp):
    """Test records t0 .. t1-1 against every ray (r, s) of one block not yet blocked.

    ``hit`` (R, S) uint8 is OR-ed in place; ``row_left`` (R,) counts each row's rays not yet
    blocked; ``left`` is their total, returned updated (0: the block is decided). ``PT`` (3, S)
    is P transposed; ``sp`` (S,) is scratch for the shooters' plane signs.
    """
    R, S = Q.shape[0], P.shape[0]
    for t in range(t0, t1):
        if left == 0:
            break
        ax, ay, az = V[t, 0, 0], V[t, 0, 1], V[t, 0, 2]
        bx, by, bz = V[t, 1, 0], V[t, 1, 1], V[t, 1, 2]
        cx, cy, cz = V[t, 2, 0], V[t, 2, 1], V[t, 2, 2]
        nx, ny, nz = n[t, 0], n[t, 1], n[t, 2]
        # shooter units: the plane side of every column's start point
        crossing = False
        for s in range(S):
            sp[s] = _sign((P[s, 0] - ax) * nx + (P[s, 1] - ay) * ny + (P[s, 2] - az) * nz)
            crossing |= sp[s] != 0
        if not crossing:
            continue
        # edges e_k = V_{k+1} - V_k
        e0x, e0y, e0z = bx - ax, by - ay, bz - az
        e1x, e1y, e1z = cx - bx, cy - by, cz - bz
        e2x, e2y, e2z = ax - cx, ay - cy, az - cz
        for r in range(R):
            if row_left[r] == 0:
                continue
            qx, qy, qz = Q[r, 0], Q[r, 1], Q[r, 2]
            sq = _sign((qx - ax) * nx + (qy - ay) * ny + (qz - az) * nz)
            if sq == 0:
                continue
            need = False
            for s in range(S):
                need |= hit[r, s] == 0 and sp[s] * sq < 0
            if not need:
                continue
            # receiver unit: w_k = (Q - V_k) x e_k
            dx, dy, dz = qx - ax, qy - ay, qz - az
            w0x, w0y, w0z = dy * e0z - dz * e0y, dz * e0x - dx * e0z, dx * e0y - dy * e0x
            dx, dy, dz = qx - bx, qy - by, qz - bz
            w1x, w1y, w1z = dy * e1z - dz * e1y, dz * e1x - dx * e1z, dx * e1y - dy * e1x
            dx, dy, dz = qx - cx, qy - cy, qz - cz
            w2x, w2y, w2z = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
            # the row's processors, without branches (so the compiler can vectorise over the columns)
            newly = 0
            for s in range(S):
                px, py, pz = PT[0, s], PT[1, s], PT[2, s]
                s0 = (px - ax) * w0x + (py - ay) * w0y + (pz - az) * w0z
                s1 = (px - bx) * w1x + (py - by) * w1y + (pz - bz) * w1z
                s2 = (px - cx) * w2x + (py - cy) * w2y + (pz - cz) * w2z
                inside = ((s0 >= 0) & (s1 >= 0) & (s2 >= 0)) | ((s0 <= 0) & (s1 <= 0) & (s2 <= 0))
                b = inside & (sp[s] * sq < 0) & (hit[r, s] == 0)
                hit[r, s] |= b
                newly += b
            row_left[r] -= newly
            left -= newly
    return left


@njit(cache=True)
def any_blocked(P, Q, V, n):
    """(R, S) bool: is the ray from shooter P[s] to receiver Q[r] blocked by any record (V[t], n[t])?

    P (S, 3), Q (R, 3), V (N, 3, 3), n (N, 3) int64; n[t] = (V1 - V0) x (V2 - V0).
    """
    R, S = Q.shape[0], P.shape[0]
    hit = np.zeros((R, S), np.uint8)
    row_left = np.full(R, S, np.int64)
    _test_records(P, np.ascontiguousarray(P.T), Q, V, n, 0, V.shape[0], hit, row_left, R * S, np.empty(S, np.int64))
    return hit.astype(np.bool_)


@njit(cache=True)
def _block_points(shooters, receivers, shooter_patch, shooter_sample, receiver_patch, c0, c1, r0, r1):
    """A block's S shooter sample points P and R receiver end points Q (integer coordinates)."""
    P = np.empty((c1 - c0, 3), np.int64)
    for s in range(c1 - c0):
        P[s] = shooters[shooter_patch[c0 + s], shooter_sample[c0 + s]]
    Q = np.empty((r1 - r0, 3), np.int64)
    for r in range(r1 - r0):
        Q[r] = receivers[receiver_patch[r0 + r]]
    return P, Q


@njit(cache=True)
def _run_block(b, shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
               vox_off, voxels, start, count, V, n, ray_off, bits, records, streamed):
    """Block b of :func:`run_blocks`: its bits, and per board its records and VOXEL cycles."""
    c0, c1 = col_off[b], col_off[b + 1]
    r0, r1 = row_off[b], row_off[b + 1]
    S, R = c1 - c0, r1 - r0
    P, Q = _block_points(shooters, receivers, shooter_patch, shooter_sample, receiver_patch, c0, c1, r0, r1)
    hit = np.zeros((R, S), np.uint8)
    row_left = np.full(R, S, np.int64)
    left = R * S
    sp = np.empty(S, np.int64)
    PT = np.ascontiguousarray(P.T)
    for p in range(start.shape[0]):
        for k in range(vox_off[b], vox_off[b + 1]):
            x = voxels[k]
            c = count[p, x]
            records[b, p] += c
            streamed[b, p] += max(c, 1)
            if left:
                left = _test_records(P, PT, Q, V, n, start[p, x], start[p, x] + c, hit, row_left, left, sp)
    o = ray_off[b]
    for r in range(R):
        for s in range(S):
            bits[o + r * S + s] = hit[r, s]


def _run(shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
         vox_off, voxels, start, count, V, n, ray_off, bits, records, streamed):
    for b in prange(len(col_off) - 1):
        _run_block(b, shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
                   vox_off, voxels, start, count, V, n, ray_off, bits, records, streamed)


_run_par, _run_ser = _threads.twins(_run)


def run_blocks(shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
               vox_off, voxels, start, count, V, n, ray_off):
    """Blocked bits of a batch of block rays on P boards (their OR), and what the boards stream.

    shooters (N, K, 3), receivers (N, 3): the quantised sample points and centroids. Block b has
    columns ``col_off[b]:col_off[b+1]`` of (shooter_patch, shooter_sample), rows
    ``row_off[b]:row_off[b+1]`` of receiver_patch and voxels ``vox_off[b]:vox_off[b+1]``.
    Board p holds voxel x's records at ``start[p, x] .. start[p, x] + count[p, x] - 1`` of V, n.

    Returns ``bits`` (rays,) uint8, block b's ray (r, s) at ``ray_off[b] + r * S_b + s``;
    ``records`` (B, P) records streamed and ``streamed`` (B, P) cycles of the VOXEL commands.
    Runs on the thread pool when the batch is large enough (:func:`blockray.threads.parallel`).
    """
    B, nb = len(col_off) - 1, start.shape[0]
    bits = np.zeros(ray_off[B], np.uint8)
    records = np.zeros((B, nb), np.int64)
    streamed = np.zeros((B, nb), np.int64)
    run = _run_par if _threads.parallel(int(ray_off[B])) else _run_ser
    run(shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
        vox_off, voxels, start, count, V, n, ray_off, bits, records, streamed)
    return bits, records, streamed


# -- the filtered cell's undecided tests (issue 16) ----------------------------------------------

@njit(cache=True, inline="always")
def _exponent3(x0, x1, x2, bits):
    """The shared exponent of :func:`blockray.filtered.truncate` of one vector."""
    mag = max(~x0 if x0 < 0 else x0, ~x1 if x1 < 0 else x1, ~x2 if x2 < 0 else x2)
    e = 0
    while (mag >> (e + bits - 1)) != 0:
        e += 1
    return e


@njit(cache=True, inline="always")
def _truncate3(x0, x1, x2, bits, out, row):
    """:func:`blockray.filtered.truncate` of one vector: mantissas into ``out[row, 0:3]``;
    returns [e > 0]."""
    e = _exponent3(x0, x1, x2, bits)
    out[row, 0], out[row, 1], out[row, 2] = x0 >> e, x1 >> e, x2 >> e
    return e > 0


@njit(cache=True, inline="always")
def _rounded_w(dx, dy, dz, ex, ey, ez, w_bits, inputs, out, row):
    """:func:`blockray.filtered.rounded_receiver_filter_terms` of one w_k = dQ_k x e_k (the lean
    cell): w^ into ``out[row, 0:3]``; returns [b > 0]."""
    al, be = _exponent3(dx, dy, dz, inputs), _exponent3(ex, ey, ez, inputs)
    dx, dy, dz, ex, ey, ez = dx >> al, dy >> al, dz >> al, ex >> be, ey >> be, ez >> be
    w0, w1, w2 = dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex
    k = _exponent3(w0, w1, w2, w_bits)
    if al + be > 0:
        k = max(k, inputs + 2)
    out[row, 0], out[row, 1], out[row, 2] = w0 >> k, w1 >> k, w2 >> k
    return al + be + k > 0


@njit(cache=True)
def _record_undecided(P, Q, V, n, t, d_bits, w_bits, w_input, md, td, mw, tw):
    """Tests of the block (every receiver Q[r] and shooter P[s]) against record t that the
    filter (:func:`blockray.filtered.filter_decision`; with ``w_input`` > 0 the lean cell's,
    w_k from ``w_input``-bit inputs) leaves undecided. Scratch: md (S*3, 3), td (S*3,),
    mw (R*3, 3), tw (R*3,)."""
    R, S = Q.shape[0], P.shape[0]
    sp = np.empty(S, np.int64)
    for s in range(S):
        sp[s] = _sign((P[s, 0] - V[t, 0, 0]) * n[t, 0] + (P[s, 1] - V[t, 0, 1]) * n[t, 1]
                      + (P[s, 2] - V[t, 0, 2]) * n[t, 2])
        for k in range(3):
            td[3 * s + k] = _truncate3(P[s, 0] - V[t, k, 0], P[s, 1] - V[t, k, 1], P[s, 2] - V[t, k, 2],
                                       d_bits, md, 3 * s + k)
    undecided = 0
    for r in range(R):
        sq = _sign((Q[r, 0] - V[t, 0, 0]) * n[t, 0] + (Q[r, 1] - V[t, 0, 1]) * n[t, 1]
                   + (Q[r, 2] - V[t, 0, 2]) * n[t, 2])
        if sq == 0:
            continue
        for k in range(3):
            j = (k + 1) % 3
            dx, dy, dz = Q[r, 0] - V[t, k, 0], Q[r, 1] - V[t, k, 1], Q[r, 2] - V[t, k, 2]
            ex, ey, ez = V[t, j, 0] - V[t, k, 0], V[t, j, 1] - V[t, k, 1], V[t, j, 2] - V[t, k, 2]
            if w_input:
                tw[3 * r + k] = _rounded_w(dx, dy, dz, ex, ey, ez, w_bits, w_input, mw, 3 * r + k)
            else:
                tw[3 * r + k] = _truncate3(dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex, w_bits, mw,
                                           3 * r + k)
        for s in range(S):
            if sp[s] * sq >= 0:
                continue                                  # not crossing: decided
            all_ge = all_le = True
            any_gt = any_lt = False
            for k in range(3):
                a, b = td[3 * s + k], tw[3 * r + k]
                dot = pd = nd = pw = nw = 0
                for c in range(3):
                    x, y = md[3 * s + k, c], mw[3 * r + k, c]
                    dot += x * y
                    pd += max(x, 0)
                    nd += max(-x, 0)
                    if w_input:                     # the lean sums: tau in (-1, 2)
                        pw += max(y + 2, 0)
                        nw += max(1 - y, 0)
                    else:
                        pw += y + b if y >= 0 else 0
                        nw += max(-y, 0)
                if w_input:
                    pd, nd = 2 * pd + nd, pd + 2 * nd
                lo = (nd if b else 0) + (nw if a else 0)
                hi = (pd if b else 0) + (pw if a else 0)
                all_ge &= dot >= lo
                any_gt |= dot > lo
                all_le &= dot <= -hi
                any_lt |= dot < -hi
            if not (all_ge or all_le or (any_gt and any_lt)):
                undecided += 1
    return undecided


@njit(cache=True)
def _block_steps(b, shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
                 vox_off, voxels, start, count, V, n, loads, d_bits, w_bits, w_input, step_off, kinds, undecided):
    c0, c1, r0, r1 = col_off[b], col_off[b + 1], row_off[b], row_off[b + 1]
    S, R = c1 - c0, r1 - r0
    P, Q = _block_points(shooters, receivers, shooter_patch, shooter_sample, receiver_patch, c0, c1, r0, r1)
    md, td = np.empty((3 * S, 3), np.int64), np.empty(3 * S, np.bool_)
    mw, tw = np.empty((3 * R, 3), np.int64), np.empty(3 * R, np.bool_)
    for p in range(start.shape[0]):
        i = step_off[b, p] + 1 + loads[b]                 # BEGIN_BLOCK and the loads: plain steps
        for k in range(vox_off[b], vox_off[b + 1]):
            x = voxels[k]
            if count[p, x] == 0:
                kinds[p, i] = 1                               # an empty voxel's bubble
                i += 1
            for t in range(start[p, x], start[p, x] + count[p, x]):
                kinds[p, i] = 2
                undecided[p, i] = _record_undecided(P, Q, V, n, t, d_bits, w_bits, w_input, md, td, mw, tw)
                i += 1
        kinds[p, i] = 3                                       # END_BLOCK's marker


@njit(cache=True, parallel=True)
def _steps_par(shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
               vox_off, voxels, start, count, V, n, loads, d_bits, w_bits, w_input, step_off, kinds, undecided):
    for b in prange(len(col_off) - 1):
        _block_steps(b, shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
                     vox_off, voxels, start, count, V, n, loads, d_bits, w_bits, w_input, step_off, kinds,
                     undecided)


def filtered_steps(shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
                   vox_off, voxels, start, count, V, n, loads, d_bits, w_bits, step_off, w_input=0):
    """The filtered board's steps of a batch on each board (the arguments of :func:`run_blocks`;
    ``loads`` (B,) the LOAD_POINTS commands of each block, ``step_off`` (B + 1, P) where each
    block's steps start): ``kinds`` (P, N) the steps (0 plain, 1 an empty voxel's bubble, 2 a
    record, 3 END_BLOCK's marker: :data:`blockray.sim.filtered_model.STEP_PLAIN` ...) and
    ``undecided`` (P, N) each record's tests the filter leaves undecided (every test of the
    block's rows and columns is evaluated: no early exit, the hardware tests them all; ``w_input``:
    the lean cell's input width, 0 for w_k rounded from its exact value)."""
    kinds = np.zeros((start.shape[0], int(step_off[-1].max())), np.int64)
    undecided = np.zeros_like(kinds)
    _steps_par(shooters, receivers, col_off, shooter_patch, shooter_sample, row_off, receiver_patch,
               vox_off, voxels, start, count, V, n, loads, d_bits, w_bits, w_input, step_off, kinds, undecided)
    return kinds, undecided
