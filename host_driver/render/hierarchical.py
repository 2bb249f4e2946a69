"""Hierarchical radiosity (Hanrahan, Salzman and Aupperle 1991) with every link's visibility
answered by the board: ``--solver hierarchical``.

**Elements.** Each input triangle is the root of a quadtree of elements (host_driver/radiosity/elements.py:
4-way midpoint subdivision, end points exact on the board's grid at one coordinate bit per level).

**Links.** A link (r <- s) carries light from source element s to receiver element r with the
unoccluded patch-to-patch factor ``F_rs`` of the two elements (the pair kernel of
host_driver/radiosity/formfactor.py, exact or certified to 1e-6) times the visible fraction ``v_rs`` the
board reports. With ``clustering`` (the default; Smits, Arvo and Greenberg 1994,
host_driver/render/clusters.py) the initial links are made top down over a tree of the input
triangles: a pair of clusters far enough apart whose power bound is under the threshold stays one
*cluster link* (a low-rank kernel over its members, its visibility from one member pair's rays),
the rest split down to pairs of input triangles, which become element links; refinement splits a
cluster link the same way once the solve's radiosity puts it over the threshold. Without, the
initial links join every pair of input triangles that can exchange light
(:func:`~blockray.host_driver.radiosity.formfactor.exchange_mask`): s**2 of them for s input triangles.

**Visibility** (``link_rays``). ``samples``: a link's K x K rays run from each of the K sample
points of its source to each of the K of its receiver, and weigh by the point-to-point kernel
``cos cos / r**2`` (0 where either end is not strictly in front of the other's plane); the visible
fraction is the weighted clear share, an estimate of the occluded over the unoccluded factor over
both elements' areas. ``spread`` (the default): a link's rays run from K / SOURCE_STEP of its
source's samples to one of its receiver's (EMITTER_ENDS to EMITTER_ENDS if the source emits),
each chosen per link (:func:`end_samples`), so a leaf's many links together still cover both
elements; a cluster link's receiver leaves take their source samples per block run instead
(:func:`source_offsets`: fuller blocks). 7x fewer rays on the room than K x K with all K source
samples, and no worse a balance; half of them again halves those rays at the same error; an
emitter's links at K x K cost cornell 2.2x the rays for the same error (docs/hierarchical.md).
``centroid``: K rays
from the source's samples to the receiver's centroid (or, where that centroid is not strictly in front of the
source's plane, from the receiver's samples to the source's centroid), the clear share of those
whose sample lies strictly in front of the far element's plane: 8x fewer rays, but the centroid
judges the whole receiver, and closed scenes gain energy where shadows cover part of a receiver.
Sample points are one fixed pattern on every element, or drawn per element (``--sample-points
draw``). The rays are grouped as the uniform render's: the rows cast from one element with the
same samples, their end points sorted by voxel, runs of at most R end points times chunks of at
most S samples, one block ray each, so every back-end of the registry answers them unchanged.

**Refinement oracle.** A link's transported power bound ``b = max_rgb B_s * F_rs * A_r`` (F
unoccluded) is compared with ``epsilon`` times the scene's emitted power ``sum_j A_j max_rgb
E_j``; links whose visibility is certain (every counted ray clear, or every one blocked) count
``b / 2``, so shadow boundaries refine first. A link over the threshold is replaced by four
links to the children of its larger element, while that element's children are at least
``min_area``. Rounds: solve, refine with that solution, cast the new links, until no link
refines. The other links of a receiver that is split move to its children (:func:`leaf_pairs`),
each cast again, so links end on leaves, each with its own rays, and a leaf's factors partition
its sources. The factors of new and moved
links are held to :func:`factor_tolerance` (absolute) where that is looser than the pair kernel's
1e-6 relative: far pairs then take a cheaper cubature whose derived bound meets it.

**Solve.** Jacobi over the links with push-pull (HSA's gathering): every element gathers
``G_p = sum_links u_r F v S_s`` (cluster links gather on the leaves directly, from their members'
``S_s``); pushing down, a leaf's radiosity is ``E + rho (G of it and its
ancestors)``; pulling up, an element's radiosity is the mean of its four children's (equal
areas), and ``S_s`` the mean of ``w B`` over its leaves. The residual is
:mod:`~blockray.host_driver.radiosity.solver`'s, on the leaves: ``sum A |B' - B| / sum A E``, RGB summed.

**Balance.** A link from a source coarser than its receiver spreads the source's mean radiosity
with the source's mean factor, so leaf l's light leaves through its ancestors' links with the
factor sum ``c_l = sum F_sr v`` (``F_sr = A_r F_rs / A_s``, s the ancestor), not the sum ``g_l``
it gathers, and absorbed minus emitted power is ``sum_l A_l B_l (c_l - 1)`` (closed scene).
:func:`transport_scales` finds receiver scales ``u`` and source scales ``w`` (Sinkhorn) with which
every leaf still gathers ``g_l`` and now shoots ``g_l``: a source of uniform radiosity delivers
what it did, and a closed scene whose leaves see a factor sum of 1 balances to the solve's
tolerance. ``--closure enforce`` takes 1 for every leaf's two sums instead (closed scenes, the
visibility estimate's own error included; refused beyond closure.MAX_CORRECTION).

**Outputs.** The leaves as a :class:`~blockray.host_driver.scene.scene.Scene` (the image, energy
balance and tests take it as any scene), and a CSV row per leaf with its input triangle and level.
"""

import functools
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ...errors import CapacityError, ParameterError, SolveError, Spelled, option
from ...exact_float import plane_signs, plane_signs_of
from ..radiosity import formfactor
from ...board import BlockBatch, BlockBits, ranges
from ..radiosity.elements import ElementPoints, children_of
from .clusters import (ClusterLinks, Transfer, build_tree, entry_keys, leaf_weights, link_clusters, power_bounds,
                       receiver_entries, source_members, split_pairs)
from ..scene.scene import Scene
from ..traverse.visibility import Phases, _morton, packed_runs, within_groups
from ..traverse.voxel import VoxelGrid
from ..traverse.cost import default_voxels

__all__ = ["Hierarchy", "Links", "LevelWarning", "render_hierarchical", "leaf_scene", "write_leaves_csv", "max_level_for",
           "CERTAIN_WEIGHT", "LEAF_COLUMNS"]

#: The scales' tolerance (largest ``|shot / target - 1|``) relative to the solve's: the power the
#: scaling leaves unbalanced stays well below what the solve's residual leaves. Only the last
#: round's scales are held to it; the rounds before (their B only decides what to refine) stop at
#: the solve's own tolerance, which saves about 20 scaling passes a round.
SCALE_TOLERANCE = 1e-2

#: The scaling stops when its residual has not halved in this many passes (a leaf whose gathered
#: and shot sums cannot both be met: in open scenes the scaling only tends to its limit).
STALL = 10

#: Steps the transport scales' Anderson acceleration remembers (0: plain Sinkhorn passes).
ANDERSON = 5

#: Share of the power bound a link of certain visibility counts in the oracle.
CERTAIN_WEIGHT = 0.5

#: A one-end link's rays (``spread``: a non-emitter's element link, a cluster link's receiver leaf)
#: start at every SOURCE_STEP-th of the source's K samples, from an offset hashed per link (an
#: element link) or chosen per block run (a cluster link's receiver leaves: :func:`source_offsets`):
#: on the room from max edge 1 at 1e-3 half the samples give the same error for half the rays.
#: Every 4th halves them again, but the visibility is then noisy enough to gain the room 0.3% of
#: energy and to put a leaf of a closed box more than closure.MAX_CORRECTION from closed
#: (docs/hierarchical.md, "Source samples").
SOURCE_STEP = 2

#: ``spread``: an emitter's link runs from EMITTER_ENDS of its source's samples to EMITTER_ENDS of
#: its receiver's (every other link ends at one). Its rays carry the first bounce: with 4 x 2 or
#: 2 x 4, a large receiver half in an emitter's shadow came out 5-7% too bright (a ratio of few
#: rays); K x K cost cornell 2.2x the rays of 4 x 4 for the same error (docs/hierarchical.md,
#: "Rays a link from an emitter").
EMITTER_ENDS = 4

