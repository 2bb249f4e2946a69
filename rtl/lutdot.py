"""Narrow dot products on ECP5 carry chains: the lean and filtered cells' products in LUTs.

A signed m x n product mapped by Yosys (``booth``, then ABC9 into LUT4s and wide muxes) costs
about 355 LUT4s at 9 x 9. Here the cell's sum of three products, s = a_0 b_0 + a_1 b_1 + a_2 b_2,
is one bit heap (Baugh-Wooley: every partial-product bit a_i b_j, a few complemented, plus one
constant) reduced by ripple adders on ``CCU2C`` carry cells, with the partial products' ANDs
inside the adders' LUTs: one half of a CCU2C (one LUT4 slot) adds two partial-product bits and
the carry, ``u(A, B) + v(C, D) + cin``, where u is any function of its two inputs and v any
function of its two that is 0 at C = D = 0 (the half's carry-generate is its LUT4's entry at
C = D = 0, so u must be what the half generates). About 3 x fewer LUTs than Yosys's multipliers.

    _dot_product(m, pairs, width, name, platform)   the sum of ``a * b`` over ``pairs`` modulo
        2**width, three cycles after the operand expressions (the same registers and latency as
        :func:`~blockray.rtl.processor._product` then a registered sum): stage 1 the operands,
        stage 2 the first adder levels, stage 3 the rest.

``platform.ccu2c``: True instantiates ``CCU2C`` (ECP5); ``"model"`` builds the same cells from
their INIT tables in Amaranth logic (``ccu2c_sim.vh``'s semantics), so the Amaranth simulator
checks the very tables and wiring the ECP5 netlist gets. Without the flag: ``*`` between
registers, as ``_product``.
"""

from amaranth.hdl import Cat, Const, Instance, Module, Signal, signed

__all__ = ["dot_product", "bit_heap", "OWN_REGISTER"]

#: the attribute of registers Yosys must not merge with identical ones (synth/yosys.py
#: ``OWN_REGISTERS`` gives their flip-flops ``keep``)
OWN_REGISTER = "blockray_own"


# a term of the heap: ("and", a, b), ("nand", a, b), ("wire", x), ("one",)
def _eval(term, x, y):
    kind = term[0]
    if kind == "and":
        return x & y
    if kind == "nand":
        return 1 - (x & y)
    if kind == "wire":
        return x
    return 1                      # one


def _ends(term):
    """The one or two signals a term reads (constants for the unused LUT inputs)."""
    kind = term[0]
    if kind in ("and", "nand"):
        return term[1], term[2]
    if kind == "wire":
        return term[1], Const(0, 1)
    return Const(0, 1), Const(0, 1)


def _v_ok(term):
    """A term may sit on the C, D side: 0 when both inputs are 0."""
    return term is None or term[0] in ("and", "wire")


def _half(u, v):
    """INIT of one CCU2C half adding terms ``u`` (A, B) and ``v`` (C, D): index {D, C, B, A}."""
    init = 0
    for idx in range(16):
        a, b, c, d = idx & 1, idx >> 1 & 1, idx >> 2 & 1, idx >> 3 & 1
        bit = (_eval(u, a, b) if u else 0) ^ (_eval(v, c, d) if v else 0)
        init |= bit << idx
    # the carry-generate is INIT[3:0] over (A, B): u itself, because v(0, 0) = 0
    assert _v_ok(v)
    return init


def _ccu2c(m, name, halves, cin, mode):
    """One CCU2C: ``halves`` = two (init, (A, B, C, D)); returns (S0, S1, COUT)."""
    s0, s1, cout = Signal(name=f"{name}_s0"), Signal(name=f"{name}_s1"), Signal(name=f"{name}_co")
    (init0, p0), (init1, p1) = halves
    if mode == "model":
        c = cin
        outs = []
        for init, pins in ((init0, p0), (init1, p1)):
            lut = Const(init, 16).bit_select(Cat(*pins), 1)
            gen = Const(init & 0xF, 4).bit_select(Cat(*pins[:2]), 1)
            outs.append(lut ^ c)
            nxt = Signal(name=f"{name}_c{len(outs)}")
            m.d.comb += nxt.eq((~lut & gen) | (lut & c))
            c = nxt
        m.d.comb += [s0.eq(outs[0]), s1.eq(outs[1]), cout.eq(c)]
    else:
        ports = {"i_CIN": cin, "o_S0": s0, "o_S1": s1, "o_COUT": cout}
        for half, pins in (("0", p0), ("1", p1)):
            for pin, value in zip("ABCD", pins):
                ports[f"i_{pin}{half}"] = value
        m.submodules[name] = Instance("CCU2C", p_INIT0=Const(init0, 16), p_INIT1=Const(init1, 16),
                                      p_INJECT1_0="NO", p_INJECT1_1="NO", **ports)
    return s0, s1, cout


