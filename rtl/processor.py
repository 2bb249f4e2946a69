"""The pipelined exact segment-triangle intersection processor and its shared-term units.

The board is an R x S array: a patch is broadcast to every cell each cycle, column ``s`` holds a
shooter point P_s, row ``r`` a receiver point Q_r. The predicate of :mod:`blockray.exact` is
split the same way as there:

``ShooterUnit``   (one per column)  d_k = P - V_k  (k = 0, 1, 2),  pP = n . (P - V0)
``ReceiverUnit``  (one per row)     w_k = (Q - V_k) x (V_{k+1} - V_k),  pQ = n . (Q - V0)
``Processor``     (one per cell)    s_k = d_k . w_k;  blocked = sign(pP) sign(pQ) < 0 and
                                    (all s_k >= 0 or all s_k <= 0)

Products per cell: 9 of (B+1) x (2B+2) bits. Per column unit: 3 of (B+1) x (2B+2). Per row
unit: 18 of (B+1) x (B+1) and 3 of (B+1) x (2B+2). All arithmetic is ring arithmetic: products
and sums are kept modulo 2**(3B+2) (the orient width), which is exact because every final value
fits (see :class:`blockray.params.Widths`).

Timing rule of the array (:class:`ArrayTiming`): both units have the same latency, so the
outputs of a column unit and a row unit fed on the same cycle meet at the processor on the same
cycle. Every multiplication is :func:`_product`, ``reg(reg(a) * reg(b))``: registered operands,
the product straight into a register (products wider than one 18 x 18 DSP are split into
DSP-sized pieces, each registered, and the pieces are added in the following stages), so no
stage has a DSP and an adder in series. With the ECP5 target (``platform.mult18x18d``, see
:mod:`blockray.synth.target`) both registers are the DSP's own pipeline registers, except in the
units named in ``platform.fabric_units`` (their products stay generic: LUT multipliers).

``Intersector`` is the 1 x 1 array behind a stream interface, the unit tested against the model.
"""

from amaranth.hdl import ClockSignal, Const, Instance, Module, Mux, ResetSignal, Signal, Value, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from ..params import Widths, check_bits
from ..records import patch_layout, point_layout, vector_layout
from .platform import product_platform

__all__ = [
    "shooter_terms_layout", "receiver_terms_layout", "query_layout", "result_layout",
    "ShooterUnit", "ReceiverUnit", "Processor", "ArrayTiming", "Intersector", "TAG_BITS",
]

TAG_BITS = 16


# -- records ----------------------------------------------------------------------------------

def shooter_terms_layout(bits):
    """Column-unit output: d (three signed B+1 vectors d_k = P - V_k) and pP (signed 3B+2)."""
    w = Widths(bits)
    return data.StructLayout({
        "d": data.ArrayLayout(vector_layout(w.diff), 3),
        "pp": signed(w.orient),
    })


def receiver_terms_layout(bits):
    """Row-unit output: w (three signed 2B+2 vectors w_k) and pQ (signed 3B+2)."""
    w = Widths(bits)
    return data.StructLayout({
        "w": data.ArrayLayout(vector_layout(w.cross), 3),
        "pq": signed(w.orient),
    })


def query_layout(bits):
    """:class:`Intersector` input payload: one segment (shooter -> receiver), one patch, a tag."""
    return data.StructLayout({
        "shooter": point_layout(bits),
        "receiver": point_layout(bits),
        "patch": patch_layout(bits),
        "tag": unsigned(TAG_BITS),
    })


def result_layout():
    """:class:`Intersector` output payload: the blocked bit and the tag of its test."""
    return data.StructLayout({"blocked": unsigned(1), "tag": unsigned(TAG_BITS)})


# -- helpers ----------------------------------------------------------------------------------

def _delay(m, value, cycles, name):
    """``value`` delayed by ``cycles`` registers (a side-band chain); returns the last stage."""
    return _delay_through(m, value, [Signal.like(value, name=f"{name}_{n + 1}") for n in range(cycles)])


