"""Measure the intersection processor: Verilator build time, cocotb vectors/s, Yosys cell counts.

    python benchmarks/processor.py [--bits 16] [--vectors 100000] [--fresh] [--synth] [--native]

``--fresh`` builds into a new temporary cache (so the build time is a real build, not a cache
hit). ``--native`` also runs the same vectors (hard cases and random, same seed, 10 % input gaps
and output stalls) through the native vector harness (sim/native/vector_harness.cpp) in the same
run, checks them against the exact predicate and prints both rates and their ratio. Prints one
line per measurement; docs/processor.md records the numbers.
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
    ap.add_argument("--native", action="store_true", help="also the native vector harness, side by side")
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
        if args.native:
            _native(args, stats["vectors_per_second"])

    if args.synth:
        from blockray.synth.yosys import synth_stats
        for target in ("generic", "ecp5"):
            s = synth_stats(Intersector(args.bits), name="intersector", target=target)
            print(f"yosys {target} (bits={args.bits}): cells {s.cells}, multipliers {s.multipliers}, "
                  f"LUTs {s.luts}, FFs {s.ffs}, {s.seconds:.1f} s; "
                  f"{s.by_type if target == 'ecp5' else sorted(set(s.mul_widths))}")


def _native(args, cocotb_rate):
    """The cocotb run's vectors through the native vector harness: build, rate, ratio."""
    import numpy as np
    import _shared  # noqa: F401  (tests/ on the path)
    from processor_vectors import hard_cases, random_tests
    from blockray.rtl.processor import Intersector
    from blockray.sim.drive import HostTiming
    from blockray.sim.native.vectors import NativeVectors

    tests = hard_cases(args.bits) + random_tests(args.bits, args.vectors, np.random.default_rng(args.seed))
    payloads = tests.payload_bytes(args.bits)
    t = time.perf_counter()
    runner = NativeVectors(lambda: Intersector(args.bits), name="intersector_vectors",
                           idle=HostTiming(0.1), backpressure=HostTiming(0.1), seed=args.seed)
    print(f"native build (bits={args.bits}): {'cached' if runner.build.cached else f'{runner.build.seconds:.1f} s'}"
          f" (with Verilog conversion {time.perf_counter() - t:.1f} s)")
    t, c = time.perf_counter(), runner.cycles
    out = runner.run(payloads)
    seconds, cycles = time.perf_counter() - t, runner.cycles - c
    mismatches = int(np.count_nonzero((out[:, 0] & 1).astype(bool) != tests.blocked))
    rate = len(tests) / seconds
    print(f"native vector harness: {len(tests)} vectors, {cycles} cycles, {mismatches} mismatches, {rate:.0f} vectors/s "
          f"({cycles / seconds:.0f} cycles/s) in the C++ loop; {rate / cocotb_rate:.1f}x cocotb's in this run")
    runner.close()


if __name__ == "__main__":
    main()
