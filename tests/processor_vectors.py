"""Test vectors for the intersection processor, shared by the Amaranth and cocotb tests.

Vectors come in blocks, the way the board sees them: S shooters x R receivers x N patches, and
the expected bits are :func:`blockray.exact.blocked_block` of the whole block (the contract),
flattened in (receiver, shooter, patch) order. ``hard_cases`` builds the degenerate geometry
(cube corners at 0 and 2**B - 1, shared edges and vertices, rays in a plane, zero-area patches,
coarse-grid coincidences); ``random_tests`` mixes uniform and crossing-heavy random blocks.
"""

import numpy as np

from blockray.exact import blocked_block, blocked_reference, blocked_tests, patch_normals
from blockray.filtered import filtered_tests
from blockray.records import pack_array, pack_bytes, patch_columns, point_columns
from blockray.rtl.processor import TAG_BITS, query_layout


class Tests:
    """Flat arrays of T tests: shooters P (T,3), receivers Q (T,3), vertices V (T,3,3),
    normals n (T,3), expected blocked (T,) bool."""

    def __init__(self, P, Q, V, n, blocked):
        self.P, self.Q, self.V, self.n, self.blocked = P, Q, V, n, blocked

    def __len__(self):
        return len(self.blocked)

    def __add__(self, other):
        return Tests(*(np.concatenate([a, b]) for a, b in zip(self._arrays(), other._arrays())))

    def __getitem__(self, index):
        return Tests(*(a[index] for a in self._arrays()))

    def _arrays(self):
        return self.P, self.Q, self.V, self.n, self.blocked

    def words(self, bits):
        """Packed :func:`~blockray.rtl.processor.query_layout` payloads; tag = index mod 2**16."""
        return pack_array(query_layout(bits), self._columns())

    def payload_bytes(self, bits):
        """:meth:`words` as bytes, (T, ceil(width / 8)) uint8, least significant first."""
        return pack_bytes(query_layout(bits), self._columns())

    def _columns(self):
        columns = {}
        for prefix, pts in (("shooter", self.P), ("receiver", self.Q)):
            columns.update({(prefix, *k): v for k, v in point_columns(pts).items()})
        columns.update({("patch", *k): v for k, v in patch_columns(self.V, self.n).items()})
        columns[("tag",)] = np.arange(len(self)) % (1 << TAG_BITS)
        return columns


def block(shooters, receivers, vertices):
    """All (receiver, shooter, patch) tests of one block with their expected bits."""
    P, Q, V = (np.asarray(a, dtype=np.int64) for a in (shooters, receivers, vertices))
    n = patch_normals(V)
    expected = blocked_block(P, Q, V, n)                      # (R, S, N)
    r, s, t = (i.ravel() for i in np.indices(expected.shape))
    return Tests(P[s], Q[r], V[t], n[t], expected.ravel())


def _concat(blocks):
    out = blocks[0]
    for b in blocks[1:]:
        out = out + b
    return out


