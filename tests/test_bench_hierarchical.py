"""benchmarks/bench_hierarchical.py's equal-error ratios: the uniform solve's cost at a given error."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_hierarchical import at_equal_error     # noqa: E402


def _runs(law, rays):
    """Uniform runs whose error follows ``law(rays)``; cycles and CPU as other power laws of rays."""
    return [{"rays": n, "error": law(n), "cycles": 0.6 * n ** 1.1, "cpu": 3e-6 * n} for n in rays]


def test_a_power_law_is_read_back_exactly_between_its_runs():
    runs = _runs(lambda n: 40.0 * n ** -0.35, [1e5, 4e5, 5e6])
    for n in (1.5e5, 4e5, 2e6):
        e = 40.0 * n ** -0.35
        assert at_equal_error(runs, e, "rays") == pytest.approx(n, rel=1e-12)
        assert at_equal_error(runs, e, "cycles") == pytest.approx(0.6 * n ** 1.1, rel=1e-12)
        assert at_equal_error(runs, e, "cpu") == pytest.approx(3e-6 * n, rel=1e-12)


def test_no_extrapolation_and_the_bracketing_neighbours():
    runs = _runs(lambda n: 40.0 * n ** -0.35, [1e5, 4e5])
    assert at_equal_error(runs, 40.0 * 5e4 ** -0.35, "rays") is None
    assert at_equal_error(runs, 40.0 * 1e6 ** -0.35, "rays") is None
    # a kink: each error is read on the segment whose runs bracket it, not on a line through all
    kinked = [{"rays": 1e5, "error": 0.06, "cycles": 1, "cpu": 1}, {"rays": 2e5, "error": 0.04, "cycles": 1, "cpu": 1},
              {"rays": 8e5, "error": 0.035, "cycles": 1, "cpu": 1}]
    assert at_equal_error(kinked, 0.04, "rays") == pytest.approx(2e5)
    assert 2e5 < at_equal_error(kinked, 0.037, "rays") < 8e5
    assert 1e5 < at_equal_error(kinked, 0.05, "rays") < 2e5
