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
"""

from dataclasses import dataclass
from functools import cached_property
from fractions import Fraction
import math

import numpy as np

from .errors import ParameterError

__all__ = ["SampleScheme", "END_LATTICES"]

#: allowed end-point lattice refinements (powers of two: each doubling costs one coordinate bit)
END_LATTICES = (1, 2, 4, 8, 16)


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

    def __post_init__(self):
        if isinstance(self.count, bool) or not isinstance(self.count, int) or not 1 <= self.count <= 64:
            raise ParameterError(f"shooter samples must be an integer from 1 to 64, not {self.count!r}")
        e = self.end_lattice
        if isinstance(e, bool) or not isinstance(e, int) or e not in END_LATTICES:
            raise ParameterError(f"end_lattice must be one of {', '.join(map(str, END_LATTICES))}, not {e!r}",
                                 parameter="end_lattice")

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
        """(K, 3) int64 barycentric weights of the shooter sample points."""
        cells = self._lattice[1]
        if self.count < len(cells):
            cells = [cells[i] for i in np.round(np.arange(self.count) * len(cells) / self.count).astype(int)]
        return _balanced(cells) * self.end_lattice

    @property
    def centroid_weights(self):
        return np.array([self.prime * self.end_lattice] * 3, dtype=np.int64)

    def points(self, vertices):
        """Float sample points of triangles (N, 3, 3) -> (N, K, 3)."""
        v = np.asarray(vertices, dtype=np.float64)
        return np.einsum("kj,njc->nkc", self.weights / self.denominator, v)

    def points_int(self, vertices):
        """Exact integer sample points of integer triangles whose coordinates are multiples of D."""
        v = np.asarray(vertices, dtype=np.int64)
        num = np.einsum("kj,njc->nkc", self.weights, v)
        assert (num % self.denominator == 0).all(), "vertex coordinates must be multiples of D"
        return num // self.denominator

    def centroids_int(self, vertices):
        v = np.asarray(vertices, dtype=np.int64)
        s = v.sum(axis=1)
        assert (s % 3 == 0).all()
        return s // 3