#: Share of the refinement threshold a link's unoccluded factor may misplace: the absolute
#: tolerance of its ``A_r F_rs`` (:func:`factor_tolerance`).
FACTOR_SHARE = 0.1

LEAF_COLUMNS = ["leaf", "patch", "level", "group", "area", "cx", "cy", "cz", "B_r", "B_g", "B_b"]


def max_level_for(scene, min_area):
    """The deepest level whose elements are still at least ``min_area`` (None: 3 levels)."""
    if min_area is None:
        return 3
    largest = float(scene.areas.max(initial=0.0))
    if largest <= min_area:
        return 0
    return int(math.floor(math.log(largest / min_area, 4) + 1e-12))


class LevelWarning(Spelled, UserWarning):
    """The default element levels did not fit the board's bits; fewer were taken."""


@dataclass
class Hierarchy:
    """The elements: ``patch`` (input triangle), ``node`` (index in its triangle's table of
    host_driver/radiosity/elements.py), ``level``, ``parent`` (-1: a root), ``child`` (first of four
    consecutive children, -1: a leaf). Element i < N is input triangle i."""
    scene: object
    points: ElementPoints
    patch: np.ndarray = None
    node: np.ndarray = None
    level: np.ndarray = None
    parent: np.ndarray = None
    child: np.ndarray = None

    def __post_init__(self):
        N = self.scene.patches
        self.patch, self.node = np.arange(N), np.zeros(N, np.int64)
        self.level, self.parent, self.child = np.zeros(N, np.int64), np.full(N, -1), np.full(N, -1)
        self._corners = np.zeros((0, 3, 3))

    def __len__(self):
        return len(self.patch)

    @property
    def areas(self):
        return self.scene.areas[self.patch] / 4.0 ** self.level

    def vertices(self, e):
        """Float corners (M, 3, 3) of elements ``e``: computed once per element, as elements are
        only ever appended (every link's factor and kernel weights take its two elements')."""
        n = len(self._corners)
        if n < len(self):
            new = self.points.element_vertices(self.scene.patch_vertices[self.patch[n:]], self.node[n:])
            self._corners = np.concatenate([self._corners, new])
        return self._corners[e]

    def split(self, e):
        """Give the leaves among elements ``e`` their four children (appended)."""
        e = np.unique(np.asarray(e, dtype=np.int64))
        e = e[self.child[e] < 0]
        if not len(e):
            return
        first = len(self) + 4 * np.arange(len(e))
        kids = np.concatenate([children_of(n, lv) for n, lv in zip(self.node[e], self.level[e])])
        self.child[e] = first
        self.patch = np.concatenate([self.patch, np.repeat(self.patch[e], 4)])
        self.node = np.concatenate([self.node, kids])
        self.level = np.concatenate([self.level, np.repeat(self.level[e] + 1, 4)])
        self.parent = np.concatenate([self.parent, np.repeat(e, 4)])
        self.child = np.concatenate([self.child, np.full(4 * len(e), -1)])

    def leaves(self):
        return np.flatnonzero(self.child < 0)


@dataclass
class Links:
    """Links (receiver ``recv`` <- source ``src``): unoccluded factor ``F`` (from the receiver),
    visible fraction ``vis``, and ``partial`` (neither every counted ray clear nor every one
    blocked)."""
    recv: np.ndarray
    src: np.ndarray
    F: np.ndarray
    vis: np.ndarray = None
    partial: np.ndarray = None

    def __len__(self):
        return len(self.recv)

    def take(self, keep):
        return Links(self.recv[keep], self.src[keep], self.F[keep], self.vis[keep], self.partial[keep])

    @staticmethod
    def join(a, b):
        cat = np.concatenate
        return Links(cat([a.recv, b.recv]), cat([a.src, b.src]), cat([a.F, b.F]), cat([a.vis, b.vis]),
                     cat([a.partial, b.partial]))


def initial_links(scene, tolerance=0.0):
    """Every (j <- i) pair of input triangles that can exchange light, with its factor (each
    ``A_j F_ji`` within the pair kernel's relative target or the absolute ``tolerance``)."""
    cache = formfactor.PairCache(scene, tolerance=tolerance)
    recv, src, F = [], [], []
    for i in range(scene.patches):
        f = formfactor.unoccluded_factors(scene, i, cache=cache)
        j = np.flatnonzero(f > 0)
        recv.append(j), src.append(np.full(len(j), i)), F.append(f[j])
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)
    return Links(cat(recv).astype(np.int64), cat(src).astype(np.int64), cat(F).astype(np.float64))


def link_threshold(scene, epsilon):
    """The oracle's threshold: ``epsilon`` times the scene's emitted power ``sum_j A_j max_rgb E_j``."""
    return epsilon * float((scene.areas * scene.emission.max(axis=1)).sum())


def factor_tolerance(scene, threshold):
    """The absolute tolerance on a link's ``A_r F_rs``: a link moves ``B_s A_r F_rs`` of power,
    and no radiosity exceeds ``E_max / (1 - rho_max)`` (the Neumann series, factor sums at most
    1), so a factor within this moves at most ``FACTOR_SHARE`` times the power the oracle lets
    a link carry unrefined. 0 (every factor to the pair kernel's relative target) where
    ``rho_max`` is 1 or nothing emits."""
    emax, rho = float(scene.emission.max(initial=0.0)), float(scene.reflectance.max(initial=0.0))
    if emax <= 0.0 or rho >= 1.0:
        return 0.0
    return FACTOR_SHARE * threshold * (1.0 - rho) / emax


def element_factors(h, recv, src, tolerance=0.0):
    """Unoccluded ``F_rs`` of element pairs (the pair kernel, as the uniform render's), each
    ``A_r F_rs`` within the kernel's relative target or the absolute ``tolerance`` (a scalar). The
    kernel gives (r, s) and (s, r) the same bits, so a pair linked both ways is computed once."""
    if not len(recv):
        return np.zeros(0)
    recv, src = np.asarray(recv, np.int64), np.asarray(src, np.int64)
    pair, inverse = np.unique(np.minimum(recv, src) * len(h) + np.maximum(recv, src), return_inverse=True)
    a, b = pair // len(h), pair % len(h)
    return formfactor.pair_factors(h.vertices(a), h.vertices(b), tolerance=tolerance)[inverse] / h.areas[recv]


def end_samples(recv, src, K, ends):
    """(n, ends): which of the receiver's K samples the links' rays end at. All K for ``ends = K``;
    else ``ends`` evenly spaced samples from an offset hashed from the link's two elements, so the
    links of one receiver end all over it (the same on every board and Dask set)."""
    step = K // ends
    offset = ((_mix(recv, src) >> np.uint64(29)) % np.uint64(step)).astype(np.int64)
    return offset[:, None] + step * np.arange(ends)


def _mix(a, b):
    """A hash of two arrays of element ids (uint64)."""
    return ((np.asarray(a, np.uint64) * np.uint64(0x9E3779B97F4A7C15))
            ^ (np.asarray(b, np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)))


def source_offsets(caster, code, rows, step):
    """(n,): the offset of each one-end row's source samples (every ``step``-th from it), one per
    run of the ``cube`` packing (:func:`packed_runs`: by caster, then by ``code``, the Z-order code
    of the end's voxel), and a caster's runs, in an order hashed from it and their place, take the
    offsets in turn from one hashed from the caster. A block's rows then share their source
    samples, so a caster's rows do not split by offset (fewer, fuller blocks); its runs take every
    offset alike (a source whose runs drew one offset gains energy) and not in the order of their
    ends (neighbouring receivers on one part of the source put a receiver at a shadow's edge 6% too
    bright): docs/hierarchical.md, "Source samples". The runs are the ``cube`` packing's whatever
    the blocks' packing, so every packing casts the same rays; a row's samples depend on the rows
    chosen with it, not on the boards or Dask sets they are then split over."""
    order, run_start, run_len = packed_runs(code, "cube", rows, caster)
    owner = caster[order[run_start]]
    shuffled = np.lexsort((_mix(owner, _groups_rank(owner)), owner))
    turn = np.empty(len(owner), dtype=np.int64)
    turn[shuffled] = _groups_rank(owner[shuffled])
    base = ((_mix(owner, 0) >> np.uint64(29)) % np.uint64(step)).astype(np.int64)
    offset = np.empty(len(caster), dtype=np.int64)
    offset[order] = np.repeat((base + turn) % step, run_len)
    return offset


