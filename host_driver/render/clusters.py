"""Clusters of input triangles for ``--solver hierarchical`` (Smits, Arvo and Greenberg 1994), so
that the initial links grow about as s log s, not s**2, for s input triangles.

**Tree.** A binary tree over the input triangles (:func:`build_tree`): each node's members are a
contiguous run of ``order``, split at the median of their centroids along the widest axis, down to
single triangles. A node has the box of its members' vertices, their area and area-weighted centre.

**Linking** (:func:`link_clusters`). From a pair (R <- S) of nodes, top down: the pair stays one
*cluster link* while its boxes are :data:`SEPARATION` times the larger one's diagonal apart and the
power it can carry is at most the threshold; the bound is ``B_S A_R A_S / (pi d**2)`` with ``B_S``
its members' largest radiosity and ``d`` the gap between the two boxes (the point-to-point kernel
``cos cos / (pi r**2)`` is at most ``1 / (pi d**2)``), so it holds whatever the members'
orientation and distance, and it bounds the link's error as well as its power. Otherwise the
node with the larger box is split (a node with itself: its children's four pairs); two single
triangles become an element link (hierarchical.py).

**Transfer** (:class:`Transfer`). A cluster link moves light with a kernel of :data:`RANK` 4,
``F_rs = a_r . b_s``: ``a_r`` the mean over points x of receiver r of ``max(0, N_r . u) / (pi |c_S
- x|**3) [x - c_S, 1]`` (u the unit vector from x to the source node's centre ``c_S``), ``b_s``
``A_s`` times the mean over points q of source s facing ``c_R`` of ``(d / |c_R - q|)**3 [N_s, N_s .
(c_S - q)]`` (``d = |c_R - c_S|``). Their dot product is ``cos_r A_s N_s . (x - q) / (pi |c_S -
x|**3)`` with a distance correction: the source's cosine is taken towards each receiver, which a
rank-1 kernel (both cosines along the centres' line) cannot do, and a receiver near the source's
plane sees it at its own grazing angle. The points are each triangle's edge midpoints (exact for
quadratics). It is reciprocal for each member pair (``A_r F_rs = A_s F_sr``), and costs the
members, not their pairs. It gathers on the receivers (the leaves of the receiver node's
triangles, each with its own terms) from its source triangles (their leaves' mean), times the
link's visible fraction.

**Visibility.** Each leaf of a cluster link's receiver node has its own visible fraction: the
rays of the element link to it from one member of the source node (:func:`source_members`),
drawn in proportion to what it sends (area times the kernel's mean towards the receiver node's
centre) from a hash of the link's two nodes (the same on every board, Dask set and resumed
checkpoint); a leaf split later gets its children's own rays, a leaf kept keeps its fraction. One
fraction for all the receivers would light a receiver cluster half under a table as a whole, and
the solve would gain energy (docs/hierarchical.md, "A visible fraction per receiver leaf").
"""

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit, prange
from scipy import sparse

from ...memory import ranges

__all__ = ["ClusterTree", "ClusterLinks", "Transfer", "build_tree", "link_clusters", "receiver_entries",
           "entry_keys", "leaf_weights", "source_members", "power_bounds", "split_pairs", "SEPARATION", "RANK"]

#: a cluster link's two boxes are at least this many times the larger box's diagonal apart: the
#: kernel's error falls with the nodes' size over their distance (a closed box of 432 triangles,
#: every one emitting, epsilon 1e-3: the largest leaf error 3.1% at 1, 0.95% at 2, 0.22% at 3,
#: for 29 k, 67 k and 112 k links; docs/hierarchical.md)
SEPARATION = 2.0



