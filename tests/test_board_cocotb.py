"""The whole board behind its byte link (BoardCore) as generated Verilog, simulated by Verilator
under cocotb (tests/cocotb_board.py).

Batches: a random scene (well-formed blocks, READ_COUNTERS between them) and the Cornell box
through the host's memories and block commands (blockray.memory.BoardMemories of a ModelBoard,
VoxelGrid registration, the renderer's own block rays), each board of the partition run in turn.
Every run but the first has random host idle cycles and result back-pressure (one with bursts of
long stalls); some have a reset in the middle of the batch. Blocked words and counters must
equal the bit-exact model exactly (board_host.check_run), and the host's OR over the P boards
must equal ModelBoard.run.

The default suite uses a 2 x 2 array; the 8 x 8 board at B = 16 is behind ``-m slow``.
"""

import pickle
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from blockray.params import BoardParams
from blockray.protocol import BoardProtocol, ReadCounters, check_capacity, fit_params
from blockray.sim.model import ModelBoard

from board_host import check_run
from board_scenes import make_batch

HERE = Path(__file__).resolve().parent

pytestmark = pytest.mark.cocotb


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
    from blockray.host_driver import builtin
    from blockray.host_driver.render import Visibility
    from blockray.host_driver.voxel import VoxelGrid
    from blockray.samples import SampleScheme

    scene = builtin.load("cornell")
    samples = SampleScheme(4)
    model = ModelBoard(BoardParams(rows=rows, cols=cols, boards=boards), bits=bits)
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


@pytest.fixture(scope="module")
def small_board():
    """One 2 x 2 build (B = 12) for the random scene and the Cornell box."""
    params_c, model, blocks = cornell_partition(2, 2, 2, 12)
    params_r, cmds = make_batch(501, rows=2, cols=2, bits=12, patches=20, voxels=8, blocks=8)
    params = params_c.with_(patch_depth=max(params_c.patch_depth, params_r.patch_depth),
                            voxel_depth=max(params_c.voxel_depth, params_r.voxel_depth))
    build = build_board(params, "board_2x2_b12")
    print(f"verilator build: {build.seconds:.1f} s (cached: {build.cached})")
    return dict(params=params, build=build, model=model, blocks=blocks, cmds=cmds)


def test_board_cocotb_random_scene(small_board):
    seed = 601
    print(f"seed={seed}")
    params, cmds = small_board["params"], small_board["cmds"]
    runs = [
        {"commands": cmds, "seed": seed, "idle": 0.0, "backpressure": 0.0},
        {"commands": cmds, "seed": seed + 1, "idle": 0.3, "backpressure": 0.5, "bursts": 0.002},
        {"commands": cmds, "seed": seed + 2, "idle": 0.2, "backpressure": 0.3, "reset_at": 150},
        {"commands": cmds, "seed": seed + 3, "idle": 0.1, "backpressure": 0.6, "reset_at": 260},
    ]
    logs = run_batch(small_board["build"], params, runs, "random")
    for run, out in zip(runs, logs):
        check_run(params, run["commands"], out["log"])
        if run.get("reset_at"):
            assert out["log"].answered_at_reset, "the reset did not happen"
    # without host stalls the first run loses no result: its last snapshot's cycles + stalls is
    # the whole run, and the link (bytes) costs stalls, not board cycles (check_run: cycles = model)
    last = BoardProtocol(params).decode_result(logs[0]["log"].results[max(logs[0]["log"].results)]).counters
    assert last["stalls"] > 0


def test_board_cocotb_cornell(small_board):
    seed = 701
    print(f"seed={seed}")
    params, model, blocks = small_board["params"], small_board["model"], small_board["blocks"][:10]
    runs = cornell_runs(model, blocks, seed=seed, idle=0.2, backpressure=0.3, reset_board=1, reset_at=2000)
    logs = run_batch(small_board["build"], params, runs, "cornell")
    assert logs[1]["log"].answered_at_reset, "the reset did not happen"
    check_cornell(params, model, blocks, runs, logs)


@pytest.mark.slow
def test_board_cocotb_8x8_cornell():
    """The full 8 x 8 board at B = 16 on the Cornell box, P = 8 partitions; build time and
    simulated cycles per second are printed."""
    seed = 801
    print(f"seed={seed}")
    params, model, blocks = cornell_partition(8, 8, 8, 16, voxels=6, shooters=(5, 300, 600), stride=11)
    build = build_board(params, "board_8x8_b16")
    print(f"verilator build (8x8, B=16): {build.seconds:.1f} s (cached: {build.cached})")
    runs = cornell_runs(model, blocks, seed=seed, idle=0.1, backpressure=0.2, reset_board=3, reset_at=2000)
    logs = run_batch(build, params, runs, "cornell8")
    cycles = sum(o["cycles"] for o in logs)
    secs = sum(o["seconds"] for o in logs)
    print(f"simulated {cycles} cycles in {secs:.1f} s: {cycles / secs:.0f} cycles/s")
    check_cornell(params, model, blocks, runs, logs)
