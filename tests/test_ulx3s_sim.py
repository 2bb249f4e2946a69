"""``--board ulx3s-sim``: the ULX3S top level (UART, framed link, the board core) under
Verilator, driven by the host driver through the same link code as the real board, renders
bit-identically to ``--board model`` (radiosities and every counter), with ``--link-faults``
too (byte-identical CSVs), and a hopeless fault rate ends with one error line, exit 2.

"""

import numpy as np
import pytest

import clirun
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.render.render import render
from blockray.host_driver.board.ulx3s import ulx3s_sim_transport
from blockray.params import BoardParams

pytestmark = pytest.mark.cocotb

COUNTERS = ("board_cycles", "tests_issued", "tests_useful", "tests", "blocks", "rays", "bits",
            "board_cycles_per_board", "load_cycles_per_board")


def _compare(scene, params, bits, **kw):
    model = render(scene, backend="model", params=params, bits=bits, **kw)
    board = BoardDriver(params.with_(bits=bits), name="ulx3s-sim", transport=ulx3s_sim_transport)
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
    from blockray.host_driver.scene.builtin import load_scene
    _compare(load_scene("cornell"), BoardParams(rows=2, cols=2, boards=1), None, max_shots=2)


# -- --link-faults through the simulated board's UART ---------------------------------------------

RENDER = ["--max-edge", "1.5", "--board", "ulx3s-sim", "--rows", "2", "--cols", "2", "--boards", "1",
          "--bits", "10", "--samples", "4", "--max-shots", "1", "--voxels", "3", "--quiet"]


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The small room and its CSV from --board model (which ulx3s-sim equals, test above)."""
    return clirun.room_render(tmp_path_factory.mktemp("ulx3s_faults"), RENDER, "--board", "model")


def _faulty_render(room, tmp_path, rate, seed):
    return clirun.faulty_render(room, tmp_path, RENDER, rate, seed)


@pytest.mark.slow
def test_render_at_1e_3_faults_is_byte_identical(room, tmp_path):
    """Faults both ways, corrected by resending; the board's own counters (read over the link)
    show the errors it saw and the frames it resent. Slow: the simulated UART carries a few
    hundred bytes per second, and every fault that needs a time-out costs 10 s of it."""
    integrity = _faulty_render(room, tmp_path, 1e-3, 3)
    assert integrity["injected_flipped"] + integrity["injected_dropped"] + integrity["injected_duplicated"] > 0
    assert integrity["board_errors"] > 0 and integrity["board_frames_resent"] > 0
    assert integrity["frames_resent"] >= integrity["board_frames_resent"]


@pytest.mark.slow
@pytest.mark.parametrize("rate,seed", [(1e-5, 24), (1e-4, 4)])
def test_render_at_low_fault_rates_is_byte_identical(room, tmp_path, rate, seed):
    _faulty_render(room, tmp_path, rate, seed)


@pytest.mark.slow
def test_render_at_a_hopeless_fault_rate_ends_with_exit_2(room, tmp_path, capsys):
    """About 3 minutes: 12 time-outs of 10 s without progress before the link is given up."""
    clirun.hopeless_render(capsys, room, tmp_path, RENDER, "the simulated board 0")
