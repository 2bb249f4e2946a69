"""The lean cell's filter (w_k from rounded inputs, blockray/filtered.py): soundness against the
exact reference and its undecided rate on real renders, beside the exact-w_k filter of the same
widths, in one run.

    python benchmarks/bench_lean.py --part verify --queries 1000000
    python benchmarks/bench_lean.py --part rate --scene cornell --max-shots 40
    python benchmarks/bench_lean.py --part rate --scene room --max-shots 40
    python benchmarks/bench_lean.py --part degenerate --queries 1000000
    python benchmarks/bench_lean.py --part units               # Yosys synth_ecp5 per unit, B = 16

``verify`` is bench_filter.py's (random and hard-case queries, each against
:func:`blockray.exact.blocked_reference`; ``wrong`` must be 0). ``rate``: every test of a
progressive render with the model board goes through each filter (``filtered_block``, so the
lean formats take the rounded-input path); prints the undecided fraction and the fraction of
broadcast cycles (one record) with an undecided test. ``degenerate``: the tests' near-degenerate
blocks (tests/processor_vectors.py ``near_degenerate``: rays through a patch's vertices, edges and
plane, rotated, scaled and rounded to the grid; B = 8, 12, 16, 20 in turn), every certified sign
against the exact s_k and every decided bit against ``blocked_block``; ``wrong`` must be 0.
``units``: Yosys (synth_ecp5, no nextpnr)
resources of each part of a lean array at B = 16, side by side: the row unit with exact w_k
(ReceiverUnit + ReceiverFilter, 9 x 9: the lean default) with its products on DSPs and with w_k's
18 cross products as CCU2C bit heaps (``LeanRowUnit``, ``rounded``), the row unit with w_k from
12-bit inputs (``LeanReceiver``) on DSPs and on bit heaps, the lean column unit, the 9 x 9 cell on
DSPs, on Yosys's LUT multipliers (the filtered cell's ``--fabric-units cell``) and as the lean
array's CCU2C bit heaps (rtl/lutdot.py), the shared exact unit.
"""

import argparse
import sys
import time

import numpy as np

from blockray.filtered import FilterFormat, filtered_block

from _run_header import print_run_header
from bench_filter import block_tests, part_verify, voxel_records

#: the exact-w_k 9 x 9 filter (the lean cell before w_k was rounded from its inputs) and the lean
#: formats at input widths 10 to 14
FORMATS = [FilterFormat(9, 9)] + [FilterFormat(9, 9, m) for m in (10, 11, 12, 13, 14)]


def _rate_board(formats):
    from blockray.sim.model import ModelBoard

    class RateBoard(ModelBoard):
        def load(self, grid):
            super().load(grid)
            self._records = voxel_records(grid)
            self.rates = {str(f): dict.fromkeys(("tests", "undecided", "cycles", "cycles_undecided"), 0)
                          for f in formats}

        def run(self, blocks):
            for P, Q, V, n in block_tests(self._records, self.quantised, blocks):
                for f in formats:
                    decided, _ = filtered_block(P, Q, V, n, f)
                    per_cycle = (~decided).sum(axis=(0, 1))
                    s = self.rates[str(f)]
                    s["tests"] += decided.size
                    s["undecided"] += int(per_cycle.sum())
                    s["cycles"] += len(V)
                    s["cycles_undecided"] += int((per_cycle > 0).sum())
            return super().run(blocks)

    return RateBoard


def part_rate(scene_name, max_shots, formats):
    from blockray.host_driver.scene.builtin import load_scene
    from blockray.host_driver.render.render import render
    from blockray.params import BoardParams
    board = _rate_board(formats)(BoardParams())
    t0 = time.perf_counter()
    r = render(load_scene(scene_name), board=board, params=BoardParams(), max_shots=max_shots).report
    print(f"rate: {scene_name}, {r['patches']} patches, B = {board.quantised.bits}, {r['shots']} shots, "
          f"{r['tests']} tests, {time.perf_counter() - t0:.0f} s")
    print(f"{'filter':12s} {'tests':>10s} {'undecided':>10s} {'rate':>9s} {'cycles w/ undecided':>19s}")
    for f, s in board.rates.items():
        print(f"{f:12s} {s['tests']:10d} {s['undecided']:10d} {s['undecided'] / s['tests']:9.2e} "
              f"{s['cycles_undecided'] / s['cycles']:19.2e}")
    return 0


def part_degenerate(queries, seed):
    import _shared  # noqa: F401  (tests/ on the path)
    from blockray.exact import block_terms, blocked_block, edge_terms, patch_normals
    from blockray.filtered import cell_certificates, rounded_receiver_filter_terms, shooter_filter_terms
    from processor_vectors import near_degenerate
    formats = [f for f in FORMATS if f.w_input_bits in (None, 12, 14)] + [FilterFormat(4, 5, 3)]
    print(f"degenerate: seed={seed}, target {queries} queries, filters {', '.join(map(str, formats))}", flush=True)
    rng = np.random.default_rng(seed)
    stats = {str(f): {"undecided": 0, "wrong": 0} for f in formats}
    total, t0 = 0, time.perf_counter()
    while total < queries:
        for bits in (8, 12, 16, 20):
            for P, Q, V in near_degenerate(bits, 500, rng):
                n = patch_normals(V)
                _, _, sides = block_terms(P, Q, V, n)
                exact = blocked_block(P, Q, V, n)
                dP, dQ, _ = edge_terms(P, Q, V)
                for f in formats:
                    decided, blocked = filtered_block(P, Q, V, n, f)
                    s = stats[str(f)]
                    s["undecided"] += int((~decided).sum())
                    s["wrong"] += int((decided & (blocked != exact)).sum())
                    if f.w_input_bits is not None:
                        c = cell_certificates(shooter_filter_terms(dP[None], f), rounded_receiver_filter_terms(
                            dQ[:, None], np.roll(V, -1, axis=-2) - V, f))
                        s["wrong"] += int((c["ge"] & (sides < 0)).sum() + (c["gt"] & (sides <= 0)).sum()
                                          + (c["le"] & (sides > 0)).sum() + (c["lt"] & (sides >= 0)).sum())
                total += exact.size
    print(f"{total} queries in {time.perf_counter() - t0:.0f} s")
    print(f"{'filter':12s} {'undecided':>10s} {'rate':>9s} {'wrong':>6s}")
    for f, s in stats.items():
        print(f"{f:12s} {s['undecided']:10d} {s['undecided'] / total:9.2e} {s['wrong']:6d}")
    return 1 if any(s["wrong"] for s in stats.values()) else 0


