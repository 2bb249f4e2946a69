"""Visibility through a board: one shooter's column (its own rays and the reverse rays of its
straddling receivers) as one board batch, against one batch per column (the old way) and against
one ray per block."""

import numpy as np
import pytest

from blockray.host_driver.radiosity import formfactor, ray_weights
from blockray.host_driver.board.backends import make_board
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.traverse.visibility import Phases, Visibility, visible_fraction
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import TraversalStats
from blockray.params import BoardParams
from blockray.samples import SampleScheme


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell")


class Recording:
    """A model board that keeps every batch's bits."""

    def __init__(self):
        self.board = make_board("model", BoardParams(bits=None))
        self.bits = []
        run = self.board.run

        def recording_run(blocks):
            bits = run(blocks)
            self.bits.append(np.asarray(bits.flat))
            return bits
        self.board.run = recording_run


def _visibility(scene, samples, *, traversal="block", packing="voxel", voxels=6):
    rec = Recording()
    rec.board.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, voxels, margin=rec.board.margin)
    rec.board.load(grid)
    p = rec.board.params
    stats = TraversalStats(grid, sample_fraction=0.3, seed=5)
    return Visibility(scene, rec.board, grid, samples, rows=p.rows, cols=p.cols, traversal=traversal,
                      packing=packing, phases=Phases(), stats=stats), rec


def _straddled_shooters(scene, count, seed):
    """``count`` shooters drawn at random among those with receivers whose centroid is behind
    the shooter's plane (so the column has reverse rays), with their receivers."""
    rng = np.random.default_rng(seed)
    out = []
    for i in rng.permutation(scene.patches):
        receivers = np.flatnonzero(formfactor.unoccluded_factors(scene, int(i)) > 0)
        if (~ray_weights.centroid_in_front(scene, int(i), receivers)).sum() >= 2:
            out.append((int(i), receivers))
        if len(out) == count:
            return out
    raise AssertionError("cornell has no shooter with straddling receivers")


@pytest.mark.parametrize("packing", ["voxel", "fill"])
def test_a_column_in_one_batch_equals_one_batch_per_column(cornell, packing):
    # The old render cast each reverse receiver's rays as its own column and board batch. One
    # batch per shooter must give every ray the same bit, every pair the same fraction to the
    # bit, the same rays, blocks, columns, tests and traversal statistics; only the board cycles
    # drop (fewer batches, so fewer waits for the slowest board and its drain).
    scene, samples = cornell, SampleScheme(8)
    seed = 1313
    print(f"seed={seed}")
    shooters = _straddled_shooters(scene, 3, seed)
    one, one_rec = _visibility(scene, samples, packing=packing)
    many, many_rec = _visibility(scene, samples, packing=packing)
    reversed_pairs = 0
    for i, receivers in shooters:
        frac = visible_fraction(scene, one, samples, i, receivers, one.phases)
        # the old way: i's own column, then one column (one batch) per reverse receiver
        direct = ray_weights.centroid_in_front(scene, i, receivers)
        old = np.empty(len(receivers))
        old[direct] = many.clear_fraction(i, receivers[direct],
                                          ray_weights.sample_weights(scene, samples, i, receivers[direct]))
        for m in np.flatnonzero(~direct):
            w = ray_weights.pair_sample_weights(scene, samples, [receivers[m]], [i])
            old[m] = many.clear_fraction(receivers[m], np.array([i]), w)[0]
        assert np.array_equal(frac, old), i
        reversed_pairs += int((~direct).sum())
    one_bits, many_bits = np.concatenate(one_rec.bits), np.concatenate(many_rec.bits)
    blocked = int(one_bits.sum())
    assert len(one_rec.bits) == len(shooters) < len(many_rec.bits)
    assert np.array_equal(one_bits, many_bits)          # block by block, ray by ray
    assert 0 < blocked < len(one_bits)                   # some rays blocked, some not
    assert (one.rays, one.blocks, one.columns) == (many.rays, many.blocks, many.columns)
    assert one.columns == len(shooters) + reversed_pairs
    assert one.stats.summary() == many.stats.summary()
    c1, cm = one_rec.board.counters(), many_rec.board.counters()
    for key in ("tests", "tests_issued", "blocks", "rays", "tests_issued_per_board", "board_cycles_per_board"):
        assert c1[key] == cm[key], key
    assert c1["board_cycles"] < cm["board_cycles"]
    print(f"{reversed_pairs} reverse pairs; blocked {blocked} of {len(one_bits)} rays; "
          f"board cycles {c1['board_cycles']} (one batch per shooter) vs {cm['board_cycles']}")


def test_pair_fractions_do_not_depend_on_the_packing(cornell):
    # Interleaved shooters (a run of equal shooters is one column): the same fractions as one ray
    # per block along its 3D-DDA, whose blocks share nothing with the packed ones.
    scene, samples = cornell, SampleScheme(8)
    seed = 1314
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    a, b = rng.choice(scene.patches, 2, replace=False)
    shooters = np.array([a] * 20 + [b] * 15 + [a] * 10)
    receivers = rng.choice(np.setdiff1d(np.arange(scene.patches), [a, b]), len(shooters), replace=False)
    weights = ray_weights.pair_sample_weights(scene, samples, shooters, receivers)
    packed, _ = _visibility(scene, samples)
    per_ray, _ = _visibility(scene, samples, traversal="ray")
    f_packed = packed.pair_clear_fraction(shooters, receivers, weights)
    f_ray = per_ray.pair_clear_fraction(shooters, receivers, weights)
    assert np.array_equal(f_packed, f_ray)
    assert np.array_equal(packed.pair_clear_fraction(shooters, receivers),
                          per_ray.pair_clear_fraction(shooters, receivers))
    assert ((f_packed > 0) & (f_packed < 1)).any() or ((f_packed == 0).any() and (f_packed == 1).any())
    assert packed.columns == 2 * 3 and packed.rays == per_ray.rays == 2 * len(shooters) * samples.count
    assert packed.pair_clear_fraction([], []).shape == (0,)
