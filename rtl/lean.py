"""The lean processor cell: the filter and nothing else in the cells; undecided tests leave as tags.

The R x S array of :class:`LeanArray` is the filtered array's datapath (docs/processor.md,
"The lean cell"): the column and row units compute the shared terms once per record and ray,
exactly (:class:`~blockray.rtl.processor.ShooterUnit`, :class:`~blockray.rtl.processor.ReceiverUnit`)
and rounded for the filter (:class:`~blockray.rtl.filtered.ShooterFilter`,
:class:`~blockray.rtl.filtered.ReceiverFilter`: mantissas and the certificate sums Pd, Nd, Pw,
Nw of every row and column); a cell (:class:`~blockray.rtl.filtered.FilteredProcessor`) holds
only the narrow products, the two threshold adders and the comparisons. What differs is the
hand-off: no exact term waits or travels. A record with undecided tests enters the queue as a
*tag* (its undecided mask, the record's patch ``address`` and its ``slot`` in the end-point
memory), and the shared exact unit (:class:`LeanExact`) recomputes each undecided test from the
patch memory (a second read port, ``patch_read``) and the test's shooter and receiver points,
which every record writes into the end-point memory (one entry per record in flight) as it
enters the array.

    LeanArray(bits, rows, cols, fmt=None, depth=None)     the ports of FilteredArray, and
        address     In: the record's address in the patch memory (with ``valid``)
        patch_read  a read port of the patch memory (registered read, one cycle)
"""

from amaranth.hdl import Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory, ReadPort
from amaranth.lib.wiring import In, Out

from ..errors import ParameterError
from ..cell import Cell
from ..params import Widths
from ..records import patch_layout, point_layout, vector_layout
from .filtered import (ArrayResolve, FilteredArray, ReceiverFilter, _exponent, _Filter, _truncate,
                       filter_terms_layout, sum_bits, sum_or)
from .platform import product_platform
from .lutdot import dot_product
from .processor import (_AXES, _VERTICES, ReceiverUnit, _combine, _cross_product, _delay, _dot_sums,
                        _product, _sign_and_zero)

__all__ = ["LeanReceiver", "LeanRowUnit", "LeanExact", "LeanResolve", "LeanArray", "tag_layout",
           "DEFAULT_ADDRESS_BITS"]

#: patch memory address width of a stand-alone array (the board's is its memory's)
DEFAULT_ADDRESS_BITS = 12


def endpoints_layout(bits, rows, cols):
    """One end-point memory entry: the S shooter points and the R receiver points of a record."""
    point = point_layout(bits)
    return data.StructLayout({"shooters": data.ArrayLayout(point, cols),
                              "receivers": data.ArrayLayout(point, rows)})


def tag_layout(address_bits, slots):
    """What a record with undecided tests queues beside its undecided mask: its patch address
    and its end-point memory slot."""
    return data.StructLayout({"address": unsigned(address_bits), "slot": range(slots)})


