"""The integer block traverse (blockray/block_walk.py through host_driver/traverse/board_walk.py) against an oracle sharing no
code with it: a closed segment against every closed voxel box by the slab method in exact
fractions (Python ``Fraction``), its entry time giving the walk's order.

Rays are drawn so that their end points often lie on grid planes, lines and corners (coordinates
that are multiples of the voxel edge, or one off), with axes held fixed (axis-parallel rays,
rays inside a plane or along a grid line) and zero-length rays; hypothesis draws more. The
conservativeness test takes the board's own exact predicate (``blocked_reference``) as "hits".
"""

import random
from fractions import Fraction
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, seed, settings, strategies as st

from blockray.errors import ParameterError
from blockray.exact import blocked_reference
from blockray.host_driver.traverse.board_walk import LatticeGrid, lattice_shift

BITS = 12


def _entry(p, q, lo, hi):
    """The first t in [0, 1] at which p + t (q - p) lies in the closed box [lo, hi], or None."""
    t0, t1 = Fraction(0), Fraction(1)
    for c in range(3):
        d = q[c] - p[c]
        if d == 0:
            if not lo[c] <= p[c] <= hi[c]:
                return None
            continue
        a, b = Fraction(lo[c] - p[c], d), Fraction(hi[c] - p[c], d)
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    return t0 if t0 <= t1 else None


def _oracle(p, q, origin, edge, v):
    """The voxels whose closed box the closed segment touches, ordered by (entry time, index)."""
    found = []
    for ix in range(v):
        for iy in range(v):
            for iz in range(v):
                lo = [origin[c] + i * edge for c, i in enumerate((ix, iy, iz))]
                t = _entry(p, q, lo, [x + edge for x in lo])
                if t is not None:
                    found.append((t, (ix * v + iy) * v + iz))
    return [i for _, i in sorted(found)]


def _grid(vertices, shift, v, origin=(0, 0, 0)):
    q = SimpleNamespace(bits=BITS, vertices=np.asarray(vertices, dtype=np.int64).reshape(-1, 3, 3))
    return LatticeGrid(q, shift=shift, v=v, origin=origin)


def _coordinate(rng, origin, edge, v):
    """A coordinate inside the grid, on a plane or next to one half of the time."""
    k = rng.randrange(v + 1)
    pick = rng.random()
    x = origin + k * edge + (0 if pick < 0.4 else rng.choice((-1, 1)) if pick < 0.55 else rng.randrange(edge))
    return min(max(x, origin), origin + v * edge)


def _ray(rng, origin, edge, v):
    p = [_coordinate(rng, origin[c], edge, v) for c in range(3)]
    q = [_coordinate(rng, origin[c], edge, v) for c in range(3)]
    shape = rng.random()
    if shape < 0.1:
        q = list(p)                                             # zero length
    elif shape < 0.5:
        for c in rng.sample(range(3), rng.choice((1, 2))):      # axis-parallel, in a plane, on a line
            q[c] = p[c]
    return p, q


@pytest.mark.parametrize("shift,v,origin", [(2, 5, (0, 0, 0)), (0, 4, (3, 1, 2)), (3, 3, (5, 0, 9))])
def test_ray_voxels_are_the_touched_boxes_in_entry_order(rng_seed, shift, v, origin):
    rng = random.Random(rng_seed)
    grid = _grid(np.zeros((0, 3, 3)), shift, v, origin)
    for _ in range(400):
        p, q = _ray(rng, origin, 1 << shift, v)
        assert grid.ray_voxels(p, q).tolist() == _oracle(p, q, origin, 1 << shift, v), (p, q)


_point = st.tuples(*[st.integers(0, 12)] * 3)


@seed(31)
@settings(max_examples=300, deadline=None)
@given(p=_point, q=_point)
def test_ray_voxels_hypothesis(p, q):
    grid = _grid(np.zeros((0, 3, 3)), 2, 3)
    assert grid.ray_voxels(p, q).tolist() == _oracle(p, q, (0, 0, 0), 4, 3)


