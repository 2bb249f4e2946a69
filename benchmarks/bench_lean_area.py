"""Where a lean array's area goes, per module: Yosys ``synth_ecp5 -noflatten`` on the ECP5 netlist
of one R x S ``LeanArray`` (B = 16 by default, cells in the fabric as ``blockray synth array --cell
lean --fabric-units cell`` builds them), each module's LUTs, FFs and DSPs, and the totals of the
array's parts: cells, row units (unit + filter), column units (unit + filter), the shared exact
unit (its row and column units, exact cell and operand selection), the hand-off (tag queue,
pending and answer FIFOs, the in-order logic) and the array's top (end-point memory, the
broadcast and glue).

    python benchmarks/bench_lean_area.py --rows 2 --cols 2 [--bits 16] [--fabric-units cell] [--json out.json]

Kept hierarchical, Yosys optimises nothing across module boundaries, so the total is a little
above a flattened run's (``blockray synth array ... --no-pnr``). LUTs count LUT4 + 2 per CCU2C +
4 per TRELLIS_DPR16X4 (as blockray synth does).
"""

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _run_header import print_run_header

#: (part, pattern of the Amaranth module path below the top)
PARTS = [("cells", r"^cell_\d+_\d+$"),
         ("row units", r"^receiver(_filter)?_\d+$"),
         ("column units", r"^shooter(_filter)?_\d+$"),
         ("shared exact unit", r"^resolve\.exact(\..*)?$"),
         ("hand-off (tag queue, FIFOs, order)", r"^resolve(\.(queue|pending|answers))?$"),
         ("array top (end-point memory, glue)", r"^$")]


def _resources(cells):
    return {"luts": cells.get("LUT4", 0) + 2 * cells.get("CCU2C", 0) + 4 * cells.get("TRELLIS_DPR16X4", 0),
            "ffs": cells.get("TRELLIS_FF", 0), "dsps": cells.get("MULT18X18D", 0), "brams": cells.get("DP16KD", 0)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=2)
    p.add_argument("--cols", type=int, default=2)
    p.add_argument("--bits", type=int, default=16)
    p.add_argument("--fabric-units", default="cell", help="comma-separated, '' for none")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    print_run_header()
    from blockray import hdl
    from blockray.rtl.lean import LeanArray
    from blockray.synth.target import ECP5Target
    from blockray.synth.yosys import yosys_command

    fabric = tuple(u for u in args.fabric_units.split(",") if u)
    name = "blockray_array"
    text = hdl.convert(LeanArray(args.bits, args.rows, args.cols), name=name, emit_src=False,
                       platform=ECP5Target(fabric))
    prefix, nodsp = (f"hierarchy -top {name}; proc; booth; ", " -nodsp") if fabric else ("", "")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-lean-area-") as tmp:
        Path(tmp, f"{name}.v").write_text(text)
        script = (f"read_verilog {name}.v; {prefix}synth_ecp5{nodsp} -noflatten -top {name}; "
                  f"tee -q -o stat.json stat -json")
        subprocess.run(yosys_command() + ["-q", "-p", script], cwd=tmp, check=True, capture_output=True)
        stat = json.loads(Path(tmp, "stat.json").read_text())
    seconds = time.perf_counter() - start
    modules = {}
    for module, data in stat["modules"].items():
        path = module.lstrip("\\")
        path = path[len(name) + 1:] if path.startswith(name + ".") else ("" if path == name else path)
        path = re.sub(r"\$\d+$", "", path)
        modules[path] = _resources(data.get("num_cells_by_type", {}))
    print(f"lean {args.rows} x {args.cols}, B = {args.bits}, fabric units {fabric or 'none'}; "
          f"Yosys synth_ecp5 -noflatten {seconds:.0f} s")
    print(f"{'module':40s} {'LUTs':>7s} {'FFs':>7s} {'DSPs':>5s}")
    for path in sorted(modules):
        r = modules[path]
        print(f"{path or '(top)':40s} {r['luts']:7d} {r['ffs']:7d} {r['dsps']:5d}")
    parts, total = {}, {"luts": 0, "ffs": 0, "dsps": 0, "brams": 0}
    for path, r in modules.items():
        part = next((label for label, pattern in PARTS if re.match(pattern, path)), "other")
        acc = parts.setdefault(part, {"luts": 0, "ffs": 0, "dsps": 0, "brams": 0, "modules": 0})
        for k in total:
            acc[k] += r[k]
            total[k] += r[k]
        acc["modules"] += 1
    print(f"\n{'part':40s} {'LUTs':>7s} {'share':>6s} {'FFs':>7s} {'DSPs':>5s}")
    for label, _ in PARTS + [("other", None)]:
        if label in parts:
            r = parts[label]
            print(f"{label:40s} {r['luts']:7d} {r['luts'] / total['luts']:6.1%} {r['ffs']:7d} {r['dsps']:5d}")
    print(f"{'total':40s} {total['luts']:7d} {'':6s} {total['ffs']:7d} {total['dsps']:5d}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": args.rows, "cols": args.cols, "bits": args.bits,
                                               "fabric_units": list(fabric), "seconds": round(seconds, 1),
                                               "modules": modules, "parts": parts, "total": total}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
