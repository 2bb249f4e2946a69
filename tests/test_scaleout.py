"""Scale-out over host + board sets (host_driver/scaleout.py, solver.gauss_seidel_sets)."""

import numpy as np
import pytest

from blockray.cli import main
from blockray.errors import ParameterError
from blockray.host_driver import solver as solvers
from blockray.host_driver.objload import load_scene
from blockray.host_driver.render import render
from blockray.host_driver.scaleout import assign_sets, exchange_bytes_per_sweep
from blockray.host_driver.scene import Scene


def _random_system(seed, n=40):
    """A scene-like object with emission, reflectance and a random F of row sums < 1."""
    rng = np.random.default_rng(seed)
    print(f"seed={seed}")
    F = rng.random((n, n)) * (rng.random((n, n)) < 0.3)
    np.fill_diagonal(F, 0)
    F /= F.sum(axis=1, keepdims=True).clip(1e-9) * rng.uniform(1.05, 2.0, (n, 1))
    emission = np.zeros((n, 3))
    emission[rng.choice(n, 3, replace=False)] = rng.random((3, 3)) + 0.5
    v = rng.random((3 * n, 3))
    scene = Scene("sys", v, np.arange(3 * n).reshape(-1, 3), rng.uniform(0.1, 0.9, (n, 3)), emission,
                  np.zeros(n, dtype=np.int64))
    return scene, F


def test_gauss_seidel_sets_limits():
    scene, F = _random_system(1)
    n = scene.patches
    one = solvers.gauss_seidel_sets(scene, F, np.zeros(n), tolerance=0, max_iterations=3)
    ref = np.array(scene.emission, dtype=np.float64)      # three in-place Gauss-Seidel sweeps, by hand
    for _ in range(3):
        for j in range(n):
            ref[j] = scene.emission[j] + scene.reflectance[j] * (F[j] @ ref)
    np.testing.assert_array_equal(one.B, ref)             # one set: Gauss-Seidel exactly
    assert one.iterations == 3
    # every patch its own set: one sweep is Jacobi's update
    sweep = solvers.gauss_seidel_sets(scene, F, np.arange(n), tolerance=0, max_iterations=1)
    np.testing.assert_allclose(sweep.B, scene.emission + scene.reflectance * (F @ scene.emission), rtol=1e-15)


@pytest.mark.parametrize("sets", [2, 5, 13])
def test_gauss_seidel_sets_converges_to_the_direct_solution(sets):
    scene, F = _random_system(7)
    n = scene.patches
    rng = np.random.default_rng(sets)
    owner = rng.integers(0, sets, n)
    owner[:sets] = np.arange(sets)
    res = solvers.gauss_seidel_sets(scene, F, owner, tolerance=1e-12, max_iterations=500)
    assert res.converged
    direct = np.stack([np.linalg.solve(np.eye(n) - scene.reflectance[:, c, None] * F, scene.emission[:, c])
                       for c in range(3)], axis=1)
    np.testing.assert_allclose(res.B, direct, rtol=1e-9, atol=1e-12)
    # more sets keep less of Gauss-Seidel's in-place updates: never fewer sweeps than one set
    assert res.iterations >= solvers.gauss_seidel(scene, F, tolerance=1e-12).iterations


def test_assign_sets():
    rng = np.random.default_rng(3)
    morton = rng.integers(0, 1000, 101)
    owner = assign_sets(morton, 4)
    sizes = np.bincount(owner)
    assert len(sizes) == 4 and sizes.max() - sizes.min() <= 1
    # each set is a run of the Z-order: its codes do not interleave with another set's
    order = np.argsort(morton, kind="stable")
    assert (np.diff(owner[order]) >= 0).all()
    assert exchange_bytes_per_sweep(owner) == 4 * 101 * 3
    # weighted: runs of equal total weight, still contiguous in Z-order and never empty
    weights = rng.integers(0, 50, 101).astype(float)
    owner_w = assign_sets(morton, 5, weights)
    assert (np.diff(owner_w[order]) >= 0).all() and len(np.bincount(owner_w)) == 5
    loads = np.bincount(owner_w, weights=weights)
    assert loads.max() - loads.min() <= 2 * weights.max(), loads      # equal to within a patch or two
    heavy = np.zeros(101)
    heavy[order[0]] = 1.0                  # all the weight on one patch: the others still get a patch each
    assert np.bincount(assign_sets(morton, 4, heavy)).min() >= 1
    for bad in (0, -1, 102, 2.5, True):
        with pytest.raises(ParameterError, match="--sets"):
            assign_sets(morton, bad)


@pytest.fixture(scope="module")
def small_cornell():
    return load_scene("cornell", max_edge=250)


def test_render_sets_same_visibility_less_machine_time(small_cornell):
    one = render(small_cornell, board="model", solver="jacobi", tolerance=1e-4, sets=1)
    three = render(small_cornell, board="model", solver="jacobi", tolerance=1e-4, sets=3)
    # the same rays with the same exact results, so the same F and (Jacobi) the same radiosity
    np.testing.assert_array_equal(one.radiosity, three.radiosity)
    assert one.report["rays"] == three.report["rays"]
    per_set = three.report["set_counters"]
    assert len(per_set) == 3 and sum(s["patches"] for s in per_set) == small_cornell.patches
    assert sum(s["rays"] for s in per_set) == three.report["rays"]
    assert sum(s["tests"] for s in per_set) == three.report["tests"]
    assert three.report["board_cycles"] == max(s["board_cycles"] for s in per_set)
    assert three.report["board_cycles"] < one.report["board_cycles"]
    # the sets were cut by the rays they receive: those differ far less than patch counts would
    rays = [s["rays"] for s in per_set]
    assert max(rays) < 1.05 * min(rays), rays        # (by patch count: 65 344 - 71 680)
    assert three.report["exchange_bytes_per_sweep"] == 4 * small_cornell.patches * 2
    assert len(three.report["board_cycles_per_board"]) == 3 * 8
    gs = render(small_cornell, board="model", solver="gauss-seidel", tolerance=1e-4, sets=3)
    assert gs.report["residual"] < 1e-4 and gs.report["sets"] == 3
    rel = np.abs(gs.radiosity - one.radiosity).max() / np.abs(one.radiosity).max()
    assert rel < 1e-3, rel


@pytest.mark.parametrize("argv", [
    ["render", "cornell", "--sets", "2"],                                      # progressive
    ["render", "cornell", "--sets", "0", "--solver", "jacobi"],
    ["render", "cornell", "--max-edge", "300", "--sets", "100000", "--solver", "jacobi"],
])
def test_cli_sets_errors(capsys, argv):
    try:
        code = main(argv + ["--quiet"])
    except SystemExit as e:                    # argparse's own range check
        code = e.code
    err = capsys.readouterr().err
    assert code == 2 and "--sets" in err and "Traceback" not in err
