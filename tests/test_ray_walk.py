"""The ray walker (rtl/ray_walk.py RayWalker) against the integer block walk it is the gateware of
(blockray/block_walk.py walk_block, itself checked against exact fractions in test_board_walk.py):
its boxes, expanded x outer, z inner, each voxel at its first box, are the walk's voxels of the
ray in the walk's order, one box a cycle from the cycle after the job was taken (random idle and
back-pressure, seeded), on rays through grid planes, lines and corners, axis-parallel and of zero
length, with the grid's origin inside the scene's box and the points outside the grid."""

import random

import numpy as np
from blockray.block_walk import walk_block
from blockray.rtl.ray_walk import RayWalker, walk_job_layout
from stream_bench import drive_streams

BITS = 8


def _job(rng):
    """A grid and a ray, coordinates often on the grid's planes or one off."""
    shift, v = rng.randint(0, BITS - 3), rng.randint(1, 6)     # up to grids spanning the B-bit range
    origin = [rng.randint(0, 20) for _ in range(3)]
    edge = 1 << shift

    def coordinate(c):
        k = rng.randint(-1, v + 1)
        x = origin[c] + k * edge + rng.choice((0, 0, 1, -1, rng.randrange(edge)))
        return min(max(x, 0), (1 << BITS) - 1)
    p = [coordinate(c) for c in range(3)]
    q = [coordinate(c) for c in range(3)]
    if rng.random() < 0.4:
        for c in rng.sample(range(3), rng.randint(1, 3)):
            q[c] = p[c]
    return p, q, origin, shift, v


def _xyz(a):
    return dict(zip("xyz", a))


def _expand(boxes, v):
    """The voxels of the boxes, x outer, z inner, each at its first box."""
    seen = []
    for lo, hi, empty in boxes:
        if empty:
            continue
        for ix in range(lo[0], hi[0] + 1):
            for iy in range(lo[1], hi[1] + 1):
                for iz in range(lo[2], hi[2] + 1):
                    i = (ix * v + iy) * v + iz
                    if i not in seen:
                        seen.append(i)
    return seen


def test_boxes_are_the_walks_voxels_one_a_cycle(rng_seed):
    rng = random.Random(rng_seed)
    jobs = [_job(rng) for _ in range(120)]
    dut = RayWalker(bits=BITS)
    layout = walk_job_layout(BITS)
    got, state = [], {"taken": None, "boxes": []}

    def payload(job):
        p, q, origin, shift, v = job
        return layout.const({"p": _xyz(p), "q": _xyz(q), "origin": _xyz(origin), "shift": shift, "v": v})

    def step(ctx, cycle, job):
        assert cycle < 100 * len(jobs), "the walker stopped giving boxes"         # a ray has < 30 boxes
        taken, boxes = state["taken"], state["boxes"]
        if ctx.get(dut.boxes.valid):
            assert taken is not None and cycle == taken[0] + 1 + len(boxes) + taken[1]
            if ctx.get(dut.boxes.ready):
                b = ctx.get(dut.boxes.payload)
                boxes.append((list(b.lo), list(b.hi), b.empty))
                if b.last:
                    got.append((taken[2], boxes))
                    state["taken"], state["boxes"] = taken, boxes = None, []
            else:
                state["taken"] = taken = (taken[0], taken[1] + 1, taken[2])   # a cycle waiting for ready
        elif taken is not None:
            raise AssertionError(f"no box in cycle {cycle}")
        if job is not None:
            assert taken is None                                            # one job at a time
            state["taken"] = (cycle, 0, job)

    drive_streams(dut, dut.jobs, dut.boxes, jobs, rng, step, payload=payload, until=lambda: len(got) == len(jobs))
    for (p, q, origin, shift, v), boxes in got:
        want = walk_block([p], [q], origin, shift, v, np.ones(v ** 3, np.int64), nonempty_only=False)
        assert _expand(boxes, v) == want.tolist(), (p, q, origin, shift, v)
