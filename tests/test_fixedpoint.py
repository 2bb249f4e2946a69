"""Quantisation onto the B-bit grid (blockray.fixedpoint) and the cycle contract (blockray.timing)."""

import math

import numpy as np
import pytest

from blockray.errors import CapacityError, ParameterError
from blockray.exact import orient3d
from blockray.fixedpoint import quantise, choose_bits, resolve_bits, DEFAULT_MAX_ERROR
from blockray.params import Widths
from blockray.samples import SampleScheme
from blockray.timing import BoardTiming, Op, load_commands_needed

from scenes import mesh_scene as make_scene


def random_scene(seed, n=40, scale=7.3):
    rng = np.random.default_rng(seed)
    print(f"seed={seed}")
    v = rng.random((3 * n, 3)) * scale - 2.0
    return make_scene(v, np.arange(3 * n))


@pytest.mark.parametrize("bits", [6, 10, 16, 20])
@pytest.mark.parametrize("count", [1, 4, 8, 9])
def test_grid_points_exact_and_on_plane(bits, count):
    s = SampleScheme(count)     # D = 21 fits every B here; too few bits: test_bits_too_small_for_denominator
    q = quantise(random_scene(bits * 100 + count), s, bits)
    assert q.D == s.denominator
    assert (q.vertices % q.D == 0).all()
    assert q.vertices.min() >= 0 and q.vertices.max() <= (1 << bits) - 1
    # the largest extent spans the whole lattice: nothing is wasted
    assert q.points.max() == ((1 << bits) - 1) // q.D * q.D
    w = Widths(bits)
    assert np.abs(q.normals).max() < 1 << (w.cross - 1)
    for i in range(0, len(q.vertices), 7):
        v0, v1, v2 = q.vertices[i]
        for p in list(q.shooters[i]) + [q.receivers[i]]:
            assert orient3d(v0, v1, v2, p) == 0                # exactly on the patch plane
        # the integer sample point is the same barycentric combination of the integer vertices
        expect = s.weights @ q.vertices[i].astype(object)
        assert all(int(e) == int(p) * q.D for e, p in zip(expect.ravel(), q.shooters[i].ravel()))


def test_displacement_measured_and_bounded():
    sc = random_scene(5)
    s = SampleScheme(8)
    for bits in (8, 12, 16):
        q = quantise(sc, s, bits)
        moved = np.linalg.norm(q.to_scene(q.points) - sc.vertices, axis=1)
        assert q.displacement == pytest.approx(moved.max())
        assert q.displacement <= math.sqrt(3) * q.step / 2 * (1 + 1e-12)
        assert q.end_displacement <= q.displacement * (1 + 1e-12)
        np.testing.assert_allclose(q.to_scene(q.receivers), q.to_scene(q.vertices).mean(axis=1), atol=1e-9)


def test_uniform_step_on_all_axes():
    sc = make_scene([[0, 0, 0], [10, 0, 0], [0, 1, 0], [0, 0, 0.1]], [[0, 1, 2], [0, 2, 3]])
    q = quantise(sc, SampleScheme(1), 12)
    # x spans the lattice; y and z use the same step, so 1 and 0.1 scene units keep their ratio
    assert q.points[1, 0] == 4095
    np.testing.assert_allclose(q.to_scene(q.points), sc.vertices, atol=q.step)
    assert abs(q.points[2, 1] - 409.5) <= q.D / 2


def test_collapsed_vertices_and_degenerate_patches_reported():
    # two vertices 1e-7 apart and a sliver that degenerates on a coarse grid
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1e-7, 1, 0], [0.31, 0.31, 1], [0.31, 0.31 + 1e-6, 1], [1, 1, 1]]
    sc = make_scene(v, [[0, 1, 2], [0, 1, 3], [4, 5, 6]])
    q = quantise(sc, SampleScheme(1), 8)
    groups = [sorted(g.tolist()) for g in q.collapsed]
    assert [2, 3] in groups
    assert q.degenerate.tolist() == [2]            # the sliver 4-5-6 collapses to a line
    assert q.report()["degenerate_patches"] == 1
    assert q.report()["collapsed_vertex_groups"] == len(q.collapsed) >= 1
    # duplicated float vertices (same coordinates) are not a collapse
    sc2 = make_scene([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 1, 3]])
    assert quantise(sc2, SampleScheme(1), 10).collapsed == []


