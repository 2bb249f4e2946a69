"""The filtered processor cell: edge signs from the certified filter, undecided tests to an exact unit.

The filter is :mod:`blockray.filtered` (derivation: docs/fixed-point.md), bit for bit:

``ShooterFilter``  (one per column)  d_k = P - V_k (exact, from :class:`ShooterUnit`) -> mantissas
                                     d^_k, Pd_k, Nd_k and [a_k > 0]
``ReceiverFilter`` (one per row)     w_k -> mantissas w^_k, Pw_k, Nw_k and [b_k > 0]
``FilteredProcessor`` (one per cell) s^_k = d^_k . w^_k (three m_d x m_w products per k, one
                                     MULT18X18D each), lo_k, hi_k, the certificates and the
                                     test's decision: ``decided``, ``blocked``

``FilteredIntersector`` is the 1 x 1 array behind stream ports, like
:class:`~blockray.rtl.processor.Intersector`, with the hand-off: an undecided test's exact
terms go through a queue to an exact :class:`~blockray.rtl.processor.Processor`, and results
leave in input order, always equal to the exact predicate's.
"""

from amaranth.hdl import Cat, Module, Mux, Shape, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from ..cell import Cell
from .array import broadcast_signature
from .lutdot import dot_product
from .platform import product_platform
from ..params import Widths, check_bits
from .processor import (TAG_BITS, Processor, ReceiverUnit, ShooterUnit, _AXES, _credits, _crossing, _delay,
                        _delay_memory, _delay_through, _product, query_layout, receiver_terms_layout, result_layout,
                        shooter_terms_layout)

__all__ = ["filter_terms_layout", "ShooterFilter", "ReceiverFilter", "FilteredProcessor", "FilteredIntersector",
           "InOrderResolve", "ArrayResolve", "FilteredArray", "array_item_layout"]


def sum_bits(bits, fmt):
    """Width of a unit's sums Pos, Neg for ``bits``-bit mantissas: bits + 1 (at most
    3 * 2**(bits-1) + 3); bits + 2 in the lean format (``fmt.w_input_bits`` set: the column's
    2 Pd + Nd, at most 3 * 2**bits)."""
    return bits + (1 if fmt.w_input_bits is None else 2)


def filter_terms_layout(bits, sums=None):
    """A unit's filter output for its three vectors: mantissas ``m[k][c]`` (signed ``bits``), the
    sums ``pos[k]``, ``neg[k]`` (unsigned ``sums`` bits, default bits + 1: :func:`sum_bits`) and
    ``truncated[k]`` (exponent > 0)."""
    sums = bits + 1 if sums is None else sums
    return data.StructLayout({
        "m": data.ArrayLayout(data.ArrayLayout(signed(bits), 3), 3),
        "pos": data.ArrayLayout(unsigned(sums), 3),
        "neg": data.ArrayLayout(unsigned(sums), 3),
        "truncated": unsigned(3),
    })


def _exponent(m, x, bits, name, floor=None):
    """Stage 1 of :func:`blockray.filtered.truncate` of vector ``x`` (three signed values): ``x``
    and its exponent (OR of the magnitudes, leading one) registered. ``floor`` = (condition,
    least): the exponent is at least ``least`` where ``condition`` holds (the lean row's w^).
    Returns (registered x, exponent)."""
    width = len(x[0])
    x1 = [Signal(signed(width), name=f"{name}_x1_{c}") for c in range(3)]
    e1 = Signal(range(max(2, width, floor[1] + 1 if floor else 0)), name=f"{name}_e1")
    magnitude = Signal(width - 1, name=f"{name}_mag")
    m.d.comb += magnitude.eq(sum_or(Mux(v[-1], ~v, v)[:width - 1] for v in x))
    e0 = Signal.like(e1, name=f"{name}_e0")
    for i in range(bits - 1, width - 1):          # leading one at i: bit length i + 1
        with m.If(magnitude[i]):
            m.d.comb += e0.eq(i + 2 - bits)       # later statements win: the highest one
    if floor is not None:
        condition, least = floor
        m.d.sync += e1.eq(Mux(condition & (e0 < least), least, e0))
    else:
        m.d.sync += e1.eq(e0)
    m.d.sync += [r.eq(v) for r, v in zip(x1, x)]
    return x1, e1


