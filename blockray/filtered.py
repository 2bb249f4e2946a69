"""The certified edge filter: the signs of s_k = (P - V_k) . w_k from a few significant bits.

The exact predicate (:mod:`blockray.exact`) needs s_k to 3B + 2 bits, i.e. per cell nine
(B+1) x (2B+2) products. The filter truncates both operands of each dot product to a few
significant bits with one exponent per vector, multiplies the short mantissas, and bounds what
the truncation can have changed. It decides a sign only where the bound allows; otherwise the
test is *undecided* and goes to an exact unit. It never gives a wrong sign.

Per vector x (three components, d_k = P - V_k or w_k), with m mantissa bits::

    e     = the least e >= 0 with every x_c in [-2**(m-1+e), 2**(m-1+e))      (shared exponent)
    x^_c  = floor(x_c / 2**e)                                                  (m-bit signed mantissa)

so x_c = 2**e x^_c + r_c with 0 <= r_c < 2**e. With a = e(d_k), b = e(w_k) and
s^ = sum_c d^_c w^_c::

    s = 2**(a+b) (s^ + eps),   eps = sum_c d^_c (t_c / 2**b)  +  sum_c (r_c / 2**a) (w_c / 2**b)

(t_c the remainder of w_c), and each term lies between 0 and its mantissa (the first) or its
w_c / 2**b, which is within [w^_c, w^_c + 1) (the second), so::

    -lo <= eps <= hi,   lo = [b > 0] Nd + [a > 0] Nw,   hi = [b > 0] Pd + [a > 0] Pw
    Pd = sum_c max(d^_c, 0),  Nd = sum_c max(-d^_c, 0)                        (column unit)
    Pw = sum_{w^_c >= 0} (w^_c + [b > 0]),  Nw = sum_c max(-w^_c, 0)            (row unit)

and the cell certifies ``s >= 0`` if s^ >= lo, ``s > 0`` if s^ > lo, ``s <= 0`` if s^ <= -hi,
``s < 0`` if s^ < -hi. The units compute the mantissas and the four sums once per column or row;
the cell needs three m_d x m_w products per edge, two small adders and the comparisons, and never
the exponents. With nothing truncated (a = b = 0) lo = hi = 0 and the signs are exact.

A test is decided when it does not cross the patch's plane (pP, pQ: exact, from the units), or
when the certified signs settle the edge test: all three ``s >= 0`` or all ``s <= 0`` (blocked),
or one ``s > 0`` and one ``s < 0`` (not blocked). Derivation and measurements: docs/fixed-point.md.

**The lean cell's w_k from rounded inputs** (``FilterFormat.w_input_bits`` = m_i, the lean
format): the row unit never forms w_k exactly. It truncates dQ_k = Q - V_k and e_k = V_{k+1} - V_k
to m_i-bit mantissas q, g (exponents al, be; remainders in [0, 1) of a unit), so
w_k = 2**(al+be) (q x g + err) with, per component, err = q x sig + rho x g + rho x sig and
|err| < 2 * 2**(m_i-1) + 2 * 2**(m_i-1) + 1 <= 2**(m_i+2). It then truncates W = q x g (exact in
2 m_i bits) to the w_bits mantissa w^ with a shift k that is at least m_i + 2 whenever anything was
rounded (al + be > 0), so |err| / 2**k < 1 and, with b = al + be + k,
w_c / 2**b = w^_c + tau_c,  -1 < tau_c < 2  (the exact path's tau_c is in [0, 1)). Hence::

    sum_c d^_c tau_c  in  [-(Pd + 2 Nd), 2 Pd + Nd]            (the lean column unit's Nd', Pd')
    sum_c rho_c w_c / 2**b  in  [-sum_c max(1 - w^_c, 0), sum_c max(w^_c + 2, 0)]   (the row's Nw', Pw')

and the cell is unchanged: lo = [b > 0] Nd' + [a > 0] Nw', hi = [b > 0] Pd' + [a > 0] Pw', where
[b > 0] is "rounded or shifted" (al + be + k > 0; with nothing rounded and k = 0, w^ = w and
tau = 0). With nothing rounded the primed sums are only looser than the exact path's, so they
hold for every row. Only the row unit's products change: 18 m_i x m_i cross terms instead of 18
(B+1) x (B+1).

Everything here is int64 and exact: mantissas are at most :data:`MAX_FILTER_BITS` bits, s^ at
most 3 * 2**34; the truncated values are at most 2B + 2 <= 42 bits, whose bit lengths
``np.frexp`` gives exactly (integers below 2**53 are exact in float64).
"""

from dataclasses import dataclass

import numpy as np

