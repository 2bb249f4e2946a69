"""Sample points on patches, chosen so they are exact integers on the quantised grid and stay off
the grid a scene was designed on.

A triangle is cut into n x n congruent cells (n = ceil(sqrt(K))). Each cell holds one sample point
with barycentric weights (w0, w1, w2) / D, integer w summing to D = 3p: the point of that
1/D lattice strictly inside the cell nearest the cell's centroid among those with **no weight a
multiple of p** (of equally near ones, the one keeping the pattern's mean on the centroids'
mean). p is the smallest prime of at least 7 above n for which every cell has such a point (7 for
K <= 36, 11 above).

Why p. Sample points on a scene's own design lattice sit exactly on its contact lines (a shelf
meeting a panel at the height of a sample row): whether such a ray is blocked is then decided by
the float scene's rounding on the golden board and by each vertex's own rounding on the fixed-point
model, and the two disagree (docs/formfactors.md, "Tie rays"). Scenes are drawn on decimal grids
(whole m, cm or mm) and their patch edges are whole fractions of such lengths, so cell centroids
in thirds or ninths (D = 3n) land on those grids. Along an axis-parallel edge of length L units a
sample point lies w L / D units from the vertex; with p dividing neither w nor L that is never a
whole unit, so no sample point of such a patch lies on a grid plane of the scene. D = 3p keeps the receiver end point, the centroid (weights p, p, p),
exact.

When the vertex grid is scaled by D (vertex coordinates are multiples of D), every sample point
sum_k w_k V_k / D is an integer point lying exactly on the triangle's plane, so the strict plane
test needs no epsilon. Scaling by D costs log2(D) coordinate bits (4.4 for D = 21).

When K < n * n, K cells are taken at evenly spread indices of the row-by-row cell order.

**Drawn sample points** (``SampleScheme(seed=N)``, ``--sample-points draw``). A fixed pattern keeps
every sample at least a cell's half-width from the edges. A shadow cast by an object resting on the
shooter (an up-light on a wall) starts at the contact line, so it covers a strip along the
shooter's edge that no fixed point lies in, and the shooter's visible factors come out too large
(docs/formfactors.md). Drawn points are stratified: sample k lies in the stratum [k, k + 1) / K of
the triangle's area (16 congruent cells in row order), at a lattice point of its cell drawn
uniformly from a hash of (seed, patch, k), so each patch has its own points and any strip is hit
in proportion to its area. They use the same allowed 1/D lattice as the end points (the finer
``end_lattice`` reaches nearer the edges).
"""

from dataclasses import dataclass
from functools import cached_property, lru_cache
from fractions import Fraction
import math

import numpy as np

from .errors import ParameterError

__all__ = ["SampleScheme", "END_LATTICES", "uniforms", "lattice_cells"]

#: allowed end-point lattice refinements (powers of two: each doubling costs one coordinate bit)
END_LATTICES = (1, 2, 4, 8, 16)
_DRAW_CELLS = 4         # drawn samples: strata over the 4 x 4 = 16 congruent cells
_DRAW_STREAM = 1 << 40  # hash streams of drawn samples, apart from the end points' (2 d, 2 d + 1)


