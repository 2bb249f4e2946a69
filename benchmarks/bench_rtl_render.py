"""Radiosity through the simulated RTL board: the native Verilator harness, the cocotb route and
the bit-exact model side by side on the same batches, and full renders.

    python benchmarks/bench_rtl_render.py [--shooters 20]                 # speed, three routes
    python benchmarks/bench_rtl_render.py --full [--scene cornell] [--cell lean]   # + full renders: native, model
    python benchmarks/bench_rtl_render.py --no-speed --clock [--library LIB ...]   # one idle board's clock

Part 1 loads the Cornell box on P = 8 boards of 8 x 8 processors at its B and sends the
renderer's block rays of ``--shooters`` shooter columns (one batch per shooter, as the renderer
does) through three boards:

* ``native``: ``--board verilator``, the BoardDriver over one
  :class:`~blockray.host_driver.board.native.NativeTransport` per board (the C++ loop, sim/native/;
  the commands go to each board as whole records, one a clock cycle);
* ``bytes``: the same build and transport with ``records=False``: the commands' bytes one a clock
  cycle over the board's byte stream;
* ``cocotb``: the BoardDriver over one :class:`~blockray.host_driver.board.simulated.VerilatorTransport`
  per board (one Verilator process per board under cocotb, sim/rtl_harness.py);
* ``model``: :class:`~blockray.sim.model.ModelBoard`.

Every route's blocked bits and board cycles are checked against the model. It prints per route
the build (cached or not), the set-up (start + memory load), the wall time of the batches, the
part of it the host did not wait for a board (``host s``: the driver encoding the commands and
decoding the results, while no board runs), the simulated clock cycles per second (all P boards advance together; max over the boards),
the clock cycles per CPU second of the boards' threads (summed over the boards: the model's cost
whatever shares the cores) and the board cycles per second (the model's ``board_cycles_per_board`` summed over the P boards).

Part 2 (``--full``) renders the whole scene (the CLI's defaults: progressive refinement to 1e-3)
with ``--board verilator`` and ``--board model`` (``--cell``: the processor cell of both), checks
that the radiosity and every counter are equal and prints both wall times, the native render's
CPU seconds (all threads: on a shared machine, what it would take alone) and the native board
cycles per second.

Part 3 (``--clock``) clocks one idle board of the Cornell box's fitted design (8 x 8, its B and
memory depths: part 1's build) in the native harness for ``--cycles`` cycles and prints its clock
cycles per second: the Verilated model's evaluation alone, without the link or the host.
``--library`` adds other builds of the native harness (``libblockray_native.so`` of another RTL
or build, from the build cache) to the same run, measured in turn, each ``--repeat`` times.
"""

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from blockray.cell import Cell
from blockray.host_driver.scene import builtin
from blockray.host_driver.board.backends import make_board
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.render.render import Visibility, render
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import default_voxels
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.sim.model import ModelBoard

COUNTERS = ("board_cycles", "tests_issued", "tests_useful", "board_cycles_per_board", "load_cycles_per_board",
            "tests_useful_per_board", "blocks", "rays")


def _boards(params):
    from blockray.host_driver.board.native import NativeTransport
    from blockray.host_driver.board.simulated import VerilatorTransport
    return {"native": lambda: make_board("verilator", params),
            "bytes": lambda: BoardDriver(params, name="verilator",
                                         transport=lambda p, b: NativeTransport(p, records=False)),
            "cocotb": lambda: BoardDriver(params, name="verilator-cocotb",
                                          transport=lambda p, b: VerilatorTransport(p)),
            "model": lambda: ModelBoard(params)}


def _cornell():
    """The Cornell box, its sample scheme, the default machine and the model board prepared for
    it (its B fitted)."""
    scene = builtin.load("cornell")
    samples = SampleScheme(8)
    params = BoardParams(bits=None)
    reference = ModelBoard(params)
    reference.prepare(scene, samples)
    return scene, samples, params, reference


def _loaded(board, scene, samples):
    """``board`` prepared for ``scene`` and loaded with its voxel grid (the renderer's default voxels)."""
    board.prepare(scene, samples)
    board.load(VoxelGrid(scene.patch_vertices, default_voxels(scene.patches, parallelism=1), margin=board.margin))
    return board


