"""Sample points on patches, chosen so they can be exact integers on the quantised grid.

A triangle is cut into n x n congruent cells (n = ceil(sqrt(K))); sample points are cell
centroids, i.e. barycentric weights (w0, w1, w2) / D with integer w summing to D = 3n. When the
vertex grid is scaled by D (vertex coordinates are multiples of D), every sample point
sum_k w_k V_k / D is an integer point lying exactly on the triangle's plane, so the strict
plane test needs no epsilon. The receiver end point of a ray is the patch centroid (weights
n, n, n), which is also exact. Scaling by D costs log2(D) coordinate bits.

When K < n * n, K cells are taken at evenly spread indices of the row-by-row cell order.
"""

from dataclasses import dataclass
from functools import cached_property
import math

import numpy as np

from .errors import ParameterError

__all__ = ["SampleScheme"]


@dataclass(frozen=True)
class SampleScheme:
    count: int = 8

    def __post_init__(self):
        if isinstance(self.count, bool) or not isinstance(self.count, int) or not 1 <= self.count <= 64:
            raise ParameterError(f"shooter samples must be an integer from 1 to 64, not {self.count!r}")

    @property
    def n(self):
        return math.isqrt(self.count - 1) + 1

    @property
    def denominator(self):
        """D: weights of every sample (and of the centroid) sum to D."""
        return 3 * self.n

    @cached_property
    def weights(self):
        """(K, 3) int64 barycentric weights of the shooter sample points."""
        n = self.n
        cells = []
        for row in range(n):                      # row = steps away from V0 along V0->V1
            for col in range(2 * row + 1):        # alternating upward / downward cells
                a, up = divmod(col, 2)
                if up == 0:   # upward cell: corners (row, a), (row+1, a), (row+1, a+1) in (i, j) steps
                    i3, j3 = 3 * row + 2, 3 * a + 1
                else:         # downward cell: corners (row, a), (row, a+1), (row+1, a+1)
                    i3, j3 = 3 * row + 1, 3 * a + 2
                # point V0 + (i/n)(V1-V0)... expressed as weights on (V0, V1, V2) over D = 3n
                w1, w2 = i3 - j3, j3
                cells.append((3 * n - i3, w1, w2))
        cells = np.array(cells, dtype=np.int64)
        if self.count < len(cells):
            pick = np.round(np.arange(self.count) * len(cells) / self.count).astype(int)
            cells = cells[pick]
        return cells

    @property
    def centroid_weights(self):
        return np.array([self.n, self.n, self.n], dtype=np.int64)

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