class LeanReceiver(wiring.Component):
    """The lean array's row unit: pQ exactly, and w^_k, Pw'_k, Nw'_k, [b_k > 0] of w_k from
    ``fmt.w_input_bits``-bit mantissas of dQ_k = Q - V_k and e_k = V_{k+1} - V_k
    (:func:`blockray.filtered.rounded_receiver_filter_terms`), never w_k itself.

    Stage 1: dQ_k, e_k and their exponents; 2: the mantissas q, g (the products' operand
    registers); 3: the 18 products q_a g_b (m_i x m_i, :func:`~blockray.rtl.processor._product`);
    4: W = q x g (exact, 2 m_i + 1 bits); 5-7: W's exponent (at least m_i + 2 where an input was
    rounded), w^ and the sums. pQ: the ReceiverUnit's (stage 4), delayed to 7. The ports and
    latency (7) of a ReceiverUnit followed by its ReceiverFilter: ``terms``, ``plane_out``,
    ``terms_valid``. Its products answer to the fabric-units key ``receiver``, the 18 of w_k also to
    ``rounded`` (``--fabric-units rounded``: on LUTs, pQ on DSPs). In the fabric of a target with
    carry cells (``ECP5Target``) each W_c = q_a g_b - q_b g_a is one bit heap on CCU2C carry
    chains (:func:`~blockray.rtl.lutdot.dot_product`), the same register values from stage 4.
    """

    latency = ReceiverUnit.latency + _Filter.latency

    def __init__(self, bits, fmt):
        self._bits, self._fmt = bits, fmt
        super().__init__({
            "point": In(point_layout(bits)), "patch": In(patch_layout(bits)), "valid": In(1),
            "terms": Out(filter_terms_layout(fmt.w_bits, sum_bits(fmt.w_bits, fmt))),
            "plane_out": Out(signed(Widths(bits).orient)),
            "terms_valid": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        w, f = Widths(self._bits), self._fmt
        inputs = f.w_input_bits
        chains = _row_chains(platform)
        platform = product_platform(platform, "receiver")
        rounded = product_platform(platform, "rounded")
        dq0, e0 = _edge_vectors(m, self.point, self.patch, w)
        pq4 = Signal(signed(w.orient), name="pq_4")
        sums3 = _dot_sums(m, [(dq0[0][c], self.patch.normal[c]) for c in _AXES], w.orient, "pq", platform)
        m.d.sync += pq4.eq(_combine(sums3, w.orient))
        for k in range(3):
            q1, al1 = _exponent(m, [dq0[k][c] for c in _AXES], inputs, f"q{k}")
            g1, be1 = _exponent(m, [e0[k][c] for c in _AXES], inputs, f"g{k}")
            q = [(v >> al1)[:inputs].as_signed() for v in q1]
            g = [(v >> be1)[:inputs].as_signed() for v in g1]
            W4 = []
            for i, c in enumerate(_AXES):       # (q x g)_c = q_{c+1} g_{c+2} - q_{c+2} g_{c+1}
                a, b = (i + 1) % 3, (i + 2) % 3
                if chains:      # the same W, cycle for cycle, from one bit heap on carry chains
                    W4.append(dot_product(m, [(q[a], g[b]), (q[b], g[a], True)], 2 * inputs + 1,
                                          f"W{k}_{c}_4", chains))
                    continue
                plus = _product(m, q[a], g[b], 2 * inputs, f"w{k}_{c}_plus_3", rounded)
                minus = _product(m, q[b], g[a], 2 * inputs, f"w{k}_{c}_minus_3", rounded)
                W4.append(Signal(signed(2 * inputs + 1), name=f"W{k}_{c}_4"))
                m.d.sync += W4[-1].eq(plus - minus)
            rounded4 = _delay(m, (al1 != 0) | (be1 != 0), 3, f"rounded{k}")
            mant, trunc, pos, neg = _truncate(
                m, W4, f.w_bits, f"f{k}", False, floor=(rounded4, inputs + 2), sum_width=sum_bits(f.w_bits, f),
                sums=lambda v: (sum(Mux(c < -2, 0, c + 2) for c in v), sum(Mux(c > 1, 0, 1 - c) for c in v)))
            m.d.comb += [self.terms.m[k][c].eq(mant[c]) for c in range(3)]
            m.d.comb += [self.terms.pos[k].eq(pos), self.terms.neg[k].eq(neg), self.terms.truncated[k].eq(trunc)]
        m.d.comb += [self.plane_out.eq(_delay(m, pq4, 3, "pq")),
                     self.terms_valid.eq(_delay(m, self.valid, self.latency, "valid"))]
        return m


def _edge_vectors(m, point, patch, w):
    """The row unit's stage-0 vectors: ``dQ_k`` (the point minus vertex k) and ``e_k`` (vertex k+1
    minus vertex k), combinational."""
    dq0 = [Signal(vector_layout(w.diff), name=f"dq{k}_0") for k in range(3)]
    e0 = [Signal(vector_layout(w.diff), name=f"e{k}_0") for k in range(3)]
    for k, vertex in enumerate(_VERTICES):
        for c in _AXES:
            m.d.comb += [dq0[k][c].eq(point[c] - patch[vertex][c]),
                         e0[k][c].eq(patch[_VERTICES[(k + 1) % 3]][c] - patch[vertex][c])]
    return dq0, e0


def _row_chains(platform):
    """The platform for the row unit's w_k bit heaps (:func:`~blockray.rtl.lutdot.dot_product`):
    a target with carry cells whose ``rounded`` products are in the fabric, else None."""
    if getattr(platform, "ccu2c", False) and "rounded" in getattr(platform, "fabric_units", ()):
        return platform
    return None


class LeanRowUnit(ReceiverUnit):
    """The lean array's row unit with w_k exact: a :class:`~blockray.rtl.processor.ReceiverUnit`
    (same ports, latency and bits) whose 18 cross products, with ``--fabric-units rounded`` on a
    target with carry cells, are nine bit heaps w_kc = dQ_a e_b - dQ_b e_a on CCU2C carry chains
    (stage 1 the operands, stage 3 w_k, as the products' registers) instead of 18 MULT18X18D;
    pQ keeps its products (the ``receiver`` key)."""

    def elaborate(self, platform):
        chains = _row_chains(platform)
        if chains is None:
            return super().elaborate(platform)
        m = Module()
        w = Widths(self._bits)
        dq0, e0 = _edge_vectors(m, self.point, self.patch, w)
        w3 = Signal(data.ArrayLayout(vector_layout(w.cross), 3), name="w_3")
        for k in range(3):
            for i, c in enumerate(_AXES):       # (a x b)_c = a_{c+1} b_{c+2} - a_{c+2} b_{c+1}
                a, b = _AXES[(i + 1) % 3], _AXES[(i + 2) % 3]
                m.d.comb += w3[k][c].eq(dot_product(m, [(dq0[k][a], e0[k][b]), (dq0[k][b], e0[k][a], True)],
                                                    w.cross, f"w{k}_{c}_3", chains))
        sums3 = _dot_sums(m, [(dq0[0][c], self.patch.normal[c]) for c in _AXES], w.orient, "pq",
                          product_platform(platform, self._unit))
        m.d.sync += [self.terms.w.eq(w3), self.terms.pq.eq(_combine(sums3, w.orient))]
        m.d.comb += self.terms_valid.eq(_delay(m, self.valid, self.latency, "valid"))
        return m


class LeanExact(wiring.Component):
    """The lean array's shared exact unit: one undecided test every :attr:`interval` cycles,
    recomputed from its tag edge by edge on a third of the products of a full exact pipeline.

    Cycle 0: ``valid``, ``which`` (the test's bit r * S + s, one-hot) and ``terms`` (its tag:
    patch ``address``, end-point ``slot``); the patch memory (``patch_read``) and the end-point
    memory (``points_read``) are read at the tag's addresses. Cycle 1: both reads registered as
    they are. Cycle 2: P_s and Q_r picked from the entry by ``which`` are held with the patch's
    vertices. Cycles 3, 4, 5 (edge k = 0, 1, 2): w_k = (Q - V_k) x (V_{k+1} - V_k) on six
    products, three cycles later s_k = (P - V_k) . w_k on three
    (:func:`~blockray.rtl.processor._dot_sums`). Edge k's sign and zero come out in cycle 9 + k;
    the decision (all s_k >= 0 or all <= 0) is ``blocked`` with ``result_valid`` in cycle
    :attr:`latency` = 12. The planes' test is not recomputed: a cell decides every test
    whose planes do not cross (its ``crossing`` is exact), so every test handed here crosses.
    ``first`` is accepted and ignored (the hand-off's exact-unit ports). All its products answer
    to the fabric-units key ``exact``. Why serial: undecided tests are about one in a thousand
    (docs/processor.md), so a test per cycle bought 48 MULT18X18D the array cannot spare; this
    takes 12 at B <= 17.
    """

    #: cycles between tests (the hand-off feeds no faster: :attr:`ArrayResolve.exact_interval`)
    interval = 3
    latency = 3 + 2 + 3 + 3 + 1

    def __init__(self, bits, rows, cols, address_bits, slots):
        self._bits, self._rows, self._cols = bits, rows, cols
        self._entry = endpoints_layout(bits, rows, cols)
        super().__init__({
            "valid": In(1), "first": In(1),
            "which": In(rows * cols),
            "terms": In(tag_layout(address_bits, slots)),
            "patch_read": In(ReadPort.Signature(addr_width=address_bits, shape=patch_layout(bits))),
            "points_read": In(ReadPort.Signature(addr_width=max(1, (slots - 1).bit_length()), shape=self._entry)),
            "blocked": Out(1), "result_valid": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        B, R, S = self._bits, self._rows, self._cols
        w = Widths(B)
        m.d.comb += [
            self.patch_read.addr.eq(self.terms.address), self.patch_read.en.eq(1),
            self.points_read.addr.eq(self.terms.slot), self.points_read.en.eq(1),
        ]
        # cycle 1: the memories' outputs registered as they are (a block RAM's output is late in
        # its cycle: picking P_s straight from it was the lean 2 x 8's critical path)
        entry = Signal(self._entry, name="entry_read")
        patch = Signal(self.patch_read.data.shape(), name="patch_read_held")
        m.d.sync += [entry.eq(self.points_read.data), patch.eq(self.patch_read.data)]
        # cycle 2: the test's points and patch held for its three edges
        valid2 = _delay(m, self.valid, 2, "valid")
        which2 = _delay(m, self.which, 2, "which")
        p, q = Signal(point_layout(B), name="p_held"), Signal(point_layout(B), name="q_held")
        vertex = [Signal(point_layout(B), name=f"v{k}_held") for k in range(3)]
        with m.If(valid2):
            m.d.sync += [
                p.eq(sum_or(Mux(sum_or(which2[r * S + s] for r in range(R)), entry.shooters[s].as_value(), 0)
                            for s in range(S))),
                q.eq(sum_or(Mux(sum_or(which2[r * S + s] for s in range(S)), entry.receivers[r].as_value(), 0)
                            for r in range(R))),
                *(v.eq(patch[name]) for v, name in zip(vertex, _VERTICES)),
            ]
        phase = [_delay(m, self.valid, 3 + k, f"edge{k}") for k in range(3)]     # cycles 3, 4, 5
        vk = Mux(phase[1], vertex[1].as_value(), Mux(phase[2], vertex[2].as_value(), vertex[0].as_value()))
        vk1 = Mux(phase[1], vertex[2].as_value(), Mux(phase[2], vertex[0].as_value(), vertex[1].as_value()))
        vk, vk1 = point_layout(B)(vk), point_layout(B)(vk1)
        negative, zero = self._edges(m, w, p, q, vk, vk1, product_platform(platform, "exact"))   # cycle 9 + k
        # cycle 11: edge 2's sign beside edges 1's and 0's, registered one and two cycles back
        neg = [_delay(m, negative, 2 - k, f"neg{k}") for k in range(3)]
        nil = [_delay(m, zero, 2 - k, f"zero{k}") for k in range(3)]
        nonneg = ~neg[0] & ~neg[1] & ~neg[2]
        nonpos = (neg[0] | nil[0]) & (neg[1] | nil[1]) & (neg[2] | nil[2])
        m.d.sync += self.blocked.eq(nonneg | nonpos)
        m.d.comb += self.result_valid.eq(_delay(m, self.valid, self.latency, "result"))
        return m

    @staticmethod
    def _edges(m, w, p, q, vk, vk1, platform):
        """Edge k's (s_k < 0, s_k == 0) six cycles after its vertices ``vk``, ``vk1``."""
        dq, e, d = (Signal(vector_layout(w.diff), name=n) for n in ("dq", "e", "d"))
        for c in _AXES:
            m.d.comb += [dq[c].eq(q[c] - vk[c]), e[c].eq(vk1[c] - vk[c]), d[c].eq(p[c] - vk[c])]
        w3 = _cross_product(m, dq, e, w.cross, "w", platform)
        d3 = _delay(m, d, 3, "d")
        sums = _dot_sums(m, [(d3[c], w3[c]) for c in _AXES], w.orient, "s", platform)
        return _sign_and_zero(m, sums, w.orient, "s_6")


class LeanResolve(ArrayResolve):
    """The lean array's in-order hand-off: :class:`~blockray.rtl.filtered.ArrayResolve` with a
    record's tag (:func:`tag_layout`) queued in place of exact terms, and :class:`LeanExact`
    (latency 12, a test every 3 cycles) as the exact unit, which ``exact_unit`` gives (its owner
    wires its read ports)."""

    exact_latency = LeanExact.latency
    exact_interval = LeanExact.interval

    def __init__(self, bits, rows, cols, mark_shape, depth, *, exact_unit, address_bits):
        self._address_bits = address_bits
        super().__init__(bits, rows, cols, mark_shape, depth, exact_unit=exact_unit)

    def _terms_layout(self):
        return tag_layout(self._address_bits, self._depth)

    def _feed(self, m, exact, terms, onehot, valid):
        m.d.comb += [exact.which.eq(onehot), exact.terms.eq(terms), exact.valid.eq(valid), exact.first.eq(1)]


class LeanArray(FilteredArray):
    """R x S lean cells: :class:`~blockray.rtl.filtered.FilteredArray`'s ports and cycle
    contract (a register before the hand-off, :attr:`latency` 13; its exact unit takes 12 cycles, not 4,
    and a test every 3), plus ``address`` (the record's
    patch address, sampled with ``valid``) and ``patch_read`` (a registered read port of the
    patch memory the records come from, for the exact unit). The owner keeps at most
    :attr:`depth` items inside (credits) and must not overwrite a patch whose record is inside.

    The end-point memory has :attr:`depth` entries: every record writes its S + R points at the
    next slot (mod depth) as it enters; with at most depth items inside, a record's entry stays
    until it is delivered. Default filter the lean cell's (:meth:`Cell.format_at <blockray.cell.Cell.format_at>`); default depth
    :meth:`default_depth` (the filtered array's, plus the hand-off register, the exact unit's 12
    cycles and 4: a record with undecided tests every few records costs no cycle; plus
    :attr:`burst_credits`)."""

    #: with ``--fabric-units cell`` on ECP5 the cells' three products and their sum per edge are
    #: one bit heap on CCU2C carry chains (rtl/lutdot.py), not Yosys's LUT multipliers
    carry_chain_cells = True
    #: credits for a burst of undecided tests (a record grazing a shooter patch's rays leaves many):
    #: the records behind keep entering while the exact unit works through it. On cornell, lean
    #: 2 x 8: utilisation 0.830 without, 0.847 with 31 (docs/synthesis.md). 30 and the hand-off
    #: register keep the array's depth at 65: a SyncFIFOBuffered of 65 holds 64 in LUT RAM; at 66
    #: Yosys put the hand-off's queue in block RAM, and its late read became the 2 x 8's critical
    #: path (59.7 MHz routed)
    burst_credits = 30
    #: the cells' ``decided`` of a 2 x 8 reach the hand-off queue's write enable across the part
    #: (its critical path, 71.8 MHz routed at seed 1); a register there costs a cycle of latency
    handoff_stages = 1
    latency = FilteredArray.latency + handoff_stages

    def __init__(self, bits, rows, cols, *, fmt=None, depth=None, mark_shape=unsigned(1),
                 address_bits=DEFAULT_ADDRESS_BITS):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        if isinstance(address_bits, bool) or not isinstance(address_bits, int) or not 1 <= address_bits <= 24:
            raise ParameterError(f"address_bits must be an integer from 1 to 24, not {address_bits!r}",
                                 parameter="address_bits")
        self._address_bits = address_bits
        super().__init__(bits, rows, cols, fmt=Cell("lean", fmt).format_at(bits),
                         depth=depth if depth is not None else self.default_depth(), mark_shape=mark_shape)

    def _extra_members(self):
        return {"address": In(self._address_bits),
                "patch_read": In(ReadPort.Signature(addr_width=self._address_bits, shape=patch_layout(self._bits)))}

    @classmethod
    def default_depth(cls, extra_latency=0):
        return FilteredArray.default_depth(extra_latency) + cls.handoff_stages + LeanExact.latency + 4 + cls.burst_credits

    def _receiver_edge(self, m, r):
        if self._fmt.w_input_bits is None:          # w_k exact, then rounded by the filter
            return self._edge_unit(m, f"receiver_{r}", LeanRowUnit, ReceiverFilter, self.receivers[r])
        unit = m.submodules[f"receiver_{r}"] = LeanReceiver(self._bits, self._fmt)
        m.d.comb += [unit.point.eq(self.receivers[r]), unit.patch.eq(self.patch), unit.valid.eq(self.valid)]
        return unit

    def _resolve(self):
        # made here, so that _queue_terms can wire its read ports to the memories
        self.exact = exact = LeanExact(self._bits, self._rows, self._cols, self._address_bits, self._depth)
        return LeanResolve(self._bits, self._rows, self._cols, self._mark_shape, self._depth,
                           exact_unit=lambda: exact, address_bits=self._address_bits)

    def _queue_terms(self, m, hand, shooters, receivers):
        R, S, depth = self._rows, self._cols, self._depth
        entry = Signal(endpoints_layout(self._bits, R, S))
        m.d.comb += [entry.shooters[s].eq(self.shooters[s]) for s in range(S)]
        m.d.comb += [entry.receivers[r].eq(self.receivers[r]) for r in range(R)]
        m.submodules.endpoints = endpoints = Memory(shape=entry.shape(), depth=depth, init=[])
        write, read = endpoints.write_port(), endpoints.read_port()
        slot = Signal(range(depth), name="slot")
        with m.If(self.valid):
            m.d.sync += slot.eq(Mux(slot == depth - 1, 0, slot + 1))
        m.d.comb += [write.addr.eq(slot), write.data.eq(entry), write.en.eq(self.valid)]
        exact = self.exact
        m.d.comb += [read.addr.eq(exact.points_read.addr), read.en.eq(exact.points_read.en),
                     exact.points_read.data.eq(read.data)]
        m.d.comb += [self.patch_read.addr.eq(exact.patch_read.addr), self.patch_read.en.eq(exact.patch_read.en),
                     exact.patch_read.data.eq(self.patch_read.data)]
        L = self.latency - self.handoff_stages
        m.d.comb += [hand.terms.slot.eq(_delay(m, slot, L, "slot")),
                     hand.terms.address.eq(_delay(m, self.address, L, "address"))]
