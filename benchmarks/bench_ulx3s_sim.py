"""``--board ulx3s-sim``'s two virtual serial ports side by side: the native one (the top and the
port in one C++ loop, sim/native/uart_harness.cpp) and the cocotb one (sim/uart_cocotb.py), on
the same render, alternating, with the model's result as the check.

    python benchmarks/bench_ulx3s_sim.py [--repeat 2] [--max-edge 1.5] [--shots 2]

The scene is tests/test_ulx3s_sim.py's small room (a closed box with a block, ``--max-edge``),
rendered on a 2 x 2 x 1 board at B = 10, 4 samples, 3^3 voxels. Builds are made (or taken from
the cache) before the timed runs. Each run's wall time is printed, then the best of each port
and their ratio.
"""

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

import _shared  # noqa: F401  (tests/ on the path)
from scenes import room_scene
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.board.uart_sim import SIM_DIVISOR, UartSimTransport
from blockray.host_driver.render.render import render
from blockray.params import BoardParams
from blockray.rtl.core import BoardCore


def _transport(native):
    def make(params, board):
        return UartSimTransport(BoardCore(params), divisor=SIM_DIVISOR, board=board, native=native,
                                name="blockray_ulx3s_sim")
    return make


def _render(scene, params, native, kw):
    board = BoardDriver(params, name="ulx3s-sim", transport=_transport(native))
    try:
        t = time.perf_counter()
        result = render(scene, board=board, params=params, bits=params.bits, **kw)
        return result, time.perf_counter() - t
    finally:
        board.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--max-edge", type=float, default=1.5)
    ap.add_argument("--shots", type=int, default=2)
    args = ap.parse_args()
    params = BoardParams(rows=2, cols=2, boards=1, bits=10)
    kw = dict(samples=4, max_shots=args.shots, voxels=3)
    scene = room_scene(Path(tempfile.mkdtemp()), args.max_edge)
    model = render(scene, backend="model", params=params, bits=params.bits, **kw)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; "
          f"{scene.patches} patches, {model.report['rays']} rays, {model.report['board_cycles']} board cycles")
    for native in (True, False):        # builds (or cache hits), untimed
        _render(scene, params, native, kw)
    best = {True: float("inf"), False: float("inf")}
    for i in range(args.repeat):
        for native in (True, False):
            result, seconds = _render(scene, params, native, kw)
            assert np.array_equal(result.radiosity, model.radiosity), "the port changed the render"
            best[native] = min(best[native], seconds)
            print(f"run {i}: {'native' if native else 'cocotb'} {seconds:.2f} s wall")
    print(f"best: native {best[True]:.2f} s, cocotb {best[False]:.2f} s; native is "
          f"{best[False] / best[True]:.1f}x faster")


if __name__ == "__main__":
    main()
