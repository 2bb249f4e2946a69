"""The certified edge filter (blockray/filtered.py): verification against the exact reference and
its undecided rate on real renders.

    python benchmarks/bench_filter.py --part verify --queries 10000000      # >= 10**7 queries
    python benchmarks/bench_filter.py --part rate --scene cornell --max-shots 40
    python benchmarks/bench_filter.py --part rate --scene room --max-shots 40

``verify``: random and hard-case queries (the batches of ``bench_model.py --part exact``:
quantised random scenes, rays through a closed cube's vertices and edges, hard random triangles
at random B), each answered by :func:`blockray.exact.blocked_reference` (Python integers) once
and by every filter width: ``wrong`` counts decided answers that differ from the reference (must
be 0), ``result`` counts disagreements of the filtered cell's output (the filter's answer where
decided, the exact unit's, ``blocked_block``, elsewhere), also 0.

``rate``: a progressive render with the bit-exact model board; every test the board's processors
see (each block ray against each patch record of its voxels, the tests the model's
``tests_useful`` counts) also goes through the filter at each width. Prints the undecided
fraction, the fraction among plane-crossing tests, and per broadcast cycle (one record against
the block's R x S rays) the fraction of cycles with an undecided test and the most undecided
tests in one cycle (what the queue to the exact unit must absorb).
"""

import argparse
import sys
import time

import numpy as np

from blockray.exact import blocked_block, blocked_reference, patch_normals, plane_crossing, plane_sides, edge_terms
from blockray.filtered import FilterFormat, filter_decision, filtered_block

from _run_header import print_run_header
from bench_model import batch_hard, batch_mesh, batch_scene

FORMATS = [FilterFormat.square(b) for b in (9, 12, 14)] + [FilterFormat(17, 18)]


def part_verify(queries, seed, formats):
    rng = np.random.default_rng(seed)
    print(f"verify: seed={seed}, target {queries} queries, filters {', '.join(map(str, formats))}", flush=True)
    kinds = {"scene": batch_scene, "mesh": batch_mesh, "hard": batch_hard}
    count = dict.fromkeys(kinds, 0)
    stats = {str(f): {"undecided": 0, "wrong": 0, "result": 0} for f in formats}
    total, t0, next_print = 0, time.perf_counter(), 10 ** 6
    while total < queries:
        for name, make in kinds.items():
            P, Q, V, bits = make(rng)
            n = patch_normals(V)
            Pl, Ql, Vl = P.tolist(), Q.tolist(), V.tolist()
            ref = np.array([[[blocked_reference(p, q, *t) for t in Vl] for p in Pl] for q in Ql], dtype=bool)
            exact = blocked_block(P, Q, V, n)
            for f in formats:
                decided, blocked = filtered_block(P, Q, V, n, f)
                s = stats[str(f)]
                s["undecided"] += int((~decided).sum())
                s["wrong"] += int((decided & (blocked != ref)).sum())
                s["result"] += int((np.where(decided, blocked, exact) != ref).sum())
            count[name] += ref.size
            total += ref.size
        if total >= next_print:
            print(f"  {total} queries, {time.perf_counter() - t0:.0f} s", flush=True)
            next_print += 10 ** 6
    print(f"{total} queries ({', '.join(f'{k} {v}' for k, v in count.items())}) in {time.perf_counter() - t0:.0f} s")
    print(f"{'filter':10s} {'undecided':>10s} {'rate':>9s} {'wrong':>6s} {'result disagreements':>21s}")
    for f, s in stats.items():
        print(f"{f:10s} {s['undecided']:10d} {s['undecided'] / total:9.2e} {s['wrong']:6d} {s['result']:21d}")
    return 1 if any(s["wrong"] or s["result"] for s in stats.values()) else 0


def voxel_records(grid):
    """The patch records of each voxel of ``grid`` (its registration), as the board streams them."""
    from blockray.memory import registration
    vox, pat, nvox = registration(grid)
    return np.split(pat, np.cumsum(np.bincount(vox, minlength=nvox))[:-1])