#: Yosys's attribute for a memory to map to block RAM (EBR on ECP5), not LUT RAM: a wide memory
#: in LUT RAM crowds the slices (and its shared addresses the routing). Not for a memory read
#: straight into logic: an EBR's clock-to-out is long (the hand-off queue in EBR halved the 1 x 2
#: filtered array's placer estimate, 81 -> 49 MHz)
BLOCK_RAM = {"ram_style": "block"}


def _delay_memory(m, value, cycles, name):
    """``value`` delayed by ``cycles`` (at least 2) through a ``cycles``-deep memory: written
    every cycle at a rotating address, read one address ahead with a registered read. The same
    outputs as :func:`_delay` once ``cycles`` values have been written (before that, the memory's
    zeros, as the chain's reset values; a reset does not clear the memory, so use it only for
    values read with a valid beside them); for wide delays, where a chain costs ``cycles`` flip-flops
    per bit and a memory one (block RAM: :data:`BLOCK_RAM`)."""
    if cycles < 2:
        raise ValueError(f"a memory delay needs at least 2 cycles, not {cycles}")
    memory = m.submodules[name] = Memory(shape=value.shape(), depth=cycles, init=[], attrs=BLOCK_RAM)
    write, read = memory.write_port(), memory.read_port()
    address = Signal(range(cycles), name=f"{name}_address")
    ahead = Signal.like(address, name=f"{name}_ahead")
    m.d.comb += [ahead.eq(Mux(address == cycles - 1, 0, address + 1)),
                 write.addr.eq(address), write.data.eq(value), write.en.eq(1), read.addr.eq(ahead)]
    m.d.sync += address.eq(ahead)
    return read.data


def _crossing(pp, pq):
    """The segment crosses the patch's plane: pP and pQ of opposite, non-zero signs."""
    return ((pp > 0) & (pq < 0)) | ((pp < 0) & (pq > 0))


def _credits(m, i, o, depth):
    """Backpressure by credits for a pipeline between streams ``i`` and ``o`` that never stalls:
    a registered count of items accepted but not delivered, ``i.ready = count < depth``.
    Returns the accept strobe."""
    accept = i.valid & i.ready
    count = Signal(range(depth + 1), name="count")
    m.d.comb += i.ready.eq(count < depth)
    m.d.sync += count.eq(count + accept - (o.valid & o.ready))
    return accept


def _delay_through(m, value, stages):
    """``value`` through the registers ``stages`` in turn (a chain made by its owner, which can
    then name every stage); returns the last."""
    for reg in stages:
        m.d.sync += reg.eq(value)
        value = reg
    return value


_AXES = ("x", "y", "z")
_VERTICES = ("v0", "v1", "v2")

#: operand width of one ECP5 MULT18X18D (signed 18 x 18)
DSP_OPERAND_BITS = 18
_CHUNK = DSP_OPERAND_BITS - 1    # unsigned low chunks of a split operand (zero-extended to 18)


def _chunks(value):
    """Split a signed operand wider than one DSP input into (chunk, shift) pieces:
    ``value = sum(chunk << shift)``, low chunks unsigned 17 bits, the top chunk signed.
    An operand of at most 18 bits is one piece."""
    if len(value) <= DSP_OPERAND_BITS:
        return [(value, 0)]
    pieces, shift = [], 0
    while len(value) - shift > DSP_OPERAND_BITS:
        pieces.append((value[shift:shift + _CHUNK], shift))          # unsigned slice
        shift += _CHUNK
    pieces.append((value[shift:].as_signed(), shift))
    return pieces