def test_corners_and_lines_by_hand():
    """Cases counted by hand on a 3^3 grid of edge 4."""
    grid = _grid(np.zeros((0, 3, 3)), 2, 3)
    assert len(grid.ray_voxels((4, 4, 4), (4, 4, 4))) == 8                  # a point on a corner
    assert len(grid.ray_voxels((4, 4, 0), (4, 4, 12))) == 12                # along a grid line: 4 x 3
    assert len(grid.ray_voxels((0, 0, 0), (12, 12, 12))) == 1 + 7 + 7       # the diagonal: 2^3 at each inner corner
    assert len(grid.ray_voxels((1, 1, 1), (1, 1, 11))) == 3                 # axis-parallel inside


def test_block_emits_each_nonempty_voxel_once_in_ray_order(rng_seed):
    """A block's voxels: its rays row-major, each ray's in the oracle's order, a voxel at its
    first visit, empty ones skipped; visited and tests count every voxel the block touches."""
    rng = random.Random(rng_seed)
    shift, v, origin = 2, 4, (0, 0, 0)
    grid = _grid(np.zeros((0, 3, 3)), shift, v, origin)
    grid.count = np.array([rng.choice((0, 0, 1, 3)) for _ in range(v ** 3)], dtype=np.int64)
    blocks = []
    for _ in range(60):
        S, R = rng.randint(1, 3), rng.randint(1, 3)
        rays = [_ray(rng, origin, 1 << shift, v) for _ in range(max(S, R))]
        blocks.append(([p for p, _ in rays[:S]], [q for _, q in rays[:R]]))
    starts = [p for b in blocks for p in b[0]]
    ends = [q for b in blocks for q in b[1]]
    s_off = np.cumsum([0] + [len(b[0]) for b in blocks])
    e_off = np.cumsum([0] + [len(b[1]) for b in blocks])
    vox, off, visited, tests = grid.traverse_blocks(starts, s_off, ends, e_off, nonempty_only=True)
    for b, (S, R) in enumerate(blocks):
        order = []
        for q in R:
            for p in S:
                order += [i for i in _oracle(p, q, origin, 1 << shift, v) if i not in order]
        assert vox[off[b]:off[b + 1]].tolist() == [i for i in order if grid.count[i] > 0], b
        assert (visited[b], tests[b]) == (len(order), sum(grid.count[i] for i in order))


def test_every_hit_patch_is_in_a_visited_voxel(rng_seed):
    """Conservative: when the board's exact predicate blocks ray p -> q by patch n, some voxel of
    the ray holds n (random triangles and rays, many on grid planes)."""
    rng = random.Random(rng_seed)
    shift, v, origin = 3, 4, (0, 0, 0)
    edge = 1 << shift
    tri = [[[_coordinate(rng, 0, edge, v) for _ in range(3)] for _ in range(3)] for _ in range(40)]
    grid = _grid(tri, shift, v, origin)
    held = [set(grid.patches[grid.start[i]:grid.start[i] + grid.count[i]].tolist()) for i in range(v ** 3)]
    hits = 0
    for _ in range(300):
        p, q = _ray(rng, origin, edge, v)
        reached = set().union(*(held[i] for i in grid.ray_voxels(p, q)))
        for n, t in enumerate(tri):
            if blocked_reference(p, q, *t):
                hits += 1
                assert n in reached, (p, q, n)
    assert hits > 50            # the test saw enough hits to mean something
    print(f"{hits} hits")


def test_for_scene_covers_the_scene_with_a_power_of_two_edge():
    q = SimpleNamespace(bits=16, vertices=np.array([[[0, 0, 0], [65520, 0, 0], [0, 30000, 21]]]))
    grid = LatticeGrid.for_scene(q, 5)
    assert (grid.shift, grid.v) == (13, 8)              # 65520 / 5 = 13104 units: 2^13 <= 13104 < 2^14
    assert lattice_shift(65520, 5, 16) == 13 and lattice_shift(0, 5, 16) == 0 and lattice_shift(8, 1, 2) == 2


@pytest.mark.parametrize("kw", [{"shift": 13, "v": 2}, {"shift": 2.0, "v": 2}, {"shift": 2, "v": 0},
                                {"shift": 2, "v": 1}])
def test_bad_grids_are_one_error(kw):
    with pytest.raises(ParameterError):
        _grid([[[0, 0, 0], [9, 0, 0], [0, 9, 0]]], **kw)