def _truncate(m, x, bits, name, one, *, sums=None, floor=None, sum_width=None):
    """Three stages of :func:`blockray.filtered.truncate` and the unit's sums for vector ``x``
    (three signed values): stage 1 the exponent (:func:`_exponent`), stage 2 the mantissas
    ``x >> e`` and [e > 0], stage 3 Pos and Neg (``one``: add [e > 0] to each non-negative
    mantissa, the row unit's Pw; ``sums``: a function of the mantissas giving (Pos, Neg)
    expressions instead, ``sum_width`` bits). Returns (mantissas, truncated, pos, neg)."""
    x1, e1 = _exponent(m, x, bits, name, floor)
    m2 = [Signal(signed(bits), name=f"{name}_m2_{c}") for c in range(3)]
    t2 = Signal(name=f"{name}_t2")
    m.d.sync += [r.eq((v >> e1)[:bits]) for r, v in zip(m2, x1)] + [t2.eq(e1 != 0)]

    pos = Signal(sum_width or bits + 1, name=f"{name}_pos3")
    neg = Signal(sum_width or bits + 1, name=f"{name}_neg3")
    if sums is None:
        extra = t2 if one else 0
        sums = lambda v: (sum(Mux(c < 0, 0, c + extra) for c in v), sum(Mux(c < 0, -c, 0) for c in v))
    m.d.sync += [a.eq(b) for a, b in zip((pos, neg), sums(m2))]
    return [_delay(m, v, 1, f"{name}_m3_{c}") for c, v in enumerate(m2)], _delay(m, t2, 1, f"{name}_t3"), pos, neg


def sum_or(values):
    out = 0
    for v in values:
        out = out | v
    return out



def _check_depth(depth):
    """The hand-off FIFOs' depth: at least 3, because the owner's credits assume every write is
    taken, and a 2-deep SyncFIFOBuffered refuses a second write one cycle after its first (found by
    the k-induction proof, tests/test_filtered_formal.py)."""
    if not isinstance(depth, int) or depth < 3:
        raise ValueError(f"hand-off depth must be an integer of at least 3, not {depth!r}")
    return depth

