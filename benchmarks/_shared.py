"""The benchmarks measure what the tests check, on the tests' own scenes, oracles and cocotb
harness (tests/scenes.py, tests/oracles.py, tests/board_cocotb_runs.py): importing this module puts
tests/ on the path, for the benchmarks only. One slow test runs a benchmark (tests/test_hard_cases.py)."""

import sys
from pathlib import Path

TESTS = str(Path(__file__).resolve().parent.parent / "tests")
if TESTS not in sys.path:
    sys.path.append(TESTS)
