"""The generated Verilog of the FilteredIntersector under cocotb + Verilator against blockray.exact.

The bench of the exact Intersector (tests/cocotb_processor.py: the two have the same ports) with
at least 100 000 random vectors plus every hard case, random input gaps and output backpressure,
zero mismatches with the exact predicate. Two filter formats: the default (d_k exact, w_k at
18 bits) and 9 x 9 bits, whose undecided hard cases (about 6 000 at B = 16) exercise the exact
path and the hand-off.
"""

import json
import os
from pathlib import Path

import pytest

from blockray.filtered import FilterFormat
from blockray.rtl.filtered import FilteredIntersector
from blockray.sim.cocotb_support import build_verilator, run_cocotb

HERE = Path(__file__).parent
BITS = 16
SEED = int(os.environ.get("BLOCKRAY_SEED", "20261126"))

pytestmark = pytest.mark.cocotb


# the 9 x 9 format sends ~6 000 hard cases through the hand-off: the default suite's run; the
# synthesised default format (d exact, w 18 bits: 781 undecided) costs a second build: slow
@pytest.fixture(scope="module", params=[pytest.param(None, marks=pytest.mark.slow), FilterFormat.square(9)],
                ids=["default", "d9w9"])
def filtered_build(request):
    dut = FilteredIntersector(BITS, request.param)
    build = build_verilator(dut, name=f"filtered_intersector_{dut.fmt}")
    print(f"verilator build: {'cached' if build.cached else f'{build.seconds:.1f} s'} in {build.build_dir}")
    return build


def test_filtered_intersector_verilator(filtered_build, tmp_path):
    print(f"seed={SEED}")
    stats = tmp_path / "stats.json"
    env = {"BLOCKRAY_BITS": BITS, "BLOCKRAY_STATS": stats, "BLOCKRAY_SEED": SEED, "BLOCKRAY_VECTORS": 100_000,
           "BLOCKRAY_BUBBLE": 0.1, "BLOCKRAY_STALL": 0.1}
    run_cocotb(filtered_build, "cocotb_processor", module_dir=HERE, env={k: str(v) for k, v in env.items()},
               test_dir=tmp_path)
    stats = json.loads(stats.read_text())
    print(stats)
    assert stats["mismatches"] == 0 and stats["vectors"] >= 100_000 + stats["hard"]
