"""The certified edge filter (blockray/filtered.py) against the exact predicate.

The contract: wherever the filter decides, its answer is the exact predicate's, and every sign it
certifies is the sign of the exact s_k. Checked on the processor's hard cases (cube corners at
the extremes, fans with rays through shared vertices and edges, in-plane rays, coarse-grid
coincidences) and on seeded random tests, at several filter widths; the 10**7-query run is
``benchmarks/bench_filter.py --part verify`` (docs/fixed-point.md).
"""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from blockray.errors import ParameterError
from blockray.exact import block_terms, edge_terms, patch_normals, vertex_terms
from blockray.filtered import (FilterFormat, cell_certificates, filtered_block, filtered_tests,
                               receiver_filter_terms, shooter_filter_terms, truncate)

from processor_vectors import check_filter_decisions, hard_cases, random_tests

FORMATS = [FilterFormat.square(b) for b in (4, 9, 12, 14)] + [FilterFormat(17, 18)]


@given(st.lists(st.integers(-(1 << 42), (1 << 42) - 1), min_size=3, max_size=3), st.integers(2, 18))
@settings(max_examples=400, deadline=None)
def test_truncate_is_floor_with_the_least_shared_exponent(x, bits):
    m, e = truncate(np.array([x]), bits)
    m, e = [int(v) for v in m[0]], int(e[0])
    assert all(-(1 << (bits - 1)) <= v < (1 << (bits - 1)) for v in m)        # fits `bits` signed
    assert all(v >> e == mv for v, mv in zip(x, m))                            # floor(x / 2**e)
    if e > 0:                                                                  # e is the least
        assert not all(-(1 << (bits - 1)) <= v >> (e - 1) < (1 << (bits - 1)) for v in x)


def _certified_signs_are_true(P, Q, V, fmt):
    """Every sign a cell certifies holds for the exact s_k (block_terms, int64)."""
    n = patch_normals(V)
    _, _, sides = block_terms(P, Q, V, n)                                     # (R, S, N, 3)
    dP, _, w = edge_terms(P, Q, V)
    c = cell_certificates(shooter_filter_terms(dP[None], fmt), receiver_filter_terms(w[:, None], fmt))
    for name, holds in (("ge", sides >= 0), ("gt", sides > 0), ("le", sides <= 0), ("lt", sides < 0)):
        wrong = c[name] & ~holds
        assert not wrong.any(), f"{fmt}: {int(wrong.sum())} wrong '{name}' certificates"
    return c


@pytest.mark.parametrize("bits", [6, 12, 16, 20])
@pytest.mark.parametrize("fmt", FORMATS, ids=str)
def test_hard_cases_never_decided_wrong(bits, fmt):
    tests = hard_cases(bits)
    undecided = check_filter_decisions(tests, fmt)
    print(f"B = {bits}, {fmt}: {undecided} of {len(tests)} hard tests undecided")
    # the hard cases are there to reach the exact path: shared edges and vertices give s_k = 0,
    # which no truncating filter can certify (B = 6 with 17/18-bit mantissas truncates nothing)
    if not (bits == 6 and fmt.d_bits > 7):
        assert undecided > 0


@pytest.mark.parametrize("bits", [8, 16, 20])
@pytest.mark.parametrize("fmt", FORMATS, ids=str)
def test_random_tests_never_decided_wrong(bits, fmt):
    seed = 73 + bits
    print(f"seed {seed}")
    tests = random_tests(bits, 4000, np.random.default_rng(seed))
    undecided = check_filter_decisions(tests, fmt)
    print(f"B = {bits}, {fmt}: {undecided} of {len(tests)} random tests undecided")


@pytest.mark.parametrize("fmt", FORMATS, ids=str)
def test_certified_signs_hold(fmt):
    seed = 82
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    for bits in (6, 11, 16, 20):
        L = (1 << bits) - 1
        for scale in (L, L // 64 + 1, 3):                  # large and small vectors (small exponents)
            centre = rng.integers(0, L + 1 - scale, 3)
            V = centre + rng.integers(0, scale + 1, (40, 3, 3))
            P = centre + rng.integers(0, scale + 1, (6, 3))
            Q = centre + rng.integers(0, scale + 1, (6, 3))
            _certified_signs_are_true(P, Q, V, fmt)


def test_nothing_truncated_is_exact():
    """With mantissas as wide as the values (B = 6: d 7 bits, w 14) the filter is the exact
    predicate, zeros included: every test decided."""
    tests = hard_cases(6) + random_tests(6, 3000, np.random.default_rng(6))
    decided, blocked = filtered_tests(tests.P, tests.Q, tests.V, tests.n, FilterFormat(7, 14))
    assert decided.all() and (blocked == tests.blocked).all()


def test_the_bound_is_needed():
    """The same filter with its error bound dropped (lo = hi = 0) gives wrong signs on these
    tests: they do reach the bound, so the checks above can fail."""
    fmt = FilterFormat.square(9)
    rng = np.random.default_rng(9)
    tests = random_tests(16, 20000, rng)
    dP, _, w = vertex_terms(tests.P, tests.Q, tests.V)
    shooter, receiver = shooter_filter_terms(dP, fmt), receiver_filter_terms(w, fmt)
    for terms in (shooter, receiver):
        terms["pos"] = terms["neg"] = np.zeros_like(terms["pos"])
    c = cell_certificates(shooter, receiver)
    sides = np.einsum("tkc,tkc->tk", dP, w)
    assert (c["gt"] & (sides <= 0)).any() or (c["lt"] & (sides >= 0)).any()


def test_block_and_flat_forms_agree():
    rng = np.random.default_rng(3)
    P, Q, V = rng.integers(0, 1 << 16, (5, 3)), rng.integers(0, 1 << 16, (4, 3)), rng.integers(0, 1 << 16, (30, 3, 3))
    n = patch_normals(V)
    fmt = FilterFormat.square(9)
    decided, blocked = filtered_block(P, Q, V, n, fmt)
    r, s, t = (i.ravel() for i in np.indices(decided.shape))
    flat = filtered_tests(P[s], Q[r], V[t], n[t], fmt)
    assert (flat[0] == decided.ravel()).all() and (flat[1] == blocked.ravel()).all()


@pytest.mark.parametrize("d, w, name", [(1, 9, "d_bits"), (9, 19, "w_bits"), (True, 9, "d_bits"), (9.0, 9, "d_bits")])
def test_bad_widths_name_the_parameter(d, w, name):
    with pytest.raises(ParameterError, match=name) as e:
        FilterFormat(d, w)
    assert e.value.parameter == name
