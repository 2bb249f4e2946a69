"""The shared definitions every layer relies on: records, widths, the exact predicate, samples."""

import numpy as np
import pytest

from blockray.errors import ParameterError
from blockray.exact import blocked_block, blocked_reference, blocked_tests, orient3d, patch_normals, block_terms
from blockray.params import BoardParams, Widths
from blockray.records import patch_layout, pack, unpack, pack_array, pack_bytes, unpack_array, patch_columns
from blockray.samples import SampleScheme


@pytest.mark.parametrize("bits", [4, 12, 20])
def test_pack_matches_amaranth_const(bits):
    seed = 1000 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    layout = patch_layout(bits)
    w = Widths(bits)
    assert layout.size == 9 * bits + 3 * w.cross
    for _ in range(50):
        v = rng.integers(0, 1 << bits, (3, 3))
        n = rng.integers(-(1 << (w.cross - 1)), 1 << (w.cross - 1), 3)
        value = {f"v{k}": dict(zip("xyz", map(int, v[k]))) for k in range(3)}
        value["normal"] = dict(zip("xyz", map(int, n)))
        bits_int = pack(layout, value)
        assert bits_int == layout.const(value).as_bits()
        assert unpack(layout, bits_int) == value
        words = pack_array(layout, patch_columns(v[None], n[None]))
        assert words == [bits_int]
        cols = unpack_array(layout, words)
        assert cols[("normal", "x")][0] == n[0]


@pytest.mark.parametrize("bits", [4, 12, 20])
def test_pack_bytes_are_the_amaranth_const_bits(bits):
    """Bulk packing, signed normals included, against ``layout.const`` record by record."""
    seed = 2000 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    layout, w = patch_layout(bits), Widths(bits)
    v = rng.integers(0, 1 << bits, (40, 3, 3))
    n = rng.integers(-(1 << (w.cross - 1)), 1 << (w.cross - 1), (40, 3))
    got = pack_bytes(layout, patch_columns(v, n), chunk=16)
    for k in range(40):
        value = {f"v{j}": dict(zip("xyz", map(int, v[k, j]))) for j in range(3)}
        value["normal"] = dict(zip("xyz", map(int, n[k])))
        assert bytes(got[k]) == layout.const(value).as_bits().to_bytes(got.shape[1], "little")


def test_blocked_tests_is_the_reference_test_by_test():
    seed = 31
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    P, Q = rng.integers(0, 64, (3000, 3)), rng.integers(0, 64, (3000, 3))
    V = rng.integers(0, 64, (3000, 3, 3))
    got = blocked_tests(P, Q, V, patch_normals(V), chunk=700)
    want = [blocked_reference(P[i], Q[i], *V[i]) for i in range(3000)]
    assert got.tolist() == want and 0 < got.sum() < 3000


def test_pack_rejects_out_of_range():
    with pytest.raises(ValueError, match="v0.x"):
        pack(patch_layout(4),
             {"v0": {"x": 16, "y": 0, "z": 0}, "v1": {"x": 0, "y": 0, "z": 0},
              "v2": {"x": 0, "y": 0, "z": 0}, "normal": {"x": 0, "y": 0, "z": 0}})


@pytest.mark.parametrize("bad", [dict(rows=0), dict(bits=3), dict(bits=21), dict(cols=1.5), dict(boards=True)])
def test_board_params_validated(bad):
    name = next(iter(bad))
    with pytest.raises(ParameterError, match=name):
        BoardParams(**bad)


def test_widths_bound_orient3d_at_cube_corners():
    # |orient3d| <= 2 L**3 < 2**(3B+1): reached by the largest tetrahedron in the cube
    bits = 10
    L = (1 << bits) - 1
    corners = [(x, y, z) for x in (0, L) for y in (0, L) for z in (0, L)]
    best = max(abs(orient3d(a, b, c, d)) for a in corners for b in corners for c in corners for d in corners[:1])
    assert best == 2 * L ** 3
    assert best < 1 << (Widths(bits).orient - 1)


