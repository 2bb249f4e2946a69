"""Host traversal speed: registration, per-ray 3D-DDA and block-ray traversal, plus the measured
traversal statistics (l, n, L, block overhead) of block rays built the way the render loop builds
them (one shooter patch, its sample points in chunks of `cols`, receivers grouped by the voxel
of their centroid in chunks of `rows`).

    /work/venv/bin/python benchmarks/bench_traverse.py [--scene room] [--voxels V] [--shooters 20]

Prints one line per measurement; the numbers are host seconds on this machine.
"""

import argparse
import platform
import time

import numpy as np

from blockray.host_driver.scene import builtin
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import TraversalStats, default_voxels
from blockray.samples import SampleScheme


def blocks_of(grid, scene, points, shooter, rows, cols):
    """(starts, ends) of the block rays of one shooter, as the render loop forms them."""
    receivers = np.flatnonzero(np.arange(scene.patches) != shooter)
    out = []
    for _, idx in grid.group_points(scene.centroids[receivers]):
        rec = receivers[idx]
        for r0 in range(0, len(rec), rows):
            ends = scene.centroids[rec[r0:r0 + rows]]
            for s0 in range(0, len(points[shooter]), cols):
                out.append((points[shooter][s0:s0 + cols], ends))
    return out


def timed(fn, reps):
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t) / reps


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=None, help="cornell or room (default: both)")
    ap.add_argument("--voxels", type=int, default=None, help="voxels per axis (default: model, and 32)")
    ap.add_argument("--shooters", type=int, default=12, help="shooter patches to traverse from")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--rows", type=int, default=8)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(f"# {platform.processor() or platform.machine()}, python {platform.python_version()}, "
          f"numpy {np.__version__}, seed={args.seed}")
    rng = np.random.default_rng(args.seed)
    scheme = SampleScheme(args.samples)
    for name in ([args.scene] if args.scene else ["cornell", "room"]):
        scene = builtin.load(name)
        N = scene.patches
        points = scheme.points(scene.patch_vertices)
        model_v = default_voxels(N, parallelism=args.rows * args.cols * 8)
        vs = [args.voxels] if args.voxels else sorted({model_v, default_voxels(N), 32})
        for v in vs:
            t = time.perf_counter()
            grid = VoxelGrid(scene.patch_vertices, v)
            t_reg = time.perf_counter() - t
            print(f"{name}: N={N} v={v} register {t_reg * 1e3:.1f} ms, "
                  f"{grid.count.sum()} registrations, {np.count_nonzero(grid.count)} occupied voxels")
            shooters = rng.choice(N, min(args.shooters, N), replace=False)
            blocks = [b for i in shooters for b in blocks_of(grid, scene, points, i, args.rows, args.cols)]
            rays = sum(len(s) * len(e) for s, e in blocks)
            t = time.perf_counter()
            for s, e in blocks:
                grid.block_voxels(s, e)
            t_block = time.perf_counter() - t
            print(f"  block_voxels: {len(blocks)} blocks, {rays / len(blocks):.1f} rays/block, "
                  f"{t_block / len(blocks) * 1e6:.0f} us/call, {t_block / rays * 1e6:.2f} us/ray")
            t = time.perf_counter()
            grid.block_voxels_many(blocks)
            t_many = time.perf_counter() - t
            print(f"  block_voxels_many: {t_many / len(blocks) * 1e6:.0f} us/block, "
                  f"{t_many / rays * 1e6:.2f} us/ray")
            pairs = [(blocks[k][0][0], blocks[k][1][0]) for k in rng.choice(len(blocks), 300)]
            t = time.perf_counter()
            for p, q in pairs:
                grid.ray_voxels(p, q)
            t_ray = (time.perf_counter() - t) / len(pairs)
            print(f"  ray_voxels: {t_ray * 1e6:.0f} us/call (= us/ray)")
            stats = TraversalStats(grid)
            sample = rng.choice(len(blocks), min(150, len(blocks)), replace=False)
            for k in sample:
                s, e = blocks[k]
                stats.add_block(grid.block_voxels(s, e), s, e, sample=True)
            st = stats.summary()
            print(f"  stats over {st['sampled_blocks']} blocks / {st['sampled_rays']} rays: "
                  f"l={st['l']:.2f} n={st['n']:.2f} L={st['L']:.2f} "
                  f"overhead={st['overhead']:.2f} test_overhead={st['test_overhead']:.2f}")
    # registration at scale: a room subdivided to about 30 000 patches
    scene = builtin.load("room", max_edge=0.2)
    t = time.perf_counter()
    grid = VoxelGrid(scene.patch_vertices, 32)
    print(f"room max_edge=0.2: N={scene.patches} v=32 register {(time.perf_counter() - t):.2f} s, "
          f"{grid.count.sum()} registrations")


if __name__ == "__main__":
    main()
