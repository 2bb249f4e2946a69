"""Clusters of input triangles for ``--solver hierarchical`` (Smits, Arvo and Greenberg 1994), so
that the initial links grow about as s log s, not s**2, for s input triangles.

**Tree.** A binary tree over the input triangles (:func:`build_tree`): each node's members are a
contiguous run of ``order``, split at the median of their centroids along the widest axis, down to
single triangles. A node has the box of its members' vertices, their area and area-weighted centre.

**Linking** (:func:`link_clusters`). From a pair (R <- S) of nodes, top down: the pair stays one
*cluster link* while the power it can carry is at most the threshold; the bound is
``B_S A_R A_S / (pi d**2)`` with ``B_S`` its members' largest radiosity and ``d`` the gap between
the two boxes (the point-to-point kernel ``cos cos / (pi r**2)`` is at most ``1 / (pi d**2)``), so
it holds whatever the members' orientation and distance, and it bounds the link's error as well as
its power. Otherwise the node with the larger box is split (a node with itself: its children's
four pairs); two single triangles become an element link (hierarchical.py).

**Transfer** (:class:`Transfer`). A cluster link moves light with a rank-one kernel: ``F_rs = a_r
b_s`` with ``a_r`` the mean of ``max(0, N_r . u) / (pi |c_S - x|**2)`` over points x of receiver r
(u the unit vector from x to ``c_S``) and ``b_s = A_s d**2`` times the same mean over source s
towards ``c_R``, where ``c`` are the nodes' centres and ``d = |c_R - c_S|``: the point-to-point
kernel where either member is small and at its node's centre. The points are each triangle's edge
midpoints (exact for quadratics). It is reciprocal for each member pair (``A_r F_rs = A_s F_sr``),
and costs the members, not their pairs. It gathers on the receivers (the leaves of the receiver
node's triangles, each with its own ``a_r``) from its source triangles (their leaves' mean), times
the link's visible fraction.

**Visibility.** A cluster link's rays are those of one element link between two of its members
(:func:`member_pairs`), drawn in proportion to what the pair carries, ``A_r a_r b_s``, from a hash of
the link's two nodes (the same on every board, Dask set and resumed checkpoint).
"""

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import sparse

from ...memory import ranges

__all__ = ["ClusterTree", "ClusterLinks", "Transfer", "build_tree", "link_clusters", "member_pairs",
           "split_links", "MEMBER_PAIRS"]

#: a cluster link's two boxes are at least this many times the larger box's diagonal apart: the
#: kernel's error falls with the nodes' size over their distance (a closed box of 432 triangles,
#: every one emitting, epsilon 1e-3: the largest leaf error 3.1% at 1, 0.95% at 2, 0.22% at 3,
#: for 29 k, 67 k and 112 k links; docs/hierarchical.md)
SEPARATION = 2.0

#: element links between members whose rays stand for a cluster link's
MEMBER_PAIRS = 1


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

    @property
    def size(self):
        """The box's diagonal."""
        return np.linalg.norm(self.hi - self.lo, axis=1)

    def members(self, nodes):
        """``(row, triangle)``: for each member of each of ``nodes``, its index in ``nodes``."""
        nodes = np.asarray(nodes, dtype=np.int64)
        count = self.end[nodes] - self.start[nodes]
        return np.repeat(np.arange(len(nodes)), count), self.order[ranges(self.start[nodes], count)]

    def maxima(self, values):
        """Per node, the largest of its members' ``values`` (one per input triangle)."""
        out = np.full(len(self), -np.inf)
        out[self.leaf] = values[self.order[self.start[self.leaf]]]
        for level in _levels_up(self):
            out[level] = np.maximum(out[self.left[level]], out[self.right[level]])
        return out


def _levels_up(tree):
    """The inner nodes by depth, deepest first (children are numbered after their parents)."""
    depth = np.zeros(len(tree), dtype=np.int64)
    for k in range(1, len(tree)):
        depth[k] = depth[tree.parent[k]] + 1
    inner = ~tree.leaf
    return [np.flatnonzero(inner & (depth == d)) for d in range(int(depth.max(initial=0)), -1, -1)]


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
    for level in _levels_up(tree):
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


def split_links(tree, R, S):
    """Each cluster link ``(R <- S)`` replaced by its two child pairs (:func:`split_pairs`); two
    single triangles stay as they are (the caller makes them an element link)."""
    both = tree.leaf[R] & tree.leaf[S]
    kids_R, kids_S = split_pairs(tree, R[~both], S[~both])
    return np.concatenate([R[both], kids_R]), np.concatenate([S[both], kids_S])


