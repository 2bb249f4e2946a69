"""The processor's vector tests through the native harness (sim/native/vectors.py,
vector_harness.cpp): the Intersector's Verilog clocked in C++, a payload a cycle each way,
against the exact predicate.

Every hard case and a million random tests in the default suite, ten million in the slow one,
with the harness's random input gaps and output back-pressure (seeded, printed). The expected
bits are :func:`~blockray.exact.blocked_tests` (blocked_block's terms, test by test), and a
sample of them is checked here against the independent orient3d evaluation
(:func:`~blockray.exact.blocked_reference`).
"""

import os

import numpy as np
import pytest

from blockray.exact import blocked_reference
from blockray.rtl.processor import Intersector
from blockray.sim.drive import HostTiming

from processor_vectors import hard_cases, random_flat

pytestmark = pytest.mark.cocotb

BITS = 16
SEED = int(os.environ.get("BLOCKRAY_SEED", "20261203"))
#: tests per run of the harness (bounds the buffers: 45 bytes in, 3 out per test at B = 16)
CHUNK = 1 << 20


@pytest.fixture(scope="module")
def intersector():
    from blockray.sim.native.vectors import NativeVectors
    print(f"seed={SEED}")
    runner = NativeVectors(lambda: Intersector(BITS), name="intersector_vectors", source=f"Intersector({BITS})",
                           idle=HostTiming(0.1), backpressure=HostTiming(0.1), seed=SEED)
    yield runner
    runner.close()


def _results(runner, tests):
    """(blocked, tag) of every test, in order, from the harness."""
    out = np.concatenate([runner.run(tests[a:a + CHUNK].payload_bytes(BITS)) for a in range(0, len(tests), CHUNK)])
    word = out[:, 0].astype(np.int64) | out[:, 1].astype(np.int64) << 8 | out[:, 2].astype(np.int64) << 16
    return (word & 1).astype(bool), word >> 1


def _check(runner, tests):
    start = runner.cycles
    blocked, tags = _results(runner, tests)
    print(f"{len(tests)} vectors in {runner.cycles - start} cycles")
    assert np.array_equal(tags, np.arange(len(tests)) % (1 << 16)), "results out of order or lost"
    wrong = np.flatnonzero(blocked != tests.blocked)
    assert len(wrong) == 0, f"{len(wrong)} mismatches, first at test {wrong[0]}"
    return blocked


def _random(count, seed):
    tests = random_flat(BITS, count, np.random.default_rng(seed))
    sample = np.random.default_rng(seed + 1).choice(count, 2000, replace=False)
    assert all(blocked_reference(tests.P[i], tests.Q[i], *tests.V[i]) == tests.blocked[i] for i in sample)
    assert 0.05 < tests.blocked.mean() < 0.5          # both answers well represented
    return tests


def test_hard_cases_and_a_million_random_vectors(intersector):
    hard = hard_cases(BITS)
    _check(intersector, hard)
    _check(intersector, _random(1_000_000, SEED))


def test_a_flipped_expectation_is_found(intersector):
    """The check can fail: one expected bit inverted is reported as that test's mismatch."""
    tests = _random(5_000, SEED + 7)
    tests.blocked[1234] ^= True
    with pytest.raises(AssertionError, match="1 mismatches, first at test 1234"):
        _check(intersector, tests)


@pytest.mark.slow
def test_ten_million_random_vectors(intersector):
    for k in range(10):
        _check(intersector, _random(1_000_000, SEED + 100 + k))
