"""Seconds to write one checkpoint (host_driver/render/checkpoint.py) of a progressive solve of N
patches: atomically (temporary file, fsync, rename; what --checkpoint does) side by side with
its peer, a plain ``numpy.savez`` over the same file (no fsync, no rename), in one run.

    python benchmarks/bench_checkpoint.py [--patches 30000] [--repeats 10] [--folder DIR]
"""

import argparse
import os
import tempfile
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.render.checkpoint import FILE, Checkpoint


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patches", type=int, default=30000)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--folder", default=None, help="where to write (default: a new folder under the temp dir)")
    args = ap.parse_args()
    print_run_header()
    n, rng = args.patches, np.random.default_rng(1)
    state = {"solver": "progressive", "B": rng.random((n, 3)), "U": rng.random((n, 3)), "energy": rng.random(n),
             "shots": 1000, "iterations": 0, "history": rng.random(1001), "row_sums": np.zeros(4)}
    folder = args.folder or tempfile.mkdtemp(prefix="bench-checkpoint-")
    saver = Checkpoint(save_to=folder, interval=0)
    saver.meta = {"format": 1, "scene": "bench", "scene_hash": "0", "options": {}}
    saver.columns = lambda: range(n)
    atomic, plain = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        saver.save(state, force=True)
        atomic.append(time.perf_counter() - t)
        t = time.perf_counter()
        with open(os.path.join(folder, "plain-" + FILE), "wb") as f:
            np.savez(f, **{k: v for k, v in state.items()})
        plain.append(time.perf_counter() - t)
    size = os.path.getsize(os.path.join(folder, FILE))
    print(f"{n} patches, {size / 1e6:.2f} MB: atomic (fsync + rename) median {np.median(atomic) * 1e3:.1f} ms, "
          f"plain savez median {np.median(plain) * 1e3:.1f} ms ({args.repeats} each, {folder})")


if __name__ == "__main__":
    main()