#: the MULT18X18D configuration of :func:`_product` on ECP5: operand A, operand B and the
#: product registered on CLK0 (timing class MULT18X18D_REGS_ALL in nextpnr), clock enable CE0,
#: synchronous reset RST0; no pipeline register, no C input, no cascade, no clock divider.
#: ``synth/ecp5_mult18x18d_sim.v`` models exactly this set and stops on any other value.
MULT18X18D_PARAMS = {
    "REG_INPUTA_CLK": "CLK0", "REG_INPUTA_CE": "CE0", "REG_INPUTA_RST": "RST0",
    "REG_INPUTB_CLK": "CLK0", "REG_INPUTB_CE": "CE0", "REG_INPUTB_RST": "RST0",
    "REG_INPUTC_CLK": "NONE", "REG_INPUTC_CE": "CE0", "REG_INPUTC_RST": "RST0",
    "REG_PIPELINE_CLK": "NONE", "REG_PIPELINE_CE": "CE0", "REG_PIPELINE_RST": "RST0",
    "REG_OUTPUT_CLK": "CLK0", "REG_OUTPUT_CE": "CE0", "REG_OUTPUT_RST": "RST0",
    "CLK0_DIV": "ENABLED", "CLK1_DIV": "ENABLED", "CLK2_DIV": "ENABLED", "CLK3_DIV": "ENABLED",
    "HIGHSPEED_CLK": "NONE", "GSR": "DISABLED", "CAS_MATCH_REG": "FALSE",
    "SOURCEB_MODE": "B_SHIFT", "MULT_BYPASS": "DISABLED", "RESETMODE": "SYNC",
}


def _fits_dsp(value):
    """An operand one signed 18-bit DSP input holds (signed <= 18 bits, unsigned <= 17)."""
    shape = value.shape()
    return len(value) <= (DSP_OPERAND_BITS if shape.signed else DSP_OPERAND_BITS - 1)


def _product(m, a, b, width, name, platform=None):
    """``reg(reg(a) * reg(b))`` modulo 2**``width``: the product of the operand expressions
    ``a`` and ``b`` (signed or unsigned values) two cycles later, as a ``signed(width)`` value.

    The one multiplication of every pipeline here. Generic (``platform`` None or without
    ``mult18x18d``): two operand registers and a product register in the fabric (Yosys may
    merge operand registers that hold the same value). ECP5 (``platform.mult18x18d``, when both
    operands fit a DSP input and ``width <= 36``): one ``MULT18X18D`` with its input and output
    registers on (:data:`MULT18X18D_PARAMS`), operands sign- or zero-extended to 18 bits,
    ``SIGNEDA = SIGNEDB = 1``, the product the low ``width`` bits of P. Both reset to 0 on the
    sync domain's reset and compute the same bits every cycle.
    """
    a, b = Value.cast(a), Value.cast(b)
    if getattr(platform, "mult18x18d", False) and _fits_dsp(a) and _fits_dsp(b) and width <= 36:
        return _mult18x18d(m, a, b, width, name)
    ra = Signal(a.shape(), name=f"{name}_a")
    rb = Signal(b.shape(), name=f"{name}_b")
    product = Signal(signed(width), name=name)
    m.d.sync += [ra.eq(a), rb.eq(b), product.eq(ra * rb)]       # wraps: ring arithmetic
    return product


def _mult18x18d(m, a, b, width, name):
    """:func:`_product` on one registered ECP5 MULT18X18D (inputs and output on CLK0)."""
    a18 = Signal(signed(DSP_OPERAND_BITS), name=f"{name}_a18")
    b18 = Signal(signed(DSP_OPERAND_BITS), name=f"{name}_b18")
    p36 = Signal(signed(2 * DSP_OPERAND_BITS), name=f"{name}_p36")
    m.d.comb += [a18.eq(a), b18.eq(b)]                  # sign- or zero-extension by shape
    zero = Const(0, 1)
    ports = {"i_SIGNEDA": Const(1, 1), "i_SIGNEDB": Const(1, 1),
             "i_SOURCEA": zero, "i_SOURCEB": zero,
             "i_CLK0": ClockSignal("sync"), "i_CE0": Const(1, 1), "i_RST0": ResetSignal("sync")}
    # CLK1..3, CE1..3, RST1..3 and the shift inputs SRIA/SRIB stay unconnected (as in Yosys's
    # own dsp_map.v): nextpnr ties unconnected DSP inputs off inside the tile, whereas a
    # constant on a clock input fails to route ("Failed to find a route ... $PACKER_GND_NET")
    for i in range(DSP_OPERAND_BITS):
        ports.update({f"i_A{i}": a18[i], f"i_B{i}": b18[i], f"i_C{i}": zero})
    for i in range(2 * DSP_OPERAND_BITS):
        ports[f"o_P{i}"] = p36[i]
    m.submodules[f"{name}_dsp"] = Instance(
        "MULT18X18D", **{f"p_{k}": v for k, v in MULT18X18D_PARAMS.items()}, **ports)
    product = Signal(signed(width), name=name)
    m.d.comb += product.eq(p36)                         # the low ``width`` bits
    return product


