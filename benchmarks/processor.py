"""Measure the intersection processor: Verilator build time, cocotb vectors/s, Yosys cell counts.

    python benchmarks/processor.py [--bits 16] [--vectors 100000] [--fresh] [--synth]

``--fresh`` builds into a new temporary cache (so the build time is a real build, not a cache
hit). Prints one line per measurement; docs/processor.md records the numbers.
"""

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bits", type=int, default=16)
    ap.add_argument("--vectors", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fresh", action="store_true", help="build in an empty cache")
    ap.add_argument("--synth", action="store_true", help="also run Yosys (generic and ECP5)")
    args = ap.parse_args()

    from blockray.rtl.processor import Intersector
    from blockray.sim.cocotb_support import build_verilator, run_cocotb

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp, "cache") if args.fresh else None
        t = time.perf_counter()
        build = build_verilator(Intersector(args.bits), name="intersector", cache=cache)
        print(f"verilator build (bits={args.bits}): {'cached' if build.cached else f'{build.seconds:.1f} s'}"
              f" (with Verilog conversion {time.perf_counter() - t:.1f} s)")
        stats_file = Path(tmp, "stats.json")
        env = {"BLOCKRAY_BITS": str(args.bits), "BLOCKRAY_SEED": str(args.seed),
               "BLOCKRAY_VECTORS": str(args.vectors), "BLOCKRAY_STATS": str(stats_file)}
        t = time.perf_counter()
        run_cocotb(build, "cocotb_processor", module_dir=ROOT / "tests", env=env, test_dir=Path(tmp, "run"))
        wall = time.perf_counter() - t
        stats = json.loads(stats_file.read_text())
        print(f"cocotb+verilator: {stats['vectors']} vectors ({stats['hard']} hard), {stats['cycles']} cycles, "
              f"{stats['mismatches']} mismatches, {stats['vectors_per_second']:.0f} vectors/s "
              f"({stats['cycles_per_second']:.0f} cycles/s) in the stream loop, {wall:.1f} s wall incl. vector generation")

    if args.synth:
        from blockray.synth.yosys import synth_stats
        for target in ("generic", "ecp5"):
            s = synth_stats(Intersector(args.bits), name="intersector", target=target)
            print(f"yosys {target} (bits={args.bits}): cells {s.cells}, multipliers {s.multipliers}, "
                  f"LUTs {s.luts}, FFs {s.ffs}, {s.seconds:.1f} s; "
                  f"{s.by_type if target == 'ecp5' else sorted(set(s.mul_widths))}")


if __name__ == "__main__":
    main()
