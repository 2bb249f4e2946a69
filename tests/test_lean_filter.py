"""The lean cell's filter: w_k from rounded dQ_k and e_k (blockray/filtered.py, the module doc's
"lean cell" bound) against the exact predicate.

The contract is the filtered cell's: wherever the filter decides, its answer is the exact
predicate's, and every sign it certifies is the exact s_k's. Checked here on the lemma itself
(w_k within (-1, 2) units of 2**b of w^, with Python integers), on near-degenerate geometry
(rays through a triangle's vertices and edges, then rotated, scaled and rounded to the grid),
hypothesis-drawn blocks, and the processor's hard and random vectors. The 10**6-query run is
``benchmarks/bench_lean.py --part verify`` (docs/processor.md).
"""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from blockray.errors import ParameterError
from blockray.exact import block_terms, blocked_block, blocked_reference, edge_terms, patch_normals
from blockray.filtered import (LEAN_INPUT_BITS, FilterFormat, cell_certificates, filter_decision, filtered_block,
                               rounded_receiver_filter_terms, shooter_filter_terms)

from processor_vectors import check_filter_decisions, hard_cases, near_degenerate, random_tests

FORMATS = [FilterFormat(9, 9, LEAN_INPUT_BITS), FilterFormat(9, 9, 9), FilterFormat(4, 5, 3), FilterFormat(12, 12, 16)]


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


@given(st.integers(4, 20).flatmap(lambda B: st.lists(st.integers(-(1 << B), (1 << B) - 1), min_size=6, max_size=6)),
       st.integers(2, 18), st.integers(2, 18))
@settings(max_examples=300, deadline=None)
def test_rounded_w_is_within_its_bound(values, w_bits, inputs):
    """2**b (w^ - 1) < w < 2**b (w^ + 2) for the exact w = dQ x e (Python integers), w^ fits
    w_bits, and w^ = w when nothing is truncated."""
    dq, e = values[:3], values[3:]
    t = rounded_receiver_filter_terms(np.array([dq]), np.array([e]), FilterFormat(9, w_bits, inputs))
    w, m, b = _cross(dq, e), [int(v) for v in t["m"][0]], int(t["exponent"][0])
    assert all(-(1 << (w_bits - 1)) <= v < (1 << (w_bits - 1)) for v in m)
    assert all((v - 1) << b < x < (v + 2) << b for v, x in zip(m, w)), (w, m, b)
    if not t["truncated"][0]:
        assert m == w


def _check_certificates(P, Q, V, fmt):
    """Every sign a lean cell certifies holds for the exact s_k (block_terms); and the decided
    bits are the exact predicate's. Returns (undecided, tests)."""
    n = patch_normals(V)
    _, _, sides = block_terms(P, Q, V, n)                                          # (R, S, N, 3)
    dP, dQ, _ = edge_terms(P, Q, V)
    E = np.roll(V, -1, axis=-2) - V
    c = cell_certificates(shooter_filter_terms(dP[None], fmt), rounded_receiver_filter_terms(dQ[:, None], E, fmt))
    for name, holds in (("ge", sides >= 0), ("gt", sides > 0), ("le", sides <= 0), ("lt", sides < 0)):
        wrong = c[name] & ~holds
        assert not wrong.any(), f"{fmt}: {int(wrong.sum())} wrong '{name}' certificates"
    decided, blocked = filtered_block(P, Q, V, n, fmt)
    assert not (decided & (blocked != blocked_block(P, Q, V, n))).any()
    return int((~decided).sum()), decided.size


@pytest.mark.parametrize("fmt", FORMATS, ids=str)
def test_near_degenerate_rounded_rotated_scaled(fmt):
    seed = 3030
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    undecided = total = 0
    for bits in (8, 12, 16, 20):
        for P, Q, V in near_degenerate(bits, 80, rng):
            u, t = _check_certificates(P, Q, V, fmt)
            undecided, total = undecided + u, total + t
    print(f"{fmt}: {undecided} of {total} undecided")
    assert undecided > 0                               # the cases reach the exact path