from .errors import ParameterError
from .exact import edge_terms, plane_sides, vertex_terms

__all__ = ["FilterFormat", "MAX_FILTER_BITS", "MIN_FILTER_BITS", "truncate", "shooter_filter_terms",
           "receiver_filter_terms", "cell_certificates", "filter_decision", "filtered_block", "filtered_tests",
           "rounded_receiver_filter_terms", "lean_filter_decision", "LEAN_INPUT_BITS"]

#: the mantissa width of the lean row unit's inputs dQ_k and e_k when w_k is rounded from them
#: (``FilterFormat(9, 9, LEAN_INPUT_BITS)``; docs/processor.md, "w_k from rounded inputs": its
#: undecided rates against the exact w_k's)
LEAN_INPUT_BITS = 12

#: mantissa widths: at most one signed MULT18X18D operand; at least a sign and one bit
MIN_FILTER_BITS, MAX_FILTER_BITS = 2, 18


def _check_width(value, name):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or \
            not MIN_FILTER_BITS <= value <= MAX_FILTER_BITS:
        raise ParameterError(f"{name} must be an integer from {MIN_FILTER_BITS} to {MAX_FILTER_BITS}, "
                             f"not {value!r}", parameter=name)
    return int(value)


@dataclass(frozen=True)
class FilterFormat:
    """Mantissa widths of the filter: ``d_bits`` for P - V_k, ``w_bits`` for w_k (signed), and
    ``w_input_bits``: None for w_k rounded from its exact value (the filtered cell), or the width
    of dQ_k and e_k when w_k comes from rounded inputs (the lean cell; the module doc)."""

    d_bits: int
    w_bits: int
    w_input_bits: int | None = None

    def __post_init__(self):
        _check_width(self.d_bits, "d_bits")
        _check_width(self.w_bits, "w_bits")
        if self.w_input_bits is not None:
            _check_width(self.w_input_bits, "w_input_bits")

    @classmethod
    def square(cls, bits):
        """Both operands at ``bits`` (the issue's "9 bits", "12 bits" filters)."""
        return cls(bits, bits)

    def __str__(self):
        rounded = "" if self.w_input_bits is None else f"i{self.w_input_bits}"
        return f"d{self.d_bits}w{self.w_bits}{rounded}"


def _bit_length(x):
    """Bit lengths of non-negative int64 values below 2**53."""
    return np.frexp(x.astype(np.float64))[1].astype(np.int64)


def truncate(x, bits):
    """(mantissa, exponent) of vectors ``x`` (..., 3) int64 at ``bits`` signed bits per
    component, one exponent per vector (the module doc): ``x >> e`` (floor) and e (...)."""
    x = np.asarray(x, dtype=np.int64)
    magnitude = np.where(x < 0, ~x, x).max(axis=-1)          # x_c < 2**k  and  x_c >= -2**k
    e = np.maximum(_bit_length(magnitude) - (bits - 1), 0)
    return x >> e[..., None], e


def _parts(m):
    return np.maximum(m, 0).sum(axis=-1), np.maximum(-m, 0).sum(axis=-1)


def shooter_filter_terms(dP, fmt):
    """Column unit: d (..., 3, 3) = P - V_k -> mantissas d^ (..., 3, 3), Pd, Nd (..., 3) and
    ``truncated`` = [a > 0] (..., 3)."""
    m, e = truncate(dP, fmt.d_bits)
    pos, neg = _parts(m)
    if fmt.w_input_bits is not None:           # the rows' tau_c in (-1, 2), not [0, 1)
        pos, neg = 2 * pos + neg, pos + 2 * neg
    return {"m": m, "pos": pos, "neg": neg, "truncated": e > 0}


def receiver_filter_terms(w, fmt):
    """Row unit: w (..., 3, 3) -> mantissas w^, Pw, Nw (..., 3) and ``truncated`` = [b > 0]."""
    m, e = truncate(w, fmt.w_bits)
    truncated = e > 0
    pos = np.where(m >= 0, m + truncated[..., None], 0).sum(axis=-1)
    neg = np.maximum(-m, 0).sum(axis=-1)
    return {"m": m, "pos": pos, "neg": neg, "truncated": truncated}