def _mix(x):
    """splitmix64 finaliser on uint64 arrays: a well-spread hash of each value."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def uniforms(seed, i, keys, stream):
    """Floats in [0, 1) from (seed, i, key, stream), broadcast over ``i`` and ``keys``: the same for
    a (patch, key) whatever batch, order or process asks (keys: receivers, or sample numbers)."""
    with np.errstate(over="ignore"):
        key = _mix(np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.asarray(i, dtype=np.uint64))
        key = _mix(key ^ (np.asarray(keys, dtype=np.uint64) * np.uint64(0xD1B54A32D192ED03) + np.uint64(stream)))
    return (key >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def lattice_cells(D, p, corners):
    """The allowed weights (L, 3) of the 1/D lattice (strictly inside, no weight a multiple of p),
    and per cell of ``corners`` (C, 3, 3 barycentric) the indices of those it holds (padded rows,
    each point in the cell it lies deepest inside) and their count."""
    w, owner, count = _owners(D, p, corners)
    assert count.min() > 0, "every cell holds a lattice point"
    members = np.zeros((len(corners), count.max()), dtype=np.int64)
    for c in range(len(corners)):
        members[c, :count[c]] = np.flatnonzero(owner == c)
    return w, members, count


def _owners(D, p, corners):
    """The allowed weights (L, 3), the cell each lies deepest inside, and the count per cell."""
    a, b = np.meshgrid(np.arange(1, D), np.arange(1, D), indexing="ij")
    w = np.stack([a.ravel(), b.ravel(), D - a.ravel() - b.ravel()], axis=1)
    w = w[(w[:, 2] >= 1) & (w % p != 0).all(axis=1)]
    inv = np.linalg.inv(np.asarray(corners, dtype=np.float64).transpose(0, 2, 1))   # corners as columns
    owner = np.argmax(np.einsum("cij,lj->lci", inv, w / D).min(axis=2), axis=1)
    return w, owner, np.bincount(owner, minlength=len(corners))


def _cell_corners(n):
    """The n x n cells (row order) as barycentric corners (n^2, 3, 3)."""
    return np.array([[(n - i, i - j, j) for i, j in cell] for cell in _cells(n)], dtype=np.float64) / n


@lru_cache(maxsize=None)
def _draw_lattice(D, p, n=_DRAW_CELLS):
    """:func:`lattice_cells` of the drawn samples' n x n cells (row order, samples.py's own)."""
    return lattice_cells(D, p, _cell_corners(n))


@lru_cache(maxsize=None)
def _strata_cells(D, p, strata):
    """Cells per side for ``strata`` drawn strata: 4 (16 cells) up to 16 strata, else the finest
    n with n^2 <= strata whose every cell holds an allowed point of the 1/D lattice."""
    n = max(_DRAW_CELLS, math.isqrt(strata))
    while n > _DRAW_CELLS and _owners(D, p, _cell_corners(n))[2].min() == 0:    # a cell too small
        n -= 1
    return n


def _primes_from(start):
    p = start
    while True:
        if all(p % d for d in range(2, math.isqrt(p) + 1)):
            yield p
        p += 1


def _cells(n):
    """The n x n cells, row by row, as corner triples (i, j) in cell units: the point
    V0 + i (V1 - V0) / n + j (V2 - V1) / n, weights (n - i, i - j, j) / n."""
    for row in range(n):
        for col in range(2 * row + 1):            # alternating upward / downward cells
            a, down = divmod(col, 2)
            if down:
                yield (row, a), (row, a + 1), (row + 1, a + 1)
            else:
                yield (row, a), (row + 1, a), (row + 1, a + 1)


def _inside(point, corners):
    """Strictly inside the triangle ``corners`` (exact, Fractions)."""
    def side(a, b, p):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    s = [side(corners[k], corners[(k + 1) % 3], point) for k in range(3)]
    return all(x > 0 for x in s) or all(x < 0 for x in s)


def _cell_choices(corners, n, p):
    """The cell's centroid as weights (Fractions), and the 1/D lattice points strictly inside the
    cell nearest it with no weight in pZ, as weight triples (empty when there is none)."""
    D = 3 * p
    cs = [(Fraction(i * D, n), Fraction(j * D, n)) for i, j in corners]
    ci, cj = sum(c[0] for c in cs) / 3, sum(c[1] for c in cs) / 3
    centre = (D - ci, ci - cj, cj)
    found = {}
    for i in range(math.floor(min(c[0] for c in cs)), math.ceil(max(c[0] for c in cs)) + 1):
        for j in range(math.floor(min(c[1] for c in cs)), math.ceil(max(c[1] for c in cs)) + 1):
            w = (D - i, i - j, j)
            if any(x % p == 0 for x in w) or not _inside((i, j), cs):
                continue
            # distance in barycentric weights (an affine image of the triangle's own metric)
            found.setdefault(sum((a - b) ** 2 for a, b in zip(w, centre)), []).append(w)
    return centre, (found[min(found)] if found else [])


def _balanced(cells):
    """One point per cell, (K, 3): of each cell's nearest points the one keeping the running sum
    of (point - centroid) smallest, so the pattern's mean stays where the centroids' is."""
    run, out = (0, 0, 0), []
    for centre, choices in cells:
        def drift(w):
            return sum((r + a - c) ** 2 for r, a, c in zip(run, w, centre)), w
        w = min(choices, key=drift)
        run = tuple(r + a - c for r, a, c in zip(run, w, centre))
        out.append(w)
    return np.array(out, dtype=np.int64)


@dataclass(frozen=True)
class SampleScheme:
    count: int = 8
    #: the end-point lattice's refinement: weights count in 1/(3p end_lattice) steps, so rows can end
    #: that much nearer a receiver's edges (host_driver/endpoints.py); costs log2 of it in coordinate bits
    end_lattice: int = 1
    #: None: the fixed pattern on every patch; an integer: each patch's points drawn from it
    seed: int = None
    #: drawn points only: each patch has ``sets`` sets of K points, stratified together over K sets
    #: strata; row d of a pair's ``--end-draws`` rows casts from set d (``--sample-points rows``)
    sets: int = 1

    def __post_init__(self):
        if isinstance(self.count, bool) or not isinstance(self.count, int) or not 1 <= self.count <= 64:
            raise ParameterError(f"shooter samples must be an integer from 1 to 64, not {self.count!r}")
        e = self.end_lattice
        if isinstance(e, bool) or not isinstance(e, int) or e not in END_LATTICES:
            raise ParameterError(f"end_lattice must be one of {', '.join(map(str, END_LATTICES))}, not {e!r}",
                                 parameter="end_lattice")
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)
                                      or not 0 <= self.seed < 2 ** 63):
            raise ParameterError(f"sample_seed must be an integer from 0 to 2**63 - 1, not {self.seed!r}",
                                 parameter="sample_seed")
        if isinstance(self.sets, bool) or not isinstance(self.sets, int) or not 1 <= self.sets <= 64:
            raise ParameterError(f"sample sets must be an integer from 1 to 64, not {self.sets!r}",
                                 parameter="end_draws")
        if self.sets > 1 and self.seed is None:
            raise ParameterError("sample sets per row need drawn points (a seed)", parameter="sample_points")

    @property
    def per_patch(self):
        """Points per patch: K in each of ``sets`` sets, set d at indices [d K, (d + 1) K)."""
        return self.count * self.sets

    @property
    def drawn(self):
        """Each patch has its own drawn points (:meth:`weights_of`)."""
        return self.seed is not None

    @property
    def n(self):
        return math.isqrt(self.count - 1) + 1

    @cached_property
    def _lattice(self):
        """(p, [(centroid, nearest points)] per cell): the first prime p >= 7 above n for which
        every cell has a point."""
        n = self.n
        for p in _primes_from(max(7, n + 1)):
            cells = [_cell_choices(c, n, p) for c in _cells(n)]
            if all(choices for _, choices in cells):
                return p, cells

    @property
    def prime(self):
        """p: no sample weight is a multiple of it."""
        return self._lattice[0]

    @property
    def denominator(self):
        """D = 3p end_lattice: weights of every sample (and of the centroid) sum to D."""
        return 3 * self.prime * self.end_lattice

    @cached_property
    def weights(self):
        """(K, 3) int64 barycentric weights of the fixed pattern's sample points (drawn points
        differ per patch: :meth:`weights_of`)."""
        if self.drawn:
            raise ParameterError("drawn sample points differ per patch: use weights_of(patches)",
                                 parameter="sample_points")
        cells = self._lattice[1]
        if self.count < len(cells):
            cells = [cells[i] for i in np.round(np.arange(self.count) * len(cells) / self.count).astype(int)]
        return _balanced(cells) * self.end_lattice

    def weights_of(self, patches):
        """(len(patches), K sets, 3) int64 weights of the sample points of each patch (a read-only
        broadcast of :attr:`weights` for the fixed pattern). Drawn: point d K + k (set d) from
        stratum k sets + d of K sets equal-area strata, so each set spreads over the triangle."""
        patches = np.asarray(patches, dtype=np.int64).reshape(-1)
        if not self.drawn:
            return np.broadcast_to(self.weights, (len(patches), self.count, 3))
        S = self.per_patch
        w, members, count = _draw_lattice(self.denominator, self.prime,
                                          _strata_cells(self.denominator, self.prime, S))
        t = np.arange(S)
        k = (t % self.count) * self.sets + t // self.count                   # the stratum of point t
        u = (k + uniforms(self.seed, patches[:, None], k, _DRAW_STREAM)) / S
        v = uniforms(self.seed, patches[:, None], k, _DRAW_STREAM + 1)
        cell = np.minimum((u * len(count)).astype(np.int64), len(count) - 1)
        return w[members[cell, np.minimum((v * count[cell]).astype(np.int64), count[cell] - 1)]]

    @property
    def centroid_weights(self):
        return np.array([self.prime * self.end_lattice] * 3, dtype=np.int64)

    def points(self, vertices, patches=None):
        """Float sample points of triangles (N, 3, 3) -> (N, K sets, 3); ``patches``: their patch
        numbers (default 0 .. N - 1), which drawn points depend on."""
        v = np.asarray(vertices, dtype=np.float64)
        if not self.drawn:
            return np.einsum("kj,njc->nkc", self.weights / self.denominator, v)
        return np.einsum("nkj,njc->nkc", self._weights_for(v, patches) / self.denominator, v)

    def points_int(self, vertices, patches=None):
        """Exact integer sample points of integer triangles whose coordinates are multiples of D."""
        v = np.asarray(vertices, dtype=np.int64)
        if not self.drawn:
            num = np.einsum("kj,njc->nkc", self.weights, v)
        else:
            num = np.einsum("nkj,njc->nkc", self._weights_for(v, patches), v)
        assert (num % self.denominator == 0).all(), "vertex coordinates must be multiples of D"
        return num // self.denominator

    def _weights_for(self, v, patches):
        return self.weights_of(np.arange(len(v)) if patches is None else patches)

    def centroids_int(self, vertices):
        v = np.asarray(vertices, dtype=np.int64)
        s = v.sum(axis=1)
        assert (s % 3 == 0).all()
        return s // 3
