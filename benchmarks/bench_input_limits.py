"""The measurements behind the input limits (docs/input.md).

    python benchmarks/bench_input_limits.py                 # image memory, subdivision time
    python benchmarks/bench_input_limits.py --board-depth 65536   # + one `verilog board` run

1. Peak memory of ``render_image`` per pixel (tracemalloc) beside the image's own 3 bytes per
   pixel (the ratio), at two sizes: the basis of ``image.BYTES_PER_PIXEL`` and ``--size``'s limit.
2. Seconds and triangles of ``subdivide`` on cornell at falling ``--max-edge``, beside the lower
   bound that ``--max-patches`` is checked against (the ratio count / bound).
3. With ``--board-depth N``: wall time and peak RSS of ``blockray verilog board --patch-depth N``
   in a child process (``/usr/bin/time`` style, from ``resource``), per bit of board memory: the
   basis of ``synth.verilog.MAX_MEMORY_BITS``. Slow (minutes) and memory-hungry (GBs).
"""

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc

import numpy as np

from _run_header import print_run_header

from blockray.host_driver.scene import builtin
from blockray.host_driver.render.image import render_image
from blockray.host_driver.scene.objload import subdivide, subdivision_lower_bound


def image_memory(sizes=(512, 1024)):
    scene = builtin.load("cornell")
    radiosity = np.random.default_rng(1).random((scene.patches, 3))
    print("size,peak_bytes_per_pixel,image_bytes_per_pixel,ratio,seconds")
    for n in sizes:
        tracemalloc.start()
        start = time.perf_counter()
        render_image(scene, radiosity, width=n, height=n)
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1] / (n * n)
        tracemalloc.stop()
        print(f"{n},{peak:.1f},3,{peak / 3:.1f},{seconds:.2f}")


def subdivision(edges=(50.0, 20.0, 10.0)):
    base = builtin.load("cornell", max_edge=1e9)
    print("max_edge,triangles,lower_bound,ratio,seconds")
    for edge in edges:
        start = time.perf_counter()
        count = subdivide(base, edge, max_triangles=10**7).patches
        seconds = time.perf_counter() - start
        bound = subdivision_lower_bound(base, edge)
        print(f"{edge:g},{count},{bound:.0f},{count / bound:.2f},{seconds:.2f}")


def board_conversion(depth):
    from blockray.params import BoardParams
    from blockray.synth.verilog import board_memory_bits
    bits = sum(board_memory_bits(BoardParams(patch_depth=depth)))
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "blockray.host_driver.cli", "verilog", "board", "--patch-depth", str(depth),
                        "--out", os.path.join(tmp, "board.v")], check=True)
        seconds = time.perf_counter() - start
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024      # Linux: KiB
    print("patch_depth,memory_bits,seconds,peak_rss_bytes,rss_bytes_per_bit")
    print(f"{depth},{bits},{seconds:.1f},{rss},{rss / bits:.0f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--board-depth", type=int, default=None, metavar="N")
    args = parser.parse_args()
    print_run_header()
    image_memory()
    subdivision()
    if args.board_depth:
        board_conversion(args.board_depth)


if __name__ == "__main__":
    main()