def speed(shooters, routes):
    scene, samples, params, reference = _cornell()
    voxels = default_voxels(scene.patches, parallelism=1)
    grid = VoxelGrid(scene.patch_vertices, voxels, margin=reference.margin)
    reference.load(grid)
    vis = Visibility(scene, reference, grid, samples, rows=params.rows, cols=params.cols)
    rng = np.random.default_rng(1)
    columns = [vis._blocks_for(int(i), np.arange(scene.patches))
               for i in rng.choice(scene.patches, shooters, replace=False)]
    expect = [reference.run(blocks) for blocks in columns]
    mc = reference.counters()
    board_cycles = sum(mc["board_cycles_per_board"])
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}, "
          f"load average {os.getloadavg()[0]:.1f} at the start")
    print(f"cornell: {scene.patches} patches, B = {reference.params.bits}, {params.boards} boards x {params.rows} x "
          f"{params.cols}; {shooters} shooter columns, {sum(len(b) for b in columns)} block rays, "
          f"{mc['board_cycles']} board cycles ({board_cycles} summed over the boards)")
    host_codec(params, scene, samples, columns)
    print(f"{'route':8} {'build s':>8} {'setup s':>8} {'batches s':>10} {'host s':>7} {'clock cycles/s':>15} "
          f"{'per CPU s':>10} {'board cycles/s':>15}")
    for name in routes:
        t0 = time.perf_counter()
        board = _loaded(_boards(params)[name](), scene, samples)
        setup = time.perf_counter() - t0
        trs = getattr(board, "transports", [])
        c0 = max((t.cycles for t in trs), default=0)
        w0 = sum(getattr(t, "simulator_seconds", 0.0) for t in trs)
        cpu0 = sum(_cpu(t) for t in trs)
        s0 = sum(t.cycles for t in trs)
        t0 = time.perf_counter()
        bits = [board.run(blocks) for blocks in columns]
        wall = time.perf_counter() - t0
        cycles = max((t.cycles for t in trs), default=0) - c0
        host = wall - (sum(getattr(t, "simulator_seconds", 0.0) for t in trs) - w0)
        cpu = sum(_cpu(t) for t in trs) - cpu0
        per_cpu = f"{(sum(t.cycles for t in trs) - s0) / cpu:,.0f}" if cpu else "-"
        rc = board.counters()
        build = trs[0].build if trs else None
        board.close()
        assert all((g == e).all() for gs, es in zip(bits, expect) for g, e in zip(gs, es)), f"{name}: bits differ"
        for key in COUNTERS:
            assert rc[key] == mc[key], f"{name}: {key} {rc[key]} != model {mc[key]}"
        built = "-" if build is None else f"{build.seconds:.0f}{' (cached)' if build.cached else ''}"
        clock = f"{cycles / wall:,.0f}" if trs else "-"
        print(f"{name:8} {built:>8} {setup:8.1f} {wall:10.2f} {host if trs else wall:7.2f} {clock:>15} "
              f"{per_cpu:>10} {board_cycles / wall:15,.0f}", flush=True)


def _cpu(transport):
    """The CPU seconds a native board's thread spent clocking it (its stats; 0 for other transports)."""
    return transport.stats().get("simulator_cpu_seconds", 0.0)