def block_tests(records, quantised, blocks):
    """(P, Q, V, n) of each block with rays and records: the tests the model board answers."""
    q = quantised
    for block in blocks:
        recs = [records[v] for v in block.voxels]
        patches = np.concatenate(recs) if recs else np.zeros(0, dtype=np.int64)
        if not len(patches) or not block.rays:
            continue
        yield (q.shooters[block.shooter_patch, block.shooter_sample], q.receivers[block.receiver_patch],
               q.vertices[patches], q.normals[patches])


def _filter_board(formats):
    """A ModelBoard that also runs every test it answers through the filters (Board interface
    only: the tests are rebuilt from the blocks and the grid's registration)."""
    from blockray.sim.model import ModelBoard

    class FilterCountingBoard(ModelBoard):
        def load(self, grid):
            super().load(grid)
            self._records = voxel_records(grid)
            self.filter_stats = {str(f): dict.fromkeys(
                ("tests", "crossing", "undecided", "cycles", "cycles_undecided", "max_per_cycle"), 0)
                for f in formats}

        def run(self, blocks):
            for P, Q, V, n in block_tests(self._records, self.quantised, blocks):
                dP, dQ, w = edge_terms(P, Q, V)
                pP, pQ = plane_sides(dP, dQ, n)
                crossing = plane_crossing(pP, pQ)
                for f in formats:
                    decided, _ = filter_decision(dP[None], pP[None], w[:, None], pQ[:, None], f)
                    per_cycle = (~decided).sum(axis=(0, 1))              # per record
                    s = self.filter_stats[str(f)]
                    s["tests"] += decided.size
                    s["crossing"] += int(crossing.sum())
                    s["undecided"] += int(per_cycle.sum())
                    s["cycles"] += len(V)
                    s["cycles_undecided"] += int((per_cycle > 0).sum())
                    s["max_per_cycle"] = max(s["max_per_cycle"], int(per_cycle.max()))
            return super().run(blocks)

    return FilterCountingBoard


def part_rate(scene_name, max_shots, bits, formats):
    from blockray.host_driver.scene.builtin import load_scene
    from blockray.host_driver.render.render import render
    from blockray.params import BoardParams
    scene = load_scene(scene_name)
    board = _filter_board(formats)(BoardParams(bits=bits))
    t0 = time.perf_counter()
    result = render(scene, board=board, params=BoardParams(bits=bits), max_shots=max_shots)
    r = result.report
    print(f"rate: {scene_name}, {r['patches']} patches, B = {board.quantised.bits}, {r['shots']} shots, "
          f"{r['blocks']} blocks, {r['tests']} tests (model tests_useful), {time.perf_counter() - t0:.0f} s")
    print(f"{'filter':10s} {'tests':>10s} {'undecided':>10s} {'rate':>9s} {'of crossing':>11s} "
          f"{'cycles w/ undecided':>19s} {'max per cycle':>13s}")
    for f, s in board.filter_stats.items():
        assert s["tests"] == r["tests"], (s["tests"], r["tests"])     # the same tests as the model's
        print(f"{f:10s} {s['tests']:10d} {s['undecided']:10d} {s['undecided'] / s['tests']:9.2e} "
              f"{s['undecided'] / max(1, s['crossing']):11.2e} {s['cycles_undecided'] / s['cycles']:19.2e} "
              f"{s['max_per_cycle']:13d}")
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=["verify", "rate"], required=True)
    p.add_argument("--queries", type=int, default=10 ** 7)
    p.add_argument("--seed", type=int, default=None, help="default: fresh, printed")
    p.add_argument("--scene", default="cornell")
    p.add_argument("--max-shots", type=int, default=40)
    p.add_argument("--bits", type=int, default=None, help="B of the render (default chosen per scene)")
    p.add_argument("--filters", default=None, metavar="D:W,...",
                   help="filter widths as d_bits:w_bits (default 9:9,12:12,14:14,17:18)")
    args = p.parse_args(argv)
    formats = FORMATS if args.filters is None else [
        FilterFormat(*(int(x) for x in spec.split(":"))) for spec in args.filters.split(",")]
    print_run_header()
    if args.part == "verify":
        seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % (1 << 32))
        return part_verify(args.queries, seed, formats)
    return part_rate(args.scene, args.max_shots, args.bits, formats)


if __name__ == "__main__":
    sys.exit(main())
