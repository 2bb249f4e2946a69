"""The board with the filtered cell as generated Verilog under Verilator + cocotb
(tests/cocotb_board.py, ``BoardTop`` fed command records): blocked words and counters, cycles
included, equal ``BoardModel(cell=Cell("filtered"))`` with zero tolerance on bigger batches than the
Amaranth simulator's (tests/test_filtered_board.py): a random scene and the Cornell box through
the host's memories and block commands, each board of the partition in turn, with a 3 x 3-bit
filter (many undecided tests in one broadcast: the shared exact unit's queue fills and the
broadcast stalls) and the default format. The host keeps the command stream full and reads
results at once (the model's assumption: the filtered board's cycles depend on the host's timing).
"""

import functools

import numpy as np
import pytest

from blockray.cell import Cell
from blockray.filtered import FilterFormat
from blockray.protocol import BoardProtocol
from blockray.sim.model import BoardModel

from board_host import check_run
from board_cocotb_runs import BUILD_ARGS, cornell_partition, cornell_runs, run_batch
from board_scenes import make_batch

pytestmark = pytest.mark.cocotb


def build_filtered(params, fmt, name):
    from blockray.rtl.board import BoardTop
    from blockray.sim.cocotb_support import build_verilator

    return build_verilator(BoardTop(params, cell=Cell("filtered", fmt)), name=name, build_args=BUILD_ARGS)


# the 3 x 3 format sends the most tests to the shared exact unit; the default format's 70 s run is slow
@pytest.mark.parametrize("fmt", [FilterFormat(3, 3), pytest.param(None, marks=pytest.mark.slow)],
                         ids=["d3w3", "default"])
def test_filtered_board_verilator_equals_model(fmt):
    seed = 901
    print(f"seed={seed}")
    params_c, model, blocks = cornell_partition(2, 2, 2, 12)
    params_r, cmds = make_batch(seed, rows=2, cols=2, bits=12, patches=20, voxels=8, blocks=8)
    params = params_c.with_(patch_depth=max(params_c.patch_depth, params_r.patch_depth),
                            voxel_depth=max(params_c.voxel_depth, params_r.voxel_depth))
    build = build_filtered(params, fmt, f"board_filtered_{fmt or 'default'}_2x2_b12")
    print(f"verilator build: {build.seconds:.1f} s (cached: {build.cached})")
    runs = [{"commands": cmds, "seed": seed, "idle": 0.0, "backpressure": 0.0, "link": "records"}]
    runs += [dict(r, link="records") for r in cornell_runs(model, blocks[:40], seed=seed + 1, idle=0.0,
                                                           backpressure=0.0)]
    logs = run_batch(build, params, runs, "filtered")
    filtered = functools.partial(BoardModel, cell=Cell("filtered", fmt))
    proto = BoardProtocol(params)
    ored = [np.zeros((len(bl.receiver_patch), len(bl.shooter_patch)), dtype=bool) for bl in blocks[:40]]
    for k, (run, out) in enumerate(zip(runs, logs)):
        check_run(params, run["commands"], out["log"], model=lambda p, t: filtered(p, t))
        res, exact = filtered(params).execute(run["commands"]), BoardModel(params).execute(run["commands"])
        print(f"run {k}: {out['cycles']} clock cycles; board cycles: filtered {res.cycles}, exact cell "
              f"{exact.cycles}; tests issued {res.tests_issued}")
        if k == 0:
            continue
        words = [proto.decode_result(out["log"].results[i]) for i in sorted(out["log"].results)]
        for b, (bl, word) in enumerate(zip(blocks, [w.blocked for w in words[1:-1]])):
            for r in range(len(bl.receiver_patch)):
                for s in range(len(bl.shooter_patch)):
                    ored[b][r, s] |= bool(word >> (r * params.cols + s) & 1)
    for got, want in zip(ored, model.run(blocks[:40])):
        assert (got == want).all()