def hard_cases(bits):
    """Deterministic degenerate geometry for coordinate width ``bits``."""
    L = (1 << bits) - 1
    h = L // 2
    blocks = []

    # 1. cube corners: extreme magnitudes (|orient3d| up to 2 L**3), coplanar and zero-area
    #    triangles (repeated / collinear corners), segments along edges and faces of the cube.
    corners = np.array([[x, y, z] for x in (0, L) for y in (0, L) for z in (0, L)])
    triples = [(a, b, c) for a in range(8) for b in range(8) for c in range(8) if a < b < c]
    triples += [(0, 0, 7), (1, 6, 1), (3, 3, 3), (0, 7, 0)]            # zero area
    blocks.append(block(corners, corners, corners[np.array(triples)]))

    # 2. fans sharing a vertex C and edges C-A_i, planar and folded; rays through C, through
    #    edge midpoints, and along the fan's plane.
    c = np.array([h, h, h])
    r = max(2, L // 4) & ~1                                               # even: midpoints exact
    ring = np.array([[r, 0, 0], [0, r, 0], [-r, 0, 0], [0, -r, 0]])
    for lift in (0, r // 2):
        rim = c + ring + np.array([0, 0, lift]) * (np.arange(4) % 2)[:, None]
        fan = np.array([[c, rim[i], rim[(i + 1) % 4]] for i in range(4)])
        mids = [(c + rim[i]) // 2 for i in range(4)] + [(rim[i] + rim[(i + 1) % 4]) // 2 for i in range(4)]
        through = [c] + mids
        offsets = np.array([[1, 2, 3], [-2, 1, 4], [3, -1, -2], [0, 0, 5], [r // 2, r // 3, r // 2]])
        shooters, receivers = [], []
        for m_ in through:
            for o in offsets:
                shooters.append(m_ + o)
                receivers.append(m_ - o)                                   # P, Q symmetric about m_
        inplane = [c + np.array([r, r // 2, 0]), c - np.array([r, r // 3, 0])]
        blocks.append(block(np.array(shooters + inplane[:1]), np.array(receivers + inplane[1:]), fan))

    # 3. rays in a plane and points on the patch (own patch, vertices, edges).
    tri = np.array([[[0, 0, h], [L, 0, h], [0, L, h]], [[0, 0, 0], [L, L, L], [L, 0, 0]]])
    pts = np.array([[0, 0, h], [L // 3, L // 3, h], [L, 0, h], [h, h, h], [1, 1, h], [0, L, h],
                    [L, L, L], [0, 0, 0], [h, h, 0], [h, h, L], [L, L, 0]])
    blocks.append(block(pts, pts, tri))

    # 4. coarse grid: many coincidences (collinear, coplanar, shared edges) by construction.
    g = np.array([0, 1, h, L - 1, L])
    rng = np.random.default_rng(bits)
    for _ in range(4):
        blocks.append(block(rng.choice(g, (6, 3)), rng.choice(g, (6, 3)), rng.choice(g, (12, 3, 3))))
    return _concat(blocks)


def random_tests(bits, count, rng, shooters=4, receivers=4, patches=8):
    """At least ``count`` random tests in blocks: uniform, and 'slab' blocks (shooters below,
    receivers above, large patches in between) where about half the rays are blocked."""
    L = (1 << bits) - 1
    per = shooters * receivers * patches
    blocks = []
    for b in range(-(-count // per)):
        if b % 2 == 0:
            P = rng.integers(0, L + 1, (shooters, 3))
            Q = rng.integers(0, L + 1, (receivers, 3))
            V = rng.integers(0, L + 1, (patches, 3, 3))
        else:
            lo, hi = L // 3, 2 * L // 3
            P = rng.integers(0, L + 1, (shooters, 3)); P[:, 2] = rng.integers(0, lo + 1, shooters)
            Q = rng.integers(0, L + 1, (receivers, 3)); Q[:, 2] = rng.integers(hi, L + 1, receivers)
            V = rng.integers(0, L + 1, (patches, 3, 3)); V[:, :, 2] = rng.integers(lo, hi + 1, (patches, 3))
            axes = rng.permutation(3)
            P, Q, V = P[:, axes], Q[:, axes], V[:, :, axes]
        blocks.append(block(P, Q, V))
    tests = _concat(blocks)
    return tests[rng.permutation(len(tests))[:count]]


def random_flat(bits, count, rng):
    """``count`` independent random tests, drawn in bulk: half uniform in the cube of 2**B (about
    9 % blocked), half 'slab' tests (shooter below, receiver above, the patch between, axes
    permuted; about 14 % blocked); expected bits by :func:`~blockray.exact.blocked_tests`."""
    L = (1 << bits) - 1
    P, Q = rng.integers(0, L + 1, (count, 3)), rng.integers(0, L + 1, (count, 3))
    V = rng.integers(0, L + 1, (count, 3, 3))
    slab = np.flatnonzero(np.arange(count) % 2 == 1)
    lo, hi = L // 3, 2 * L // 3
    P[slab, 2] = rng.integers(0, lo + 1, len(slab))
    Q[slab, 2] = rng.integers(hi, L + 1, len(slab))
    V[slab, :, 2] = rng.integers(lo, hi + 1, (len(slab), 3))
    axes = np.argsort(rng.random((len(slab), 3)), axis=1)          # a permutation per test
    P[slab], Q[slab] = np.take_along_axis(P[slab], axes, 1), np.take_along_axis(Q[slab], axes, 1)
    V[slab] = np.take_along_axis(V[slab], axes[:, None, :], 2)
    n = patch_normals(V)
    return Tests(P, Q, V, n, blocked_tests(P, Q, V, n))


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def near_degenerate(bits, count, rng):
    """``count`` blocks (P (2, 3), Q (2, 3), V (4, 3, 3)) whose rays pass through a vertex, an edge
    point or the plane of the first patch (the others share its edges), drawn in [0, 1]**3, then
    rotated, scaled and translated and rounded to the B-bit grid (so the coincidences are
    rounded, not exact)."""
    L = (1 << bits) - 1
    for _ in range(count):
        V = rng.random((3, 3))
        t = rng.choice([0.0, 0.5, rng.random()])
        X = V[0] + t * (V[1] - V[0]) if rng.random() < 0.7 else V.mean(axis=0)
        d = rng.normal(size=3)
        P = X - rng.uniform(0.05, 1, (2, 1)) * d
        Q = X + rng.uniform(0.05, 1, (2, 1)) * d
        if rng.random() < 0.3:                                        # in the plane
            Q = P + np.cross(V[1] - V[0], np.cross(V[1] - V[0], V[2] - V[0]))[None] * 0.3
        fan = np.stack([V, [V[1], V[0], V[2] * 2 - V[0]], [V[0], V[2], V[1] + V[2] - V[0]], V[[2, 1, 0]]])
        points = np.concatenate([fan.reshape(-1, 3), P, Q])
        centre = points.mean(axis=0)
        points = (points - centre) @ _rotation(rng).T
        scale = rng.choice([1.0, 1e-2, 1e-4]) * L / max(1e-9, np.ptp(points))
        points = points * scale + rng.uniform(0.3, 0.7) * L
        points = np.clip(np.rint(points), 0, L).astype(np.int64)
        yield points[12:14], points[14:16], points[:12].reshape(4, 3, 3)


def check_filter_decisions(tests, fmt):
    """The filter (:func:`blockray.filtered.filtered_tests`) at ``fmt`` on :class:`Tests`: its
    decided tests agree with the expected bits (blocked_block) and, on a sample, with
    blocked_reference (Python integers); returns the undecided count."""
    decided, blocked = filtered_tests(tests.P, tests.Q, tests.V, tests.n, fmt)
    wrong = decided & (blocked != tests.blocked)
    assert not wrong.any(), f"{fmt}: {int(wrong.sum())} wrong decisions"
    for i in np.flatnonzero(decided)[::97]:                                   # the independent evaluation
        assert blocked[i] == blocked_reference(tests.P[i], tests.Q[i], *tests.V[i])
    return int((~decided).sum())