def _partial_products(m, pairs, width, name, platform=None):
    """The registered partial products of ``sum(a * b for a, b in pairs)`` modulo 2**width,
    two cycles after the operand expressions ``a``, ``b`` (:func:`_product`).

    Each product is split along ``b`` (:func:`_chunks`) so that every multiplication fits one
    DSP and its output goes straight into registers (no adder between a DSP and its register):
    this stage is DSP-only. Returns ``{shift: [products]}``; a partial of shift ``k`` is kept
    modulo 2**(width - k), which is all the final sum modulo 2**width needs.
    """
    groups = {}
    for i, (a, b) in enumerate(pairs):
        for chunk, shift in _chunks(b):
            product = _product(m, a, chunk, min(len(a) + len(chunk) + 1, width - shift),
                               f"{name}_{i}_p{shift}", platform)
            groups.setdefault(shift, []).append(product)
    return groups


def _dot_sums(m, pairs, width, name, platform=None):
    """Three pipeline stages of ``sum(a * b for a, b in pairs)`` modulo 2**width from the operand
    expressions: the partial products (:func:`_partial_products`, two stages: operands, then
    products), then per shift their sum (one stage, at most two chained adders). Returns
    ``{shift: register}``; :func:`_combine` finishes the sum."""
    sums = {}
    for shift, terms in _partial_products(m, pairs, width, name, platform).items():
        reg = Signal(signed(width - shift), name=f"{name}_sum_p{shift}")
        m.d.sync += reg.eq(sum(terms))
        sums[shift] = reg
    return sums


def _combine(groups, width):
    """``sum(term << shift)`` of ``{shift: term}`` modulo 2**``width`` (a value; callers truncate
    it to ``width``). Each addend is cut to ``width`` bits first: the same low bits, but no
    sign-extended adder wider than 64 bits, which Verilator evaluates word by word."""
    total = 0
    for shift, term in sorted(groups.items()):
        total = total + term[:width - shift].shift_left(shift)
    return total


def _cross_product(m, a, b, width, name, platform=None):
    """``a x b`` (vectors of :func:`~blockray.records.vector_layout`) modulo 2**``width`` a
    component, three cycles after the operand expressions: (a x b)_c = a_{c+1} b_{c+2} -
    a_{c+2} b_{c+1}, six :func:`_product` then their differences registered."""
    out = Signal(vector_layout(width), name=f"{name}_3")
    for i, c in enumerate(_AXES):
        x, y = _AXES[(i + 1) % 3], _AXES[(i + 2) % 3]
        plus = _product(m, a[x], b[y], width, f"{name}_{c}_plus_2", platform)
        minus = _product(m, a[y], b[x], width, f"{name}_{c}_minus_2", platform)
        m.d.sync += out[c].eq(plus - minus)
    return out


def _sign_and_zero(m, groups, width, name):
    """(s < 0, s == 0) of ``s = sum(term << shift)`` modulo 2**width, ``groups`` = ``{shift:
    term}`` (:func:`_dot_sums`). The sign is the top bit of the joined sum (one carry chain).
    With two pieces ``lo + (hi << k)``, s == 0 iff the low k bits of lo are 0 and
    ``x + y == 0`` modulo 2**(width - k) for x = lo >> k, y = hi, which is tested without a
    carry chain: ``x + y == 0  <=>  x ^ y == (x | y) << 1`` (modulo 2**(width - k)); so the zero
    test runs in parallel with the adder instead of after it."""
    total = Signal(signed(width), name=name)
    m.d.comb += total.eq(_combine(groups, width))
    negative = total[-1]
    if len(groups) != 2:
        return negative, total == 0
    (_, lo), (shift, hi) = sorted(groups.items())
    n = width - shift
    x = Signal(n, name=f"{name}_x")
    y = Signal(n, name=f"{name}_y")
    m.d.comb += [x.eq(lo[shift:width]), y.eq(hi)]
    zero = (lo[:shift] == 0) & ((x ^ y) == ((x | y) << 1)[:n])
    return negative, zero


