"""Scale-out over host + board sets (host_driver/cluster/scaleout.py, solver.gauss_seidel_sets)."""

import json
import logging
import os
import signal
import socket
import threading
import time

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.errors import ParameterError
from blockray.host_driver.radiosity import solver as solvers
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import render
from blockray.host_driver.cluster.scaleout import assign_sets, exchange_bytes_per_sweep
from blockray.host_driver.scene.scene import Scene


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


def test_product_rows_are_the_whole_products_rows():
    """A set's rows of F B, computed alone, equal the same rows of the whole product bit for bit
    (numpy's BLAS matmul does not guarantee this; Jacobi over sets relies on it)."""
    scene, F = _random_system(11, n=333)
    B = np.random.default_rng(11).random((333, 3))
    whole = solvers.product(F, B)
    owner = np.random.default_rng(12).integers(0, 3, 333)
    for k in range(3):
        own = np.flatnonzero(owner == k)
        np.testing.assert_array_equal(solvers.product(F[own], B), whole[own])


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
        with pytest.raises(ParameterError, match="^sets "):
            assign_sets(morton, bad)


@pytest.fixture(scope="module")
def small_cornell():
    return load_scene("cornell", max_edge=250)


@pytest.fixture(scope="module")
def one_set(small_cornell):
    """The reference: one set, in this process, no cluster."""
    return render(small_cornell, backend="model", solver="jacobi", tolerance=1e-4, sets=1)


@pytest.fixture(scope="module")
def tiny_cornell():
    """70 patches and their one-set reference: for the runs that check only the answer."""
    scene = load_scene("cornell", max_edge=400)
    return scene, render(scene, backend="model", solver="jacobi", tolerance=1e-4, sets=1)


@pytest.fixture(scope="module")
def cluster():
    """A two-worker LocalCluster of the tests' own, on the loopback interface."""
    from dask.distributed import LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", scheduler_kwargs={"dashboard": False},
                      silence_logs=logging.CRITICAL) as c:
        yield c


def test_render_sets_same_visibility_less_machine_time(small_cornell, one_set, cluster):
    one = one_set
    three = render(small_cornell, backend="model", solver="jacobi", tolerance=1e-4, sets=3,
                   scheduler=cluster.scheduler_address)
    # the same rays with the same exact results, so the same F and (Jacobi) the same radiosity
    np.testing.assert_array_equal(one.radiosity, three.radiosity)
    assert one.report["rays"] == three.report["rays"]
    assert one.report["iterations"] == three.report["iterations"]
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
    # what moved: per sweep the radiosities (N x RGB float64) to each of the 3 sets and each
    # set's own back; the sets' rows of F stayed on the workers
    run = three.report["cluster"]
    sweeps = three.report["iterations"] + 1
    assert run["exchanges"] == sweeps
    assert run["exchanged_bytes"] == sweeps * (3 + 1) * small_cornell.patches * 3 * 8
    assert len(run["workers"]) == 2 and {s["worker"] for s in per_set} <= {w["address"] for w in run["workers"]}
    assert len(run["cast_seconds_per_set"]) == 3
    gs = render(small_cornell, backend="model", solver="gauss-seidel", tolerance=1e-4, sets=3,
                scheduler=cluster.scheduler_address)
    assert gs.report["residual"] < 1e-4 and gs.report["sets"] == 3
    assert gs.report["cluster"]["exchanged_bytes"] == (gs.report["iterations"] + 1) * (
        3 * small_cornell.patches * 3 * 8 + small_cornell.patches * 3 * 8 + 3 * 8)
    rel = np.abs(gs.radiosity - one.radiosity).max() / np.abs(one.radiosity).max()
    assert rel < 1e-3, rel


def test_render_sets_on_its_own_local_cluster(tiny_cornell):
    """Without --scheduler blockray starts a LocalCluster on 127.0.0.1 and closes it."""
    scene, one = tiny_cornell
    two = render(scene, backend="model", solver="jacobi", tolerance=1e-4, sets=2)
    np.testing.assert_array_equal(one.radiosity, two.radiosity)
    # the largest row sum and gain, from the sets' shares of every shooter's sums (issue 34)
    sets, whole = two.report["visible_row_sum"], one.report["visible_row_sum"]
    assert (sets["patch"], sets["gain_patch"]) == (whole["patch"], whole["gain_patch"])
    assert sets["max"] == pytest.approx(whole["max"], rel=1e-12) and sets["gain_max"] == pytest.approx(
        whole["gain_max"], rel=1e-12)
    assert two.report["absorbed_balance"] == one.report["absorbed_balance"]
    workers = [w["address"] for w in two.report["cluster"]["workers"]]
    assert len(workers) == 2 and all(a.startswith("tcp://127.0.0.1:") for a in workers), workers


