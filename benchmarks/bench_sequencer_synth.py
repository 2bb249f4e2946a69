"""Yosys resource counts (``synth_ecp5``, no place and route) of the block sequencer of rays made
on the board (rtl/sequencer.py) and of the two units inside it, for docs/synthesis.md.

    python benchmarks/bench_sequencer_synth.py [--rows 1] [--cols 2] [--bits 16] [--patch-depth 2048] [--voxel-depth 512] [--core]

The defaults are the ULX3S default board's (synth/bitstream.py). Block RAMs are DP16KD, LUTs
LUT4 plus two per CCU2C, multipliers MULT18X18D (``blockray.synth.yosys.synth_stats``).
``--core`` adds the board behind its link (``BoardCore``) without and with the sequencer.
"""

import argparse

from _run_header import print_run_header
from blockray.params import BoardParams
from blockray.rtl.core import BoardCore
from blockray.rtl.points import PointUnit
from blockray.rtl.ray_walk import RayWalker
from blockray.rtl.sequencer import BlockSequencer
from blockray.synth.bitstream import DEFAULT_PATCH_DEPTH, DEFAULT_VOXEL_DEPTH
from blockray.synth.yosys import synth_stats


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1)
    ap.add_argument("--cols", type=int, default=2)
    ap.add_argument("--bits", type=int, default=16)
    ap.add_argument("--patch-depth", type=int, default=DEFAULT_PATCH_DEPTH)
    ap.add_argument("--voxel-depth", type=int, default=DEFAULT_VOXEL_DEPTH)
    ap.add_argument("--core", action="store_true", help="also BoardCore without and with the sequencer")
    args = ap.parse_args()
    print_run_header()
    params = BoardParams(rows=args.rows, cols=args.cols, boards=1, bits=args.bits, patch_depth=args.patch_depth,
                         voxel_depth=args.voxel_depth)
    print(f"`{params!r}`\n")
    print("| unit | LUTs | FFs | MULT18X18D | DP16KD | other RAM cells | Yosys s |")
    print("|---|---|---|---|---|---|---|")
    units = [("BlockSequencer", lambda: BlockSequencer(params)), ("RayWalker", lambda: RayWalker(bits=args.bits)),
             ("PointUnit (D learnt)", lambda: PointUnit(bits=args.bits))]
    if args.core:
        units += [("BoardCore", lambda: BoardCore(params)), ("BoardCore(rays=True)", lambda: BoardCore(params, rays=True))]
    for name, make in units:
        unit = make()
        s = synth_stats(unit, name="top", target="ecp5")
        ram = sum(n for kind, n in s.by_type.items() if kind in ("DPR16X4", "TRELLIS_DPR16X4"))
        print(f"| {name} | {s.luts} | {s.ffs} | {s.multipliers} | {s.by_type.get('DP16KD', 0)} | {ram} | "
              f"{s.seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
