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

import pytest

from blockray.protocol import BoardProtocol

from board_cocotb_runs import build_board, check_cornell, cornell_partition, cornell_runs, run_batch
from board_host import check_run
from board_scenes import make_batch

pytestmark = pytest.mark.cocotb


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