@dataclass(frozen=True)
class ClusterTree:
    """Nodes 0.. (0: every triangle); members of node k: ``order[start[k]:end[k]]``; ``left``,
    ``right``: children (-1: a single triangle); ``lo``, ``hi``: the members' box; ``area``;
    ``centre``: area-weighted centroid; ``parent`` (-1: the root)."""
    order: np.ndarray
    start: np.ndarray
    end: np.ndarray
    left: np.ndarray
    right: np.ndarray
    parent: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    area: np.ndarray
    centre: np.ndarray

    def __len__(self):
        return len(self.start)

    @property
    def leaf(self):
        return self.left < 0

    @cached_property
    def size(self):
        """The box's diagonal (computed once: every linking pass reads it)."""
        return np.linalg.norm(self.hi - self.lo, axis=1)

    @cached_property
    def levels(self):
        """The inner nodes by depth, deepest first (children are numbered after their parents)."""
        depth = np.zeros(len(self), dtype=np.int64)
        for k in range(1, len(self)):
            depth[k] = depth[self.parent[k]] + 1
        inner = ~self.leaf
        return [np.flatnonzero(inner & (depth == d)) for d in range(int(depth.max(initial=0)), -1, -1)]

    def members(self, nodes):
        """``(row, triangle)``: for each member of each of ``nodes``, its index in ``nodes``."""
        nodes = np.asarray(nodes, dtype=np.int64)
        count = self.end[nodes] - self.start[nodes]
        return np.repeat(np.arange(len(nodes)), count), self.order[ranges(self.start[nodes], count)]

    def maxima(self, values):
        """Per node, the largest of its members' ``values`` (one per input triangle)."""
        out = np.full(len(self), -np.inf)
        out[self.leaf] = values[self.order[self.start[self.leaf]]]
        for level in self.levels:
            out[level] = np.maximum(out[self.left[level]], out[self.right[level]])
        return out


def build_tree(scene):
    """The cluster tree of ``scene``'s input triangles (module docstring)."""
    N, c = scene.patches, scene.centroids
    order = np.arange(N)
    start, end, parent = [0], [N], [-1]
    left, right = [-1], [-1]
    k = 0
    while k < len(start):
        s, e = start[k], end[k]
        if e - s > 1:
            run = order[s:e]
            axis = int(np.argmax(np.ptp(c[run], axis=0)))
            order[s:e] = run[np.argsort(c[run, axis], kind="stable")]
            mid = s + (e - s) // 2
            left[k], right[k] = len(start), len(start) + 1
            start += [s, mid]
            end += [mid, e]
            parent += [k, k]
            left += [-1, -1]
            right += [-1, -1]
        k += 1
    a = lambda xs: np.array(xs, dtype=np.int64)
    start, end, left, right, parent = a(start), a(end), a(left), a(right), a(parent)
    V, A = scene.patch_vertices, scene.areas
    cum_a = np.concatenate([[0.0], np.cumsum(A[order])])
    cum_c = np.concatenate([np.zeros((1, 3)), np.cumsum(A[order, None] * c[order], axis=0)])
    area = cum_a[end] - cum_a[start]
    centre = (cum_c[end] - cum_c[start]) / np.where(area > 0, area, 1.0)[:, None]
    tree = ClusterTree(order, start, end, left, right, parent, np.zeros((len(start), 3)), np.zeros((len(start), 3)),
                       area, centre)
    leaf = tree.leaf
    tree.lo[leaf], tree.hi[leaf] = V[order[start[leaf]]].min(axis=1), V[order[start[leaf]]].max(axis=1)
    for level in tree.levels:
        tree.lo[level] = np.minimum(tree.lo[left[level]], tree.lo[right[level]])
        tree.hi[level] = np.maximum(tree.hi[left[level]], tree.hi[right[level]])
    return tree


def power_bounds(tree, R, S, source_max):
    """``B_S A_R A_S / (pi d**2)`` (module docstring); inf where the boxes touch."""
    gap = np.maximum(0.0, np.maximum(tree.lo[S] - tree.hi[R], tree.lo[R] - tree.hi[S]))
    d2 = np.einsum("nc,nc->n", gap, gap)
    power = np.maximum(source_max[S], 0.0) * tree.area[R] * tree.area[S]
    apart = (d2 > 0) & (d2 >= (SEPARATION * np.maximum(tree.size[R], tree.size[S])) ** 2)
    return np.where(apart, power / (math.pi * np.where(d2 > 0, d2, 1.0)), np.inf)


def link_clusters(tree, R, S, source_max, threshold):
    """From node pairs ``(R <- S)`` down (module docstring): ``(R, S, recv, src)``, the pairs kept
    as cluster links and the pairs of input triangles that became element links."""
    keep_R, keep_S, recv, src = [], [], [], []
    R, S = np.asarray(R, dtype=np.int64), np.asarray(S, dtype=np.int64)
    while len(R):
        ok = (R != S) & (power_bounds(tree, R, S, source_max) <= threshold)
        keep_R.append(R[ok]), keep_S.append(S[ok])
        R, S = R[~ok], S[~ok]
        both = tree.leaf[R] & tree.leaf[S]
        pair = both & (R != S)              # a triangle does not light itself
        recv.append(tree.order[tree.start[R[pair]]]), src.append(tree.order[tree.start[S[pair]]])
        R, S = split_pairs(tree, R[~both], S[~both])
    cat = lambda xs: np.concatenate([np.zeros(0, np.int64)] + xs).astype(np.int64)
    return cat(keep_R), cat(keep_S), cat(recv), cat(src)


