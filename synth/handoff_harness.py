"""Formal harnesses of the filtered cell's hand-offs (rtl/filtered.py): :class:`HandoffHarness`
drives the 1 x 1 array's ``InOrderResolve``, :class:`ArrayHandoffHarness` the R x S array's
``ArrayResolve`` (or, ``lean=True``, the lean array's tag queue ``LeanResolve``, rtl/lean.py),
each with an exact-unit stand-in, the properties as ``Assert`` / ``Cover`` and,
with ``invariants=True``, the invariants that make them inductive. The proofs that use them are
tests/test_filtered_formal.py (the properties are described there) and
benchmarks/bench_formal.py; they run through :func:`blockray.synth.formal.prove`.
"""

from amaranth.hdl import Assert, Assume, Cat, Cover, Module, Mux, ResetSignal, Signal, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.wiring import In

from ..rtl.filtered import InOrderResolve, sum_or

DEPTH = 4
OPERAND_BITS = 4
TAG_BITS = 5                    # sequence numbers: more than the tests a run of BMC_DEPTH cycles can hold
EXACT_LATENCY = 3
BMC_DEPTH = 12                  # fills the hand-off (step 4), delivers while full and drains



def _answer(operands):
    return operands[0] ^ operands[3]


def _owner(m, valid, deliver, depth, tag_bits):
    """The owner's credits: a test enters on ``valid`` while fewer than ``depth`` are inside,
    tagged with its sequence number. Returns (accept, entered, delivered, inside)."""
    entered, delivered = Signal(tag_bits), Signal(tag_bits)
    inside = Signal(range(depth + 1))
    accept = valid & (inside < depth)
    m.d.sync += [entered.eq(entered + accept), delivered.eq(delivered + deliver), inside.eq(inside + accept - deliver)]
    m.d.comb += Assert((entered - delivered)[:tag_bits] == inside)
    return accept, entered, delivered, inside


def _inside(tag, delivered, inside, tag_bits):
    """Sequence number ``tag`` (modulo 2 ** tag_bits) is one of the ``inside`` after ``delivered``."""
    return (tag - delivered)[:tag_bits] < inside


def _fixed(m, value):
    """``value`` is the solver's choice, constant over the run."""
    prev, started = Signal.like(value), Signal()
    m.d.sync += [prev.eq(value), started.eq(1)]
    with m.If(started):
        m.d.comb += Assume(value == prev)


def _progress(m, inside, offered, bound, message):
    """With tests inside, something is offered within ``bound`` cycles."""
    waiting = Signal(range(64))
    with m.If((inside != 0) & ~offered):
        m.d.sync += waiting.eq(waiting + 1)
    with m.Else():
        m.d.sync += waiting.eq(0)
    m.d.comb += Assert(waiting <= bound, message)


def _overflow(fifos):
    return sum_or(f.w_en & ~f.w_rdy for f in fifos.values())


def _drop_once(m, valid, now):
    """A broken exact unit's input: ``valid`` lost once, when ``now``."""
    dropped = Signal()
    m.d.sync += dropped.eq(dropped | (valid & now))
    return valid & ~(now & ~dropped)