def test_zero_area_triangle_is_not_degenerate_report():
    sc = make_scene([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 1, 3]])
    q = quantise(sc, SampleScheme(8), 10)
    assert q.degenerate.tolist() == []        # zero float area: nothing lost
    assert (q.normals[0] == 0).all()


def _moved(sc, q):
    """The largest vertex displacement of ``q`` recomputed from its integer points (test-side)."""
    used = np.unique(sc.triangles)
    back = q.lo + q.points[used].astype(np.float64) * q.h
    return float(np.sqrt(((back - np.asarray(sc.vertices)[used]) ** 2).sum(axis=1)).max()) / float(
        np.linalg.norm(np.ptp(np.asarray(sc.vertices)[used], axis=0)))


@pytest.mark.parametrize("scheme", ["uniform", "elements"])
def test_choose_bits_is_the_fewest_that_meet_the_bound(scheme):
    """choose_bits tests the vertex lattice alone; the full quantisation at its B and at B - 1
    (end points and all) agrees, the displacement recomputed here from the integer points."""
    from blockray.host_driver.radiosity.elements import ElementPoints
    s = SampleScheme(8) if scheme == "uniform" else ElementPoints(SampleScheme(8, seed=3), 1)
    for seed in range(3):
        sc = random_scene(seed)
        b, bound = choose_bits(sc, s)
        assert bound == DEFAULT_MAX_ERROR
        q = quantise(sc, s, b)
        assert len(q.degenerate) == 0 and q.relative_error <= DEFAULT_MAX_ERROR
        assert _moved(sc, q) == pytest.approx(q.relative_error, rel=1e-9)
        qb = quantise(sc, s, b - 1)
        assert len(qb.degenerate) > 0 or _moved(sc, qb) > DEFAULT_MAX_ERROR
        # a looser bound never needs more bits
        assert choose_bits(sc, s, max_error=1e-2)[0] <= b


def test_choose_bits_models_only_what_the_scene_needs():
    # a unit cube's corners are on every lattice: the smallest B that holds D is enough
    cube = make_scene([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)],
                      [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]])
    s = SampleScheme(8)
    assert choose_bits(cube, s) == (max(4, s.denominator.bit_length()), DEFAULT_MAX_ERROR)
    # a tiny triangle beside a huge one needs more bits than the huge one alone
    big = [[0, 0, 0], [1000, 0, 0], [0, 1000, 0]]
    tiny = [[500, 500, 1], [500.05, 500, 1], [500, 500.05, 1]]
    alone = make_scene(big + [[1000, 1000, 1000]], [[0, 1, 2]])
    both = make_scene(big + [[1000, 1000, 1000]] + tiny, [[0, 1, 2], [4, 5, 6]])
    assert choose_bits(both, s)[0] > choose_bits(alone, s)[0]


def test_finer_end_points_fall_back_to_the_looser_bound_only_when_the_default_leaves_no_bits():
    """End points 8 times finer take 3 bits. On a scene that meets the default bound at 18 bits,
    that is 21 > 20: B is then the fewest meeting FINE_POINTS_MAX_ERROR. The uniform scheme never
    falls back, and a scene meeting the default bound with the finer points keeps it."""
    from blockray.fixedpoint import FINE_POINTS_MAX_ERROR
    rng = np.random.default_rng(5)
    print("seed=5")
    v = np.concatenate([rng.random((30, 3)) * [3.7, 2.9, 2.3], [[0, 0, 0], [3.7, 2.9, 2.3]]])
    sc = make_scene(v, rng.permutation(30)[:30].reshape(-1, 3))
    base, fine = SampleScheme(8), SampleScheme(8, 8)
    b, bound = choose_bits(sc, base)
    assert bound == DEFAULT_MAX_ERROR and b + 3 > 20, b       # the finer points cannot meet the default
    bf, boundf = choose_bits(sc, fine)
    assert boundf == FINE_POINTS_MAX_ERROR
    q, below = quantise(sc, fine, bf), quantise(sc, fine, bf - 1)
    assert q.relative_error <= FINE_POINTS_MAX_ERROR < below.relative_error
    assert q.relative_error > DEFAULT_MAX_ERROR               # it really is the looser bound
    with pytest.raises(CapacityError, match="8 times finer than the sample lattice take 3 of the bits"):
        choose_bits(sc, fine, fine_points_error=DEFAULT_MAX_ERROR)
    assert resolve_bits(sc, fine).report()["max_error_bound"] == FINE_POINTS_MAX_ERROR
    cube = make_scene([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], [[0, 1, 3], [0, 3, 2]])
    assert choose_bits(cube, fine)[1] == DEFAULT_MAX_ERROR