def split_pairs(tree, R, S):
    """The child pairs of node pairs (not both single triangles): a node with itself gives its
    children's four pairs; otherwise the node with the larger box (not a single triangle) splits."""
    same = R == S
    l, r = tree.left, tree.right
    pairs_R = [l[R[same]], l[R[same]], r[R[same]], r[R[same]]]
    pairs_S = [l[S[same]], r[S[same]], l[S[same]], r[S[same]]]
    R, S = R[~same], S[~same]
    size = tree.size
    split_R = ~tree.leaf[R] & (tree.leaf[S] | (size[R] >= size[S]))
    for child in (l, r):
        pairs_R.append(np.where(split_R, child[R], R))
        pairs_S.append(np.where(split_R, S, child[S]))
    return np.concatenate(pairs_R), np.concatenate(pairs_S)


@dataclass
class ClusterLinks:
    """Cluster links (node ``R`` <- node ``S``), their visible fraction ``vis`` and ``partial`` (the
    rays neither all clear nor all blocked). ``rvis``: once cast, the visible fraction of each
    receiver leaf of each link, in the order of :func:`receiver_entries` on the leaves they were
    cast for, and ``rkey`` the entries' keys (:func:`entry_keys`); None: ``vis`` for all of them
    (links not cast; :meth:`take` and :meth:`join` drop them, a new cast carries them over).
    ``rweight``: the entries' :func:`leaf_weights`, ``rlink`` their links and ``rsize`` the
    elements there were, kept so a new cast finds the entries it shares with this one in order and
    computes only the others' weights (None: not kept, as after a checkpoint). ``origin``: each
    link's index in the links it was taken from (:meth:`take`; -1 for a link :meth:`join` added)."""
    R: np.ndarray
    S: np.ndarray
    vis: np.ndarray = None
    partial: np.ndarray = None
    rkey: np.ndarray = None
    rvis: np.ndarray = None
    rweight: np.ndarray = None
    rlink: np.ndarray = None
    rsize: int = None
    origin: np.ndarray = None

    @staticmethod
    def empty():
        z = np.zeros(0, dtype=np.int64)
        return ClusterLinks(z, z.copy(), np.zeros(0), np.zeros(0, dtype=bool), np.zeros((0, 2), np.int64), np.zeros(0))

    def __len__(self):
        return len(self.R)

    def take(self, keep):
        return ClusterLinks(self.R[keep], self.S[keep], self.vis[keep], self.partial[keep],
                            origin=np.arange(len(self))[keep])

    @staticmethod
    def join(a, b):
        """``a`` then ``b`` (links not cast yet: clear, not partial, until cast)."""
        cat = np.concatenate
        vis = [np.ones(len(x)) if x.vis is None else x.vis for x in (a, b)]
        partial = [np.zeros(len(x), dtype=bool) if x.partial is None else x.partial for x in (a, b)]
        origin = [np.full(len(x), -1) if x.origin is None else x.origin for x in (a, b)]
        return ClusterLinks(cat([a.R, b.R]), cat([a.S, b.S]), cat(vis), cat(partial), origin=cat(origin))


def receiver_entries(tree, links, leaves, N):
    """``(link, leaf)``: every leaf of every triangle of each link's receiver node, link after link,
    triangles in the tree's member order, a triangle's leaves in the order of ``leaves = (ids,
    patch)`` (the rows of :class:`Transfer`'s receiver table; ``leaf`` indexes ``ids``)."""
    ids, patch = leaves
    by_patch = np.argsort(patch, kind="stable")
    count = np.bincount(patch, minlength=N)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    return _receiver_entries(tree.start[links.R], tree.end[links.R], tree.order, first, count, by_patch)


def entry_keys(tree, links, link, element):
    """(m, 2) keys of (cluster link, receiver element) entries that stay the same while the link
    and the element exist: the link's two nodes, and the element's id."""
    return np.stack([links.R[link] * np.int64(len(tree)) + links.S[link], np.asarray(element, np.int64)], axis=1)


