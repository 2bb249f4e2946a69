"""``--board ulx3s-sim``: the ULX3S top level (UART, FIFOs, credits, the board core) under
Verilator, driven by the host driver through the same link code as the real board, renders
bit-identically to ``--board model`` (radiosities and every counter).

"""

import numpy as np
import pytest

from blockray.host_driver.driver import BoardDriver
from blockray.host_driver.render import render
from blockray.host_driver.ulx3s import ulx3s_sim_transport
from blockray.params import BoardParams

pytestmark = pytest.mark.cocotb

COUNTERS = ("board_cycles", "tests_issued", "tests_useful", "tests", "blocks", "rays", "bits",
            "board_cycles_per_board", "load_cycles_per_board")


def _compare(scene, params, bits, **kw):
    model = render(scene, backend="model", params=params, bits=bits, **kw)
    board = BoardDriver(params, bits=bits, name="ulx3s-sim", transport=ulx3s_sim_transport)
    sim = render(scene, board=board, params=params, bits=bits, **kw)
    assert np.array_equal(model.radiosity, sim.radiosity)
    for key in COUNTERS:
        assert model.report[key] == sim.report[key], key
    return sim


def test_small_scene_equals_the_model(tmp_path):
    from scenes import room_scene
    scene = room_scene(tmp_path, 1.5)
    sim = _compare(scene, BoardParams(rows=2, cols=2, boards=1), 10, samples=4, max_shots=2, voxels=3)
    assert sim.report["rays"] > 0


@pytest.mark.slow
def test_cornell_equals_the_model():
    from blockray.host_driver.builtin import load_scene
    _compare(load_scene("cornell"), BoardParams(rows=2, cols=2, boards=1), None, max_shots=2)
