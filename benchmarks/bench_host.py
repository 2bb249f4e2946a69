"""Host time per ray by phase, and Embree answering the same occlusion queries (the peer).

    python benchmarks/bench_host.py                          # cornell (full), room (300 shots)
    python benchmarks/bench_host.py room --max-shots 0       # room, full render
    python benchmarks/bench_host.py cornell --threads 1

For each scene, one ``--board model`` render (progressive refinement, default options otherwise)
with every phase timed, wall clock and CPU time of the whole process (all threads), per ray:
form factors, commands (packing block rays), traverse (block traversal + traversal statistics),
board (the model board's compiled kernel), solve (the solver's own arithmetic). CPU time is the
figure on this shared machine: CPU microseconds per ray = microseconds per ray per core.

Then Embree (embreex, ``pip install blockray[bench]``) answers the same occlusion queries: the
rays the render cast (at most ``--embree-rays`` of them, whole batches drawn with a fixed seed),
from the float sample point to the receiver's centroid, shortened by 1e-4 at both ends (so a ray
does not hit its own end patches). Printed: its CPU microseconds per ray, the render's rays per
CPU second against Embree's (the ratio), and how often Embree's answer equals the model board's
(they differ by the board's quantisation and Embree's float arithmetic at grazing rays).
One JSON line per scene; docs/measurements.md records them with the command.
"""

import argparse
import json
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import make_board, render
from blockray.params import BoardParams

PHASES = ("formfactor", "commands", "traverse", "board", "solve")


def recorded_render(scene, max_shots, threads, stats_fraction):
    """A model-board render that keeps every batch of block rays and its bits."""
    board = make_board("model", BoardParams(bits=None))
    batches = []
    run = board.run

    def recording_run(blocks):
        bits = run(blocks)
        batches.append((blocks, bits))
        return bits
    board.run = recording_run
    res = render(scene, board=board, max_shots=max_shots or None, threads=threads, stats_fraction=stats_fraction)
    return res, board, batches


def queries(scene, board, batches, cap, seed=13):
    """Float end points (P, Q) and the model's bits of the rays of whole batches drawn at random
    until ``cap`` rays."""
    rng = np.random.default_rng(seed)
    points = board.samples.points(scene.patch_vertices)
    P, Q, bits, n = [], [], [], 0
    for k in rng.permutation(len(batches)):
        blocks, b = batches[k]
        R, S = blocks.rows, blocks.cols
        rays = R * S
        block = np.repeat(np.arange(len(blocks)), rays)
        local = np.arange(rays.sum()) - np.repeat(np.cumsum(rays) - rays, rays)
        r, s = np.divmod(local, S[block])
        col = blocks.col_off[block] + s
        P.append(points[blocks.shooter_patch[col], blocks.shooter_sample[col]])
        Q.append(scene.centroids[blocks.receiver_patch[blocks.row_off[block] + r]])
        bits.append(b.flat)
        n += len(local)
        if n >= cap:
            break
    return np.concatenate(P), np.concatenate(Q), np.concatenate(bits)


def link(board, batches):
    """Bytes per ray on one board's link in the compact wire format (blockray.protocol): every
    block's BEGIN_BLOCK, LOAD_POINTS (the last one partly filled), one VOXEL per nonempty voxel and
    END_BLOCK, and its result; and the board cycles per ray."""
    from blockray.protocol import BoardProtocol, Op, ResultKind
    from blockray.timing import POINTS_PER_LOAD
    proto = BoardProtocol(board.params)
    size = lambda op, points=POINTS_PER_LOAD: proto.command_bytes(op, points)     # noqa: E731
    commands = command_bytes = results = rays = 0
    for blocks, _ in batches:
        points = blocks.rows + blocks.cols
        full, rest = points // POINTS_PER_LOAD, points % POINTS_PER_LOAD
        voxels = np.diff(blocks.vox_off)
        partial = np.array([0] + [size(Op.LOAD_POINTS, k) for k in range(1, POINTS_PER_LOAD)])
        command_bytes += int((size(Op.BEGIN_BLOCK) + size(Op.END_BLOCK) + full * size(Op.LOAD_POINTS)
                              + partial[rest] + voxels * size(Op.VOXEL)).sum())
        commands += int((2 + full + (rest > 0) + voxels).sum())
        results += len(blocks)
        rays += blocks.rays
    result_bytes = proto.result_bytes(ResultKind.BLOCKED)
    return {"result_bytes": result_bytes, "commands_per_ray": round(commands / rays, 4),
            "link_bytes_per_ray": round((command_bytes + results * result_bytes) / rays, 3),
            "board_cycles_per_ray": round(board.counters()["board_cycles"] / rays, 4)}


