"""Formal properties of the lean array's tag queue (rtl/lean.py ``LeanResolve``: ArrayResolve with
a record's tag queued instead of exact terms, and LeanExact's latency of 12 and a test every 3
cycles), checked with
SymbiYosys and Boolector through :class:`blockray.synth.handoff_harness.ArrayHandoffHarness`
(``lean=True``) and its stand-in :class:`~blockray.synth.handoff_harness.LeanStandIn`, which
answers each test from its own tag and bit. Properties (the filtered array's, docs/processor.md):
the n-th item delivered is the n-th entered (in order, none lost or duplicated) with its marker
flag; a solver-chosen record's bits are, per test, the filter's when decided, else the exact
unit's answer for that test's own tag and bit; no deadlock (an item delivered within
RS x depth x 3 + 16 cycles while any is inside); covers: full, and delivering while full.
"""

import pytest

from blockray.synth.formal import prove
from blockray.synth.handoff_harness import ARRAY_PROOF, MEMORIES_AS_FLOPS, ArrayHandoffHarness

#: a record's first answer leaves the exact unit 12 cycles after its tag heads the queue, its
#: second 3 cycles later: 25 cycles fill the hand-off with records of two undecided tests and
#: deliver while full
LEAN_BMC_DEPTH = 25
#: the induction must outlast an item's way from deep in the pending FIFO to delivery behind
#: records served 3 cycles a test: depth 27 fails (a wrong answer from an unreachable start), 34
#: passes
LEAN_INDUCTION_DEPTH = 34


def _check(tmp_path, harness, mode, depth, timeout=1800):
    result = prove(harness, name=f"lean_{mode}", mode=mode, depth=depth, workdir=tmp_path,
                   script=MEMORIES_AS_FLOPS if mode == "prove" else ("memory_map",), timeout=timeout)
    print(f"{mode}: {result.status} in {result.seconds} s")
    return result


@pytest.mark.parametrize("mode", [pytest.param("bmc", marks=pytest.mark.slow), "cover"])     # bmc: ~3 min
def test_tag_queue_properties_bounded(tmp_path, mode):
    """LeanResolve (1 x 2 tests per record, depth 4) under every input sequence of 25 cycles."""
    result = _check(tmp_path, ArrayHandoffHarness(lean=True), mode, LEAN_BMC_DEPTH)
    assert result.passed, f"sby {result.status}:\n{result.log[-3000:]}"


@pytest.mark.parametrize("fault", ["drop", "duplicate"])
def test_tag_queue_check_fails_for_a_broken_exact_unit(tmp_path, fault):
    """The bounded check can fail: an exact unit that loses an answer or gives one twice."""
    result = _check(tmp_path, ArrayHandoffHarness(lean=True, fault=fault), "bmc", LEAN_BMC_DEPTH)
    assert result.status == "FAIL", result.log[-2000:]


@pytest.mark.slow
def test_tag_queue_proven_unbounded(tmp_path):
    """Every reachable state (k-induction) of the small configuration of the filtered array's
    proof (depth 3, 2-bit sequence numbers) with the lean stand-in, every record checked."""
    result = _check(tmp_path, ArrayHandoffHarness(**ARRAY_PROOF, invariants=True, lean=True), "prove",
                    LEAN_INDUCTION_DEPTH)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"