@pytest.mark.parametrize("bits", [6, 16, 20])
def test_block_predicate_equals_reference(bits):
    seed = 2000 + bits
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    top = 1 << bits
    V = rng.integers(0, top, (40, 3, 3))
    # some degenerate and some axis-aligned patches
    V[0, 2] = V[0, 1]
    V[1, :, 2] = V[1, 0, 2]
    P = rng.integers(0, top, (5, 3))
    Q = rng.integers(0, top, (4, 3))
    got = blocked_block(P, Q, V, patch_normals(V))
    for r in range(4):
        for s in range(5):
            for t in range(40):
                assert got[r, s, t] == blocked_reference(P[s], Q[r], *V[t]), (r, s, t)


def test_block_terms_fit_their_widths():
    bits = 20
    L = (1 << bits) - 1
    w = Widths(bits)
    V = np.array([[[0, 0, 0], [L, 0, 0], [0, L, 0]], [[L, L, L], [0, L, 0], [L, 0, L]]])
    P = np.array([[0, 0, L], [L, L, 0]])
    Q = np.array([[L, L, L], [0, 0, 0]])
    pP, pQ, sides = block_terms(P, Q, V, patch_normals(V))
    for x in (pP, pQ, sides):
        assert int(np.abs(x).max()) < 1 << (w.orient - 1)
    assert int(np.abs(patch_normals(V)).max()) < 1 << (w.cross - 1)


@pytest.mark.parametrize("count", [1, 4, 8, 9, 16])
def test_samples_lie_exactly_on_their_patch(count):
    seed = 3000 + count
    print(f"seed={seed}")
    scheme = SampleScheme(count)
    rng = np.random.default_rng(seed)
    D = scheme.denominator
    V = rng.integers(0, 1000, (20, 3, 3)) * D
    pts = scheme.points_int(V)
    cen = scheme.centroids_int(V)
    for t in range(20):
        for k in range(count):
            assert orient3d(V[t, 0], V[t, 1], V[t, 2], pts[t, k]) == 0
        assert orient3d(V[t, 0], V[t, 1], V[t, 2], cen[t]) == 0
    # strictly inside: positive barycentric weights
    assert (scheme.weights > 0).all() and (scheme.weights.sum(axis=1) == D).all()
    assert len({tuple(w) for w in scheme.weights}) == count


@pytest.mark.parametrize("count", [1, 4, 8, 9, 16, 36, 37, 64])
def test_samples_keep_off_the_grid_a_scene_is_drawn_on(count):
    """Issue 17's tie rays: sample points in ninths sat on the contact lines of a scene drawn on a
    decimal grid (room: 0.45 m panels, shelves at 1.40 m). No sample point of a triangle cut from an
    axis-parallel rectangle with integer corners lies on an integer plane across the rectangle,
    for any side lengths not a multiple of p (docs: blockray/samples.py)."""
    seed = 3100 + count
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    scheme = SampleScheme(count)
    p, D, W = scheme.prime, scheme.denominator, scheme.weights
    assert p >= 7 and all(p % d for d in range(2, p)) and D == 3 * p
    assert (W % p != 0).all() and (W.sum(axis=1) == D).all()
    assert (scheme.centroid_weights * 3 == D).all()
    checked = 0
    for _ in range(300):
        x0, y0 = rng.integers(-1000, 1000, 2)
        L, H = rng.integers(1, 600, 2)
        if L % p == 0 or H % p == 0:
            continue
        corners = np.array([(x0, y0), (x0 + L, y0), (x0 + L, y0 + H), (x0, y0 + H)])
        for tri in ((0, 1, 2), (0, 2, 3), (1, 2, 3), (1, 3, 0)):
            for turn in range(3):                   # every vertex order the scene could give
                V = corners[np.roll(tri, turn)]
                num = W @ V                         # D x each sample point, exact integers
                assert (num % D != 0).all(), (V.tolist(), W.tolist())
                checked += 1
    assert checked > 2000


def test_sample_scheme_validated():
    with pytest.raises(ParameterError, match="samples"):
        SampleScheme(0)