def traverse_only(scene, board, batches, voxels, threads):
    """CPU us per ray of the block traversal kernel alone (VoxelGrid.traverse_blocks, no packing,
    no statistics) on the render's batches, one call per batch as the render makes them."""
    from blockray import threads as host_threads
    from blockray.host_driver.traverse.voxel import VoxelGrid
    grid = VoxelGrid(scene.patch_vertices, voxels, margin=board.margin)
    points = board.samples.points(scene.patch_vertices)
    inputs = [(points[b.shooter_patch, b.shooter_sample], b.col_off, scene.centroids[b.receiver_patch], b.row_off)
              for b, _ in batches]
    with host_threads.using(threads):
        c0 = time.process_time()
        for P, po, Q, qo in inputs:
            grid.traverse_blocks(P, po, Q, qo, nonempty_only=True)
        cpu = time.process_time() - c0
    return round(cpu / sum(b.rays for b, _ in batches) * 1e6, 4)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", default=["cornell", "room"])
    ap.add_argument("--max-shots", type=int, default=None,
                    help="progressive shots (default: cornell full, room 300; 0: full)")
    ap.add_argument("--threads", type=int, default=None, help="host threads (default: all cores)")
    ap.add_argument("--embree-rays", type=int, default=2_000_000)
    ap.add_argument("--stats-fraction", type=float, default=0.02,
                    help="blocks whose rays the traversal statistics also walk by DDA (render's default 0.02)")
    ap.add_argument("--parallel-min-rays", type=int, default=None,
                    help="batches of at least this many rays run on the thread pool (default: threads.PARALLEL_MIN_RAYS)")
    args = ap.parse_args(argv)
    if args.parallel_min_rays is not None:
        from blockray import threads as host_threads
        host_threads.PARALLEL_MIN_RAYS = args.parallel_min_rays
    print_run_header()
    for name in args.scenes:
        scene = load_scene(name)
        shots = args.max_shots if args.max_shots is not None else (300 if name == "room" else 0)
        # loading the compiled kernels (from numba's disk cache, or compiling them on a fresh
        # machine) is once per process: done here, by a one-shot render, and reported apart
        t0 = time.perf_counter()
        render(scene, backend="model", max_shots=1, threads=args.threads)
        warmup = time.perf_counter() - t0
        t0 = time.perf_counter()
        res, board, batches = recorded_render(scene, shots, args.threads, args.stats_fraction)
        wall = time.perf_counter() - t0
        r = res.report
        rays = r["rays"]
        import numba
        row = {"scene": name, "threading_layer": numba.threading_layer(), "patches": r["patches"], "voxels": r["voxels"], "shots": r["shots"],
               "threads": r["threads"], "rays": rays, "tests": r["tests"], "render_wall_s": round(wall, 2), "warmup_wall_s": round(warmup, 2),
               "total_cpu_s": round(r["cpu_seconds"]["total"], 2),
               "cpu_us_per_ray": {p: round(r["cpu_seconds"][p] / rays * 1e6, 4) for p in PHASES},
               "wall_us_per_ray": {p: round(r["seconds"][p] / rays * 1e6, 4) for p in PHASES},
               "board_M_tests_per_cpu_s": round(r["tests"] / max(r["cpu_seconds"]["board"], 1e-9) / 1e6, 1)}
        host_cpu = sum(r["cpu_seconds"][p] for p in ("commands", "traverse", "board"))
        row["traverse_commands_cpu_us_per_ray"] = round(
            (r["cpu_seconds"]["traverse"] + r["cpu_seconds"]["commands"]) / rays * 1e6, 4)
        row["link"] = link(board, batches)
        row["traverse_kernel_only_cpu_us_per_ray"] = traverse_only(scene, board, batches, r["voxels"], args.threads)
        row["visibility_rays_per_cpu_s"] = round(rays / host_cpu)                   # commands + traverse + board
        row["render_rays_per_cpu_s"] = round(rays / r["cpu_seconds"]["total"])      # the whole render
        try:
            P, Q, bits = queries(scene, board, batches, args.embree_rays)
            from blockray.host_driver.traverse.peer import embree_occluded
            hit, e_wall, e_cpu, build = embree_occluded(scene, P, Q)
            row["embree"] = {"rays": len(P), "cpu_us_per_ray": round(e_cpu / len(P) * 1e6, 4),
                             "wall_us_per_ray": round(e_wall / len(P) * 1e6, 4), "build_cpu_s": round(build, 3),
                             "agreement_with_model": round(float((hit == bits).mean()), 5)}
            # the figure: rays per CPU second of the simulated host + board against Embree's
            row["visibility_over_embree"] = round(row["visibility_rays_per_cpu_s"] * e_cpu / len(P), 4)
            row["render_over_embree"] = round(row["render_rays_per_cpu_s"] * e_cpu / len(P), 4)
        except ImportError:
            row["embree"] = "embreex not installed (pip install blockray[bench])"
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