def host_codec(params, scene, samples, columns):
    """The driver's host work on part 1's batches, per record (``encode_all`` over each block's
    typed commands, ``decode_result`` per result) against in bulk (``encode_blocks``,
    ``decode_blocked``: what the driver runs), both checked to give the same bytes and bits."""
    from blockray.board import BlockBatch
    from blockray.protocol import BoardResult, ResultKind

    drv = _loaded(make_board("model-link", params), scene, samples)
    proto = drv.protocol
    times = {"per record": [0.0, 0.0], "bulk": [0.0, 0.0]}
    for blocks in columns:
        t0 = time.perf_counter()
        old = b"".join(proto.encode_all(drv.memory.block_commands(b)) for b in blocks)
        t1 = time.perf_counter()
        new = drv._block_wire(BlockBatch.from_blocks(blocks))
        t2 = time.perf_counter()
        assert old == new, "the bulk commands differ"
        times["per record"][0] += t1 - t0
        times["bulk"][0] += t2 - t1
        words = [int(w) for w in np.random.default_rng(len(blocks)).integers(0, 1 << 62, len(blocks))]
        words = [w & ((1 << params.processors) - 1) for w in words]
        wire = b"".join(proto.result_wire(BoardResult(ResultKind.BLOCKED, blocked=w)) for w in words)
        nb = proto.result_bytes(ResultKind.BLOCKED)
        t0 = time.perf_counter()
        old = [proto.decode_result(wire[k * nb:(k + 1) * nb]).blocked for k in range(len(blocks))]
        t1 = time.perf_counter()
        _, bits = proto.decode_blocked(wire, len(blocks))
        t2 = time.perf_counter()
        assert old == words and (np.packbits(bits, axis=1, bitorder="little") ==
                                 np.array([list(w.to_bytes(-(-params.processors // 8), "little")) for w in words])).all()
        times["per record"][1] += t1 - t0
        times["bulk"][1] += t2 - t1
    drv.close()
    rays = sum(len(b) for b in columns)
    for name, (enc, dec) in times.items():
        print(f"host {name}: encode {enc:.2f} s ({1e3 * enc / rays:.3f} ms a block ray), decode {dec:.2f} s "
              f"({1e3 * dec / rays:.3f} ms a result)", flush=True)


def full(scene_name, cell):
    scene = builtin.load(scene_name)
    runs = {}
    print(f"load average {os.getloadavg()[0]:.1f} at the start; cell {cell.kind}", flush=True)
    for board in ("verilator", "model"):
        t0, c0 = time.perf_counter(), time.process_time()
        runs[board] = render(scene, backend=board, params=BoardParams(bits=None), cell=cell)
        runs[board + " wall"] = time.perf_counter() - t0
        runs[board + " cpu"] = time.process_time() - c0
    v, m = runs["verilator"], runs["model"]
    assert np.array_equal(v.radiosity, m.radiosity), "radiosity differs from the model"
    for key in COUNTERS + ("utilization", "shots", "residual"):
        assert v.report[key] == m.report[key], f"{key}: {v.report[key]} != model {m.report[key]}"
    r = v.report
    transports = r["driver"]["transports"]
    clock = max(t["simulated_clock_cycles"] for t in transports)
    phases = ", ".join(f"{k} {s:.0f} s" for k, s in r["seconds"].items())
    print(f"{scene_name} ({scene.patches} patches) --board verilator: {runs['verilator wall']:.0f} s wall, "
          f"{runs['verilator cpu']:.0f} CPU s (phases {phases}); --board model: {runs['model wall']:.0f} s; radiosity "
          f"and counters equal; load average {os.getloadavg()[0]:.1f} at the end")
    print(f"  board_cycles {r['board_cycles']} ({sum(r['board_cycles_per_board'])} summed over the boards), "
          f"simulated clock cycles {clock} per board (max), {r['shots']} shots, {r['blocks']} blocks")
    board = r["seconds"]["board"]
    print(f"  {sum(r['board_cycles_per_board']) / board:,.0f} board cycles/s summed over the boards, "
          f"{clock / board:,.0f} clock cycles/s per board, over the report's board phase ({board:.0f} s)")
    cpu = sum(t["simulator_cpu_seconds"] for t in transports)
    print(f"  the boards' threads: {cpu:.0f} CPU s, "
          f"{sum(t['simulated_clock_cycles'] for t in transports) / cpu:,.0f} clock cycles per CPU second")


def clock(libraries, cycles, repeat, cell):
    from blockray.host_driver.board.native import native_build
    from blockray.sim.native import NativeBoard, NativeBuild, NativeRunError

    scene, samples, params, _ = _cornell()
    board = _loaded(make_board("model-link", params, cell=cell), scene, samples)
    params = board.board_params             # fitted to the records and voxels each board holds, as part 1's
    board.close()
    current = native_build(params, cell=cell)
    builds = {"this RTL": current}
    builds.update({str(lib): NativeBuild(Path(lib), Path(lib).parent, False, 0.0, True) for lib in libraries})
    print(f"load average {os.getloadavg()[0]:.1f}; one idle {params.rows} x {params.cols} {cell.kind} board, B = {params.bits}, "
          f"{cycles} cycles; this RTL's build {current.seconds:.0f} s{' (cached)' if current.cached else ''}")
    for _ in range(repeat):
        for name, build in builds.items():
            board = NativeBoard(build, patience=cycles)
            board.reset()
            t0 = time.perf_counter()
            try:
                board.run(b"", 1)               # no commands: clocks until its patience runs out
            except NativeRunError:
                pass
            wall = time.perf_counter() - t0
            print(f"  {name}: {board.cycles / wall:,.0f} clock cycles/s, {board.cycles / board.cpu_seconds:,.0f} "
                  f"per CPU second", flush=True)
            board.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shooters", type=int, default=20, help="shooter columns for the speed measurement")
    ap.add_argument("--routes", default="native,cocotb,model", help="comma-separated: native, bytes, cocotb, model")
    ap.add_argument("--full", action="store_true", help="also render the whole scene, native and model")
    ap.add_argument("--scene", default="cornell", help="--full: the built-in scene")
    ap.add_argument("--no-speed", action="store_true", help="skip part 1")
    ap.add_argument("--clock", action="store_true", help="one idle board's clock cycles/s in the native harness")
    ap.add_argument("--library", action="append", default=[], help="--clock: another build's libblockray_native.so")
    ap.add_argument("--cycles", type=int, default=40000, help="--clock: cycles per measurement")
    ap.add_argument("--repeat", type=int, default=3, help="--clock: measurements per build")
    ap.add_argument("--cell", default="exact", choices=["exact", "lean"], help="--full, --clock: the processor cell")
    args = ap.parse_args()
    cell = Cell(args.cell)
    if not args.no_speed:
        speed(args.shooters, args.routes.split(","))
    if args.full:
        full(args.scene, cell)
    if args.clock:
        clock(args.library, args.cycles, args.repeat, cell)


if __name__ == "__main__":
    main()