@given(st.integers(4, 20).flatmap(lambda B: st.tuples(st.just(B), st.integers(0, B))),
       st.randoms(use_true_random=False), st.sampled_from(FORMATS))
@settings(max_examples=150, deadline=None)
def test_certified_signs_hold_on_drawn_blocks(bits_spread, random, fmt):
    """Blocks in a box of side 2**spread inside the B-bit grid (small boxes: few truncated bits)."""
    bits, spread = bits_spread
    rng = np.random.default_rng(random.getrandbits(32))
    corner = rng.integers(0, (1 << bits) - (1 << spread) + 1, 3)
    V = corner + rng.integers(0, 1 << spread, (6, 3, 3))
    P, Q = corner + rng.integers(0, 1 << spread, (3, 3)), corner + rng.integers(0, 1 << spread, (3, 3))
    _check_certificates(P, Q, V, fmt)


@pytest.mark.parametrize("bits", [6, 16, 20])
@pytest.mark.parametrize("fmt", FORMATS[:3], ids=str)
def test_processor_vectors_never_decided_wrong(bits, fmt):
    seed = 91 + bits
    print(f"seed {seed}")
    tests = hard_cases(bits) + random_tests(bits, 2000, np.random.default_rng(seed))
    print(f"B = {bits}, {fmt}: {check_filter_decisions(tests, fmt)} of {len(tests)} undecided")


def test_the_wider_bound_is_needed():
    """With the exact path's column sums (Pd, Nd: tau in [0, 1)) in place of the lean ones
    (2 Pd + Nd, Pd + 2 Nd), the rounded w^ gives wrong certificates on near-degenerate blocks:
    the lean bound is reached, so the checks above can fail."""
    fmt = FilterFormat(4, 5, 3)
    seed = 31
    print(f"seed {seed}")
    wrong = 0
    for P, Q, V in near_degenerate(16, 100, np.random.default_rng(seed)):
        _, _, sides = block_terms(P, Q, V, patch_normals(V))
        dP, dQ, _ = edge_terms(P, Q, V)
        shooter = shooter_filter_terms(dP[None], FilterFormat(fmt.d_bits, fmt.w_bits))     # tau in [0, 1)
        receiver = rounded_receiver_filter_terms(dQ[:, None], np.roll(V, -1, axis=-2) - V, fmt)
        c = cell_certificates(shooter, receiver)
        wrong += int((c["gt"] & (sides <= 0)).sum() + (c["lt"] & (sides >= 0)).sum()
                     + (c["ge"] & (sides < 0)).sum() + (c["le"] & (sides > 0)).sum())
    assert wrong > 0


def test_format_names():
    assert str(FilterFormat(9, 9, 12)) == "d9w9i12" and str(FilterFormat(9, 9)) == "d9w9"


def test_bad_input_width_names_the_parameter():
    with pytest.raises(ParameterError, match="w_input_bits") as e:
        FilterFormat(9, 9, 19)
    assert e.value.parameter == "w_input_bits"


def test_the_exact_w_decision_refuses_a_lean_format():
    z = np.zeros((1, 3, 3), np.int64)
    with pytest.raises(ParameterError, match="lean_filter_decision"):
        filter_decision(z, np.zeros(1, np.int64), z, np.zeros(1, np.int64), FilterFormat(9, 9, 12))


def test_a_sample_against_the_independent_predicate():
    """Decided answers against blocked_reference (Python integers, orient3d), not blocked_block."""
    rng = np.random.default_rng(4242)
    print("seed 4242")
    checked = 0
    for P, Q, V in near_degenerate(16, 60, rng):
        decided, blocked = filtered_block(P, Q, V, patch_normals(V), FORMATS[0])
        for r, s, t in zip(*np.nonzero(decided)):
            assert blocked[r, s, t] == blocked_reference(P[s], Q[r], *V[t])
            checked += 1
    assert checked > 300
