"""The generated Verilog of the Intersector under cocotb + Verilator against blockray.exact.

At least 100 000 random vectors plus every hard case (tests/processor_vectors.py), with random
input gaps and output backpressure, zero mismatches. The Verilator build is cached by content
(sim/cocotb_support.py), so only the first session after a change pays for it.
"""

import json
import os
from pathlib import Path

import pytest

from blockray.rtl.processor import Intersector
from blockray.sim.cocotb_support import build_verilator, run_cocotb

HERE = Path(__file__).parent
BITS = 16
SEED = int(os.environ.get("BLOCKRAY_SEED", "20240605"))

pytestmark = pytest.mark.cocotb


@pytest.fixture(scope="session")
def intersector_build():
    build = build_verilator(Intersector(BITS), name="intersector")
    print(f"verilator build: {'cached' if build.cached else f'{build.seconds:.1f} s'} in {build.build_dir}")
    return build


def run(build, tmp_path, **env):
    stats = tmp_path / "stats.json"
    env = {"BLOCKRAY_BITS": str(BITS), "BLOCKRAY_STATS": str(stats), **{k: str(v) for k, v in env.items()}}
    run_cocotb(build, "cocotb_processor", module_dir=HERE, env=env, test_dir=tmp_path)
    return json.loads(stats.read_text())


def test_intersector_verilator(intersector_build, tmp_path):
    print(f"seed={SEED}")
    stats = run(intersector_build, tmp_path, BLOCKRAY_SEED=SEED, BLOCKRAY_VECTORS=100_000,
                BLOCKRAY_BUBBLE=0.1, BLOCKRAY_STALL=0.1)
    print(stats)
    assert stats["mismatches"] == 0 and stats["vectors"] >= 100_000 + stats["hard"]


def test_mismatch_fails(intersector_build, tmp_path):
    """A single wrong expectation makes the cocotb run, and so this pytest call, fail."""
    with pytest.raises(SystemExit):
        run(intersector_build, tmp_path, BLOCKRAY_SEED=SEED, BLOCKRAY_VECTORS=100,
            BLOCKRAY_FLIP=12345, BLOCKRAY_BUBBLE=0, BLOCKRAY_STALL=0)
    assert json.loads((tmp_path / "stats.json").read_text())["mismatches"] == 1