def _again(m, valid, now):
    """A broken exact unit's output: an answer given again the cycle after, when ``now``."""
    again = Signal()
    m.d.sync += again.eq(valid)
    return valid | (now & again)


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

        deliver = dut.o.valid & dut.o.ready
        accept, entered, delivered, inside = _owner(m, self.i_valid, deliver, self.depth, self.tag_bits)
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
            valid = _drop_once(m, valid, self.fault_now)
        stages = []
        for n in range(self.latency):
            v, a = Signal(name=f"exact_valid_{n}"), Signal(name=f"exact_answer_{n}")
            m.d.sync += [v.eq(valid), a.eq(answer)]
            valid, answer = v, a
            stages.append(v)
        if self.fault == "duplicate":       # gives an answer twice: again the cycle after
            valid = _again(m, valid, self.fault_now)
        m.d.comb += [dut.resolved.valid.eq(valid), dut.resolved.payload.eq(answer)]

        # in order, none lost or duplicated
        with m.If(deliver):
            m.d.comb += Assert(dut.o.payload.tag == delivered, "results out of order, lost or duplicated")

        # one test chosen by the solver: its answer
        _fixed(m, self.target)
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

        _progress(m, inside, dut.o.valid, self.latency + 4, "deadlock: tests inside and nothing offered")

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
        m.d.comb += undecided.eq(sum(Mux(_inside(t, delivered, inside, self.tag_bits) & ~decided_of[t], 1, 0)
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




# unbounded: k-induction on a small configuration (depth 3, 3-bit tags; at depth 2 a
# SyncFIFOBuffered refuses a second write one cycle after its first, while its level is 1)
PROOF_DEPTH, PROOF_TAG_BITS, PROOF_LATENCY, INDUCTION_DEPTH, MAX_STALL = 3, 2, 1, 20, 2
# the FIFOs' memories as flip-flops: the proofs run 2 to 2.75 times faster than with SMT arrays
# (benchmarks/bench_formal.py, docs/processor.md)
MEMORIES_AS_FLOPS = ("memory_map", "opt -fast")



# -- the filtered array's hand-off (ArrayResolve) ------------------------------------------------

ARRAY_BITS, ARRAY_ROWS, ARRAY_COLS, ARRAY_DEPTH = 4, 1, 2, 4
ARRAY_BMC_DEPTH = 14                    # fills the hand-off with records of two undecided tests, drains


class ExactStandIn(wiring.Component):
    """The exact Processor's ports and latency (4), answering a function of its operands.
    ``stages``, ``answers``: its pipeline (stage n: a test given n + 1 cycles ago, and its answer;
    the last is ``result_valid``), named for the proof's invariants. ``fault``: ``"drop"`` loses one answer,
    ``"duplicate"`` gives one twice (again the cycle after), when ``fault_now`` (the solver's
    choice) says so."""

    def __init__(self, bits=ARRAY_BITS, fault=None):
        from blockray.rtl.processor import Processor, receiver_terms_layout, shooter_terms_layout
        self.fault = fault
        self.stages = [Signal(name=f"valid_{n}") for n in range(Processor.latency)]
        self.answers = [Signal(name=f"blocked_{n}") for n in range(Processor.latency)]
        super().__init__({
            "shooter": In(shooter_terms_layout(bits)), "receiver": In(receiver_terms_layout(bits)),
            "valid": In(1), "first": In(1), "fault_now": In(1),
            "blocked": wiring.Out(1), "hit": wiring.Out(1), "result_valid": wiring.Out(1),
        })

    @staticmethod
    def answer(shooter, receiver):
        return shooter.pp[0] ^ receiver.pq[1] ^ shooter.d[2].z[-1]

    @classmethod
    def test_answer(cls, terms, r, s, cols=None):
        """The answer for test (r, s) of a queued record's ``terms``."""
        return cls.answer(terms.shooters[s], terms.receivers[r])

    def _answer(self):
        return self.answer(self.shooter, self.receiver)

    def elaborate(self, platform):
        m = Module()
        valid, blocked = self.valid, self._answer()
        if self.fault == "drop":
            valid = _drop_once(m, valid, self.fault_now)
        for v, b in zip(self.stages, self.answers):
            m.d.sync += [v.eq(valid), b.eq(blocked)]
            valid, blocked = v, b
        if self.fault == "duplicate":
            valid = _again(m, valid, self.fault_now)
        m.d.comb += [self.result_valid.eq(valid), self.blocked.eq(blocked)]
        return m


class LeanStandIn(ExactStandIn):
    """:class:`~blockray.rtl.lean.LeanExact`'s ports and latency (12): a test is its record's tag
    (``terms``: patch address, end-point slot) and its bit ``which``; it answers the tag's
    address bit at the test's index, XOR the slot's low bit (so a test answered for another
    test's bit or another record's tag is caught). ``fault`` as :class:`ExactStandIn`'s."""

    def __init__(self, rows, cols, address_bits, slots, fault=None):
        from blockray.rtl.lean import LeanExact, tag_layout
        self.fault, self.cols = fault, cols
        self.stages = [Signal(name=f"valid_{n}") for n in range(LeanExact.latency)]
        self.answers = [Signal(name=f"blocked_{n}") for n in range(LeanExact.latency)]
        wiring.Component.__init__(self, {
            "which": In(rows * cols), "terms": In(tag_layout(address_bits, slots)),
            "valid": In(1), "first": In(1), "fault_now": In(1),
            "blocked": wiring.Out(1), "result_valid": wiring.Out(1),
        })

    @staticmethod
    def test_answer(terms, r, s, cols=None):
        return terms.address[r * cols + s] ^ terms.slot[0]

    def _answer(self):
        return ((self.terms.address & self.which) != 0) ^ self.terms.slot[0]


class ArrayHandoffHarness(wiring.Component):
    """The environment and properties around one ``ArrayResolve`` (default R x S = 1 x 2, depth
    4), driven as ``FilteredArray`` drives it: records (with undecided tests and the exact terms
    of every row and column) and markers, at most ``depth`` items inside (the board's credits);
    every item's ``mark_data`` carries its sequence number; ``o`` is always taken, as the
    accumulators do. Properties: the n-th item delivered has sequence number n (in order, none
    lost or duplicated) and its marker flag; a solver-chosen item's delivered bits are, per test,
    the filter's when decided, else the exact unit's answer for that test's own row and column
    terms; no deadlock (with items inside, one is delivered within RS * depth * the exact unit's
    interval + its latency + 4 cycles);
    covers: full, and delivering while full. ``invariants``: the assertions that make these
    inductive (:meth:`_invariants`); ``fault``: a broken exact unit (:class:`ExactStandIn`)."""

    def __init__(self, depth=ARRAY_DEPTH, tag_bits=TAG_BITS, *, bits=ARRAY_BITS, rows=ARRAY_ROWS, cols=ARRAY_COLS,
                 invariants=False, fault=None, lean=False):
        from blockray.rtl.filtered import ArrayResolve
        from blockray.rtl.lean import LeanResolve
        self.depth, self.tag_bits, self.rows, self.cols, self.invariants = depth, tag_bits, rows, cols, invariants
        if lean:            # the lean array's: tags to LeanExact (latency 12, a test every 3 cycles); address bits = the tests
            self.exact = LeanStandIn(rows, cols, rows * cols, depth, fault)
            self.dut = LeanResolve(bits, rows, cols, unsigned(tag_bits), depth, exact_unit=lambda: self.exact,
                                   address_bits=rows * cols)
        else:
            self.exact = ExactStandIn(bits, fault)
            self.dut = ArrayResolve(bits, rows, cols, unsigned(tag_bits), depth, exact_unit=lambda: self.exact)
        super().__init__({
            "i_valid": In(1), "i_mark": In(1), "i_first": In(1), "i_blocked": In(rows * cols),
            "i_undecided": In(rows * cols), "i_terms": In(self.dut.i.payload.shape()["terms"].shape),
            "target": In(tag_bits), "fault_now": In(1),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self.dut
        R, S, RS, tag_bits = self.rows, self.cols, self.rows * self.cols, self.tag_bits
        m.d.comb += Assume(~ResetSignal("sync"))
        deliver = dut.o.valid
        accept, entered, delivered, inside = _owner(m, self.i_valid, deliver, self.depth, tag_bits)
        record = ~self.i_mark
        undecided = Mux(record, self.i_undecided, 0)
        m.d.comb += Assume((self.i_blocked & self.i_undecided) == 0)     # a cell's blocked is 0 when undecided
        item = dut.i.payload.item
        m.d.comb += [
            dut.i.valid.eq(accept), item.mark.eq(self.i_mark), item.first.eq(self.i_first),
            item.blocked.eq(self.i_blocked), item.needs.eq(undecided != 0), item.mark_data.eq(entered),
            dut.i.payload.undecided.eq(undecided), dut.i.payload.terms.eq(self.i_terms),
            self.exact.fault_now.eq(self.fault_now),
        ]
        out = dut.o.payload
        with m.If(deliver):
            m.d.comb += Assert(out.item.mark_data == delivered, "items out of order, lost or duplicated")

        # per test, the filter's answer when decided, else the exact unit's for its row and column
        terms = dut.i.payload.terms
        answers = Cat(*(Mux(undecided[r * S + s], self.exact.test_answer(terms, r, s, S),
                            self.i_blocked[r * S + s]) for r in range(R) for s in range(S)))
        if self.invariants:             # every item checked against the shadow
            self._invariants(m, accept, deliver, inside, delivered, undecided, answers)
        else:                           # one item chosen by the solver: its marker flag and answer
            _fixed(m, self.target)
            seen, mark, expected = Signal(), Signal(), Signal(RS)
            with m.If(accept & (entered == self.target)):
                m.d.sync += [seen.eq(1), mark.eq(self.i_mark), expected.eq(answers)]
            with m.If(deliver & (out.item.mark_data == self.target)):
                m.d.comb += Assert(seen & (out.item.mark == mark), "wrong item")
                with m.If(~mark):
                    m.d.comb += Assert(out.blocked == expected, "wrong answer")

        _progress(m, inside, deliver, RS * self.depth * self.dut.exact_interval + self.dut.exact_latency + 4,
                  "deadlock: items inside and nothing delivered")
        m.d.comb += [Cover(inside == self.depth), Cover((inside == self.depth) & deliver & (out.blocked != 0))]
        return m

    def _invariants(self, m, accept, deliver, inside, delivered, undecided, answers):
        """A shadow of the items inside, per sequence number (modulo ``2 ** tag_bits``): marker or
        not, its undecided tests, its right answer vector; and, tied to it:

        * a marker has no undecided tests;
        * the pending FIFO holds every item inside, its head the oldest with its own flags;
        * every record inside with undecided tests is in exactly one place on the exact path: the
          queue, the exact unit (its last test, marked ``final``), the answers FIFO;
        * the server: a queue head has undecided tests; once started, it is serving the head,
          some of its tests are out (the lowest ones) and some remain;
        * a record's tests leave the server the exact unit's interval I apart, lowest first: a
          test in the exact unit (one bit of ``which``) that is not its record's last has the
          next one, a higher bit, I stages behind it (or the server, started, still holds it and
          feeds it when ``wait`` has counted down), and answers are gathered, from lower bits,
          only while the next one is in the last I stages;
        * no FIFO written when it cannot take it; every delivered record has its right answer.

        Items deep in the pending FIFO cannot be named (its memory): the induction depth covers
        the 12 cycles such an item can take to reach the head. Tying more to the shadow (the
        answers head, each stage's answer, the queue head's operands) does not shorten that and
        doubles the solver's time.
        """
        dut, exact, RS, tag_bits = self.dut, self.exact, self.rows * self.cols, self.tag_bits
        tags = 2 ** tag_bits
        mark_of = Signal(tags, name="mark_of")
        undecided_of = Signal(data.ArrayLayout(RS, tags), name="undecided_of")
        answer_of = Signal(data.ArrayLayout(RS, tags), name="answer_of")
        tag = dut.i.payload.item.mark_data
        with m.If(accept):
            m.d.sync += [mark_of.bit_select(tag, 1).eq(self.i_mark), undecided_of[tag].eq(undecided),
                         answer_of[tag].eq(answers)]

        needing = sum(Mux(_inside(t, delivered, inside, tag_bits) & (undecided_of[t] != 0), 1, 0)
                      for t in range(tags))
        fifos = dut.fifos
        finals = sum(Mux(v & f, 1, 0) for v, f in zip(exact.stages, dut.final))
        m.d.comb += [Assert(~mark_of[t] | (undecided_of[t] == 0), "a marker with tests") for t in range(tags)]
        m.d.comb += [
            Assert(fifos["pending"].level == inside, "an item lost or duplicated in the pending FIFO"),
            Assert(fifos["queue"].level + finals + fifos["answers"].level == needing,
                   "a record lost or duplicated between the queue, the exact unit and the answers"),
            Assert(~_overflow(fifos), "a FIFO written while it cannot take it"),
        ]
        head = dut.o.payload.item
        with m.If(fifos["pending"].r_rdy):
            m.d.comb += [Assert(head.mark_data == delivered), Assert(head.mark == mark_of.bit_select(delivered, 1)),
                         Assert(head.needs == (undecided_of[delivered] != 0))]
        with m.If(deliver & ~head.mark):
            m.d.comb += Assert(dut.o.payload.blocked == answer_of[delivered], "wrong answer")

        # the queue head and the server
        undecided, remaining, started = dut.head.undecided, dut.remaining, dut.started
        lowest, served = Signal(RS), Signal(RS)
        m.d.comb += [lowest.eq(remaining & -remaining), served.eq(undecided & ~remaining)]
        with m.If(fifos["queue"].r_rdy):
            m.d.comb += Assert(undecided != 0)
        with m.If(started):
            m.d.comb += Assert(fifos["queue"].r_rdy & (remaining != 0) & ((remaining & ~undecided) == 0)
                               & (served != 0) & (served < lowest))
        # stage j's next test: the one in stage j - I (I, the exact unit's interval), or, for the
        # I newest stages, the server's next, which it feeds when ``wait`` has counted down
        interval = dut.exact_interval
        for j, (valid, final, which) in enumerate(zip(exact.stages, dut.final, dut.which), start=1):
            with m.If(valid):
                m.d.comb += Assert((which != 0) & ((which & (which - 1)) == 0), "not one test")
            if j > interval:
                following = exact.stages[j - 1 - interval] & (which < dut.which[j - 1 - interval])
            else:
                following = started & (dut.wait == interval - j) & (which < lowest)
            with m.If(valid & ~final):
                m.d.comb += Assert(following, "a record's tests not an interval apart")
        with m.If(dut.gathered != 0):
            m.d.comb += Assert(sum_or(v & (dut.gathered < w) for v, w in
                                      zip(exact.stages[-interval:], dut.which[-interval:])),
                               "answers gathered from no record")


# unbounded: k-induction on a small configuration (1 x 2 tests per record, so the server serves a
# record over two cycles; depth 3, 2-bit sequence numbers, B = 1: the terms only ride along)
ARRAY_PROOF = dict(depth=3, tag_bits=2, bits=1)
ARRAY_INDUCTION_DEPTH = 12
