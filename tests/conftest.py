"""Fixtures the tests share; the scenes and mesh builders they are made from are in
tests/scenes.py."""

import pytest

from scenes import room_scene


@pytest.fixture(scope="module")
def rtl_room(tmp_path_factory):
    """The small closed room with one emitting wall and a shadow-casting box (max edge 1.5) that
    the RTL back-ends render (tests/test_rtl_board.py, test_filtered_render.py)."""
    return room_scene(tmp_path_factory.mktemp("rtl_scene"), 1.5)