def test_unreachable_scheduler_fails_fast(capsys):
    with socket.socket() as s:                   # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    code = main(["render", "cornell", "--max-edge", "1000", "--solver", "jacobi", "--sets", "2",
                 "--scheduler", f"tcp://127.0.0.1:{port}", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "--scheduler" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert time.monotonic() - t0 < 60          # a bounded connect, not a hang (CONNECT_TIMEOUT = 5 s)


@pytest.mark.parametrize("argv, option", [
    (["render", "cornell", "--sets", "2"], "--sets"),                                      # progressive
    (["render", "cornell", "--sets", "0", "--solver", "jacobi"], "--sets"),
    (["render", "cornell", "--max-edge", "300", "--sets", "100000", "--solver", "jacobi"], "--sets"),
    (["render", "cornell", "--max-edge", "1000", "--sets", "2", "--solver", "jacobi", "--workers", "2",
      "--scheduler", "tcp://127.0.0.1:8786"], "--workers"),
    (["render", "cornell", "--max-edge", "1000", "--sets", "2", "--solver", "jacobi", "--board", "amaranth",
      "--vcd", "x.vcd"], "--vcd"),
    (["render", "cornell", "--max-edge", "1000", "--sets", "2", "--solver", "jacobi", "--workers", "0"], "--workers"),
])
def test_cli_sets_errors(capsys, argv, option):
    try:
        code = main(argv + ["--quiet"])
    except SystemExit as e:                    # argparse's own range check
        code = e.code
    err = capsys.readouterr().err
    assert code == 2 and option in err and "Traceback" not in err, err


def test_cli_joins_a_scheduler(tiny_cornell, cluster, tmp_path):
    scene, one = tiny_cornell
    report = tmp_path / "r.json"
    code = main(["render", "cornell", "--max-edge", "400", "--solver", "jacobi", "--tolerance", "1e-4",
                 "--sets", "2", "--scheduler", cluster.scheduler_address, "--report", str(report), "--quiet"])
    assert code == 0
    r = json.loads(report.read_text())
    assert r["cluster"]["scheduler"] == cluster.scheduler_address and len(r["cluster"]["workers"]) == 2
    assert r["residual"] == one.report["residual"] and r["rays"] == one.report["rays"]
    assert len(r["set_counters"]) == 2 and r["board_cycles"] == max(s["board_cycles"] for s in r["set_counters"])


def test_worker_killed_while_casting(tiny_cornell, cluster):
    """A worker process killed in the middle of its set's cast: Dask runs the set again on a
    live worker, and the answer is the same to the last bit. (Last in this file: it restarts one
    of the module cluster's workers.)"""
    from dask.distributed import Client
    scene, one = tiny_cornell
    out = {}

    def run():
        try:
            out["result"] = render(scene, backend="model", solver="jacobi", tolerance=1e-4, sets=2,
                                   scheduler=cluster.scheduler_address)
        except BaseException as e:              # re-raised below, in the test's thread
            out["error"] = e

    with Client(cluster.scheduler_address) as watcher:
        thread = threading.Thread(target=run)
        thread.start()
        victim, deadline = None, time.monotonic() + 120
        while victim is None and time.monotonic() < deadline and thread.is_alive():
            casting = {w: keys for w, keys in watcher.processing().items()
                       if any(str(k).startswith("cast_set") for k in keys)}
            victim = next(iter(casting), None)
            time.sleep(0.02)
        assert victim is not None, "no set was ever seen casting"
        pid = watcher.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)
        thread.join(timeout=300)
    assert not thread.is_alive(), "render did not finish after the worker was killed"
    if "error" in out:
        raise out["error"]
    result = out["result"]
    np.testing.assert_array_equal(one.radiosity, result.radiosity)
    # the killed worker's set was cast again elsewhere (a restarted worker has a new address)
    assert victim not in {s["worker"] for s in result.report["set_counters"]}


def test_quiet_silences_dask(tmp_path):
    """--quiet: nothing on stderr, Dask's INFO lines included (the local cluster's start and close)."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-m", "blockray.host_driver.cli", "render", "cornell", "--max-edge", "1000",
                           "--solver", "jacobi", "--sets", "2", "--workers", "1", "--quiet",
                           "--patches", str(tmp_path / "p.csv")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stderr == "", done.stderr
