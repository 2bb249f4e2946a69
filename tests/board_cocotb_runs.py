"""The board's Verilog under Verilator + cocotb: its build, a batch of runs, the Cornell box's
partition and its check (imported as ``board_cocotb_runs``; tests/test_board_cocotb.py,
test_filtered_board_cocotb.py)."""

import pickle
import shutil
import tempfile
from pathlib import Path

import numpy as np

from blockray.params import BoardParams
from blockray.protocol import BoardProtocol, ReadCounters, check_capacity, fit_params
from blockray.sim.model import ModelBoard

from board_host import check_run

HERE = Path(__file__).resolve().parent


BUILD_ARGS = ("-Wno-fatal", "-Wno-lint", "-Wno-style", "-O3", "--x-assign", "fast", "--x-initial", "fast")


def build_board(params, name):
    """Build the board's Verilog with Verilator (cached by content, sim/cocotb_support.py)."""
    from blockray.rtl.core import BoardCore
    from blockray.sim.cocotb_support import build_verilator

    return build_verilator(BoardCore(params), name=name, build_args=BUILD_ARGS)


def run_batch(build, params, runs, tag):
    """Run tests/cocotb_board.py on ``build`` with ``runs``; returns its per-run logs."""
    from blockray.sim.cocotb_support import run_cocotb

    work = Path(tempfile.mkdtemp(prefix=f"board_{tag}_"))
    batch_path, log_path = work / "batch.pkl", work / "log.pkl"
    with open(batch_path, "wb") as f:
        pickle.dump({"params": params, "runs": runs}, f)
    run_cocotb(build, "cocotb_board", module_dir=HERE, test_dir=work,
               env={"BOARD_BATCH": str(batch_path), "BOARD_LOG": str(log_path)})
    with open(log_path, "rb") as f:
        logs = pickle.load(f)
    shutil.rmtree(work, ignore_errors=True)
    return logs


def cornell_partition(rows, cols, boards, bits, *, voxels=4, shooters=(5, 600), stride=37):
    """The Cornell box through the host driver: params sized for the largest partition, the
    ModelBoard, and its block rays (the renderer's Visibility blocks)."""
    from blockray.host_driver.scene import builtin
    from blockray.host_driver.render.render import Visibility
    from blockray.host_driver.traverse.voxel import VoxelGrid
    from blockray.samples import SampleScheme

    scene = builtin.load("cornell")
    samples = SampleScheme(4)
    model = ModelBoard(BoardParams(rows=rows, cols=cols, boards=boards, bits=bits))
    model.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, voxels, margin=model.margin)
    model.load(grid)
    vis = Visibility(scene, model, grid, samples, rows=rows, cols=cols)
    blocks = []
    for i in shooters:
        blocks += vis._blocks_for(i, np.arange(0, scene.patches, stride))
    records = max(len(m["patch"]) for m in model.memories)
    params = fit_params(model.params, records=records, voxels=grid.v ** 3)
    check_capacity(params, records=records, voxels=grid.v ** 3)
    return params, model, blocks


def cornell_runs(model, blocks, *, seed, idle, backpressure, reset_board=None, reset_at=None):
    runs = []
    for b in range(model.params.boards):
        cmds = model.memory.load_commands(b) + [ReadCounters()]
        for block in blocks:
            cmds += model.memory.block_commands(block)
        cmds.append(ReadCounters())
        runs.append({"commands": cmds, "seed": seed + b, "idle": idle, "backpressure": backpressure,
                     "reset_at": reset_at if b == reset_board else None})
    return runs


def check_cornell(params, model, blocks, runs, logs):
    proto = BoardProtocol(params)
    before = np.array(model.counters()["board_cycles_per_board"])
    expect = model.run(blocks)
    block_cycles = np.array(model.counters()["board_cycles_per_board"]) - before
    ored = [np.zeros((len(bl.receiver_patch), len(bl.shooter_patch)), dtype=bool) for bl in blocks]
    for b, (run, out) in enumerate(zip(runs, logs)):
        check_run(params, run["commands"], out["log"])
        words = [proto.decode_result(out["log"].results[i]) for i in sorted(out["log"].results)]
        blocked = [w.blocked for w in words[1:-1]]
        assert len(blocked) == len(blocks)
        for k, (bl, word) in enumerate(zip(blocks, blocked)):
            R, S = len(bl.receiver_patch), len(bl.shooter_patch)
            for r in range(R):
                for s in range(S):
                    ored[k][r, s] |= bool(word >> (r * params.cols + s) & 1)
        if out["log"].answered_at_reset:
            continue
        # the blocks' cycles on this board equal ModelBoard's, between the two counter reads
        first, last = words[0].counters, words[-1].counters
        assert last["cycles"] - first["cycles"] - 1 == block_cycles[b]
    for k, (got, want) in enumerate(zip(ored, expect)):
        assert (got == want).all(), f"block {k}: boards ORed {got.astype(int).tolist()}, model {want.astype(int).tolist()}"
    assert any(w.any() for w in expect) and not all(w.all() for w in expect)
