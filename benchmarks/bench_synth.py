"""Full synthesis runs for docs/synthesis.md (Yosys synth_ecp5 + nextpnr-ecp5, YoWASP).

    python benchmarks/bench_synth.py                      # everything (over an hour on 2 cores)
    python benchmarks/bench_synth.py --only processor     # one processor at B = 12, 14, 16
    python benchmarks/bench_synth.py --only array         # largest R x S array on the 85k at B = 16
    python benchmarks/bench_synth.py --only array --fabric-units shooter   # column units on LUTs
    python benchmarks/bench_synth.py --only board         # the 8 x 8 board, Yosys only (~27 min)
    python benchmarks/bench_synth.py --only cells         # 2 x 2 and 4 x 4 arrays, exact / filtered / lean, Yosys only

Each run is ``blockray.synth.nextpnr.synth_report`` (the same as ``blockray synth``: the ECP5
netlist, every product a registered MULT18X18D); the JSON reports go to ``--out`` (default
``synth-reports/``), a summary table to stdout. ``--seeds 1 2 3`` repeats every place and route
with each nextpnr placement seed (Fmax varies with the seed by several per cent). ``--also-speed
8`` times each routed design again at -8 as well (docs/synthesis.md, "The same routing at
another grade").

Array search: every R x S with R, S <= 8 whose DSP count (``dsp_estimate``, checked against
Yosys in tests/test_synth.py) fits the part is ranked by processors (then squareness); Yosys runs
on the candidates from the largest down (resources only) until one fits the part by every
resource, and that one goes through place and route. ``--fabric-units shooter[,receiver]`` puts
those units' products on LUT multipliers (``blockray synth --fabric-units``) in the search and
the runs.
"""

import argparse
import json
import sys
import time
from pathlib import Path

from blockray.cell import CELLS, Cell
from blockray.params import BoardParams
from blockray.synth.nextpnr import DEVICES, ROUTER, SPEEDS, dsp_estimate, synth_report


def _row(name, r):
    res = r["resources"]
    fmax = r.get("fmax_mhz")
    return (f"{name:28s} {r.get('part', '')} LUT {res['luts']:7d}  FF {res['ffs']:7d}  DSP {res['dsps']:5d}  BRAM {res['brams']:4d}  "
            f"fits {str(r['fits']):5s}  Fmax {fmax if fmax else '-':>7}  "
            + "".join(f"(-{o['speed']}: {o['scaled_mhz']} scaled) " for o in r.get("same_routing", [])[1:])
            + f"({', '.join(f'{k} {v}s' for k, v in r['seconds'].items())})")


def _grade(args):
    """Report-name suffix of a non-default speed grade."""
    return "" if args.speed is None else f"-speed{args.speed}"


def run(name, unit, params, out, **kw):
    start = time.perf_counter()
    r = synth_report(unit, params, workdir=out / f"{name}.work", **kw)
    (out / f"{name}.json").write_text(json.dumps(r, indent=2) + "\n")
    print(_row(name, r), f"total {time.perf_counter() - start:.0f} s", flush=True)
    return r


def processors(out, args):
    for bits in (12, 14, 16):
        for seed in args.seeds:
            run(f"processor-B{bits}-seed{seed}{_grade(args)}", "processor", BoardParams(bits=bits), out,
                device=args.device, speed=args.speed, freq=args.freq, seed=seed, also_speeds=args.also_speed,
                router=args.router)


def largest_array(out, args):
    bits = args.bits
    shapes = sorted(((r, s) for r in range(1, 9) for s in range(1, 9)),
                    key=lambda rs: (-rs[0] * rs[1], abs(rs[0] - rs[1])))
    for rows, cols in shapes:
        if dsp_estimate(bits, rows, cols, args.fabric_units) > DEVICES[args.device]["dsps"]:
            continue
        params = BoardParams(rows=rows, cols=cols, bits=bits)
        tag = "".join(f"-{u}-luts" for u in args.fabric_units)
        r = run(f"array-{rows}x{cols}-B{bits}{tag}-yosys", "array", params, out, device=args.device, place=False,
                fabric_units=args.fabric_units)
        if r["fits"]:
            return [run(f"array-{rows}x{cols}-B{bits}{tag}-seed{seed}{_grade(args)}", "array", params, out,
                        device=args.device, speed=args.speed, freq=args.freq, seed=seed,
                        fabric_units=args.fabric_units, also_speeds=args.also_speed, router=args.router)
                    for seed in args.seeds]
    return None


def cells(out, args):
    """Yosys counts (no place and route) of the 2 x 2 and 4 x 4 arrays of each cell at ``--bits``,
    side by side in one run: exact, filtered (default format) and lean (9 x 9 bits)."""
    for rows, cols in ((2, 2), (4, 4)):
        for kind in CELLS:
            run(f"array-{rows}x{cols}-B{args.bits}-{kind}-yosys", "array",
                BoardParams(rows=rows, cols=cols, bits=args.bits), out, device=args.device, place=False,
                cell=Cell(kind), fabric_units=args.fabric_units)


def board(out, args):
    run("board-8x8-B16", "board", BoardParams(), out, device=args.device, place=False)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=["processor", "array", "cells", "board"], action="append")
    p.add_argument("--out", default="synth-reports", help="directory for the JSON reports and tool files")
    p.add_argument("--device", default="85k", choices=["85k", "45k", "25k"])
    p.add_argument("--freq", type=float, default=100.0)
    p.add_argument("--speed", type=int, default=None, choices=SPEEDS,
                   help="ECP5 speed grade for nextpnr (default the part's, -6)")
    p.add_argument("--router", default=ROUTER, choices=["router1", "router2"],
                   help=f"nextpnr router (default {ROUTER}; router2 routes the 1 x 5 with LUT shooter units)")
    p.add_argument("--also-speed", type=int, action="append", default=[], choices=SPEEDS,
                   help="also time each routed design at this grade (blockray synth --also-speed)")
    p.add_argument("--bits", type=int, default=BoardParams().bits, help="B of the array search")
    p.add_argument("--seeds", type=int, nargs="+", default=[1], help="nextpnr placement seeds (default 1)")
    p.add_argument("--fabric-units", type=lambda t: tuple(u for u in t.split(",") if u), default=(),
                   help="array search: units whose products are LUT multipliers (shooter, receiver)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    todo = args.only or ["processor", "array", "board"]
    if "processor" in todo:
        processors(out, args)
    if "array" in todo:
        largest_array(out, args)
    if "cells" in todo:
        cells(out, args)
    if "board" in todo:
        board(out, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