class Transfer:
    """The kernels of cluster links (module docstring) as two sparse tables, ``F = P diag(v) Q``:
    ``P`` (receivers x links * RANK) and ``Q`` (links * RANK x input triangles), the visible
    fractions in ``Q``. The receivers are the member triangles, or with ``leaves = (ids, patch,
    corners)`` the leaf elements of each member (each with its own terms, so a leaf's factor sum
    is its own, not its triangle's mean), numbered by ``ids`` among ``size`` elements."""

    def __init__(self, tree, scene, links, leaves=None, size=None):
        self.N, self.size = scene.patches, size or scene.patches
        ids, patch, corners = leaves if leaves is not None else (np.arange(self.N), np.arange(self.N),
                                                                   scene.patch_vertices)
        per_link, link, leaf = receiver_entries(tree, links, (ids, patch), self.N)
        c, R, S = tree.centre, links.R, links.S
        if links.rvis is None:              # one fraction per link: on the source side
            rvis, vis = np.ones(len(link)), np.asarray(links.vis, dtype=np.float64)
        else:                               # each receiver leaf its own
            rvis, vis = np.asarray(links.rvis, dtype=np.float64), np.ones(len(R))
            assert len(rvis) == len(link), "cluster links cast for other leaves"
        self.PT = _table(*_receiver_table(per_link, link, leaf, patch, ids, corners, scene.normals, c[S], rvis),
                         self.size)
        self.Q = _table(*_source_table(tree.start[S], tree.end[S], tree.order, scene.patch_vertices, scene.normals,
                                       scene.areas, c[R], c[S], vis), self.N)
        self.P, self.QT = self.PT.T, self.Q.T
        # a solve gathers and shoots through the same tables a few dozen times: where the product
        # is small enough to hold, one pass forms it and each use is a dense product (the room
        # from max edge 1: 4.4 M entries, 5 ms a use against 17-26 ms through both tables)
        self.M = None
        if self.size * self.N <= DENSE_ENTRIES:
            self.M = _dense_product(self.PT.indptr, self.PT.indices, self.PT.data, self.Q.indptr, self.Q.indices,
                                    self.Q.data, self.size, self.N)

    def gather(self, x):
        """Per receiver r: ``sum_links v sum_s F_rs x_s`` (``x`` per input triangle, (N,) or (N, c))."""
        return self.M @ x if self.M is not None else self.P @ (self.Q @ x)

    def shoot(self, y):
        """The transpose: per input triangle s, ``sum_links v sum_r F_rs y_r`` (``y`` per receiver)."""
        return self.M.T @ y if self.M is not None else self.QT @ (self.PT @ y)


#: the most entries (receivers x input triangles) :class:`Transfer` holds as one dense product
#: (64 MB); larger ones stay two sparse tables
DENSE_ENTRIES = 1 << 23


@njit(cache=True)
def _dense_product(pt_ptr, pt_idx, pt_dat, q_ptr, q_idx, q_dat, rows, cols):
    """``P Q`` as a dense (rows, cols) array from the CSR arrays of ``P.T`` and ``Q``, link by
    link: a link's RANK term rows hold the same receivers (in ``P.T``) and the same sources (in
    ``Q``), so each (receiver, source) pair of the link adds its RANK-term dot product once."""
    L = (len(pt_ptr) - 1) // RANK
    M = np.zeros((rows, cols))
    for l in range(L):
        for a in range(pt_ptr[l + 1] - pt_ptr[l]):
            r = pt_idx[pt_ptr[l] + a]
            for b in range(q_ptr[l + 1] - q_ptr[l]):
                v = 0.0
                for k in range(RANK):
                    v += pt_dat[pt_ptr[k * L + l] + a] * q_dat[q_ptr[k * L + l] + b]
                M[r, q_idx[q_ptr[l] + b]] += v
    return M


#: terms of a cluster link's kernel (:func:`_receiver_table`, :func:`_source_terms`)
RANK = 4


def _table(data, index, indptr, width):
    return sparse.csr_matrix((data, index, indptr), shape=(len(indptr) - 1, width))


