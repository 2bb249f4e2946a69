"""``--board ulx3s-sim``: the ULX3S top level (UART, framed link, the board core) under
Verilator, driven by the host driver through the same link code as the real board, renders
bit-identically to ``--board model`` (radiosities and every counter), with ``--link-faults``
too (byte-identical CSVs, each side's errors and resends what the injected faults imply), and a
hopeless fault rate ends with one error line, exit 2. The simulation runs in lockstep with the
host (its time-outs count clock cycles), so every run here is the same under any load.

"""

import numpy as np
import pytest

import clirun
import link_oracle
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.board.framed import LinkFaults
from blockray.host_driver.render.render import render
from blockray.host_driver.board.ulx3s import ulx3s_sim_transport
from blockray.params import BoardParams

pytestmark = pytest.mark.cocotb

COUNTERS = ("board_cycles", "tests_issued", "tests_useful", "tests", "blocks", "rays", "bits",
            "board_cycles_per_board", "load_cycles_per_board")


def _compare(scene, params, bits, transport=ulx3s_sim_transport, **kw):
    model = render(scene, backend="model", params=params, bits=bits, **kw)
    board = BoardDriver(params.with_(bits=bits), name="ulx3s-sim", transport=transport)
    try:
        sim = render(scene, board=board, params=params, bits=bits, **kw)
    finally:
        board.close()
    assert np.array_equal(model.radiosity, sim.radiosity)
    for key in COUNTERS:
        assert model.report[key] == sim.report[key], key
    return sim


@pytest.mark.parametrize("traversal", ["block", "board"])
def test_small_scene_equals_the_model(tmp_path, traversal):
    """``board``: rays made on the board, by the block sequencer behind the link's deframer."""
    from scenes import room_scene
    scene = room_scene(tmp_path, 1.5)
    sim = _compare(scene, BoardParams(rows=2, cols=2, boards=1), 10, samples=4, max_shots=2, voxels=3,
                   traversal=traversal)
    assert sim.report["rays"] > 0


def test_lean_board_equals_the_model(tmp_path):
    """``--cell lean`` (``blockray bitstream --cell lean``'s core): rays made on the board, a
    3 x 3-bit filter so that the shared exact unit re-reads the patch memory often. Radiosity and
    tests are the model's. The commands arrive at the UART's pace, so the array drains between
    them: each board's cycles lie between the exact cell's and the lean model's (which assumes a
    full command stream; docs/board-protocol.md)."""
    from blockray.cell import Cell
    from blockray.filtered import FilterFormat
    from scenes import room_scene
    scene, params, cell = room_scene(tmp_path, 1.5), BoardParams(rows=2, cols=2, boards=1), Cell("lean", FilterFormat(3, 3))
    kw = dict(params=params, bits=10, samples=4, max_shots=2, voxels=3, traversal="board")
    exact, model = render(scene, backend="model", **kw), render(scene, backend="model", cell=cell, **kw)
    board = BoardDriver(params.with_(bits=10), name="ulx3s-sim", cell=cell,
                        transport=lambda p, b: ulx3s_sim_transport(p, b, cell=cell))
    try:
        sim = render(scene, board=board, cell=cell, **kw)
    finally:
        board.close()
    assert np.array_equal(model.radiosity, sim.radiosity) and np.array_equal(exact.radiosity, sim.radiosity)
    for key in ("tests_issued", "tests_useful", "blocks", "rays", "load_cycles_per_board"):
        assert model.report[key] == sim.report[key], key
    cycles = [r.report["board_cycles_per_board"][0] for r in (exact, sim, model)]
    print("board cycles: exact cell, lean through the UART, lean model", cycles)
    assert cycles[0] <= cycles[1] <= cycles[2] and cycles[0] < cycles[2]


@pytest.mark.slow
@pytest.mark.parametrize("traversal", ["block", "board"])
def test_cornell_equals_the_model(traversal):
    from blockray.host_driver.scene.builtin import load_scene
    _compare(load_scene("cornell"), BoardParams(rows=2, cols=2, boards=1), None, max_shots=2, traversal=traversal)


