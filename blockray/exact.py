"""The exact segment-triangle occlusion predicate, in the form the hardware computes it.

The question is only *is the segment P -> Q blocked by triangle V0 V1 V2?* With integer inputs
and wide enough integers nothing rounds, so hardware, model and any exact evaluation agree.

    pP  = n . (P - V0),  pQ = n . (Q - V0),       n = (V1 - V0) x (V2 - V0)   (plane sides)
    s_k = (P - V_k) . w_k,  w_k = (Q - V_k) x (V_{k+1} - V_k),  k = 0, 1, 2  (edge sides)

    blocked  <=>  sign(pP) * sign(pQ) < 0  and  (s_0, s_1, s_2 all >= 0 or all <= 0)

Strict plane test: a segment that starts or ends on the triangle's plane (own patch, coplanar
neighbours, zero-area triangles with n = 0) is never blocked. Closed edge test: a segment through
a shared edge or vertex is blocked by at least one of the triangles sharing it (watertight).

The shared-term split is the one the R x S array uses: ``w_k`` depends on the receiver Q and the
broadcast patch only (one receiver unit per row), ``P - V_k`` and ``pP`` on the shooter P and the
patch (one shooter unit per column), ``pQ`` on Q and the patch (receiver unit), and each processor
does the three 3-term dot products ``s_k`` plus the sign logic. Widths: :class:`blockray.params.Widths`.

:func:`blocked_block` is the vectorised int64 form (exact for B <= 20: every value that matters
fits 3B + 2 <= 62 bits and int64 products wrap modulo 2**64, a ring, so the sums are exact).
:func:`orient3d` and :func:`blocked_reference` are an independent Python-integer evaluation from
the 4x4 orient3d determinant, for testing.
"""

import numpy as np

__all__ = ["orient3d", "blocked_reference", "patch_normals", "blocked_block", "blocked_tests", "block_terms", "vertex_terms",
           "edge_terms", "plane_sides", "plane_crossing"]


def orient3d(a, b, c, d):
    """det[a - d; b - d; c - d] with Python integers (exact for any size)."""
    ax, ay, az = (int(a[i]) - int(d[i]) for i in range(3))
    bx, by, bz = (int(b[i]) - int(d[i]) for i in range(3))
    cx, cy, cz = (int(c[i]) - int(d[i]) for i in range(3))
    return ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)


def _sign(x):
    return (x > 0) - (x < 0)


def blocked_reference(p, q, v0, v1, v2):
    """Independent exact evaluation of the predicate from orient3d (Python integers)."""
    pp = orient3d(v0, v1, v2, p)
    pq = orient3d(v0, v1, v2, q)
    if _sign(pp) * _sign(pq) >= 0:
        return False
    s = [orient3d(p, q, a, b) for a, b in ((v0, v1), (v1, v2), (v2, v0))]
    return all(x >= 0 for x in s) or all(x <= 0 for x in s)


def patch_normals(vertices):
    """n = (V1 - V0) x (V2 - V0) for integer vertices (N, 3, 3) -> (N, 3) int64."""
    v = np.asarray(vertices, dtype=np.int64)
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


def vertex_terms(P, Q, V):
    """The units' vectors for broadcast-aligned P (..., 3), Q (..., 3), V (..., 3, 3):
    ``dP`` = P - V_k, ``dQ`` = Q - V_k and ``w`` = (Q - V_k) x (V_{k+1} - V_k), each (..., 3, 3)."""
    E = np.roll(V, -1, axis=-2) - V                                   # e_k = V_{k+1} - V_k
    dP = P[..., None, :] - V                                          # shooter unit
    dQ = Q[..., None, :] - V
    return dP, dQ, np.cross(dQ, E)                                    # receiver unit: w_k


def edge_terms(shooters, receivers, vertices):
    """:func:`vertex_terms` of a block: ``dP`` (S, N, 3, 3), ``dQ`` and ``w`` (R, N, 3, 3), int64."""
    P = np.asarray(shooters, dtype=np.int64)
    Q = np.asarray(receivers, dtype=np.int64)
    V = np.asarray(vertices, dtype=np.int64)
    return vertex_terms(P[:, None], Q[:, None], V)                    # P and Q never meet here


def block_terms(shooters, receivers, vertices, normals):
    """The shared terms of one block against N patches.

    shooters (S, 3), receivers (R, 3), vertices (N, 3, 3), normals (N, 3), all int64.
    Returns ``pP (S, N)``, ``pQ (R, N)``, ``sides (R, S, N, 3)`` (the s_k), as int64.
    """
    dP, dQ, w = edge_terms(shooters, receivers, vertices)
    pP, pQ = plane_sides(dP, dQ, normals)
    sides = np.einsum("snkc,rnkc->rsnk", dP, w)                       # processors           (R, S, N, 3)
    return pP, pQ, sides


def plane_sides(dP, dQ, normals):
    """pP = n . (P - V0) and pQ = n . (Q - V0) from the dP, dQ of :func:`vertex_terms` or
    :func:`edge_terms` (then (S, N) and (R, N)), normals broadcast against them."""
    n = np.asarray(normals, dtype=np.int64)
    return np.einsum("...c,...c->...", dP[..., 0, :], n), np.einsum("...c,...c->...", dQ[..., 0, :], n)


def plane_crossing(pP, pQ):
    """sign(pP) sign(pQ) < 0 for every (receiver, shooter, patch): pP (S, N), pQ (R, N) -> (R, S, N)."""
    return (np.sign(pQ)[:, None, :] * np.sign(pP)[None, :, :]) < 0


def blocked_block(shooters, receivers, vertices, normals):
    """Blocked bits of every (receiver r, shooter s, patch t): bool array (R, S, N)."""
    pP, pQ, sides = block_terms(shooters, receivers, vertices, normals)
    crossing = plane_crossing(pP, pQ)
    s0, s1, s2 = sides[..., 0], sides[..., 1], sides[..., 2]
    # written out: a reduction over an axis of length 3 costs more than the comparisons
    inside = ((s0 >= 0) & (s1 >= 0) & (s2 >= 0)) | ((s0 <= 0) & (s1 <= 0) & (s2 <= 0))
    return crossing & inside


def blocked_tests(P, Q, V, normals, *, chunk=1 << 16):
    """Blocked bits of T single tests: P (T, 3), Q (T, 3), V (T, 3, 3), normals (T, 3) -> (T,)
    bool; the same terms as :func:`blocked_block`, test by test (in chunks: nine int64 per
    vector term)."""
    out = np.empty(len(P), dtype=bool)
    for a in range(0, len(P), chunk):
        p, q, v, n = (np.asarray(x[a:a + chunk], dtype=np.int64) for x in (P, Q, V, normals))
        dP, dQ, w = vertex_terms(p, q, v)
        pP, pQ = plane_sides(dP, dQ, n)
        s0, s1, s2 = np.einsum("tkc,tkc->tk", dP, w).T
        inside = ((s0 >= 0) & (s1 >= 0) & (s2 >= 0)) | ((s0 <= 0) & (s1 <= 0) & (s2 <= 0))
        out[a:a + chunk] = (np.sign(pP) * np.sign(pQ) < 0) & inside
    return out