class _Filter(wiring.Component):
    """A unit's filter stage: exact terms in, filter terms out after :attr:`latency` cycles,
    with the exact plane term (``plane``: pP or pQ) beside them for
    the cells' crossing test. Subclasses set ``exact_layout``, ``vectors``, ``plane`` and ``one``."""

    latency = 3

    def __init__(self, bits, fmt):
        self._bits = check_bits(bits)
        self._fmt = fmt
        super().__init__({
            "exact": In(self.exact_layout(bits)),
            "valid": In(1),
            "terms": Out(filter_terms_layout(self.mantissa_bits, sum_bits(self.mantissa_bits, fmt))),
            "plane_out": Out(signed(Widths(bits).orient)),
            "terms_valid": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        for k in range(3):
            vector = getattr(self.exact, self.vectors)[k]
            mant, trunc, pos, neg = _truncate(m, [vector[c] for c in _AXES], self.mantissa_bits, f"f{k}", self.one,
                                              sums=self._sums(), sum_width=sum_bits(self.mantissa_bits, self._fmt))
            for c in range(3):
                m.d.comb += self.terms.m[k][c].eq(mant[c])
            m.d.comb += [self.terms.pos[k].eq(pos), self.terms.neg[k].eq(neg), self.terms.truncated[k].eq(trunc)]
        m.d.comb += [
            self.plane_out.eq(_delay(m, getattr(self.exact, self.plane), self.latency, self.plane)),
            self.terms_valid.eq(_delay(m, self.valid, self.latency, "valid")),
        ]
        return m


class ShooterFilter(_Filter):
    """Column unit's filter: d^_k, Pd_k, Nd_k, [a_k > 0] from the exact d_k (latency 3); in the
    lean format (rows with w^ from rounded inputs) Pd' = 2 Pd + Nd, Nd' = Pd + 2 Nd."""
    exact_layout = staticmethod(shooter_terms_layout)
    vectors, plane, one = "d", "pp", False

    def _sums(self):
        if self._fmt.w_input_bits is None:
            return None
        return lambda v: (sum(Mux(c < 0, -c, c << 1) for c in v), sum(Mux(c < 0, -(c << 1), c) for c in v))

    @property
    def mantissa_bits(self):
        return self._fmt.d_bits


class ReceiverFilter(_Filter):
    """Row unit's filter: w^_k, Pw_k, Nw_k, [b_k > 0] from the exact w_k (latency 3)."""
    exact_layout = staticmethod(receiver_terms_layout)
    vectors, plane, one = "w", "pq", True

    @property
    def mantissa_bits(self):
        return self._fmt.w_bits

    def _sums(self):
        return None


def _carry_chain_cell(platform):
    """The platform for :func:`~blockray.rtl.lutdot.dot_product` when the cells' products are in
    the fabric of a target with carry cells (``ECP5Target(fabric_units={"cell"})``: ``CCU2C``
    bit heaps instead of Yosys's LUT multipliers), else None."""
    if getattr(platform, "ccu2c", False) and "cell" in getattr(platform, "fabric_units", ()):
        return platform
    return None


class FilteredProcessor(wiring.Component):
    """Filtered cell: the certified decision of one test per cycle (:func:`blockray.filtered.
    filter_decision`).

    Stages 1-2: the nine products d^_kc w^_kc (:func:`~blockray.rtl.processor._product`, one
    MULT18X18D each on ECP5; with ``carry_chains`` (the lean cell) and the cells in the fabric of
    ``ECP5Target(fabric_units={"cell"})`` the three products and their sum are one bit heap on
    CCU2C carry chains, :func:`~blockray.rtl.lutdot.dot_product`, the same register values from
    stage 3) and lo_k, hi_k; stage 3: s^_k; stage 4: s^ - lo and s^ + hi (one adder each); stage 5: the certificates s^ >= lo, s^ > lo, s^ <= -hi, s^ < -hi from their
    signs and zero tests, and ``decided`` and ``blocked`` (meaningful when ``decided``). ``crossing`` (sign(pP) sign(pQ) < 0, exact) comes with the terms.
    Latency :attr:`latency` = 5, one test per cycle.
    """

    latency = 5

    def __init__(self, fmt, *, carry_chains=False):
        self._fmt = fmt
        self._carry_chains = carry_chains
        super().__init__({
            "shooter": In(filter_terms_layout(fmt.d_bits, sum_bits(fmt.d_bits, fmt))),
            "receiver": In(filter_terms_layout(fmt.w_bits, sum_bits(fmt.w_bits, fmt))),
            "crossing": In(1),
            "valid": In(1),
            "decided": Out(1),
            "blocked": Out(1),
            "result_valid": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        f = self._fmt
        chains = _carry_chain_cell(platform) if self._carry_chains else None
        platform = product_platform(platform, "cell")
        width = f.d_bits + f.w_bits + 2
        sh, rc = self.shooter, self.receiver
        ge, gt, le, lt = [], [], [], []
        for k in range(3):
            if chains:      # the same s^_k, cycle for cycle, from one bit heap on carry chains
                s3 = dot_product(m, [(sh.m[k][c], rc.m[k][c]) for c in range(3)], width, f"s{k}_3", chains)
            else:
                products = [_product(m, sh.m[k][c], rc.m[k][c], f.d_bits + f.w_bits, f"p{k}{c}", platform)
                            for c in range(3)]
                s3 = Signal(signed(width), name=f"s{k}_3")
                m.d.sync += s3.eq(sum(products))
            a, b = sh.truncated[k], rc.truncated[k]
            lo1 = Signal(max(f.d_bits, f.w_bits) + 3, name=f"lo{k}_1")
            hi1 = Signal.like(lo1, name=f"hi{k}_1")
            m.d.sync += [lo1.eq(Mux(b, sh.neg[k], 0) + Mux(a, rc.neg[k], 0)),
                         hi1.eq(Mux(b, sh.pos[k], 0) + Mux(a, rc.pos[k], 0))]
            lo3, hi3 = _delay(m, lo1, 2, f"lo{k}"), _delay(m, hi1, 2, f"hi{k}")
            # stage 4: one adder each (no -hi formed, no comparator after an adder)
            x4 = Signal(signed(width + 1), name=f"x{k}_4")           # s^ - lo
            y4 = Signal(signed(width + 1), name=f"y{k}_4")           # s^ + hi
            m.d.sync += [x4.eq(s3 - lo3), y4.eq(s3 + hi3)]
            # stage 5 (with the decision): the certificates from signs and zero tests
            ge.append(~x4[-1])
            gt.append(~x4[-1] & (x4 != 0))
            le.append(y4[-1] | (y4 == 0))
            lt.append(y4[-1])
        crossing4 = _delay(m, self.crossing, 4, "crossing")
        inside = (ge[0] & ge[1] & ge[2]) | (le[0] & le[1] & le[2])
        outside = (gt[0] | gt[1] | gt[2]) & (lt[0] | lt[1] | lt[2])
        m.d.sync += [
            self.decided.eq(~crossing4 | inside | outside),
            self.blocked.eq(crossing4 & inside),
            self.result_valid.eq(_delay(m, self.valid, self.latency - 1, "valid")),
        ]
        return m


def pending_layout(tag_bits=TAG_BITS):
    """A test in the in-order hand-off: its tag, whether the filter decided it, and its answer."""
    return data.StructLayout({"tag": unsigned(tag_bits), "decided": unsigned(1), "blocked": unsigned(1)})


class InOrderResolve(wiring.Component):
    """The hand-off between a filtered cell and an exact unit, results in input order.

    ``i`` (valid only: the datapath never stalls; the owner's credits keep at most ``depth``
    tests inside): a test's tag, ``decided``, ``blocked`` and its exact ``operands``.
    Every test enters the *pending* FIFO (tag, decided, blocked); an undecided one's operands
    enter the *queue* to the exact unit. ``resolve`` offers the queue head to the exact unit
    (which must take it: ``resolve.valid`` is a pop), and ``resolved`` takes the exact unit's
    answers, in the order it was given the operands, into the *answers* FIFO. ``o`` delivers the
    pending head: its own answer if decided, else (once it is there) the answers head.

    In order because the queue, the exact unit and the answers are FIFOs: the oldest undecided
    test in the pending FIFO is the one whose answer heads the answers FIFO. Every FIFO has
    ``depth`` entries, so with at most ``depth`` tests inside none overflows.
    ``tag_bits``: the tag's width (:data:`TAG_BITS`; the formal harness uses fewer).
    """

    def __init__(self, operand_shape, depth, tag_bits=TAG_BITS):
        self._operand_shape = operand_shape
        self._depth = _check_depth(depth)
        self._tag_bits = tag_bits
        super().__init__({
            "i": In(stream.Signature(data.StructLayout({
                "tag": unsigned(tag_bits), "decided": unsigned(1), "blocked": unsigned(1),
                "operands": operand_shape}), always_ready=True)),
            "resolve": Out(stream.Signature(operand_shape, always_ready=True)),
            "resolved": In(stream.Signature(unsigned(1), always_ready=True)),
            "o": Out(stream.Signature(data.StructLayout({"blocked": unsigned(1), "tag": unsigned(tag_bits)}))),
        })
        # for the formal proofs' invariants (tests/test_filtered_formal.py): each FIFO's level,
        # whether some FIFO is written while it cannot take it, whether the pending FIFO's head
        # is there and whether the filter decided it
        self.levels = {name: Signal(range(depth + 1), name=f"{name}_level")
                       for name in ("pending", "queue", "answers")}
        self.overflow = Signal()
        self.head_valid, self.head_decided = Signal(), Signal()

    @property
    def depth(self):
        return self._depth

    def elaborate(self, platform):
        m = Module()
        op_width = Shape.cast(self._operand_shape).width
        layout = pending_layout(self._tag_bits)
        m.submodules.pending = pending = SyncFIFOBuffered(width=layout.size, depth=self._depth)
        m.submodules.queue = queue = SyncFIFOBuffered(width=op_width, depth=self._depth)
        m.submodules.answers = answers = SyncFIFOBuffered(width=1, depth=self._depth)
        fifos = {"pending": pending, "queue": queue, "answers": answers}
        m.d.comb += [self.levels[n].eq(f.level) for n, f in fifos.items()]
        m.d.comb += self.overflow.eq(sum_or(f.w_en & ~f.w_rdy for f in fifos.values()))

        entry = Signal(layout)
        head = Signal(layout)
        m.d.comb += [
            entry.tag.eq(self.i.payload.tag), entry.decided.eq(self.i.payload.decided),
            entry.blocked.eq(self.i.payload.blocked),
            pending.w_data.eq(entry), pending.w_en.eq(self.i.valid),
            queue.w_data.eq(self.i.payload.operands), queue.w_en.eq(self.i.valid & ~self.i.payload.decided),
            self.resolve.payload.eq(queue.r_data), self.resolve.valid.eq(queue.r_rdy), queue.r_en.eq(1),
            answers.w_data.eq(self.resolved.payload), answers.w_en.eq(self.resolved.valid),
            head.eq(pending.r_data), self.head_valid.eq(pending.r_rdy), self.head_decided.eq(head.decided),
            self.o.valid.eq(pending.r_rdy & (head.decided | answers.r_rdy)),
            self.o.payload.tag.eq(head.tag),
            self.o.payload.blocked.eq(Mux(head.decided, head.blocked, answers.r_data)),
            pending.r_en.eq(self.o.valid & self.o.ready),
            answers.r_en.eq(self.o.valid & self.o.ready & ~head.decided),
        ]
        return m


class _FilteredCells:
    """What the filtered arrays (1 x 1 and R x S) share: the latency from their input to the
    filtered cells' results, the filter format :attr:`fmt` and the hand-off's :attr:`depth`."""

    #: cycles from the input to the filtered cells' results (units, filters, cells)
    latency = ShooterUnit.latency + _Filter.latency + FilteredProcessor.latency

    def _configure(self, bits, fmt, depth):
        self._bits = check_bits(bits)
        # default: the filtered cell's (d_k exact, w_k at 18 bits); the lean array passes its own
        self._fmt = fmt if fmt is not None else Cell("filtered").format_at(bits)
        self._depth = _check_depth(depth)

    @property
    def depth(self):
        return self._depth

    @property
    def fmt(self):
        return self._fmt


class FilteredIntersector(_FilteredCells, wiring.Component):
    """The 1 x 1 filtered array with stream ports (the ports of
    :class:`~blockray.rtl.processor.Intersector`): exact units, their filters, the filtered cell,
    the hand-off (:class:`InOrderResolve`) and one exact :class:`Processor` for the undecided
    tests. Results in input order, always the exact predicate's.

    Backpressure by credits, as in the Intersector: a registered count of tests accepted but not
    delivered, ``i.ready = count < depth``. The datapath never stalls; an undecided test at the
    head of the pending FIFO holds back the decided ones behind it (:attr:`resolve_latency`
    cycles more), so the credits run out, and ``i.ready`` falls, only when undecided tests come
    faster than the depth covers: the timing depends on the data.
    """

    def __init__(self, bits, fmt=None, depth=None):
        self._configure(bits, fmt, depth if depth is not None else self.latency + Processor.latency + 4)
        super().__init__({
            "i": In(stream.Signature(query_layout(bits))),
            "o": Out(stream.Signature(result_layout())),
        })

    def elaborate(self, platform):
        m = Module()
        bits = self._bits
        m.submodules.shooter = shooter = ShooterUnit(bits)
        m.submodules.receiver = receiver = ReceiverUnit(bits)
        m.submodules.shooter_filter = sf = ShooterFilter(bits, self._fmt)
        m.submodules.receiver_filter = rf = ReceiverFilter(bits, self._fmt)
        m.submodules.cell = cell = FilteredProcessor(self._fmt)
        operands = data.StructLayout({"shooter": shooter_terms_layout(bits), "receiver": receiver_terms_layout(bits)})
        m.submodules.handoff = handoff = InOrderResolve(operands, self._depth)
        m.submodules.exact = exact = Processor(bits, unit="exact")

        accept = _credits(m, self.i, self.o, self._depth)

        payload = self.i.payload
        m.d.comb += [
            shooter.point.eq(payload.shooter), shooter.patch.eq(payload.patch), shooter.valid.eq(accept),
            receiver.point.eq(payload.receiver), receiver.patch.eq(payload.patch), receiver.valid.eq(accept),
            sf.exact.eq(shooter.terms), sf.valid.eq(shooter.terms_valid),
            rf.exact.eq(receiver.terms), rf.valid.eq(receiver.terms_valid),
            cell.shooter.eq(sf.terms), cell.receiver.eq(rf.terms), cell.valid.eq(sf.terms_valid),
            cell.crossing.eq(_crossing(sf.plane_out, rf.plane_out)),
        ]
        exact_terms = Signal(operands)
        m.d.comb += [exact_terms.shooter.eq(shooter.terms), exact_terms.receiver.eq(receiver.terms)]
        hand = handoff.i.payload
        m.d.comb += [
            hand.tag.eq(_delay(m, payload.tag, self.latency, "tag")),
            hand.decided.eq(cell.decided), hand.blocked.eq(cell.blocked),
            hand.operands.eq(_delay_memory(m, exact_terms, _Filter.latency + FilteredProcessor.latency, "operands")),
            handoff.i.valid.eq(cell.result_valid),
            exact.shooter.eq(handoff.resolve.payload.shooter), exact.receiver.eq(handoff.resolve.payload.receiver),
            exact.valid.eq(handoff.resolve.valid), exact.first.eq(1),
            handoff.resolved.payload.eq(exact.blocked), handoff.resolved.valid.eq(exact.result_valid),
        ]
        wiring.connect(m, handoff.o, wiring.flipped(self.o))
        return m


def array_item_layout(rows, cols, mark_shape):
    """An item of the filtered array's in-order hand-off (:class:`ArrayResolve`): a record's
    filter results (``blocked``: bit r * S + s, ``needs``: some test went to the exact unit,
    ``first``) or a marker (``mark``, its opaque ``mark_data``)."""
    return data.StructLayout({
        "first": unsigned(1), "mark": unsigned(1), "needs": unsigned(1),
        "blocked": unsigned(rows * cols), "mark_data": mark_shape,
    })


class ArrayResolve(wiring.Component):
    """The filtered array's hand-off: every item (a broadcast record's R x S filter results, or
    a board marker) leaves in input order, a record once its undecided tests have their exact
    answers, which come from ONE exact :class:`~blockray.rtl.processor.Processor` shared by the
    array.

    ``i`` (valid only): an item and, for a record, ``undecided`` (bit r * S + s: the tests the
    exact unit must decide) with the exact terms of every column and row. Every item enters the
    *pending* FIFO; a record with undecided tests enters the *queue* with its terms. The
    *server* takes the queue head's undecided tests one per :attr:`exact_interval` cycles (lowest
    index first) into the exact Processor; its answers are gathered per record, and a record's
    answer vector enters the *answers* FIFO with its last test's answer. ``o`` (always taken)
    delivers the pending head: a marker or a record without undecided tests at once, else with
    the answers head.

    In order because the queue, the server, the Processor and the answers are in order. Every
    FIFO has ``depth`` entries; the owner's credits keep at most ``depth`` items inside.
    ``exact_unit``: a factory of the exact unit (default ``Processor(bits)``; the formal harness
    gives a stand-in with its ports and latency).

    Named for the formal proof's invariants (tests/test_filtered_formal.py), made here so that
    they exist before elaboration (no added logic): ``fifos`` (``pending``, ``queue``,
    ``answers``), the queue ``head``, the server's state ``started`` (the head's first test is
    out) and ``remaining`` (its tests still to serve, when started), ``gathered`` (the answers of
    the record being gathered), and beside the exact unit the Processor.latency stages of
    ``which`` (a test's bit in its record) and ``final`` (its record's last test); ``serve``
    (a test goes to the exact unit) and ``wait`` (cycles until it takes the next).
    """

    def __init__(self, bits, rows, cols, mark_shape, depth, *, exact_unit=None):
        self._bits, self._rows, self._cols, self._depth = bits, rows, cols, _check_depth(depth)
        self._exact_unit = exact_unit or self._default_exact_unit
        self._mark_shape = mark_shape
        self._terms = self._terms_layout()
        item = array_item_layout(rows, cols, mark_shape)
        RS = rows * cols
        self._queued = data.StructLayout({"undecided": unsigned(RS), "terms": self._terms})
        self.fifos = {name: SyncFIFOBuffered(width=width, depth=self._depth)
                      for name, width in (("pending", item.size), ("queue", self._queued.size), ("answers", RS))}
        self.head = Signal(self._queued, name="head")
        self.started, self.remaining = Signal(name="started"), Signal(RS, name="remaining")
        self.gathered = Signal(RS, name="gathered")
        self.serve = Signal(name="serve")
        self.wait = Signal(range(max(2, self.exact_interval)), name="wait")
        self.which = [Signal(RS, name=f"which_{n + 1}") for n in range(self.exact_latency)]
        self.final = [Signal(name=f"final_{n + 1}") for n in range(self.exact_latency)]
        super().__init__({
            "i": In(stream.Signature(data.StructLayout({
                "item": item, "undecided": unsigned(rows * cols), "terms": self._terms}), always_ready=True)),
            "o": Out(stream.Signature(data.StructLayout({
                "item": item, "blocked": unsigned(rows * cols)}), always_ready=True)),
        })

    #: the exact unit's latency (valid in, result_valid out)
    exact_latency = Processor.latency
    #: cycles from one test into the exact unit to the next (the server waits between them)
    exact_interval = 1

    def _default_exact_unit(self):
        return Processor(self._bits, unit="exact")

    def _terms_layout(self):
        """What a record with undecided tests takes into the queue beside them: the exact terms
        of every column and row."""
        return data.StructLayout({
            "shooters": data.ArrayLayout(shooter_terms_layout(self._bits), self._cols),
            "receivers": data.ArrayLayout(receiver_terms_layout(self._bits), self._rows)})

    def _feed(self, m, exact, terms, onehot, valid):
        """Give the exact unit the test ``onehot`` of the queue head (``terms``) when ``valid``:
        its column's and row's exact terms."""
        R, S = self._rows, self._cols
        shooter, receiver = Signal(shooter_terms_layout(self._bits)), Signal(receiver_terms_layout(self._bits))
        m.d.comb += [
            shooter.eq(sum_or(Mux(sum_or(onehot[r * S + s] for r in range(R)), terms.shooters[s].as_value(), 0)
                              for s in range(S))),
            receiver.eq(sum_or(Mux(sum_or(onehot[r * S + s] for s in range(S)), terms.receivers[r].as_value(), 0)
                               for r in range(R))),
            exact.shooter.eq(shooter), exact.receiver.eq(receiver),
            exact.valid.eq(valid), exact.first.eq(1),
        ]

    def _exact_free(self, m):
        """The exact unit takes a test this cycle: always, or ``exact_interval`` cycles after
        the last (``wait`` counts them down)."""
        if self.exact_interval == 1:
            return 1
        wait = self.wait
        with m.If(self.serve):
            m.d.sync += wait.eq(self.exact_interval - 1)
        with m.Elif(wait != 0):
            m.d.sync += wait.eq(wait - 1)
        return wait == 0

    def elaborate(self, platform):
        m = Module()
        R, S, RS = self._rows, self._cols, self._rows * self._cols
        item_layout = array_item_layout(R, S, self._mark_shape)
        m.submodules.pending = pending = self.fifos["pending"]
        m.submodules.queue = queue = self.fifos["queue"]
        m.submodules.answers = answers = self.fifos["answers"]
        m.submodules.exact = exact = self._exact_unit()

        # in: every item to pending, a record with undecided tests to the queue
        entry = Signal(self._queued)
        m.d.comb += [
            pending.w_data.eq(self.i.payload.item), pending.w_en.eq(self.i.valid),
            entry.undecided.eq(self.i.payload.undecided), entry.terms.eq(self.i.payload.terms),
            queue.w_data.eq(entry), queue.w_en.eq(self.i.valid & (self.i.payload.undecided != 0)),
        ]

        # the server: the head's undecided tests, lowest index first, one per exact_interval cycles
        head, started, remaining = self.head, self.started, self.remaining
        current = Signal(RS)
        onehot = Signal(RS)
        last = Signal()
        serve = self.serve
        m.d.comb += [
            head.eq(queue.r_data),
            current.eq(Mux(started, remaining, head.undecided)),
            onehot.eq(current & -current),
            last.eq((current & ~onehot) == 0),
            serve.eq(queue.r_rdy & self._exact_free(m)),
            queue.r_en.eq(serve & last),
        ]
        with m.If(serve):
            m.d.sync += [remaining.eq(current & ~onehot), started.eq(~last)]
        self._feed(m, exact, head.terms, onehot, serve)

        # the answers: gathered per record, pushed with its last test's answer
        which = _delay_through(m, onehot, self.which)
        final = _delay_through(m, last, self.final)
        gathered = self.gathered
        vector = Signal(RS)
        m.d.comb += [
            vector.eq(gathered | Mux(exact.blocked, which, 0)),
            answers.w_data.eq(vector), answers.w_en.eq(exact.result_valid & final),
        ]
        with m.If(exact.result_valid):
            m.d.sync += gathered.eq(Mux(final, 0, vector))

        # out: the pending head, in order
        item = Signal(item_layout)
        m.d.comb += [
            item.eq(pending.r_data),
            self.o.valid.eq(pending.r_rdy & (~item.needs | answers.r_rdy)),
            self.o.payload.item.eq(item),
            self.o.payload.blocked.eq(item.blocked | Mux(item.needs, answers.r_data, 0)),
            pending.r_en.eq(self.o.valid),
            answers.r_en.eq(self.o.valid & item.needs),
        ]
        return m


class FilteredArray(_FilteredCells, wiring.Component):
    """R x S filtered cells fed by one broadcast patch record per cycle, with one exact unit
    shared by the array (:class:`ArrayResolve`): the ports of
    :class:`~blockray.rtl.array.ProcessorArray` and a marker path.

    Column ``s``: a ShooterUnit and its ShooterFilter; row ``r``: a ReceiverUnit and its
    ReceiverFilter; cell (r, s): a :class:`FilteredProcessor`. A test of a loaded row and
    column (``row_mask``, ``col_mask``, sampled with the record) that the filter leaves
    undecided goes to the exact unit; the record's results reach the accumulators ``hit`` in
    input order once its answers are in, so ``hit`` is always the exact predicate's OR (tests of
    rows or columns not loaded are not resolved; the board masks them out).

    ``mark`` (with ``mark_data``) puts a marker into the record stream instead of a record: it
    leaves (``mark_out``, ``mark_data_out``) in order, when ``hit`` holds the OR of every record
    before it. ``delivered``: an item (record or marker) left this cycle; the owner keeps at most
    :attr:`depth` items inside (its credits) and never presents two in one cycle.
    Latency from the input to the hand-off: :attr:`latency` = 12; to ``delivered`` at the
    earliest :attr:`latency` + 2 (the pending FIFO's write and output register).
    """

    #: the cells' products as CCU2C bit heaps when in the ECP5 fabric (the lean array's)
    carry_chain_cells = False
    #: registers between the cells' decisions and the hand-off (0 or 1; in :attr:`latency`)
    handoff_stages = 0

    def __init__(self, bits, rows, cols, *, fmt=None, depth=None, mark_shape=unsigned(1)):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        self._configure(bits, fmt, depth if depth is not None else self.default_depth())
        self._rows, self._cols = rows, cols
        self._mark_shape = mark_shape
        super().__init__({
            **broadcast_signature(bits, rows, cols).members,
            "row_mask": In(rows),
            "col_mask": In(cols),
            "mark": In(1),
            "mark_data": In(mark_shape),
            "hit": Out(unsigned(rows * cols)),
            "delivered": Out(1),
            "mark_out": Out(1),
            "mark_data_out": Out(mark_shape),
            **self._extra_members(),
        })
        self._MustUse__silence = False

    def _extra_members(self):
        """Ports a subclass adds after these."""
        return {}

    @classmethod
    def default_depth(cls, extra_latency=0):
        """Items in flight for one record per cycle while every test is decided: the latency to
        delivery (plus ``extra_latency`` in front of the array, the board's memory) and 4."""
        return cls.latency + 2 + extra_latency + 4

    def _edge_unit(self, m, name, unit_cls, filter_cls, point):
        """An array-edge unit (shooter or receiver) for ``point`` and its filter, named
        ``name`` and ``name``'s filter; returns the filter, whose terms the cells take."""
        unit = m.submodules[name] = unit_cls(self._bits)
        kind, index = name.rsplit("_", 1)
        filt = m.submodules[f"{kind}_filter_{index}"] = filter_cls(self._bits, self._fmt)
        m.d.comb += [unit.point.eq(point), unit.patch.eq(self.patch), unit.valid.eq(self.valid),
                     filt.exact.eq(unit.terms), filt.valid.eq(unit.terms_valid)]
        return filt

    def _receiver_edge(self, m, r):
        """Row ``r``'s unit and filter; returns what the cells take (``terms``, ``plane_out``,
        ``terms_valid``, ``exact``)."""
        return self._edge_unit(m, f"receiver_{r}", ReceiverUnit, ReceiverFilter, self.receivers[r])

    def _resolve(self):
        """The hand-off with the array's exact unit."""
        return ArrayResolve(self._bits, self._rows, self._cols, self._mark_shape, self._depth)

    def _queue_terms(self, m, hand, shooters, receivers):
        """The ``terms`` of a record at the hand-off: the exact terms of every column and row,
        which wait for the cells' decisions in one memory, not in flip-flop chains (a 2 x 2
        array's chains were half its flip-flops)."""
        terms = Signal.like(hand.terms)
        m.d.comb += [terms.shooters[s].eq(shooters[s].exact) for s in range(self._cols)]
        m.d.comb += [terms.receivers[r].eq(receivers[r].exact) for r in range(self._rows)]
        m.d.comb += hand.terms.eq(_delay_memory(m, terms, _Filter.latency + FilteredProcessor.latency, "terms"))

    def elaborate(self, platform):
        m = Module()
        B, R, S, fmt = self._bits, self._rows, self._cols, self._fmt
        shooters = [self._edge_unit(m, f"shooter_{s}", ShooterUnit, ShooterFilter, self.shooters[s]) for s in range(S)]
        receivers = [self._receiver_edge(m, r) for r in range(R)]

        m.submodules.resolve = resolve = self._resolve()
        hand = Signal(resolve.i.payload.shape(), name="hand")
        hand_valid = Signal(name="hand_valid")
        # the lean array's register: its cells' decisions reach the queue across the part
        handoff = m.d.sync if self.handoff_stages else m.d.comb
        handoff += [resolve.i.payload.eq(hand), resolve.i.valid.eq(hand_valid)]
        L = self.latency - self.handoff_stages
        valid = _delay(m, self.valid, L, "valid")
        row_mask = _delay(m, self.row_mask, L, "row_mask")
        col_mask = _delay(m, self.col_mask, L, "col_mask")
        blocked, undecided = [], []
        for r in range(R):
            for s in range(S):
                cell = m.submodules[f"cell_{r}_{s}"] = FilteredProcessor(fmt, carry_chains=self.carry_chain_cells)
                m.d.comb += [
                    cell.shooter.eq(shooters[s].terms), cell.receiver.eq(receivers[r].terms),
                    cell.valid.eq(shooters[s].terms_valid),
                    cell.crossing.eq(_crossing(shooters[s].plane_out, receivers[r].plane_out)),
                ]
                blocked.append(cell.blocked)
                undecided.append(~cell.decided & row_mask[r] & col_mask[s])
        self._queue_terms(m, hand, shooters, receivers)
        mark = _delay(m, self.mark, L, "mark")
        m.d.comb += [
            hand.undecided.eq(Mux(valid, Cat(*undecided), 0)),
            hand.item.blocked.eq(Cat(*blocked)),
            hand.item.needs.eq(valid & (Cat(*undecided) != 0)),
            hand.item.first.eq(_delay(m, self.first, L, "first")),
            hand.item.mark.eq(mark),
            hand.item.mark_data.eq(_delay(m, self.mark_data, L, "mark_data")),
            hand_valid.eq(valid | mark),
        ]

        out = resolve.o.payload
        record = resolve.o.valid & ~out.item.mark
        with m.If(record):
            m.d.sync += self.hit.eq(out.blocked | Mux(out.item.first, 0, self.hit))
        m.d.comb += [
            self.delivered.eq(resolve.o.valid),
            self.mark_out.eq(resolve.o.valid & out.item.mark),
            self.mark_data_out.eq(out.item.mark_data),
        ]
        return m