def _add_rows(m, x, y, width, name, mode):
    """The chain x + y of two rows ({weight: term}) modulo 2**width: a row of wires."""
    lo = min(min(x), min(y))
    top = min(width, max(max(x), max(y)) + 2)       # the carry out's weight included
    halves = []
    for w in range(lo, top):
        u, v = x.get(w), y.get(w)
        if not _v_ok(v):
            u, v = v, u
        pins = _ends(u) if u else (Const(0, 1), Const(0, 1))
        pins = pins + (_ends(v) if v else (Const(0, 1), Const(0, 1)))
        halves.append((_half(u, v), pins))
    if len(halves) % 2:
        halves.append((0, (Const(0, 1),) * 4))
    out, carry = {}, Const(0, 1)
    for i in range(0, len(halves), 2):
        s0, s1, carry = _ccu2c(m, f"{name}_{i // 2}", halves[i:i + 2], carry, mode)
        for w, s in ((lo + i, s0), (lo + i + 1, s1)):
            if w < top:
                out[w] = ("wire", s)
    return out


def _conflict(x, y):
    """Two rows that cannot share a chain: some weight with two terms that both need the A, B side."""
    return any(not _v_ok(t) and not _v_ok(y.get(w)) for w, t in x.items())


def _register(m, row, name):
    out = {}
    for w, t in row.items():
        r = Signal(name=f"{name}_w{w}")
        a, b = _ends(t)
        m.d.sync += r.eq(Const(_eval(t, 0, 0), 1) if t[0] == "one" else
                         (a & b) if t[0] == "and" else ~(a & b) if t[0] == "nand" else a)
        out[w] = ("wire", r)
    return out


def bit_heap(pairs, width):
    """Baugh-Wooley rows of sum(+-a * b) modulo 2**width (a, b signed values; a pair (a, b, True)
    is subtracted): a list of rows {weight: term}, the last the constant's (if not 0)."""
    rows, constant = [], 0
    for a, b, *minus in pairs:
        na, nb = len(a), len(b)
        assert a.shape().signed and b.shape().signed and na >= 2 and nb >= 2
        for i in range(na):
            row = {}
            for j in range(nb):
                w = i + j
                if w >= width:
                    continue
                # a partial-product bit of weight -2^w: its complement, and -2^w in the constant
                negative = ((i == na - 1) != (j == nb - 1)) != bool(minus and minus[0])
                row[w] = ("nand" if negative else "and", a[i], b[j])
                if negative:
                    constant -= 1 << w          # -x 2^w = (1 - x) 2^w - 2^w
            if row:
                rows.append(row)
    constant %= 1 << width
    if constant:
        rows.append({w: ("one",) for w in range(width) if constant >> w & 1})
    return rows


def _reduce_level(m, rows, width, name, mode):
    """One level: rows paired (in order of their lowest weight, without conflicts) into chains."""
    rows = sorted(rows, key=lambda r: (min(r), max(r)))
    out, left = [], list(rows)
    n = 0
    while left:
        x = left.pop(0)
        for i, y in enumerate(left):
            if not _conflict(x, y):
                left.pop(i)
                out.append(_add_rows(m, x, y, width, f"{name}_{n}", mode))
                n += 1
                break
        else:
            out.append(x)
    return out


def dot_product(m, pairs, width, name, platform=None, first_stage_levels=None):
    """sum(a * b for a, b in pairs) modulo 2**width as a ``signed(width)`` register, three cycles
    after the operand expressions (see the module doc); a pair ``(a, b, True)`` is subtracted."""
    mode = getattr(platform, "ccu2c", False)
    # each heap its own operand registers: the cells of a row (column) take the same broadcast
    # operands, and Yosys would merge their registers into one far from most of them
    attrs = {OWN_REGISTER: 1} if mode else {}
    regs = []
    for i, (a, b, *minus) in enumerate(pairs):
        ra = Signal(a.shape(), name=f"{name}_a{i}", attrs=attrs)
        rb = Signal(b.shape(), name=f"{name}_b{i}", attrs=attrs)
        m.d.sync += [ra.eq(a), rb.eq(b)]
        regs.append((ra, rb, *minus))
    s = Signal(signed(width), name=name)
    if not mode:
        total = 0
        for i, (ra, rb, *minus) in enumerate(regs):
            p = Signal(signed(width), name=f"{name}_p{i}")
            m.d.sync += p.eq(ra * rb)
            total = total - p if minus and minus[0] else total + p
        m.d.sync += s.eq(total)
        return s
    mode = "model" if mode == "model" else "ecp5"
    rows = bit_heap(regs, width)
    levels = 0
    while len(rows) > 1 and levels < 64:
        levels += 1
        rows = _reduce_level(m, rows, width, f"{name}_l{levels}", mode)
        if levels == (first_stage_levels or 3):
            rows = [_register(m, r, f"{name}_r{k}") for k, r in enumerate(rows)]
    if levels < (first_stage_levels or 3):           # (few rows: the stage-2 register at the end)
        rows = [_register(m, r, f"{name}_r{k}") for k, r in enumerate(rows)]
    assert len(rows) == 1, "rows left that conflict"
    (row,) = rows
    bits = [row[w][1] if w in row and row[w][0] == "wire" else Const(0, 1) for w in range(width)]
    assert all(row[w][0] == "wire" for w in row)
    m.d.sync += s.eq(Cat(*bits))
    return s
