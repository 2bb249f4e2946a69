"""Verilator build time and simulated cycles per second of the whole board under cocotb.

    python benchmarks/board_verilator.py [--rows 8 --cols 8 --bits 16] [--boards 2]

Builds BoardCore (cached by content under ~/.cache/blockray/verilator: delete the directory, or
set BLOCKRAY_CACHE_DIR to an empty one, to time a fresh build), then runs the Cornell box batch of
the first ``--boards`` partitions (memory load + block rays + counter reads) with a host that never
idles and never back-pressures, and prints the build time, the simulated cycles and cycles/s.
The host is Python driving every cycle (tests/cocotb_board.py), so cycles/s is for the
cocotb-driven simulation, not for Verilator alone. Results are checked against the model.
"""

import argparse
import platform
import time

import _shared  # noqa: F401  (tests/ on the path: the cocotb harness)
from board_cocotb_runs import build_board, cornell_partition, cornell_runs, run_batch


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=8)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--bits", type=int, default=16)
    ap.add_argument("--boards", type=int, default=2, help="partitions to simulate (of P = 8)")
    args = ap.parse_args()

    params, model, blocks = cornell_partition(args.rows, args.cols, 8, args.bits, voxels=6,
                                              shooters=(5, 300, 600), stride=11)
    t0 = time.perf_counter()
    build = build_board(params, f"board_{args.rows}x{args.cols}_b{args.bits}")
    total = time.perf_counter() - t0
    runs = cornell_runs(model, blocks, seed=1, idle=0.0, backpressure=0.0)[:args.boards]
    logs = run_batch(build, params, runs, "bench")
    check_cornell_subset(params, model, blocks, runs, logs)
    cycles = sum(o["cycles"] for o in logs)
    seconds = sum(o["seconds"] for o in logs)
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
    print(f"board: {args.rows} x {args.cols}, B = {args.bits}, patch_depth {params.patch_depth}, "
          f"voxel_depth {params.voxel_depth}, {len(blocks)} block rays")
    print(f"verilog + verilator build: {total:.1f} s (verilator {build.seconds:.1f} s, cached: {build.cached})")
    print(f"simulated {cycles} cycles in {seconds:.2f} s: {cycles / seconds:.0f} cycles/s (cocotb host every cycle)")


def check_cornell_subset(params, model, blocks, runs, logs):
    """check_run on each simulated partition (the OR over all P needs every partition)."""
    from board_host import check_run
    for run, out in zip(runs, logs):
        check_run(params, run["commands"], out["log"])


if __name__ == "__main__":
    main()