def rounded_receiver_filter_terms(dQ, E, fmt):
    """Lean row unit: dQ_k, e_k (..., 3, 3) -> w^ of w_k = dQ_k x e_k from ``fmt.w_input_bits``-bit
    mantissas of dQ_k and e_k, Pw', Nw' (..., 3), ``truncated`` = [al + be + k > 0] and
    ``exponent`` b = al + be + k (..., 3): 2**b (w^ - 1) < w_k < 2**b (w^ + 2) (the module doc)."""
    inputs = fmt.w_input_bits
    q, al = truncate(dQ, inputs)
    g, be = truncate(E, inputs)
    W = np.cross(q, g)                                    # exact: |W| <= 2**(2 m_i - 1)
    rounded = al + be > 0
    k = np.maximum(_bit_length(np.where(W < 0, ~W, W).max(axis=-1)) - (fmt.w_bits - 1), 0)
    k = np.where(rounded, np.maximum(k, inputs + 2), k)   # |err| < 2**(m_i + 2) <= 2**k
    m = W >> k[..., None]
    return {"m": m, "pos": np.maximum(m + 2, 0).sum(axis=-1), "neg": np.maximum(1 - m, 0).sum(axis=-1),
            "truncated": rounded | (k > 0), "exponent": al + be + k}


def cell_certificates(shooter, receiver):
    """Certified signs of the s_k of one cell, or broadcast: ``shooter`` and ``receiver`` terms
    (dicts of :func:`shooter_filter_terms`, :func:`receiver_filter_terms`, broadcastable).
    Returns s^ and the bools ``ge``, ``gt``, ``le``, ``lt`` (certified s >= 0, > 0, <= 0, < 0),
    each of the broadcast shape (..., 3)."""
    s = (shooter["m"] * receiver["m"]).sum(axis=-1)
    a, b = shooter["truncated"], receiver["truncated"]
    lo = np.where(b, shooter["neg"], 0) + np.where(a, receiver["neg"], 0)
    hi = np.where(b, shooter["pos"], 0) + np.where(a, receiver["pos"], 0)
    return {"s": s, "ge": s >= lo, "gt": s > lo, "le": s <= -hi, "lt": s < -hi}


def filter_decision(dP, pP, w, pQ, fmt):
    """``decided`` and ``blocked`` (bool, the broadcast shape) from the exact unit outputs
    d_k = P - V_k (..., 3, 3), pP (...), w_k (..., 3, 3), pQ (...), broadcast against each other.
    Where ``decided``, ``blocked`` is the exact predicate's answer; elsewhere it is False and the
    test needs the exact unit."""
    if fmt.w_input_bits is not None:
        raise ParameterError(f"filter {fmt} rounds w_k from its inputs: lean_filter_decision, not "
                             "filter_decision", parameter="fmt")
    return _decision(shooter_filter_terms(dP, fmt), pP, receiver_filter_terms(w, fmt), pQ)


def lean_filter_decision(dP, pP, dQ, E, pQ, fmt):
    """:func:`filter_decision` of the lean format (``fmt.w_input_bits`` set): the row's terms
    from dQ_k and e_k (``E``, (..., 3, 3)) instead of w_k."""
    return _decision(shooter_filter_terms(dP, fmt), pP, rounded_receiver_filter_terms(dQ, E, fmt), pQ)


def _decision(shooter, pP, receiver, pQ):
    c = cell_certificates(shooter, receiver)
    crossing = np.sign(pP) * np.sign(pQ) < 0
    inside = c["ge"].all(axis=-1) | c["le"].all(axis=-1)
    outside = c["gt"].any(axis=-1) & c["lt"].any(axis=-1)
    return ~crossing | inside | outside, crossing & inside


def filtered_block(shooters, receivers, vertices, normals, fmt):
    """:func:`filter_decision` of a block: ``decided``, ``blocked`` (R, S, N), the shapes of
    :func:`blockray.exact.blocked_block`."""
    dP, dQ, w = edge_terms(shooters, receivers, vertices)
    pP, pQ = plane_sides(dP, dQ, normals)                            # exact, in the units
    if fmt.w_input_bits is not None:
        E = _edges(vertices)
        return lean_filter_decision(dP[None], pP[None], dQ[:, None], E[None, None], pQ[:, None], fmt)
    return filter_decision(dP[None], pP[None], w[:, None], pQ[:, None], fmt)


def filtered_tests(P, Q, V, n, fmt):
    """:func:`filter_decision` of T single tests: P, Q (T, 3), V (T, 3, 3), n (T, 3) -> (T,)."""
    P, Q, V = (np.asarray(a, dtype=np.int64) for a in (P, Q, V))
    dP, dQ, w = vertex_terms(P, Q, V)
    pP, pQ = plane_sides(dP, dQ, n)
    if fmt.w_input_bits is not None:
        return lean_filter_decision(dP, pP, dQ, _edges(V), pQ, fmt)
    return filter_decision(dP, pP, w, pQ, fmt)


def _edges(V):
    """e_k = V_{k+1} - V_k of vertices (..., 3, 3) int64."""
    V = np.asarray(V, dtype=np.int64)
    return np.roll(V, -1, axis=-2) - V
