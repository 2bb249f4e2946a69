"""Full renders: traversal statistics, host time per ray, and model-vs-golden radiosity error.

    python benchmarks/bench_render.py cornell                 # full render, golden and model
    python benchmarks/bench_render.py room --max-shots 300    # capped progressive refinement
    python benchmarks/bench_render.py cornell --traversal ray --max-shots 20   # per-ray DDA

Prints one JSON line per (board, traversal) run and, when both boards ran, the RMS relative
radiosity error of the model against golden. Numbers go into docs/measurements.md by hand,
with the command line that produced them.
"""

import argparse
import json
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import render


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--boards", default="golden,model")
    ap.add_argument("--traversal", default="block", help="block, ray or block,ray")
    ap.add_argument("--max-shots", type=int, default=None)
    ap.add_argument("--voxels", type=int, default=None)
    ap.add_argument("--bits", type=int, default=None)
    ap.add_argument("--stats-fraction", type=float, default=0.02)
    ap.add_argument("--save", default=None, help="write each run's radiosity to SAVE-<board>-<traversal>.npy")
    ap.add_argument("--compare", default=None, help="a saved radiosity (.npy) to report each run's change against")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    print_run_header()
    B = {}
    for traversal in args.traversal.split(","):
        for board in args.boards.split(","):
            t0 = time.perf_counter()
            res = render(scene, backend=board, bits=args.bits, voxels=args.voxels,
                         max_shots=args.max_shots, traversal=traversal,
                         stats_fraction=args.stats_fraction)
            r = res.report
            ts = r["traversal_stats"]
            row = {k: r.get(k) for k in ("scene", "patches", "board", "traversal", "voxels", "bits", "shots",
                                         "columns_cast", "rays", "blocks", "tests", "tests_per_ray",
                                         "residual", "host_seconds_per_ray", "board_cycles",
                                         "tests_useful", "tests_issued", "utilization")}
            row.update({k: ts.get(k) for k in ("l", "n", "L", "overhead", "test_overhead")})
            row["seconds"] = {k: round(v, 3) for k, v in r["seconds"].items()}
            row["wall"] = round(time.perf_counter() - t0, 2)
            print(json.dumps(row), flush=True)
            B[(board, traversal)] = res.radiosity
            if args.save:
                np.save(f"{args.save}-{board}-{traversal}.npy", res.radiosity)
            if args.compare:
                ref = np.load(args.compare)
                print(json.dumps({"board": board, "traversal": traversal, "compared_with": args.compare,
                                  **_change(res.radiosity, ref)}), flush=True)
    for traversal in args.traversal.split(","):
        if ("golden", traversal) in B and ("model", traversal) in B:
            g, m = B[("golden", traversal)], B[("model", traversal)]
            rms = float(np.sqrt(np.mean((m - g) ** 2)) / np.sqrt(np.mean(g ** 2)))
            worst = float(np.max(np.abs(m - g).sum(1) / np.maximum(g.sum(1), 1e-30)))
            print(json.dumps({"traversal": traversal, "rms_relative_error_model_vs_golden": rms,
                              "max_patch_relative_error": worst}), flush=True)


def _change(B, ref):
    """RMS relative change of radiosity B against ref, and the largest per-patch change."""
    return {"rms_relative_change": float(np.sqrt(np.mean((B - ref) ** 2)) / np.sqrt(np.mean(ref ** 2))),
            "max_patch_relative_change": float(np.max(np.abs(B - ref).sum(1) / np.maximum(ref.sum(1), 1e-30))),
            "mean_relative_change_per_channel": ((B * 1.0).sum(0) / ref.sum(0) - 1).tolist()}


if __name__ == "__main__":
    main()
