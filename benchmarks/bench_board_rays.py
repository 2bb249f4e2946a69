"""Link bytes per ray with rays made on the board (``--traversal board``: COLUMN and RECEIVERS)
against today's block commands (``--traversal block``: BEGIN_BLOCK, LOAD_POINTS, VOXEL,
END_BLOCK), side by side, on the 1 x 2 and the 2 x 2 board.

    python benchmarks/bench_board_rays.py [--scene cornell] [--shooters 10] [--seed 1] [--boards 1x2,2x2]
                                          [--baud 3000000] [--clock 45]

One one-part board per configuration, the host driver over the framed link (blockray.framing) to
the bit-exact model (``ModelTransport``: for ``board`` the block sequencer's model makes the
blocks). The renderer's columns of ``--shooters`` random shooters to every patch (one batch per
column, as bench_ulx3s_link.py), the CLI's voxels, B and K = 8. Counted after the load: the core
bytes each way (commands; results) at the transport, and the framed link's wire bytes. The two
modes' clear fractions must be equal (checked). Rays/s through a UART moving ``baud / 10`` bytes a
second each way is bound by the busier direction (framed); the array's rate is rays per board
cycle (the records' cycles) at ``--clock``; with ``board`` the block sequencer's cycles per ray
(its model's cycle contract, docs/board-protocol.md "The sequencer's cycles": it makes the
records one thing at a time while the board runs the earlier ones).
"""

import argparse

import numpy as np

from _run_header import print_run_header
from bench_ulx3s_link import framed_board
from blockray.host_driver.scene import builtin
from blockray.host_driver.traverse.visibility import Visibility
from blockray.link import DEFAULT_BAUD
from blockray.samples import SampleScheme
from blockray.synth.bitstream import DEFAULT_FREQ_MHZ


def measure(scene, rows, cols, traversal, shooters):
    """Bytes and cycles of ``shooters``' columns on a one-part R x S board; their clear fractions."""
    samples = SampleScheme(8)
    driver, grid, cores, wires = framed_board(scene, rows, cols, traversal, samples, "bench")
    cycles0, wire0 = driver.counters()["board_cycles"], wires[0].stats()
    sequencer0 = cores[0].sequencer.cycle
    cores[0].on = True
    vis = Visibility(scene, driver, grid, samples, rows=rows, cols=cols, traversal=traversal)
    frac = np.concatenate([vis.clear_fraction(int(i), np.arange(scene.patches)) for i in shooters])
    c, wire = driver.counters(), wires[0].stats()
    driver.close()
    return {"rays": c["rays"], "blocks": c["blocks"], "cycles": c["board_cycles"] - cycles0, "bits": driver.params.bits,
            "sequencer": cores[0].sequencer.cycle - sequencer0,
            "down": cores[0].sent, "up": cores[0].received, "voxels": grid.v,
            "down_wire": wire["wire_bytes_sent"] - wire0["wire_bytes_sent"],
            "up_wire": wire["wire_bytes_received"] - wire0["wire_bytes_received"]}, frac


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cornell")
    ap.add_argument("--shooters", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--boards", default="1x2,2x2", help="R x S of each board, comma-separated")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD)
    ap.add_argument("--clock", type=float, default=DEFAULT_FREQ_MHZ, help="board clock, MHz")
    args = ap.parse_args()
    print_run_header()
    scene = builtin.load(args.scene)
    shooters = np.random.default_rng(args.seed).choice(scene.patches, args.shooters, replace=False)
    bps = args.baud / 10
    print(f"{args.scene} ({scene.patches} patches), {args.shooters} shooter columns to every patch, seed {args.seed}, "
          f"K = 8; bytes per ray after the load (framed: on the wire)")
    print("| board | traversal | B | voxels | blocks | rays | to board B/ray | to host B/ray | together | "
          "framed to board | framed to host | framed together | rays/s at 3 Mbaud | array rays/s | "
          "board cycles/ray | sequencer cycles/ray |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for shape in args.boards.split(","):
        rows, cols = (int(x) for x in shape.split("x"))
        fracs = {}
        for traversal in ("block", "board"):
            r, fracs[traversal] = measure(scene, rows, cols, traversal, shooters)
            n = r["rays"]
            down, up, fdown, fup = (r[k] / n for k in ("down", "up", "down_wire", "up_wire"))
            print(f"| {rows} x {cols} | {traversal} | {r['bits']} | {r['voxels']}^3 | {r['blocks']} | {n} | "
                  f"{down:.3f} | {up:.3f} | **{down + up:.3f}** | {fdown:.3f} | {fup:.3f} | {fdown + fup:.3f} | "
                  f"{bps / max(fdown, fup):,.0f} | {n / r['cycles'] * args.clock * 1e6:,.0f} | "
                  f"{r['cycles'] / n:.1f} | {r['sequencer'] / n if traversal == 'board' else 0:.1f} |", flush=True)
        assert np.array_equal(fracs["block"], fracs["board"]), "the two traversals' clear fractions differ"
    print(f"clear fractions of the two traversals equal on every board; array rate at {args.clock:g} MHz")


if __name__ == "__main__":
    main()
