"""Elements of hierarchical radiosity: the quadtree of each input triangle, and the board's table of
their end points.

An input triangle (level 0) splits by 4-way midpoint subdivision: children (a, ab, ca),
(ab, b, bc), (ca, bc, c) and the middle (ab, bc, ca), all of the parent's orientation and a
quarter of its area. Every element of level <= L has corners whose barycentric weights on its
input triangle are integers over 2**L, so an element's sample point ``sum_k w_k V_k / D``
(:class:`~blockray.samples.SampleScheme`) is an integer combination of the input triangle's
corners over ``D 2**L``. :class:`ElementPoints` lists those points for every element of every
level up to ``max_level``, as a sample scheme of denominator ``D 2**L``: the quantiser then puts
the input vertices on multiples of ``D 2**L`` (L more coordinate bits than the uniform render), and
every element point is an exact integer on its input triangle's plane, so the board's strict
plane test needs no epsilon for sub-element end points either. The golden board takes the same
rational points exactly.

Element numbering within an input triangle: level-major, ``offset(l) + q`` for the element of
path number q at level l (``offset(l) = (4**l - 1) / 3``); element q's children at level l + 1 are
``4 q + c``, c = 0..3 in the order above.
"""

import numpy as np

from ...errors import ParameterError
from ...params import MAX_BITS

__all__ = ["ElementPoints", "level_offset", "level_corners", "children_of", "MAX_LEVEL"]

#: Deepest level of the point table: (4**(L+1) - 1) / 3 elements of K + 1 points per input
#: triangle (L = 4: 341 elements, 3069 points at K = 8, 74 KB per triangle as int64 on the model).
MAX_LEVEL = 4


def level_offset(level):
    """Index of the first element of ``level`` in an input triangle's table."""
    return (4 ** level - 1) // 3


def children_of(node, level):
    """Table indices (4,) of the children of element ``node`` (of ``level``)."""
    q = node - level_offset(level)
    return level_offset(level + 1) + 4 * q + np.arange(4)


def level_corners(level):
    """(4**level, 3, 3) barycentric corners of the elements ``level`` levels below a triangle, in
    table order: the four children of one parent together, so neighbours in the order are near."""
    return _corner_weights(level)[level_offset(level):] / float(1 << level)


