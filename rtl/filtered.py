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

from amaranth.hdl import Module, Mux, Shape, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from ..filtered import FilterFormat
from .platform import product_platform
from ..params import Widths
from .processor import (TAG_BITS, Processor, ReceiverUnit, ShooterUnit, _AXES, _check_bits, _delay, _product,
                        query_layout, receiver_terms_layout, result_layout, shooter_terms_layout)

__all__ = ["filter_terms_layout", "ShooterFilter", "ReceiverFilter", "FilteredProcessor", "FilteredIntersector",
           "InOrderResolve"]


def filter_terms_layout(bits):
    """A unit's filter output for its three vectors: mantissas ``m[k][c]`` (signed ``bits``), the
    sums ``pos[k]``, ``neg[k]`` (unsigned bits + 1: at most 3 * 2**(bits-1) + 3) and
    ``truncated[k]`` (exponent > 0)."""
    return data.StructLayout({
        "m": data.ArrayLayout(data.ArrayLayout(signed(bits), 3), 3),
        "pos": data.ArrayLayout(unsigned(bits + 1), 3),
        "neg": data.ArrayLayout(unsigned(bits + 1), 3),
        "truncated": unsigned(3),
    })


def _truncate(m, x, bits, name, one):
    """Three stages of :func:`blockray.filtered.truncate` and the unit's sums for vector ``x``
    (three signed values): stage 1 the exponent (OR of the magnitudes, leading one), stage 2 the
    mantissas ``x >> e`` and [e > 0], stage 3 Pos and Neg (``one``: add [e > 0] to each
    non-negative mantissa, the row unit's Pw). Returns (mantissas, truncated, pos, neg)."""
    width = len(x[0])
    x1 = [Signal(signed(width), name=f"{name}_x1_{c}") for c in range(3)]
    e1 = Signal(range(max(2, width)), name=f"{name}_e1")
    magnitude = Signal(width - 1, name=f"{name}_mag")
    m.d.comb += magnitude.eq(sum_or(Mux(v[-1], ~v, v)[:width - 1] for v in x))
    e0 = Signal.like(e1, name=f"{name}_e0")
    for i in range(bits - 1, width - 1):          # leading one at i: bit length i + 1
        with m.If(magnitude[i]):
            m.d.comb += e0.eq(i + 2 - bits)       # later statements win: the highest one
    m.d.sync += [e1.eq(e0)] + [r.eq(v) for r, v in zip(x1, x)]

    m2 = [Signal(signed(bits), name=f"{name}_m2_{c}") for c in range(3)]
    t2 = Signal(name=f"{name}_t2")
    m.d.sync += [r.eq((v >> e1)[:bits]) for r, v in zip(m2, x1)] + [t2.eq(e1 != 0)]

    pos = Signal(bits + 1, name=f"{name}_pos3")
    neg = Signal(bits + 1, name=f"{name}_neg3")
    extra = t2 if one else 0
    m.d.sync += [
        pos.eq(sum(Mux(v < 0, 0, v + extra) for v in m2)),
        neg.eq(sum(Mux(v < 0, -v, 0) for v in m2)),
    ]
    return [_delay(m, v, 1, f"{name}_m3_{c}") for c, v in enumerate(m2)], _delay(m, t2, 1, f"{name}_t3"), pos, neg


def sum_or(values):
    out = 0
    for v in values:
        out = out | v
    return out


