"""Scale-out (the paper's section 6): K host + board sets solving one scene by gathering.

    python benchmarks/bench_scaleout.py cornell --sets 1,2,4,8
    python benchmarks/bench_scaleout.py cornell --sets 1,4 --solver jacobi --tolerance 1e-4

For every K the same render runs with ``--sets K`` on the bit-exact model board (each set its own
P x R x S boards, docs/scaling.md). Printed per K (a JSON line, then a Markdown table): the
machine's board cycles (the slowest set's), the speed-up over K = 1, the sets' spread of board
cycles, sweeps (= radiosity exchanges), bytes exchanged per sweep, utilization, rays, and the
radiosity's largest relative difference from K = 1.
"""

import argparse
import json
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.objload import load_scene
from blockray.host_driver.render import render


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--sets", default="1,2,4,8", help="comma-separated K values; the first is the reference")
    ap.add_argument("--solver", default="gauss-seidel", choices=["gauss-seidel", "jacobi"])
    ap.add_argument("--tolerance", type=float, default=1e-3)
    ap.add_argument("--max-edge", type=float, default=None)
    ap.add_argument("--clock", type=float, default=95.0, help="MHz for the machine-time column")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene, max_edge=args.max_edge)
    print_run_header()
    rows, ref = [], None
    for K in (int(x) for x in args.sets.split(",")):
        t0 = time.perf_counter()
        res = render(scene, board="model", solver=args.solver, tolerance=args.tolerance, sets=K)
        r = res.report
        if ref is None:
            ref = res
        sets = r.get("set_counters") or [{"board_cycles": r["board_cycles"]}]
        cycles = [s["board_cycles"] for s in sets]
        diff = float(np.abs(res.radiosity - ref.radiosity).max() / np.abs(ref.radiosity).max())
        row = {"sets": K, "patches": r["patches"], "board_cycles": r["board_cycles"],
               "set_cycles_min": min(cycles), "set_cycles_max": max(cycles),
               "sweeps": r["iterations"], "residual": r["residual"],
               "exchange_bytes_per_sweep": r["exchange_bytes_per_sweep"],
               "utilization": r["utilization"], "rays": r["rays"], "blocks": r["blocks"],
               "max_rel_diff_from_first": diff, "wall": round(time.perf_counter() - t0, 1)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    base = rows[0]["board_cycles"]
    print()
    print(f"| K sets | board cycles (slowest set) | ms @ {args.clock:g} MHz | speed-up | set cycles min-max | "
          f"sweeps | bytes exchanged / sweep | utilization | rays | blocks | max rel. diff from K = {rows[0]['sets']} |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for w in rows:
        print(f"| {w['sets']} | {w['board_cycles']:,} | {w['board_cycles'] / args.clock / 1e3:.2f} | "
              f"{base / w['board_cycles']:.2f} | {w['set_cycles_min']:,}-{w['set_cycles_max']:,} | {w['sweeps']} | "
              f"{w['exchange_bytes_per_sweep']:,} | {w['utilization']:.3f} | {w['rays']:,} | {w['blocks']:,} | "
              f"{w['max_rel_diff_from_first']:.1e} |")


if __name__ == "__main__":
    main()