# -- units ------------------------------------------------------------------------------------

class _TermsUnit(wiring.Component):
    """The ports every array-edge unit shares: a held end point and the broadcast patch in,
    that point's terms out after :attr:`latency` cycles (subclasses set ``terms_layout``)."""

    latency = 4

    def __init__(self, bits, *, unit=None):
        self._bits = check_bits(bits)
        self._unit = unit or self.unit        # the fabric_units key of its products (rtl/platform.py)
        super().__init__({
            "point": In(point_layout(bits)),
            "patch": In(patch_layout(bits)),
            "valid": In(1),
            "terms": Out(self.terms_layout(bits)),
            "terms_valid": Out(1),
        })

    @property
    def bits(self):
        return self._bits


class ShooterUnit(_TermsUnit):
    """Column unit: the terms of a block ray that depend on the shooter point P and the patch.

    Stage 1 registers d_k = P - V_k and the multiplier inputs (P - V0)_c and n_c, stage 2 the
    partial products of n_c (P - V0)_c (DSP outputs; at B >= 9 each product is two
    18-bit-operand pieces; stages 1 and 2 of a product are :func:`_product`), stage 3 their sums
    per piece, stage 4 pP (one adder joining the pieces) and d_k.

    Latency :attr:`latency` = 4 cycles, throughput one patch per cycle (fully pipelined, no
    stalls). ``valid`` travels through a register chain of the same length as ``terms``.

    Ports: ``point`` (:func:`~blockray.records.point_layout`), ``patch``
    (:func:`~blockray.records.patch_layout`), ``valid`` in; ``terms``
    (:func:`shooter_terms_layout`), ``terms_valid`` out.
    """

    terms_layout = staticmethod(shooter_terms_layout)
    unit = "shooter"

    def elaborate(self, platform):
        m = Module()
        w = Widths(self._bits)

        d0 = [Signal(vector_layout(w.diff), name=f"d{k}_0") for k in range(3)]
        for k, vertex in enumerate(_VERTICES):
            for c in _AXES:
                m.d.comb += d0[k][c].eq(self.point[c] - self.patch[vertex][c])

        platform = product_platform(platform, self._unit)
        sums3 = _dot_sums(m, [(d0[0][c], self.patch.normal[c]) for c in _AXES], w.orient, "pp", platform)
        d3 = [_delay(m, d0[k], 3, f"d{k}") for k in range(3)]

        m.d.sync += self.terms.pp.eq(_combine(sums3, w.orient))
        for k in range(3):
            m.d.sync += self.terms.d[k].eq(d3[k])
        m.d.comb += self.terms_valid.eq(_delay(m, self.valid, self.latency, "valid"))
        return m


class ReceiverUnit(_TermsUnit):
    """Row unit: the terms of a block ray that depend on the receiver point Q and the patch.

    Stage 1 registers the multiplier inputs (components of dQ_k = Q - V_k, e_k = V_{k+1} - V_k
    and n), stage 2 the 18 cross-product terms and the partial products of pQ (DSP outputs;
    stages 1 and 2 of a product are :func:`_product`), stage 3 the differences
    w_k = dQ_k x e_k and the per-piece sums of pQ, stage 4 pQ (joining the pieces) and w_k.

    Latency :attr:`latency` = 4 cycles (equal to :attr:`ShooterUnit.latency`), throughput one
    patch per cycle. ``valid`` travels through a register chain of the same length as ``terms``.

    Ports: ``point``, ``patch``, ``valid`` in; ``terms`` (:func:`receiver_terms_layout`),
    ``terms_valid`` out.
    """

    terms_layout = staticmethod(receiver_terms_layout)
    unit = "receiver"

    def elaborate(self, platform):
        m = Module()
        w = Widths(self._bits)

        dq0 = [Signal(vector_layout(w.diff), name=f"dq{k}_0") for k in range(3)]
        e0 = [Signal(vector_layout(w.diff), name=f"e{k}_0") for k in range(3)]
        for k, vertex in enumerate(_VERTICES):
            following = _VERTICES[(k + 1) % 3]
            for c in _AXES:
                m.d.comb += [
                    dq0[k][c].eq(self.point[c] - self.patch[vertex][c]),
                    e0[k][c].eq(self.patch[following][c] - self.patch[vertex][c]),
                ]

        platform = product_platform(platform, self._unit)
        w3 = [_cross_product(m, dq0[k], e0[k], w.cross, f"w{k}", platform) for k in range(3)]   # |w| <= 2 L**2
        sums3 = _dot_sums(m, [(dq0[0][c], self.patch.normal[c]) for c in _AXES], w.orient, "pq", platform)
        m.d.sync += [self.terms.w[k].eq(w3[k]) for k in range(3)]
        m.d.sync += self.terms.pq.eq(_combine(sums3, w.orient))
        m.d.comb += self.terms_valid.eq(_delay(m, self.valid, self.latency, "valid"))
        return m