def _groups_rank(sorted_ids):
    """Each entry's place among the equal ids before it (``sorted_ids`` grouped)."""
    first = np.ones(len(sorted_ids), dtype=bool)
    first[1:] = sorted_ids[1:] != sorted_ids[:-1]
    return within_groups(first)


class LinkCaster:
    """Casts the rays of links through ``board`` as block rays (module docstring) and counts them."""

    #: links cast per board batch (bounds the host's arrays)
    CHUNK = 65536

    def __init__(self, h, board, grid, *, rows, cols, phases, link_rays="spread", packing="cube"):
        self.h, self.board, self.grid, self.rows, self.cols, self.phases = h, board, grid, rows, cols, phases
        self.link_rays, self.packing = link_rays, packing
        self.rays = self.blocks = 0

    def counters(self):
        return self.board.counters()

    def cast(self, links, ends=None, sources=None, offsets=None):
        """Set ``links.vis`` and ``links.partial`` from the board's blocked bits (``ends``: the
        receiver samples every link's rays end at, instead of :meth:`_groups`' rule; ``sources``:
        how many of the source's K samples they start at, :meth:`_sources` if None; ``offsets``:
        where each link's source samples start, -1 or None for an offset hashed per link)."""
        vis, partial = np.empty(len(links)), np.empty(len(links), dtype=bool)
        offsets = np.full(len(links), -1, dtype=np.int64) if offsets is None else offsets
        for ends, sources, which in self._plan(links, ends, sources):
            which = which[np.argsort(links.src[which], kind="stable")]     # a source's rows in one chunk: its runs
            if ends:
                fractions = functools.partial(self._sample_fractions, ends=ends, sources=sources)
                chunk = self.CHUNK // ends
            else:
                fractions, chunk = self._centroid_fractions, self.CHUNK
            for a in range(0, len(which), chunk):
                part = which[a:a + chunk]
                vis[part], partial[part] = fractions(links.recv[part], links.src[part], offsets=offsets[part])
        links.vis, links.partial = vis, partial

    def offsets(self, links, ends=None, sources=None):
        """(n,): where each link's source samples start (every K / sources-th from there) when its
        rays end at one receiver sample and start at fewer than K (:func:`source_offsets`, over
        these links together: computed before they are split over boards or Dask sets); -1 for
        the others (:func:`end_samples`' offset hashed per link)."""
        out = np.full(len(links), -1, dtype=np.int64)
        K = self.h.points.K
        for ends, sources, which in self._plan(links, ends, sources):
            if ends == 1 and sources < K:
                recv, src, pts = links.recv[which], links.src[which], self.h.points
                with self.phases.timed("commands"):
                    end = self.h.node[recv] * pts.per_element + end_samples(recv, src, K, 1)[:, 0]
                    points = self._end_points(recv, pts.weights_at(self.h.patch[recv], end))
                    out[which] = source_offsets(src, _morton(self.grid.cell_of(points)), self.rows, K // sources)
        return out

    def _plan(self, links, ends, sources):
        """``(ends, sources, links)`` per group: :meth:`_groups`, or all with ``ends``."""
        groups = self._groups(links) if ends is None else [(ends, np.arange(len(links)))]
        return [(e, (sources or self._sources(e)) if e else 0, which) for e, which in groups]

    def _sources(self, ends):
        """The source samples a link's rays start at when they end at ``ends`` receiver samples:
        all K to all K, EMITTER_ENDS to an emitter's EMITTER_ENDS, else every SOURCE_STEP-th."""
        K = self.h.points.K
        if ends == K:
            return K
        return min(EMITTER_ENDS, K) if ends > 1 else max(1, K // SOURCE_STEP)

    def _groups(self, links):
        """``(ends, links)``: the receiver samples each link's rays end at (0: the centroid rule).
        ``spread`` gives an emitter's links EMITTER_ENDS (they carry the first bounce, the most light
        a link carries, as the uniform render's ``--emitter-factor`` gives them more rows) and every
        other link one, each from :meth:`_sources` of the source's."""
        K, every = self.h.points.K, np.arange(len(links))
        if self.link_rays != "spread":
            return [(K if self.link_rays == "samples" else 0, every)]
        emits = self.h.scene.emission[self.h.patch[links.src]].max(axis=1) > 0
        return [(min(EMITTER_ENDS, K), every[emits]), (1, every[~emits])]

    def _centroid_fractions(self, recv, src, offsets=None):
        """All K source samples to the receiver's centroid (``offsets`` unused: no sample is left
        out; taken so both fraction rules share :meth:`cast`'s one call)."""
        h, pts = self.h, self.h.points
        V, K = h.scene.patch_vertices, pts.K
        with self.phases.timed("formfactor"):
            # forward (source samples -> receiver centroid) where that centroid is in front of the source
            ahead = plane_signs(V[h.patch[src]], V[h.patch[recv]], pts.centres[h.node[recv]]) > 0
            caster, target = np.where(ahead, src, recv), np.where(ahead, recv, src)
            counts = self._in_front(target, caster, self._sample_weights(caster))
        every = np.broadcast_to(np.arange(K), (len(caster), K))
        clear = self._clear(caster, target, pts.centres[h.node[target]], every)
        counted = np.where(counts.any(axis=1, keepdims=True), counts, True)
        n_clear = (clear & counted).sum(axis=1)
        n = counted.sum(axis=1)
        return n_clear / n, (n_clear > 0) & (n_clear < n)

    def _sample_fractions(self, recv, src, ends, sources, offsets):
        """``sources`` x ``ends`` rays per link, ``sources`` of the source's K samples (all, or evenly
        spaced from ``offsets`` (:meth:`offsets`) or, where that is -1, a hashed offset:
        :func:`end_samples` with the ends swapped) to ``ends`` of the
        receiver's K samples (:func:`end_samples`), each weighed by the point-to-point kernel
        ``cos cos / r**2`` (0 where either end is not strictly in front of the other's plane): the
        weighted clear share is the ratio of the occluded to the unoccluded factor, over both
        elements' areas. (One end point at
        the receiver's centroid judges the whole receiver by it: a receiver partly in shadow whose
        centroid is lit counts both the light the shadow hides and the occluder's face the shadowed
        part sees, and closed scenes gain energy.)"""
        h, K, n = self.h, self.h.points.K, len(recv)
        with self.phases.timed("formfactor"):
            take = end_samples(src, recv, K, sources)
            given = offsets >= 0
            take[given] = offsets[given, None] + K // sources * np.arange(sources)
            ws = np.take_along_axis(self._sample_weights(src), take[:, :, None], axis=1)
            wr = np.take_along_axis(self._sample_weights(recv), end_samples(recv, src, K, ends)[:, :, None], axis=1)
            # (n, end, sample): both ends strictly in front of the other element's plane
            lit = self._in_front(recv, src, ws)[:, None, :] & self._in_front(src, recv, wr)[:, :, None]
            d = self._points(recv, wr)[:, :, None] - self._points(src, ws)[:, None]
            r2 = np.einsum("...c,...c->...", d, d)
            ns, nr = h.scene.normals[h.patch[src]], h.scene.normals[h.patch[recv]]
            cos_s = np.einsum("nc,nekc->nek", ns, d)
            cos_r = -np.einsum("nc,nekc->nek", nr, d)
            weight = np.where(lit, np.abs(cos_s * cos_r) / np.maximum(r2, 1e-300) ** 2, 0.0)
        clear = self._clear(np.repeat(src, ends), np.repeat(recv, ends), wr.reshape(-1, 3),
                            np.repeat(take, ends, axis=0)).reshape(n, ends, sources)
        total = weight.sum(axis=(1, 2))
        plain = clear.mean(axis=(1, 2))
        frac = np.where(total > 0, (weight * clear).sum(axis=(1, 2)) / np.where(total > 0, total, 1), plain)
        counted = np.where(total[:, None, None] > 0, weight > 0, True)
        return frac, (clear & counted).any(axis=(1, 2)) & (~clear & counted).any(axis=(1, 2))

    def _sample_weights(self, e):
        """(n, K, 3) weights of the K samples of elements ``e`` on their input triangles."""
        return self.h.points.element_samples(self.h.patch[e], self.h.node[e])

    def _in_front(self, plane, points, w):
        """(n, k) bool: point j of element ``points[m]`` (weights ``w[m, j]``) lies strictly in front
        of ``plane[m]``'s plane."""
        patch = self.h.patch
        return plane_signs_of(self.h.scene.patch_vertices, patch[plane], patch[points], w) > 0

    def _points(self, e, w):
        """(n, K, 3) float points of weights ``w`` (n, K, 3) on the input triangles of elements ``e``."""
        V = self.h.scene.patch_vertices[self.h.patch[e]]
        return np.matmul(w / float(self.h.points.denominator), V)     # batched: 6x einsum's speed here

    def _clear(self, caster, target, end_w, take):
        """(n, k) bool: ray j of row m (sample ``take[m, j]`` of ``caster[m]`` to the point of weights
        ``end_w[m]`` (over the table's denominator) on ``target[m]``'s input triangle) is clear."""
        batch, row_link, col_j = self._blocks(caster, target, end_w, take)
        with self.phases.timed("board"):
            bits = self.board.run(batch)
        flat = bits.flat if isinstance(bits, BlockBits) else np.concatenate(
            [np.asarray(b, dtype=bool).ravel() for b in bits] or [np.zeros(0, bool)])
        rb, cb = batch.rows, batch.cols
        block = np.repeat(np.arange(len(batch)), rb * cb)
        t = np.arange(len(flat)) - batch.ray_off[block]
        clear = np.zeros(take.shape, dtype=bool)
        clear[row_link[batch.row_off[block] + t // cb[block]], col_j[batch.col_off[block] + t % cb[block]]] = ~flat
        self.rays += batch.rays
        self.blocks += len(batch)
        return clear

    def _end_points(self, target, end_w):
        """(n, 3) float end points of weights ``end_w`` (n, 3) on elements ``target``."""
        V = self.h.scene.patch_vertices[self.h.patch[target]]
        return np.einsum("np,npc->nc", end_w / float(self.h.points.denominator), V)

    def _blocks(self, caster, target, end_w, take):
        """The block rays of the rows (caster samples ``take[m]`` -> its end point): the rows grouped
        by caster and samples taken, then packed by their ends' voxels (``packing``,
        :func:`~blockray.host_driver.traverse.visibility.packed_runs`) into runs of at most R, times
        chunks of at most S of the samples. Returns the BlockBatch, the row of each block row and the
        position in ``take`` of each column."""
        h, pts, grid = self.h, self.h.points, self.grid
        V, k = h.scene.patch_vertices, take.shape[1]
        with self.phases.timed("commands"):
            ends = self._end_points(target, end_w)
            cell = grid.cell_of(ends)
            voxel = grid.index_of(cell) if self.packing == "voxel" else _morton(cell)
            # evenly spaced samples: the first names them all
            order, run_start, run_len = packed_runs(voxel, self.packing, self.rows, caster, take[:, 0])
            chunk_start = np.arange(0, k, self.cols)
            chunk_len = np.minimum(self.cols, k - chunk_start)
            rows, cols = np.repeat(run_len, len(chunk_start)), np.tile(chunk_len, len(run_start))
            row_link = order[ranges(np.repeat(run_start, len(chunk_start)), rows)]
            col_j = ranges(np.tile(chunk_start, len(run_start)), cols)
            col_row = np.repeat(np.repeat(order[run_start], len(chunk_start)), cols)     # a row of the column's run
            col_elem = caster[col_row]
            shooter_patch = h.patch[col_elem]
            shooter_point = h.node[col_elem] * pts.per_element + take[col_row, col_j]
            receiver_patch, receiver_weights = h.patch[target[row_link]], end_w[row_link]
            row_off = np.concatenate([[0], np.cumsum(rows)])
            col_off = np.concatenate([[0], np.cumsum(cols)])
            starts = pts.point(V[shooter_patch], shooter_patch, shooter_point)
        with self.phases.timed("traverse"):
            vox, vox_off, _, _ = grid.traverse_blocks(starts, col_off, ends[row_link], row_off, nonempty_only=True)
        batch = BlockBatch(shooter_patch, shooter_point, col_off, receiver_patch, row_off, vox, vox_off,
                           receiver_weights)
        return batch, row_link, col_j


class SetCaster:
    """:class:`LinkCaster` on ``options.run.sets`` host + board sets of a Dask cluster (``cluster``
    = ``(client, threads)``): the links split by their receiver's input triangle, the input
    triangles cut into runs of equal count in Z-order of their centroids' voxels (scaleout.assign_sets),
    each set casting its share on its own board (:func:`cast_on_set`). A ray's blocked bit does not
    depend on the block it travels in, so the fractions equal one set's bit for bit."""

    def __init__(self, cluster, h, board, grid, options, phases):
        from ..cluster.cluster import SetJob, _hold
        from ..cluster.scaleout import assign_sets
        b, ray = options.board, options.ray
        (self.client, threads), self.h, self.phases = cluster, h, phases
        params = getattr(board, "params", None) or b.params
        quantised = getattr(board, "quantised", None)
        self.job = SetJob(board=b.backend, params=params if quantised is None else params.with_(bits=quantised.bits),
                          partition=b.partition, samples=ray.samples, traversal=ray.traversal, packing=options.packing,
                          stats_fraction=ray.stats_fraction, threads=threads, link_rays=options.solve.link_rays)
        self.owner = assign_sets(_morton(grid.cell_of(h.scene.centroids)), options.run.sets)
        self.scene_f, self.grid_f = _hold(self.client, h.scene), _hold(self.client, grid)
        # source offsets over all the links cast together, as one LinkCaster's
        self.plan = LinkCaster(h, None, grid, rows=params.rows, cols=params.cols, phases=phases,
                               link_rays=options.solve.link_rays, packing=options.packing)
        self.offsets = self.plan.offsets
        self.rays = self.blocks = 0
        self.per_set = [{"rays": 0, "blocks": 0, "counters": {}} for _ in range(options.run.sets)]

    def cast(self, links, ends=None, sources=None, offsets=None):
        from ..cluster.cluster import _results
        h, sets = self.h, len(self.per_set)
        part = self.owner[h.patch[links.recv]]
        mine = [np.flatnonzero(part == k) for k in range(sets)]
        with self.phases.timed("cluster"):
            futures = [self.client.submit(cast_on_set, self.scene_f, self.grid_f, self.job, h.points.max_level,
                                          h.patch, h.node, links.recv[m], links.src[m], ends, sources,
                                          None if offsets is None else offsets[m],
                                          pure=False)
                       for m in mine]
            answers = _results(self.client, futures)
        links.vis, links.partial = np.empty(len(links)), np.empty(len(links), dtype=bool)
        for m, (vis, partial, rays, blocks, counters), total in zip(mine, answers, self.per_set):
            links.vis[m], links.partial[m] = vis, partial
            total["rays"] += rays
            total["blocks"] += blocks
            for key, value in counters.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    total["counters"][key] = total["counters"].get(key, 0) + value
        self.rays, self.blocks = sum(t["rays"] for t in self.per_set), sum(t["blocks"] for t in self.per_set)

    def counters(self):
        from ..cluster.scaleout import combine_counters
        out = combine_counters(self.owner, self.per_set, self.job.params.processors * self.job.params.boards)
        out.pop("utilization", None)
        return out


def cast_on_set(scene, grid, job, max_level, patch, node, recv, src, ends=None, sources=None, offsets=None):
    """On a worker: the links ``(recv <- src)`` of one set cast on its own board (built, given the
    element points to ``max_level``, loaded with the grid) with rays ``job.link_rays`` (``ends``,
    ``sources``, ``offsets``: :meth:`LinkCaster.cast`'s): ``(vis, partial, rays, blocks, counters)``."""
    from ..board.backends import make_board
    from ...threads import available, set_threads
    if job.threads is not None:
        set_threads(min(job.threads, available()))
    board = make_board(job.board, job.params, partition=job.partition)
    try:
        points = ElementPoints(job.samples, max_level)
        board.prepare(scene, points)
        board.load(grid)
        h = Hierarchy(scene, points)
        h.patch, h.node = patch, node
        caster = LinkCaster(h, board, grid, rows=job.params.rows, cols=job.params.cols, phases=Phases(),
                            link_rays=job.link_rays, packing=job.packing)
        links = Links(recv, src, np.zeros(len(recv)))
        if len(links):
            caster.cast(links, ends, sources, offsets)
        else:
            links.vis, links.partial = np.zeros(0), np.zeros(0, dtype=bool)
        return links.vis, links.partial, caster.rays, caster.blocks, board.counters()
    finally:
        if hasattr(board, "close"):
            board.close()


def refine(h, links, B, threshold, min_area, max_level):
    """Split the links whose oracle exceeds ``threshold`` (module docstring), splitting elements as
    needed: ``(recv, src, kept)``, the new links' ends (factors not computed, not cast) and the
    links kept."""
    A = h.areas
    bound = B[links.src].max(axis=1) * links.F * A[links.recv]
    bound = np.where(links.partial, bound, CERTAIN_WEIGHT * bound)
    can = lambda e: (h.level[e] < max_level) & (A[e] / 4 >= min_area)
    larger_recv = A[links.recv] >= A[links.src]
    first, second = np.where(larger_recv, links.recv, links.src), np.where(larger_recv, links.src, links.recv)
    split_recv = np.where(can(first), larger_recv, ~larger_recv)
    chosen = (bound > threshold) & (can(first) | can(second))
    e = np.where(split_recv, links.recv, links.src)[chosen]
    h.split(e)
    kids = (h.child[e][:, None] + np.arange(4)).ravel()
    recv = np.where(np.repeat(split_recv[chosen], 4), kids, np.repeat(links.recv[chosen], 4))
    src = np.where(np.repeat(split_recv[chosen], 4), np.repeat(links.src[chosen], 4), kids)
    return recv, src, links.take(~chosen)


def leaf_pairs(h, recv, src):
    """The pairs ``(recv, src)`` with every receiver that has children replaced by the leaves below
    it, each with the same source. A link ends on a leaf, with its own unoccluded factor and its
    own rays (a parent's visible fraction is not its children's: a shadow may cover one child and
    miss the next), so a leaf's links partition its sources: the unoccluded factors of a leaf in a
    closed scene sum to 1 (not so with the ancestors' averages, which a leaf gathering through its
    ancestors' links would mix)."""
    leaf_recv, leaf_src = [], []
    while len(recv):
        leaf = h.child[recv] < 0
        leaf_recv.append(recv[leaf])
        leaf_src.append(src[leaf])
        recv, src = (h.child[recv[~leaf]][:, None] + np.arange(4)).ravel(), np.repeat(src[~leaf], 4)
    return np.concatenate(leaf_recv + [recv]), np.concatenate(leaf_src + [src])


def level_steps(h):
    """``(down, up)``: the elements of levels 1.. (top first), for pushing to children, and the
    inner elements of levels ..0 (deepest first), for pulling from them."""
    depth = int(h.level.max(initial=0))
    down = [np.flatnonzero(h.level == lv) for lv in range(1, depth + 1)]
    up = [np.flatnonzero((h.level == lv) & (h.child >= 0)) for lv in range(depth - 1, -1, -1)]
    return down, up


def pull_means(h, x, up):
    """``x`` (leaves set) with every inner element the mean of its four equal children (in place)."""
    for idx in up:
        x[idx] = sum(x[h.child[idx] + c] for c in range(4)) / 4
    return x


def push_sums(h, x, down):
    """``x`` with every element's value plus its ancestors' (in place)."""
    for idx in down:
        x[idx] += x[h.parent[idx]]
    return x


def shooter_sums(h, links, u, down, transfer=None):
    """Per element: ``sum F_sr v u_r`` over the links whose source is it or an ancestor, the share
    of a leaf's light its ancestors' links deliver (``F_sr = A_r F_rs / A_s``); cluster links
    (``transfer``) shoot from input triangles to their receivers' leaves."""
    A = h.areas
    share = u[links.recv] * A[links.recv] * links.F * links.vis / A[links.src]
    x = np.bincount(links.src, share, minlength=len(h)).astype(np.float64)
    if transfer is not None:
        N = h.scene.patches
        x[:N] += transfer.shoot(u * A) / A[:N]
    return push_sums(h, x, down)


def cluster_gathered(h, transfer, x):
    """Per element: what the cluster links (``transfer``, or None) gather on the leaves from ``x``
    (per element, every input triangle its leaves' mean)."""
    if transfer is None:
        return np.zeros((len(h),) + x.shape[1:])
    return transfer.gather(x[:h.scene.patches])


def cluster_transfer(tree, h, clinks):
    """The cluster links' :class:`~.clusters.Transfer` onto the current leaves (None: no links)."""
    if not len(clinks):
        return None
    leaves = h.leaves()
    return Transfer(tree, h.scene, clinks, leaves=(leaves, h.patch[leaves], h.vertices(leaves)), size=len(h))


def transport_scales(h, links, *, transfer=None, closed=False, tolerance=1e-14, max_iterations=200, start=None):
    """Receiver scales ``u`` and source scales ``w`` (per element; used on the leaves) with which
    every leaf gathers and shoots the same factor sum (module docstring, "Balance"): its own
    gathered sum ``g = sum F v``; ``closed``: 1 (0 where a leaf that gathers sees nothing).
    Leaves of zero reflectance gather nothing, so only ``closed`` sets what they shoot. Cluster
    links (``transfer``) count in both sums, scaled as element links are. ``start``: ``(u, w)`` to
    start from (the last round's: most leaves keep theirs, so a round takes fewer passes).
    Alternating Sinkhorn scaling, the source scales' steps Anderson-accelerated; returns ``(u, w,
    info)``."""
    down, up = level_steps(h)
    leaves, n = h.leaves(), len(h)
    Fv = links.F * links.vis
    g = (np.bincount(links.recv, Fv, minlength=n) + cluster_gathered(h, transfer, np.ones(n)))[leaves]
    gathers = (h.scene.reflectance[h.patch[leaves]] > 0).any(axis=1)
    target = np.where(gathers, g > 0, 1.0) if closed else g
    u, w = (np.ones(n), np.ones(n)) if start is None else (start[0].copy(), start[1].copy())
    gathered = target if closed else g
    raw = shooter_sums(h, links, np.ones(n), down, transfer)[leaves]
    fitted = (raw > 0) & (gathers | closed)

    def rows():
        mean = pull_means(h, w.copy(), up)
        rows = np.bincount(links.recv, Fv * mean[links.src], minlength=n) + cluster_gathered(h, transfer, mean)
        return rows[leaves]
    history, mix = [], Anderson()
    scaled = fitted & (target > 0) & (w[leaves] > 0)        # w stays positive there: log scale
    for it in range(1, max_iterations + 1):
        R = rows()
        u[leaves] = np.divide(gathered, R, out=np.ones_like(R), where=R > 0)
        shot = w[leaves] * shooter_sums(h, links, u, down, transfer)[leaves]
        ratio = np.divide(target, shot, out=np.ones_like(shot), where=fitted & (shot > 0))
        w[leaves[~scaled]] *= ratio[~scaled]        # w *= ratio; on the scaled leaves accelerated
        w[leaves[scaled]] = np.exp(mix.step(np.log(w[leaves[scaled]]), np.log(ratio[scaled])))
        history.append(float(np.abs(ratio - 1).max(initial=0.0)))
        if history[-1] <= tolerance or (it > STALL and history[-1] > 0.5 * history[-1 - STALL]):
            break                           # converged, or a leaf's sums cannot both be met (open scenes)
    residual = history[-1]
    R = rows()                              # rows exact for the final w: a uniform source delivers g
    u[leaves] = np.divide(gathered, R, out=np.ones_like(R), where=R > 0)
    live = gathers & (g > 0) & (raw > 0)
    info = {"iterations": it, "residual": residual, "tolerance": tolerance, "raw_shooter_sum": _range(raw[live] / g[live] - 1),
            "receiver_scale": _range(u[leaves]), "source_scale": _range(w[leaves]), "closed": bool(closed)}
    if closed:
        seen = gathers & (g > 0)
        info["closure_change"] = float(np.abs(g[seen] - 1).max(initial=0.0))
    return u, w, info


class Anderson:
    """Anderson acceleration (Walker and Ni 2011) of a fixed-point iteration ``x <- x + f``: the
    next ``x`` from the last :data:`ANDERSON` steps' ``x`` and ``f`` (least squares), restarted
    when ``f`` grows or the extrapolation strays more than 1 from the plain step ``x + f``. On
    the room's transport scales it halves the passes (from max edge 1 at 1e-3: 59 to 30 over the
    five solves, the same B to 1e-8)."""

    def __init__(self, memory=None):
        self.memory, self.xs, self.fs = ANDERSON if memory is None else memory, [], []

    def step(self, x, f):
        if self.fs and np.abs(f).max(initial=0.0) > np.abs(self.fs[-1]).max(initial=0.0):
            self.xs, self.fs = [], []
        self.xs, self.fs = (self.xs + [x])[-self.memory - 1:], (self.fs + [f])[-self.memory - 1:]
        if len(self.xs) < 2:
            return x + f
        dX, dF = (np.diff(np.stack(v, axis=1), axis=1) for v in (self.xs, self.fs))
        with np.errstate(all="ignore"):
            mixed = x + f - (dX + dF) @ np.linalg.lstsq(dF, f, rcond=None)[0]
        if not np.isfinite(mixed).all() or np.abs(mixed - x - f).max(initial=0.0) > 1.0:
            self.xs, self.fs = [x], [f]     # an extrapolation past a factor e of the plain step: not trusted
            return x + f
        return mixed


def check_closed(info):
    """Raise ParameterError (naming ``--closure``) where :func:`transport_scales` closed the
    scene's leaves by more than closure.MAX_CORRECTION, or could not."""
    from ..radiosity.closure import MAX_CORRECTION
    if info["closure_change"] > MAX_CORRECTION or info["residual"] > info["tolerance"]:
        raise ParameterError(f"{option('closure')} enforce: a leaf gathers a factor sum {info['closure_change']:.3g} from 1 "
                             f"(at most {MAX_CORRECTION:g}; scaling residual {info['residual']:.3g}); the scene is not "
                             f"closed, or its visibility too coarse to enforce", parameter="closure")


def _range(x):
    return [float(x.min(initial=np.inf)), float(x.max(initial=-np.inf))] if len(x) else [0.0, 0.0]


def solve_links(h, links, B, scales, *, tolerance, max_iterations, transfer=None):
    """Jacobi sweeps with push-pull from ``B`` (every element's radiosity, (M, 3)) over the links
    and the cluster links (``transfer``) scaled by ``scales = (u, w)`` (:func:`transport_scales`):
    ``(B, sweeps, residual, history)``, B the iterate whose residual is reported (as
    solver.jacobi_sweeps)."""
    scene = h.scene
    E, rho, A = scene.emission[h.patch], scene.reflectance[h.patch], h.areas
    leaves = h.leaves()
    down, up = level_steps(h)
    u, w = scales
    weight = links.F * links.vis * u[links.recv]
    emitted = float((A[leaves, None] * E[leaves]).sum())
    history = []
    for sweep in range(max_iterations + 1):
        shot = pull_means(h, w[:, None] * B, up)   # each leaf's light as its ancestors' links shoot it
        G = np.stack([np.bincount(links.recv, weight * shot[links.src, c], minlength=len(h)) for c in range(3)],
                     axis=1).astype(np.float64)
        push_sums(h, G, down)                      # a leaf gathers through its ancestors' links too
        if transfer is not None:
            G[leaves] += u[leaves, None] * cluster_gathered(h, transfer, shot)[leaves]
        new = np.empty_like(B)
        new[leaves] = E[leaves] + rho[leaves] * G[leaves]
        pull_means(h, new, up)                     # an element's radiosity: the mean of its leaves'
        change = float((A[leaves, None] * np.abs(new[leaves] - B[leaves])).sum())
        res = change / emitted if emitted else (0.0 if change == 0 else float("inf"))
        history.append(res)
        if not (np.isfinite(res) and res <= 2.0 * history[0]):
            raise SolveError(f"solve diverged: the hierarchical residual grew from {history[0]:.3g} to {res:.3g} "
                             f"after {sweep} sweeps (link factors wrong?)")
        if res < tolerance or sweep == max_iterations:
            return B, sweep, res, history
        B = new


@dataclass
class HierarchicalResult:
    """What :func:`render_hierarchical` gives back: the leaves as a scene and their radiosity,
    the solve's numbers and the report's keys."""
    leaves: Scene
    radiosity: np.ndarray
    hierarchy: Hierarchy
    links: Links
    residual: float
    iterations: int
    history: list = field(default_factory=list)
    balance: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)
    cluster_links: ClusterLinks = None
    tree: object = None


def prepare_board(scene, board, ray, solve, phases):
    """Give ``board`` the scene with the element points as its samples and the voxel grid:
    ``(points, grid, voxels)``. Without ``min_area`` the elements go 3 levels deep, or as deep as
    the board's bits hold (a LevelWarning says so); a ``min_area`` whose levels the bits cannot
    hold is a CapacityError naming it."""
    levels = max_level_for(scene, solve.min_area)
    with phases.timed("prepare"):
        while True:
            points = ElementPoints(ray.samples, levels)
            try:
                board.prepare(scene, points)
                break
            except CapacityError as e:
                if not levels:
                    raise
                if solve.min_area is not None:
                    raise CapacityError(f"{e.spelled(option)}; {levels} of them are the element levels "
                                        f"{option('min_area')} asks for (one bit each): use a larger "
                                        f"{option('min_area')}") from None
                levels -= 1
    if levels < max_level_for(scene, solve.min_area):
        warnings.warn(LevelWarning(f"{levels} element levels below each input triangle, not "
                                   f"{max_level_for(scene, None)}: the scene's vertices leave the board's bits no "
                                   f"more (give {option('min_area')} to choose)"))
    voxels = ray.voxels or default_voxels(scene.patches, parallelism=1)
    with phases.timed("voxelise"):
        grid = VoxelGrid(scene.patch_vertices, voxels, margin=board.margin)
    with phases.timed("load"):
        board.load(grid)
    return points, grid, voxels


def solve_state(h, links, clinks, B, scales, rounds, sweeps, solved):
    """What the rounds need to continue after a solve (a checkpoint): the elements, the links and
    cluster links, every element's B and transport scales, the rounds and sweeps done, and that
    solve's residual history and balance."""
    res, history, balance = solved
    arrays = dict(patch=h.patch, node=h.node, level=h.level, parent=h.parent, child=h.child, recv=links.recv,
                  src=links.src, F=links.F, vis=links.vis, partial=links.partial, B=B,
                  history=np.array(history, dtype=np.float64), cluster_R=clinks.R, cluster_S=clinks.S,
                  cluster_vis=clinks.vis, cluster_partial=clinks.partial, cluster_rkey=clinks.rkey,
                  cluster_rvis=clinks.rvis, u=scales[0], w=scales[1])
    return {"solver": "hierarchical", "shots": 0, "iterations": int(sweeps), "rounds": int(rounds),
            "residual": float(res), "balance": balance, "arrays": arrays}


def _restore(state, scene, points):
    """:func:`solve_state`'s ``state`` back as ``(h, links, clinks, B, scales, rounds, sweeps, solved)``."""
    a = state["arrays"]
    h = Hierarchy(scene, points)
    h.patch, h.node, h.level, h.parent, h.child = (np.array(a[k]) for k in ("patch", "node", "level", "parent", "child"))
    links = Links(*(np.array(a[k]) for k in ("recv", "src", "F", "vis", "partial")))
    clinks = ClusterLinks(*(np.array(a[f"cluster_{k}"]) for k in ("R", "S", "vis", "partial", "rkey", "rvis")))
    solved = (float(state["residual"]), list(a["history"]), dict(state["balance"]))
    scales = (np.array(a["u"]), np.array(a["w"]))
    return h, links, clinks, np.array(a["B"]), scales, int(state["rounds"]), int(state["iterations"]), solved


def first_radiosity(scene):
    """Per input triangle, a guess of its largest radiosity before any solve: its emission plus
    its reflectance times the mean irradiance of a closed scene after one bounce (the emitted
    power over the scene's area); refinement corrects it after each solve."""
    A = scene.areas
    mean = float((A * scene.emission.max(axis=1)).sum()) / max(float(A.sum()), 1e-300)
    return scene.emission.max(axis=1) + scene.reflectance.max(axis=1) * mean


def initial_links_clustered(h, tree, threshold, tolerance):
    """The initial element links and cluster links (uncast), linked top down from (every triangle <-
    every triangle) (clusters.link_clusters)."""
    R, S, recv, src = link_clusters(tree, [0], [0], tree.maxima(first_radiosity(h.scene)), threshold)
    F = element_factors(h, recv, src, tolerance)
    return Links(recv[F > 0], src[F > 0], F[F > 0]), ClusterLinks(R, S)


def cast_clusters(caster, tree, clinks, known=None):
    """Set ``clinks.rvis`` (each receiver leaf's visible fraction: clusters.receiver_entries on the
    current leaves), ``rkey``, ``vis`` (the leaves' fractions weighted by what each can receive) and
    ``partial``. An entry of ``known`` (cluster links cast before) keeps its fraction; the others
    get the rays of the element link to the leaf from the link's drawn source member
    (clusters.source_members). Leaves that face away, and links whose source members all do,
    carry nothing and count as clear."""
    h, n = caster.h, len(clinks)
    if not n:
        empty = ClusterLinks.empty()
        clinks.vis, clinks.partial, clinks.rkey, clinks.rvis = empty.vis, empty.partial, empty.rkey, empty.rvis
        return
    with caster.phases.timed("formfactor"):      # the entries, their kernel weights and draws
        leaves = h.leaves()
        _, link, leaf = receiver_entries(tree, clinks, (leaves, h.patch[leaves]), h.scene.patches)
        element = leaves[leaf]
        key = entry_keys(tree, clinks, link, element)
        found, theirs = _known_entries(known, key, len(h), clinks.origin, link, element, h.child < 0)
        rvis, weight, fresh = np.ones(len(key)), np.empty(len(key)), ~found
        if len(theirs):
            rvis[found] = known.rvis[theirs]
        if len(theirs) and known.rweight is not None:        # kept entries keep their weights
            weight[found] = known.rweight[theirs]
        else:
            fresh[:] = True
        weight[fresh] = leaf_weights(tree, h.scene, clinks, link[fresh], h.vertices(element[fresh]),
                                     h.patch[element[fresh]], h.areas[element[fresh]])
        src, need = np.full(len(key), -1), np.unique(link[~found])     # draws only for links with new entries
        drawn = np.full(n, -1)
        drawn[need] = source_members(tree, h.scene, ClusterLinks(clinks.R[need], clinks.S[need]))
        src[~found] = drawn[link[~found]]
    cast = np.flatnonzero(~found & (src >= 0) & (weight > 0))
    if len(cast):
        pairs = Links(element[cast], src[cast], np.zeros(len(cast)))
        # a receiver leaf's rays (the link's light is spread over its leaves), a member's samples per block run
        caster.cast(pairs, ends=1, offsets=caster.offsets(pairs, 1))
        rvis[cast] = pairs.vis
    total = np.bincount(link, weight, minlength=n)
    clinks.vis = np.where(total > 0, np.bincount(link, weight * rvis, minlength=n) / np.where(total > 0, total, 1), 1.0)
    some = lambda x: np.bincount(link, (weight > 0) & x, minlength=n) > 0
    clinks.partial = some(rvis < 1) & some(rvis > 0)
    clinks.rkey, clinks.rvis, clinks.rweight, clinks.rlink, clinks.rsize = key, rvis, weight, link, len(h)


def _known_entries(known, key, elements, origin=None, link=None, element=None, leaf=None):
    """``(found, theirs)``: which entries ``key`` (clusters.entry_keys; element ids below
    ``elements``) ``known`` (cast cluster links, or None) holds, and where in its entries.
    ``origin`` (each link's index in ``known``, -1 if new), the entries' ``link`` and ``element``
    and the current ``leaf`` mask find them in order (:func:`_kept_entries`); otherwise, or if
    that does not hold, by their keys."""
    found, none = np.zeros(len(key), dtype=bool), np.zeros(0, dtype=np.int64)
    if known is None or known.rkey is None or not len(known.rkey) or not len(key):
        return found, none
    if origin is not None and known.rlink is not None:
        kept = _kept_entries(known, key, origin, link, element, leaf)
        if kept is not None:
            return kept
    flat = lambda k: k[:, 0] * np.int64(elements) + k[:, 1]     # one int64 while it cannot overflow
    if max(int(known.rkey[:, 0].max()), int(key[:, 0].max())) >= (1 << 62) // max(elements, 1):
        raise CapacityError(f"{len(known.rkey)} cluster link entries over {elements} elements overflow their keys")
    theirs, mine = flat(known.rkey), flat(key)
    order, by_key = np.argsort(theirs), np.argsort(mine)       # both sorted: the search runs in order
    at = np.minimum(np.searchsorted(theirs[order], mine[by_key]), len(order) - 1)     # keys are unique
    found[by_key] = theirs[order[at]] == mine[by_key]
    where = np.empty(len(key), dtype=np.int64)
    where[by_key] = order[at]
    return found, where[found]


def _kept_entries(known, key, origin, link, element, leaf):
    """:func:`_known_entries` without a search: a kept link's entries that were cast before are
    its receiver leaves that existed then (elements are only appended, and a leaf that existed
    was a leaf then), in the same order, and ``known``'s entries that stay are those of kept
    links whose element is still a leaf. None where the two do not pair up key for key."""
    was_kept = np.zeros(len(known), dtype=bool)
    was_kept[origin[origin >= 0]] = True
    theirs = np.flatnonzero(was_kept[known.rlink] & leaf[known.rkey[:, 1]])
    found = (origin[link] >= 0) & (element < known.rsize)
    if len(theirs) != found.sum() or not (known.rkey[theirs] == key[found]).all():
        return None
    return found, theirs


def refine_clusters(tree, h, clinks, B, threshold):
    """The cluster links whose power bound (``CERTAIN_WEIGHT`` of it where visibility is certain)
    exceeds ``threshold`` under the solve's ``B``, relinked from their child pairs:
    ``(recv, src, kept, new)``, the input triangle pairs that became element links (factors not
    computed), the cluster links kept, and the new ones (not cast)."""
    if tree is None or not len(clinks):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), clinks, ClusterLinks.empty()
    source_max = tree.maxima(B[:h.scene.patches].max(axis=1))
    bound = power_bounds(tree, clinks.R, clinks.S, source_max)
    over = np.where(clinks.partial, bound, CERTAIN_WEIGHT * bound) > threshold
    R, S = clinks.R[over], clinks.S[over]
    both = tree.leaf[R] & tree.leaf[S]
    kid_R, kid_S = split_pairs(tree, R[~both], S[~both])
    new_R, new_S, recv, src = link_clusters(tree, kid_R, kid_S, source_max, threshold)
    recv = np.concatenate([tree.order[tree.start[R[both]]], recv])
    src = np.concatenate([tree.order[tree.start[S[both]]], src])
    return recv, src, clinks.take(~over), ClusterLinks(new_R, new_S)


def solve_round(tree, h, links, clinks, B, scales, solve, *, final, transfer=None):
    """One round's transport scales and Jacobi sweeps, each started from the last round's:
    ``(B, scales, sweeps, (residual, history, balance), transfer)``. The scales stop at the
    solve's tolerance, or ``final`` at :data:`SCALE_TOLERANCE` times it. ``transfer``: the cluster
    links' tables if already built for these links and leaves."""
    transfer = transfer or cluster_transfer(tree, h, clinks)
    u, w, balance = transport_scales(h, links, transfer=transfer, closed=solve.closure == "enforce",
                                     tolerance=(SCALE_TOLERANCE if final else 1.0) * solve.tolerance, start=scales)
    B, done, res, history = solve_links(h, links, B, (u, w), tolerance=solve.tolerance,
                                        max_iterations=solve.max_iterations, transfer=transfer)
    return B, (u, w), done, (res, history, balance), transfer


def render_hierarchical(scene, board, options, *, phases=None, checkpoint=None, resume=None, cluster=None):
    """``--solver hierarchical`` on a built ``board`` (see the module docstring). ``checkpoint``:
    called with :func:`solve_state` after every round's solve; ``resume``: such a state to
    continue from (the same CSV, bit for bit, as a render never stopped). ``cluster``: a Dask
    ``(client, threads)`` whose ``options.run.sets`` sets cast the links (:class:`SetCaster`)."""
    solve, ray = options.solve, options.ray
    params = getattr(board, "params", None) or options.board.params
    phases = phases or Phases()
    t0, c0 = time.perf_counter(), time.process_time()
    min_area = 0.0 if solve.min_area is None else solve.min_area
    points, grid, voxels = prepare_board(scene, board, ray, solve, phases)
    if cluster is None:
        make_caster = lambda h: LinkCaster(h, board, grid, rows=params.rows, cols=params.cols, phases=phases,
                                           link_rays=solve.link_rays, packing=options.packing)
    else:
        make_caster = lambda h: SetCaster(cluster, h, board, grid, options, phases)
    threshold = link_threshold(scene, solve.epsilon)
    tolerance = factor_tolerance(scene, threshold)
    with phases.timed("formfactor"):
        tree = build_tree(scene) if solve.clustering else None
    if resume is None:
        h = Hierarchy(scene, points)
        caster = make_caster(h)
        with phases.timed("formfactor"):
            if tree is None:
                links, clinks = initial_links(scene, tolerance), ClusterLinks.empty()
            else:
                links, clinks = initial_links_clustered(h, tree, threshold, tolerance)
        caster.cast(links)
        cast_clusters(caster, tree, clinks)
        B, scales, rounds, sweeps, solved = np.array(scene.emission, dtype=np.float64), None, 0, 0, None
    else:
        h, links, clinks, B, scales, rounds, sweeps, solved = _restore(resume, scene, points)
        caster = make_caster(h)
    transfer = None                        # the cluster tables of the last round's solve
    while True:
        if solved is None:
            with phases.timed("solve"):
                B, scales, done, solved, transfer = solve_round(tree, h, links, clinks, B, scales, solve, final=False)
            sweeps += done
            if checkpoint is not None:
                checkpoint(solve_state(h, links, clinks, B, scales, rounds, sweeps, solved))
        solved = None
        with phases.timed("formfactor"):
            recv, src, kept = refine(h, links, B, threshold, min_area, points.max_level)
            c_recv, c_src, c_kept, c_new = refine_clusters(tree, h, clinks, B, threshold)
        if not (len(recv) or len(c_recv) or len(c_new)):
            break
        rounds += 1
        inherit = lambda x: np.concatenate([x, x[h.parent[len(x):]]])     # new elements start as their parent
        B, scales = inherit(B), tuple(inherit(x) for x in scales)
        with phases.timed("formfactor"):
            # the new links and those of receivers split this round, down to the leaves
            down = h.child[kept.recv] >= 0
            recv, src = leaf_pairs(h, np.concatenate([kept.recv[down], recv, c_recv]),
                                   np.concatenate([kept.src[down], src, c_src]))
            F = element_factors(h, recv, src, tolerance)
            new = Links(recv[F > 0], src[F > 0], F[F > 0])
        caster.cast(new)
        links, known, clinks = Links.join(kept.take(~down), new), clinks, ClusterLinks.join(c_kept, c_new)
        cast_clusters(caster, tree, clinks, known)
    with phases.timed("solve"):             # the last round's scales and B to the full tolerances
        B, scales, done, (res, history, balance), _ = solve_round(tree, h, links, clinks, B, scales, solve,
                                                                  final=True, transfer=transfer)
    sweeps += done
    if solve.closure == "enforce":
        check_closed(balance)
    leaves = h.leaves()
    out = leaf_scene(h, leaves)
    result = HierarchicalResult(out, B[leaves], h, links, res, sweeps, history, balance, cluster_links=clinks,
                                tree=tree)
    result.report = _report(result, board, options, caster, rounds, voxels, phases, t0, c0)
    return result


def _report(result, board, options, caster, rounds, voxels, phases, t0, c0):
    """The ``--report`` keys of a hierarchical render (the board's counters last, never overriding)."""
    from ..radiosity.closure import absorbed_balance
    from .options import estimator_of
    h, solve, scene = result.hierarchy, options.solve, result.hierarchy.scene
    leaves = h.leaves()
    counters = caster.counters()
    with np.errstate(divide="ignore", invalid="ignore"):
        balance = absorbed_balance(result.leaves, result.radiosity)
    report = {
        "scene": scene.name, "source": scene.source, "patches": int(scene.patches), "solver": "hierarchical",
        "board": board.name, "samples": options.ray.samples.count, "voxels": int(voxels),
        "estimator": estimator_of(options.ray), "packing": options.packing, "epsilon": solve.epsilon,
        "min_area": solve.min_area, "link_rays": solve.link_rays, "clustering": solve.clustering,
        "max_level": h.points.max_level,
        "tolerance": solve.tolerance, "links": len(result.links), "leaves": int(len(leaves)),
        "cluster_links": len(result.cluster_links), "clusters": 0 if result.tree is None else len(result.tree),
        "elements": int(len(h)), "elements_per_level": np.bincount(h.level).tolist(),
        "leaves_per_level": np.bincount(h.level[leaves], minlength=h.points.max_level + 1).tolist(),
        "refinement_rounds": int(rounds), "iterations": int(result.iterations), "shots": 0,
        "residual": float(result.residual), "rays": int(caster.rays), "blocks": int(caster.blocks),
        "tests": int(counters.get("tests", 0)),
        "absorbed_balance": [float(b) if np.isfinite(b) else None for b in balance],
        "transport_balance": result.balance,
        "factor_tolerance": factor_tolerance(scene, link_threshold(scene, solve.epsilon)),
    }
    for name, times in (("seconds", phases.seconds), ("cpu_seconds", phases.cpu)):
        report[name] = dict(times)
    report["seconds"]["total"] = time.perf_counter() - t0
    report["cpu_seconds"]["total"] = time.process_time() - c0
    report.update({k: v for k, v in counters.items() if k not in report})
    return report


def leaf_scene(h, leaves):
    """The leaf elements ``leaves`` as a :class:`Scene` (each its own three vertices), their
    material and group their input triangle's."""
    scene, p = h.scene, h.patch[leaves]
    return Scene(name=scene.name, vertices=h.vertices(leaves).reshape(-1, 3),
                 triangles=np.arange(3 * len(leaves)).reshape(-1, 3), reflectance=scene.reflectance[p],
                 emission=scene.emission[p], group=scene.group[p], group_names=list(scene.group_names),
                 camera=scene.camera, source=scene.source)


def write_leaves_csv(path, result, outputs=None):
    """One row per leaf: ``leaf,patch,level,group,area,cx,cy,cz,B_r,B_g,B_b`` (``patch``: its
    input triangle)."""
    import csv
    from ...atomic import write_file
    from ...errors import printable
    h, leaves, B = result.hierarchy, result.hierarchy.leaves(), result.radiosity
    bad = np.flatnonzero(~np.isfinite(B).all(axis=1))
    if len(bad):
        raise SolveError(f"{option('patches')} {printable(path, 200)}: leaf {int(bad[0])}'s radiosity is "
                         f"{B[bad[0]].tolist()}; not written")
    out = result.leaves

    def write(f):
        w = csv.writer(f)
        w.writerow(LEAF_COLUMNS)
        for m, e in enumerate(leaves):
            g = out.group_names[out.group[m]] if out.group_names else str(out.group[m])
            w.writerow([m, int(h.patch[e]), int(h.level[e]), g, repr(float(out.areas[m])),
                        *(repr(float(x)) for x in out.centroids[m]), *(repr(float(x)) for x in B[m])])
    write_file(path, "--patches", write, outputs=outputs)
