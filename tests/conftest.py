"""Fixtures the tests share; the scenes and mesh builders they are made from are in
tests/scenes.py."""

import os
import zlib

import pytest

from scenes import room_scene


@pytest.fixture(scope="module")
def rtl_room(tmp_path_factory):
    """The small closed room with one emitting wall and a shadow-casting box (max edge 1.5) that
    the RTL back-ends render (tests/test_rtl_board.py, test_filtered_render.py)."""
    return room_scene(tmp_path_factory.mktemp("rtl_scene"), 1.5)


@pytest.fixture
def rng_seed(request):
    """A randomised test's seed: fixed per test (a CRC of its id), so every run draws the same
    cases, or ``BLOCKRAY_SEED`` to try others; printed so a failure can be replayed."""
    seed = int(os.environ.get("BLOCKRAY_SEED") or zlib.crc32(request.node.nodeid.encode()))
    print(f"seed={seed} (BLOCKRAY_SEED={seed} repeats it)")
    return seed
