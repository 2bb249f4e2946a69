"""Unoccluded form factors: exact patch-to-patch, chosen per pair between the closed form and a cubature.

A pair's factor is the closed form's (:mod:`.closed_form`; its special functions in
:mod:`.special`), or, where a derived bound allows it or the closed form cancels, a
cubature of the point factor (:mod:`.cubature`, :mod:`.point_factor`).

The result is ``A_j F_ji``, symmetric in (i, j): reciprocity holds by construction, and to the
bit, since every pair is computed in a canonical order (below). :func:`unoccluded_factors`
divides by the receiver's area.

The pair is put in a canonical order (its triangles' coordinates) before either form is chosen,
so ``(i, j)`` and ``(j, i)`` give the same bits: the render computes each unordered pair once
(:class:`PairCache`).
"""

import numpy as np
from numba import njit, prange

from ...exact_float import _plane_sign
from .closed_form import CANCELLATION, EDGE_TARGET, _contour
from .point_factor import _clip, _needs_clip
from .cubature import _centroid, _far, _grazing, _normal, _radius, _two_rules

__all__ = ["exchange_mask", "pair_factors", "unoccluded_factors", "PairCache", "form_factor_matrix",
           "FAR_TARGET", "METHODS"]

#: relative error bound a far-pair cubature must meet to replace the closed form
FAR_TARGET = 1e-6
#: method codes in the statistics of :func:`pair_factors`
METHODS = ("zero", "closed form", "centroid", "7-point", "25-point", "64-point", "subdivided", "edge quadrature",
           "144-point", "unresolved")


@njit(cache=True)
def _before(A, B):
    """Lexicographic order of two triangles' coordinates (a canonical order of a pair)."""
    for k in range(3):
        for c in range(3):
            if A[k, c] != B[k, c]:
                return A[k, c] < B[k, c]
    return False


@njit(cache=True)
def _pair(Ti, Tj, target, tolerance, stats, P, Q):
    """A_j F_ji (= A_i F_ij) for shooter Ti, receiver Tj, within ``target`` of itself or, where
    larger, ``tolerance`` (absolute; 0: none); stats[method] += 1. P, Q: (4, 3) work arrays. The
    pair is first put in a canonical order, so that (Ti, Tj) and (Tj, Ti) give the same bits:
    reciprocity holds exactly and a pair's value can be reused for the reverse pair."""
    if _before(Tj, Ti):
        Ti, Tj = Tj, Ti
    nix, niy, niz, Ai2 = _normal(Ti)
    njx, njy, njz, Aj2 = _normal(Tj)
    if Ai2 == 0.0 or Aj2 == 0.0:
        stats[0] += 1
        return 0.0
    if (not _needs_clip(Tj, Ti[0, 0], Ti[0, 1], Ti[0, 2], nix, niy, niz)
            and not _needs_clip(Ti, Tj[0, 0], Tj[0, 1], Tj[0, 2], njx, njy, njz)):
        # integrate over the smaller triangle: the bound falls with its radius
        cix, ciy, ciz = _centroid(Ti)
        cjx, cjy, cjz = _centroid(Tj)
        if _radius(Tj, cjx, cjy, cjz) <= _radius(Ti, cix, ciy, ciz):
            value = _far(Ti, Tj, target, tolerance, stats, P)
        else:
            value = _far(Tj, Ti, target, tolerance, stats, P)
        if value >= 0.0:
            return value
    nP = _clip(Tj, Ti[0, 0], Ti[0, 1], Ti[0, 2], nix, niy, niz, P)     # receiver part in front of the shooter
    nQ = _clip(Ti, Tj[0, 0], Tj[0, 1], Tj[0, 2], njx, njy, njz, Q)     # shooter part in front of the receiver
    if nP < 3 or nQ < 3:
        stats[0] += 1
        return 0.0
    # each edge pair held to a tenth of the pair's target (EDGE_TARGET for the reference, target 0)
    value, size, err, quadrature = _contour(P, nP, Q, nQ, 0.1 * target if target > 0.0 else EDGE_TARGET)
    if CANCELLATION * size + err > max(max(target, EDGE_TARGET) * value, tolerance):
        # the closed form may have lost the target to cancellation (grazing far pairs, slivers):
        # a product cubature with the cosine-free bound instead, else two high-order rules
        if target > 0.0:
            g = _grazing(P, nP, njx, njy, njz, Q, nQ, nix, niy, niz, target)
            if g >= 0.0:
                stats[6] += 1
                return g
        if Aj2 <= Ai2:          # over the smaller one's part in front of the other
            g = _two_rules(P, nP, njx, njy, njz, Ti, max(target, EDGE_TARGET))
        else:
            g = _two_rules(Q, nQ, nix, niy, niz, Tj, max(target, EDGE_TARGET))
        if g >= 0.0:
            stats[8] += 1
            return g
        stats[9] += 1           # no method met the target: counted, so a render can report it
        return value
    stats[7 if quadrature else 1] += 1
    return value


@njit(cache=True, parallel=True)
def _pairs(shooters, receivers, target, tolerance, methods):
    """Every pair on the thread pool: pairs are independent, each with its own work arrays and
    its own row of ``methods`` (M, len(METHODS)), so the result does not depend on the threads."""
    out = np.empty(len(shooters))
    for m in prange(len(shooters)):
        P = np.empty((4, 3))
        Q = np.empty((4, 3))
        out[m] = _pair(shooters[m], receivers[m], target, tolerance[m], methods[m], P, Q)
    return out