class Processor(wiring.Component):
    """Array cell: the decision for one (shooter, receiver, patch) test per cycle.

    Stage 1 registers d_k and w_k (multiplier inputs) and the plane-crossing bit
    sign(pP) * sign(pQ) < 0, stage 2 the partial products of the nine (d_k)_c (w_k)_c modulo
    2**(3B+2) (DSP outputs; two pieces each at B >= 9), stage 3 their sums per k and piece,
    stage 4 s_k (one adder joining the pieces) and the decision.

    Latency :attr:`latency` = 4 cycles from ``valid`` (with its terms) to ``result_valid``,
    throughput one test per cycle.

    Outputs, registered, meaningful when ``result_valid``:

    ``blocked``  the test's own result.
    ``hit``      the OR of ``blocked`` over a block of tests: a valid result updates it to
                 ``blocked | (hit & ~first)``, where ``first`` is the side-band bit given with
                 the block's first test (it travels with the test, so it is the accumulator's
                 clear, aligned with the data; back-to-back blocks need no bubble). After a
                 block's last result, ``hit`` holds the block's OR until the next valid result.

    Inputs ``shooter`` (:func:`shooter_terms_layout`), ``receiver``
    (:func:`receiver_terms_layout`), ``valid``, ``first``.

    ``unit``: the name its products answer to in ``platform.fabric_units`` (``"cell"``; the
    filtered array's shared exact unit is ``"exact"``, so that its products can stay in DSPs
    while the cells' go to LUTs).
    """

    latency = 4

    def __init__(self, bits, *, unit="cell"):
        self._bits = check_bits(bits)
        self._unit = unit
        super().__init__({
            "shooter": In(shooter_terms_layout(bits)),
            "receiver": In(receiver_terms_layout(bits)),
            "valid": In(1),
            "first": In(1),
            "blocked": Out(1),
            "hit": Out(1),
            "result_valid": Out(1),
        })

    @property
    def bits(self):
        return self._bits

    def elaborate(self, platform):
        m = Module()
        w = Widths(self._bits)

        crossing1 = Signal(name="crossing_1")
        pp, pq = self.shooter.pp, self.receiver.pq
        m.d.sync += crossing1.eq(_crossing(pp, pq))

        platform = product_platform(platform, self._unit)
        # stage 1: the operands (d_k)_c and the pieces of (w_k)_c registered; stage 2: their
        # partial products (each straight from a DSP into registers, :func:`_product`);
        # stage 3: per shift, their sum over the three axes
        sums3 = [_dot_sums(m, [(self.shooter.d[k][c], self.receiver.w[k][c]) for c in _AXES],
                           w.orient, f"s{k}", platform) for k in range(3)]
        crossing3 = _delay(m, crossing1, 2, "crossing")

        # stage 4: sign and zero of s_k = the shifted sums joined (one adder at B >= 9; the
        # zero test runs beside the adder's carry chain, not after it), then the decision
        negative, zero = [], []
        for k in range(3):
            neg, nil = _sign_and_zero(m, sums3[k], w.orient, f"s{k}_4")
            negative.append(neg)
            zero.append(nil)
        nonneg = ~negative[0] & ~negative[1] & ~negative[2]
        nonpos = (negative[0] | zero[0]) & (negative[1] | zero[1]) & (negative[2] | zero[2])
        blocked = crossing3 & (nonneg | nonpos)
        valid3 = _delay(m, self.valid, self.latency - 1, "valid")
        first3 = _delay(m, self.first, self.latency - 1, "first")
        m.d.sync += [
            self.blocked.eq(blocked),
            self.result_valid.eq(valid3),
        ]
        with m.If(valid3):
            m.d.sync += self.hit.eq(blocked | (self.hit & ~first3))
        return m


