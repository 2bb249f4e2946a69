"""Radiosity through the simulated RTL board under Verilator: simulation speed and render wall time.

    python benchmarks/bench_rtl_render.py [--shooters 20]          # simulated cycles per second
    python benchmarks/bench_rtl_render.py --full [--report r.json] # + a complete cornell render

Part 1 builds (or reuses, cached by content) the Verilator simulation of P = 8 boards of 8 x 8
processors at the Cornell box's B (sim/rtl_harness.py), loads the Cornell partition and sends the
renderer's block rays of ``--shooters`` shooter columns (all their receivers, one batch per
shooter as the renderer does) through :class:`blockray.host_driver.driver.BoardDriver` over one
:class:`~blockray.host_driver.simulated.VerilatorTransport` per board. It checks the
blocked bits and the board cycles against the bit-exact model and prints

* simulated clock cycles per second while the simulator runs (all P boards advance together in
  each clock cycle) and the same counted in board cycles (sum over the P boards);
* the host-side overhead per batch (encoding, command file, result log, decoding);
* the bytes per ray on one board's link.

Part 2 (``--full``) renders the whole ``cornell`` scene with ``--board verilator`` (the CLI's
defaults: progressive refinement to tolerance 1e-3) and prints its wall time and phases.
"""

import argparse
import json
import platform
import time

import numpy as np

from blockray.host_driver import builtin
from blockray.host_driver.backends import make_board
from blockray.host_driver.render import Visibility, render
from blockray.host_driver.voxel import VoxelGrid, default_voxels
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.sim.model import ModelBoard


def speed(shooters):
    scene = builtin.load("cornell")
    samples = SampleScheme(8)
    params = BoardParams()
    voxels = default_voxels(scene.patches, parallelism=1)
    t0 = time.perf_counter()
    board = make_board("verilator", params)
    board.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, voxels, margin=board.margin)
    board.load(grid)
    setup = time.perf_counter() - t0
    model = ModelBoard(params)
    model.prepare(scene, samples)
    model.load(grid)
    vis = Visibility(scene, model, grid, samples, rows=params.rows, cols=params.cols)
    rng = np.random.default_rng(1)
    columns = [vis._blocks_for(int(i), np.arange(scene.patches))
               for i in rng.choice(scene.patches, shooters, replace=False)]
    trs = board.transports
    c0, s0 = max(t.cycles for t in trs), sum(t.simulator_seconds for t in trs)
    t0 = time.perf_counter()
    bits = [board.run(blocks) for blocks in columns]
    wall = time.perf_counter() - t0
    # the simulators run concurrently; collecting from each in turn, the summed waits are the wall time
    cycles, sim_seconds = max(t.cycles for t in trs) - c0, sum(t.simulator_seconds for t in trs) - s0
    expect = [model.run(blocks) for blocks in columns]
    assert all((g == e).all() for gs, es in zip(bits, expect) for g, e in zip(gs, es)), "bits differ from the model"
    rc, mc = board.counters(), model.counters()
    assert rc["board_cycles"] == mc["board_cycles"] and rc["board_cycles_per_board"] == mc["board_cycles_per_board"]
    board_cycles = sum(mc["board_cycles_per_board"])
    build = trs[0].build
    link = rc["link"]
    board.close()
    nblocks = sum(len(b) for b in columns)
    print(f"machine: {platform.machine()}, python {platform.python_version()}")
    print(f"cornell: {scene.patches} patches, {voxels}^3 voxels, B = {board.params.bits}; simulated memories "
          f"patch_depth {board.board_params.patch_depth}, voxel_depth {board.board_params.voxel_depth}")
    print(f"harness: {params.boards} boards x {params.rows} x {params.cols}; Verilator build "
          f"{build.seconds:.0f} s (cached: {build.cached}); setup incl. build, start and memory load {setup:.1f} s")
    print(f"{shooters} shooter columns, {nblocks} block rays, {cycles} clock cycles "
          f"({rc['board_cycles']} board cycles, max over boards per block)")
    print(f"simulator: {cycles / sim_seconds:,.0f} clock cycles/s ({board_cycles / sim_seconds:,.0f} board cycles/s "
          f"summed over the {params.boards} boards) in {sim_seconds:.2f} s")
    print(f"end to end through the host: {cycles / wall:,.0f} clock cycles/s; host overhead "
          f"{(wall - sim_seconds) / shooters * 1e3:.1f} ms per batch")
    print(f"link: {link['bytes_per_ray']:.2f} bytes per ray per board")
    return cycles / sim_seconds


def full(report_path):
    scene = builtin.load("cornell")
    t0 = time.perf_counter()
    res = render(scene, backend="verilator", params=BoardParams())
    wall = time.perf_counter() - t0
    r = res.report
    print(f"cornell --board verilator: {wall:.0f} s wall; {r['columns_cast']} columns, {r['blocks']} blocks, "
          f"board_cycles {r['board_cycles']}, simulated clock cycles "
          f"{max(t['simulated_clock_cycles'] for t in r['driver']['transports'])}, simulator "
          f"{sum(t['simulator_seconds'] for t in r['driver']['transports']):.0f} s; phases " +
          ", ".join(f"{k} {v:.0f} s" for k, v in r["seconds"].items()))
    if report_path:
        with open(report_path, "w") as f:
            json.dump(r, f, indent=1, default=float)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shooters", type=int, default=20, help="shooter columns for the speed measurement")
    ap.add_argument("--full", action="store_true", help="also render the whole cornell scene")
    ap.add_argument("--report", help="--full: write the render's report here")
    args = ap.parse_args()
    speed(args.shooters)
    if args.full:
        full(args.report)


if __name__ == "__main__":
    main()