@njit(cache=True)
def _offsets(count):
    """Rows of link l start at ``start[l]``; the CSR row ``k * L + l`` (term k) at ``k m + start[l]``."""
    L = len(count)
    start = np.zeros(L + 1, dtype=np.int64)
    for l in range(L):
        start[l + 1] = start[l] + count[l]
    m = start[L]
    indptr = np.empty(RANK * L + 1, dtype=np.int64)
    for k in range(RANK):
        for l in range(L):
            indptr[k * L + l] = k * m + start[l]
    indptr[RANK * L] = RANK * m
    return start, m, indptr


@njit(cache=True)
def _receiver_entries(R_start, R_end, order, first, count, by_patch):
    """:func:`receiver_entries`: ``(per_link, link, leaf)``."""
    L = len(R_start)
    per_link = np.zeros(L, dtype=np.int64)
    for l in range(L):
        for j in range(R_start[l], R_end[l]):
            per_link[l] += count[order[j]]
    m = per_link.sum()
    link, leaf = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
    pos = 0
    for l in range(L):
        for j in range(R_start[l], R_end[l]):
            t = order[j]
            for q in range(count[t]):
                link[pos], leaf[pos] = l, by_patch[first[t] + q]
                pos += 1
    return per_link, link, leaf


@njit(cache=True, parallel=True)
def _receiver_table(per_link, link, leaf, patch, ids, corners, normals, c_S, rvis):
    """The CSR arrays of ``P.T``: per link, its receiver entries (:func:`receiver_entries`), each
    with its terms times its visible fraction ``rvis``, the mean over its points x of ``max(0,
    cos_r) / (pi |c_S - x|**3) [x - c_S, 1]`` (:func:`_kernel_terms`, ``cos_r`` towards the
    source's centre). With :func:`_source_terms` the dot product is ``cos_r A_s w_s N_s . (x -
    x_s) / (pi |c_S - x|**3)``: the source's cosine towards this very receiver (linear in x), so
    a receiver near the source's plane sees it at its own grazing angle."""
    start, m, indptr = _offsets(per_link)
    data, index = np.empty(RANK * m), np.empty(RANK * m, dtype=np.int64)
    for i in prange(m):
        e = leaf[i]
        terms = _kernel_terms(corners[e], normals[patch[e]], c_S[link[i]])
        for k in range(RANK):
            data[k * m + i] = terms[k] * rvis[i] / np.pi
            index[k * m + i] = ids[e]
    return data, index, indptr


@njit(cache=True, parallel=True)
def _source_table(S_start, S_end, order, corners, normals, areas, c_R, c_S, vis):
    """The CSR arrays of ``Q``: per link, its source node's triangles, each with
    :func:`_source_terms` times the link's visible fraction."""
    L = len(S_start)
    start, m, indptr = _offsets(S_end - S_start)
    data, index = np.empty(RANK * m), np.empty(RANK * m, dtype=np.int64)
    for l in prange(L):
        for j in range(S_start[l], S_end[l]):
            pos = start[l] + j - S_start[l]
            t = order[j]
            terms = _source_terms(corners[t], normals[t], areas[t], c_R[l], c_S[l])
            for k in range(RANK):
                data[k * m + pos] = terms[k] * vis[l]
                index[k * m + pos] = t
    return data, index, indptr


@njit(cache=True)
def _kernel_terms(corners, normal, target):
    """Over the edge midpoints x of a triangle (a rule exact for quadratics): the means of
    ``k`` and ``k (x - target)`` with ``k = max(0, cos) / |target - x|**3``, cos against ``normal``.
    (Scalars throughout: no array is allocated per call.)"""
    o0 = o1 = o2 = o3 = 0.0
    for q in range(3):
        p = (q + 1) % 3
        t0 = target[0] - 0.5 * (corners[q, 0] + corners[p, 0])
        t1 = target[1] - 0.5 * (corners[q, 1] + corners[p, 1])
        t2 = target[2] - 0.5 * (corners[q, 2] + corners[p, 2])
        r2 = t0 * t0 + t1 * t1 + t2 * t2
        if r2 <= 0.0:
            continue
        cos = (normal[0] * t0 + normal[1] * t1 + normal[2] * t2) / np.sqrt(r2)
        if cos > 0.0:
            k = cos / (r2 * np.sqrt(r2)) / 3.0
            o0 -= k * t0
            o1 -= k * t1
            o2 -= k * t2
            o3 += k
    return (o0, o1, o2, o3)


