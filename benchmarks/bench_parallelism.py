"""The paper's figures 2 and 4: time per ray against parallelism P x R x S, measured.

    python benchmarks/bench_parallelism.py room --max-shots 40
    python benchmarks/bench_parallelism.py room --max-shots 40 --configs 1x1x1,2x2x2,8x8x8 --voxels hw

For every configuration ``PxRxS`` (P boards, each an R x S array) the same progressive render runs
on the bit-exact model board, which counts the RTL's board cycles exactly (docs/board-protocol.md).
Printed per configuration (one JSON line, then a Markdown table): rays, blocks, board cycles,
board cycles per ray, the board's time per ray at the paper's 50 MHz and at ``--clock`` MHz,
utilization, the host's measured traversal seconds per ray, and the paper's cost model
(eq. 5 with t_I0 / (P R S), host constants of 1995) for the same v. The last line fits
``cycles/ray ~ (P R S)^-a`` by least squares on log-log (the paper: time falls as
parallelism^0.6-0.7, figure 2; 0.12 us per ray at P = R = S = 8 on its 3013-patch room, figure 4).

``--voxels``: an integer (every configuration on the same grid), ``default`` (the renderer's
default, the cost model at parallelism 1) or ``hw`` (the cost model's optimum for each
configuration's P R S, as the paper chooses v).

``--plot DIR`` also draws the two figures (matplotlib, the ``[plot]`` extra): ``DIR/paper-fig2.png``,
board time per ray against P R S beside the paper's cost model (eq. 5 with t_I0 / (P R S)) for the
same v, and ``DIR/paper-fig4.png``, the board's and the host's time per ray against P R S beside the
paper's machine (0.12 us per ray at P = R = S = 8, 34 us for its host alone).
"""

import argparse
import json
import sys
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import render
from blockray.host_driver.traverse.cost import cost_model, default_voxels
from blockray.params import BoardParams

DEFAULT_CONFIGS = "1x1x1,1x2x2,2x2x2,2x4x4,4x4x4,4x8x8,8x8x8"


def parse_configs(text):
    out = []
    for item in text.split(","):
        try:
            p, r, s = (int(x) for x in item.lower().split("x"))
        except ValueError:
            sys.exit(f"bench_parallelism: --configs: {item!r} is not PxRxS (e.g. 8x8x8)")
        out.append((p, r, s))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--configs", default=DEFAULT_CONFIGS, help="comma-separated PxRxS")
    ap.add_argument("--max-shots", type=int, default=40)
    ap.add_argument("--voxels", default="default", help="an integer, 'default' or 'hw'")
    ap.add_argument("--bits", type=int, default=None)
    ap.add_argument("--clock", type=float, default=95.0, help="MHz for the second time column")
    ap.add_argument("--partition", default="deal", choices=["deal", "patch"])
    ap.add_argument("--plot", metavar="DIR", help="write paper-fig2.png and paper-fig4.png into DIR")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    print_run_header()
    rows = []
    for P, R, S in parse_configs(args.configs):
        params = BoardParams(rows=R, cols=S, boards=P)
        if args.voxels == "hw":
            v = default_voxels(scene.patches, parallelism=P * R * S)
        elif args.voxels == "default":
            v = None
        else:
            v = int(args.voxels)
        t0 = time.perf_counter()
        res = render(scene, backend="model", params=params, bits=args.bits, voxels=v,
                     max_shots=args.max_shots, partition=args.partition, stats_fraction=0.0)
        r = res.report
        rays, cycles = r["rays"], r["board_cycles"]
        row = {"P": P, "R": R, "S": S, "PRS": P * R * S, "voxels": r["voxels"], "shots": r["shots"],
               "rays": rays, "blocks": r["blocks"], "board_cycles": cycles,
               "cycles_per_ray": cycles / rays, "us_per_ray_50MHz": cycles / rays / 50.0,
               f"us_per_ray_{args.clock:g}MHz": cycles / rays / args.clock,
               "utilization": r["utilization"],
               "traverse_s_per_ray": r["seconds"]["traverse"] / rays,
               "paper_model_us_per_ray": float(cost_model(r["voxels"], scene.patches, P * R * S)),
               "wall": round(time.perf_counter() - t0, 1)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    base = rows[0]["cycles_per_ray"]
    print()
    print(f"| P x R x S | PRS | v | rays | blocks | board cycles | cycles/ray | us/ray @ 50 MHz | "
          f"us/ray @ {args.clock:g} MHz | speed-up | utilization | host traverse us/ray | paper eq. 5 us/ray |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for w in rows:
        print(f"| {w['P']} x {w['R']} x {w['S']} | {w['PRS']} | {w['voxels']} | {w['rays']:,} | {w['blocks']:,} | "
              f"{w['board_cycles']:,} | {w['cycles_per_ray']:.4f} | {w['us_per_ray_50MHz']:.5f} | "
              f"{w[f'us_per_ray_{args.clock:g}MHz']:.5f} | {base / w['cycles_per_ray']:.1f} | "
              f"{w['utilization']:.3f} | {w['traverse_s_per_ray'] * 1e6:.2f} | {w['paper_model_us_per_ray']:.3f} |")
    if len(rows) >= 2:
        x = np.log([w["PRS"] for w in rows])
        y = np.log([w["cycles_per_ray"] for w in rows])
        slope = np.polyfit(x, y, 1)[0]
        print(f"\nfit: board cycles per ray ~ (P R S)^{slope:.3f}  (the paper: time ~ parallelism^-0.6 to -0.7)")
        if args.plot:
            plot(rows, slope, args.plot, f"{args.scene}, {scene.patches} patches, --max-shots {args.max_shots}")


#: the paper's machine (figure 4): time per ray at P = R = S = 8 and on its host alone, us
PAPER_US_PER_RAY, PAPER_HOST_US_PER_RAY = 0.12, 34.0


def plot(rows, slope, folder, what):
    import os
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    os.makedirs(folder, exist_ok=True)
    prs = [w["PRS"] for w in rows]

    def figure(name, title, draw):
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        ax.plot(prs, [w["us_per_ray_50MHz"] for w in rows], "o-", label=draw(ax))
        ax.set(xscale="log", yscale="log", xlabel="parallelism P x R x S", ylabel="time per ray (us)",
               title=f"{title}\n{what}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(os.path.join(folder, name), dpi=120)
        plt.close(fig)

    def fig2(ax):
        ax.plot(prs, [w["paper_model_us_per_ray"] for w in rows], "s--", label="paper's eq. 5: board and host traversal (1995 constants), same v")
        return f"blockray board at 50 MHz (slope {slope:.2f})"

    def fig4(ax):
        ax.plot(prs, [w["traverse_s_per_ray"] * 1e6 for w in rows], "^-", label="blockray host traversal (this machine)")
        ax.plot([512], [PAPER_US_PER_RAY], "r*", markersize=12, label="paper: 8 x 8 x 8, 0.12 us")
        ax.axhline(PAPER_HOST_US_PER_RAY, color="gray", ls=":", label="paper: host alone, 34 us")
        return "blockray board at 50 MHz"

    figure("paper-fig2.png", "Figure 2: time per ray against parallelism", fig2)
    figure("paper-fig4.png", "Figure 4: the machine's time per ray", fig4)


if __name__ == "__main__":
    main()
