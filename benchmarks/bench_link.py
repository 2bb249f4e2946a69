"""Bytes per ray on one board's link: the wire format against the paper's formula and the
fixed-width records it replaced.

    python benchmarks/bench_link.py [--scenes cornell,room] [--shooters 40] [--seed 1]

For each scene and board shape (8 x 8 array, P = 8; and a one-part 2 x 2 board) the renderer's
block rays of ``--shooters`` random shooter columns (all receivers, one batch per shooter as the
renderer sends them; seeded) go through :class:`~blockray.host_driver.board.driver.BoardDriver` over
:class:`~blockray.host_driver.board.simulated.ModelTransport` (the bit-exact model behind the link),
and the driver's ``link`` counters give the bytes on one board's link per ray: the block commands
(BEGIN_BLOCK, LOAD_POINTS, VOXEL, END_BLOCK), one READ_COUNTERS per batch, and the results
(blocked words, the batch's counter snapshot). The blocked bits are checked against
:class:`~blockray.sim.model.ModelBoard`.

Printed beside it:

* ``paper``: section 5.3's 4 l / L + 12 (R + S) / (R S) + 4 / P bytes per ray (32-bit voxel
  numbers and coordinates), with l the measured voxels per block and L the measured rays per
  block in place of R S, and R, S, P the board's;
* ``records``: the same commands as fixed-width records, as the link carried them before issue 12
  (every command ``command_layout.size`` bits, every result ``result_layout.size`` bits, and a
  READ_COUNTERS after every block), in bytes.
"""

import argparse
import platform

import numpy as np

from blockray.host_driver.scene import builtin
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.render.render import Visibility
from blockray.host_driver.board.simulated import ModelTransport
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import default_voxels
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.sim.model import ModelBoard
from blockray.timing import load_commands_needed

SHAPES = {"8x8x8": BoardParams(bits=None), "2x2x1": BoardParams(rows=2, cols=2, boards=1, bits=None)}


def measure(scene_name, shape, shooters, seed):
    scene = builtin.load(scene_name)
    samples = SampleScheme(8)
    params = SHAPES[shape]
    grid_v = default_voxels(scene.patches, parallelism=1)
    driver = BoardDriver(params, transport=lambda p, b: ModelTransport(p), name="model-link")
    driver.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, grid_v, margin=driver.margin)
    driver.load(grid)
    model = ModelBoard(params)
    model.prepare(scene, samples)
    model.load(grid)
    vis = Visibility(scene, model, grid, samples, rows=params.rows, cols=params.cols)
    rng = np.random.default_rng(seed)
    commands = 0                                  # block commands, for the fixed-record figure
    for i in rng.choice(scene.patches, shooters, replace=False):
        blocks = vis._blocks_for(int(i), np.arange(scene.patches))
        commands += sum(2 + len(b.voxels) + load_commands_needed(len(b.receiver_patch), len(b.shooter_patch))
                        for b in blocks)
        got, want = driver.run(blocks), model.run(blocks)
        assert all((g == w).all() for g, w in zip(got, want)), "blocked bits differ from the model"
    c = driver.counters()
    link = c["link"]
    proto = driver.protocol
    R, S, P = params.rows, params.cols, params.boards
    l, L = link["voxels_per_block"], link["rays_per_block"]
    paper = 4 * l / L + 12 * (R + S) / (R * S) + 4 / P
    # the old link: fixed-width records, and a READ_COUNTERS after every block (both ways)
    cmd, res = (proto.command_layout.size + 7) // 8, (proto.result_layout.size + 7) // 8
    blocks = c["blocks"]
    records = (commands + blocks) * cmd + 2 * blocks * res
    return {"scene": scene_name, "shape": shape, "patches": scene.patches, "voxels": grid_v, "bits": driver.params.bits,
            "blocks": blocks, "rays": c["rays"], "l": l, "L": L, "bytes_per_ray": link["bytes_per_ray"],
            "paper": paper, "records": records / c["rays"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="cornell,room")
    ap.add_argument("--shooters", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(f"machine: {platform.machine()}, python {platform.python_version()}; seed {args.seed}, "
          f"{args.shooters} shooter columns per scene")
    print("| scene | board | B | voxels | blocks | rays | l (voxels/block) | L (rays/block) | bytes/ray (link) "
          "| paper 4l/L + 12(R+S)/(RS) + 4/P | fixed records (before) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for scene in args.scenes.split(","):
        for shape in SHAPES:
            r = measure(scene, shape, args.shooters, args.seed)
            print(f"| {r['scene']} ({r['patches']} patches) | {r['shape']} | {r['bits']} | {r['voxels']}^3 | "
                  f"{r['blocks']} | {r['rays']} | {r['l']:.2f} | {r['L']:.2f} | **{r['bytes_per_ray']:.2f}** | "
                  f"{r['paper']:.2f} | {r['records']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