def _units(bits):
    """(name, component, fabric units) of each part of a lean array at B = ``bits``."""
    from amaranth.hdl import Module
    from amaranth.lib import wiring
    from blockray.cell import Cell
    from blockray.rtl.filtered import FilteredProcessor, ReceiverFilter, ShooterFilter
    from blockray.rtl.lean import LeanExact, LeanReceiver, LeanRowUnit
    from blockray.rtl.processor import ReceiverUnit, ShooterUnit

    class Edge(wiring.Component):
        """An array-edge unit and its filter, the filter's outputs as ports."""
        def __init__(self, unit, filt):
            self._unit, self._filt = unit, filt
            super().__init__({"point": wiring.In(unit.point.shape()), "patch": wiring.In(unit.patch.shape()),
                              "valid": wiring.In(1), "terms": wiring.Out(filt.terms.shape()),
                              "plane_out": wiring.Out(filt.plane_out.shape())})

        def elaborate(self, platform):
            m = Module()
            m.submodules.unit, m.submodules.filt = u, f = self._unit, self._filt
            m.d.comb += [u.point.eq(self.point), u.patch.eq(self.patch), u.valid.eq(self.valid),
                         f.exact.eq(u.terms), f.valid.eq(u.terms_valid), self.terms.eq(f.terms),
                         self.plane_out.eq(f.plane_out)]
            return m

    lean, exact_w, rounded = Cell("lean").format_at(bits), FilterFormat(9, 9), FilterFormat(9, 9, 12)
    return [("row, exact w_k", lambda: Edge(ReceiverUnit(bits), ReceiverFilter(bits, exact_w)), ()),
            ("row, exact w_k, chains", lambda: Edge(LeanRowUnit(bits), ReceiverFilter(bits, exact_w)), ("rounded",)),
            ("row, m_i = 12", lambda: LeanReceiver(bits, rounded), ()),
            ("row, m_i = 12, chains", lambda: LeanReceiver(bits, rounded), ("rounded",)),
            ("column, lean", lambda: Edge(ShooterUnit(bits), ShooterFilter(bits, lean)), ()),
            ("cell 9 x 9, DSPs", lambda: FilteredProcessor(lean), ()),
            ("cell 9 x 9, LUT mult.", lambda: FilteredProcessor(lean), ("cell",)),
            ("cell 9 x 9, carry chains", lambda: FilteredProcessor(lean, carry_chains=True), ("cell",)),
            ("exact unit", lambda: LeanExact(bits, 2, 2, 14, 33), ())]


def part_units(bits, only):
    import tempfile
    from pathlib import Path
    from blockray import hdl
    from blockray.synth.nextpnr import _cells_resources, _yosys_ecp5
    from blockray.synth.target import ECP5Target
    print(f"units: Yosys synth_ecp5, B = {bits}")
    print(f"{'unit':26s} {'LUTs':>7s} {'FFs':>7s} {'DSPs':>5s} {'seconds':>8s}")
    for name, make, fabric in _units(bits):
        if only and not any(o in name for o in only):
            continue
        with tempfile.TemporaryDirectory(prefix="bench-lean-") as tmp:
            text = hdl.convert(make(), name="top", emit_src=False, platform=ECP5Target(fabric))
            cells, seconds, _ = _yosys_ecp5(text, "top", Path(tmp), "unit", netlist=False, lut_multipliers=bool(fabric))
        r = _cells_resources(cells)
        print(f"{name:26s} {r['luts']:7d} {r['ffs']:7d} {r['dsps']:5d} {seconds:8.0f}", flush=True)
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=["verify", "degenerate", "rate", "units"], required=True)
    p.add_argument("--queries", type=int, default=10 ** 6)
    p.add_argument("--seed", type=int, default=None, help="default: fresh, printed")
    p.add_argument("--scene", default="cornell")
    p.add_argument("--max-shots", type=int, default=40)
    p.add_argument("--bits", type=int, default=16, help="units: B")
    p.add_argument("--only", nargs="*", default=[], help="units: names containing these words")
    args = p.parse_args(argv)
    print_run_header()
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % (1 << 32))
    if args.part == "verify":
        return part_verify(args.queries, seed, FORMATS)
    if args.part == "degenerate":
        return part_degenerate(args.queries, seed)
    if args.part == "units":
        return part_units(args.bits, args.only)
    return part_rate(args.scene, args.max_shots, FORMATS)


if __name__ == "__main__":
    sys.exit(main())