def pair_factors(shooters, receivers, *, target=FAR_TARGET, tolerance=0.0, stats=None):
    """``A_j F_ji`` for shooter triangles i (M,3,3) and receiver triangles j (M,3,3) -> (M,).

    Each within ``target`` of itself (relative) or, where that is larger, within ``tolerance``
    (absolute, on ``A_j F_ji``; a scalar or (M,); 0: the relative target alone): a cheaper
    cubature is taken wherever its derived bound meets either (docs/formfactors.md, "Far pairs").
    Symmetric in (i, j) bit for bit (the kernel puts each pair in a canonical order). ``stats``, an int64
    array of len(METHODS), counts the pairs per method. Geometry only: which side faces which
    is :func:`exchange_mask`'s business; a pair where one lies wholly behind the other's plane
    gets 0.
    """
    S = np.ascontiguousarray(np.asarray(shooters, dtype=np.float64).reshape(-1, 3, 3))
    R = np.ascontiguousarray(np.asarray(receivers, dtype=np.float64).reshape(-1, 3, 3))
    S, R = np.broadcast_arrays(S, R)
    tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (len(S),)))
    methods = np.zeros((len(S), len(METHODS)), dtype=np.int64)
    out = _pairs(np.ascontiguousarray(S), np.ascontiguousarray(R), float(target), tol, methods)
    if stats is not None:
        stats += methods.sum(axis=0)
    return out


def exchange_mask(scene, i):
    """bool (N,): receivers j that can exchange light with shooter i, so rays only where they count.

    j qualifies when all of these hold, each decided exactly on the float scene
    (:func:`blockray.exact_float.plane_signs`; no tolerance, so tiny patches beside huge ones
    are treated like any others):

    - j != i, j has non-zero area and a reflectance that is not all zero;
    - some vertex of j is strictly in front of i's plane (i emits from its front) and some vertex
      of i strictly in front of j's plane: exactly the pairs whose clipped factor is not 0.
    """
    eligible = (scene.reflectance > 0).any(axis=1) & (scene.areas > 0)
    return _exchange_row(scene.patch_vertices, int(i), eligible)


_UNITS = np.eye(3, dtype=np.int64)


@njit(cache=True)
def _vertex_in_front(P, T):
    """Some vertex of triangle P strictly in front of T's plane (exact signs)."""
    for k in range(3):
        if _plane_sign(T, P, _UNITS[k]) > 0:
            return True
    return False


@njit(cache=True)
def _exchange_row(V, i, eligible):
    mask = np.zeros(len(V), dtype=np.bool_)
    for j in range(len(V)):
        if j != i and eligible[j] and _vertex_in_front(V[j], V[i]) and _vertex_in_front(V[i], V[j]):
            mask[j] = True
    return mask


class PairCache:
    """``A_j F_ji`` of a scene's pairs, each unordered pair computed once: the pair kernel gives
    the same bits for (i, j) and (j, i), so the column of shooter j reuses what the column of
    shooter i computed. Dense N x N float64 (NaN: not yet computed), so only for scenes of up to
    ``max_patches`` patches (73 MB at the room's 3032); larger scenes compute every column."""

    def __init__(self, scene, *, target=FAR_TARGET, tolerance=0.0, max_patches=5000):
        self.target, self.tolerance = target, tolerance
        N = scene.patches
        self.values = np.full((N, N), np.nan) if N <= max_patches else None
        self.computed = 0           # pairs computed (the rest were reused)

    def pairs(self, scene, i, j, stats=None):
        """``A_j F_ji`` for shooter i and receivers j (array of indices)."""
        V = scene.patch_vertices
        if self.values is None:
            self.computed += len(j)
            return pair_factors(V[i][None], V[j], target=self.target, tolerance=self.tolerance, stats=stats)
        row = self.values[i, j]
        todo = np.isnan(row)
        if todo.any():
            row[todo] = pair_factors(V[i][None], V[j[todo]], target=self.target, tolerance=self.tolerance,
                                     stats=stats)
            self.computed += int(todo.sum())
            self.values[i, j] = row
            self.values[j, i] = row
        return row


def unoccluded_factors(scene, i, *, stats=None, cache=None, target=FAR_TARGET):
    """(N,) exact patch-to-patch ``F_ji`` from every receiver j to shooter patch i; 0 outside
    :func:`exchange_mask`. ``cache``, a :class:`PairCache`, reuses the pairs of earlier columns
    (the same bits) and then sets the far-pair target itself."""
    mask = exchange_mask(scene, i)
    out = np.zeros(scene.patches)
    j = np.flatnonzero(mask)
    if len(j):
        if cache is not None:
            out[j] = cache.pairs(scene, i, j, stats=stats) / scene.areas[j]
        else:
            out[j] = pair_factors(scene.patch_vertices[i][None], scene.patch_vertices[j], target=target,
                                  stats=stats) / scene.areas[j]
    return out


def form_factor_matrix(scene, visibility=None):
    """Dense unoccluded ``F[j, i] = F_ji`` (receiver rows, shooter columns), masked.

    ``visibility`` (N, N), optional, multiplies F elementwise (fraction of clear rays). Memory is
    N^2 floats: for small scenes and tests; the render loop builds columns with
    :func:`unoccluded_factors` and the board.
    """
    F = np.zeros((scene.patches, scene.patches))
    for i in range(scene.patches):
        F[:, i] = unoccluded_factors(scene, i)
    if visibility is not None:
        F *= visibility
    return F
