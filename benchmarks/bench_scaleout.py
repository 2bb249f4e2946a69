"""Scale-out (the paper's section 6): K host + board sets solving one scene by gathering.

    python benchmarks/bench_scaleout.py cornell --sets 1,2,4,8
    python benchmarks/bench_scaleout.py cornell --sets 1,4 --solver jacobi --tolerance 1e-4
    python benchmarks/bench_scaleout.py cornell --sets 1,2 --in-process    # wall clock, 1 vs 2 workers

For every K the same render runs with ``--sets K`` on the bit-exact model board (each set its own
P x R x S boards, docs/scaling.md), each set on a worker of a Dask LocalCluster of min(K, cores)
worker processes (``--workers`` fixes the count), started and closed by the render.
``--in-process`` first runs the plain one-set render in this process (no cluster) as a further
reference. Printed per run (a JSON line, then a Markdown table): the machine's board cycles (the
slowest set's), the projected speed-up over the first K, the sets' spread of board cycles, sweeps
(= radiosity exchanges), bytes exchanged per sweep (the paper's 4 bytes per patch to each other
set, and what moved through Dask), utilization, rays, the radiosity's largest relative
difference from the first K, and the measured wall-clock seconds and speed-up over the first K.
"""

import argparse
import json
import os
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import render


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--sets", default="1,2,4,8", help="comma-separated K values; the first is the reference")
    ap.add_argument("--solver", default="gauss-seidel", choices=["gauss-seidel", "jacobi"])
    ap.add_argument("--tolerance", type=float, default=1e-3)
    ap.add_argument("--max-edge", type=float, default=None)
    ap.add_argument("--clock", type=float, default=95.0, help="MHz for the machine-time column")
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default min(K, cores))")
    ap.add_argument("--in-process", action="store_true", help="first run one set in this process, no cluster")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene, max_edge=args.max_edge)
    print_run_header()
    rows, ref, ref_wall, in_process_wall = [], None, None, None
    runs = ([(1, 0)] if args.in_process else []) + [
        (K, args.workers or min(K, os.cpu_count() or 1)) for K in (int(x) for x in args.sets.split(","))]
    for K, workers in runs:
        print(f"# load average before K = {K}: {os.getloadavg()[0]:.1f}", flush=True)
        t0 = time.perf_counter()
        res = render(scene, backend="model", solver=args.solver, tolerance=args.tolerance, sets=K,
                     workers=workers or None)
        wall = time.perf_counter() - t0
        r = res.report
        if ref is None:
            ref = res
        if not workers:
            in_process_wall = wall
        elif ref_wall is None:
            ref_wall = wall                 # wall speed-ups are over the first run on the cluster
        sets = r.get("set_counters") or [{"board_cycles": r["board_cycles"]}]
        cycles = [s["board_cycles"] for s in sets]
        diff = float(np.abs(res.radiosity - ref.radiosity).max() / np.abs(ref.radiosity).max())
        row = {"sets": K, "workers": workers, "patches": r["patches"], "board_cycles": r["board_cycles"],
               "set_cycles_min": min(cycles), "set_cycles_max": max(cycles),
               "sweeps": r["iterations"], "residual": r["residual"],
               "exchange_bytes_per_sweep": r["exchange_bytes_per_sweep"],
               "dask_bytes_per_sweep": (r["cluster"]["exchanged_bytes"] // r["cluster"]["exchanges"]
                                        if "cluster" in r else 0),
               "utilization": r["utilization"], "rays": r["rays"], "blocks": r["blocks"],
               "max_rel_diff_from_first": diff, "wall": round(wall, 1),
               "wall_speedup": ref_wall / wall if ref_wall else None,
               "wall_speedup_over_in_process": in_process_wall / wall if in_process_wall else None,
               "cast_seconds_per_set": [round(x, 1) for x in r["cluster"]["cast_seconds_per_set"]]
               if "cluster" in r else None,
               "cast_cpu_seconds_per_set": [round(x, 1) for x in r["cluster"]["cast_cpu_seconds_per_set"]]
               if "cluster" in r else None,
               "load_average_after": os.getloadavg()[0]}
        print(json.dumps(row), flush=True)
        rows.append(row)
    base = rows[0]["board_cycles"]
    print()
    print(f"| K sets | workers | board cycles (slowest set) | ms @ {args.clock:g} MHz | projected speed-up | "
          f"set cycles min-max | sweeps | bytes exchanged / sweep (paper) | bytes via Dask / sweep | utilization | "
          f"rays | blocks | max rel. diff from first | wall s | wall speed-up | over in-process |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for w in rows:
        print(f"| {w['sets']} | {w['workers'] or 'in-process'} | {w['board_cycles']:,} | "
              f"{w['board_cycles'] / args.clock / 1e3:.2f} | "
              f"{base / w['board_cycles']:.2f} | {w['set_cycles_min']:,}-{w['set_cycles_max']:,} | {w['sweeps']} | "
              f"{w['exchange_bytes_per_sweep']:,} | {w['dask_bytes_per_sweep']:,} | {w['utilization']:.3f} | "
              f"{w['rays']:,} | {w['blocks']:,} | {w['max_rel_diff_from_first']:.1e} | {w['wall']:.1f} | "
              + (f"{w['wall_speedup']:.2f} | " if w["wall_speedup"] else "- | ")
              + (f"{w['wall_speedup_over_in_process']:.2f} |" if w["wall_speedup_over_in_process"] else "- |"))


if __name__ == "__main__":
    main()