class ArrayTiming:
    """Latencies of the array datapath for ``bits``.

    Rule: the shooter (column) and receiver (row) units have equal latency ``unit``, so a
    patch, P and Q presented on the same cycle produce terms that reach the processor on the
    same cycle; the processor adds ``processor`` cycles. ``latency`` = unit + processor is the
    cycle count from a test entering the units to its ``result_valid``.
    """

    def __init__(self, bits):
        check_bits(bits)
        if ShooterUnit.latency != ReceiverUnit.latency:    # pragma: no cover - design invariant
            raise AssertionError("shooter and receiver unit latencies differ")
        self.unit = ShooterUnit.latency
        self.processor = Processor.latency
        self.latency = self.unit + self.processor


class Intersector(wiring.Component):
    """The 1 x 1 array (one shooter unit, one receiver unit, one processor) with stream ports.

    ``i``: stream of :func:`query_layout` (shooter point, receiver point, patch, tag).
    ``o``: stream of :func:`result_layout` (blocked, tag), in input order.

    The datapath never stalls. Backpressure uses credits: an output FIFO of
    :attr:`fifo_depth` entries and a registered count of accepted but not yet delivered
    tests; ``i.ready`` is ``count < fifo_depth``, so results in flight always have a FIFO slot,
    and ``i.ready`` depends on registers only (no path from ``o.ready`` or ``i.valid``).
    ``o.valid`` comes from the FIFO's output register.

    Latency :attr:`latency` = 10 cycles (array datapath 8, FIFO write and output register 2): a
    test presented and accepted in cycle c is on ``o`` (valid) in cycle c + 9 when the FIFO is
    empty. Throughput one test per cycle while ``o.ready`` stays high (the FIFO depth covers
    the credit loop).
    """

    def __init__(self, bits):
        self._bits = check_bits(bits)
        self._timing = ArrayTiming(bits)
        super().__init__({
            "i": In(stream.Signature(query_layout(bits))),
            "o": Out(stream.Signature(result_layout())),
        })

    @property
    def bits(self):
        return self._bits

    @property
    def timing(self):
        return self._timing

    @property
    def latency(self):
        return self._timing.latency + 2            # + FIFO write and its output register

    @property
    def fifo_depth(self):
        return self.latency + 1                    # a test holds a credit for latency cycles

    def elaborate(self, platform):
        m = Module()
        m.submodules.shooter = shooter = ShooterUnit(self._bits)
        m.submodules.receiver = receiver = ReceiverUnit(self._bits)
        m.submodules.processor = processor = Processor(self._bits)
        m.submodules.fifo = fifo = SyncFIFOBuffered(width=result_layout().size, depth=self.fifo_depth)

        accept = _credits(m, self.i, self.o, self.fifo_depth)

        payload = self.i.payload
        m.d.comb += [
            shooter.point.eq(payload.shooter),
            shooter.patch.eq(payload.patch),
            shooter.valid.eq(accept),
            receiver.point.eq(payload.receiver),
            receiver.patch.eq(payload.patch),
            receiver.valid.eq(accept),
            processor.shooter.eq(shooter.terms),
            processor.receiver.eq(receiver.terms),
            processor.valid.eq(shooter.terms_valid),
            processor.first.eq(1),
        ]
        tag = _delay(m, payload.tag, self._timing.latency, "tag")

        result = Signal(result_layout())
        m.d.comb += [
            result.blocked.eq(processor.blocked),
            result.tag.eq(tag),
            fifo.w_data.eq(result),
            fifo.w_en.eq(processor.result_valid),
            self.o.payload.eq(fifo.r_data),
            self.o.valid.eq(fifo.r_rdy),
            fifo.r_en.eq(self.o.ready),
        ]
        return m