def _corner_weights(max_level):
    """(E, 3, 3) int64: corner v of element m as integer weights (over 2**max_level) on the input
    triangle's corners, every element of levels 0..max_level in table order."""
    unit = 1 << max_level
    levels = [np.eye(3, dtype=np.int64)[None] * unit]
    for _ in range(max_level):
        t = levels[-1]
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        ab, bc, ca = (a + b) // 2, (b + c) // 2, (c + a) // 2       # exact: multiples of 2 here
        kids = np.stack([np.stack(x, axis=1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], axis=1)
        levels.append(kids.reshape(-1, 3, 3))
    return np.concatenate(levels)


class ElementPoints:
    """The end points of every element up to ``max_level``, as a sample scheme for the board.

    Point ``m (K + 1) + k`` of an input triangle is sample k (k < K) of its element m, or its
    centroid (k = K). A block ray's columns address the table as ``(patch, point)``; its rows end
    at ``receiver_weights`` (blockray/board.py) taken from it, :meth:`weights_at`. With drawn
    ``samples`` (a seed) every element of every input triangle has its own K points, drawn and
    stratified over the element as the scheme draws them over a patch: one pattern shared by every
    element would give every link the same error, which sums instead of averaging out.
    """

    def __init__(self, samples, max_level):
        if not 0 <= max_level <= MAX_LEVEL:
            raise ParameterError(f"min_area asks for elements {max_level} levels below the input triangles; at most "
                                 f"{MAX_LEVEL} are supported (each level costs a coordinate bit of the board's "
                                 f"{MAX_BITS} and 4x the point table)", parameter="min_area")
        self.samples, self.max_level = samples, int(max_level)
        self.K = samples.count
        self.per_element = self.K + 1
        self.drawn = samples.drawn
        self.corners = _corner_weights(self.max_level)                       # (E, 3, 3) over 2**L
        self.centres = np.einsum("v,mvp->mp", samples.centroid_weights, self.corners)      # (E, 3)
        self.count = self.elements * self.per_element
        self.denominator = samples.denominator << self.max_level
        if not self.drawn:
            self.weights = self._table(np.einsum("kv,mvp->mkp", samples.weights, self.corners)).reshape(-1, 3)
            assert (self.weights.sum(axis=1) == self.denominator).all()

    def _table(self, sample_w):
        """(..., E, K + 1, 3): the elements' samples ``sample_w`` (..., E, K, 3) and their centroids."""
        centre = np.broadcast_to(self.centres[:, None], sample_w.shape[:-3] + (self.elements, 1, 3))
        return np.concatenate([sample_w, centre], axis=-2)

    @property
    def elements(self):
        """Elements per input triangle in the table."""
        return len(self.corners)

    @property
    def prime(self):
        return self.samples.prime

    @property
    def centroid_weights(self):
        return np.full(3, self.denominator // 3, dtype=np.int64)

    def sample_index(self, node):
        """(len(node), K) table indices of the K samples of elements ``node``."""
        return np.asarray(node, dtype=np.int64)[:, None] * self.per_element + np.arange(self.K)

    def element_samples(self, patch, node):
        """(M, K, 3) weights of the K samples of elements ``node`` of input triangles ``patch``."""
        node = np.asarray(node, dtype=np.int64).reshape(-1)
        if not self.drawn:
            return self.weights[self.sample_index(node)]
        drawn = self.samples.weights_of(np.asarray(patch, dtype=np.int64).reshape(-1) * self.elements + node)
        return np.einsum("mkv,mvp->mkp", drawn, self.corners[node])

    def weights_at(self, patch, index):
        """(M, 3) weights of table points ``index`` of input triangles ``patch``."""
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        if not self.drawn:
            return self.weights[index]
        node, k = np.divmod(index, self.per_element)
        out = self.centres[node].copy()
        at = np.flatnonzero(k < self.K)
        out[at] = self.element_samples(np.broadcast_to(patch, index.shape)[at], node[at])[np.arange(len(at)), k[at]]
        return out

    def element_vertices(self, vertices, node):
        """Float corners (M, 3, 3) of elements ``node`` of input triangles ``vertices`` (M, 3, 3)."""
        w = self.corners[np.asarray(node, dtype=np.int64)] / float(1 << self.max_level)
        return np.einsum("mvp,mpc->mvc", w, np.asarray(vertices, dtype=np.float64))

    def point(self, vertices, patch, index):
        """Float points (M, 3) of table points ``index`` of input triangles ``patch`` (corners
        ``vertices`` (M, 3, 3))."""
        w = self.weights_at(patch, index) / float(self.denominator)
        return np.einsum("mp,mpc->mc", w, np.asarray(vertices, dtype=np.float64))

    # -- the SampleScheme interface the boards and the quantiser use --------------------------------

    @property
    def per_patch(self):
        """Points per input triangle: the whole table."""
        return self.count

    def weights_of(self, patches):
        """(len(patches), count, 3): the table of each input triangle ``patches``."""
        patches = np.asarray(patches, dtype=np.int64).reshape(-1)
        if not self.drawn:
            return np.broadcast_to(self.weights, (len(patches), self.count, 3))
        keys = (patches[:, None] * self.elements + np.arange(self.elements)).ravel()
        drawn = self.samples.weights_of(keys).reshape(len(patches), self.elements, self.K, 3)
        return self._table(np.einsum("nmkv,mvp->nmkp", drawn, self.corners)).reshape(len(patches), -1, 3)

    def points(self, vertices, patches=None):
        v = np.asarray(vertices, dtype=np.float64)
        return np.einsum("nkj,njc->nkc", self._weights_for(v, patches) / self.denominator, v)

    def points_int(self, vertices, patches=None):
        v = np.asarray(vertices, dtype=np.int64)
        num = np.einsum("nkj,njc->nkc", self._weights_for(v, patches), v)
        assert (num % self.denominator == 0).all(), "vertex coordinates must be multiples of D 2**L"
        return num // self.denominator

    def _weights_for(self, v, patches):
        return self.weights_of(np.arange(len(v)) if patches is None else patches)

    def centroids_int(self, vertices):
        s = np.asarray(vertices, dtype=np.int64).sum(axis=1)
        assert (s % 3 == 0).all()
        return s // 3