@njit(cache=True)
def _source_terms(corners, n, area, c_R, c_S):
    """A source's terms: ``A_s`` times the mean over its points q facing the receiver's centre of
    ``(d / |c_R - q|)**3 [N_s, N_s . (c_S - q)]``, d the centres' distance (the distance to this
    source point, exact where the receiver is at its centre). (Scalars throughout.)"""
    o0 = o1 = o2 = o3 = 0.0
    d0, d1, d2 = c_R[0] - c_S[0], c_R[1] - c_S[1], c_R[2] - c_S[2]
    d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    for q in range(3):
        p = (q + 1) % 3
        x0 = 0.5 * (corners[q, 0] + corners[p, 0])
        x1 = 0.5 * (corners[q, 1] + corners[p, 1])
        x2 = 0.5 * (corners[q, 2] + corners[p, 2])
        t0, t1, t2 = c_R[0] - x0, c_R[1] - x1, c_R[2] - x2
        r2 = t0 * t0 + t1 * t1 + t2 * t2
        if r2 <= 0.0 or n[0] * t0 + n[1] * t1 + n[2] * t2 <= 0.0:
            continue
        w = area * (d / np.sqrt(r2)) ** 3 / 3.0
        o0 += w * n[0]
        o1 += w * n[1]
        o2 += w * n[2]
        o3 += w * (n[0] * (c_S[0] - x0) + n[1] * (c_S[1] - x1) + n[2] * (c_S[2] - x2))
    return (o0, o1, o2, o3)


def leaf_weights(tree, scene, links, link, corners, patch, area):
    """What each receiver entry (``link``, a leaf of corners ``corners`` and ``area`` on input
    triangle ``patch``) can receive: its area times its kernel mean towards the link's source
    centre (0: it faces away)."""
    return area * _kernel_mean(corners, scene.normals[patch], tree.centre[links.S][link])


def source_members(tree, scene, links, stream=0):
    """Per link, one member of its source node, drawn in proportion to what it sends (its area
    times its kernel mean towards the receiver node's centre) from a hash of the link's nodes and
    ``stream`` (the same on every board, Dask set and checkpoint); -1 where none faces the receiver."""
    n = len(links)
    link, src = tree.members(links.S)
    c, V, N_ = tree.centre, scene.patch_vertices, scene.normals
    weight = scene.areas[src] * _kernel_mean(V[src], N_[src], c[links.R][link])
    drawn = _draw(link, src, weight, n, _uniform(links.R, links.S, 2 * stream + 1))
    return np.where(np.bincount(link, weight, minlength=n) > 0, drawn, -1)


@njit(cache=True)
def _kernel_mean(corners, normals, target):
    """Mean of ``max(0, cos) / r**2`` from ``target`` over each triangle ``corners`` (m, 3, 3) (its
    edge midpoints), ``cos`` against the triangle's normal."""
    out = np.zeros(len(corners))
    for m in range(len(corners)):
        for q in range(3):
            to = target[m] - 0.5 * (corners[m, q] + corners[m, (q + 1) % 3])
            r2 = to[0] * to[0] + to[1] * to[1] + to[2] * to[2]
            cos = normals[m, 0] * to[0] + normals[m, 1] * to[1] + normals[m, 2] * to[2]
            if r2 > 0.0 and cos > 0.0:
                out[m] += cos / np.sqrt(r2) / r2 / 3.0
    return out


def _uniform(R, S, k):
    """Deterministic uniforms in [0, 1) from node pairs and a stream number."""
    mixed = ((np.asarray(R, np.uint64) * np.uint64(0x9E3779B97F4A7C15))
             ^ (np.asarray(S, np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F))
             ^ np.uint64((k + 1) * 0x165667B19E3779F9 % (1 << 64)))
    mixed ^= mixed >> np.uint64(31)
    mixed *= np.uint64(0xBF58476D1CE4E5B9)
    mixed ^= mixed >> np.uint64(29)
    return (mixed >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _draw(row_link, value, weight, n, u):
    """Per link, one of its rows' ``value`` drawn with probability proportional to ``weight``
    (rows grouped by link, in link order)."""
    cum = np.cumsum(weight)
    total = np.bincount(row_link, weight, minlength=n)
    first = np.searchsorted(row_link, np.arange(n))
    last = np.searchsorted(row_link, np.arange(n), side="right") - 1
    base = np.where(first > 0, cum[np.maximum(first - 1, 0)], 0.0)
    pick = np.searchsorted(cum, base + u * total, side="right")
    return value[np.clip(pick, first, np.maximum(last, first))]