@dataclass
class ClusterLinks:
    """Cluster links (node ``R`` <- node ``S``), their visible fraction ``vis`` and ``partial`` (the
    member pairs' rays neither all clear nor all blocked)."""
    R: np.ndarray
    S: np.ndarray
    vis: np.ndarray = None
    partial: np.ndarray = None

    @staticmethod
    def empty():
        z = np.zeros(0, dtype=np.int64)
        return ClusterLinks(z, z.copy(), np.zeros(0), np.zeros(0, dtype=bool))

    def __len__(self):
        return len(self.R)

    def take(self, keep):
        return ClusterLinks(self.R[keep], self.S[keep], self.vis[keep], self.partial[keep])

    @staticmethod
    def join(a, b):
        cat = np.concatenate
        return ClusterLinks(cat([a.R, b.R]), cat([a.S, b.S]), cat([a.vis, b.vis]), cat([a.partial, b.partial]))


class Transfer:
    """The kernels of cluster links (module docstring) as two tables: receiver rows ``(link,
    receiver, a)`` and source rows ``(link, triangle, b)``, ``a`` and ``b`` of :data:`RANK`
    terms. The receivers are the member triangles, or with ``leaves = (ids, patch, corners)`` the
    leaf elements of each member (each with its own ``a``, so a leaf's factor sum is its own, not
    its triangle's mean), numbered by ``ids`` among ``size`` elements."""

    def __init__(self, tree, scene, links, leaves=None, size=None):
        self.vis = np.asarray(links.vis, dtype=np.float64)
        self.recv_link, self.recv = tree.members(links.R)
        self.src_link, self.src = tree.members(links.S)
        self.N, self.size = scene.patches, size or scene.patches
        corners, row, tri = scene.patch_vertices, self.recv, self.recv
        if leaves is not None:              # each member triangle's leaves in its place
            ids, patch, corners = leaves
            by_patch = np.argsort(patch, kind="stable")
            count = np.bincount(patch, minlength=self.N)
            first = np.concatenate([[0], np.cumsum(count)[:-1]])
            n = count[self.recv]
            row = by_patch[ranges(first[self.recv], n)]
            self.recv_link, tri = np.repeat(self.recv_link, n), np.repeat(self.recv, n)
            self.recv = ids[row]
        # each receiver seen from the source's centre, each source member from the receiver's
        c = tree.centre
        self.a = _receiver_terms(corners, row, scene.normals, tri, c[links.S], self.recv_link)
        self.b = _source_terms(scene.patch_vertices, scene.normals, scene.areas, self.src, c[links.R], c[links.S],
                               self.src_link) * self.vis[self.src_link, None]
        # F = P diag(v) Q as sparse matrices (v in Q): a gather costs the rows, in compiled loops
        self.PT = _link_major(self.a, self.recv_link, self.recv, len(self.vis), self.size)
        self.Q = _link_major(self.b, self.src_link, self.src, len(self.vis), self.N)
        self.P, self.QT = self.PT.T, self.Q.T

    def gather(self, x):
        """Per receiver r: ``sum_links v sum_s F_rs x_s`` (``x`` per input triangle, (N,) or (N, c))."""
        return self.P @ (self.Q @ x)

    def shoot(self, y):
        """The transpose: per input triangle s, ``sum_links v sum_r F_rs y_r`` (``y`` per receiver)."""
        return self.QT @ (self.PT @ y)


#: terms of a cluster link's kernel (:func:`_receiver_terms`)
RANK = 4


def _link_major(terms, link, column, links, width):
    """The CSR matrix (links * RANK, width) whose row ``l * RANK + k`` holds ``terms[i, k]`` at
    ``column[i]`` for the rows i of link l (rows grouped by link, in link order): built in place,
    no sort."""
    count = np.bincount(link, minlength=links)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    within = np.arange(len(link)) - start[link]
    pos = (RANK * start[link] + within)[:, None] + np.arange(RANK) * count[link][:, None]
    data, index = np.empty(RANK * len(link)), np.empty(RANK * len(link), dtype=np.int64)
    data[pos] = terms
    index[pos] = column[:, None]
    indptr = np.append((RANK * start[:, None] + np.arange(RANK) * count[:, None]).ravel(), RANK * len(link))
    return sparse.csr_matrix((data, index, indptr), shape=(links * RANK, width))