def test_choose_bits_capacity_error():
    # a triangle 1e-9 thin in a unit scene degenerates at every B <= 20
    sc = make_scene([[0, 0, 0], [1, 0, 0], [0.5, 1e-9, 0], [0, 1, 1]], [[0, 1, 2], [0, 1, 3]])
    with pytest.raises(CapacityError, match="20"):
        choose_bits(sc, SampleScheme(8))


@pytest.mark.parametrize("bad", [3, 21, 0, -1, 16.0, "16", True])
def test_forced_bits_validated(bad):
    with pytest.raises(ParameterError, match="^bits must be an integer from 4 to 20") as e:
        resolve_bits(random_scene(0), SampleScheme(8), bad)
    assert e.value.parameter == "bits"


def test_bits_too_small_for_denominator():
    with pytest.raises(ParameterError, match="^bits 4 is too small for 64 samples") as e:
        quantise(random_scene(0), SampleScheme(64), 4)     # D = 33 > 15
    assert e.value.parameter == "bits"


def test_forced_bits_refused_when_scene_degenerates_badly():
    rng = np.random.default_rng(11)
    print("seed=11")
    # 50 small triangles in a large box: at 6 bits most of them collapse
    base = rng.random((50, 1, 3)) * 100
    tris = base + rng.random((50, 3, 3)) * 0.5
    v = np.concatenate([tris.reshape(-1, 3), [[0, 0, 0], [100, 100, 100], [0, 100, 0]]])
    t = np.concatenate([np.arange(150).reshape(-1, 3), [[150, 151, 152]]])
    sc = make_scene(v, t)
    with pytest.raises(ParameterError, match="^bits 6 is too few for scene 't': 50 of 51 patches") as e:
        resolve_bits(sc, SampleScheme(8), 6)
    assert e.value.parameter == "bits"
    q = resolve_bits(sc, SampleScheme(8), 20)
    assert q.bits == 20 and len(q.degenerate) == 0
    # the chosen B is accepted as well
    assert resolve_bits(sc, SampleScheme(8)).bits == choose_bits(sc, SampleScheme(8))[0]


def test_timing_contract():
    t = BoardTiming(processor_latency=7, memory_latency=2)
    assert t.drain_latency == 8        # memory + processor - 1: END_BLOCK starts after the last issue
    assert t.result_latency == 10      # + the result FIFO's write and output register
    assert [t.cost(op) for op in (Op.WRITE_PATCH, Op.WRITE_VOXEL, Op.BEGIN_BLOCK, Op.LOAD_RECEIVER,
                                  Op.LOAD_SHOOTER, Op.LOAD_POINTS, Op.END_BLOCK,
                                  Op.READ_COUNTERS)] == [1] * 8
    assert t.cost(Op.VOXEL, 0) == 1 and t.cost(Op.VOXEL, 5) == 5
    # BEGIN + 3 receivers and 2 shooters in two LOAD_POINTS + (4 + 1 + 2) + END; no drain
    assert t.block_cycles(3, 2, [4, 0, 2]) == 1 + 2 + 7 + 1
    assert [load_commands_needed(r, s) for r, s in ((0, 0), (1, 0), (4, 0), (3, 2), (8, 8))] == [0, 1, 1, 2, 4]
    with pytest.raises(ParameterError, match="processor_latency"):
        BoardTiming(processor_latency=-1)