# -- --link-faults through the simulated board's UART ---------------------------------------------

RENDER = ["--max-edge", "1.5", "--board", "ulx3s-sim", "--rows", "2", "--cols", "2", "--boards", "1",
          "--bits", "10", "--samples", "4", "--max-shots", "1", "--voxels", "3", "--quiet"]


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The small room and its CSV from --board model (which ulx3s-sim equals, test above)."""
    return clirun.room_render(tmp_path_factory.mktemp("ulx3s_faults"), RENDER, "--board", "model")


def _faulty_render(room, tmp_path, rate, seed):
    return clirun.faulty_render(room, tmp_path, RENDER, rate, seed)


def _faulty_links(rate, seed):
    """A transport factory injecting faults with records, and the links it opened (each keeps
    ``final``: its stats at close, after the last traffic, as its injectors' records end)."""
    links = []

    def transport(params, board):
        link = ulx3s_sim_transport(params, board, faults=LinkFaults(rate, seed, record=True))
        close = link.close

        def final_close():
            link.final = link.stats()
            close()
        link.close = final_close
        links.append(link)
        return link
    return transport, links


def _check_faults(links):
    """Per direction: the receiver's errors are the corrupted chunks, the sender resent every
    first send that was hit (tests/link_oracle.py). Returns the corrupted chunks to the boards
    and from them, over all links."""
    to_boards = from_boards = 0
    for link in links:
        board, host = link.final["board"], link.final["host"]
        print("simulated cycles", link.pipe.pipe.cycles, "time-outs", host["timeouts"])
        to_boards += link_oracle.check_direction(link.pipe.outgoing, errors=board["errors"],
                                                 resent=host["frames_resent"], where="to the board")[0]
        from_boards += link_oracle.check_direction(link.pipe.incoming, errors=host["errors"],
                                                   resent=board["frames_resent"], where="from the board")[0]
    return to_boards, from_boards


@pytest.mark.slow
@pytest.mark.parametrize("max_edge,samples,voxels,seed", [(2.0, 2, 2, 5), (1.5, 4, 3, 3)])
def test_room_at_1e_3_faults_both_ways(tmp_path, max_edge, samples, voxels, seed):
    """The room at 1e-3 faults per byte through the Python API (so the oracle sees the
    injectors' records): the render equals the model's, and what each side counted is what the
    faults injected imply. The upload's thousands of bytes always meet faults; the few hundred
    result bytes may not (seed 5 on the smaller room: 7 corrupted chunks to the board, none back;
    tests/test_uart_sim.py has both ways)."""
    from scenes import room_scene
    print("seed", seed)
    transport, links = _faulty_links(1e-3, seed)
    _compare(room_scene(tmp_path, max_edge), BoardParams(rows=2, cols=2, boards=1), 10, transport=transport,
             samples=samples, max_shots=1, voxels=voxels)
    to_boards, _ = _check_faults(links)
    assert to_boards


@pytest.mark.slow
@pytest.mark.parametrize("rate,seed", [(1e-5, 5), (1e-4, 4)])
def test_render_at_low_fault_rates_is_byte_identical(room, tmp_path, rate, seed):
    """Seeds at which the small room's ~10 kB of link traffic does meet a fault, even at 1e-5
    (seed 5: one flipped byte to the board), so the test is one of faults corrected."""
    integrity = _faulty_render(room, tmp_path, rate, seed)
    assert integrity["injected_flipped"] + integrity["injected_dropped"] + integrity["injected_duplicated"] > 0
    assert integrity["frames_resent"] + integrity["board_frames_resent"] > 0 and integrity["errors"] > 0


@pytest.mark.slow
def test_render_at_a_hopeless_fault_rate_ends_with_exit_2(room, tmp_path, capsys):
    """12 time-outs of 0.5 simulated ms without progress before the link is given up."""
    clirun.hopeless_render(capsys, room, tmp_path, RENDER, "the simulated board 0")