@njit(cache=True)
def _kernel_terms(corners, normal, target):
    """Over the edge midpoints x of a triangle (a rule exact for quadratics): the means of
    ``k`` and ``k (x - target)`` with ``k = max(0, cos) / |target - x|**3``, cos against ``normal``."""
    out = np.zeros(4)
    for q in range(3):
        x = 0.5 * (corners[q] + corners[(q + 1) % 3])
        to = target - x
        r2 = to[0] * to[0] + to[1] * to[1] + to[2] * to[2]
        if r2 <= 0.0:
            continue
        cos = (normal[0] * to[0] + normal[1] * to[1] + normal[2] * to[2]) / np.sqrt(r2)
        if cos > 0.0:
            k = cos / (r2 * np.sqrt(r2)) / 3.0
            out[0] -= k * to[0]
            out[1] -= k * to[1]
            out[2] -= k * to[2]
            out[3] += k
    return out


@njit(cache=True)
def _receiver_terms(corners, element, normals, triangle, c_S, link):
    """(m, 4): the mean over a receiver's points x of ``max(0, cos_r) / (pi |c_S - x|**3) [x - c_S, 1]``,
    ``cos_r`` towards the source's centre. With :func:`_source_terms` the dot product is
    ``cos_r A_s w_s N_s . (x - x_s) / (pi |c_S - x|**3)``: the source's cosine towards this very
    receiver (linear in x), so a receiver near the source's plane sees it at its own grazing angle."""
    m = len(element)
    out = np.empty((m, 4))
    for i in range(m):
        out[i] = _kernel_terms(corners[element[i]], normals[triangle[i]], c_S[link[i]]) / np.pi
    return out


@njit(cache=True)
def _source_terms(corners, normals, areas, triangle, c_R, c_S, link):
    """(m, 4): ``A_s`` times the mean over a source's points q facing the receiver's centre of
    ``(d / |c_R - q|)**3 [N_s, N_s . (c_S - q)]``, d the centres' distance (the distance to this
    source point, exact where the receiver is at its centre)."""
    m = len(triangle)
    out = np.zeros((m, 4))
    for i in range(m):
        t, l = triangle[i], link[i]
        n = normals[t]
        dv = c_R[l] - c_S[l]
        d = np.sqrt(dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2])
        for q in range(3):
            x = 0.5 * (corners[t, q] + corners[t, (q + 1) % 3])
            to = c_R[l] - x
            r2 = to[0] * to[0] + to[1] * to[1] + to[2] * to[2]
            if r2 <= 0.0 or n[0] * to[0] + n[1] * to[1] + n[2] * to[2] <= 0.0:
                continue
            w = areas[t] * (d / np.sqrt(r2)) ** 3 / 3.0
            out[i, 0] += w * n[0]
            out[i, 1] += w * n[1]
            out[i, 2] += w * n[2]
            out[i, 3] += w * (n[0] * (c_S[l, 0] - x[0]) + n[1] * (c_S[l, 1] - x[1]) + n[2] * (c_S[l, 2] - x[2]))
    return out


def member_pairs(tree, scene, links, pairs=MEMBER_PAIRS):
    """``(link, recv, src)``: ``pairs`` member pairs per cluster link, each drawn in proportion to
    what it carries (``A_r A_s`` times each one's kernel mean towards the other node's centre)
    from a hash of the link's nodes; links that carry nothing (no member faces the other node)
    get none."""
    n = len(links)
    recv_link, recv = tree.members(links.R)
    src_link, src = tree.members(links.S)
    c, V, N_ = tree.centre, scene.patch_vertices, scene.normals
    wr = scene.areas[recv] * _kernel_mean(V[recv], N_[recv], c[links.S][recv_link])
    ws = scene.areas[src] * _kernel_mean(V[src], N_[src], c[links.R][src_link])
    live = (np.bincount(recv_link, wr, minlength=n) > 0) & (np.bincount(src_link, ws, minlength=n) > 0)
    out_link, out_r, out_s = [], [], []
    for k in range(pairs):
        r = _draw(recv_link, recv, wr, n, _uniform(links.R, links.S, 2 * k))
        s = _draw(src_link, src, ws, n, _uniform(links.R, links.S, 2 * k + 1))
        out_link.append(np.flatnonzero(live)), out_r.append(r[live]), out_s.append(s[live])
    return tuple(np.concatenate(x).astype(np.int64) for x in (out_link, out_r, out_s))


def _square(v):
    return np.einsum("...c,...c->...", v, v)


def _kernel_mean(corners, normals, target):
    """Mean of ``max(0, cos) / r**2`` from ``target`` over each triangle ``corners`` (m, 3, 3) (its
    edge midpoints), ``cos`` against the triangle's normal."""
    to = target[:, None, :] - 0.5 * (corners + np.roll(corners, -1, axis=1))
    r2 = _square(to)
    cos = np.einsum("mc,mqc->mq", normals, to) / np.sqrt(np.where(r2 > 0, r2, 1.0))
    return (np.maximum(cos, 0.0) / np.where(r2 > 0, r2, np.inf)).mean(axis=1)


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