class _Filter(wiring.Component):
    """A unit's filter stage: exact terms in, filter terms (and the exact terms, delayed) out
    after :attr:`latency` cycles. Subclasses set ``exact_layout``, ``vectors`` and ``one``."""

    latency = 3

    def __init__(self, bits, fmt):
        self._bits = _check_bits(bits)
        self._fmt = fmt
        super().__init__({
            "exact": In(self.exact_layout(bits)),
            "valid": In(1),
            "terms": Out(filter_terms_layout(self.mantissa_bits)),
            "exact_out": Out(self.exact_layout(bits)),
            "terms_valid": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        for k in range(3):
            vector = getattr(self.exact, self.vectors)[k]
            mant, trunc, pos, neg = _truncate(m, [vector[c] for c in _AXES], self.mantissa_bits, f"f{k}", self.one)
            for c in range(3):
                m.d.comb += self.terms.m[k][c].eq(mant[c])
            m.d.comb += [self.terms.pos[k].eq(pos), self.terms.neg[k].eq(neg), self.terms.truncated[k].eq(trunc)]
        m.d.comb += [
            self.exact_out.eq(_delay(m, self.exact, self.latency, "exact")),
            self.terms_valid.eq(_delay(m, self.valid, self.latency, "valid")),
        ]
        return m


class ShooterFilter(_Filter):
    """Column unit's filter: d^_k, Pd_k, Nd_k, [a_k > 0] from the exact d_k (latency 3)."""
    exact_layout = staticmethod(shooter_terms_layout)
    vectors, one = "d", False

    @property
    def mantissa_bits(self):
        return self._fmt.d_bits


class ReceiverFilter(_Filter):
    """Row unit's filter: w^_k, Pw_k, Nw_k, [b_k > 0] from the exact w_k (latency 3)."""
    exact_layout = staticmethod(receiver_terms_layout)
    vectors, one = "w", True

    @property
    def mantissa_bits(self):
        return self._fmt.w_bits


class FilteredProcessor(wiring.Component):
    """Filtered cell: the certified decision of one test per cycle (:func:`blockray.filtered.
    filter_decision`).

    Stages 1-2: the nine products d^_kc w^_kc (:func:`~blockray.rtl.processor._product`, one
    MULT18X18D each on ECP5) and lo_k, hi_k; stage 3: s^_k; stage 4: s^ - lo and s^ + hi (one
    adder each); stage 5: the certificates s^ >= lo, s^ > lo, s^ <= -hi, s^ < -hi from their
    signs and zero tests, and ``decided`` and ``blocked`` (meaningful when ``decided``). ``crossing`` (sign(pP) sign(pQ) < 0, exact) comes with the terms.
    Latency :attr:`latency` = 5, one test per cycle.
    """

    latency = 5

    def __init__(self, fmt):
        self._fmt = fmt
        super().__init__({
            "shooter": In(filter_terms_layout(fmt.d_bits)),
            "receiver": In(filter_terms_layout(fmt.w_bits)),
            "crossing": In(1),
            "valid": In(1),
            "decided": Out(1),
            "blocked": Out(1),
            "result_valid": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        f = self._fmt
        platform = product_platform(platform, "cell")
        width = f.d_bits + f.w_bits + 2
        sh, rc = self.shooter, self.receiver
        ge, gt, le, lt = [], [], [], []
        for k in range(3):
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
        self._depth = depth
        self._tag_bits = tag_bits
        super().__init__({
            "i": In(stream.Signature(data.StructLayout({
                "tag": unsigned(tag_bits), "decided": unsigned(1), "blocked": unsigned(1),
                "operands": operand_shape}), always_ready=True)),
            "resolve": Out(stream.Signature(operand_shape, always_ready=True)),
            "resolved": In(stream.Signature(unsigned(1), always_ready=True)),
            "o": Out(stream.Signature(data.StructLayout({"blocked": unsigned(1), "tag": unsigned(tag_bits)}))),
        })

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

        entry = Signal(layout)
        head = Signal(layout)
        m.d.comb += [
            entry.tag.eq(self.i.payload.tag), entry.decided.eq(self.i.payload.decided),
            entry.blocked.eq(self.i.payload.blocked),
            pending.w_data.eq(entry), pending.w_en.eq(self.i.valid),
            queue.w_data.eq(self.i.payload.operands), queue.w_en.eq(self.i.valid & ~self.i.payload.decided),
            self.resolve.payload.eq(queue.r_data), self.resolve.valid.eq(queue.r_rdy), queue.r_en.eq(1),
            answers.w_data.eq(self.resolved.payload), answers.w_en.eq(self.resolved.valid),
            head.eq(pending.r_data),
            self.o.valid.eq(pending.r_rdy & (head.decided | answers.r_rdy)),
            self.o.payload.tag.eq(head.tag),
            self.o.payload.blocked.eq(Mux(head.decided, head.blocked, answers.r_data)),
            pending.r_en.eq(self.o.valid & self.o.ready),
            answers.r_en.eq(self.o.valid & self.o.ready & ~head.decided),
        ]
        return m


class FilteredIntersector(wiring.Component):
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
        self._bits = _check_bits(bits)
        # default: d_k exact (B + 1 bits), w_k at 18 bits: one MULT18X18D per product
        self._fmt = fmt if fmt is not None else FilterFormat(min(bits + 1, 18), 18)
        self._depth = depth if depth is not None else self.latency + Processor.latency + 4
        super().__init__({
            "i": In(stream.Signature(query_layout(bits))),
            "o": Out(stream.Signature(result_layout())),
        })

    #: cycles from acceptance to the filtered cell's result (units, filters, cell)
    latency = ShooterUnit.latency + _Filter.latency + FilteredProcessor.latency

    @property
    def depth(self):
        return self._depth

    @property
    def fmt(self):
        return self._fmt

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
        m.submodules.exact = exact = Processor(bits)

        accept = self.i.valid & self.i.ready
        deliver = self.o.valid & self.o.ready
        count = Signal(range(self._depth + 1))
        m.d.comb += self.i.ready.eq(count < self._depth)
        m.d.sync += count.eq(count + accept - deliver)

        payload = self.i.payload
        pp, pq = sf.exact_out.pp, rf.exact_out.pq
        m.d.comb += [
            shooter.point.eq(payload.shooter), shooter.patch.eq(payload.patch), shooter.valid.eq(accept),
            receiver.point.eq(payload.receiver), receiver.patch.eq(payload.patch), receiver.valid.eq(accept),
            sf.exact.eq(shooter.terms), sf.valid.eq(shooter.terms_valid),
            rf.exact.eq(receiver.terms), rf.valid.eq(receiver.terms_valid),
            cell.shooter.eq(sf.terms), cell.receiver.eq(rf.terms), cell.valid.eq(sf.terms_valid),
            cell.crossing.eq(((pp > 0) & (pq < 0)) | ((pp < 0) & (pq > 0))),
        ]
        exact_terms = Signal(operands)
        m.d.comb += [exact_terms.shooter.eq(sf.exact_out), exact_terms.receiver.eq(rf.exact_out)]
        hand = handoff.i.payload
        m.d.comb += [
            hand.tag.eq(_delay(m, payload.tag, self.latency, "tag")),
            hand.decided.eq(cell.decided), hand.blocked.eq(cell.blocked),
            hand.operands.eq(_delay(m, exact_terms, FilteredProcessor.latency, "operands")),
            handoff.i.valid.eq(cell.result_valid),
            exact.shooter.eq(handoff.resolve.payload.shooter), exact.receiver.eq(handoff.resolve.payload.receiver),
            exact.valid.eq(handoff.resolve.valid), exact.first.eq(1),
            handoff.resolved.payload.eq(exact.blocked), handoff.resolved.valid.eq(exact.result_valid),
        ]
        wiring.connect(m, handoff.o, wiring.flipped(self.o))
        return m
